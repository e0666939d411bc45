"""Train a registered environment with Brax's PPO: ``kamino train TASK`` or :func:`train`.

The PPO settings of each task are ``kamino.envs.configs.PPO_CONFIGS``; ``--steps``, ``--num-envs``, ``--evals``,
``--seed`` and ``--set`` override them, ``--env`` the environment's keywords and ``--solver`` its ``SolverConfig``;
``--randomize`` trains with domain randomization (``kamino.envs.randomize``'s ranges, on either backend).
``--distributed`` trains across processes and hosts (:mod:`kamino.envs.distributed`; process 0 writes the run folder).
``--init-from POLICY`` starts a new run from a trained policy (a shipped policy's name, a run folder or a checkpoint)
instead of random weights: fine-tuning, for example on rough terrain or under randomization. It restores the
policy network and the observation normaliser; the value network starts afresh (a policy file holds none).
The run folder (``--out``, default ``scratch/rl/TASK``; its layout: :mod:`kamino.envs.runs`) gets a checkpoint
after every evaluation. The evaluations come at fixed steps: every ``eval_every`` environment steps (Brax's epoch
for the run's first ``--steps`` and ``--evals``, recorded in ``run.json``), up to ``--steps``. Running the same
command again resumes from the newest complete checkpoint and trains to the same steps (Brax restores the
parameters; the optimizer state starts afresh), with the environment of the run's ``env.json``. Each evaluation's
row is committed with its checkpoint, so a run killed at any moment and resumed ends with the record of a run never
interrupted: the same evaluation steps, each row once, the same checkpoints. ``--fresh`` starts over, and refuses a
folder that holds a run unless ``--overwrite`` is given.

Besides the checkpoints the run writes ``curve.json`` (each evaluation: step, mean and spread of the episode return,
wall time, env steps/s of the epoch before it), ``train_curve.json`` (``--train-returns N``: the training episodes'
return every ~N steps and each episode metric), ``walk_tests.json`` (``--walk-test EPISODES``, joystick tasks, and
the show test of ``olaf_show``: :func:`kamino.envs.evaluate.task_test` on each checkpoint), ``reward_curve.png`` and
``report.json``.
"""

from __future__ import annotations

import argparse
import inspect
import math
import platform
import sys
import time
from pathlib import Path

from kamino.config import solver_settings
from kamino.envs import runs
from kamino.envs.evaluate import task_test
from kamino.envs.runs import OptionError, key_values
from kamino.simulator import DEFAULT_BACKEND


def walk_test_due(step: int, tested: list[int], start: int, every: int) -> bool:
    """Whether the checkpoint at ``step`` gets the walking test: from ``start`` steps on, and at least ``every``
    steps after the last tested checkpoint (``tested``, ascending; a resumed run continues the saved list)."""
    return step >= start and (not tested or step - tested[-1] >= every)


def epoch_unit(ppo: dict, defaults: dict) -> int:
    """Environment steps of the smallest epoch Brax's PPO runs with the keywords ``ppo`` (``defaults``: those of
    ``ppo.train``): ``batch_size x unroll_length x num_minibatches x action_repeat``, times the resets per
    evaluation when there are any."""
    get = lambda name: int(ppo.get(name, defaults[name]))  # noqa: E731
    resets = max(get("num_resets_per_eval"), 1)
    return get("batch_size") * get("unroll_length") * get("num_minibatches") * get("action_repeat") * resets


def eval_spacing(total: int, num_evals: int, unit: int) -> int:
    """The environment steps between two evaluations of a run of ``total`` steps and ``num_evals`` evaluations, on
    epochs of ``unit`` steps: Brax's epoch, ``ceil(total / (max(num_evals - 1, 1) unit)) unit``."""
    return math.ceil(total / (max(num_evals - 1, 1) * unit)) * unit


def eval_steps(total: int, num_evals: int, every: int) -> list[int]:
    """The evaluation (and checkpoint) steps of a run: every ``every`` steps, ``max(num_evals - 1, 1)`` of them
    and more when ``total`` lies beyond (a run resumed with more ``--steps`` than it started with)."""
    count = max(max(num_evals - 1, 1), math.ceil(total / every))
    return [every * k for k in range(1, count + 1)]


class Progress:
    """A tqdm bar over environment steps if tqdm is installed, else a printed line per update."""

    def __init__(self, total: int, start: int, enabled: bool = True):
        self.total, self.start, self.enabled = total, start, enabled
        self.bar = None
        self.shown: dict[str, str] = {}  # the bar's postfix: the last returns shown, the env steps/s
        if enabled:
            try:
                from tqdm import tqdm
            except ImportError:
                pass
            else:
                self.bar = tqdm(total=total, initial=start, unit="step", unit_scale=True, dynamic_ncols=True)

    def update(self, step: int, sps: float, elapsed: float, *, eval_return: float | None = None,
               eval_std: float | None = None, train_return: float | None = None) -> None:
        """Show ``step`` with the env steps/s and whichever return the update brings: an evaluation's (Brax's
        evaluator) or the training episodes' (``--train-returns``). A return an update lacks (an evaluation under
        ``run_evals=False``) keeps the last one shown."""
        if not self.enabled:
            return
        if eval_return is not None:
            self.shown["eval_return"] = f"{eval_return:.2f}"
        if train_return is not None:
            self.shown["train_return"] = f"{train_return:.2f}"
        self.shown["env_steps_per_s"] = f"{sps:.0f}"
        if self.bar is not None:
            self.bar.n = step
            self.bar.set_postfix(self.shown)
            self.bar.refresh()
            return
        returns = (f"eval return {eval_return:9.3f} +- {eval_std or 0.0:7.3f}  " if eval_return is not None else
                   f"train return {train_return:9.3f}  " if train_return is not None else "")
        print(f"[{step:>10d}/{self.total}] {100 * step / self.total:5.1f}%  {returns}{sps:9.0f} env steps/s  "
              f"{elapsed:7.1f} s", flush=True)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()


def plot_curve(curve: list[dict], path: Path, title: str, train_curve: list[dict] = ()) -> None:
    """The evaluation return (and the training episodes' return) against environment steps, saved atomically."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    step = np.array([c["step"] for c in curve], float)
    mean = np.array([c.get("reward", np.nan) for c in curve], float)
    std = np.array([c.get("reward_std", np.nan) for c in curve], float)
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
    if ax.get_legend_handles_labels()[0]:
        ax.legend()
    fig.tight_layout()
    tmp = path.with_name(f".{path.stem}.tmp{path.suffix}")
    fig.savefig(tmp, dpi=120)
    plt.close(fig)
    runs.replace(tmp, path)


def _check_options(task: str, steps, num_envs, evals, train_returns, walk_test, walk_test_from, walk_test_every,
                   solver: dict) -> None:
    """Refuse bad options before anything is built, naming the option."""
    from kamino.config import field_names
    from kamino.envs.configs import PPO_CONFIGS

    if task not in PPO_CONFIGS:
        raise OptionError(f"unknown task {task!r}; choose one of {sorted(PPO_CONFIGS)}")
    for name, value in (("steps", steps), ("num_envs", num_envs), ("evals", evals), ("train_returns", train_returns)):
        if value is not None and value < 1:
            raise OptionError(f"--{name.replace('_', '-')} must be >= 1, got {value}")
    for name, value in (("walk_test", walk_test), ("walk_test_from", walk_test_from),
                        ("walk_test_every", walk_test_every)):
        if value < 0:
            raise OptionError(f"--{name.replace('_', '-')} must be >= 0, got {value}")
    unknown = sorted(set(solver) - set(field_names()))
    if unknown:
        raise TypeError(f"--solver: SolverConfig has no setting {', '.join(map(repr, unknown))} (the settings, "
                        f"nested ones by their dotted names: {', '.join(field_names())})")


def randomization_of(ranges: dict):
    """The Brax ``randomization_fn`` of ``kamino train --randomize`` (``ranges``: keywords of
    :func:`kamino.envs.randomize`); an unknown keyword or a bad range raises :class:`OptionError` naming
    ``--randomize``."""
    from kamino.envs.randomization import randomize

    try:
        return randomize(**ranges)
    except (TypeError, ValueError) as e:
        known = [n for n in inspect.signature(randomize).parameters]
        raise OptionError(f"--randomize: {e} (the ranges: {', '.join(known)})") from None


def _prepare_folder(out: Path, task: str, fresh: bool, overwrite: bool, write: bool = True) -> None:
    """Create ``out``; refuse a run of another task, or ``fresh`` into a used folder without ``overwrite``.
    ``write=False`` makes the checks only (the processes of a distributed run other than process 0)."""
    if fresh and runs.is_used(out):
        if not overwrite:
            raise OptionError(f"{out} already holds a run; pass --overwrite to replace it (its checkpoints and "
                             "curves are deleted), or choose another --out")
        if write:
            runs.clear_run(out)
    recorded = None if fresh and overwrite else runs.read_json(out / "run.json", {}).get("task")
    if recorded is not None and recorded != task:
        raise OptionError(f"{out} holds a run of {recorded!r}, not {task!r}; choose another --out")
    if write:
        out.mkdir(parents=True, exist_ok=True)
        runs.clear_partial(out / "checkpoints")


def train(task: str, *, out: Path | str | None = None, backend: str = DEFAULT_BACKEND, steps: int | None = None,
          num_envs: int | None = None, evals: int | None = None, seed: int | None = None, fresh: bool = False,
          overwrite: bool = False, train_returns: int | None = None, walk_test: int = 0, walk_seed: int = 1,
          walk_test_from: int = 0, walk_test_every: int = 0, ppo: dict | None = None, solver: dict | None = None,
          env: dict | None = None, randomization: dict | None = None, init_from: str | Path | None = None,
          progress: bool = True, command: str = "") -> dict:
    """Train ``task`` with Brax's PPO into the run folder ``out`` (resuming it when it holds a run) and return the
    report (also written to ``out/report.json``).

    ``steps``, ``num_envs``, ``evals``, ``seed`` and ``ppo`` (any ``ppo.train`` keyword) override the task's PPO
    config; ``env`` overrides the environment's keywords (over the run's ``env.json`` when resuming) and ``solver``
    fields of its ``SolverConfig``. ``randomization`` (keywords of :func:`kamino.envs.randomize`; ``{}`` its
    defaults; ``None`` none) trains with Brax's domain randomization (``ppo.train(randomization_fn=...)``: every
    environment of the training and evaluation batches with its own draw). ``fresh`` starts over (``overwrite``
    allows it in a used folder). ``init_from`` (a shipped policy's name, a run folder or a checkpoint) starts a new
    run from that policy's network and normaliser (:func:`initial_params`); a run that resumes from its own
    checkpoint ignores it.
    ``walk_test`` > 0 runs the walking test with that many episodes on each checkpoint (joystick tasks), from
    ``walk_test_from`` steps on and at least ``walk_test_every`` steps apart. A bad option raises before training:
    :class:`OptionError` (a ``ValueError``), or ``TypeError`` for a keyword the environment or ``SolverConfig``
    lacks."""
    ppo, solver, env_overrides = dict(ppo or {}), dict(solver or {}), dict(env or {})
    _check_options(task, steps, num_envs, evals, train_returns, walk_test, walk_test_from, walk_test_every, solver)
    randomization_fn = None if randomization is None else randomization_of(randomization)
    import jax
    import numpy as np
    from brax.training.agents.ppo import checkpoint as ppo_checkpoint
    from brax.training.agents.ppo import train as ppo_train

    import kamino
    from kamino.envs import TASKS, make
    from kamino.envs.configs import ppo_kwargs, task_config

    if walk_test and TASKS[task].evaluation not in ("walking", "show"):
        raise OptionError(f"--walk-test needs a task with a walking or show test (kamino.envs.evaluate.task_test); "
                          f"{task} has neither")
    out = Path(out if out is not None else Path("scratch") / "rl" / task).resolve()
    # across processes (kamino.envs.distributed) process 0 owns the run folder: Brax's PPO evaluates, reports and
    # hands over the parameters there only; the others check the options alike, wait until process 0 has prepared
    # the folder, then read it (a resumed run's checkpoint) and write nothing
    lead = jax.process_index() == 0
    _prepare_folder(out, task, fresh, overwrite, write=lead)
    if jax.process_count() > 1:
        from kamino.envs.distributed import same_everywhere, synchronize

        synchronize("kamino train: run folder prepared")
    cfg = task_config(task)
    overrides = {k: v for k, v in (("num_timesteps", steps), ("num_envs", num_envs), ("num_evals", evals),
                                   ("seed", seed)) if v is not None}
    kwargs = ppo_kwargs(task, **{**ppo, **overrides})
    total, num_evals = int(kwargs["num_timesteps"]), int(kwargs["num_evals"])
    ckpt_dir = out / "checkpoints"
    paths = {key: out / name for key, name in runs.RECORD_FILES.items()}

    done, restore = runs.latest_checkpoint(ckpt_dir)
    restore_params = None if init_from is None or restore is not None else initial_params(init_from, task)
    if jax.process_count() > 1:  # every process resumes the same checkpoint, or none does
        same_everywhere(done, f"the newest checkpoint in {ckpt_dir} (its step; the run folder must be one that "
                              "every process reads, a shared file system)")
    # the rows the committed checkpoints hold; rows a killed run wrote after its last checkpoint go
    record = runs.committed_record(out) if restore is not None else {key: [] for key in paths}
    curve, train_curve, walks = record["curve"], record["train_curve"], record["walk_tests"]
    unit = epoch_unit(kwargs, _ppo_defaults(ppo_train.train))
    every = _schedule(out, restore, done, total, num_evals, unit)
    schedule = eval_steps(total, num_evals, every)
    left = sum(step > done for step in schedule)
    end = schedule[-1]
    # a resumed run keeps the environment it was trained with (env.json), a new one starts from the task's config
    env_kwargs = {**(runs.run_env(out, task) if restore else cfg["env"]), **env_overrides}
    used = min(jax.local_device_count(), kwargs.get("max_devices_per_host") or jax.local_device_count())
    # --solver settings replace the task's own solver defaults; the environment is built once, with them. On the
    # Warp backend the step of PPO's batch (num_envs over the processes and their devices) compiles in the
    # background while the environment and PPO set up
    stepping = {"solver_config": TASKS[task].default_solver_config().replace(**solver)} if solver else {}
    if backend == "warp":
        stepping["compile_for"] = max(int(kwargs["num_envs"]) // (used * jax.process_count()), 1)
    environment = make(task, backend=backend, **env_kwargs, **stepping)
    if lead:
        started_from = runs.read_json(out / "run.json", {}).get("init_from") if restore else init_from
        runs.write_json(out / "run.json", {"task": task, "backend": backend, "eval_every": every,
                                           "init_from": None if started_from is None else str(started_from)})
        runs.write_json(out / "env.json", env_kwargs)
        for key, path in paths.items():  # the run files as the committed checkpoints hold them
            if path.exists() or record[key]:
                runs.write_json_if_changed(path, record[key])
    progress = progress and lead
    if progress:
        print(f"{task}: backend {backend}, {used} device(s) {jax.devices()[0].platform}, "
              f"{environment.observation_size} observations, {environment.action_size} actions, policy "
              f"{1 / environment.dt:.0f} Hz; {'resuming at step ' + str(done) if restore else 'starting'}, "
              f"{max(end - done, 0)} steps to go{' (compiling first)' if left else ''}", flush=True)

    bar = Progress(end, done, progress)
    start = time.perf_counter()
    last: dict = {}
    first: dict = {}
    net_config = ppo_checkpoint.network_config(environment.observation_size, environment.action_size,
                                               kwargs.get("normalize_observations", False), kwargs["network_factory"])
    # what the next checkpoint commits: its parameters (Brax hands them over before evaluating them), and the rows
    # since the checkpoint before
    pending: dict = {"params": None, "make_policy": None, "curve": [], "train_curve": [], "walk_tests": []}
    walk_run = None
    # the walking test holds its command for the episode; the show test redraws its targets as in training
    held = {"resample_steps": None} if TASKS[task].evaluation == "walking" else {}
    walk_env = make(task, backend=backend, **{**env_kwargs, **held}) if walk_test else None

    def on_metrics(step: int, metrics: dict) -> None:
        nonlocal last, first
        metrics = {k: float(np.asarray(v)) for k, v in metrics.items()}
        if "episode/sum_reward" in metrics:  # brax's training-episode logger (train_returns), not an evaluation
            pending["train_curve"].append({
                "step": done + step, "reward": metrics["episode/sum_reward"],
                "length": metrics.get("episode/length", float("nan")),
                "env_steps_per_s": metrics.get("episode/sps", float("nan")),
                "run_wall_s": time.perf_counter() - start,
                "episode": {k[len("episode/"):]: v for k, v in metrics.items() if k.startswith("episode/")}})
            runs.write_json(paths["train_curve"], train_curve + pending["train_curve"])
            e = pending["train_curve"][-1]
            bar.update(e["step"], e["env_steps_per_s"], e["run_wall_s"], train_return=e["reward"])
            return
        entry = {"step": done + step, "run_wall_s": time.perf_counter() - start}
        if "eval/episode_reward" in metrics:  # none under ppo's run_evals=False (--set run_evals=False)
            entry.update(reward=metrics["eval/episode_reward"], reward_std=metrics["eval/episode_reward_std"])
        if "training/sps" in metrics:  # the epoch before this evaluation; the first one includes compilation
            entry["env_steps_per_s"] = metrics["training/sps"]
        if restore is not None and step == 0:
            # the restored policy: its row is in its checkpoint's record; a checkpoint written without one (by an
            # older kamino) may lack its row in curve.json, and this evaluation gives it
            if done not in {row["step"] for row in curve}:
                curve.append(entry)
                curve.sort(key=lambda row: row["step"])
                runs.write_json(paths["curve"], curve)
            return
        pending["curve"].append(entry)
        first = first or metrics
        last = metrics
        if step > 0:
            _commit(done + step)
        bar.update(done + step, metrics.get("training/sps", 0.0), entry["run_wall_s"], eval_return=entry.get("reward"),
                   eval_std=entry.get("reward_std"))

    def on_params(step: int, make_policy, params) -> None:
        if step > 0:  # committed with its evaluation's row (on_metrics)
            pending["params"], pending["make_policy"] = params, make_policy

    def _commit(step: int) -> None:
        """Run the walking test when due, then commit the checkpoint of ``step`` with its rows, then the run
        files."""
        nonlocal walk_run
        params = pending["params"]
        if walk_test and walk_test_due(step, [w["step"] for w in walks], walk_test_from, walk_test_every):
            t0 = time.perf_counter()
            walk_run = walk_run or task_test(walk_env, pending["make_policy"], episodes=walk_test, seconds=10.0,
                                             speed=(0.3, 0.5), seed=walk_seed)
            pending["walk_tests"].append({"step": step, **walk_run(params), "seed": walk_seed,
                                          "wall_s": time.perf_counter() - t0})
            w = pending["walk_tests"][-1]
            if "tracking_error_mean" in w:
                print(f"walking test at {w['step']}: error {w['tracking_error_mean']:.3f} m/s, falls "
                      f"{100 * w['fall_fraction']:.1f} %, forward {w['forward_speed_mean']:.3f} m/s "
                      f"({w['wall_s']:.0f} s)", flush=True)
            else:
                print(f"show test at {w['step']}: error {w['show_error_mean']:.3f} rad, falls "
                      f"{100 * w['fall_fraction']:.1f} % ({w['wall_s']:.0f} s)", flush=True)
        rows = {key: pending[key] for key in paths}
        runs.save_checkpoint(ckpt_dir, step, params, net_config, record={"step": step, "env": env_kwargs, **rows})
        for key, target in (("curve", curve), ("train_curve", train_curve), ("walk_tests", walks)):
            target.extend(pending[key])
            pending[key] = []
            if target:
                runs.write_json(paths[key], target)
        pending["params"] = pending["make_policy"] = None

    if left:
        kwargs.update(num_timesteps=left * every, num_evals=left + 1 if restore is not None or num_evals > 1 else 1,
                      progress_fn=on_metrics, policy_params_fn=on_params,
                      restore_checkpoint_path=None if restore is None else str(restore))
        if train_returns:
            kwargs.update(log_training_metrics=True, training_metrics_steps=train_returns)
        if randomization_fn is not None:
            kwargs.update(randomization_fn=randomization_fn)
        if restore_params is not None:
            check_initial_params(restore_params, environment.observation_size, environment.action_size,
                                 net_config, init_from)
            kwargs.update(restore_params=(*restore_params, None), restore_value_fn=False)
        with jax.enable_x64(False):  # brax's wrappers build float32 info entries at step only
            ppo_train.train(environment=environment, **kwargs)
    bar.close()
    wall = time.perf_counter() - start

    if not lead:
        return {"task": task, "process": jax.process_index(), "processes": jax.process_count(),
                "wall_s_this_run": wall}
    if curve or train_curve:
        try:
            plot_curve(curve, out / "reward_curve.png", f"{task} (PPO, kamino {backend} backend)", train_curve)
        except ImportError:
            pass  # matplotlib is optional: the curve stays in curve.json
    report = {
        "task": task, "backend": backend, "command": command, "env": env_kwargs, "solver_overrides": solver,
        "randomization": randomization, "init_from": runs.read_json(out / "run.json", {}).get("init_from"),
        "network": cfg["network"],
        "ppo": {k: v for k, v in kwargs.items() if isinstance(v, (int, float, str, bool)) or v is None},
        "total_steps": end, "eval_every": every, "steps_before_this_run": done,
        "steps_this_run": max(end - done, 0),
        "wall_s_this_run": wall, "env_steps_per_s": last.get("training/sps"),
        "first_eval": first, "last_eval": last, "curve": curve, "train_curve": train_curve,
        "checkpoint": str(runs.latest_checkpoint(ckpt_dir)[1]), "walk_tests": walks,
        "device": str(jax.devices()[0]), "device_count": used, "processes": jax.process_count(),
        "platform": platform.platform(),
        "versions": {"kamino": kamino.__version__, "jax": jax.__version__, "brax": _version("brax"),
                     "python": platform.python_version()},
    }
    runs.write_json(out / "report.json", report, default=str)
    if progress and curve and all("reward" in c for c in (curve[0], curve[-1])):
        print(f"return {curve[0]['reward']:.2f} (step {curve[0]['step']}) -> {curve[-1]['reward']:.2f} "
              f"(step {curve[-1]['step']}); run folder {out}", flush=True)
    return report


def initial_params(source: str | Path, task: str) -> tuple:
    """``(normaliser state, policy parameters)`` of the policy ``source`` (a shipped policy's name, a run folder or a
    checkpoint: :func:`kamino.envs.evaluate.resolve`) to start a run of ``task`` from; raises
    :class:`OptionError` naming ``--init-from`` when there is no such policy."""
    from kamino.envs.evaluate import resolve

    try:
        return tuple(resolve(source).params)
    except (FileNotFoundError, ValueError) as e:
        raise OptionError(f"--init-from: {e} (to start {task} from)") from None


def check_initial_params(params: tuple, observation_size: int, action_size: int, net_config: dict,
                         source: str | Path) -> None:
    """Raise :class:`OptionError` naming ``--init-from`` unless the policy parameters ``params`` (from
    :func:`initial_params`) fit the network that ``net_config`` describes (Brax's ``network_config``): the same
    observation and action sizes and the same hidden layers."""
    import jax

    normalizer, policy = params
    layers = [leaf.shape for leaf in jax.tree_util.tree_leaves(policy) if getattr(leaf, "ndim", 0) == 2]
    hidden = list(net_config["network_factory_kwargs"]["policy_hidden_layer_sizes"])
    want = list(zip([observation_size, *hidden[:-1]], hidden, strict=True))
    got_obs = int(normalizer.mean.shape[-1])
    fits = any(sorted(layers) == sorted([*want, (hidden[-1], k * action_size)]) for k in (1, 2))
    if got_obs != observation_size or not fits:
        raise OptionError(f"--init-from: the policy {source} takes {got_obs} observations through layers "
                          f"{[shape for shape in layers]}; this task's network takes {observation_size} observations "
                          f"through hidden layers {hidden} to {action_size} actions")


def _ppo_defaults(ppo_train_fn) -> dict:
    """The keyword defaults of Brax's ``ppo.train``."""
    return {name: p.default for name, p in inspect.signature(ppo_train_fn).parameters.items()
            if p.default is not inspect.Parameter.empty}


def _schedule(out: Path, restore: Path | None, done: int, total: int, num_evals: int, unit: int) -> int:
    """The steps between the evaluations of the run in ``out``: those recorded in its ``run.json`` when it resumes,
    else Brax's epoch for ``total`` and ``num_evals``. Raises :class:`OptionError` when the restored step ``done``
    is not an evaluation step of that schedule, or the epoch of ``unit`` steps does not divide it."""
    recorded = runs.read_json(out / "run.json", {}).get("eval_every") if restore is not None else None
    every = int(recorded) if recorded else eval_spacing(total, num_evals, unit)
    if every % unit:
        raise OptionError(f"{out} evaluates every {every} environment steps, which epochs of {unit} steps "
                          "(batch_size x unroll_length x num_minibatches x action_repeat) do not divide; resume "
                          "with the PPO settings the run started with, or start over with --fresh --overwrite")
    if done % every:
        raise OptionError(f"{out}'s newest checkpoint is at step {done}, not an evaluation step of its schedule "
                          f"(every {every} environment steps); resume with the settings the run started with, or "
                          "start over with --fresh --overwrite")
    return every


def _version(package: str) -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version(package)
    except PackageNotFoundError:
        return "not installed"


def parser() -> argparse.ArgumentParser:
    """The options of ``kamino train``."""
    from kamino.envs.configs import PPO_CONFIGS

    p = argparse.ArgumentParser(prog="kamino train", description="Train a registered environment with Brax's PPO. "
                                "Training into a run folder again resumes it from its newest checkpoint.",
                                epilog="The run folder's files: kamino.envs.runs. Evaluate a run: kamino eval RUN.")
    p.add_argument("task", choices=sorted(PPO_CONFIGS), help="the environment")
    p.add_argument("steps_pos", nargs="?", type=int, metavar="STEPS", help="total environment steps (as --steps)")
    p.add_argument("--backend", choices=("jax", "warp"), default=DEFAULT_BACKEND,
                   help=f"kamino backend (default {DEFAULT_BACKEND})")
    p.add_argument("--steps", type=int, help="total environment steps over all runs (default: the task's config)")
    p.add_argument("--num-envs", type=int, help="parallel environments (default: the task's config)")
    p.add_argument("--evals", type=int, help="evaluations (and checkpoints) over the whole training")
    p.add_argument("--seed", type=int, help="PPO seed (default: the task's config)")
    p.add_argument("--out", type=Path, help="run folder (default: scratch/rl/TASK)")
    p.add_argument("--fresh", action="store_true", help="start over instead of resuming")
    p.add_argument("--overwrite", action="store_true", help="with --fresh: delete the run already in --out")
    p.add_argument("--train-returns", type=int, metavar="N", help="log the training episodes' return every ~N steps")
    p.add_argument("--walk-test", type=int, default=0, metavar="EPISODES",
                   help="joystick tasks: the walking test with EPISODES episodes on each checkpoint")
    p.add_argument("--walk-seed", type=int, default=1, help="the walking test's seed (default 1)")
    p.add_argument("--walk-test-from", type=int, default=0, metavar="STEPS", help="no walking test before STEPS")
    p.add_argument("--walk-test-every", type=int, default=0, metavar="STEPS",
                   help="at least STEPS between walking tests (default 0: every checkpoint)")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="a ppo.train keyword, VALUE a Python literal (repeatable)")
    p.add_argument("--solver", action="append", default=[], metavar="KEY=VALUE",
                   help="a SolverConfig setting, dotted for a nested one (penalty.rho=0.05), VALUE a Python "
                        "literal or a bare word (reduction=schur; repeatable)")
    p.add_argument("--env", action="append", default=[], metavar="KEY=VALUE",
                   help="an environment keyword, VALUE a Python literal (repeatable)")
    p.add_argument("--init-from", metavar="POLICY", help="start a new run from this policy (a shipped policy's name, "
                   "a run folder or a checkpoint): its network and normaliser; the value network starts afresh")
    p.add_argument("--randomize", action="append", default=None, nargs="?", const="", metavar="KEY=(LOW,HIGH)",
                   help="train with domain randomization: a range of kamino.envs.randomize (mass_scale=(0.8,1.2), "
                        "gravity_scale=None, ...; repeatable); alone, randomize's default ranges")
    group = p.add_argument_group("training across processes", "one process per host, each on its local devices "
                                 "(jax.distributed); the same command on every host (docs/envs.md)")
    group.add_argument("--distributed", action="store_true",
                       help="start JAX's multi-process runtime; alone, it reads the cluster's settings (SLURM, Open "
                            "MPI, JAX_COORDINATOR_ADDRESS)")
    group.add_argument("--coordinator", metavar="HOST:PORT", help="process 0's address")
    group.add_argument("--num-processes", type=int, metavar="N", help="the processes in all")
    group.add_argument("--process-id", type=int, metavar="I", help="this process's index, 0 to N - 1")
    return p


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    """``kamino train``'s options, with ``--set``, ``--solver`` and ``--env`` read into ``ppo_overrides``,
    ``solver_overrides`` and ``env_overrides``; a bad option exits through argparse, naming it."""
    p = parser()
    args = p.parse_args(argv)
    if args.steps_pos is not None:
        if args.steps is not None and args.steps != args.steps_pos:
            p.error(f"STEPS {args.steps_pos} and --steps {args.steps} disagree")
        args.steps = args.steps_pos
    try:
        args.ppo_overrides = key_values(args.set, "--set")
        args.solver_overrides = solver_settings(args.solver)
        args.env_overrides = key_values(args.env, "--env")
        args.randomization = (None if args.randomize is None
                              else key_values([r for r in args.randomize if r], "--randomize"))
        if args.randomization is not None:
            randomization_of(args.randomization)
        _check_options(args.task, args.steps, args.num_envs, args.evals, args.train_returns, args.walk_test,
                       args.walk_test_from, args.walk_test_every, args.solver_overrides)
    except (ValueError, TypeError) as e:
        p.error(str(e))
    if args.overwrite and not args.fresh:
        p.error("--overwrite only goes with --fresh")
    given = [o for o, v in (("--coordinator", args.coordinator), ("--num-processes", args.num_processes),
                            ("--process-id", args.process_id)) if v is not None]
    if given and not args.distributed:
        p.error(f"{', '.join(given)} only go with --distributed")
    if (args.num_processes is None) != (args.process_id is None):
        p.error("--num-processes and --process-id go together")
    if args.num_processes is not None and not 0 <= args.process_id < args.num_processes:
        p.error(f"--process-id must be in [0, {args.num_processes}), got {args.process_id}")
    return args


def main(argv: list[str] | None = None) -> int:
    """``kamino train ARGS``: returns the exit status."""
    args = parse_args(sys.argv[1:] if argv is None else argv)
    if args.distributed:  # before any JAX computation
        from kamino.envs.distributed import initialize

        initialize(args.coordinator, args.num_processes, args.process_id)
    try:
        train(args.task, out=args.out, backend=args.backend, steps=args.steps, num_envs=args.num_envs,
              evals=args.evals, seed=args.seed, fresh=args.fresh, overwrite=args.overwrite,
              train_returns=args.train_returns, walk_test=args.walk_test, walk_seed=args.walk_seed,
              walk_test_from=args.walk_test_from, walk_test_every=args.walk_test_every, ppo=args.ppo_overrides,
              solver=args.solver_overrides, env=args.env_overrides, randomization=args.randomization,
              init_from=args.init_from,
              command=" ".join(["kamino", "train", *(sys.argv[1:] if argv is None else argv)]))
    except OptionError as e:
        print(f"kamino train: error: {e}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
