"""``kamino bench``: the benchmark runs from the command line (here on Warp's CPU device, 2 worlds)."""

import json

import pytest

from kamino import cli


def test_kamino_bench_writes_speed_next_to_error(tmp_path):
    """One record per load, each with the statistics of its own timed batch (10 steps of 2 worlds)."""
    out = tmp_path / "bench.json"
    assert cli.main(["bench", "--scenes", "fourbar", "--worlds", "2", "--configs", "sparse-llt", "--no-peers",
                     "--graph-steps", "2", "--replays", "5", "--repeats", "1", "--out", str(out)]) == 0
    recs = json.loads(out.read_text())["records"]
    assert [r["load"] for r in recs] == ["gentle", "rl"]
    for rec in recs:
        assert rec["scene"] == "fourbar" and rec["num_worlds"] == 2 and rec["throughput"] > 0
        assert rec["batch_world_steps"] == 20 and rec["sim_seconds_per_s"] == pytest.approx(rec["throughput"] * 0.0025)
        # the MJCF four-bar's loop over the timed steps: closed to well below the 1e-5 m benchmark target
        assert rec["closure_batch_max_m"] < 1e-5
        assert rec["converged_share"] == 1.0 and rec["iterations_max"] < 100 and rec["failed_worlds"] == 0


def test_kamino_bench_tables_saved_runs_beside_the_peers(tmp_path, capsys):
    """``--table``: one markdown row per scene and world count from several saved runs, kamino's default
    configuration beside each peer, and kamino's speed and memory over MuJoCo Warp's (here 3e5 / 2e5 = 1.50x and
    90 kB / 60 kB = 1.50x). A peer that did not run shows its reason; other kamino configurations are left out.
    Below it, the speed at each closure target (``throughput.pareto``): kamino's 3e5 x 2.5 ms = 750 s/s at 1.5e-6 m
    meets all three; MuJoCo Warp's 4.5e-3 m none, so its best closure is given."""
    kam = {"kamino": "warp", "config": "default", "scene": "ladder32", "num_worlds": 4096, "throughput": 3e5,
           "closure_max_m": 1.5e-6, "converged_fraction": 1.0, "memory_per_world_bytes": 9e4}
    other = dict(kam, config="sparse-cr", throughput=1.0)
    mjw = {"peer": "mujoco_warp", "variant": "soft", "scene": "ladder32", "num_worlds": 4096, "throughput": 2e5,
           "closure_max_m": 4.5e-3, "converged_fraction": None, "memory_per_world_bytes": 6e4}
    sk = {"peer": "newton_solver_kamino", "variant": "dvi", "scene": "ladder32", "num_worlds": 4096,
          "throughput": None, "reason": "load: int32 overflow"}
    files = []
    for i, recs in enumerate(([kam, other], [mjw, sk])):
        files.append(tmp_path / f"run{i}.json")
        files[-1].write_text(json.dumps({"records": recs}))
    assert cli.main(["bench", "--table", *map(str, files)]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    assert lines[0] == ("| scene | load | worlds | kamino | MuJoCo Warp | SolverKamino dvi | speed / MuJoCo Warp "
                        "| memory / MuJoCo Warp |")
    assert lines[2] == ("| ladder32 | gentle | 4096 | 3.00e+05 (1.5e-06 m, 100.0 %, 90.0 kB) "
                        "| 2.00e+05 (4.5e-03 m, 60.0 kB) | not run: load: int32 overflow | 1.50x | 1.50x |")
    assert lines[3] == "" and lines[4].startswith("| scene | load | worlds | solver | closure <= 1e-03 m |")
    assert lines[6:] == ["| ladder32 | gentle | 4096 | kamino |" + " 750 s/s (defaults, 1.5e-06 m) |" * 3,
                         "| ladder32 | gentle | 4096 | MuJoCo Warp |"
                         + " best reached: 500 s/s at 4.5e-03 m (file's settings) |" * 3]


def test_kamino_bench_plots_several_runs_with_the_later_record_of_each_thing(tmp_path):
    """``--plot A.json B.json --out STEM.json``: one plot of both runs, named after ``--out``; a record of the same
    scene, size and solver in the later file replaces the earlier one (a size measured again in a second process),
    so each series keeps one point per size."""
    pytest.importorskip("matplotlib")
    from kamino.bench import throughput

    kam = {"kamino": "warp", "config": "default", "scene": "fourbar", "closure_max_m": 1.4e-6}
    runs = [[dict(kam, num_worlds=4096, throughput=3.3e6), dict(kam, num_worlds=16384, throughput=3.9e6)],
            [dict(kam, num_worlds=16384, throughput=6.1e6),
             {"peer": "mujoco_warp", "variant": "soft", "scene": "fourbar", "num_worlds": 16384, "throughput": 7e6}]]
    merged = throughput.latest_records(r for recs in runs for r in recs)
    assert [(r.get("peer"), r["num_worlds"], r["throughput"]) for r in merged] == [
        (None, 4096, 3.3e6), (None, 16384, 6.1e6), ("mujoco_warp", 16384, 7e6)]
    files = []
    for i, recs in enumerate(runs):
        files.append(tmp_path / f"run{i}.json")
        files[-1].write_text(json.dumps({"records": recs}))
    assert cli.main(["bench", "--plot", *map(str, files), "--out", str(tmp_path / "both.json")]) == 0
    assert (tmp_path / "both_throughput.png").stat().st_size > 0 and (tmp_path / "both_error.png").exists()


def test_kamino_bench_help_is_short_and_names_the_command(capsys):
    """``kamino bench --help``: the usage line names ``kamino bench``, the options fit a screen, and the other
    benchmarks are listed; ``kamino bench NAME --help`` is that module's help under ``kamino bench NAME``."""
    with pytest.raises(SystemExit) as done:
        cli.main(["bench", "--help"])
    assert done.value.code == 0
    out = capsys.readouterr().out
    assert out.startswith("usage: kamino bench ") and len(out.splitlines()) <= 32
    assert "--configs" in out and "convergence" in out and "time_to_first_step" in out
    with pytest.raises(SystemExit) as done:
        cli.main(["bench", "roofline", "--help"])
    assert done.value.code == 0
    assert capsys.readouterr().out.startswith("usage: kamino bench roofline ")


@pytest.mark.parametrize("argv, names", [
    (["--configs", "nosuch"], ["--configs", "'nosuch'", "sparse-llt", "jax"]),
    (["--scenes", "nosuch"], ["--scenes", "'nosuch'", "ladder8", "dr_legs"]),
    (["--worlds", "0"], ["--worlds", ">= 1"]),
    (["--solver", "nosuch=1"], ["--solver", "'nosuch=1'", "tolerance"]),
    (["--solver", "linear_solver=cr"], ["--solver", "'linear_solver=cr'", "warp.linear_solver"]),
    (["--table", "missing.json"], ["--table", "missing.json"]),
])
def test_kamino_bench_bad_values_name_the_option_and_the_choices(argv, names, capsys, tmp_path, monkeypatch):
    """A bad value ends in a one-line message that names the option, the value and what is valid (argparse's
    exit status 2 for a bad option), never a traceback; nothing is simulated."""
    monkeypatch.chdir(tmp_path)
    with pytest.raises(SystemExit) as done:
        cli.main(["bench", *argv])
    err = capsys.readouterr().err
    message = err if done.value.code == 2 else str(done.value.code)
    assert done.value.code not in (0, None) and "Traceback" not in err
    assert all(n in message for n in names), message


def test_kamino_bench_unknown_name_lists_the_benchmarks(capsys):
    assert cli.main(["bench", "nosuch"]) == 2
    err = capsys.readouterr().err
    assert "'nosuch'" in err and "convergence" in err and "profile_step" in err


def test_kamino_bench_plot_without_matplotlib_names_the_extra(tmp_path, capsys, monkeypatch):
    """``--plot`` needs matplotlib (the bench extra): without it, a message that says so, not an ImportError."""
    import sys

    monkeypatch.setitem(sys.modules, "matplotlib", None)  # import matplotlib now raises ImportError
    run = tmp_path / "run.json"
    run.write_text(json.dumps({"records": []}))
    with pytest.raises(SystemExit) as done:
        cli.main(["bench", "--plot", str(run)])
    assert done.value.code == 2
    err = capsys.readouterr().err
    assert "--plot needs matplotlib" in err and "kamino[bench]" in err


def test_bench_solver_settings_take_dotted_names():
    """``--solver F=V`` sets a nested setting by its path, on top of a benchmark configuration's own Warp settings.
    Every command line reads the value alike (``kamino.config.setting_value``): a Python literal, a JSON one, or a
    bare word as the string it spells; anything else is refused, naming the setting."""
    import kamino
    from kamino.bench import throughput
    from kamino.config import solver_settings

    overrides = throughput.solver_overrides(["warp.cr_iterations=20", "penalty.rho=0.05", "integrator=midpoint"])
    assert overrides == {"warp.cr_iterations": 20, "penalty.rho": 0.05, "integrator": "midpoint"}
    assert solver_settings(["reduction=schur"]) == solver_settings(["reduction='schur'"]) == {"reduction": "schur"}
    refine = "stabilisation.curvature_refinement"
    assert solver_settings([f"{refine}=false"]) == {refine: False}
    with pytest.raises(ValueError, match="--solver tolerance"):
        solver_settings(["tolerance=1e-3)"])
    with pytest.raises(ValueError, match=r"--set 'tolerence=0\.01'"):
        solver_settings(["tolerence=0.01"], "--set")
    cfg = kamino.SolverConfig(dt=throughput.DT).replace(**overrides, **throughput.CONFIGS["sparse-cr"])
    assert cfg.warp == kamino.WarpSettings(jacobian="sparse", linear_solver="cr", cr_iterations=20)
    assert cfg.penalty == kamino.Penalty(rho=0.05) and cfg.integrator == "midpoint"
