"""What a joystick policy's velocity-tracking error is made of: ``python benchmarks/rl_velocity_trace.py CHECKPOINT``.

The walking test (``benchmarks/rl_eval.py``) reports the mean over policy steps of ``|cmd_xy - v_xy|``. This script
runs the same episodes (forward commands uniform in ``--speed``, deterministic actions, the same seed convention)
and splits that error, per episode that does not fall, after the first ``--settle`` seconds:

- ``oscillation``: the mean of ``|v_xy - mean(v_xy)|``, the gait's sway about the episode's mean velocity. A policy
  whose mean velocity equalled the command would still score this much;
- ``mean_velocity_error``: ``|cmd_xy - mean(v_xy)|``, the error of the walking speed and drift;
- ``per_step_error``: the walking test's quantity over the same steps;
- the mean forward and lateral speed, their standard deviations, and the mean yaw rate (the command's is 0);
- ``sway_hz``: the frequency of the largest peak of the lateral velocity's spectrum.

``--out`` writes the JSON (every episode and the means over the upright ones).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))  # rl_eval, beside this script


def split_error(command: float, lin, ang, upright, dt: float, settle: float, fell: bool | None = None) -> dict:
    """The error of one episode split as the module doc says; an episode that fell (``fell``, by default: not
    ``upright`` throughout) reports only its upright steps."""
    import numpy as np

    if fell is None:
        fell = not bool(upright.all())
    if fell:
        return {"command": float(command), "fell": True, "steps_up": int(upright.sum())}
    v = lin[round(settle / dt):, :2]
    cmd = np.array([command, 0.0])
    mean_v = v.mean(0)
    lateral = v[:, 1] - v[:, 1].mean()
    freq = np.fft.rfftfreq(len(lateral), dt)
    spectrum = np.abs(np.fft.rfft(lateral))
    return {"command": float(command), "fell": False,
            "per_step_error": float(np.linalg.norm(cmd - v, axis=1).mean()),
            "oscillation": float(np.linalg.norm(v - mean_v, axis=1).mean()),
            "mean_velocity_error": float(np.linalg.norm(cmd - mean_v)),
            "forward_mean": float(mean_v[0]), "lateral_mean": float(mean_v[1]),
            "forward_std": float(v[:, 0].std()), "lateral_std": float(v[:, 1].std()),
            "yaw_rate_mean": float(ang[round(settle / dt):, 2].mean()),
            "sway_hz": float(freq[1:][np.argmax(spectrum[1:])])}


def main(argv=None) -> int:
    from rl_eval import load_policy, newest_checkpoint, walking_test

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("checkpoint", type=Path, help="a checkpoint folder, or an rl_train.py output folder")
    p.add_argument("--task", default="dr_legs_joystick")
    p.add_argument("--backend", choices=("jax", "warp"), default="warp")
    p.add_argument("--episodes", type=int, default=16)
    p.add_argument("--seconds", type=float, default=10.0)
    p.add_argument("--settle", type=float, default=2.0, help="seconds left out at the start of each episode")
    p.add_argument("--speed", type=float, nargs=2, default=(0.3, 0.5), metavar=("LOW", "HIGH"))
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", type=Path, default=None)
    args = p.parse_args(argv)
    if args.episodes < 1 or not 0 <= args.settle < args.seconds or not args.speed[0] <= args.speed[1]:
        p.error("--episodes must be >= 1, 0 <= --settle < --seconds and --speed LOW <= HIGH")
    import numpy as np
    from rl_train import run_env

    from kamino.envs import make

    ckpt = newest_checkpoint(args.checkpoint.resolve())
    env = make(args.task, backend=args.backend, **{**run_env(args.checkpoint.resolve(), args.task),
                                                   "resample_steps": None})
    t0 = time.perf_counter()
    make_policy, params = load_policy(ckpt, args.task)
    cmd, lin, ang, upright, fell = walking_test(env, make_policy, episodes=args.episodes, seconds=args.seconds,
                                                speed=tuple(args.speed), seed=args.seed)(params)
    rows = [split_error(c, lin[i], ang[i], upright[i], env.dt, args.settle, bool(fell[i])) for i, c in enumerate(cmd)]
    up = [r for r in rows if not r["fell"]]
    keys = ("per_step_error", "oscillation", "mean_velocity_error", "forward_mean", "forward_std", "lateral_std",
            "yaw_rate_mean", "sway_hz")
    means = {k: float(np.mean([r[k] for r in up])) for k in keys} if up else {}
    report = {"checkpoint": str(ckpt), "task": args.task, "backend": args.backend, "episodes": args.episodes,
              "seconds": args.seconds, "settle": args.settle, "speed_range": list(args.speed), "seed": args.seed,
              "fell": len(rows) - len(up), "means_over_upright": means, "episodes_detail": rows,
              "wall_s": time.perf_counter() - t0}
    print(f"{len(up)} of {len(rows)} episodes upright; means after {args.settle:g} s: "
          + ", ".join(f"{k} {v:.3f}" for k, v in means.items()))
    if args.out:
        args.out.write_text(json.dumps(report, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
