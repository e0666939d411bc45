"""MuJoCo Warp under the throughput benchmark's loads (``kamino.bench.peers``): kamino's ``rl`` starts converted to
MuJoCo's qpos put MuJoCo's bodies where kamino's are (host C MuJoCo), MuJoCo Warp's ``rl`` drive draws the same
controls as kamino's (both on Warp's CPU device), and, where MuJoCo Warp is installed, a small ``rl`` run whose
device-folded batch statistics equal the host readings after every step."""

import pathlib

import numpy as np
import pytest

import kamino
from kamino.bench import loads, scene_path

wp = pytest.importorskip("warp")
mujoco = pytest.importorskip("mujoco")

#: the forward-kinematics tolerance of the starts (kamino.forward_kinematics, 1e-6 per constraint row) in float32
#: poses of order 1 m: an anchor distance combines three rows and rounding of 6e-8 per coordinate
FK_CLOSURE = 5e-6
#: float32 poses of order 1 m carried through the conversion (a pose composition and kamino's joint coordinates, in
#: float32) and back through MuJoCo's kinematics: a few ulp of 6e-8 per coordinate, summed along a leg's chain of
#: joints (dr_legs: 2.2e-6)
POSE_TOL = 1e-5


@pytest.fixture(scope="module")
def peers():
    from kamino.bench import peers

    return peers


def _scene(name: str, tmp: pathlib.Path):
    """(path, kamino model) of a peer scene: a shipped MJCF, or a robot exported by ``kamino.save_mjcf``."""
    if name in ("fourbar", "ladder8"):
        path = str(scene_path(name))
        return path, kamino.load_mjcf(path)
    model = getattr(kamino.models, name)()
    path = str(tmp / f"{name}.xml")
    kamino.save_mjcf(model, path, model_name=name)
    return path, model


@pytest.mark.parametrize("name", ["fourbar", "ladder8", "dr_legs"])
def test_rl_starts_as_qpos_put_mujoco_where_kamino_is(peers, name, tmp_path):
    """Three ``rl`` starts of the four-bar (free base, hinges, one ``<connect>``), ladder8 (eight ``<connect>``) and
    dr_legs (exported: bodies on kamino's CoM frames, free base, revolute loops as pairs of ``<connect>``):
    ``mj_kinematics`` of the converted qpos puts every body's CoM and axes where kamino's are and closes every
    ``<connect>`` to the FK tolerance; MuJoCo's reference pose is not one of them (the check can fail)."""
    path, base = _scene(name, tmp_path)
    num_worlds = 3
    body_q = loads.random_configurations(base, kamino.replicate(base, num_worlds), loads.RL_FRACTION, seed=2)
    qpos = peers.mujoco_qpos(path, base, body_q)
    mjm = mujoco.MjModel.from_xml_path(path)
    assert qpos.shape == (num_worlds, mjm.nq)
    err, closure = peers.mujoco_pose_errors(mjm, qpos, base, body_q)
    assert err <= POSE_TOL and closure <= FK_CLOSURE
    # the same poses against MuJoCo's reference configuration: the starts are far from it (centimetres)
    wrong, _ = peers.mujoco_pose_errors(mjm, np.repeat(mjm.qpos0[None], num_worlds, 0), base, body_q)
    assert wrong > 1e-3


def test_mujoco_qpos_names_the_bodies_it_cannot_match(peers, tmp_path):
    """A kamino model that the file does not describe: a clear error naming the missing bodies."""
    other = kamino.load_mjcf(scene_path("fourbar"))
    with pytest.raises(ValueError, match="have no body of that name"):
        peers.mujoco_qpos(str(scene_path("ladder8")), other, np.asarray(other.body_q0))


@pytest.mark.parametrize("name", ["fourbar", "ladder8", "bdx"])
def test_mujoco_warp_rl_drive_draws_what_kamino_draws(peers, name, tmp_path):
    """kamino's ``rl`` hook and MuJoCo Warp's ``rl`` kernel at the same world times (three worlds, a time in each
    of several control periods, the periods' first and last steps among them): the four-bar's motor gets the same
    torque (gear 1: ctrl = effort), as does ladder8's unnamed motor (``actuator0`` to kamino's importer), bdx's
    fourteen ``<position>`` actuators (matched by name) the same targets, bit for bit; the draws differ between
    worlds and periods."""
    from kamino.bench import throughput

    path, base = _scene(name, tmp_path)
    num_worlds, seed = 3, 7
    with wp.ScopedDevice("cpu"):
        st, _, _ = throughput.warp_stepper(name, "default", num_worlds, load="rl", seed=seed)
        hook = st.pre_step[-1]
        mjm = mujoco.MjModel.from_xml_path(path)
        drive = peers._mjw_rl_drive(mjm, base, wp.get_device("cpu"), seed, throughput.DT)
        index = drive.actuator.numpy()
        dofs = base.actuator_dof[None, :] + base.num_dofs * np.arange(num_worlds)[:, None]
        _, _, effort = loads.rl_control_map(base)
        seen = []
        for step in (0, 7, 8, 15, 16, 101, 4000):
            t = np.full(num_worlds, step * throughput.DT, np.float32)
            st.work.time.assign(t)
            hook(st)
            kam = np.where(effort[None], st.work.effort.numpy()[dofs], st.work.position_target.numpy()[dofs])
            ctrl = wp.zeros((num_worlds, mjm.nu), dtype=wp.float32)
            wp.launch(peers._kernels().mjw_rl_drive, dim=(num_worlds, base.num_actuators),
                      inputs=[wp.array(t), drive.actuator, drive.offset, drive.scale, drive.rate, drive.half_dt,
                              drive.seed], outputs=[ctrl])
            np.testing.assert_array_equal(ctrl.numpy()[:, index], kam)
            seen.append(kam)
    seen = np.array(seen)
    assert np.all(seen[1] == seen[0]) and np.all(seen[3] == seen[2])  # steps 0/7 and 8/15 share a period
    assert np.all(seen[2] != seen[0]) and np.all(seen[0, 1] != seen[0, 0])  # periods and worlds differ


def test_mujoco_warp_rl_run_folds_its_batch(peers):
    """MuJoCo Warp on the four-bar under the ``rl`` load (3 worlds, Warp's CPU device): ``run_mujoco_warp`` gives a
    record with kamino's batch keys, the checked starts and no failed world; stepped by hand, the motor's ctrl is a
    draw within ``[-2, 2] N m``, and the device-folded iterations, convergence and closure equal the host readings
    of ``solver_niter`` and the ``<connect>`` anchors after every step."""
    pytest.importorskip("mujoco_warp", reason="MuJoCo Warp (the peer) is not installed")
    scene = str(scene_path("fourbar"))
    base = kamino.load_mjcf(scene)
    num_worlds, steps = 3, 6
    rec = peers.run_mujoco_warp(scene, num_worlds, device="cpu", graph_steps=2, warmup=1, replays=3, repeats=1,
                                load="rl", seed=4)
    assert rec["reason"] is None, rec.get("traceback")
    assert rec["load"] == "rl" and rec["batch_world_steps"] == num_worlds * steps and rec["failed_worlds"] == 0
    assert rec["start_pose_error_m"] <= POSE_TOL and rec["start_closure_m"] <= FK_CLOSURE
    assert rec["sim_seconds_per_s"] == pytest.approx(rec["throughput"] * peers.DT)
    assert rec["iterations_mean"] <= rec["iterations_p99"] <= rec["iterations_max"] <= rec["settings"]["iterations"]

    dev = wp.get_device("cpu")
    with wp.ScopedDevice(dev):
        body_q = loads.random_configurations(base, kamino.replicate(base, num_worlds), loads.RL_FRACTION, 4)
        mjm, m, d, _, _ = peers._mjw_build(scene, num_worlds, dev, peers.mujoco_qpos(scene, base, body_q))
        rl = peers._mjw_rl_drive(mjm, base, dev, 4, peers.DT)
        connects = peers._mjw_connects(mjm, dev)
        stats = peers._MjwBatchStats(num_worlds, mjm.opt.iterations, connects, dev)
        step = peers._mjw_stepper(m, d, num_worlds, rl=rl, stats=stats)
        niter, closure = [], 0.0
        for _ in range(steps):
            step()
            assert np.all(np.abs(d.ctrl.numpy()) <= loads.MOTOR_AMPLITUDE)
            niter.append(d.solver_niter.numpy().copy())
            xpos, xmat = d.xpos.numpy().astype(float), d.xmat.numpy().astype(float)
            for i in range(connects[0].shape[0]):
                b1, b2 = int(connects[0].numpy()[i]), int(connects[1].numpy()[i])
                p1 = xpos[:, b1] + xmat[:, b1] @ connects[2].numpy()[i]
                p2 = xpos[:, b2] + xmat[:, b2] @ connects[3].numpy()[i]
                closure = max(closure, float(np.linalg.norm(p1 - p2, axis=-1).max()))
        summary = stats.summary()
    niter = np.array(niter)
    assert summary["batch_world_steps"] == num_worlds * steps and summary["failed_worlds"] == 0
    assert summary["iterations_mean"] == pytest.approx(niter.mean(), rel=1e-12)
    assert summary["iterations_max"] == niter.max()
    assert summary["converged_share"] == pytest.approx(np.mean(niter < mjm.opt.iterations))
    # float32 anchors of order 0.1 m on the device against float64 of the same float32 poses: a few ulp
    assert summary["closure_batch_max_m"] == pytest.approx(closure, abs=1e-7)
    assert 0 < summary["closure_batch_max_m"] < 1e-2


def test_run_peers_runs_mujoco_warp_per_load_and_setting(peers, monkeypatch):
    """``kamino bench``'s peer loop (``run_peers``) with ``--loads gentle rl --mjw-sweep timeconst=0.02,0.004 dt=0.001``
    and one SolverKamino variant: MuJoCo Warp once per load, world count and combination (2 x 1 x 2), each given the
    kamino model of the scene; SolverKamino under the gentle load only. The peers are stand-ins recording their calls;
    a bad sweep item is a clear error."""
    import argparse

    from kamino.bench import throughput

    calls = []

    def fake(name):
        def run(path, nw, **kw):
            calls.append((name, nw, kw))
            return {"peer": name, "num_worlds": nw, "load": kw.get("load", "gentle")}
        return run

    monkeypatch.setattr(peers, "run_mujoco_warp", fake("mujoco_warp"))
    monkeypatch.setattr(peers, "run_solver_kamino", fake("solver_kamino"))
    args = argparse.Namespace(loads=["gentle", "rl"], worlds=[4], graph_steps=2, warmup=1, replays=1, repeats=1,
                              closure_steps=5, kamino_variants=["dvi"], mjw_sweep=["timeconst=0.02,0.004", "dt=0.001"])
    records = []
    throughput.run_peers("fourbar", args, records.append)
    mjw = [(kw["load"], kw["timeconst"], kw["timestep"]) for name, _, kw in calls if name == "mujoco_warp"]
    assert mjw == [("gentle", 0.02, 0.001), ("gentle", 0.004, 0.001), ("rl", 0.02, 0.001), ("rl", 0.004, 0.001)]
    assert all(kw["kamino_model"].body_names == kamino.load_mjcf(scene_path("fourbar")).body_names
               for name, _, kw in calls if name == "mujoco_warp")
    assert [kw.get("variant") for name, _, kw in calls if name == "solver_kamino"] == ["dvi"]
    assert len(records) == 5 and all(r["scene"] == "fourbar" for r in records)
    with pytest.raises(ValueError, match="KEY one of timeconst, dt, iterations, tolerance"):
        throughput.mjw_sweep(["solref=0.02"])


def test_accuracy_settings_set_the_model_and_name_what_runs(peers, tmp_path):
    """``run_mujoco_warp``'s accuracy settings on the host model (ladder8, eight ``<connect>``): ``timeconst``
    sets the ``<connect>`` rows' ``solref`` time constant, and MuJoCo's effective constant is
    ``max(timeconst, 2 timestep)`` (refsafe); ``timestep``, ``iterations`` and ``tolerance`` set ``opt``; without
    settings the file's values stay but the benchmark's time step."""
    path = str(scene_path("ladder8"))
    mjm = mujoco.MjModel.from_xml_path(path)
    connect = np.asarray(mjm.eq_type) == int(mujoco.mjtEq.mjEQ_CONNECT)
    assert connect.sum() == 8
    file_tc, file_iterations = float(mjm.eq_solref[connect, 0][0]), int(mjm.opt.iterations)
    used = peers._mjw_settings(mjm)
    assert used == {"timestep": peers.DT, "iterations": file_iterations, "tolerance": float(mjm.opt.tolerance),
                    "timeconst": file_tc, "timeconst_effective": max(file_tc, 2 * peers.DT)}
    used = peers._mjw_settings(mjm, timeconst=0.001, timestep=0.002, iterations=7, tolerance=1e-6)
    assert np.all(mjm.eq_solref[connect, 0] == 0.001) and mjm.opt.timestep == 0.002
    assert mjm.opt.iterations == 7 and mjm.opt.tolerance == 1e-6
    assert used["timeconst"] == 0.001 and used["timeconst_effective"] == 0.004  # 2 x 0.002 s
    used = peers._mjw_settings(mujoco.MjModel.from_xml_path(path), timeconst=0.02, timestep=0.001)
    assert used["timeconst_effective"] == 0.02
    with pytest.raises(ValueError, match="timeconst must be > 0"):
        peers._mjw_settings(mjm, timeconst=0.0)
