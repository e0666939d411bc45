"""benchmarks/rl_train.py's command line: ``--solver`` overrides reach the task's SolverConfig, bad ones raise."""

import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))

import rl_train


def test_solver_overrides_are_parsed_as_literals():
    args = rl_train.parse_args(["fourbar_track", "--solver", "max_iterations=100", "--solver", "tolerance=1e-3"])
    assert args.solver_overrides == {"max_iterations": 100, "tolerance": 1e-3}
    with pytest.raises(SystemExit):  # argparse's error: not KEY=VALUE
        rl_train.parse_args(["fourbar_track", "--solver", "max_iterations"])


def test_an_unknown_solver_field_raises_naming_it(tmp_path):
    with pytest.raises(TypeError, match="no_such_field"):
        rl_train.main(["fourbar_track", "--solver", "no_such_field=1", "--out", str(tmp_path)])


def test_env_overrides_are_parsed_as_literals_and_reach_the_environment(tmp_path):
    args = rl_train.parse_args(["fourbar_track", "--env", "tracking_sigma=0.1"])
    assert args.env_overrides == {"tracking_sigma": 0.1}
    with pytest.raises(TypeError, match="no_such_keyword"):  # the task's constructor names what it does not take
        rl_train.main(["fourbar_track", "--env", "no_such_keyword=1", "--out", str(tmp_path)])


def test_the_walking_test_needs_a_joystick_task(tmp_path):
    """``--walk-test`` runs rl_eval's walking test on every checkpoint; a task without a velocity command refuses it
    before training starts (the test itself: tests/test_rl_eval.py)."""
    with pytest.raises(SystemExit, match="needs a joystick task"):
        rl_train.main(["fourbar_track", "--walk-test", "4", "--out", str(tmp_path)])
    with pytest.raises(SystemExit):
        rl_train.parse_args(["fourbar_track", "--walk-test", "-1"])
    with pytest.raises(SystemExit):
        rl_train.parse_args(["fourbar_track", "--walk-test-from", "-1"])
    with pytest.raises(SystemExit):
        rl_train.parse_args(["dr_legs_joystick", "--walk-test-every", "-1"])


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
    """``env.json`` of a run folder is the environment ``rl_eval.py`` and ``rl_velocity_trace.py`` build for its
    checkpoints (a gait clock adds observations, so the config of another day would not fit the policy), found from
    the run, its ``checkpoints`` folder or one checkpoint; a run without it reads the task's config."""
    from kamino.envs.configs import task_config

    run = tmp_path / "run"
    step = run / "checkpoints" / "000000131072"
    step.mkdir(parents=True)
    assert rl_train.run_env(step, "dr_legs_joystick") == task_config("dr_legs_joystick")["env"]
    (run / "env.json").write_text('{"gait_frequency": null, "command_lin_x": 0.4}')
    for path in (run, run / "checkpoints", step):
        assert rl_train.run_env(path, "dr_legs_joystick") == {"gait_frequency": None, "command_lin_x": 0.4}
