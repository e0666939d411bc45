"""Forward kinematics for resets (docs/formulation.md §9): loop closure from actuated coordinates, exact
round trips of full coordinates for every joint type, base placement, flags for unreachable targets."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import kamino
from kamino import JointType as JT
from kamino.models.shapes import box_inertia
from tests.helpers import trajectory_joint_positions

TOL = 1e-6  # the convergence criterion: max |constraint residual| (m or rad)


def _state(model, body_q):
    return kamino.init_state(model).replace(body_q=jnp.asarray(body_q))


def test_fourbar_closes_from_actuated_angle_on_the_reference_branch():
    """The crank angle is reached exactly, the loop closes, and the solution is the continuation of
    the reference assembly: sweeping the crank in small steps (each FK starting from the last pose)
    reaches the same poses as one FK from the reference pose with sub-targets."""
    model = kamino.models.fourbar(actuated=True)
    for angle in (0.3, -0.5, 1.0):
        fk = kamino.forward_kinematics(model, actuated_positions=[angle])
        assert bool(fk.converged[0]) and float(fk.residual[0]) < 1e-9
        st = _state(model, fk.body_q)
        assert float(kamino.metrics(model, st)["constraint_violation"][0]) < 1e-9
        np.testing.assert_allclose(np.asarray(kamino.joint_positions(model, st))[0], angle, atol=1e-9)
        q = jnp.asarray(model.body_q0)
        for a in np.linspace(0.0, angle, 41)[1:]:
            step = kamino.forward_kinematics(model, actuated_positions=[a], initial_body_q=q)
            q = step.body_q
        np.testing.assert_allclose(np.asarray(q), np.asarray(fk.body_q), atol=1e-8)


def _all_joint_types_chain() -> kamino.Model:
    """A floating chain using every joint type once: FREE base, then SPHERICAL, UNIVERSAL, CYLINDRICAL,
    PRISMATIC, CARTESIAN, REVOLUTE, FIXED; link frames rotated off the world axes."""
    b = kamino.ModelBuilder()
    rng = np.random.default_rng(3)
    bodies, pos = [], np.zeros(3)
    for k in range(8):
        pos = pos + np.array([0.3, 0.05 * k, 0.1])
        q = rng.normal(size=4)
        bodies.append(b.add_body(1.0 + k, box_inertia(1.0 + k, (0.1, 0.2, 0.3)), pos=pos, quat=q / np.linalg.norm(q),
                                 name=f"b{k}"))
    b.add_joint_at(JT.FREE, -1, bodies[0], anchor=(0, 0, 0), name="base")
    kinds = [JT.SPHERICAL, JT.UNIVERSAL, JT.CYLINDRICAL, JT.PRISMATIC, JT.CARTESIAN, JT.REVOLUTE, JT.FIXED]
    for k, jt in enumerate(kinds):
        anchor = 0.5 * (np.asarray(b._bodies[k].pos) + np.asarray(b._bodies[k + 1].pos))
        axis = rng.normal(size=3)
        b.add_joint_at(jt, bodies[k], bodies[k + 1], anchor=anchor, axis=axis / np.linalg.norm(axis),
                       axis2=np.cross(axis, [0.3, 1, 0.2]) if jt == JT.UNIVERSAL else None, name=jt.name.lower())
    return b.finalize()


def _random_coords(model: kamino.Model, rng) -> np.ndarray:
    out = []
    for j in range(model.num_joints):
        jt = JT(int(model.joint_type[j]))
        if jt in (JT.SPHERICAL, JT.FREE):
            q = rng.normal(size=4)
            q = q / np.linalg.norm(q) * np.sign(q[3])
            out.append(np.r_[rng.uniform(-0.5, 0.5, 3), q] if jt == JT.FREE else q)
        else:
            out.append(rng.uniform(-1.2, 1.2, int(model.joint_coord_count[j])))
    return np.concatenate(out)


def test_full_coordinates_round_trip_every_joint_type():
    """FK from all coordinates, then reading the coordinates back, returns them (tree: unique poses).
    Quaternions compare up to sign. Converges from the reference pose in a few iterations."""
    model = _all_joint_types_chain()
    rng = np.random.default_rng(0)
    for _ in range(3):
        coords = _random_coords(model, rng)
        fk = kamino.forward_kinematics(model, joint_positions=coords)
        assert bool(fk.converged[0]), float(fk.residual[0])
        back = np.asarray(kamino.joint_positions(model, _state(model, fk.body_q)))
        for j in range(model.num_joints):
            s, n = int(model.joint_coord_start[j]), int(model.joint_coord_count[j])
            a, b = coords[s:s + n], back[s:s + n]
            jt = JT(int(model.joint_type[j]))
            if jt == JT.SPHERICAL:
                a, b = a * np.sign(a[3]), b * np.sign(b[3])
            if jt == JT.FREE:
                a = np.r_[a[:3], a[3:] * np.sign(a[6])]
                b = np.r_[b[:3], b[3:] * np.sign(b[6])]
            np.testing.assert_allclose(b, a, atol=1e-8, err_msg=jt.name)


def test_base_pose_places_a_floating_robot():
    model = _all_joint_types_chain()
    target = np.r_[1.0, -2.0, 0.7, np.array([0.2, -0.1, 0.4, 0.9]) / np.linalg.norm([0.2, -0.1, 0.4, 0.9])]
    fk = kamino.forward_kinematics(model, base_pose=target)
    assert bool(fk.converged[0])
    q = np.asarray(fk.body_q)
    np.testing.assert_allclose(q[0, :3], target[:3], atol=1e-9)
    assert abs(abs(q[0, 3:] @ target[3:]) - 1.0) < 1e-12
    # passive joints keep the reference coordinates: the whole robot moved rigidly
    ref = np.asarray(kamino.joint_positions(model, kamino.init_state(model)))
    got = np.asarray(kamino.joint_positions(model, _state(model, q)))
    np.testing.assert_allclose(got[7:], ref[7:], atol=1e-9)
    with pytest.raises(ValueError, match="no floating base"):
        kamino.forward_kinematics(kamino.models.fourbar(), base_pose=target)


def test_unreachable_target_is_flagged_and_finite():
    """Inconsistent loop coordinates (the four-bar's joints set independently) cannot all hold: the
    world is flagged, the poses are the least-squares compromise, finite; other worlds unaffected."""
    fourbar = kamino.models.fourbar(actuated=True)
    model = kamino.replicate(fourbar, 2)
    good = np.asarray(kamino.joint_positions(fourbar, kamino.init_state(fourbar)))
    bad = good + np.array([0.0, 0.4, -0.3, 0.5])
    fk = kamino.forward_kinematics(model, joint_positions=np.r_[good, bad])
    assert np.asarray(fk.converged).tolist() == [True, False]
    assert float(fk.residual[1]) > 1e-3 and np.all(np.isfinite(np.asarray(fk.body_q)))
    with pytest.raises(ValueError, match="did not converge in worlds \\[1\\]"):
        kamino.init_state(model, joint_positions=np.r_[good, bad])
    with pytest.raises(ValueError, match="NaN"):
        kamino.forward_kinematics(fourbar, actuated_positions=[np.nan])
    with pytest.raises(ValueError, match="actuated_positions has shape"):
        kamino.forward_kinematics(fourbar, actuated_positions=[0.1, 0.2])


def test_heterogeneous_batch_under_jit_matches_single_worlds():
    """One batched, jitted FK over different robots gives each world its standalone answer."""
    fourbar = kamino.models.fourbar(actuated=True)
    parts = [fourbar, kamino.models.chain_of_loops(3), fourbar]
    model = kamino.concat(parts)
    targets = jnp.asarray([0.4, -0.7])
    fk = jax.jit(lambda a: kamino.forward_kinematics(model, actuated_positions=a))(targets)
    assert np.all(np.asarray(fk.converged))
    starts = model.world_body_start
    for w, (part, a) in enumerate(zip(parts, [[0.4], [], [-0.7]], strict=True)):
        single = kamino.forward_kinematics(part, actuated_positions=a)
        n = part.num_bodies
        np.testing.assert_allclose(np.asarray(fk.body_q)[starts[w]:starts[w] + n], np.asarray(single.body_q),
                                   atol=1e-10)


def test_coupled_joint_follows_actuated_joint():
    """A passive hinge coupled to an actuated one (q_a = 0.1 + 1.5 q_b - 0.4 q_b^2) gets its coupled
    angle from FK; simulating afterwards keeps the coupling within 1e-6 (the issue's mimic bound)."""
    b = kamino.ModelBuilder()
    la = b.add_body(1.0, box_inertia(1.0, (0.05, 0.05, 1.0)), pos=(0, 0, 0.5), name="a")
    lb = b.add_body(1.0, box_inertia(1.0, (0.05, 0.05, 1.0)), pos=(1, 0, 0.5), name="b")
    ja = b.add_joint_at(JT.REVOLUTE, -1, la, anchor=(0, 0, 1), axis=(0, 1, 0), name="follower")
    jb = b.add_joint_at(JT.REVOLUTE, -1, lb, anchor=(1, 0, 1), axis=(0, 1, 0), name="driver",
                        actuation=kamino.Actuation("position", kp=400.0, kd=20.0))
    b.add_coupling(ja, jb, (0.1, 1.5, -0.4), name="mimic")
    model = b.finalize()
    poly = lambda x: 0.1 + 1.5 * x - 0.4 * x * x  # noqa: E731
    state = kamino.init_state(model, actuated_positions=[0.6])
    q = np.asarray(kamino.joint_positions(model, state))
    np.testing.assert_allclose(q, [poly(0.6), 0.6], atol=1e-9)
    t = np.arange(1, 481) / 240.0
    target = 0.6 * np.cos(np.pi * t)  # a smooth 0.5 Hz swing of the driver through -0.6..0.6 rad
    ctrl = kamino.Control.from_ctrl(model, jnp.asarray(target)[:, None])
    traj = kamino.rollout(model, state, ctrl, config=kamino.SolverConfig(dt=1 / 240, tolerance=1e-10), backend="warp")
    qs = trajectory_joint_positions(model, state, traj)
    assert np.max(np.abs(qs[:, 0] - poly(qs[:, 1]))) < 1e-6
    assert np.max(np.abs(qs[:, 1] - target)) < 0.1  # the driver tracks: the coupling did not lock it
    assert np.all(np.isfinite(np.asarray(traj.coupling_force)))


def test_set_joint_positions_resets_velocities_and_keeps_time():
    model = kamino.models.fourbar(actuated=True)
    state = kamino.init_state(model)
    state = kamino.rollout(model, state, num_steps=10, backend="warp")
    state = jax.tree_util.tree_map(lambda x: x[-1], state)
    reset = kamino.set_joint_positions(model, state, actuated_positions=[0.25])
    assert float(jnp.abs(reset.body_u).max()) == 0.0 and float(reset.time[0]) == float(state.time[0])
    assert abs(float(kamino.joint_positions(model, reset)[0]) - 0.25) < 1e-9
    assert float(kamino.metrics(model, reset)["constraint_violation"][0]) < TOL
