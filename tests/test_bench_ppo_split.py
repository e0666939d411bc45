"""``kamino.bench.ppo_split`` on the CPU at tiny PPO sizes: the split of brax's PPO epoch into collection and
learning, whose collection loop takes the env steps brax's epoch takes (counted, not timed), and the command's
record end to end."""

import json

import pytest

pytest.importorskip("brax")

import jax
import jax.numpy as jnp
import numpy as np

from kamino.bench import ppo_split

#: fourbar_track's networks at 8 environments: 2 unrolls of 5 env steps per training step, 2 minibatches
TINY = {"batch_size": 8, "num_minibatches": 2, "unroll_length": 5}


def _cuda() -> bool:
    """Whether Warp sees a CUDA device."""
    import warp as wp

    return wp.is_cuda_available()


class CountingEnv(ppo_split.NullEnv):
    """The null environment with a host counter of the env steps it takes (one ``jax.debug.callback`` per step; under
    ``vmap`` the callback sees the batch, sequentially or at once, so it counts the elements of what it is given)."""

    def __init__(self, observation_size: int, action_size: int):
        super().__init__(observation_size, action_size)
        self.count = 0

    def _add(self, entries) -> None:
        self.count += int(np.size(entries))

    def step(self, state, action):
        jax.debug.callback(self._add, action[:1])  # one entry per env step, batched with the actions
        return super().step(state, action)


def test_null_env_steps_follow_the_actions():
    """The null environment's observation moves halfway to the tiled, clipped action each step, so that the policy's
    actions feed its next observation; it never ends an episode itself."""
    env = ppo_split.NullEnv(5, 2)
    s = env.reset(jax.random.PRNGKey(0))
    assert s.obs.shape == (5,) and float(s.obs[0]) == -1.0 and float(s.obs[-1]) == 1.0
    s = env.step(s, jnp.array([3.0, -0.5]))
    expected = 0.5 * (jnp.linspace(-1.0, 1.0, 5) + jnp.array([1.0, -0.5, 1.0, -0.5, 1.0]))
    assert jnp.allclose(s.obs, expected) and float(s.done) == 0.0
    assert float(s.reward) == pytest.approx(-(1.0 + 0.25) / 2)  # the clipped action's mean square


def test_bad_sizes_and_options_are_named():
    with pytest.raises(ValueError, match="trajectories"):
        ppo_split.training_config("fourbar_track", 3, TINY)  # 16 trajectories are not whole unrolls of 3 envs
    with pytest.raises(SystemExit):
        ppo_split.parse_args(["--set", "num_evals=3"])
    with pytest.raises(SystemExit):
        ppo_split.parse_args(["--epochs", "0"])
    with pytest.raises(SystemExit):
        ppo_split.parse_args(["--solver", "nosuch=1"])


def test_collection_alone_takes_the_env_steps_of_brax_s_training_steps():
    """The split is only as good as its collection loop: it must take exactly the env steps brax's PPO epoch takes
    (``batch_size x num_minibatches / num_envs`` unrolls of ``unroll_length`` steps per training step, E in all),
    or its time is that of another loop (one unroll per training step instead of brax's two would be half). Counted
    on the host, not timed: the same env steps, ``(WARMUP_EPOCHS + epochs) x steps_per_epoch x E``, in brax's
    ``ppo.train`` and in :func:`ppo_split.time_collection`. The record's shares of the epoch add up to one."""
    kwargs = ppo_split.training_config("fourbar_track", 8, TINY)
    unit = ppo_split.env_steps_per_training_step(kwargs)
    assert unit == 8 * 5 * 2
    steps_per_epoch, epochs = 2, 1
    want = (ppo_split.WARMUP_EPOCHS + epochs) * steps_per_epoch * unit
    env = CountingEnv(7, 1)
    train = ppo_split.time_ppo(env, kwargs, steps_per_epoch, epochs)
    assert env.count == want, (env.count, want)
    env.count = 0
    collect = ppo_split.time_collection(env, kwargs, steps_per_epoch, epochs)
    assert env.count == want, (env.count, want)
    for r in (train, collect):
        assert len(r["epochs_s"]) == epochs and len(r["warmup_epochs_s"]) == ppo_split.WARMUP_EPOCHS
        assert r["env_steps_per_s"] == pytest.approx(steps_per_epoch * unit / r["epoch_s"])
    r = ppo_split.measure(ppo_split.NullEnv(7, 1), kwargs, 1, 1)
    assert r["collect_share"] + r["learn_share"] == pytest.approx(1.0)


# the gpu tier, where the command is run: about a minute on the 2-core CPU (the four-bar's Warp step compiles in PPO
# and in the collection); the split itself is checked on the CPU above
@pytest.mark.gpu
@pytest.mark.skipif(not _cuda(), reason="the gpu tier: needs a CUDA device for Warp")
def test_command_writes_the_record_of_both_environments(tmp_path):
    """``kamino bench ppo_split fourbar_track`` at tiny sizes appends one record with both environments' PPO env
    steps/s, the task's split, and the configuration and host it ran with; the four-bar's physics makes its PPO
    slower than the null environment's."""
    pytest.importorskip("warp")
    out = tmp_path / "split.jsonl"
    argv = ["fourbar_track", "--num-envs", "8", *(f"--set={k}={v}" for k, v in TINY.items()),
            "--steps-per-epoch", "2", "--epochs", "2", "--out", str(out)]
    assert ppo_split.main(argv) == 0
    (rec,) = (json.loads(line) for line in out.read_text().splitlines())
    assert rec["task"] == "fourbar_track" and rec["ppo"]["num_envs"] == 8 and rec["ppo"]["batch_size"] == 8
    assert rec["network"]["policy_hidden_layer_sizes"] == [32, 32]
    assert rec["observation_size"] == 7 and rec["action_size"] == 1
    assert rec["env_steps_per_training_step"] == 80 and rec["timed_env_steps"] == 2 * 2 * 80
    assert rec["ppo_env_steps_per_s"] == rec["task_run"]["ppo_env_steps_per_s"] > 0
    assert rec["ceiling_env_steps_per_s"] == rec["null"]["ppo_env_steps_per_s"] > rec["ppo_env_steps_per_s"]
    assert rec["collect_share"] + rec["learn_share"] == pytest.approx(1.0)
    assert {"jax", "warp", "python", "brax", "command", "device"} <= set(rec)
