"""``kamino bench``'s speed-against-accuracy sweeps (``--kamino-sweep``, ``--sk-sweep``), the speed each solver
reaches at each loop-closure target (``throughput.pareto``) and the ``--suite`` presets, on the CPU: the timed runs
and the peers are stand-ins that record what they were asked to run."""

import json
import pathlib
import sys
from types import SimpleNamespace

import pytest

from kamino import cli
from kamino.bench import throughput


def _fake_bench_warp(calls: list):
    """A stand-in for ``throughput.bench_warp``: records the run and the solver settings in force, returns a record
    as the real one keys it."""

    def bench(name, config, num_worlds, args, load="gentle"):
        calls.append({"scene": name, "config": config, "num_worlds": num_worlds, "load": load,
                      "solver": dict(throughput.SOLVER), "replays": args.replays, "repeats": args.repeats})
        return {"kamino": "warp", "config": config, "scene": name, "load": load, "num_worlds": num_worlds,
                "throughput": 1e5, "sim_seconds_per_s": 250.0, "closure_batch_max_m": 2e-6,
                "solver": dict(throughput.SOLVER)}

    return bench


def test_kamino_sweep_runs_every_combination_on_top_of_the_solver_options(tmp_path, monkeypatch, capsys):
    """``--kamino-sweep tolerance=1e-2,1e-3 warp.linear_solver=llt,cr`` with ``--solver penalty.rho=0.05``: four
    runs per scene, load and world count, each with ``penalty.rho`` and its own combination in ``solver``, so the
    four records have four keys and four table columns; the settings of the command are back in force after."""
    calls = []
    monkeypatch.setattr(throughput, "bench_warp", _fake_bench_warp(calls))
    out = tmp_path / "sweep.json"
    assert cli.main(["bench", "--scenes", "fourbar", "--worlds", "2", "--configs", "default", "--loads", "gentle",
                     "--no-peers", "--no-progress", "--solver", "penalty.rho=0.05", "--kamino-sweep",
                     "tolerance=1e-2,1e-3", "warp.linear_solver=llt,cr", "--out", str(out)]) == 0
    capsys.readouterr()
    assert [c["solver"] for c in calls] == [
        {"penalty.rho": 0.05, "tolerance": t, "warp.linear_solver": s} for t in (0.01, 0.001) for s in ("llt", "cr")]
    records = json.loads(out.read_text())["records"]
    assert len({throughput.record_key(r) for r in records}) == 4
    header = throughput.table(records).splitlines()[0]
    assert "| kamino penalty.rho=0.05 tolerance=0.001 warp.linear_solver=cr |" in header
    assert header.count("| kamino ") == 4
    assert throughput.SOLVER == {"penalty.rho": 0.05}


@pytest.mark.parametrize("argv, names", [
    (["--kamino-sweep", "tolerance=-1"], ["--kamino-sweep", "'tolerance=-1'", "must be > 0"]),
    (["--kamino-sweep", "dt=0.001"], ["--kamino-sweep", "'dt=0.001'", "penalty.rho"]),
    (["--kamino-sweep", "tolerance"], ["--kamino-sweep", "KEY=V[,V...]"]),
    (["--sk-sweep", "tolerance=0"], ["--sk-sweep", "'tolerance=0'", "> 0"]),
    (["--sk-sweep", "rho_0=0.1"], ["--sk-sweep", "KEY one of tolerance, iterations"]),
    (["--sk-sweep", "iterations=2.5"], ["--sk-sweep", "must be ints"]),
    (["--mjw-sweep", "solref=0.02"], ["--mjw-sweep", "timeconst"]),
    (["--mjw-sweep", "timeconst=0.02", "+", "dt"], ["--mjw-sweep", "'dt'", "'+' between groups"]),
])
def test_a_bad_sweep_names_the_option_and_what_is_valid(argv, names, capsys):
    """A bad sweep item ends the command before anything runs with argparse's status 2 and one line naming the
    option, the item and what is valid (a kamino setting is checked by ``SolverConfig`` itself; ``dt`` is not
    swept: the benchmark's time step is fixed)."""
    with pytest.raises(SystemExit) as done:
        cli.main(["bench", *argv])
    err = capsys.readouterr().err
    assert done.value.code == 2 and "Traceback" not in err
    assert all(n in err for n in names), err


def test_a_plus_starts_another_group_of_combinations():
    """``+`` between sweep items: each group's combinations after the previous group's, a setting listed already left
    out, and an empty group the run without settings."""
    assert throughput.mjw_sweep(["timeconst=0.02,0.005", "dt=0.0025", "+", "iterations=10", "tolerance=1e-4", "+",
                                 "timeconst=0.005", "dt=0.0025", "+"]) == [
        {"timeconst": 0.02, "timestep": 0.0025}, {"timeconst": 0.005, "timestep": 0.0025},
        {"iterations": 10, "tolerance": 1e-4}, {}]
    assert throughput.kamino_sweep(["tolerance=1e-2", "+", "tolerance=1e-4", "max_iterations=50"]) == [
        {"tolerance": 1e-2}, {"tolerance": 1e-4, "max_iterations": 50}]


def _fake_peers(calls: list) -> SimpleNamespace:
    def runner(name):
        def run(path, num_worlds, **kw):
            calls.append((name, num_worlds, kw))
            return {"peer": name, "num_worlds": num_worlds, "throughput": 1.0}
        run.__name__ = f"run_{name}"
        return run

    return SimpleNamespace(run_mujoco_warp=runner("mujoco_warp"), run_solver_kamino=runner("solver_kamino"))


def test_sk_sweep_runs_each_variant_per_setting_under_the_gentle_load(monkeypatch):
    """``--sk-sweep tolerance=1e-4,1e-6 iterations=50`` with two variants: SolverKamino once per variant and
    combination (2 x 2), under the gentle load only, each given its ``tolerance`` and ``iterations``; MuJoCo Warp
    once per load."""
    import argparse

    calls, records = [], []
    monkeypatch.setitem(sys.modules, "kamino.bench.peers", _fake_peers(calls))
    args = argparse.Namespace(loads=["gentle", "rl"], worlds=[4], graph_steps=2, warmup=1, replays=1, repeats=1,
                              closure_steps=5, kamino_variants=["padmm_dense", "dvi"], mjw_sweep=[],
                              sk_sweep=["tolerance=1e-4,1e-6", "iterations=50"])
    throughput.run_peers("fourbar", args, records.append)
    sk = [(kw["variant"], kw["tolerance"], kw["iterations"]) for name, _, kw in calls if name == "solver_kamino"]
    assert sk == [("padmm_dense", 1e-4, 50), ("padmm_dense", 1e-6, 50), ("dvi", 1e-4, 50), ("dvi", 1e-6, 50)]
    assert [kw["load"] for name, _, kw in calls if name == "mujoco_warp"] == ["gentle", "rl"]
    assert len(records) == 6


def test_solver_kamino_sweep_sets_the_named_fields_and_names_the_record(monkeypatch):
    """``tolerance`` sets PADMM's three tolerances (DVI's one) and ``iterations`` its ``max_iterations`` (DVI's
    ``max_alternating_iterations``); ``None`` keeps a value; a solver or field the installed Newton lacks is an error,
    never a setting silently ignored. The record's ``variant`` names the sweep's settings even when Newton cannot be
    imported, so that a sweep's failed runs stay apart too."""
    from kamino.bench import peers

    padmm = SimpleNamespace(dynamics_solver="padmm", padmm=SimpleNamespace(
        primal_tolerance=1e-4, dual_tolerance=1e-4, compl_tolerance=1e-4, max_iterations=200))
    peers._set_solver_settings(padmm, tolerance=1e-6, iterations=None)
    assert vars(padmm.padmm) == {"primal_tolerance": 1e-6, "dual_tolerance": 1e-6, "compl_tolerance": 1e-6,
                                 "max_iterations": 200}
    dvi = SimpleNamespace(dynamics_solver="dvi", dvi=SimpleNamespace(tolerance=1e-5, max_alternating_iterations=8))
    peers._set_solver_settings(dvi, tolerance=1e-7, iterations=50)
    assert vars(dvi.dvi) == {"tolerance": 1e-7, "max_alternating_iterations": 50}
    with pytest.raises(ValueError, match="max_alternating_iterations"):
        peers._set_solver_settings(SimpleNamespace(dynamics_solver="dvi", dvi=SimpleNamespace(tolerance=1.0)),
                                   iterations=5)
    with pytest.raises(ValueError, match="'lox'"):
        peers._set_solver_settings(SimpleNamespace(dynamics_solver="lox"), tolerance=1e-6)
    peers._set_solver_settings(SimpleNamespace(dynamics_solver="lox"))  # nothing to set: no error

    monkeypatch.setitem(sys.modules, "newton", None)  # import newton now raises ImportError
    rec = peers.run_solver_kamino("fourbar", 2, variant="padmm_dense", tolerance=1e-6, iterations=50)
    assert rec["variant"] == "padmm_dense tolerance=1e-06 iterations=50"
    assert rec["throughput"] is None and rec["reason"].startswith("import")


def _kam(tol, thr, closure, worlds=8, **kw):
    return {"kamino": "warp", "config": "default", "scene": "s", "load": "gentle", "num_worlds": worlds,
            "throughput": thr, "sim_seconds_per_s": thr * 0.0025, "closure_batch_max_m": closure,
            "solver": {"tolerance": tol}, **kw}


def _mjw(settings, sim, closure, **kw):
    return {"peer": "mujoco_warp", "variant": f"newton_solver_soft_connect {settings}", "scene": "s",
            "load": "gentle", "num_worlds": 8, "throughput": 1e6, "sim_seconds_per_s": sim,
            "closure_batch_max_m": closure, **kw}


def _sk(variant, thr, closure, worlds):
    return {"peer": "newton_solver_kamino", "variant": variant, "scene": "s", "num_worlds": worlds,
            "throughput": thr, "closure_max_m": closure, "dt": 0.0025, "settings": "newton_example"}


def test_pareto_reads_each_solvers_fastest_setting_at_each_closure():
    """Synthetic records of one scene and load: the fastest setting of each solver with closure <= 1e-3, 1e-4 and
    1e-5 m that failed no world, or, where none does, the setting of the smallest closure ("best reached").

    kamino: tolerance 1e-2 is the fastest (1,000 s/s) at 2e-5 m, so it wins at 1e-3 and 1e-4 m, and 1e-3 (750 s/s at
    2e-6 m) at 1e-5 m; an earlier record of the same setting (1 world-step/s) is replaced by the later one and another
    configuration is left out. MuJoCo Warp: 7,020 s/s at 2.5e-4 m meets 1e-3 m; a setting at 5e-5 m failed 3 worlds,
    so nothing meets 1e-4 m and its point is the best reached. SolverKamino: no ``sim_seconds_per_s``, so 1e4
    world-steps/s x 2.5 ms = 25 s/s; at 16 worlds its record has no closure and takes the 8-world run's (the
    one-world run is made once per setting); a variant without any closure gets no row; failed runs are left out."""
    records = [
        _kam(1e-3, 1.0, 2e-6), _kam(1e-2, 4e5, 2e-5), _kam(1e-3, 3e5, 2e-6), _kam(1e-4, 2e5, 1.9e-6),
        dict(_kam(1e-2, 9e9, 1e-9), config="sparse-cr"),
        _mjw("timeconst=0.02 timestep=0.0025", 7040, 3.7e-3), _mjw("timeconst=0.02 timestep=0.00025", 716, 1.1e-3),
        _mjw("timeconst=0.005 timestep=0.0025", 7020, 2.5e-4), _mjw("timeconst=0.005 timestep=0.00025", 717, 2.2e-4),
        _mjw("timeconst=0.001 timestep=0.0025", 9000, 5e-5, failed_worlds=3),
        _sk("padmm_dense tolerance=1e-06", 1e4, 3e-5, 8), _sk("padmm_dense tolerance=1e-06", 1.5e4, None, 16),
        _sk("dvi", 1e4, None, 8), _sk("dvi tolerance=1e-06", None, None, 8),
        {"kamino": "warp", "config": "default", "scene": "s", "num_worlds": 8, "error": "RuntimeError()"},
    ]
    lines = throughput.pareto(records).splitlines()
    assert lines[0] == ("| scene | load | worlds | solver | closure <= 1e-03 m | closure <= 1e-04 m "
                        "| closure <= 1e-05 m |")
    assert lines[2:] == [
        "| s | gentle | 8 | kamino | 1,000 s/s (tolerance=0.01, 2.0e-05 m) | 1,000 s/s (tolerance=0.01, 2.0e-05 m) "
        "| 750 s/s (tolerance=0.001, 2.0e-06 m) |",
        "| s | gentle | 8 | MuJoCo Warp | 7,020 s/s (timeconst=0.005 timestep=0.0025, 2.5e-04 m) |"
        + " best reached: 9,000 s/s at 5.0e-05 m (timeconst=0.001 timestep=0.0025, 3 failed worlds) |" * 2,
        "| s | gentle | 8 | SolverKamino padmm_dense |" + " 25 s/s (tolerance=1e-06, 3.0e-05 m) |" * 2
        + " best reached: 25 s/s at 3.0e-05 m (tolerance=1e-06) |",
        "| s | gentle | 16 | SolverKamino padmm_dense |" + " 37.5 s/s (tolerance=1e-06, 3.0e-05 m) |" * 2
        + " best reached: 37.5 s/s at 3.0e-05 m (tolerance=1e-06) |",
    ]


def _run_suite(argv, monkeypatch):
    """``kamino bench ARGV`` with the kamino runs, the peers and the plots replaced by stand-ins; what each got."""
    calls, peer_args, plots = [], [], []
    monkeypatch.setattr(throughput, "bench_warp", _fake_bench_warp(calls))
    monkeypatch.setattr(throughput, "run_peers", lambda scene, args, emit: peer_args.append((scene, args)))
    monkeypatch.setattr(throughput, "plot", lambda results, stem: plots.append((len(results["records"]), stem)))
    assert cli.main(["bench", *argv, "--no-progress"]) == 0
    return calls, peer_args, plots


def test_the_accuracy_suite_expands_to_every_scene_load_world_count_and_sweep(tmp_path, monkeypatch, capsys):
    """``kamino bench --suite accuracy``: kamino's default configuration on the seven scenes, both loads, 4096 and
    16384 worlds, at three tolerances (7 x 2 x 2 x 3 = 84 runs, one trial of 30 blocks each); the peers on each scene
    with MuJoCo Warp's eight settings and SolverKamino's two variants at two tolerances; the records in
    ``bench_accuracy.json``, both tables in ``bench_accuracy.md`` and the plots named after it."""
    monkeypatch.chdir(tmp_path)
    calls, peer_args, plots = _run_suite(["--suite", "accuracy"], monkeypatch)
    capsys.readouterr()
    scenes = ["fourbar", "ladder8", "ladder32", "dr_legs", "bdx", "olaf", "animatronic"]
    assert len(calls) == 84 and {c["config"] for c in calls} == {"default"}
    assert sorted({(c["scene"], c["load"], c["num_worlds"], c["solver"]["tolerance"]) for c in calls}) == sorted(
        (s, load, n, t) for s in scenes for load in ("gentle", "rl") for n in (4096, 16384) for t in (1e-2, 1e-3, 1e-4))
    assert {(c["replays"], c["repeats"]) for c in calls} == {(30, 1)}
    assert [scene for scene, _ in peer_args] == scenes
    args = peer_args[0][1]
    mjw = throughput.mjw_sweep(args.mjw_sweep)  # every knob: time constant, time step, iterations, tolerance
    assert len(mjw) == 8 and {k for setting in mjw for k in setting} == {"timeconst", "timestep", "iterations",
                                                                        "tolerance"}
    assert args.kamino_variants == ["padmm_dense", "dvi"]
    assert throughput.sk_sweep(args.sk_sweep) == [{"tolerance": 1e-4}, {"tolerance": 1e-6}]
    assert len(json.loads((tmp_path / "bench_accuracy.json").read_text())["records"]) == 84
    report = (tmp_path / "bench_accuracy.md").read_text()
    assert "| kamino tolerance=0.0001 |" in report and "| solver | closure <= 1e-03 m |" in report
    assert plots == [(84, pathlib.Path("bench_accuracy"))]


def test_a_suite_runs_in_parts_with_its_options_overridden(tmp_path, monkeypatch, capsys):
    """What the command line gives wins over the preset: one scene at one world count with 5 blocks, kamino alone
    (``--no-peers``), into ``part.json``/``part.md``; ``--configs`` with no value runs the peers alone."""
    monkeypatch.chdir(tmp_path)
    calls, peer_args, _ = _run_suite(["--suite", "accuracy", "--scenes", "olaf", "--worlds", "16384", "--replays", "5",
                                      "--no-peers", "--out", "part.json"], monkeypatch)
    assert [(c["scene"], c["num_worlds"], c["replays"]) for c in calls] == [("olaf", 16384, 5)] * 6
    assert peer_args == [] and (tmp_path / "part.md").exists()
    calls, peer_args, _ = _run_suite(["--suite", "accuracy", "--scenes", "bdx", "--configs", "--out", "peers.json"],
                                     monkeypatch)
    capsys.readouterr()
    assert calls == [] and [scene for scene, _ in peer_args] == ["bdx"]
    assert peer_args[0][1].worlds == [4096, 16384]


def test_gpus_run_every_part_on_its_own_gpu_and_merge_them(tmp_path, monkeypatch, capsys):
    """``--gpus 0 1``: per scene and world count one part for kamino (``--no-peers``) and one for the peers
    (``--configs`` with no value), the larger world count first, each part with ``--scenes``/``--worlds`` narrowed and
    its own ``--out``, spread over the two GPUs; a part that fails leaves a record naming its log, keyed as its
    records would be, and the other parts' records are merged into ``--out`` with the suite's report. The parts run
    in this process here (``run_part`` stands in for the subprocess), with the timed runs stood in as above."""
    calls, seen = [], []
    monkeypatch.setattr(throughput, "bench_warp", _fake_bench_warp(calls))
    monkeypatch.setattr(throughput, "run_peers", lambda scene, args, emit: emit(
        {"peer": "mujoco_warp", "variant": "v", "scene": scene, "num_worlds": args.worlds[0], "load": "gentle",
         "throughput": 2e5, "sim_seconds_per_s": 500.0, "closure_batch_max_m": 1e-3}))
    monkeypatch.setattr(throughput, "write_report", lambda results, out: seen.append(("report", out)))

    def run_part(cmd, gpu, out, log):
        seen.append((gpu, cmd))
        if "ladder8" in cmd and "--configs" in cmd:
            return 3  # the peers' part of ladder8 fails
        return throughput.main([*cmd, "--out", str(out)])

    monkeypatch.setattr(throughput, "run_part", run_part)
    out = tmp_path / "suite.json"
    assert cli.main(["bench", "--suite", "accuracy", "--scenes", "fourbar", "ladder8", "--worlds", "2", "4",
                     "--loads", "gentle", "--gpus", "0", "1", "--out", str(out), "--no-progress"]) == 0
    capsys.readouterr()
    runs = [cmd for gpu, cmd in seen if gpu != "report"]
    assert {gpu for gpu, _ in seen} == {"0", "1", "report"}
    assert len(runs) == 8  # 2 scenes x 2 world counts x (kamino, peers)
    assert [c[c.index("--worlds") + 1] for c in runs] == ["4"] * 4 + ["2"] * 4
    for c in runs:
        assert "--part" in c and "--gpus" not in c and "--out" not in c
        assert c.count("--scenes") == 1 and c.count("--worlds") == 1
    records = json.loads(out.read_text())["records"]
    kamino_runs = [r for r in records if r.get("kamino") and "error" not in r]
    assert len(kamino_runs) == 2 * 2 * 3  # the suite's three tolerances per scene and world count
    failed = [r for r in records if "error" in r]
    assert [(r["peer"], r["scene"]) for r in failed] == [("all", "ladder8")] * 2
    assert all("ladder8_" in r["error"] and r["error"].endswith(".log") for r in failed)
    assert {r["scene"] for r in records if r.get("peer") == "mujoco_warp"} == {"fourbar"}
    assert seen[-1] == ("report", out)  # the report of the merged run, none of the parts'
