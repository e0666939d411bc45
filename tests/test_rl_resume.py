"""A training run killed at any moment and resumed ends with the record of a run never interrupted.

``kamino train fourbar_track`` (Warp backend, the faster of the two on the CPU; a tiny PPO config: three
evaluations, each with its checkpoint, 240 environment steps apart) runs once without interruption, the reference.
Five more runs are killed with SIGKILL, each in a subprocess that kills itself at a chosen point:

- inside the second checkpoint write (the checkpoint staged whole, before its rename into place);
- inside the second ``curve.json`` write (the temporary file whole, before its rename);
- inside the ``env.json`` write of a run resuming the first killed one;
- at two random moments: of a fresh run, and of a run resuming the second killed one.

Every killed run is then resumed to its end, and its record compared with the reference's: the same evaluation
steps in ``curve.json``, none missing or doubled, the same checkpoints, each committed with its row and loadable by
the function behind ``kamino eval``, and no temporary file left. The kills inside a write are deterministic: a wrapper
around ``kamino.envs.runs.replace`` (the one rename that commits a checkpoint or a run file) sends SIGKILL at the
N-th rename of the chosen kind. The reference run and the five resumed runs share one process and its compiled
programs.
"""

from __future__ import annotations

import os
import random
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("brax")

from kamino.envs import runs
from kamino.envs.policy import load_checkpoint

#: three evaluations (``--evals 4``: brax's first one at step 0 is off with ``run_evals=False``), 240 env steps
#: apart: a PPO iteration collects batch_size x num_minibatches x unroll_length = 80 env steps, three per evaluation
STEPS, EVERY = 720, 240
ARGS = ["fourbar_track", "--backend", "warp", "--steps", str(STEPS), "--num-envs", "8", "--evals", "4",
        "--set", "batch_size=8", "--set", "num_minibatches=2", "--set", "unroll_length=5",
        "--set", "num_eval_envs=4", "--set", "episode_length=20", "--set", "run_evals=False", "--env", "reset_bank=8"]

#: ``kamino train`` that kills itself: KILL_AT=KIND:N at the N-th commit of a checkpoint, curve.json or env.json
#: (KIND checkpoint, curve or env), before its rename; KILL_AFTER=SECONDS that long after its imports. It writes
#: STARTED_MARKER once its imports are done.
KILLED = """
import os, signal, sys, threading, pathlib
from kamino.envs import runs, train
kind, _, nth = os.environ.get("KILL_AT", "").partition(":")
renames = {"checkpoint": 0, "curve": 0, "env": 0}
rename = runs.replace
def kind_of(dst):
    dst = pathlib.Path(dst)
    if dst.parent.name == "checkpoints":
        return "checkpoint"
    return {"curve.json": "curve", "env.json": "env"}.get(dst.name)
def replace(src, dst):
    k = kind_of(dst)
    if k is not None:
        renames[k] += 1
        if k == kind and renames[k] == int(nth):
            os.kill(os.getpid(), signal.SIGKILL)
    rename(src, dst)
runs.replace = replace
if os.environ.get("KILL_AFTER"):
    threading.Timer(float(os.environ["KILL_AFTER"]), os.kill, (os.getpid(), signal.SIGKILL)).start()
pathlib.Path(os.environ["STARTED_MARKER"]).write_text("")
sys.exit(train.main(sys.argv[1:]))
"""

#: the reference run into its folder, then every killed run resumed to its end, in one process
RESUMED = """
import sys
from kamino.envs import train
args, folders = sys.argv[1:sys.argv.index("--")], sys.argv[sys.argv.index("--") + 1:]
for out in folders:
    print("== run", out, flush=True)
    status = train.main([*args, "--out", out])
    if status:
        sys.exit(status)
"""


def _killed(out: Path, tmp: Path, **env: str) -> tuple[int, float]:
    """Run ``KILLED`` into ``out`` with the kill settings ``env``: its exit status and its seconds from the end of
    its imports to its end."""
    started = tmp / f"{out.name}.started"
    proc = subprocess.Popen([sys.executable, "-c", KILLED, *ARGS, "--out", str(out)],
                            env={**os.environ, "STARTED_MARKER": str(started), **env},
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    t0 = None
    while proc.poll() is None:
        if t0 is None and started.exists():
            t0 = time.monotonic()
        time.sleep(0.02)
    output = proc.stdout.read()
    assert proc.returncode in (0, -signal.SIGKILL), output
    return proc.returncode, time.monotonic() - (t0 or time.monotonic())


def _plant_debris(out: Path) -> None:
    """What a kill inside a writer without staging would leave: an empty step folder, one with only its network
    config, and a temporary side file; none may be taken for a checkpoint or a row."""
    ckpt = out / "checkpoints"
    (ckpt / f"{10 * STEPS:012d}").mkdir(parents=True, exist_ok=True)
    half = ckpt / f"{9 * STEPS:012d}"
    half.mkdir(exist_ok=True)
    (half / runs.NETWORK_CONFIG).write_text("{}")
    (out / ".curve.json.x.tmp").write_text('[{"step": ')


def _record(out: Path) -> dict:
    """What a run folder's record is compared on."""
    found = runs.committed_checkpoints(out / "checkpoints")
    return {"curve": [row["step"] for row in runs.read_json(out / "curve.json", [])],
            "checkpoints": [step for step, _ in found],
            "rows": [[row["step"] for row in runs.checkpoint_record(path)["curve"]] for _, path in found],
            "run": runs.read_json(out / "run.json"), "env": runs.read_json(out / "env.json"),
            "leftovers": sorted(p.name for p in (*out.iterdir(), *(out / "checkpoints").iterdir())
                                if p.name.startswith("."))}


def test_a_run_killed_anywhere_resumes_to_the_record_of_an_uninterrupted_run(tmp_path):
    rng = random.Random(int.from_bytes(os.urandom(4), "little"))
    t0 = time.monotonic()
    case = {name: tmp_path / name for name in ("checkpoint", "curve", "env", "random", "random_resumed")}

    status, to_second_write = _killed(case["checkpoint"], tmp_path, KILL_AT="checkpoint:2")
    assert status == -signal.SIGKILL
    assert [s for s, _ in runs.committed_checkpoints(case["checkpoint"] / "checkpoints")] == [EVERY]
    assert (case["checkpoint"] / "checkpoints" / runs.STAGING / f"{2 * EVERY:012d}").is_dir()  # staged, not renamed
    _plant_debris(case["checkpoint"])
    shutil.copytree(case["checkpoint"], case["env"])
    status, _ = _killed(case["env"], tmp_path, KILL_AT="env:1")  # the resumed run, at its env.json
    assert status == -signal.SIGKILL
    assert runs.read_json(case["env"] / "env.json") == {"reset_bank": 8}  # the old file, whole
    assert list(case["env"].glob(".env.json.*.tmp"))  # the new one, whole and not renamed

    status, _ = _killed(case["curve"], tmp_path, KILL_AT="curve:2")
    assert status == -signal.SIGKILL
    assert [s for s, _ in runs.committed_checkpoints(case["curve"] / "checkpoints")] == [EVERY, 2 * EVERY]
    assert [row["step"] for row in runs.read_json(case["curve"] / "curve.json")] == [EVERY]  # row 480 not yet in
    shutil.copytree(case["curve"], case["random_resumed"])

    delays = [rng.uniform(0.0, 1.2) * to_second_write for _ in range(2)]
    print(f"random kills {delays[0]:.1f} s and {delays[1]:.1f} s after the imports (the second checkpoint write came "
          f"{to_second_write:.1f} s after them)")
    _killed(case["random"], tmp_path, KILL_AFTER=f"{delays[0]:.3f}")
    _killed(case["random_resumed"], tmp_path, KILL_AFTER=f"{delays[1]:.3f}")
    t_kills = time.monotonic() - t0

    reference = tmp_path / "reference"
    folders = [reference, *case.values()]
    proc = subprocess.run([sys.executable, "-c", RESUMED, *ARGS, "--", *map(str, folders)], capture_output=True,
                          text=True, timeout=600)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    print(f"five killed runs in {t_kills:.1f} s, the reference and five resumed runs in "
          f"{time.monotonic() - t0 - t_kills:.1f} s")

    expected = _record(reference)
    assert expected["curve"] == expected["checkpoints"] == [EVERY, 2 * EVERY, 3 * EVERY]
    assert expected["rows"] == [[EVERY], [2 * EVERY], [3 * EVERY]]
    assert expected["run"]["eval_every"] == EVERY and expected["leftovers"] == []
    obs = np.linspace(-1.0, 1.0, 7, dtype=np.float32)[None]
    for name, out in case.items():
        assert _record(out) == expected, name
        for step, path in runs.committed_checkpoints(out / "checkpoints"):
            policy = load_checkpoint(path)
            assert policy.task == "fourbar_track" and policy.step == step and policy.env == {"reset_bank": 8}, name
            action = np.asarray(policy.act(obs))
            assert action.shape == (1, 1) and np.all(np.abs(action) <= 1.0), name
        assert load_checkpoint(out).step == 3 * EVERY  # the run folder evaluates its newest checkpoint
