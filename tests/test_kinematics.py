"""Joint residuals, Jacobians and coordinates of every joint type (docs/formulation.md §2, §11.1)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import kamino
from kamino.hostmath import quat_from_axis_angle, quat_mul
from kamino.jax_ref.jacobians import constraint_jacobian, constraint_residual, dof_jacobian, joint_frames
from kamino.jax_ref.types import layout_of
from kamino.spatial import integrate_pose

JT = kamino.JointType


def _two_bodies(jtype: JT, unary: bool, seed: int) -> kamino.Model:
    """A random body pair (or a body on the world) joined by ``jtype`` at a random anchor and axis."""
    rng = np.random.default_rng(seed)
    b = kamino.ModelBuilder()
    bodies = []
    for k in range(2):
        q = rng.normal(size=4)
        bodies.append(b.add_body(mass=rng.uniform(0.5, 2), inertia=np.diag(rng.uniform(0.5, 1.0, 3)) * 0.1,
                                 pos=rng.normal(size=3), quat=q / np.linalg.norm(q), name=f"b{k}"))
    axis = rng.normal(size=3)
    axis2 = np.cross(axis, rng.normal(size=3))
    b.add_joint_at(jtype, -1 if unary else bodies[0], bodies[1], anchor=rng.normal(size=3), axis=axis,
                   axis2=axis2 if jtype == JT.UNIVERSAL else None, name="j")
    return b.finalize()


def _world(model):
    lay = layout_of(model, jnp.float64)
    return jax.tree.map(lambda x: x[0], lay.padded)


@pytest.mark.parametrize("unary", [False, True])
@pytest.mark.parametrize("jtype", [t for t in JT if t != JT.FREE])
def test_jacobian_matches_residual_rate(jtype, unary):
    """J u equals the central difference of the residual along u at e = 0 (docs/formulation.md §11.1)."""
    model = _two_bodies(jtype, unary, seed=int(jtype) + 10 * unary)
    pm = _world(model)
    q = jnp.asarray(model.body_q0)
    res = lambda x: constraint_residual(pm, joint_frames(pm, x))  # noqa: E731
    assert float(jnp.abs(res(q)).max()) < 1e-12  # add_joint_at builds a consistent joint
    u = jnp.asarray(np.random.default_rng(3).normal(size=(2, 6)))
    eps = 1e-6
    fd = (res(integrate_pose(q, u, eps)) - res(integrate_pose(q, u, -eps))) / (2 * eps)
    J = constraint_jacobian(pm, joint_frames(pm, q), 2)
    # central differences: O(eps^2 |u|^3) truncation plus O(1e-16 / eps) rounding ~ 1e-9
    np.testing.assert_allclose(np.asarray(J @ u.reshape(-1)), np.asarray(fd), atol=1e-8)


@pytest.mark.parametrize("jtype", [JT.REVOLUTE, JT.PRISMATIC, JT.CYLINDRICAL, JT.UNIVERSAL, JT.CARTESIAN])
def test_joint_coordinate_rates_match_dof_jacobian(jtype):
    """d/dt of the joint coordinates equals J_dofs u for 1-3 DoF joints (docs/formulation.md §2.4-2.5)."""
    model = _two_bodies(jtype, False, seed=7)
    pm = _world(model)
    state = kamino.init_state(model)
    q = jnp.asarray(model.body_q0)
    u = jnp.asarray(np.random.default_rng(5).normal(size=(2, 6)))
    # move along the joint's own DoFs so the constraint stays satisfied, then compare rates there
    Jd = dof_jacobian(pm, joint_frames(pm, q), 2)
    ndof = model.num_dofs
    coords = lambda x: kamino.joint_positions(model, state.replace(body_q=x))[:ndof]  # noqa: E731
    eps = 1e-6
    fd = (coords(integrate_pose(q, u, eps)) - coords(integrate_pose(q, u, -eps))) / (2 * eps)
    np.testing.assert_allclose(np.asarray(Jd @ u.reshape(-1)), np.asarray(fd), atol=1e-7)  # FD error


def _hinge() -> kamino.Model:
    """Two unit bodies 1 m apart along x, joined by a hinge about z at their midpoint (0.5, 0, 0)."""
    b = kamino.ModelBuilder()
    p = b.add_body(mass=1.0, inertia=np.eye(3), name="p")
    c = b.add_body(mass=1.0, inertia=np.eye(3), pos=(1, 0, 0), name="c")
    b.add_joint_at(JT.REVOLUTE, p, c, anchor=(0.5, 0, 0), axis=(0, 0, 1), name="hinge")
    return b.finalize()


def test_revolute_angle_reads_back():
    """Rotating the child about the hinge axis by a known angle reads back that angle."""
    model = _hinge()
    state = kamino.init_state(model)
    for angle in (-2.5, -0.3, 0.0, 1.1, 3.0):
        rot = quat_from_axis_angle((0, 0, 1), angle)
        pos = np.array([0.5, 0, 0]) + np.array([np.cos(angle), np.sin(angle), 0]) * 0.5
        q = np.array(model.body_q0)
        q[1] = np.concatenate([pos, quat_mul(rot, q[1, 3:])])
        s = state.replace(body_q=jnp.asarray(q))
        assert abs(float(kamino.joint_positions(model, s)[0]) - angle) < 1e-12
        assert float(kamino.metrics(model, s)["constraint_violation"][0]) < 1e-12


def test_anchor_gap_reads_the_anchors_apart_and_not_a_tilt():
    """``metrics()["anchor_gap"]`` is the largest translational residual [m]: moving the child of a hinge 0.5 mm
    along the axis opens its anchors by exactly that, and tilting it by 1 mrad about its anchor opens the hinge's
    rotational rows (``constraint_violation``, 1e-3 rad to first order) but no anchor gap (the anchor stays put)."""
    model = _hinge()
    state = kamino.init_state(model)
    q = np.array(model.body_q0)
    q[1, 2] += 5e-4
    shifted = kamino.metrics(model, state.replace(body_q=jnp.asarray(q)))
    assert abs(float(shifted["anchor_gap"][0]) - 5e-4) < 1e-15
    assert float(shifted["constraint_violation"][0]) >= float(shifted["anchor_gap"][0])
    tilt = 1e-3
    q = np.array(model.body_q0)
    q[1, :3] = np.array([0.5, 0, 0]) + np.array([0.5, 0, 0])  # about the x axis through the anchor: x stays
    q[1, 3:] = quat_mul(quat_from_axis_angle((1, 0, 0), tilt), q[1, 3:])
    tilted = kamino.metrics(model, state.replace(body_q=jnp.asarray(q)))
    assert float(tilted["anchor_gap"][0]) < 1e-15
    assert abs(float(tilted["constraint_violation"][0]) - tilt) < tilt**2


def test_quaternion_products_round_as_the_written_out_formulas():
    """``kamino.spatial.quat_mul`` and ``quat_to_matrix`` (one outer product and a gather) evaluate exactly the
    operations of the formulas written out term by term (``kamino.hostmath``, NumPy, the same left-to-right sums):
    bit for bit in float64, eagerly (no XLA fusion that could contract a product and a sum), on unit and non-unit
    quaternions, signed zeros included, batched and broadcast. A wrong index, sign or order of a sum shows."""
    from kamino import hostmath, spatial

    rng = np.random.default_rng(7)
    a = rng.normal(size=(64, 4))
    a[:32] /= np.linalg.norm(a[:32], axis=1, keepdims=True)
    a[:4] = [[0.0, 0.0, 0.0, 1.0], [1.0, 0.0, 0.0, 0.0], [0.0, -0.0, 0.0, -1.0], [0.5, 0.5, 0.5, 0.5]]
    b = rng.normal(size=(64, 4))
    R = np.asarray(spatial.quat_to_matrix(jnp.asarray(a)))
    np.testing.assert_array_equal(R, np.stack([hostmath.quat_to_matrix(q) for q in a]))
    ab = np.asarray(spatial.quat_mul(jnp.asarray(a), jnp.asarray(b)))
    np.testing.assert_array_equal(ab, np.stack([hostmath.quat_mul(p, q) for p, q in zip(a, b, strict=True)]))
    # one quaternion against a batch, and an outer broadcast [64, 1] x [1, 5]
    np.testing.assert_array_equal(np.asarray(spatial.quat_mul(jnp.asarray(a[5]), jnp.asarray(b))),
                                  np.stack([hostmath.quat_mul(a[5], q) for q in b]))
    outer = np.asarray(spatial.quat_mul(jnp.asarray(a[:, None]), jnp.asarray(b[None, :5])))
    assert outer.shape == (64, 5, 4)
    np.testing.assert_array_equal(outer[9, 3], hostmath.quat_mul(a[9], b[3]))
