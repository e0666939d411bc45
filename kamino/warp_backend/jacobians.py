"""Joint Jacobians in Warp: joint frames, residuals and the Jacobian blocks of DoF and constraint rows
(docs/formulation.md §2).

The same formulas as ``kamino/jax_ref/jacobians.py`` and ``couplings.py``. A Jacobian row is stored
block-sparse: up to ``nblk`` pairs (body, 1x6 block) per row — the follower ``F`` and the base ``B``
of its joint (§2.5); a coupling row spans the DoF rows of two joints (four blocks). A block on the
world (body ``-1``) is dropped.

Each ``wp.func`` comes from its own builder, cached per precision (``np_dtype``).
"""

import functools

import warp as wp

from kamino.model import DOF_FREE, DOF_TRANS, DOF_UNIV, RES_HINGE, RES_LOG, RES_TRANS, RES_UNIV, JointType
from kamino.warp_backend.spatial import spatial_funcs
from kamino.warp_backend.workspace import builder_types

_UNIVERSAL = int(JointType.UNIVERSAL)


# --- joint frames (§2.1-2.4) ---------------------------------------------------------------------------------------

@functools.cache
def body_pose_func(np_dtype):
    """``body_pose(body_q, b)``: the pose of body ``b``, the identity for the world (§2.1)."""
    transform, scalar = builder_types(np_dtype).take("transform", "scalar")

    @wp.func
    def body_pose(body_q: wp.array(dtype=transform), b: int):
        """Pose of body ``b``; the identity for the world (``b = -1``)."""
        if b < 0:
            return wp.transform_identity(dtype=scalar)
        return body_q[b]

    return body_pose


@functools.cache
def joint_frame_func(np_dtype):
    """``joint_frame(m, body_q, j)``: the world quantities of joint ``j`` (§2.1-2.2)."""
    transform, M = builder_types(np_dtype).take("transform", "M")
    body_pose = body_pose_func(np_dtype)

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

    return joint_frame


@functools.cache
def universal_axes_func(np_dtype):
    """``universal_axes(Q)``: the intermediate frame of a universal joint (§2.4)."""
    scalar, vec3, quat = builder_types(np_dtype).take("scalar", "vec3", "quat")

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

    return universal_axes


@functools.cache
def residual_func(np_dtype):
    """``residual(kind, axis, Q, t)``: the position residual of one kinematic row (§2.3)."""
    scalar, vec3, quat = builder_types(np_dtype).take("scalar", "vec3", "quat")
    quat_log = spatial_funcs(np_dtype).quat_log

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

    return residual


# --- Jacobian blocks (§2.5) ----------------------------------------------------------------------------------------

@functools.cache
def axis_blocks_func(np_dtype):
    """``axis_blocks(is_trans, a, p, r_F, r_B)``: the follower and base blocks of a row along a world axis (§2.5)."""
    scalar, vec3 = builder_types(np_dtype).take("scalar", "vec3")
    twist = spatial_funcs(np_dtype).twist

    @wp.func
    def axis_blocks(is_trans: int, a: vec3, p: vec3, r_F: vec3, r_B: vec3):
        """Follower and base 1x6 blocks of a row along world axis ``a`` (§2.5): translational
        ``J_F = [a, (p - r_F) x a]``, ``J_B = -[a, (p - r_B) x a]``; rotational ``J_F = [0, a] = -J_B``."""
        if is_trans != 0:
            return twist(a, wp.cross(p - r_F, a)), -twist(a, wp.cross(p - r_B, a))
        z = vec3(scalar(0.0), scalar(0.0), scalar(0.0))
        return twist(z, a), -twist(z, a)

    return axis_blocks


@functools.cache
def row_axis_func(np_dtype):
    """``row_axis(is_trans, is_univ, axis, R_j, Q)``: the world axis of a DoF or kinematic row (§2.4-2.5)."""
    vec3, quat, mat33 = builder_types(np_dtype).take("vec3", "quat", "mat33")
    universal_axes = universal_axes_func(np_dtype)

    @wp.func
    def row_axis(is_trans: int, is_univ: int, axis: int, R_j: mat33, Q: quat):
        """World axis of a row on joint axis ``axis`` (0-2 translational, 3-5 rotational): column ``axis`` of the
        joint rotation ``R_j`` for a translation, column ``axis - 3`` of ``R_j`` for a rotation, or of ``R_j``
        times the intermediate frame (:func:`universal_axes_func`) on a universal joint's rotation."""
        a = vec3()
        if is_trans != 0:
            a = vec3(R_j[0, axis], R_j[1, axis], R_j[2, axis])
        else:
            k = axis - 3
            if is_univ != 0:
                U = R_j * universal_axes(Q)
                a = vec3(U[0, k], U[1, k], U[2, k])
            else:
                a = vec3(R_j[0, k], R_j[1, k], R_j[2, k])
        return a

    return row_axis


@functools.cache
def cts_row_func(np_dtype):
    """``cts_row(m, body_q, c)``: the residual and blocks of kinematic row ``c`` (§2.3-2.5)."""
    transform, M = builder_types(np_dtype).take("transform", "M")
    joint_frame, residual = joint_frame_func(np_dtype), residual_func(np_dtype)
    row_axis, axis_blocks = row_axis_func(np_dtype), axis_blocks_func(np_dtype)

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
        a = row_axis(is_trans, int(kind == RES_UNIV), axis, R_j, Q)
        JF, JB = axis_blocks(is_trans, a, p_B, r_F, r_B)
        return e, JF, JB

    return cts_row


@functools.cache
def cts_residual_func(np_dtype):
    """``cts_residual(m, body_q, c)``: the residual of kinematic row ``c`` (§2.3)."""
    transform, M = builder_types(np_dtype).take("transform", "M")
    joint_frame, residual = joint_frame_func(np_dtype), residual_func(np_dtype)

    @wp.func
    def cts_residual(m: M, body_q: wp.array(dtype=transform), c: int):
        """Residual of kinematic row ``c`` at the poses ``body_q`` (``constraint_residual`` of the JAX reference)."""
        j = m.cts_joint[c]
        r_B, r_F, p_B, R_j, Q, t = joint_frame(m, body_q, j)
        return residual(m.cts_kind[c], m.cts_axis[c], Q, t)

    return cts_residual


@functools.cache
def dof_position_func(np_dtype):
    """``dof_position(m, body_q, d)``: the position of DoF ``d`` (§2.4)."""
    scalar, vec3, transform, M = builder_types(np_dtype).take("scalar", "vec3", "transform", "M")
    joint_frame = joint_frame_func(np_dtype)
    quat_log = spatial_funcs(np_dtype).quat_log

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

    return dof_position


@functools.cache
def dof_blocks_func(np_dtype):
    """``dof_blocks(m, body_q, d)``: the (follower, base) blocks of DoF row ``d`` of ``J_dofs`` (§2.5)."""
    scalar, vec3, vec6, transform, M = builder_types(np_dtype).take("scalar", "vec3", "vec6", "transform", "M")
    joint_frame = joint_frame_func(np_dtype)
    row_axis, axis_blocks = row_axis_func(np_dtype), axis_blocks_func(np_dtype)
    twist = spatial_funcs(np_dtype).twist

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
        a = row_axis(is_trans, int(kind == DOF_UNIV), axis, R_j, Q)
        return axis_blocks(is_trans, a, p_B, r_F, r_B)

    return dof_blocks


# --- couplings (docs/conventions.md "Couplings") -------------------------------------------------------------------

@functools.cache
def coupling_residual_func(np_dtype):
    """``coupling_residual(m, k, q_a, q_b)``: the residual ``q_a - p(q_b)`` of coupling ``k`` and ``p'(q_b)``."""
    scalar, M = builder_types(np_dtype).take("scalar", "M")

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

    return coupling_residual
