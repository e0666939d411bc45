"""``kamino.bench.convergence`` end to end on Warp's CPU device: the MJCF four-bar and one stress model
(the four-bar with a hinge tilted by 10 degrees), 2 worlds x 30 steps at the library defaults."""

import json
import math
import pathlib

import pytest


@pytest.fixture(scope="module")
def convergence():
    pytest.importorskip("warp")
    from kamino.bench import convergence

    return convergence


def test_convergence_benchmark_writes_every_field(convergence, tmp_path):
    out = tmp_path / "convergence.json"
    assert convergence.main(["--scenes", "fourbar", "fourbar_tilt10", "--worlds", "2", "--steps", "30", "--no-sweep",
                             "--device", "cpu", "--sample-every", "10", "--out", str(out)]) == 0
    results = json.loads(out.read_text())
    env = results["environment"]
    assert env["device"] == "cpu" and env["warp"] and env["jax"] and "--worlds 2" in env["command"]
    assert env["solver_config"]["dt"] == 0.0025 and env["solver_config"]["penalty"]["mode"] == "adaptive"
    recs = {r["scene"]: r for r in results["records"]}
    assert set(recs) == {"fourbar", "fourbar_tilt10"}
    assert recs["fourbar_tilt10"]["suite"] == "stress"
    for rec in recs.values():
        assert "error" not in rec, rec
        assert rec["num_worlds"] == 2 and rec["steps"] == 30 and rec["world_steps"] == 60
        assert isinstance(rec["converged_fraction"], float) and 0.0 <= rec["converged_fraction"] <= 1.0
        it = rec["iterations"]
        assert 0 <= it["mean"] <= it["max"] and it["p50"] <= it["p99"] <= it["max"]
        assert sum(c for _, c in rec["iterations_histogram"]) == 60
        assert isinstance(rec["failed_worlds"], int) and isinstance(rec["diverged"], bool)
        assert math.isfinite(rec["closure_max_m"]) and rec["closure_max_m"] >= 0.0
        for key in ("solve", "pre", "post"):
            assert rec["bilateral_velocity"][key]["trans_max_m_s"] >= 0.0
        assert rec["throughput_world_steps_per_s"] is None  # not measured on the CPU
        assert rec["config"]["tolerance"] == 1e-3
    # the default four-bar converges and keeps its loop closed over these 30 driven steps
    assert recs["fourbar"]["closure_max_m"] < 1e-4 and not recs["fourbar"]["diverged"]
    table = convergence.table(results)
    assert table.count("\n| fourbar") == 2
    pngs = convergence.plot(results, tmp_path / "convergence")
    assert [pathlib.Path(p).name for p in pngs] == ["convergence_iterations.png"]


def test_a_run_past_its_time_limit_reports_what_it_ran(convergence, tmp_path):
    """``--time-limit``: a scene whose run would pass the limit stops and still writes its record, marked
    ``truncated`` with the steps it ran (here none: a limit of 0 s stops before the first step)."""
    out = tmp_path / "limited.json"
    assert convergence.main(["--scenes", "fourbar", "--worlds", "2", "--steps", "30", "--no-sweep", "--device", "cpu",
                             "--time-limit", "0", "--out", str(out)]) == 0
    (rec,) = json.loads(out.read_text())["records"]
    assert "error" not in rec, rec
    assert rec["truncated"] is True and rec["steps"] == 0 and rec["world_steps"] == 0
