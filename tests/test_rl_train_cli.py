"""``kamino train``'s options (kamino.envs.train): overrides parsed as literals, bad ones refused naming them before
anything is built, ``--fresh`` refusing a used run folder, and the run folder's own records."""

import json

import pytest

pytest.importorskip("brax")

from kamino.envs import runs
from kamino.envs import train as rl_train


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


def test_the_walking_test_needs_a_joystick_task(tmp_path):
    """``--walk-test`` runs the walking test (tests/test_rl_eval.py) on every checkpoint; a task without a velocity
    command refuses it before training starts."""
    with pytest.raises(rl_train.OptionError, match="needs a joystick task"):
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
