"""Progress bars: ``--no-progress`` in both benchmark modules' parsers (nothing is run), and the Warp
backend's host-side rollout, silent below ``PROGRESS_MIN_STEPS`` steps and with a tqdm bar on stderr above."""

import importlib
import json

import numpy as np
import pytest

import kamino


def _script(name: str):
    """The benchmark module ``kamino.bench.NAME``."""
    return importlib.import_module(f"kamino.bench.{name}")


@pytest.mark.parametrize("name", ["throughput", "convergence"])
def test_benchmarks_accept_no_progress(name, capsys):
    module = _script(name)
    assert module._parser().parse_args(["--no-progress"]).no_progress is True
    assert module._parser().parse_args([]).no_progress is False
    with pytest.raises(SystemExit) as done:
        module.main(["--help"])
    assert done.value.code == 0
    assert "--no-progress" in capsys.readouterr().out


@pytest.mark.parametrize("disable", [True, False])
def test_benchmark_bar_follows_no_progress(disable, capsys):
    """``throughput.progress`` (both modules' bars) draws on stderr unless ``--no-progress``; stdout stays clean."""
    module = _script("throughput")
    args = module._parser().parse_args(["--no-progress"] if disable else [])
    for _ in module.progress(range(3), args=args, desc="bench-bar"):
        pass
    out, err = capsys.readouterr()
    assert out == ""
    assert ("bench-bar" in err) is not disable


def test_warp_rollout_bar_only_for_long_rollouts(capsys, monkeypatch):
    pytest.importorskip("warp")
    from kamino.warp_backend import backend as wb

    model = kamino.models.fourbar()
    state = kamino.init_state(model, np.float32)
    cfg = kamino.SolverConfig(dt=1 / 240)
    short = kamino.rollout(model, state, num_steps=5, config=cfg, backend="warp")
    assert short.body_q.shape[0] == 5
    assert "kamino rollout" not in capsys.readouterr().err  # a short rollout prints no bar
    # the same 5 steps with the threshold lowered: the bar shows, on stderr only, and the trajectory is unchanged
    monkeypatch.setattr(wb, "PROGRESS_MIN_STEPS", 5)
    long = kamino.rollout(model, state, num_steps=5, config=cfg, backend="warp")
    out, err = capsys.readouterr()
    assert "kamino rollout (warp)" in err and "kamino rollout" not in out
    np.testing.assert_array_equal(np.asarray(long.body_q), np.asarray(short.body_q))


def test_convergence_bars_on_stderr_only(capsys):
    """A tiny ``kamino bench convergence`` run on Warp's CPU device: the bars go to stderr (none with
    ``--no-progress``); stdout holds the JSON record lines alone either way."""
    pytest.importorskip("warp")
    module = _script("convergence")
    argv = ["--scenes", "fourbar", "--worlds", "2", "--steps", "10", "--no-sweep", "--device", "cpu"]
    for flag in ([], ["--no-progress"]):
        assert module.main(argv + flag) == 0
        out, err = capsys.readouterr()
        (line,) = out.splitlines()
        assert json.loads(line)["scene"] == "fourbar" and json.loads(line)["steps"] == 10
        assert ("fourbar tol" in err) is not bool(flag)


def test_the_training_bar_keeps_the_last_return_when_an_evaluation_brings_none(capsys):
    # under run_evals=False Brax's evaluations carry no return: the bar keeps the training episodes' return it
    # showed last instead of printing nan
    from kamino.envs.train import Progress

    bar = Progress(100, 0)
    bar.update(10, 1000.0, 1.0, train_return=5.0)
    bar.update(20, 1200.0, 2.0)  # an evaluation without a return
    assert bar.shown == {"train_return": "5.00", "env_steps_per_s": "1200"}
    bar.update(30, 1300.0, 3.0, eval_return=7.5, eval_std=0.5)
    assert bar.shown["eval_return"] == "7.50" and bar.shown["train_return"] == "5.00"
    bar.close()
    out = capsys.readouterr()
    assert "nan" not in out.out + out.err
    assert "train_return=5.00" in out.out + out.err
