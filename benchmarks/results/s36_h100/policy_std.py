"""Session 36's check of why PPO's adaptive-KL rule held the learning rate at its 1e-5 floor (docs/envs.md, "The
eleventh run"): per action dimension, the policy's pre-tanh std and mean over the states its deterministic policy
visits (16 resets x 60 policy steps, JAX backend on the CPU, F25's settings: `gait_frequency` 2.5), and each
dimension's share of the Gaussian KL for equal shifts of every mean (sum_a d^2 / (2 std_a^2)).
Run from the repository root: `python benchmarks/results/s36_h100/policy_std.py ABSOLUTE_CHECKPOINT_PATH`
(output: `policy_std_F25.txt`; the action order is the model's `actuator_names`)."""

import json
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from brax.training.acme import running_statistics

sys.path.insert(0, "benchmarks")
from rl_eval import load_policy

from kamino.envs import make
from kamino.envs.configs import ppo_kwargs, task_config

TASK, EPISODES, STEPS, MIN_STD = "dr_legs_joystick", 16, 60, 0.001  # MIN_STD: brax's NormalTanhDistribution


def main(ckpt: Path) -> None:
    env = make(TASK, backend="jax", **{**task_config(TASK)["env"], "gait_frequency": 2.5})
    make_policy, params = load_policy(ckpt, TASK)
    config = json.loads((ckpt / "ppo_network_config.json").read_text())
    net = ppo_kwargs(TASK)["network_factory"](config["observation_size"], config["action_size"],
                                              preprocess_observations_fn=running_statistics.normalize)
    policy = make_policy(params, deterministic=True)
    step = jax.jit(jax.vmap(env.step))
    act = jax.jit(lambda o: policy(o, jax.random.PRNGKey(0))[0])
    s = jax.jit(jax.vmap(env.reset))(jax.random.split(jax.random.PRNGKey(0), EPISODES))
    obs = []
    for _ in range(STEPS):
        obs.append(np.asarray(s.obs))
        s = step(s, act(s.obs))
    logits = np.asarray(net.policy_network.apply(params[0], params[1], jnp.asarray(np.concatenate(obs))))
    loc, raw = np.split(logits, 2, axis=-1)
    std = np.asarray(jax.nn.softplus(raw)) + MIN_STD
    print("action dims", loc.shape[-1])
    for a in range(loc.shape[-1]):
        print(f"{a} std median {np.median(std[:, a]):.4f} min {std[:, a].min():.4f} | loc median "
              f"{np.median(loc[:, a]):.2f} |loc|>2: {100 * np.mean(np.abs(loc[:, a]) > 2):.0f}%")
    inv = np.mean(1 / (2 * std**2), axis=0)
    print("share of KL per dim for equal mean shifts:", np.round(inv / inv.sum(), 3))


if __name__ == "__main__":
    main(Path(sys.argv[1]))
