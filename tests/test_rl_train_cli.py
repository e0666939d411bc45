"""``kamino train``'s options (kamino.envs.train): overrides parsed as literals, bad ones refused naming them before
anything is built, ``--fresh`` refusing a used run folder, and the run folder's own records."""

import json
import os

import numpy as np
import pytest

pytest.importorskip("brax")

from kamino.envs import runs
from kamino.envs import train as rl_train
from kamino.envs.runs import OptionError


def test_solver_overrides_are_parsed_as_literals():
    args = rl_train.parse_args(["fourbar_track", "--solver", "max_iterations=100", "--solver", "tolerance=1e-3"])
    assert args.solver_overrides == {"max_iterations": 100, "tolerance": 1e-3}
    with pytest.raises(SystemExit):  # argparse's error: not KEY=VALUE
        rl_train.parse_args(["fourbar_track", "--solver", "max_iterations"])
    args = rl_train.parse_args(["fourbar_track", "--solver", "stabilisation.post_stabilisation=2"])
    assert args.solver_overrides == {"stabilisation.post_stabilisation": 2}  # a nested setting, by its path


def test_an_unknown_solver_field_raises_naming_it(tmp_path):
    with pytest.raises(TypeError, match="no_such_field"):
        rl_train.train("fourbar_track", solver={"no_such_field": 1}, out=tmp_path)
    with pytest.raises(TypeError, match=r"'baumgarte'.*stabilisation\.baumgarte"):  # the path it goes by
        rl_train.train("fourbar_track", solver={"baumgarte": 0.1}, out=tmp_path)
    with pytest.raises(SystemExit):
        rl_train.parse_args(["fourbar_track", "--solver", "no_such_field=1"])


def test_env_overrides_are_parsed_as_literals_and_reach_the_environment(tmp_path):
    args = rl_train.parse_args(["fourbar_track", "--env", "tracking_sigma=0.1"])
    assert args.env_overrides == {"tracking_sigma": 0.1}
    with pytest.raises(TypeError, match="no_such_keyword"):  # the task's constructor names what it does not take
        rl_train.train("fourbar_track", env={"no_such_keyword": 1}, out=tmp_path)


def test_the_step_count_is_positional_or_an_option():
    assert rl_train.parse_args(["fourbar_track", "2000"]).steps == 2000
    assert rl_train.parse_args(["fourbar_track", "--steps", "2000"]).steps == 2000
    for bad in (["fourbar_track", "0"], ["fourbar_track", "100", "--steps", "200"], ["nosuch_task"]):
        with pytest.raises(SystemExit):
            rl_train.parse_args(bad)


def test_the_walking_test_needs_a_task_with_a_test(tmp_path):
    """``--walk-test`` runs the task's walking or show test (tests/test_rl_eval.py, tests/test_olaf_show.py) on every
    checkpoint; a task with neither refuses it before training starts."""
    with pytest.raises(rl_train.OptionError, match="needs a task with a walking or show test"):
        rl_train.train("fourbar_track", walk_test=4, out=tmp_path)
    assert rl_train.main(["fourbar_track", "--walk-test", "4", "--out", str(tmp_path)]) == 2
    with pytest.raises(SystemExit):
        rl_train.parse_args(["fourbar_track", "--walk-test", "-1"])
    with pytest.raises(SystemExit):
        rl_train.parse_args(["fourbar_track", "--walk-test-from", "-1"])
    with pytest.raises(SystemExit):
        rl_train.parse_args(["dr_legs_joystick", "--walk-test-every", "-1"])


def test_fresh_refuses_a_used_folder_unless_told_to_overwrite(tmp_path):
    """A folder that holds a run (a curve, a checkpoint folder) is not started over silently: ``--fresh`` alone is
    an error naming ``--overwrite``, and another task's run is refused; ``--overwrite`` deletes the run's files and
    nothing else."""
    (tmp_path / "curve.json").write_text("[]")
    (tmp_path / "checkpoints").mkdir()
    (tmp_path / "notes.txt").write_text("mine")
    with pytest.raises(rl_train.OptionError, match="--overwrite"):
        rl_train._prepare_folder(tmp_path, "fourbar_track", fresh=True, overwrite=False)
    assert (tmp_path / "curve.json").exists()
    runs.write_json(tmp_path / "run.json", {"task": "dr_legs_joystick"})
    with pytest.raises(rl_train.OptionError, match="dr_legs_joystick"):
        rl_train._prepare_folder(tmp_path, "fourbar_track", fresh=False, overwrite=False)
    rl_train._prepare_folder(tmp_path, "fourbar_track", fresh=True, overwrite=True)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["notes.txt"]
    with pytest.raises(SystemExit):
        rl_train.parse_args(["fourbar_track", "--overwrite"])  # only with --fresh


def test_side_files_are_replaced_whole(tmp_path, monkeypatch):
    """``write_json`` goes through a temporary file and one rename: a writer killed before the rename leaves the old
    file intact (simulated by a rename that fails), and no temporary file stays behind."""
    path = tmp_path / "curve.json"
    runs.write_json(path, [{"step": 1}])

    def killed(src, dst):
        raise KeyboardInterrupt

    monkeypatch.setattr(runs, "replace", killed)
    with pytest.raises(KeyboardInterrupt):
        runs.write_json(path, [{"step": 1}, {"step": 2}])
    assert json.loads(path.read_text()) == [{"step": 1}]
    assert [p.name for p in tmp_path.iterdir()] == ["curve.json"]


def test_only_complete_checkpoints_count(tmp_path):
    """A step folder counts only with orbax's commit marker and the network config; the staging area and stray
    files never do, and ``clear_partial`` removes what a killed writer left."""
    ckpt = tmp_path / "checkpoints"
    for step, files in ((100, (runs.COMMIT_MARKER, runs.NETWORK_CONFIG)), (200, (runs.NETWORK_CONFIG,)),
                        (300, ())):
        (ckpt / f"{step:012d}").mkdir(parents=True)
        for name in files:
            (ckpt / f"{step:012d}" / name).write_text("{}")
    (ckpt / runs.STAGING / f"{400:012d}").mkdir(parents=True)
    assert runs.latest_checkpoint(ckpt) == (100, ckpt / f"{100:012d}")
    assert runs.latest_checkpoint(tmp_path / "none") == (0, None)
    runs.clear_partial(ckpt)
    assert sorted(p.name for p in ckpt.iterdir()) == [f"{100:012d}"]


def test_the_walking_test_skips_checkpoints_closer_than_every():
    """Checkpoints every 4 M steps, tests from 36 M, every 8 M: 36, 44, 52 M tested, 40 and 48 M skipped; a resumed
    run counts from its saved list's last test."""
    tested: list[int] = []
    for step in range(4, 56, 4):
        if rl_train.walk_test_due(step, tested, start=36, every=8):
            tested.append(step)
    assert tested == [36, 44, 52]
    assert not rl_train.walk_test_due(56, [36, 44, 52], start=36, every=8)
    assert rl_train.walk_test_due(56, [36, 44, 52], start=36, every=0)  # the default: every checkpoint


def test_a_run_keeps_its_environment(tmp_path):
    """``env.json`` of a run folder is the environment ``kamino eval`` builds for its checkpoints (a gait clock adds
    observations, so another config would not fit the policy), found from the run, its ``checkpoints`` folder or one
    checkpoint; a run without it reads the task's config."""
    from kamino.envs.configs import task_config

    run = tmp_path / "run"
    step = run / "checkpoints" / "000000131072"
    step.mkdir(parents=True)
    assert runs.run_env(step, "dr_legs_joystick") == task_config("dr_legs_joystick")["env"]
    (run / "env.json").write_text('{"gait_frequency": null, "command_lin_x": 0.4}')
    for path in (run, run / "checkpoints", step):
        assert runs.run_env(path, "dr_legs_joystick") == {"gait_frequency": None, "command_lin_x": 0.4}
    assert runs.run_task(step) is None
    runs.write_json(run / "run.json", {"task": "dr_legs_joystick", "backend": "warp"})
    assert runs.run_task(step) == "dr_legs_joystick"


@pytest.mark.parametrize("command", ["train", "eval"])
def test_the_kamino_command_reaches_the_library(command, capsys):
    """``kamino train`` and ``kamino eval`` are the library modules' own command lines: their help names them, and
    ``kamino eval`` of a name that is neither a shipped policy nor a path is an error naming the shipped ones."""
    from kamino import cli

    with pytest.raises(SystemExit) as exit_:
        cli.main([command, "--help"])
    assert exit_.value.code == 0
    assert f"usage: kamino {command}" in capsys.readouterr().out
    if command == "eval":
        with pytest.raises(SystemExit) as exit_:
            cli.main(["eval", "no_such_policy"])
        assert exit_.value.code == 2
        assert "dr_legs_walk" in capsys.readouterr().err


@pytest.mark.parametrize("total, num_evals, unit", [(720, 4, 80), (1000, 5, 96), (100, 5, 40), (300, 1, 64)])
def test_the_evaluation_steps_stay_fixed_when_a_run_resumes(total, num_evals, unit):
    """The evaluations of a run come every Brax epoch of its first settings. A run resumed at any evaluation step
    asks Brax for the evaluations left and their steps, and Brax's epoch for those (``ceil(steps / ((evals - 1)
    unit)) unit``) is the same spacing: the resumed run evaluates at the uninterrupted run's steps, not at steps
    recomputed from what remains."""
    every = rl_train.eval_spacing(total, num_evals, unit)
    schedule = rl_train.eval_steps(total, num_evals, every)
    assert every % unit == 0 and schedule[-1] >= total and len(schedule) == max(num_evals - 1, 1)
    assert schedule == [every * k for k in range(1, len(schedule) + 1)]
    for done in (0, *schedule[:-1]):
        left = sum(step > done for step in schedule)
        assert rl_train.eval_spacing(left * every, left + 1, unit) == every
    assert rl_train.eval_steps(3 * schedule[-1], num_evals, every)[-1] >= 3 * schedule[-1]  # --steps raised later


def test_a_resume_off_the_evaluation_schedule_is_refused(tmp_path):
    """A resumed run keeps the spacing ``run.json`` records; a checkpoint off it, or PPO settings whose epoch does not
    divide it, is an error naming the step and the way out."""
    ckpt = tmp_path / "checkpoints" / f"{480:012d}"
    runs.write_json(tmp_path / "run.json", {"task": "fourbar_track", "backend": "warp", "eval_every": 240})
    assert rl_train._schedule(tmp_path, ckpt, 480, total=10_000, num_evals=3, unit=80) == 240
    assert rl_train._schedule(tmp_path, None, 0, total=720, num_evals=4, unit=80) == 240  # a new run: Brax's epoch
    with pytest.raises(rl_train.OptionError, match=r"step 400.*--fresh"):
        rl_train._schedule(tmp_path, ckpt, 400, total=720, num_evals=4, unit=80)
    with pytest.raises(rl_train.OptionError, match="epochs of 96 steps"):
        rl_train._schedule(tmp_path, ckpt, 480, total=720, num_evals=4, unit=96)


def _fake_checkpoint(folder, step: int, record: dict | None = None) -> None:
    path = folder / "checkpoints" / f"{step:012d}"
    path.mkdir(parents=True)
    for name in (runs.COMMIT_MARKER, runs.NETWORK_CONFIG):
        (path / name).write_text("{}")
    if record is not None:
        runs.write_json(path / runs.RECORD, record)


def test_a_resumed_run_takes_its_rows_from_the_committed_checkpoints(tmp_path):
    """Each checkpoint holds the rows since the one before (row 0 goes with the first); the rows a killed run wrote
    after its last checkpoint, or twice, are not in the record. A checkpoint without ``record.json`` (an older run)
    keeps the run files' rows up to its step."""
    rows = lambda *steps: [{"step": s, "reward": float(s)} for s in steps]  # noqa: E731
    _fake_checkpoint(tmp_path, 100, {"step": 100, "env": {"a": 1}, "curve": rows(0, 100), "train_curve": rows(50),
                                     "walk_tests": []})
    _fake_checkpoint(tmp_path, 200, {"step": 200, "env": {"a": 1}, "curve": rows(200), "train_curve": rows(150),
                                     "walk_tests": rows(200)})
    runs.write_json(tmp_path / "curve.json", rows(0, 0, 100, 200, 300))
    record = runs.committed_record(tmp_path)
    assert [r["step"] for r in record["curve"]] == [0, 100, 200]
    assert [r["step"] for r in record["train_curve"]] == [50, 150]
    assert [r["step"] for r in record["walk_tests"]] == [200]
    assert runs.run_env(tmp_path / "checkpoints" / f"{200:012d}", "fourbar_track") == {"a": 1}  # the checkpoint's own

    legacy = tmp_path / "legacy"
    _fake_checkpoint(legacy, 100)
    _fake_checkpoint(legacy, 200, {"step": 200, "curve": rows(200)})
    runs.write_json(legacy / "curve.json", rows(0, 100, 200, 300))
    assert [r["step"] for r in runs.committed_record(legacy)["curve"]] == [0, 100, 200]


def test_a_run_file_that_holds_its_rows_already_is_not_rewritten(tmp_path, monkeypatch):
    """A resumed run rewrites ``curve.json`` only when it differs from what the committed checkpoints hold (rows
    with a NaN return compare equal by their text)."""
    path = tmp_path / "curve.json"
    rows = [{"step": 240, "reward": float("nan")}]
    assert runs.write_json_if_changed(path, rows)
    renamed = []
    monkeypatch.setattr(runs, "replace", lambda src, dst: renamed.append(dst) or os.replace(src, dst))
    assert not runs.write_json_if_changed(path, [{"step": 240, "reward": float("nan")}]) and renamed == []
    assert runs.write_json_if_changed(path, [*rows, {"step": 480, "reward": 1.0}]) and renamed == [path]


def test_the_distributed_options_go_together():
    """``--coordinator``, ``--num-processes`` and ``--process-id`` need ``--distributed``, the last two go together,
    and the index lies in [0, N)."""
    ok = rl_train.parse_args(["fourbar_track", "--distributed", "--coordinator", "127.0.0.1:1234",
                              "--num-processes", "2", "--process-id", "1"])
    assert (ok.distributed, ok.coordinator, ok.num_processes, ok.process_id) == (True, "127.0.0.1:1234", 2, 1)
    assert rl_train.parse_args(["fourbar_track", "--distributed"]).num_processes is None  # the cluster's settings
    for bad in (["--num-processes", "2", "--process-id", "0"], ["--distributed", "--num-processes", "2"],
                ["--distributed", "--num-processes", "2", "--process-id", "2"]):
        with pytest.raises(SystemExit):
            rl_train.parse_args(["fourbar_track", *bad])


def test_init_from_takes_a_policy_whose_network_fits_the_task():
    """``--init-from``: the shipped dr_legs policy (50 observations, hidden layers 128 x 3, 12 actions) fits
    dr_legs_joystick's network; one observation more, other hidden layers, or an unknown policy raise naming the
    option (Brax would otherwise fail inside its jitted update with a shape error)."""
    from brax.training.agents.ppo import checkpoint as ppo_checkpoint

    from kamino.envs.configs import ppo_kwargs

    def config(hidden):
        factory = ppo_kwargs("dr_legs_joystick")["network_factory"]
        factory.keywords["policy_hidden_layer_sizes"] = hidden
        return ppo_checkpoint.network_config(50, 12, True, factory)

    params = rl_train.initial_params("dr_legs_walk", "dr_legs_joystick")
    rl_train.check_initial_params(params, 50, 12, config((128, 128, 128)), "dr_legs_walk")
    for obs, act, hidden in ((51, 12, (128, 128, 128)), (50, 12, (64, 64)), (50, 14, (128, 128, 128))):
        with pytest.raises(OptionError, match="--init-from"):
            rl_train.check_initial_params(params, obs, act, config(hidden), "dr_legs_walk")
    with pytest.raises(OptionError, match="--init-from"):
        rl_train.initial_params("no_such_policy", "dr_legs_joystick")


def test_init_from_reaches_brax_as_restored_policy_and_normaliser(tmp_path, monkeypatch):
    """A new run with ``init_from`` hands Brax the policy's normaliser and network (``restore_params``) with a fresh
    value network, and records the source in run.json."""
    import functools

    import brax.training.agents.ppo.train as ppo_train

    seen = {}

    @functools.wraps(ppo_train.train)
    def capture(**kwargs):
        seen.update(kwargs)

    monkeypatch.setattr(ppo_train, "train", capture)
    source = rl_train.initial_params("dr_legs_walk", "dr_legs_joystick")
    rl_train.train("dr_legs_joystick", backend="jax", init_from="dr_legs_walk", out=tmp_path / "b", steps=1000,
                   evals=1, env={"reset_bank": 2}, progress=False)
    normalizer, policy, value = seen["restore_params"]
    assert seen["restore_value_fn"] is False and value is None
    np.testing.assert_array_equal(normalizer.mean, source[0].mean)
    np.testing.assert_array_equal(policy["params"]["hidden_0"]["kernel"], source[1]["params"]["hidden_0"]["kernel"])
    assert runs.read_json(tmp_path / "b" / "run.json", {})["init_from"] == "dr_legs_walk"
