"""Train a kamino environment with brax's PPO (issue 18): ``python benchmarks/rl_train.py TASK``.

The PPO settings of each task are ``kamino.envs.configs.PPO_CONFIGS`` (``--steps``, ``--num-envs``, ``--evals``,
``--seed`` and ``--set`` override them; ``--env`` overrides the environment's keywords, ``--solver`` its
``SolverConfig``). Writes into ``--out`` (default ``scratch/rl/TASK``, git-ignored):

- ``env.json``: the environment's keywords (the task's config with ``--env`` over it). A resumed run starts from
  these instead of the config, and ``rl_eval.py`` and ``rl_velocity_trace.py`` build the environment from them;
- ``checkpoints/<step>/``: the policy (normalizer, policy, value parameters; brax's orbax format and network config)
  after every evaluation, ``<step>`` counting environment steps over all runs. A later run of the same command
  resumes from the newest one and trains the steps that remain (brax restores the parameters; the optimizer state
  starts afresh); ``--fresh`` ignores them.
- ``curve.json``: every evaluation (step, mean and spread of the episode return, wall time, and the env steps/s of
  the training epoch before it: the first epoch includes compilation), over all runs;
- ``train_curve.json`` (``--train-returns N``): the mean return and length of the training episodes that ended in
  each window of about ``N`` environment steps (brax's ``log_training_metrics``), every episode metric (each reward
  term and the world-health flag, summed over the episode), and the env steps/s of that window.
  It costs no evaluation rollouts, so a run with ``--set run_evals=False`` still shows whether the policy learns;
- ``walk_tests.json`` (``--walk-test EPISODES``, joystick tasks): the walking test of ``benchmarks/rl_eval.py``
  (forward commands 0.3-0.5 m/s, 10 s, deterministic actions; seed ``--walk-seed``, by default 1, not the issue's
  0) on every checkpoint as it is saved, compiled once per run: the checkpoint to keep is chosen on it;
- ``reward_curve.png``: the evaluation return against environment steps, and the training episodes' return when
  ``--train-returns`` is given (matplotlib);
- ``report.json``: the task, backend, settings, device, versions, the first and last evaluation with every
  ``eval/`` metric (the reward terms of docs/envs.md), training throughput and wall time.

Progress: a tqdm bar when tqdm is installed, else one line per evaluation, both with the environment steps per
second of the last training epoch.
"""

from __future__ import annotations

import argparse
import ast
import dataclasses
import json
import platform
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def key_values(p: argparse.ArgumentParser, flag: str, items: list[str]) -> dict:
    """``KEY=VALUE`` options (``VALUE`` a Python literal) as a dict; a malformed one is ``p.error`` naming ``flag``.
    The benchmarks' ``--set``, ``--solver`` and ``--env`` options all read through it."""
    out = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep or not key.isidentifier():
            p.error(f"{flag} expects KEY=VALUE, got {item!r}")
        try:
            out[key] = ast.literal_eval(value)
        except (ValueError, SyntaxError):
            p.error(f"{flag} {key}: {value!r} is not a Python literal")
    return out


def parse_args(argv=None) -> argparse.Namespace:
    from kamino.envs.configs import PPO_CONFIGS

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0], formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("task", choices=sorted(PPO_CONFIGS), help="the environment (kamino.envs.TASKS)")
    p.add_argument("--backend", choices=("jax", "warp"), default="jax", help="kamino backend (default jax)")
    p.add_argument("--steps", type=int, help="total environment steps over all runs (default: the task's config)")
    p.add_argument("--num-envs", type=int, help="parallel environments (default: the task's config)")
    p.add_argument("--evals", type=int, help="evaluations over the whole training (default: the task's config)")
    p.add_argument("--seed", type=int, help="PPO seed (default: the task's config)")
    p.add_argument("--out", type=Path, help="output folder (default: scratch/rl/TASK)")
    p.add_argument("--fresh", action="store_true", help="ignore existing checkpoints and curve; start over")
    p.add_argument("--train-returns", type=int, metavar="N",
                   help="log the training episodes' mean return every ~N env steps (train_curve.json)")
    p.add_argument("--walk-test", type=int, default=0, metavar="EPISODES",
                   help="run the walking test (benchmarks/rl_eval.py) with EPISODES episodes on every checkpoint")
    p.add_argument("--walk-seed", type=int, default=1, help="the walking test's seed (default 1)")
    p.add_argument("--walk-test-from", type=int, default=0, metavar="STEPS",
                   help="skip the walking test on checkpoints before STEPS environment steps (a run from scratch "
                        "does not walk for its first tens of millions; each test costs about 40 s on an H100)")
    p.add_argument("--walk-test-every", type=int, default=0, metavar="STEPS",
                   help="skip the walking test on a checkpoint less than STEPS environment steps after the last "
                        "tested one (default 0: every checkpoint; a test of 30 s every 4 M steps costs a quarter of "
                        "an H100's training time at 4.5e4 env steps/s)")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="any other ppo.train keyword, VALUE a Python literal (repeatable): --set batch_size=32")
    p.add_argument("--solver", action="append", default=[], metavar="KEY=VALUE",
                   help="a field of the task's SolverConfig, VALUE a Python literal (repeatable): --solver "
                        "max_iterations=100")
    p.add_argument("--env", action="append", default=[], metavar="KEY=VALUE",
                   help="an environment keyword over the task's config, VALUE a Python literal (repeatable): "
                        "--env tracking_sigma=0.1 (over the run's env.json when resuming)")
    args = p.parse_args(argv)
    args.ppo_overrides = key_values(p, "--set", args.set)
    args.solver_overrides = key_values(p, "--solver", args.solver)
    args.env_overrides = key_values(p, "--env", args.env)
    if args.walk_test < 0:
        p.error(f"--walk-test must be >= 0, got {args.walk_test}")
    if args.walk_test_from < 0:
        p.error(f"--walk-test-from must be >= 0, got {args.walk_test_from}")
    if args.walk_test_every < 0:
        p.error(f"--walk-test-every must be >= 0, got {args.walk_test_every}")
    for name in ("steps", "num_envs", "evals", "train_returns"):
        value = getattr(args, name)
        if value is not None and value < 1:
            p.error(f"--{name.replace('_', '-')} must be >= 1, got {value}")
    return args


def walk_test_due(step: int, tested: list[int], start: int, every: int) -> bool:
    """Whether the checkpoint at ``step`` gets the walking test: from ``start`` steps on, and at least ``every``
    steps after the last tested checkpoint (``tested``, ascending; a resumed run continues the saved list)."""
    return step >= start and (not tested or step - tested[-1] >= every)


def run_env(path: Path, task: str) -> dict:
    """The environment keywords a run was trained with: ``env.json`` of the run folder ``path`` (or of the run that
    holds the checkpoint ``path``: ``RUN/checkpoints/<step>``), else the task's config (a run written before
    session 37, which saved none, trained with the config of its day: docs/envs.md names it)."""
    from kamino.envs.configs import task_config

    for folder in (path, path.parent, path.parent.parent):
        if (folder / "env.json").exists():
            return json.loads((folder / "env.json").read_text())
    return task_config(task)["env"]


def latest_checkpoint(folder: Path) -> tuple[int, Path | None]:
    """``(step, path)`` of the newest checkpoint under ``folder`` (``(0, None)`` without one)."""
    steps = sorted(int(d.name) for d in folder.glob("*") if d.is_dir() and d.name.isdigit()) if folder.exists() else []
    return (steps[-1], folder / f"{steps[-1]:012d}") if steps else (0, None)


class Progress:
    """A tqdm bar over environment steps if tqdm is installed, else a printed line per update."""

    def __init__(self, total: int, start: int):
        self.total, self.start = total, start
        try:
            from tqdm import tqdm
        except ImportError:
            self.bar = None
        else:
            self.bar = tqdm(total=total, initial=start, unit="step", unit_scale=True, dynamic_ncols=True)

    def update(self, step: int, reward: float, std: float, sps: float, elapsed: float) -> None:
        if self.bar is not None:
            self.bar.n = step
            self.bar.set_postfix(reward=f"{reward:.2f}", env_steps_per_s=f"{sps:.0f}")
            self.bar.refresh()
            return
        print(f"[{step:>10d}/{self.total}] {100 * step / self.total:5.1f}%  eval return {reward:9.3f} +- {std:7.3f}  "
              f"{sps:9.0f} env steps/s  {elapsed:7.1f} s", flush=True)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()


def plot_curve(curve: list[dict], path: Path, title: str, train_curve: list[dict] = ()) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    step = np.array([c["step"] for c in curve], float)
    mean = np.array([c["reward"] for c in curve])
    std = np.array([c["reward_std"] for c in curve])
    fig, ax = plt.subplots(figsize=(6, 4))
    if np.isfinite(mean).any():
        ax.plot(step, mean, marker="o", label="evaluation episodes")
        ax.fill_between(step, mean - std, mean + std, alpha=0.25, label="spread of the evaluation returns")
    if train_curve:
        ax.plot([c["step"] for c in train_curve], [c["reward"] for c in train_curve], label="training episodes (mean)")
    ax.set_xlabel("environment steps")
    ax.set_ylabel("episode return")
    ax.set_title(title)
    ax.grid(alpha=0.3)
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main(argv=None) -> int:
    args = parse_args(argv)
    import jax
    import numpy as np
    from brax.training.agents.ppo import checkpoint as ppo_checkpoint
    from brax.training.agents.ppo import train as ppo

    import kamino
    from kamino.envs import TASKS, make
    from kamino.envs.configs import ppo_kwargs, task_config

    cfg = task_config(args.task)
    overrides = {k: v for k, v in (("num_timesteps", args.steps), ("num_envs", args.num_envs),
                                   ("num_evals", args.evals), ("seed", args.seed)) if v is not None}
    kwargs = ppo_kwargs(args.task, **{**args.ppo_overrides, **overrides})
    total, evals = int(kwargs["num_timesteps"]), int(kwargs["num_evals"])
    out = (args.out or ROOT / "scratch" / "rl" / args.task).resolve()
    ckpt_dir = out / "checkpoints"
    curve_path = out / "curve.json"
    out.mkdir(parents=True, exist_ok=True)

    done, restore = (0, None) if args.fresh else latest_checkpoint(ckpt_dir)
    curve = json.loads(curve_path.read_text()) if curve_path.exists() and not args.fresh else []
    curve = [c for c in curve if c["step"] <= done]
    train_path = out / "train_curve.json"
    train_curve = json.loads(train_path.read_text()) if train_path.exists() and not args.fresh else []
    train_curve = [c for c in train_curve if c["step"] <= done]
    remaining = total - done
    # a resumed run keeps the environment it was trained with (env.json), a new one starts from the task's config
    env_kwargs = {**(run_env(out, args.task) if restore else cfg["env"]), **args.env_overrides}
    # refused before any environment is built (a robot's construction solves its reset bank)
    dataclasses.replace(kamino.SolverConfig(), **args.solver_overrides)  # a field it lacks raises, naming it
    if args.walk_test and not hasattr(TASKS[args.task], "with_command"):
        raise SystemExit(f"rl_train: --walk-test needs a joystick task; {args.task} has no velocity command")
    env = make(args.task, backend=args.backend, **env_kwargs)
    (out / "env.json").write_text(json.dumps(env_kwargs, indent=1) + "\n")
    if args.solver_overrides:
        config = dataclasses.replace(env.solver_config, **args.solver_overrides)
        env = make(args.task, backend=args.backend, solver_config=config, **env_kwargs)
    used = min(jax.local_device_count(), kwargs.get("max_devices_per_host") or jax.local_device_count())
    print(f"{args.task}: backend {args.backend}, {used} device(s) {jax.devices()[0].platform}, "
          f"{env.observation_size} observations, {env.action_size} actions, policy {1 / env.dt:.0f} Hz; "
          f"{'resuming at step ' + str(done) if restore else 'starting'}, {max(remaining, 0)} steps to go", flush=True)

    progress = Progress(total, done)
    start = time.perf_counter()
    last: dict = {}
    first: dict = {}
    config = ppo_checkpoint.network_config(env.observation_size, env.action_size,
                                           kwargs.get("normalize_observations", False), kwargs["network_factory"])

    def on_eval(step: int, metrics: dict) -> None:
        nonlocal last, first
        metrics = {k: float(np.asarray(v)) for k, v in metrics.items()}
        if "episode/sum_reward" in metrics:  # brax's training-episode logger (--train-returns), not an evaluation
            train_curve.append({"step": done + step, "reward": metrics["episode/sum_reward"],
                                "length": metrics.get("episode/length", float("nan")),
                                "env_steps_per_s": metrics.get("episode/sps", float("nan")),
                                "run_wall_s": time.perf_counter() - start,
                                # every episode metric: each reward term and `failed` summed over the episode
                                "episode": {k[len("episode/"):]: v for k, v in metrics.items()
                                            if k.startswith("episode/")}})
            train_path.write_text(json.dumps(train_curve, indent=1))
            entry = train_curve[-1]
            progress.update(entry["step"], entry["reward"], float("nan"), entry["env_steps_per_s"], entry["run_wall_s"])
            return
        if restore is not None and step == 0:
            return  # the restored policy, evaluated by the previous run already
        entry = {"step": done + step, "reward": metrics.get("eval/episode_reward", float("nan")),
                 "reward_std": metrics.get("eval/episode_reward_std", float("nan")),
                 "run_wall_s": time.perf_counter() - start}
        if "training/sps" in metrics:  # the epoch before this evaluation; the first one includes compilation
            entry["env_steps_per_s"] = metrics["training/sps"]
        curve.append(entry)
        curve_path.write_text(json.dumps(curve, indent=1))
        first = first or metrics
        last = metrics
        progress.update(done + step, entry["reward"], entry["reward_std"], metrics.get("training/sps", 0.0),
                        entry["run_wall_s"])

    walk_path = out / "walk_tests.json"
    walks = json.loads(walk_path.read_text()) if walk_path.exists() and not args.fresh else []
    walks = [w for w in walks if w["step"] <= done]
    walk_run = None
    if args.walk_test:
        walk_env = make(args.task, backend=args.backend, **{**env_kwargs, "resample_steps": None})

    def save(step: int, make_policy, params) -> None:
        nonlocal walk_run
        if step == 0:
            return
        ppo_checkpoint.save(ckpt_dir, done + step, params, config)
        if args.walk_test and walk_test_due(done + step, [w["step"] for w in walks], args.walk_test_from,
                                            args.walk_test_every):
            from rl_eval import summarize, walking_test

            t0 = time.perf_counter()
            walk_run = walk_run or walking_test(walk_env, make_policy, episodes=args.walk_test, seconds=10.0,
                                                speed=(0.3, 0.5), seed=args.walk_seed)
            vx, lin, _, counted, fell = walk_run(params)
            walks.append({"step": done + step, **summarize(vx, lin, counted, fell), "seed": args.walk_seed,
                          "wall_s": time.perf_counter() - t0})
            walk_path.write_text(json.dumps(walks, indent=1))
            w = walks[-1]
            print(f"walking test at {w['step']}: error {w['tracking_error_mean']:.3f} m/s, falls "
                  f"{100 * w['fall_fraction']:.1f} %, forward {w['forward_speed_mean']:.3f} m/s; mean-velocity error "
                  f"{w['mean_velocity_error']:.3f}, sway x/y {w['fluctuation_std_x']:.3f}/{w['fluctuation_std_y']:.3f} "
                  f"({w['wall_s']:.0f} s)", flush=True)

    if remaining > 0:
        run_evals = max(2, round(evals * remaining / total))
        kwargs.update(num_timesteps=remaining, num_evals=run_evals, progress_fn=on_eval, policy_params_fn=save,
                      restore_checkpoint_path=None if restore is None else str(restore))
        if args.train_returns:
            kwargs.update(log_training_metrics=True, training_metrics_steps=args.train_returns)
        with jax.enable_x64(False):  # brax's wrappers build float32 info entries at step only
            ppo.train(environment=env, **kwargs)
    progress.close()
    wall = time.perf_counter() - start

    if curve or train_curve:
        plot_curve(curve, out / "reward_curve.png", f"{args.task} (PPO, kamino {args.backend} backend)", train_curve)
    report = {
        "task": args.task, "backend": args.backend, "command": " ".join(sys.argv),
        "env": env_kwargs, "solver_overrides": args.solver_overrides, "network": cfg["network"],
        "ppo": {k: v for k, v in kwargs.items() if isinstance(v, (int, float, str, bool)) or v is None},
        "total_steps": total, "steps_before_this_run": done, "steps_this_run": max(remaining, 0),
        "wall_s_this_run": wall, "env_steps_per_s": last.get("training/sps"),
        "first_eval": first, "last_eval": last, "curve": curve, "train_curve": train_curve,
        "checkpoint": str(latest_checkpoint(ckpt_dir)[1]), "walk_tests": walks,
        "device": str(jax.devices()[0]), "device_count": used, "platform": platform.platform(),
        "versions": {"kamino": kamino.__version__, "jax": jax.__version__, "brax": _version("brax"),
                     "python": platform.python_version()},
    }
    (out / "report.json").write_text(json.dumps(report, indent=1, default=str))
    if train_curve:
        print(f"training episodes' return {train_curve[0]['reward']:.2f} (step {train_curve[0]['step']}) -> "
              f"{train_curve[-1]['reward']:.2f} (step {train_curve[-1]['step']})")
    if curve and np.isfinite([c["reward"] for c in curve]).any():
        print(f"return {curve[0]['reward']:.2f} (step {curve[0]['step']}) -> {curve[-1]['reward']:.2f} "
              f"(step {curve[-1]['step']}); {out / 'report.json'}, {out / 'reward_curve.png'}")
    return 0


def _version(package: str) -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version(package)
    except PackageNotFoundError:
        return "not installed"


if __name__ == "__main__":
    sys.exit(main())
