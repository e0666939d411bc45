"""Run folders of ``kamino train``: atomic side files, committed checkpoints, and what a run was trained with.

A run folder ``RUN`` holds:

- ``run.json``: the task, the backend and the evaluation spacing (``eval_every``, environment steps);
- ``env.json``: the environment's keywords (the task's config with ``--env`` over it);
- ``checkpoints/<step>/``: Brax's PPO checkpoint (orbax parameters and ``ppo_network_config.json``) and
  ``record.json`` (the environment's keywords, and the curve rows, training-return rows and walking tests of the
  steps since the checkpoint before) after each evaluation, ``<step>`` the environment steps over all runs,
  zero-padded to 12 digits;
- ``curve.json``, ``train_curve.json``, ``walk_tests.json``, ``report.json``, ``reward_curve.png``.

Every JSON file is written whole or not at all (:func:`write_json`: a temporary file in the same folder, then
``os.replace``). A checkpoint is written complete under ``checkpoints/.staging/`` and renamed into place
(:func:`save_checkpoint`), so ``checkpoints/<step>/`` exists only once every file in it does; a folder that lacks
orbax's ``commit_success.txt`` marker or the network config is not a checkpoint (:func:`committed_checkpoints`).
An evaluation's row and its checkpoint are one committed unit: the row lives in the checkpoint's ``record.json``,
and the run's ``curve.json``, ``train_curve.json`` and ``walk_tests.json`` are rebuilt from the committed
checkpoints when a run resumes (:func:`committed_record`). Whenever a run is killed, the run it resumes to ends with
the same evaluation steps, each row once, and the same checkpoints as a run never interrupted.
"""

from __future__ import annotations

import ast
import json
import os
import shutil
import tempfile
from pathlib import Path
from typing import Any

#: the network config Brax writes beside the parameters
NETWORK_CONFIG = "ppo_network_config.json"
#: orbax's marker of a finished save
COMMIT_MARKER = "commit_success.txt"
#: where a checkpoint is assembled before its rename into ``checkpoints/``
STAGING = ".staging"
#: the file in a checkpoint with the environment's keywords and the rows the checkpoint commits
RECORD = "record.json"
#: the run files rebuilt from the checkpoints' records, each a list of rows with a ``step``
RECORD_FILES = {"curve": "curve.json", "train_curve": "train_curve.json", "walk_tests": "walk_tests.json"}
#: the files a run writes; ``--fresh --overwrite`` removes these and nothing else
RUN_FILES = ("run.json", "env.json", "curve.json", "train_curve.json", "walk_tests.json", "report.json",
             "reward_curve.png")


def write_json(path: Path, data: Any, **dump_kwargs) -> None:
    """Write ``data`` as JSON to ``path`` atomically: a reader (or a resumed run) sees the old file or the new one,
    never a part of either, whenever the writer is killed."""
    text = json.dumps(data, indent=1, **dump_kwargs) + "\n"
    write_text(path, text)


def write_json_if_changed(path: Path, data: Any) -> bool:
    """:func:`write_json` unless ``path`` already holds exactly that JSON; whether it wrote."""
    path = Path(path)
    text = json.dumps(data, indent=1) + "\n"
    if path.is_file() and path.read_text() == text:
        return False
    write_text(path, text)
    return True


def write_text(path: Path, text: str) -> None:
    """Write ``text`` to ``path`` atomically (a temporary file beside it, flushed to disk, then ``os.replace``)."""
    path = Path(path)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "w") as f:
            f.write(text)
            f.flush()
            os.fsync(f.fileno())
        replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def replace(src: str | Path, dst: str | Path) -> None:
    """``os.replace(src, dst)``: the one rename that commits a side file or a checkpoint."""
    os.replace(src, dst)


def read_json(path: Path, default: Any = None) -> Any:
    """The JSON in ``path``, or ``default`` when it does not exist."""
    path = Path(path)
    return json.loads(path.read_text()) if path.exists() else default


def is_checkpoint(path: Path) -> bool:
    """Whether ``path`` is a complete Brax PPO checkpoint: orbax's commit marker and the network config present."""
    path = Path(path)
    return (path / COMMIT_MARKER).is_file() and (path / NETWORK_CONFIG).is_file()


def committed_checkpoints(folder: Path) -> list[tuple[int, Path]]:
    """``(step, path)`` of every complete checkpoint ``folder/<step>/``, ascending; anything else (a half-written
    folder, the staging area, a stray file) is skipped."""
    folder = Path(folder)
    if not folder.is_dir():
        return []
    found = [(int(d.name), d) for d in folder.iterdir() if d.name.isdigit() and d.is_dir() and is_checkpoint(d)]
    return sorted(found)


def latest_checkpoint(folder: Path) -> tuple[int, Path | None]:
    """``(step, path)`` of the newest complete checkpoint under ``folder`` (``(0, None)`` without one)."""
    found = committed_checkpoints(folder)
    return found[-1] if found else (0, None)


def stage_checkpoint(staging: Path, step: int, params: Any, config: Any) -> Path:
    """Write the checkpoint of ``step`` under ``staging``; returns its folder.

    In one process this is Brax's writer (``brax.training.agents.ppo.checkpoint.save``). Across processes
    (``jax.process_count() > 1``, :mod:`kamino.envs.distributed`) only process 0 holds the parameters at a checkpoint:
    Brax's PPO hands them over there alone. Brax's writer saves through orbax's default checkpointer, whose ``save``
    waits at a barrier for every process, and the other processes never reach it; process 0 then writes the same
    files alone (:func:`write_checkpoint_alone`)."""
    import jax

    if jax.process_count() > 1:
        return write_checkpoint_alone(staging, step, params, config)
    from brax.training.agents.ppo import checkpoint as ppo_checkpoint

    ppo_checkpoint.save(staging, step, params, config)
    return staging / f"{step:012d}"


def write_checkpoint_alone(staging: Path, step: int, params: Any, config: Any) -> Path:
    """The files of Brax's PPO checkpoint writer, ``staging/<step>/``, written by this process without waiting for
    any other: the parameters through an orbax checkpointer whose multiprocessing options name this process as the
    only active one (orbax skips its barriers for a single active process), as host arrays in the containers orbax
    gives Brax's writer (a dataclass's fields as a dict, a tuple as a list), and the network config as Brax writes
    it (:func:`network_config_text`). Brax's loader reads it as it reads its own checkpoints."""
    import jax
    import numpy as np
    from flax import serialization
    from orbax import checkpoint as ocp

    path = Path(staging) / f"{step:012d}"
    path.mkdir(parents=True, exist_ok=True)
    alone = ocp.options.MultiprocessingOptions(primary_host=jax.process_index(),
                                                active_processes={jax.process_index()})
    checkpointer = ocp.Checkpointer(ocp.PyTreeCheckpointHandler(multiprocessing_options=alone),
                                    multiprocessing_options=alone)
    # host copies: a device array of the multi-process runtime is process-local and orbax refuses it; a dataclass
    # (Brax's UInt64 step count) turns its fields back into device arrays, hence its state dict
    tree = jax.tree.map(np.asarray, [serialization.to_state_dict(p) for p in params])
    checkpointer.save(path, args=ocp.args.PyTreeSave(tree, save_args=jax.tree.map(lambda _: ocp.SaveArgs(), tree)),
                      force=True)
    (path / NETWORK_CONFIG).write_text(network_config_text(config))
    return path


def network_config_text(config: Any) -> str:
    """``ppo_network_config.json`` of the network config ``config`` (``ppo.checkpoint.network_config``'s
    ``ConfigDict``) as Brax's checkpoint writer makes it: the activation and kernel initialisers by their names in
    Brax's registries (``brax.training.networks.ACTIVATION``, ``KERNEL_INITIALIZER``), arrays as Python numbers
    and lists, then ``ConfigDict.to_json_best_effort``. A function outside the registries raises ``ValueError``
    (Brax's loader could not rebuild it)."""
    import numpy as np
    from brax.training import networks
    from ml_collections import config_dict

    def plain(value):
        if isinstance(value, dict):
            return {k: plain(v) for k, v in value.items()}
        if isinstance(value, (list, tuple)):
            return type(value)(plain(v) for v in value)
        if hasattr(value, "ndim") and hasattr(value, "tolist"):
            return np.asarray(value).tolist()
        return value

    data = config.to_dict()
    factory = data["network_factory_kwargs"]
    for key, registry in (("activation", networks.ACTIVATION),
                          *((k, networks.KERNEL_INITIALIZER) for k in ("policy_network_kernel_init_fn",
                                                                       "value_network_kernel_init_fn",
                                                                       "q_network_kernel_init_fn",
                                                                       "mean_kernel_init_fn"))):
        fn = factory.get(key)
        if callable(fn):
            if fn.__name__ not in registry:
                raise ValueError(f"network_config_text: {key} {fn.__name__!r} is not in Brax's registry")
            factory[key] = fn.__name__
    return config_dict.ConfigDict(plain(data)).to_json_best_effort()


def save_checkpoint(folder: Path, step: int, params: Any, config: Any, record: dict | None = None) -> Path:
    """Save a checkpoint as ``folder/<step>/`` so that it appears complete or not at all: written under
    ``folder/.staging/`` (Brax's parameters and network config, and ``record``, when given, as ``record.json``),
    then renamed into place (a previous checkpoint of the same step is replaced)."""
    folder = Path(folder).resolve()
    staging = folder / STAGING
    shutil.rmtree(staging, ignore_errors=True)
    staging.mkdir(parents=True)
    written = stage_checkpoint(staging, step, params, config)
    if record is not None:
        write_json(written / RECORD, record)
    if not is_checkpoint(written):
        raise RuntimeError(f"save_checkpoint: the checkpoint written to {written} lacks {COMMIT_MARKER} or "
                           f"{NETWORK_CONFIG}")
    target = folder / f"{step:012d}"
    if target.exists():
        shutil.rmtree(target)
    replace(written, target)
    shutil.rmtree(staging, ignore_errors=True)
    return target


def checkpoint_record(path: Path) -> dict | None:
    """The ``record.json`` of the checkpoint ``path``; ``None`` for a checkpoint written without one."""
    return read_json(Path(path) / RECORD)


def committed_record(out: Path) -> dict[str, list[dict]]:
    """The rows (``curve``, ``train_curve``, ``walk_tests``) that the committed checkpoints of the run folder ``out``
    hold, in step order, each once. A checkpoint without ``record.json`` (written before records existed) keeps the
    rows of the run files up to its step."""
    found = committed_checkpoints(Path(out) / "checkpoints")
    rows: dict[str, list[dict]] = {key: [] for key in RECORD_FILES}
    covered = -1  # the rows at or below this step come from the run files
    for step, path in found:
        record = checkpoint_record(path)
        if record is None:
            covered = step
            continue
        for key in RECORD_FILES:
            rows[key].extend(record.get(key, []))
    if covered >= 0:
        for key, name in RECORD_FILES.items():
            legacy = [r for r in read_json(Path(out) / name, []) if r["step"] <= covered]
            rows[key] = legacy + [r for r in rows[key] if r["step"] > covered]
    for key in rows:  # each step once: the last committed row of a step wins
        by_step = {r["step"]: r for r in rows[key]}
        rows[key] = sorted(by_step.values(), key=lambda r: r["step"])
    return rows


def clear_partial(folder: Path) -> None:
    """Remove what a killed run left half-written in the checkpoint folder ``folder``: the staging area, step folders
    that are not complete checkpoints, and the temporary files of the run files beside it."""
    folder = Path(folder)
    for name in RUN_FILES:
        stem = Path(name).stem
        for tmp in (*folder.parent.glob(f".{name}.*.tmp"), *folder.parent.glob(f".{stem}.tmp*")):
            tmp.unlink(missing_ok=True)
    if not folder.is_dir():
        return
    shutil.rmtree(folder / STAGING, ignore_errors=True)
    for d in folder.iterdir():
        if d.name.isdigit() and d.is_dir() and not is_checkpoint(d):
            shutil.rmtree(d, ignore_errors=True)


def is_used(out: Path) -> bool:
    """Whether ``out`` already holds a run: a checkpoint folder or one of the files a run writes."""
    out = Path(out)
    return (out / "checkpoints").exists() or any((out / name).exists() for name in RUN_FILES)


def clear_run(out: Path) -> None:
    """Remove the run in ``out`` (its checkpoints and the files of :data:`RUN_FILES`); other files stay."""
    out = Path(out)
    shutil.rmtree(out / "checkpoints", ignore_errors=True)
    for name in RUN_FILES:
        (out / name).unlink(missing_ok=True)


def run_folder(path: Path) -> Path | None:
    """The run folder of ``path``: ``path`` itself, or the run that holds it when ``path`` is its ``checkpoints``
    folder or one checkpoint; ``None`` when none of these has ``env.json`` or ``run.json``."""
    path = Path(path)
    for folder in (path, path.parent, path.parent.parent):
        if (folder / "env.json").exists() or (folder / "run.json").exists():
            return folder
    return None


def run_env(path: Path, task: str) -> dict:
    """The environment keywords a run was trained with: those in the ``record.json`` of the checkpoint ``path``,
    else ``env.json`` of the run folder of ``path`` (:func:`run_folder`), else the task's config."""
    from kamino.envs.configs import task_config

    record = checkpoint_record(path) if is_checkpoint(path) else None
    if record is not None and "env" in record:
        return record["env"]
    folder = run_folder(path)
    if folder is not None and (folder / "env.json").exists():
        return json.loads((folder / "env.json").read_text())
    return task_config(task)["env"]


def run_task(path: Path) -> str | None:
    """The task a run was trained on (``run.json`` of the run folder of ``path``), ``None`` when not recorded."""
    folder = run_folder(path)
    info = read_json(folder / "run.json", {}) if folder is not None else {}
    return info.get("task")


class OptionError(ValueError):
    """A training or evaluation option that cannot work (named in the message), raised before anything runs."""


def key_values(items: list[str], flag: str) -> dict[str, Any]:
    """``KEY=VALUE`` options (``VALUE`` a Python literal; ``KEY`` a name, or a dotted one for a nested setting:
    ``warp.linear_solver='cr'``) as a dict; a malformed one raises ``ValueError`` naming ``flag``."""
    out = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep or not all(part.isidentifier() for part in key.split(".")):
            raise OptionError(f"{flag} expects KEY=VALUE, got {item!r}")
        try:
            out[key] = ast.literal_eval(value)
        except (ValueError, SyntaxError):
            raise OptionError(f"{flag} {key}: {value!r} is not a Python literal") from None
    return out


__all__ = ["COMMIT_MARKER", "NETWORK_CONFIG", "RECORD", "RECORD_FILES", "RUN_FILES", "OptionError",
           "checkpoint_record", "clear_partial", "clear_run", "committed_checkpoints", "committed_record",
           "is_checkpoint", "is_used", "key_values", "latest_checkpoint", "network_config_text", "read_json",
           "run_env", "run_folder", "run_task", "save_checkpoint", "write_checkpoint_alone", "write_json",
           "write_json_if_changed", "write_text"]
