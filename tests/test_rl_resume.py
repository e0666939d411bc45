"""``kamino train`` survives being killed: runs of ``fourbar_track`` killed with SIGKILL (inside a checkpoint write, and
at a random moment) resume every time and complete, and every checkpoint left loads for evaluation.

Each training runs in a subprocess through ``kamino.envs.train.main``. A hook in the subprocess (a wrapper around
``kamino.envs.runs.stage_checkpoint``) writes a marker file once a checkpoint has been written to the staging
area but not yet renamed into place, then sleeps: the test kills there. The run folder also gets, by hand, what a
kill in the middle of an older, non-atomic writer leaves: an empty ``checkpoints/<step>/`` with a higher step than
any real one, a step folder with only its network config, and a temporary side file.
"""

from __future__ import annotations

import json
import os
import random
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

#: the training: a checkpoint every 240 env steps, three in all; a PPO iteration collects batch_size x
#: num_minibatches x unroll_length = 80 env steps, three of them between checkpoints (no evaluation rollouts)
STEPS, EVERY = 720, 240
ARGS = ["fourbar_track", "--backend", "warp", "--steps", str(STEPS), "--num-envs", "8", "--evals", "4",
        "--set", "batch_size=8", "--set", "num_minibatches=2", "--set", "unroll_length=5",
        "--set", "num_eval_envs=4", "--set", "episode_length=20", "--set", "run_evals=False", "--env", "reset_bank=8"]

#: runs ``kamino train`` with a hook: KILL_AT=N marks (KILL_MARKER) the N-th checkpoint of the process once it is
#: written to the staging area, before its rename into place, and sleeps there until killed
HOOKED = """
import os, sys, time, pathlib
from kamino.envs import runs, train
marker = pathlib.Path(os.environ["KILL_MARKER"])
if os.environ.get("KILL_AT"):
    written, calls = runs.stage_checkpoint, []
    def stage(*args, **kwargs):
        folder = written(*args, **kwargs)
        calls.append(folder)
        if len(calls) == int(os.environ["KILL_AT"]):
            marker.write_text(str(folder))
            time.sleep(600)
        return folder
    runs.stage_checkpoint = stage
marker.with_suffix(".started").write_text("")
sys.exit(train.main(sys.argv[1:]))
"""


def _start(out: Path, marker: Path, kill_at: str) -> subprocess.Popen:
    env = {**os.environ, "KILL_MARKER": str(marker), "KILL_AT": kill_at}
    return subprocess.Popen([sys.executable, "-c", HOOKED, *ARGS, "--out", str(out)], env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)


def _kill(proc: subprocess.Popen, *, may_have_finished: bool = False) -> str:
    """SIGKILL ``proc``; with ``may_have_finished``, a run that completed between the caller's last look at it and
    the signal passes as well (the random kill of step 2 can come after a short resumed run has ended)."""
    proc.send_signal(signal.SIGKILL)
    out, _ = proc.communicate(timeout=60)
    assert proc.returncode == -signal.SIGKILL or (may_have_finished and proc.returncode == 0), out
    return out


def _wait_for(path: Path, proc: subprocess.Popen, timeout: float) -> None:
    t0 = time.monotonic()
    while not path.exists():
        if proc.poll() is not None:
            raise AssertionError(f"the run ended (status {proc.returncode}) before {path.name}:\n{proc.stdout.read()}")
        if time.monotonic() - t0 > timeout:
            _kill(proc)
            raise AssertionError(f"no {path.name} within {timeout} s")
        time.sleep(0.05)


def _plant_debris(out: Path) -> None:
    """What a kill inside a non-atomic writer leaves: an empty step folder, one with only its network config, and a
    temporary side file; none may be taken for a checkpoint or a curve."""
    ckpt = out / "checkpoints"
    (ckpt / f"{10 * STEPS:012d}").mkdir(parents=True, exist_ok=True)
    half = ckpt / f"{9 * STEPS:012d}"
    half.mkdir(exist_ok=True)
    (half / runs.NETWORK_CONFIG).write_text("{}")
    (out / ".curve.json.x.tmp").write_text('[{"step": ')


def test_training_killed_anywhere_resumes_to_completion(tmp_path):
    out, marker = tmp_path / "run", tmp_path / "marker"
    rng = random.Random(int.from_bytes(os.urandom(4), "little"))
    t0 = time.monotonic()

    # 1. killed inside the second checkpoint write: that checkpoint is staged, not committed; the first one is
    started = marker.with_suffix(".started")
    proc = _start(out, marker, "2")
    _wait_for(started, proc, timeout=300)
    t_started = time.monotonic()
    _wait_for(marker, proc, timeout=300)
    to_write = time.monotonic() - t_started  # from the run's start (imports done) to its second write
    _kill(proc)
    staged = Path(marker.read_text())
    assert staged.exists() and runs.STAGING in staged.parts and staged.name == f"{2 * EVERY:012d}"
    assert [s for s, _ in runs.committed_checkpoints(out / "checkpoints")] == [EVERY]
    _plant_debris(out)

    # 2. resumed from the first checkpoint and killed at a random moment of its training, timed from its own start
    #    (a resumed run reads its compiles from the cache: it takes less than the first run to the same point)
    marker.unlink()
    started.unlink()
    delay = rng.uniform(0.05, 1.0) * to_write
    print(f"random kill {delay:.1f} s after the resumed run's start (the first run's second write came "
          f"{to_write:.1f} s after its start)")
    proc = _start(out, marker, "")
    _wait_for(started, proc, timeout=300)
    t1 = time.monotonic()
    while time.monotonic() - t1 < delay and proc.poll() is None:
        time.sleep(0.05)
    if proc.poll() is None:
        _kill(proc, may_have_finished=True)
    for path in ("run.json", "env.json", "curve.json"):  # whatever exists is whole
        if (out / path).exists():
            json.loads((out / path).read_text())

    # 3. resumed to completion
    proc = subprocess.run([sys.executable, "-c", HOOKED, *ARGS, "--out", str(out)], capture_output=True, text=True,
                          env={**os.environ, "KILL_MARKER": str(marker), "KILL_AT": ""}, timeout=600)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert "resuming at step" in proc.stdout, proc.stdout
    print(f"three runs in {time.monotonic() - t0:.1f} s")

    found = runs.committed_checkpoints(out / "checkpoints")
    steps = [s for s, _ in found]
    assert steps[-1] >= STEPS and steps == sorted(set(steps)) and steps[0] == EVERY
    assert not (out / "checkpoints" / runs.STAGING).exists()
    curve = json.loads((out / "curve.json").read_text())
    curve_steps = [c["step"] for c in curve]
    assert curve_steps == sorted(set(curve_steps)) and curve_steps[-1] == steps[-1]
    assert json.loads((out / "run.json").read_text())["task"] == "fourbar_track"
    obs = np.linspace(-1.0, 1.0, 7, dtype=np.float32)[None]
    for step, path in found:
        policy = load_checkpoint(path)
        assert policy.task == "fourbar_track" and policy.step == step
        action = np.asarray(policy.act(obs))
        assert action.shape == (1, 1) and np.all(np.abs(action) <= 1.0)
    assert load_checkpoint(out).step == steps[-1]  # the run folder evaluates its newest checkpoint
