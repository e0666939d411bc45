"""``kamino.plots``: the figures hold the data they claim to (a four-bar rollout's metrics and solver reports; the
committed benchmark JSONs' records), one panel per scene."""

import json
import pathlib
import sys

import numpy as np
import pytest

import kamino
from kamino import plots

pytest.importorskip("matplotlib")
RESULTS = pathlib.Path(__file__).resolve().parents[1] / "benchmarks" / "results"


@pytest.fixture(scope="module")
def fourbar_rollout():
    model = kamino.replicate(kamino.models.fourbar(), 2)
    traj = kamino.rollout(model, kamino.init_state(model), num_steps=50, backend="warp")
    return model, traj, {k: np.asarray(v) for k, v in kamino.metrics(model, traj).items()}


def _lines(ax) -> dict[str, np.ndarray]:
    return {line.get_label(): np.asarray(line.get_ydata()) for line in ax.get_lines()}


@pytest.mark.parametrize("world", [1, None])
def test_rollout_diagnostics_draws_the_metrics_and_the_solver_reports(fourbar_rollout, world):
    import matplotlib.pyplot as plt

    model, traj, m = fourbar_rollout
    pick = (lambda a: np.asarray(a)[:, world]) if world is not None else (lambda a: np.asarray(a).max(axis=1))
    fig = plots.rollout_diagnostics(model, traj, world=world)
    try:
        closure, energy, iters, residuals = fig.axes
        assert len(fig.axes) == 4
        np.testing.assert_array_equal(_lines(closure)["constraint violation"], pick(m["constraint_violation"]))
        assert closure.get_yscale() == "log" and residuals.get_yscale() == "log"
        # the x axis is the simulated time
        np.testing.assert_array_equal(closure.get_lines()[0].get_xdata(), pick(traj.time))
        e = _lines(energy)
        assert set(e) == {"kinetic energy", "potential energy", "total energy"}
        for key in ("kinetic_energy", "potential_energy", "total_energy"):
            np.testing.assert_array_equal(e[key.replace("_", " ")], pick(m[key]))
        np.testing.assert_array_equal(_lines(iters)["iterations"], pick(traj.info.iterations))
        r = _lines(residuals)
        np.testing.assert_array_equal(r["primal residual"], pick(traj.info.primal_residual))
        np.testing.assert_array_equal(r["dual residual"], pick(traj.info.dual_residual))
        assert all(len(y) == 50 for ax in fig.axes for y in _lines(ax).values() if ax is not iters)
    finally:
        plt.close(fig)


def test_rollout_diagnostics_step_axis_and_caller_axes(fourbar_rollout):
    import matplotlib.pyplot as plt

    model, traj, _ = fourbar_rollout
    fig, axes = plt.subplots(1, 4)
    try:
        assert plots.rollout_diagnostics(model, traj.replace(time=None), dt=0.01, ax=axes) is fig
        np.testing.assert_allclose(axes[0].get_lines()[0].get_xdata(), 0.01 * np.arange(1, 51))
        with pytest.raises(ValueError, match="out of range"):
            plots.rollout_diagnostics(model, traj, world=2)
        with pytest.raises(ValueError, match="4 panel"):
            plots.rollout_diagnostics(model, traj, ax=axes[:2])
    finally:
        plt.close(fig)


def _records(*names: str) -> dict:
    """The throughput records of several committed result files, merged as ``kamino bench --plot`` merges them."""
    return {"records": [r for n in names for r in json.loads((RESULTS / n).read_text())["records"]]}


#: the fourbar and ladder8 records at 4096 and 16384 worlds: kamino and both peers at two world counts each
_PEER_RUNS = ("throughput_fourbar_4096_h100_2026-11-28.json", "throughput_fourbar_16384_h100_2026-11-28.json",
              "throughput_ladder8_4096_h100_2026-11-28.json", "throughput_ladder8_16384_h100_2026-11-28.json")
#: the tolerance sweep on the benchmark four-bar: five tolerances (and the default run), each with its iterations
#: histogram
_SWEEP = "convergence_tolerance_fourbar_h200_2026-11-29.json"


def test_speed_against_error_one_panel_per_scene():
    import matplotlib.pyplot as plt

    results = _records(*_PEER_RUNS)
    fig = plots.speed_against_error(results)
    try:
        assert [ax.get_title() for ax in fig.axes] == ["fourbar", "ladder8"]
        for ax in fig.axes:
            assert ax.get_xscale() == "log" and ax.get_yscale() == "log"
            lines = {line.get_label(): line for line in ax.get_lines()}
            recs = [r for r in results["records"] if r["scene"] == ax.get_title()]
            assert set(lines) == {plots._series(r) for r in recs}  # one line per simulator, kamino and the peers
            assert len(lines) == 4
            for label, line in lines.items():
                series = sorted((r for r in recs if plots._series(r) == label), key=lambda r: r["num_worlds"])
                assert len(line.get_xdata()) == len(series)  # one point per world count
                np.testing.assert_allclose(line.get_ydata(), [r["throughput"] for r in series])
                np.testing.assert_allclose(line.get_xdata(), [r["closure_max_m"] for r in series])
    finally:
        plt.close(fig)


def test_speed_against_error_reads_a_convergence_sweep():
    import matplotlib.pyplot as plt

    results = json.loads((RESULTS / _SWEEP).read_text())
    fig = plots.speed_against_error(results)
    try:
        (ax,) = fig.axes
        (line,) = ax.get_lines()
        by_tol = {r["tolerance"]: r for r in results["records"]}  # the default run repeats the sweep's 1e-3
        recs = [by_tol[t] for t in sorted(by_tol, reverse=True)]
        assert ax.get_title() == "fourbar" and len(line.get_xdata()) == len(recs) == 5
        np.testing.assert_allclose(line.get_xdata(), [r["closure_max_m"] for r in recs])
        np.testing.assert_allclose(line.get_ydata(), [r["throughput_world_steps_per_s"] for r in recs])
    finally:
        plt.close(fig)


def test_benchmark_results_helpers_and_save(tmp_path):
    results = _records(*_PEER_RUNS)
    fig = plots.throughput_against_worlds(results)
    assert [ax.get_title() for ax in fig.axes] == ["fourbar", "ladder8"]  # one panel per scene
    for ax in fig.axes:
        series = {plots._series(r) for r in results["records"] if r["scene"] == ax.get_title()}
        assert {line.get_label() for line in ax.get_lines()} == series and len(series) == 4
    assert plots.save_figure(fig, tmp_path / "t.png") == str(tmp_path / "t.png") and (tmp_path / "t.png").stat().st_size
    conv = json.loads((RESULTS / _SWEEP).read_text())
    fig = plots.iterations_histogram(conv)
    drawn = [ax for ax in fig.axes if ax.axison]  # 5 panels in a 2 x 4 grid, the rest blank
    assert len(drawn) == len({r["tolerance"] for r in conv["records"] if r.get("iterations_histogram")}) == 5
    assert all(len(ax.patches) for ax in drawn)
    plots.save_figure(fig, tmp_path / "h.png")
    with pytest.raises(ValueError, match="no record"):
        plots.speed_against_error({"records": [{"scene": "x", "num_worlds": 1, "throughput": 1.0}]})


def test_without_matplotlib_the_error_names_the_extra(monkeypatch):
    monkeypatch.setitem(sys.modules, "matplotlib", None)  # import matplotlib now raises ImportError
    with pytest.raises(ImportError, match=r"pip install 'kamino\[bench\]'"):
        plots.throughput_against_worlds({"records": [{"scene": "x", "num_worlds": 1, "throughput": 1.0}]})



def test_speed_at_accuracy_one_panel_per_scene_load_and_worlds():
    """kamino at two tolerances and MuJoCo Warp at two sweep settings, under two loads: a panel per load, a series per
    solver, a point per setting at (closure, simulated seconds per second); a record without ``sim_seconds_per_s``
    gets world-steps/s x the benchmark's 2.5 ms; other kamino configurations are left out."""
    import matplotlib.pyplot as plt

    def kam(load, tol, thr, closure):
        return {"kamino": "warp", "config": "default", "scene": "s", "load": load, "num_worlds": 8,
                "throughput": thr, "closure_batch_max_m": closure, "solver": {"tolerance": tol} if tol else {}}

    def mjw(load, settings, sim, closure):
        return {"peer": "mujoco_warp", "variant": f"newton_solver_soft_connect {settings}".strip(), "scene": "s",
                "load": load, "num_worlds": 8, "throughput": 1.0, "sim_seconds_per_s": sim,
                "closure_batch_max_m": closure}

    recs = [kam("gentle", None, 4e5, 2e-6), kam("gentle", 0.01, 5e5, 3e-6), kam("rl", None, 1e5, 2e-6),
            mjw("gentle", "timeconst=0.02", 7e3, 4e-3), mjw("gentle", "timeconst=0.005", 6e3, 3e-4),
            mjw("rl", "", 6e3, 4e-2), dict(kam("gentle", None, 1.0, 1e-6), config="sparse-cr")]
    fig = plots.speed_at_accuracy({"records": recs})
    try:
        assert [ax.get_title() for ax in fig.axes] == ["s, gentle load, 8 worlds", "s, rl load, 8 worlds"]
        gentle = {line.get_label(): line for line in fig.axes[0].get_lines()}
        assert set(gentle) == {"kamino", "MuJoCo Warp"}
        np.testing.assert_allclose(gentle["kamino"].get_xdata(), [3e-6, 2e-6])  # loosest closure first
        np.testing.assert_allclose(gentle["kamino"].get_ydata(), [5e5 * 0.0025, 4e5 * 0.0025])
        np.testing.assert_allclose(gentle["MuJoCo Warp"].get_ydata(), [7e3, 6e3])
        labels = {t.get_text() for t in fig.axes[1].texts}
        assert labels == {"defaults", "file's settings"}
    finally:
        plt.close(fig)
