"""Joint kinematics in Warp: joint frames, residuals and Jacobian blocks (docs/formulation.md §2).

The same formulas as ``kamino/jax_ref/joints.py`` and ``couplings.py``. A Jacobian row is stored
block-sparse: up to ``nblk`` pairs (body, 1x6 block) per row — the follower ``F`` and the base ``B``
of its joint (§2.5); a coupling row spans the DoF rows of two joints (four blocks). A block on the
world (body ``-1``) is dropped.
"""

import functools
from types import SimpleNamespace

import warp as wp

from kamino.model import DOF_FREE, DOF_TRANS, DOF_UNIV, RES_HINGE, RES_LOG, RES_TRANS, RES_UNIV, JointType
from kamino.warp_backend.model_data import model_struct
from kamino.warp_backend.spatial import spatial_funcs
from kamino.warp_backend.types import types_of

_UNIVERSAL = int(JointType.UNIVERSAL)
_REVOLUTE = int(JointType.REVOLUTE)


@functools.cache
def kinematics_funcs(np_dtype) -> SimpleNamespace:
    T = types_of(np_dtype)
    scalar, vec3, vec6, quat, transform = T.scalar, T.vec3, T.vec6, T.quat, T.transform
    sp = spatial_funcs(np_dtype)
    quat_log, twist = sp.quat_log, sp.twist
    M = model_struct(np_dtype)

    @wp.func
    def body_pose(body_q: wp.array(dtype=transform), b: int):
        """Pose of body ``b``; the identity for the world (``b = -1``)."""
        if b < 0:
            return wp.transform_identity(dtype=scalar)
        return body_q[b]

    @wp.func
    def joint_frame(m: M, body_q: wp.array(dtype=transform), j: int):
        """World quantities of joint ``j`` (§2.1-2.2): base CoM ``r_B``, follower CoM ``r_F``, base
        anchor ``p_B``, joint rotation ``R_j = R_B X_B``, relative rotation ``Q`` and translation ``t``."""
        xB = body_pose(body_q, m.joint_parent[j])
        xF = body_q[m.joint_child[j]]
        r_B = wp.transform_get_translation(xB)
        r_F = wp.transform_get_translation(xF)
        qB = wp.transform_get_rotation(xB)
        qF = wp.transform_get_rotation(xF)
        p_B = r_B + wp.quat_rotate(qB, m.anchor_B[j])
        p_F = r_F + wp.quat_rotate(qF, m.anchor_F[j])
        q_Bj = qB * m.frame_B[j]
        q_Fj = qF * m.frame_F[j]
        R_j = wp.quat_to_matrix(q_Bj)
        Q = wp.quat_inverse(q_Bj) * q_Fj
        t = wp.transpose(R_j) * (p_F - p_B)
        return r_B, r_F, p_B, R_j, Q, t

    @wp.func
    def universal_axes(Q: quat):
        """Intermediate frame ``[e_x, a_y, a_z]`` (columns, joint coordinates) of a universal joint (§2.4)."""
        R = wp.quat_to_matrix(Q)
        y_F = vec3(R[0, 1], R[1, 1], R[2, 1])
        e_x = vec3(scalar(1.0), scalar(0.0), scalar(0.0))
        a_y = y_F - y_F[0] * e_x
        a_y = a_y / wp.max(wp.length(a_y), scalar(1e-12))
        a_z = wp.cross(e_x, a_y)
        return wp.matrix_from_cols(e_x, a_y, a_z)

    @wp.func
    def residual(kind: int, axis: int, Q: quat, t: vec3):
        """Position residual of one kinematic row (§2.3): ``t``, ``Log(Q)``, hinge or universal."""
        if kind == RES_TRANS:
            return t[axis]
        k = axis - 3
        if kind == RES_LOG:
            return quat_log(Q)[k]
        R = wp.quat_to_matrix(Q)
        if kind == RES_HINGE:
            hinge = vec3(scalar(0.0), -R[2, 0], R[1, 0])  # e_x x x_F
            return hinge[k]
        univ = vec3(scalar(0.0), scalar(0.0), -R[0, 1])  # RES_UNIV
        return univ[k]

    @wp.func
    def axis_blocks(is_trans: int, a: vec3, p: vec3, r_F: vec3, r_B: vec3):
        """Follower and base 1x6 blocks of a row along world axis ``a`` (§2.5): translational
        ``J_F = [a, (p - r_F) x a]``, ``J_B = -[a, (p - r_B) x a]``; rotational ``J_F = [0, a] = -J_B``."""
        if is_trans != 0:
            return twist(a, wp.cross(p - r_F, a)), -twist(a, wp.cross(p - r_B, a))
        z = vec3(scalar(0.0), scalar(0.0), scalar(0.0))
        return twist(z, a), -twist(z, a)

    @wp.func
    def cts_row(m: M, body_q: wp.array(dtype=transform), c: int):
        """Residual and (follower, base) blocks of kinematic row ``c`` (``constraint_residual`` /
        ``constraint_jacobian`` of the JAX reference)."""
        j = m.cts_joint[c]
        axis = m.cts_axis[c]
        kind = m.cts_kind[c]
        r_B, r_F, p_B, R_j, Q, t = joint_frame(m, body_q, j)
        e = residual(kind, axis, Q, t)
        is_trans = int(kind == RES_TRANS)
        a = vec3()
        if is_trans != 0:
            a = vec3(R_j[0, axis], R_j[1, axis], R_j[2, axis])
        else:
            k = axis - 3
            if kind == RES_UNIV:
                U = R_j * universal_axes(Q)
                a = vec3(U[0, k], U[1, k], U[2, k])
            else:
                a = vec3(R_j[0, k], R_j[1, k], R_j[2, k])
        JF, JB = axis_blocks(is_trans, a, p_B, r_F, r_B)
        return e, JF, JB

    @wp.func
    def cts_residual(m: M, body_q: wp.array(dtype=transform), c: int):
        j = m.cts_joint[c]
        r_B, r_F, p_B, R_j, Q, t = joint_frame(m, body_q, j)
        return residual(m.cts_kind[c], m.cts_axis[c], Q, t)

    @wp.func
    def dof_position(m: M, body_q: wp.array(dtype=transform), d: int):
        """Position of DoF ``d`` in DoF space (``dof_positions`` of the JAX reference): ``t`` or ``Log(Q)``
        components, a universal joint's two angles ``(theta_1, theta_2)``."""
        j = m.dof_joint[d]
        axis = m.dof_axis[d]
        r_B, r_F, p_B, R_j, Q, t = joint_frame(m, body_q, j)
        if axis < 3:
            return t[axis]
        if m.joint_type[j] == _UNIVERSAL:
            R = wp.quat_to_matrix(Q)
            x_F = vec3(R[0, 0], R[1, 0], R[2, 0])
            y_F = vec3(R[0, 1], R[1, 1], R[2, 1])
            if axis == 3:
                return wp.atan2(y_F[2], y_F[1])
            e_x = vec3(scalar(1.0), scalar(0.0), scalar(0.0))
            return wp.atan2(wp.dot(wp.cross(e_x, x_F), y_F), x_F[0])
        return quat_log(Q)[axis - 3]

    @wp.func
    def dof_blocks(m: M, body_q: wp.array(dtype=transform), d: int):
        """(follower, base) blocks of DoF row ``d`` of ``J_dofs`` (§2.5). FREE joints: ``J_F = I_6`` rows and
        ``J_B = -[[I, 0], [[r_F - r_B]x, I]]`` rows (Newton's convention, as the JAX reference)."""
        j = m.dof_joint[d]
        axis = m.dof_axis[d]
        kind = m.dof_kind[d]
        r_B, r_F, p_B, R_j, Q, t = joint_frame(m, body_q, j)
        if kind == DOF_FREE:
            JF = vec6()
            JF[axis] = scalar(1.0)
            e_lin = vec3()
            e_ang = vec3()
            if axis < 3:
                e_lin[axis] = scalar(1.0)
            else:
                e_ang[axis - 3] = scalar(1.0)
            return JF, -twist(e_lin, wp.cross(r_F - r_B, e_lin) + e_ang)
        is_trans = int(kind == DOF_TRANS)
        a = vec3()
        if is_trans != 0:
            a = vec3(R_j[0, axis], R_j[1, axis], R_j[2, axis])
        else:
            k = axis - 3
            if kind == DOF_UNIV:
                U = R_j * universal_axes(Q)
                a = vec3(U[0, k], U[1, k], U[2, k])
            else:
                a = vec3(R_j[0, k], R_j[1, k], R_j[2, k])
        return axis_blocks(is_trans, a, p_B, r_F, r_B)

    @wp.func
    def poly(m: M, k: int, x: scalar):
        """``p(x)`` and ``p'(x)`` of coupling ``k``'s quartic (Horner)."""
        p = scalar(0.0)
        dp = scalar(0.0)
        for i in range(5):
            c = m.cpl_coef[k, 4 - i]
            dp = dp * x + p
            p = p * x + c
        return p, dp

    @wp.func
    def coupling_residual(m: M, k: int, q_a: scalar, q_b: scalar):
        """``q_a - p(q_b)`` (wrapped to ``[-pi, pi]`` for a hinge) and ``p'(q_b)`` (docs/conventions.md "Couplings")."""
        has_b = m.cpl_dof_b[k] >= 0
        qb = scalar(0.0)
        if has_b:
            qb = q_b
        p, dp = poly(m, k, qb)
        e = q_a - p
        if m.cpl_wrap[k] != 0:
            two_pi = scalar(2.0 * 3.141592653589793)
            s = e + scalar(3.141592653589793)
            e = s - two_pi * wp.floor(s / two_pi) - scalar(3.141592653589793)
        if not has_b:
            dp = scalar(0.0)
        return e, dp

    return SimpleNamespace(body_pose=body_pose, joint_frame=joint_frame, cts_row=cts_row, cts_residual=cts_residual,
                           dof_position=dof_position, dof_blocks=dof_blocks, coupling_residual=coupling_residual,
                           universal_axes=universal_axes)
