"""A training run killed inside its writes and resumed ends with the record of a run never interrupted.

``kamino train fourbar_track`` (Warp backend, the faster of the two on the CPU for a first training in a process; a
tiny PPO config: three evaluations, each with its checkpoint, 240 environment steps apart) runs once without
interruption, the reference. Another run of the same command is killed with SIGKILL twice, each time in a
subprocess that resumes the run folder the kill before left and kills itself at a chosen point:

1. inside its first checkpoint write (the checkpoint staged whole, before its rename into place);
2. inside the ``curve.json`` write that follows its first checkpoint commit (the temporary file whole, before its
   rename);

and is then resumed to its end. (A kill at a random moment would cost a third process, about 15 s of CI; it lands
before the first checkpoint commit five times in six, where the first kill already leaves the folder.) After each
kill, what the run folder holds is a prefix of the reference's record: committed checkpoints at evaluation steps,
each with its own row, and whole run files. At the end the record equals
the reference's: the same evaluation steps in ``curve.json``, none missing or doubled, the same checkpoints, each
committed with its row and loadable by the function behind ``kamino eval``, and no temporary file left. The kills
are deterministic: a wrapper around ``kamino.envs.runs.replace`` (the one rename that commits a
checkpoint or a run file) sends SIGKILL at the N-th rename of the chosen kind. The reference and the final resumed
run share one process, and every process reads its compiled programs from the persistent cache.
"""

from __future__ import annotations

import os
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

#: ``kamino train`` that kills itself: KILL_AT=KIND:N at the N-th commit of a checkpoint, env.json or curve.json
#: (KIND checkpoint, env or curve; curve.json writes counted from the process's first checkpoint commit on), before
#: its rename
KILLED = """
import os, signal, sys, pathlib
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
    if k is not None and (k != "curve" or renames["checkpoint"]):
        renames[k] += 1
        if k == kind and renames[k] == int(nth):
            os.kill(os.getpid(), signal.SIGKILL)
    rename(src, dst)
runs.replace = replace
sys.exit(train.main(sys.argv[1:]))
"""

#: the reference run, then the killed run resumed to its end, in one process (the reward plot, drawn after
#: training, is left out: it is not part of the record and its first drawing costs seconds)
RESUMED = """
import sys
from kamino.envs import train
train.plot_curve = lambda *args, **kwargs: None
args, folders = sys.argv[1:sys.argv.index("--")], sys.argv[sys.argv.index("--") + 1:]
for out in folders:
    status = train.main([*args, "--out", out])
    if status:
        sys.exit(status)
"""


def _killed(out: Path, tmp: Path, kill_at: str) -> int:
    """Run ``KILLED`` into ``out``, killed at ``kill_at`` (``KIND:N``): its exit status."""
    log = tmp / "killed.log"
    with log.open("w") as sink:
        try:
            proc = subprocess.run([sys.executable, "-c", KILLED, *ARGS, "--out", str(out)],
                                  env={**os.environ, "KILL_AT": kill_at}, stdout=sink, stderr=subprocess.STDOUT,
                                  timeout=300, check=False)
        except subprocess.TimeoutExpired:
            raise AssertionError(f"the run into {out} took over 300 s:\n{log.read_text()}") from None
    assert proc.returncode in (0, -signal.SIGKILL), log.read_text()
    return proc.returncode


def _plant_debris(out: Path) -> None:
    """What a kill inside a writer without staging would leave: an empty step folder, one with only its network
    config, and a temporary side file; none may be taken for a checkpoint or a row."""
    ckpt = out / "checkpoints"
    (ckpt / f"{10 * STEPS:012d}").mkdir(parents=True, exist_ok=True)
    half = ckpt / f"{9 * STEPS:012d}"
    half.mkdir(exist_ok=True)
    (half / runs.NETWORK_CONFIG).write_text("{}")
    (out / ".curve.json.x.tmp").write_text('[{"step": ')


def _committed(out: Path) -> list[int]:
    """The steps of the committed checkpoints of ``out``, after checking that each is an evaluation step of the
    reference's schedule and holds its own row, and that the run files are whole and hold no other rows."""
    found = runs.committed_checkpoints(out / "checkpoints")
    steps = [step for step, _ in found]
    assert steps == SCHEDULE[:len(steps)], steps
    for step, path in found:
        record = runs.checkpoint_record(path)
        assert [row["step"] for row in record["curve"]] == [step] and record["env"] == {"reset_bank": 8}
    curve = [row["step"] for row in runs.read_json(out / "curve.json", [])]  # parses: whole
    assert curve == SCHEDULE[:len(curve)] and len(curve) >= len(steps) - 1, (curve, steps)
    for name in ("run.json", "env.json"):
        runs.read_json(out / name)
    return steps


def _record(out: Path) -> dict:
    """What a run folder's record is compared on."""
    found = runs.committed_checkpoints(out / "checkpoints")
    return {"curve": [row["step"] for row in runs.read_json(out / "curve.json", [])],
            "checkpoints": [step for step, _ in found],
            "rows": [[row["step"] for row in runs.checkpoint_record(path)["curve"]] for _, path in found],
            "run": runs.read_json(out / "run.json"), "env": runs.read_json(out / "env.json"),
            "leftovers": sorted(p.name for p in (*out.iterdir(), *(out / "checkpoints").iterdir())
                                if p.name.startswith("."))}


#: the evaluation (and checkpoint) steps of the uninterrupted run
SCHEDULE = [EVERY, 2 * EVERY, 3 * EVERY]


def test_a_run_killed_twice_resumes_to_the_record_of_an_uninterrupted_run(tmp_path):
    out = tmp_path / "run"
    t0 = time.monotonic()

    assert _killed(out, tmp_path, "checkpoint:1") == -signal.SIGKILL and _committed(out) == []
    assert (out / "checkpoints" / runs.STAGING / f"{EVERY:012d}").is_dir()  # staged whole, not renamed
    _plant_debris(out)

    # the resumed run starts over (nothing was committed), commits its first checkpoint, then dies at its row
    assert _killed(out, tmp_path, "curve:1") == -signal.SIGKILL
    assert list(out.glob(".curve.json.*.tmp"))  # the new file whole, not renamed
    assert _committed(out) == SCHEDULE[:1]
    t_kills = time.monotonic() - t0

    reference = tmp_path / "reference"
    proc = subprocess.run([sys.executable, "-c", RESUMED, *ARGS, "--", str(reference), str(out)], capture_output=True,
                          text=True, timeout=600)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    print(f"two killed runs in {t_kills:.1f} s, the reference and the resumed run in "
          f"{time.monotonic() - t0 - t_kills:.1f} s")

    expected = _record(reference)
    assert expected["curve"] == expected["checkpoints"] == SCHEDULE
    assert expected["rows"] == [[step] for step in SCHEDULE]
    assert expected["run"]["eval_every"] == EVERY and expected["leftovers"] == []
    assert _record(out) == expected
    obs = np.linspace(-1.0, 1.0, 7, dtype=np.float32)[None]
    for step, path in runs.committed_checkpoints(out / "checkpoints"):
        policy = load_checkpoint(path)
        assert policy.task == "fourbar_track" and policy.step == step and policy.env == {"reset_bank": 8}
        action = np.asarray(policy.act(obs))
        assert action.shape == (1, 1) and np.all(np.abs(action) <= 1.0)
    assert load_checkpoint(out).step == SCHEDULE[-1]  # the run folder evaluates its newest checkpoint
