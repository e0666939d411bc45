"""The peers of the throughput benchmark (``kamino.bench.peers``: MuJoCo Warp, Newton SolverKamino) on kamino's
robots.

``kamino.bench.throughput``'s ``run_peers`` exports a robot with ``kamino.save_mjcf`` into a temporary directory and
hands the file to both peers with the robot's drive (position target ``0.2 sin(2 pi t)`` rad on the first actuator);
the MJCF scenes keep their file and the 2 N m torque. The first tests replace the peers by a stand-in (no peer
needed); the last two run the real peers on Warp's CPU device and skip where ``mujoco_warp`` / ``newton`` are not
installed (CI)."""

import argparse
import importlib
import math
import sys
import types
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pytest

import kamino
from kamino.bench import scene_path

ROOT = Path(__file__).resolve().parents[1]


def _module(name: str):
    """The benchmark module ``kamino.bench.NAME`` (``throughput``, ``peers``)."""
    return importlib.import_module(f"kamino.bench.{name}")


def _fake_peers(calls: list) -> types.ModuleType:
    """A stand-in for ``kamino.bench.peers`` whose runners record their arguments and the MJCF text they were given."""

    def runner(peer: str):
        def run(path, num_worlds, **kw):
            calls.append({"peer": peer, "path": path, "text": Path(path).read_text(), "num_worlds": num_worlds, **kw})
            return {"peer": peer, "scene": Path(path).stem, "num_worlds": num_worlds, "throughput": 1.0}

        run.__name__ = f"run_{peer}"
        return run

    fake = types.ModuleType("kamino.bench.peers")
    fake.run_mujoco_warp = runner("mujoco_warp")
    fake.run_solver_kamino = runner("solver_kamino")
    return fake


def _args(**kw) -> argparse.Namespace:
    base = dict(worlds=[2, 4], graph_steps=1, warmup=2, replays=3, repeats=1, closure_steps=5,
                kamino_variants=["padmm_dense"])
    return argparse.Namespace(**{**base, **kw})


def _first_actuated_joint(model) -> str:
    dof = int(model.actuator_dof[model.world_actuator_start[0]])
    j = int(np.flatnonzero((model.joint_dof_start <= dof) & (dof < model.joint_dof_start + model.joint_dof_count))[0])
    return model.joint_names[j]


def test_run_peers_exports_the_robot_and_drives_its_position_target(monkeypatch):
    tp = _module("throughput")
    calls, records = [], []
    monkeypatch.setitem(sys.modules, "kamino.bench.peers", _fake_peers(calls))
    tp.run_peers("dr_legs", _args(), records.append)

    # both peers at both world counts, on one exported file; the closure run only at the first world count
    assert [(c["peer"], c["num_worlds"]) for c in calls] == [
        ("mujoco_warp", 2), ("solver_kamino", 2), ("mujoco_warp", 4), ("solver_kamino", 4)]
    assert [c["closure_steps"] for c in calls] == [5, 5, 0, 0]
    # the peers time kamino's window: the same warm-up and replays (kamino.bench.timed_window)
    assert all((c["graph_steps"], c["warmup"], c["replays"], c["repeats"]) == (1, 2, 3, 1) for c in calls)
    assert calls[1]["variant"] == "padmm_dense"
    assert all(c["amplitude"] == 0.2 for c in calls)  # rad, as kamino's own drive of the robots
    assert len({c["path"] for c in calls}) == 1
    path = Path(calls[0]["path"])
    assert not path.exists()  # a temporary directory, removed after the runs
    assert ROOT not in path.parents and scene_path("fourbar").parent not in path.parents
    for rec in records:
        assert rec["scene"] == "dr_legs" and rec["scene_source"] == "kamino.save_mjcf(kamino.models.dr_legs())"

    # the file is kamino's export: position actuators (the drive's first one on kamino's first actuated joint) and
    # the loop closures as <connect>
    root = ET.fromstring(calls[0]["text"])
    first = next(iter(root.find("actuator")))
    assert first.tag == "position" and float(first.get("kp")) > 0
    assert first.get("joint") == _first_actuated_joint(kamino.models.dr_legs())
    assert len(root.find("equality").findall("connect")) == 12
    assert kamino.load_mjcf(calls[0]["text"]).num_bodies > 0


def test_run_peers_keeps_the_mjcf_scenes_and_their_torque(monkeypatch):
    tp = _module("throughput")
    calls, records = [], []
    monkeypatch.setitem(sys.modules, "kamino.bench.peers", _fake_peers(calls))
    tp.run_peers("fourbar", _args(worlds=[2]), records.append)
    assert [Path(c["path"]) for c in calls] == [scene_path("fourbar")] * 2
    assert all(c["amplitude"] == 2.0 for c in calls)
    assert all(r["scene"] == "fourbar" and r["scene_source"] == "kamino/bench/scenes/fourbar.xml" for r in records)


def test_peers_read_the_first_actuator_of_an_export(tmp_path):
    pytest.importorskip("warp")
    peers = _module("peers")
    path = tmp_path / "bdx.xml"
    kamino.save_mjcf(kamino.models.bdx(), path)
    joint, kind = peers._first_actuator(str(path))
    assert (joint, kind) == (_first_actuated_joint(kamino.models.bdx()), "position")
    assert peers._first_actuator(str(scene_path("fourbar"))) == ("link1_to_link2", "motor")
    assert "0.2 sin" in peers._drive_text(kind, joint, 0.2)


def test_mujoco_warp_runs_an_exported_robot(tmp_path):
    pytest.importorskip("mujoco_warp")
    peers = _module("peers")
    path = tmp_path / "dr_legs.xml"
    kamino.save_mjcf(kamino.models.dr_legs(), path)
    r = peers.run_mujoco_warp(str(path), 1, device="cpu", graph_steps=1, replays=1, repeats=1, closure_steps=2,
                              amplitude=0.2)
    assert r["reason"] is None, r.get("traceback")
    assert r["scene"] == "dr_legs" and r["drive"].startswith("position target 0.2 sin")
    assert math.isfinite(r["throughput"]) and r["throughput"] > 0
    assert 0 < r["closure_max_m"] < 1e-3 and r["joint_error_max_m"] == r["closure_max_m"]
    assert r["memory_per_world_arrays_bytes"] > 0
    assert "timestep 0.002 s of the file replaced by 0.0025 s" in r["notes"]


def test_solver_kamino_drives_the_joint_target_of_an_exported_robot(tmp_path):
    pytest.importorskip("newton")
    wp = pytest.importorskip("warp")
    peers = _module("peers")
    path = tmp_path / "dr_legs.xml"
    kamino.save_mjcf(kamino.models.dr_legs(), path)
    dev = wp.get_device("cpu")
    with wp.ScopedDevice(dev):
        built = peers._newton_build(str(path), 2, dev, "mjcf")
        assert built.drive_field == "joint_target_q" and built.drive_offset.tolist() == [0.0, 0.0]
        assert "12 <position> actuators -> Newton joint PD" in built.note
        assert "forcerange -> joint_effort_limit on 12" in built.note
        sim = peers._newton_sim(built, "dvi")
        step = peers._newton_stepper(built, sim, amplitude=0.2)
        step()
        step()  # the second step's drive: t = dt
        target = sim.control.joint_target_q.numpy()[built.drive_index]
        np.testing.assert_allclose(target, 0.2 * math.sin(2 * math.pi * peers.DT), rtol=1e-6)
        assert not np.any(sim.control.joint_f.numpy())  # no torque drive
        assert np.all(np.isfinite(sim.states[0].body_q.numpy()))
    r = peers.run_solver_kamino(str(path), 1, device="cpu", variant="dvi", graph_steps=2, replays=1, repeats=1,
                                closure_steps=2, amplitude=0.2)
    assert r["reason"] is None, r.get("traceback")
    assert math.isfinite(r["throughput"]) and r["throughput"] > 0
    assert 0 <= r["closure_max_m"] <= r["joint_error_max_m"] < 1e-3
    assert r["memory_per_world_arrays_bytes"] > 0
