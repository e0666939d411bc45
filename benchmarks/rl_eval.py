"""Evaluate a trained joystick policy at chosen commands (issue 18): ``python benchmarks/rl_eval.py CHECKPOINT``.

The issue's walking test: 256 episodes of 10 s, each with a forward command drawn uniformly in 0.3-0.5 m/s (no
lateral or yaw command), the policy's deterministic action. It reports, over the episodes:

- the **velocity-tracking error**: per episode, the mean over its policy steps (up to a fall) of
  ``|cmd_xy - v_xy|``, the base body's planar velocity in its own frame (the quantity of the ``tracking_lin_vel``
  reward, docs/envs.md), then the mean over episodes;
- the **fall fraction**: episodes that end before 10 s (a fall, or the world-health flag);
- the mean forward speed, and the pass/fail of the issue's bars (error <= 0.1 m/s, falls <= 5 %);
- where the error comes from (reported, not a bar): the **error of the mean velocity**, per episode ``|cmd_xy -
  mean v_xy|`` over the same steps, and the **fluctuation**, per episode the standard deviation of ``v_x`` and of
  ``v_y`` about their means (a gait's sway within its strides); the tracking error lies between the first and the
  root of the sum of squares of all three.

``CHECKPOINT`` is a folder written by ``benchmarks/rl_train.py`` (``checkpoints/<step>/``; a run folder takes its
newest checkpoint). ``--out`` writes the JSON report.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))  # rl_train, beside this script


def newest_checkpoint(path: Path) -> Path:
    """``path`` itself if it holds a checkpoint, else the newest one of an ``rl_train.py`` run folder (its
    ``checkpoints/<step>/``, found as ``rl_train.py`` resumes) or of a ``checkpoints`` folder."""
    from rl_train import latest_checkpoint

    if (path / "ppo_network_config.json").exists():
        return path
    for folder in (path / "checkpoints", path):
        _, newest = latest_checkpoint(folder)
        if newest is not None:
            return newest
    raise FileNotFoundError(f"rl_eval: no brax PPO checkpoint in {path} (expected ppo_network_config.json, or "
                            "checkpoints/<step>/ as benchmarks/rl_train.py writes)")


def load_policy(ckpt: Path, task: str):
    """``(make_policy, params)`` of a checkpoint: brax's inference-function factory for the task's networks
    (``kamino.envs.configs``) and the saved parameters; ``make_policy(params, deterministic=True)`` is the policy.
    brax's own ``checkpoint.load_policy`` cannot read the configs it writes for the default networks (brax 0.14:
    ``mean_kernel_init_fn: null`` fails its lookup), so only the parameters are read."""
    from brax.training.acme import running_statistics
    from brax.training.agents.ppo import checkpoint as ppo_checkpoint
    from brax.training.agents.ppo import networks as ppo_networks

    from kamino.envs.configs import ppo_kwargs

    config = json.loads((ckpt / "ppo_network_config.json").read_text())
    normalize = running_statistics.normalize if config.get("normalize_observations") else (lambda x, y: x)
    net = ppo_kwargs(task)["network_factory"](config["observation_size"], config["action_size"],
                                               preprocess_observations_fn=normalize)
    return ppo_networks.make_inference_fn(net), ppo_checkpoint.load(ckpt)


def walking_test(env, make_policy, *, episodes: int, seconds: float, speed: tuple[float, float], seed: int = 0,
                 deterministic: bool = True):
    """The walking test's rollout, compiled once for any parameters of ``make_policy``: returns ``run(params)``.

    ``run`` plays ``episodes`` episodes of ``seconds`` at forward commands uniform in ``speed`` [m/s] (no lateral or
    yaw command), the policy's deterministic action (its mode; ``deterministic=False``: actions sampled as in
    training), and returns numpy arrays ``(commands [E], lin_vel [E, T, 3],
    ang_vel [E, T, 3], counted [E, T], fell [E])``: the base body's velocities in its own frame after each policy
    step; ``counted`` is True for the steps that began with the robot up (the step that ends an episode is its
    last counted one); ``fell`` marks the episodes that ended before ``seconds``."""
    import jax
    import jax.numpy as jnp
    import numpy as np

    from kamino.envs.geometry import body_frame_vectors

    steps = round(seconds / env.dt)
    key_reset, key_cmd, key_policy = jax.random.split(jax.random.PRNGKey(seed), 3)
    vx = jax.random.uniform(key_cmd, (episodes,), jnp.float32, speed[0], speed[1])
    commands = jnp.stack([vx, jnp.zeros_like(vx), jnp.zeros_like(vx)], -1)

    def start(rng, command):
        return env.with_command(env.reset(rng), command)

    def rollout(params, state, key):
        policy = make_policy(params, deterministic=deterministic)

        def body(carry, k):
            s, alive = carry
            action, _ = policy(s.obs, k)
            s = env.step(s, action)
            ps = env.full_state(s.pipeline_state)
            frame = body_frame_vectors(ps.body_q, ps.body_u, env._base)
            return (s, alive & (s.done == 0)), (frame["lin_vel"], frame["ang_vel"], alive)

        (_, alive_end), out = jax.lax.scan(body, (state, jnp.bool_(True)), jax.random.split(key, steps))
        return (*out, ~alive_end)

    with jax.enable_x64(False):
        states = jax.jit(jax.vmap(start))(jax.random.split(key_reset, episodes), commands)
    play = jax.jit(jax.vmap(rollout, in_axes=(None, 0, 0)))
    keys = jax.random.split(key_policy, episodes)

    def run(params):
        with jax.enable_x64(False):
            out = play(params, states, keys)
        return (np.asarray(vx), *(np.asarray(x) for x in out))

    return run


def summarize(vx, lin, counted, fell) -> dict:
    """The walking test's figures (the module doc) of a :func:`walking_test` rollout."""
    import numpy as np

    cmd = np.stack([vx, np.zeros_like(vx)], -1)
    err = np.linalg.norm(cmd[:, None, :] - lin[..., :2], axis=-1)
    n = np.maximum(counted.sum(1), 1)
    err = np.where(counted, err, 0.0).sum(1) / n
    mean_v = np.where(counted[..., None], lin[..., :2], 0.0).sum(1) / n[:, None]  # [E, 2] per episode
    var = np.where(counted[..., None], (lin[..., :2] - mean_v[:, None, :]) ** 2, 0.0).sum(1) / n[:, None]
    std = np.sqrt(var).mean(0)
    return {"episodes": len(vx), "policy_steps": lin.shape[1], "tracking_error_mean": float(err.mean()),
            "tracking_error_p90": float(np.quantile(err, 0.9)), "forward_speed_mean": float(mean_v[:, 0].mean()),
            "command_mean": float(vx.mean()), "fall_fraction": float(fell.mean()),
            "mean_velocity_error": float(np.linalg.norm(cmd - mean_v, axis=-1).mean()),
            "fluctuation_std_x": float(std[0]), "fluctuation_std_y": float(std[1])}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("checkpoint", type=Path, help="a checkpoint folder, or an rl_train.py output folder")
    p.add_argument("--task", default="dr_legs_joystick")
    p.add_argument("--backend", choices=("jax", "warp"), default="warp")
    p.add_argument("--episodes", type=int, default=256)
    p.add_argument("--seconds", type=float, default=10.0)
    p.add_argument("--speed", type=float, nargs=2, default=(0.3, 0.5), metavar=("LOW", "HIGH"),
                   help="forward command range [m/s] (default 0.3 0.5)")
    p.add_argument("--max-error", type=float, default=0.1, help="the bar on the mean tracking error [m/s]")
    p.add_argument("--max-falls", type=float, default=0.05, help="the bar on the fall fraction")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--stochastic", action="store_true",
                   help="sample the policy's actions as in training (default: its deterministic mode)")
    p.add_argument("--env", action="append", default=[], metavar="KEY=VALUE",
                   help="environment keyword over the task's config, VALUE a Python literal (repeatable)")
    p.add_argument("--out", type=Path, default=None)
    args = p.parse_args(argv)
    if args.episodes < 1 or args.seconds <= 0 or not args.speed[0] <= args.speed[1]:
        p.error("--episodes must be >= 1, --seconds > 0 and --speed LOW <= HIGH")
    from rl_train import key_values, run_env

    env_overrides = key_values(p, "--env", args.env)
    from kamino.envs import make

    ckpt = newest_checkpoint(args.checkpoint.resolve())
    env = make(args.task, backend=args.backend,
               **{**run_env(args.checkpoint.resolve(), args.task), **env_overrides, "resample_steps": None})
    if not hasattr(env, "with_command"):
        print(f"rl_eval: {args.task} has no velocity command (a joystick task is needed)", file=sys.stderr)
        return 2
    make_policy, params = load_policy(ckpt, args.task)
    t0 = time.perf_counter()
    vx, lin, _, counted, fell = walking_test(env, make_policy, episodes=args.episodes, seconds=args.seconds,
                                             speed=tuple(args.speed), seed=args.seed,
                                             deterministic=not args.stochastic)(params)
    report = {**summarize(vx, lin, counted, fell), "seconds": args.seconds, "speed_range": list(args.speed),
              "seed": args.seed, "deterministic": not args.stochastic, "wall_s": time.perf_counter() - t0}
    report.update(task=args.task, backend=args.backend, checkpoint=str(ckpt), env=env_overrides,
                  passed=report["tracking_error_mean"] <= args.max_error and report["fall_fraction"] <= args.max_falls,
                  bars={"max_error": args.max_error, "max_falls": args.max_falls})
    print(f"| episodes | command [m/s] | forward speed [m/s] | tracking error, mean / p90 [m/s] | falls | passes |\n"
          f"|---|---|---|---|---|---|\n"
          f"| {report['episodes']} x {args.seconds:g} s | {args.speed[0]:g}-{args.speed[1]:g} (mean "
          f"{report['command_mean']:.3f}) | {report['forward_speed_mean']:.3f} | {report['tracking_error_mean']:.3f} / "
          f"{report['tracking_error_p90']:.3f} | {100 * report['fall_fraction']:.1f} % | "
          f"{'yes' if report['passed'] else 'no'} (<= {args.max_error:g} m/s, <= {100 * args.max_falls:g} %) |\n"
          f"error of the mean velocity {report['mean_velocity_error']:.3f} m/s; fluctuation (std within episodes) "
          f"v_x {report['fluctuation_std_x']:.3f}, v_y {report['fluctuation_std_y']:.3f} m/s")
    if args.out:
        args.out.write_text(json.dumps(report, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
