"""Joint kinematics in maximal coordinates for one world (docs/formulation.md §2).

Every function here works on one world's padded arrays; ``kamino.jax_ref.pipeline`` vmaps them.
A joint connects a base ``B`` (a body or the world) to a follower ``F``; its frame is attached
to the base side and its local x axis is the (first) motion axis (§2.1).
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp

from kamino.jax_ref.types import PaddedModel
from kamino.model import DOF_FREE, DOF_TRANS, DOF_UNIV, RES_HINGE, RES_LOG, RES_TRANS, RES_UNIV, JointType
from kamino.spatial import quat_conj, quat_log, quat_mul, quat_to_matrix


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class JointFrames:
    """Per-joint world quantities of §2.1-2.3 (arrays ``[nj, ...]``)."""

    r_B: jax.Array  # base CoM (zero for the world)
    r_F: jax.Array  # follower CoM
    p_B: jax.Array  # base-side anchor in world (lever-arm origin of every row, §2.5)
    p_F: jax.Array  # follower-side anchor in world
    R_j: jax.Array  # joint frame rotation R_B X_B
    Q: jax.Array  # relative rotation q_Bj^-1 ⊗ q_Fj
    t: jax.Array  # relative translation in the joint frame
    has_parent: jax.Array  # bool


def joint_frames(pm: PaddedModel, body_q: jax.Array) -> JointFrames:
    """World joint frames, relative pose ``(t, Q)`` of every joint (docs/formulation.md §2.1-2.2)."""
    has_parent = pm.joint_parent >= 0
    parent = jnp.where(has_parent, pm.joint_parent, 0)
    qB = jnp.where(has_parent[:, None], body_q[parent], jnp.array([0, 0, 0, 0, 0, 0, 1.0], body_q.dtype))
    qF = body_q[pm.joint_child]
    R_B, R_F = quat_to_matrix(qB[:, 3:]), quat_to_matrix(qF[:, 3:])
    p_B = qB[:, :3] + jnp.einsum("jab,jb->ja", R_B, pm.anchor_B)
    p_F = qF[:, :3] + jnp.einsum("jab,jb->ja", R_F, pm.anchor_F)
    q_Bj = quat_mul(qB[:, 3:], pm.frame_B)
    q_Fj = quat_mul(qF[:, 3:], pm.frame_F)
    R_j = quat_to_matrix(q_Bj)
    Q = quat_mul(quat_conj(q_Bj), q_Fj)
    t = jnp.einsum("jba,jb->ja", R_j, p_F - p_B)
    return JointFrames(r_B=qB[:, :3], r_F=qF[:, :3], p_B=p_B, p_F=p_F, R_j=R_j, Q=Q, t=t, has_parent=has_parent)


def _universal_axes(Q: jax.Array) -> jax.Array:
    """Intermediate frame ``[a_x, a_y, a_z]`` (columns, joint coordinates) of a universal joint (§2.4)."""
    R = quat_to_matrix(Q)
    y_F = R[:, :, 1]
    e_x = jnp.zeros_like(y_F).at[:, 0].set(1.0)
    a_y = y_F - y_F[:, :1] * e_x
    a_y = a_y / jnp.maximum(jnp.linalg.norm(a_y, axis=-1, keepdims=True), 1e-12)
    a_z = jnp.cross(e_x, a_y)
    return jnp.stack([e_x, a_y, a_z], axis=-1)


def joint_residuals6(jf: JointFrames) -> dict[int, jax.Array]:
    """The 6-vector residual building blocks per joint, keyed by residual kind (§2.3)."""
    R_rel = quat_to_matrix(jf.Q)
    x_F, y_F = R_rel[:, :, 0], R_rel[:, :, 1]
    e_x = jnp.zeros_like(x_F).at[:, 0].set(1.0)
    hinge = jnp.cross(e_x, x_F)
    univ = jnp.zeros_like(x_F).at[:, 2].set(-y_F[:, 0])
    return {RES_LOG: quat_log(jf.Q), RES_HINGE: hinge, RES_UNIV: univ}


def constraint_residual(pm: PaddedModel, jf: JointFrames) -> jax.Array:
    """Position-level residual ``e`` of every kinematic constraint row ``[nr]`` (§2.3-2.4).

    Translational rows read ``t``; rotational rows read the log, hinge or universal residual,
    as the row's kind says. Padded rows are zero.
    """
    res = joint_residuals6(jf)
    j, axis, kind = pm.row_joint, pm.row_axis, pm.row_kind
    rot_axis = jnp.clip(axis - 3, 0, 2)
    e = jnp.where(kind == RES_TRANS, jf.t[j, jnp.clip(axis, 0, 2)], 0.0)
    for k in (RES_LOG, RES_HINGE, RES_UNIV):
        e = jnp.where(kind == k, res[k][j, rot_axis], e)
    return jnp.where(pm.row_mask, e, 0.0)


def _row_blocks(jf: JointFrames, j, axis, is_trans, rot_dir):
    """Two 1x6 blocks (follower, base) of rows on joint ``j`` along frame ``axis`` (§2.5).

    Translational axis ``a``: ``J_F = [a, (p - r_F) x a]``, ``J_B = -[a, (p - r_B) x a]`` with
    ``p = p_B``; rotational axis ``b``: ``J_F = [0, b]``, ``J_B = [0, -b]``.
    """
    a = jf.R_j[j, :, jnp.clip(axis, 0, 2)]
    p = jf.p_B[j]
    lin_F = jnp.where(is_trans[:, None], a, 0.0)
    ang_F = jnp.where(is_trans[:, None], jnp.cross(p - jf.r_F[j], a), rot_dir)
    ang_B = jnp.where(is_trans[:, None], jnp.cross(p - jf.r_B[j], a), rot_dir)
    J_F = jnp.concatenate([lin_F, ang_F], axis=-1)
    J_B = -jnp.concatenate([lin_F, ang_B], axis=-1)
    return J_F, J_B


def _scatter_dense(pm: PaddedModel, jf: JointFrames, j, J_F, J_B, mask, nb: int) -> jax.Array:
    """Dense ``[rows, nb*6]`` Jacobian from per-row follower/base blocks (unary joints drop J_B)."""
    n = J_F.shape[0]
    rows = jnp.arange(n)
    J = jnp.zeros((n, nb, 6), J_F.dtype)
    J = J.at[rows, pm.joint_child[j]].add(jnp.where(mask[:, None], J_F, 0.0))
    has_parent = jf.has_parent[j] & mask
    J = J.at[rows, jnp.where(has_parent, pm.joint_parent[j], 0)].add(jnp.where(has_parent[:, None], J_B, 0.0))
    return J.reshape(n, nb * 6)


def constraint_jacobian(pm: PaddedModel, jf: JointFrames, nb: int) -> jax.Array:
    """Dense constraint Jacobian ``J_cts`` ``[nr, nb*6]`` in row order (§2.5, §7.1)."""
    j, axis, kind = pm.row_joint, pm.row_axis, pm.row_kind
    is_trans = kind == RES_TRANS
    rot_k = jnp.clip(axis - 3, 0, 2)
    b_std = jf.R_j[j, :, rot_k]
    U = jnp.einsum("jab,jbc->jac", jf.R_j, _universal_axes(jf.Q))  # world universal axes
    b = jnp.where((kind == RES_UNIV)[:, None], U[j, :, rot_k], b_std)
    J_F, J_B = _row_blocks(jf, j, axis, is_trans, b)
    return _scatter_dense(pm, jf, j, J_F, J_B, pm.row_mask, nb)


def dof_jacobian(pm: PaddedModel, jf: JointFrames, nb: int) -> jax.Array:
    """Actuation (DoF) Jacobian ``J_dofs`` ``[nd, nb*6]``, one row per joint DoF (§2.5).

    FREE joints use Newton's convention: ``J_F = I_6`` (world-aligned force/torque at the child
    CoM) and ``J_B = -[[I, 0], [[r_F - r_B]x, I]]``.
    """
    j, axis, kind = pm.dof_joint, pm.dof_axis, pm.dof_kind
    is_trans = kind == DOF_TRANS
    rot_k = jnp.clip(axis - 3, 0, 2)
    U = jnp.einsum("jab,jbc->jac", jf.R_j, _universal_axes(jf.Q))
    b = jnp.where((kind == DOF_UNIV)[:, None], U[j, :, rot_k], jf.R_j[j, :, rot_k])
    J_F, J_B = _row_blocks(jf, j, axis, is_trans, b)
    # FREE: unit rows in world axes at the child CoM
    unit = jax.nn.one_hot(axis, 6, dtype=J_F.dtype)
    d = jf.r_F[j] - jf.r_B[j]
    lin_e = unit[:, :3]
    free_B = -jnp.concatenate([lin_e, jnp.cross(d, lin_e) + unit[:, 3:]], axis=-1)
    is_free = (kind == DOF_FREE)[:, None]
    J_F = jnp.where(is_free, unit, J_F)
    J_B = jnp.where(is_free, free_B, J_B)
    return _scatter_dense(pm, jf, j, J_F, J_B, pm.dof_mask, nb)


def joint_coordinates(pm: PaddedModel, jf: JointFrames) -> jax.Array:
    """All joints' coordinates packed per joint into ``[nj, 7]`` (docs/formulation.md §2.4 column "coordinates").

    Layout per type (unused trailing entries are zero): REVOLUTE ``angle``; PRISMATIC ``t_x``;
    CYLINDRICAL ``(t_x, Log(Q)_x)``; UNIVERSAL ``(theta_1, theta_2)``; SPHERICAL ``Q (x,y,z,w)``;
    CARTESIAN ``t``; FREE ``(t, Q)``. Angles are the raw values in ``[-pi, pi]``.
    """
    Q = jnp.where(jf.Q[:, 3:4] < 0, -jf.Q, jf.Q)
    t = jf.t
    angle = 2.0 * jnp.arctan2(Q[:, 0], Q[:, 3])
    R = quat_to_matrix(Q)
    x_F, y_F = R[:, :, 0], R[:, :, 1]
    th1 = jnp.arctan2(y_F[:, 2], y_F[:, 1])
    e_x = jnp.zeros_like(x_F).at[:, 0].set(1.0)
    th2 = jnp.arctan2(jnp.sum(jnp.cross(e_x, x_F) * y_F, axis=-1), x_F[:, 0])
    z = jnp.zeros_like(angle)
    T = pm.joint_type
    out = jnp.zeros((T.shape[0], 7), t.dtype)
    table = {
        JointType.REVOLUTE: jnp.stack([angle] + [z] * 6, -1),
        JointType.PRISMATIC: jnp.stack([t[:, 0]] + [z] * 6, -1),
        JointType.CYLINDRICAL: jnp.stack([t[:, 0], quat_log(Q)[:, 0]] + [z] * 5, -1),
        JointType.UNIVERSAL: jnp.stack([th1, th2] + [z] * 5, -1),
        JointType.SPHERICAL: jnp.concatenate([Q, jnp.zeros((T.shape[0], 3), t.dtype)], -1),
        JointType.CARTESIAN: jnp.concatenate([t, jnp.zeros((T.shape[0], 4), t.dtype)], -1),
        JointType.FREE: jnp.concatenate([t, Q], -1),
    }
    for jt, val in table.items():
        out = jnp.where((T == int(jt))[:, None], val, out)
    return out


def dof_positions(pm: PaddedModel, jf: JointFrames) -> jax.Array:
    """Position of every joint DoF ``[nd]`` in DoF space (docs/formulation.md §4.1 "coordinates are mapped to
    DoF space"): translations read ``t``; rotations read ``Log(Q)`` componentwise (the angle, for a
    hinge), and a UNIVERSAL joint's DoFs read its two angles ``(theta_1, theta_2)``."""
    six = jnp.concatenate([jf.t, quat_log(jf.Q)], axis=-1)  # [nj, 6]
    coords = joint_coordinates(pm, jf)
    univ = six.at[:, 3].set(coords[:, 0]).at[:, 4].set(coords[:, 1])
    six = jnp.where((pm.joint_type == int(JointType.UNIVERSAL))[:, None], univ, six)
    j = pm.dof_joint
    return jnp.where(pm.dof_mask, six[j, pm.dof_axis], 0.0)
