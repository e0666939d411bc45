"""Loop-aware inverse kinematics (``kamino.inverse_kinematics``, docs/formulation.md §9 "Inverse kinematics"): dr_legs
foot targets drawn by forward kinematics are solved with the loops closed; a four-bar's coupler point against the
closed-form circle geometry; an unreachable target is reported with the closure still held; jit and vmap.

The tolerances: 1e-6 is the solver's ``tolerance`` on max |closure residual| [m or rad] and on each target's error
[m, rad]; closed-form comparisons allow 1e-5 m, the position error a 1e-6 residual on the loop's rows can cause over
the four-bar's 0.2-0.3 m links (a few times the residual)."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import kamino
from kamino.bench.ik_convergence import FEET, foot_targets
from kamino.envs.geometry import sole_offsets, support_points
from kamino.hostmath import quat_to_matrix
from kamino.spatial import rotate

jax.config.update("jax_enable_x64", True)


def test_sole_offsets_put_the_sole_point_under_the_foot():
    """``sole_offsets``: at the reference pose each dr_legs foot's sole point is as low as the foot's lowest support
    point (1e-9 m: rounding) and inside the footprint of its support points (x and y within their range)."""
    robot = kamino.models.dr_legs()
    pts, owner, _ = support_points(robot)
    for name, offset in zip(FEET, sole_offsets(robot, FEET), strict=True):
        b = robot.body_index(name)
        R = quat_to_matrix(np.asarray(robot.body_q0[b, 3:], float))
        world = robot.body_q0[b, :3] + pts[owner == b] @ R.T
        sole = robot.body_q0[b, :3] + R @ offset
        assert abs(sole[2] - world[:, 2].min()) <= 1e-9
        assert np.all(sole[:2] >= world[:, :2].min(0)) and np.all(sole[:2] <= world[:, :2].max(0))


def _closure(model, body_q) -> np.ndarray:
    state = kamino.init_state(model, dtype=jnp.float64).replace(body_q=jnp.asarray(body_q))
    return np.asarray(kamino.metrics(model, state)["constraint_violation"])


def test_dr_legs_foot_poses_from_forward_kinematics_are_reached():
    """Both feet's contact points and orientations (12 rows for the 12 actuated DoFs, pelvis pinned) at 16 random
    reachable targets: every world converges (``kamino bench ik_convergence`` runs 1000: docs/formulation.md §9)."""
    model, pos, rot, offsets, base, _ = foot_targets(16, seed=5)
    ik = kamino.inverse_kinematics(model, FEET, pos, rot, offsets=offsets, base_pose=base, dtype=jnp.float64)
    converged = np.asarray(ik.converged)
    assert converged.all(), np.asarray(ik.target_error)[~converged]
    assert np.all(np.asarray(ik.closure_error) <= 1e-6) and np.all(np.asarray(ik.target_error) <= 1e-6)
    # the poses are what the result claims: the simulator's own constraint metric and the targets
    assert np.all(_closure(model, ik.body_q) <= 1e-6)
    bq = np.asarray(ik.body_q).reshape(16, -1, 7)[:, [model.body_index(f) for f in FEET]]
    reached = bq[..., :3] + np.asarray(rotate(jnp.asarray(bq[..., 3:]),
                                              jnp.asarray(np.broadcast_to(offsets, pos.shape))))
    assert np.max(np.linalg.norm(reached - pos, axis=-1)) <= 1e-6
    assert np.all(np.asarray(ik.within_limits))


def test_dr_legs_foot_positions_with_a_free_base():
    """Positions only, the pelvis free: 6 target rows for 18 DoFs; the remaining freedom stays near the start (the
    damping). 7 of these 8 worlds converge; the eighth ends at a joint limit with its loops open (closure 1.3e-2
    after 100 iterations, the active set and the merit trading one against the other) and says so: the flags are
    what the simulator's own constraint metric measures."""
    model, pos, _, offsets, _, _ = foot_targets(8, seed=6)
    ik = kamino.inverse_kinematics(model, FEET, pos, offsets=offsets, dtype=jnp.float64)
    converged = np.asarray(ik.converged)
    assert converged.sum() >= 7, np.asarray(ik.target_error)
    viol = _closure(model, ik.body_q)
    assert np.all(viol[converged] <= 1e-6)
    np.testing.assert_allclose(np.asarray(ik.closure_error), viol, rtol=1e-6, atol=1e-12)


def _fourbar_coupler_point(model):
    """The coupler-rocker joint's point ``C`` in the coupler's CoM frame, and the rocker's pivot ``D`` (world)."""
    co = model.body_index("coupler")
    q_co = np.asarray(model.body_q0[co], float)
    # C: the end of the coupler shared with the rocker; from the builder's geometry (fourbar defaults)
    A = np.array([0.0, 0.0, 1.0])
    D = A + np.array([0.3, 0.0, 0.0])
    B = A + 0.18 * np.array([np.cos(-1.2), 0.0, np.sin(-1.2)])
    C = 2.0 * q_co[:3] - B  # the coupler's CoM is its midpoint
    assert np.isclose(np.linalg.norm(C - D), 0.24) and np.isclose(np.linalg.norm(C - B), 0.26)
    offset = quat_to_matrix(q_co[3:]).T @ (C - q_co[:3])
    return offset, A, D


@pytest.mark.parametrize("psi", [1.4, 1.9, 2.6])
def test_fourbar_coupler_point_on_the_rocker_circle(psi):
    """Target the coupler point at ``D + 0.24 (cos psi, 0, sin psi)`` on the rocker's circle: the crank pin ``B``
    that IK finds is one of the two closed-form intersections of ``|B - A| = 0.18`` and ``|B - C*| = 0.26``. The
    crank-rocker reaches ``0.08 <= |C - A| <= 0.44``, i.e. ``1.25 <= psi <= 2.94`` rad."""
    model = kamino.models.fourbar()
    offset, A, D = _fourbar_coupler_point(model)
    target = D + 0.24 * np.array([np.cos(psi), 0.0, np.sin(psi)])
    ik = kamino.inverse_kinematics(model, ["coupler"], target[None], offsets=offset[None], dtype=jnp.float64)
    assert bool(ik.converged[0]) and float(ik.closure_error[0]) <= 1e-6
    q_cr = np.asarray(ik.body_q)[model.body_index("crank")]
    B = 2.0 * q_cr[:3] - A  # the crank's CoM is its midpoint
    # closed form: circle-circle intersection in the xz plane
    d = np.linalg.norm(target - A)
    a = (0.18**2 - 0.26**2 + d**2) / (2 * d)
    h = np.sqrt(0.18**2 - a**2)
    e = (target - A) / d
    n = np.array([-e[2], 0.0, e[0]])
    candidates = [A + a * e + h * n, A + a * e - h * n]
    assert min(np.linalg.norm(B - c) for c in candidates) <= 1e-5


def test_unreachable_target_is_reported_with_the_loop_closed():
    """A coupler-point target 0.5 m above the rocker's pivot lies off the rocker's circle: IK reports it unconverged
    with the closure held and the residual of the closest point of the circle, ``0.5 - 0.24 = 0.26`` m."""
    model = kamino.models.fourbar()
    offset, _, D = _fourbar_coupler_point(model)
    ik = kamino.inverse_kinematics(model, ["coupler"], (D + np.array([0.0, 0.0, 0.5]))[None], offsets=offset[None],
                                   dtype=jnp.float64)
    assert not bool(ik.converged[0])
    assert float(ik.closure_error[0]) <= 1e-6
    assert abs(float(ik.target_error[0]) - 0.26) <= 1e-5
    assert np.all(np.isfinite(np.asarray(ik.body_q)))


def test_jit_and_vmap_match_the_batched_call():
    """``inverse_kinematics`` under ``jax.jit`` and under ``jax.vmap`` over target sets gives the poses of the
    batched (replicated-model) call to rounding (1e-9: the same iteration, compiled in another program)."""
    model = kamino.models.fourbar()
    offset, _, D = _fourbar_coupler_point(model)
    psis = np.array([1.6, 2.2])
    targets = D + 0.24 * np.stack([np.cos(psis), np.zeros(2), np.sin(psis)], -1)

    def solve(t):
        return kamino.inverse_kinematics(model, ["coupler"], t[None], offsets=offset[None], dtype=jnp.float64)

    jitted = jax.jit(lambda t: solve(t).body_q)(jnp.asarray(targets[0]))
    mapped = jax.vmap(lambda t: solve(t).body_q)(jnp.asarray(targets))
    two = kamino.replicate(model, 2)
    batched = kamino.inverse_kinematics(two, ["coupler"], targets[:, None], offsets=offset[None], dtype=jnp.float64)
    assert np.all(np.asarray(batched.converged))
    ref = np.asarray(batched.body_q).reshape(2, model.num_bodies, 7)
    np.testing.assert_allclose(np.asarray(jitted), ref[0], atol=1e-9)
    np.testing.assert_allclose(np.asarray(mapped), ref, atol=1e-9)


def _retarget_example():
    path = Path(__file__).resolve().parents[1] / "examples" / "retarget_dr_legs.py"
    spec = importlib.util.spec_from_file_location("retarget_dr_legs_example", path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    return module


def test_retargeted_gait_replays_in_the_simulator():
    """examples/retarget_dr_legs.py at 8 frames of 0.1 s (a 0.8 s gait cycle: 12 cm stride, 5 cm swing height; the
    replay in steps of 10 ms, 80 steps): every frame's IK converges (closure and target error <= 1e-6), and the
    commands replayed by the PD servos (kp 300 N m/rad at the hips and knees, 150 at the ankles, the pelvis welded to
    the world, gravity on) put the sole points within 15 mm of the targets at every frame time and 6 mm on average
    (measured: 7.4 mm and 4.8 mm), with the loops closed to 1e-5 (measured 1e-8). The bound is the servos' lag and
    sag: the lifted leg's weight (about 5 kg, 0.1 m from the hip axis) bends a 300 N m/rad hip by 0.016 rad, 8 mm at
    the foot 0.5 m below; a wrong command (another actuator's, a sign, a frame late) misses by centimetres (the stride
    is 12 cm)."""
    ex = _retarget_example()
    out = ex.retarget(frames=8, frame_dt=0.1, dt=0.01)
    assert out["converged"].all(), out["ik_error"]
    assert out["ik_closure"].max() <= 1e-6 and out["ik_error"].max() <= 1e-6
    err = out["replay_error"]
    assert err.max() <= 0.015 and err.mean() <= 0.006, err
    assert out["replay_closure"].max() <= 1e-5, out["replay_closure"]
    # the replay swings the feet: its highest sole point is within the bound of the 5 cm swing
    rest = out["targets"][:, :, 2].min()
    assert abs(out["replayed"][:, :, 2].max() - rest - 0.05) <= 0.015
