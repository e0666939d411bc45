"""The bilateral / limit constraint rows of a step, as Warp kernels.

Formulas of ``kamino/jax_ref/rows.py`` (docs/formulation.md §3.2, §4.1, §5); the body dynamics they start from are
in ``dynamics.py``.
Kernels run on ``(num_worlds, max_count)`` grids; a world's rows are written into its segment:
``[joint-dynamics | kinematic | coupling | active limits (compacted) | contacts]``.

Each kernel and each ``wp.func`` comes from its own builder, cached per precision (``np_dtype``) and, where a kernel
depends on the integrator or on the curvature term, per mode (``midpoint``, ``curvature``: compile-time).
"""

import functools
from types import SimpleNamespace

import warp as wp

from kamino.config import MIDPOINT_DAMPING
from kamino.model import ActuationMode
from kamino.tables import DYN_ACTUATOR
from kamino.warp_backend.dynamics import bodies_kernel
from kamino.warp_backend.indexing import index_funcs
from kamino.warp_backend.jacobians import (
    coupling_residual_func,
    cts_residual_func,
    cts_row_func,
    dof_blocks_func,
    dof_position_func,
)
from kamino.warp_backend.spatial import spatial_funcs
from kamino.warp_backend.workspace import builder_types

# row families (for splitting the solution into the State's force fields)
ROW_ACTUATOR, ROW_PASSIVE, ROW_JOINT, ROW_COUPLING, ROW_LIMIT, ROW_CONTACT = 0, 1, 2, 3, 4, 5
_PASSIVE, _EFFORT, _POSITION = int(ActuationMode.PASSIVE), int(ActuationMode.EFFORT), int(ActuationMode.POSITION)


def row_kernels(np_dtype) -> SimpleNamespace:
    """The row helpers other modules call by name (``contacts.py``, ``solver.py``): the builders' ``wp.func``s."""
    return SimpleNamespace(set_blocks=set_blocks_func(np_dtype), row_dot=row_dot_func(np_dtype),
                           body_dot=body_dot_func(np_dtype), free_velocity=free_velocity_func(np_dtype))


def step_row_kernels(np_dtype, curvature: bool, midpoint: bool) -> SimpleNamespace:
    """The body and row kernels of a step (the launches in ``pipeline.py``), for the curvature term on or off and the
    midpoint rule or Euler."""
    curvature, midpoint = bool(curvature), bool(midpoint)
    return SimpleNamespace(advance_poses=advance_poses_kernel(np_dtype), dof_blocks=dof_blocks_kernel(np_dtype),
                           bodies=bodies_kernel(np_dtype), dof_rates=dof_rates_kernel(np_dtype),
                           dyn_rows=dyn_rows_kernel(np_dtype),
                           joint_rows=joint_rows_kernel(np_dtype, curvature, midpoint),
                           coupling_rows=coupling_rows_kernel(np_dtype, curvature, midpoint),
                           limits=limits_kernel(np_dtype), pack_limits=pack_limits_kernel(np_dtype),
                           refine_joint_rows=refine_joint_rows_kernel(np_dtype, midpoint),
                           refine_coupling_rows=refine_coupling_rows_kernel(np_dtype, midpoint))


# --- block-sparse rows (docs/formulation.md §2.5) ------------------------------------------------------------------

@functools.cache
def body_dot_func(np_dtype):
    """``body_dot(u, b, J)``: one block's share ``J u_b`` of a row's product with a twist array (0 on the world)."""
    scalar, vec6 = builder_types(np_dtype).take("scalar", "vec6")

    @wp.func
    def body_dot(u: wp.array(dtype=vec6), b: int, J: vec6):
        if b < 0:
            return scalar(0.0)
        return wp.dot(J, u[b])

    return body_dot


@functools.cache
def set_blocks_func(np_dtype):
    """``set_blocks(row_body, row_J, r, nblk, bF, JF, bB, JB)``: row ``r``'s two blocks (§2.5)."""
    vec6 = builder_types(np_dtype).vec6

    @wp.func
    def set_blocks(row_body: wp.array(dtype=wp.int32), row_J: wp.array(dtype=vec6), r: int, nblk: int, bF: int,
                   JF: vec6, bB: int, JB: vec6):
        """Row ``r`` = blocks ``(bF, JF)``, ``(bB, JB)``; the other block slots empty."""
        for k in range(nblk):
            row_body[r * nblk + k] = -1
            row_J[r * nblk + k] = vec6()
        row_body[r * nblk] = bF
        row_J[r * nblk] = JF
        row_body[r * nblk + 1] = bB
        if bB >= 0:
            row_J[r * nblk + 1] = JB

    return set_blocks


@functools.cache
def row_dot_func(np_dtype):
    """``row_dot(row_body, row_J, r, nblk, u)``: ``J_r u`` over row ``r``'s blocks (§2.5)."""
    scalar, vec6 = builder_types(np_dtype).take("scalar", "vec6")
    body_dot = body_dot_func(np_dtype)

    @wp.func
    def row_dot(row_body: wp.array(dtype=wp.int32), row_J: wp.array(dtype=vec6), r: int, nblk: int,
                u: wp.array(dtype=vec6)):
        """``J_r u`` over the row's blocks."""
        s = scalar(0.0)
        for k in range(nblk):
            s += body_dot(u, row_body[r * nblk + k], row_J[r * nblk + k])
        return s

    return row_dot


@functools.cache
def dof_row_func(np_dtype):
    """``dof_row(m, dof_JF, dof_JB, row_body, row_J, r, nblk, d, sign)``: row ``r``'s blocks are ``sign`` times DoF
    ``d``'s (§2.5, §3.2, §4.1)."""
    scalar, vec6, M = builder_types(np_dtype).take("scalar", "vec6", "M")
    set_blocks = set_blocks_func(np_dtype)

    @wp.func
    def dof_row(m: M, dof_JF: wp.array(dtype=vec6), dof_JB: wp.array(dtype=vec6), row_body: wp.array(dtype=wp.int32),
                row_J: wp.array(dtype=vec6), r: int, nblk: int, d: int, sign: scalar):
        j = m.dof_joint[d]
        set_blocks(row_body, row_J, r, nblk, m.joint_child[j], sign * dof_JF[d], m.joint_parent[j], sign * dof_JB[d])

    return dof_row


@functools.cache
def set_row_func(np_dtype):
    """``set_row(vstar, reg, lo, hi, f0, v0, row_info, r, vstar_r, reg_r, lo_r, hi_r, f0_r, info_r)``: the numbers of
    row ``r`` besides its blocks (§7.1)."""
    scalar = builder_types(np_dtype).scalar

    @wp.func
    def set_row(vstar: wp.array(dtype=scalar), reg: wp.array(dtype=scalar), lo: wp.array(dtype=scalar),
                hi: wp.array(dtype=scalar), f0: wp.array(dtype=scalar), v0: wp.array(dtype=scalar),
                row_info: wp.array(dtype=wp.int32), r: int, vstar_r: scalar, reg_r: scalar, lo_r: scalar, hi_r: scalar,
                f0_r: scalar, info_r: int):
        """Row ``r``'s bias ``v*``, regularisation ``R``, box ``[lo, hi]``, warm-start force ``f0`` and its packed
        description ``row_info`` (the arrays: ``Work``'s fields; the ``*_r``: row ``r``'s values); no restitution
        target (``v0 = 0``)."""
        vstar[r] = vstar_r
        reg[r] = reg_r
        lo[r] = lo_r
        hi[r] = hi_r
        f0[r] = f0_r
        v0[r] = scalar(0.0)
        row_info[r] = info_r

    return set_row


# --- body dynamics (docs/formulation.md §1.4, §3.1, §6.3) ----------------------------------------------------------

@functools.cache
def advance_poses_kernel(np_dtype):
    """A pose update of every body (docs/formulation.md §6.1): the midpoint pose (§6.3) and the predicted pose along
    the solved velocity (curvature refinement, §5)."""
    scalar, vec6, transform, M = builder_types(np_dtype).take("scalar", "vec6", "transform", "M")
    integrate_pose = spatial_funcs(np_dtype).integrate_pose

    @wp.kernel(module="unique", enable_backward=False)
    def advance_poses(
        # model (read only)
        m: M,
        # in
        h: scalar,
        x: wp.array(dtype=transform),
        u: wp.array(dtype=vec6),
        # out
        out: wp.array(dtype=transform),
    ):
        """``out = x ⊕ h u``: the midpoint pose ``q_m = q ⊕ h u`` (docs/formulation.md §6.3), or ``q_pred = q_eval
        ⊕ h u_new``, the predicted pose along the solved velocity (curvature refinement)."""
        wid, i = wp.tid()
        if i >= m.body_count[wid]:
            return
        b = m.body_start[wid] + i
        out[b] = integrate_pose(x[b], u[b], h)

    return advance_poses


@functools.cache
def dof_blocks_kernel(np_dtype):
    """``J_dofs`` and the explicit efforts (docs/formulation.md §2.5, §3.1)."""
    scalar, vec6, transform, M = builder_types(np_dtype).take("scalar", "vec6", "transform", "M")
    joint_dof_blocks, dof_position = dof_blocks_func(np_dtype), dof_position_func(np_dtype)

    @wp.kernel(module="unique", enable_backward=False)
    def dof_blocks(
        # model (read only)
        m: M,
        # in
        q_eval: wp.array(dtype=transform),
        effort: wp.array(dtype=scalar),
        # out
        dof_JF: wp.array(dtype=vec6),
        dof_JB: wp.array(dtype=vec6),
        q_dof: wp.array(dtype=scalar),
        tau_explicit: wp.array(dtype=scalar),
    ):
        """``J_dofs`` blocks, DoF positions and the explicit efforts (docs/formulation.md §3.1) at ``q_eval``."""
        wid, i = wp.tid()
        if i >= m.dof_count[wid]:
            return
        d = m.dof_start[wid] + i
        JF, JB = joint_dof_blocks(m, q_eval, d)
        dof_JF[d] = JF
        dof_JB[d] = JB
        q_dof[d] = dof_position(m, q_eval, d)
        mode = m.act_mode[d]
        tau = effort[d]
        if mode == _EFFORT:
            tau = wp.clamp(tau, -m.effort_limit[d], m.effort_limit[d])
        elif mode != _PASSIVE:
            tau = scalar(0.0)
        tau_explicit[d] = tau

    return dof_blocks


@functools.cache
def dof_rates_kernel(np_dtype):
    """DoF velocities and predicted DoF positions (docs/formulation.md §3.2, §4.1, §5)."""
    scalar, vec6, transform, M = builder_types(np_dtype).take("scalar", "vec6", "transform", "M")
    body_dot, dof_position = body_dot_func(np_dtype), dof_position_func(np_dtype)

    @wp.kernel(module="unique", enable_backward=False)
    def dof_rates(
        # model (read only)
        m: M,
        # in
        u: wp.array(dtype=vec6),
        u_f: wp.array(dtype=vec6),
        dof_JF: wp.array(dtype=vec6),
        dof_JB: wp.array(dtype=vec6),
        q_pred: wp.array(dtype=transform),
        # out
        qd_minus: wp.array(dtype=scalar),
        qd_free: wp.array(dtype=scalar),
        q_dof_pred: wp.array(dtype=scalar),
    ):
        """DoF velocities before the step and of the free motion, DoF positions at the predicted pose."""
        wid, i = wp.tid()
        if i >= m.dof_count[wid]:
            return
        d = m.dof_start[wid] + i
        j = m.dof_joint[d]
        bF = m.joint_child[j]
        bB = m.joint_parent[j]
        qd_minus[d] = body_dot(u, bF, dof_JF[d]) + body_dot(u, bB, dof_JB[d])
        qd_free[d] = body_dot(u_f, bF, dof_JF[d]) + body_dot(u_f, bB, dof_JB[d])
        q_dof_pred[d] = dof_position(m, q_pred, d)

    return dof_rates


# --- joint-dynamics rows (docs/formulation.md §3.2) ----------------------------------------------------------------

@functools.cache
def dyn_rows_kernel(np_dtype):
    """The joint-dynamics rows (docs/formulation.md §3.2)."""
    scalar, vec6, M, inf = builder_types(np_dtype).take("scalar", "vec6", "M", "inf")
    ix = index_funcs(np_dtype)
    ridx, pack_info = ix.ridx, ix.row_info
    dof_row, set_row = dof_row_func(np_dtype), set_row_func(np_dtype)

    @wp.kernel(module="unique", enable_backward=False)
    def dyn_rows(
        # model (read only)
        m: M,
        # in
        nblk: int,
        dt: scalar,
        h: scalar,
        row_stride: int,
        dof_JF: wp.array(dtype=vec6),
        dof_JB: wp.array(dtype=vec6),
        q_dof: wp.array(dtype=scalar),
        qd_minus: wp.array(dtype=scalar),
        effort: wp.array(dtype=scalar),
        position_target: wp.array(dtype=scalar),
        velocity_target: wp.array(dtype=scalar),
        act_force: wp.array(dtype=scalar),
        pas_force: wp.array(dtype=scalar),
        # out
        row_body: wp.array(dtype=wp.int32),
        row_J: wp.array(dtype=vec6),
        vstar: wp.array(dtype=scalar),
        reg: wp.array(dtype=scalar),
        lo: wp.array(dtype=scalar),
        hi: wp.array(dtype=scalar),
        f0: wp.array(dtype=scalar),
        v0: wp.array(dtype=scalar),
        row_info: wp.array(dtype=wp.int32),
    ):
        """Joint-dynamics rows (docs/formulation.md §3.2; ``dynamics_rows`` of the JAX reference): implicit inertia
        ``m`` (``R = 1/m``), bias ``-p0/m`` and the effort bound of actuator rows."""
        wid, i = wp.tid()
        if i >= m.dyn_count[wid]:
            return
        k = m.dyn_start[wid] + i
        d = m.dyn_dof[k]
        r = ridx(m, row_stride, wid, i)
        dof_row(m, dof_JF, dof_JB, row_body, row_J, r, nblk, d, scalar(1.0))
        q = q_dof[d]
        mi = scalar(0.0)
        p0 = scalar(0.0)
        bound = inf
        info = int(0)
        f = scalar(0.0)
        if m.dyn_kind[k] == DYN_ACTUATOR:
            kp = scalar(0.0)
            if m.act_mode[d] == _POSITION:
                kp = m.kp[d]
            kd = m.kd[d]
            mi = dt * (kd + h * kp)
            p0 = dt * (effort[d] + kp * (position_target[d] - q) + kd * velocity_target[d])
            bound = dt * m.effort_limit[d]
            info = pack_info(ROW_ACTUATOR, d, scalar(1.0))
            f = act_force[d]
        else:
            a = m.armature[d]
            ks = m.stiffness[d]
            mi = a + dt * m.damping[d] + dt * h * ks
            p0 = a * qd_minus[d] + dt * ks * (m.springref[d] - q)
            info = pack_info(ROW_PASSIVE, d, scalar(1.0))
            f = pas_force[d]
        mi = wp.max(mi, scalar(1e-30))
        set_row(vstar, reg, lo, hi, f0, v0, row_info, r, -p0 / mi, scalar(1.0) / mi, -bound, bound, f, info)

    return dyn_rows


# --- joint and coupling rows and their bias (docs/formulation.md §5; docs/conventions.md "Stabilisation") ----------

@functools.cache
def stabilisation_bias_func(np_dtype, midpoint: bool):
    """``stabilisation_bias(e, e_start, c, alpha, delta)``: ``h v*`` of a joint or coupling row (docs/formulation.md
    §5) for the midpoint rule (``midpoint``) or Euler."""
    scalar = builder_types(np_dtype).scalar
    deadband = spatial_funcs(np_dtype).deadband
    gamma = scalar(MIDPOINT_DAMPING)

    @wp.func
    def stabilisation_bias(e: scalar, e_start: scalar, c: scalar, alpha: scalar, delta: scalar):
        """``h v*`` of a joint or coupling row (``joint_bias`` of the JAX reference; docs/conventions.md
        "Stabilisation"): the end-of-step target ``(1 - alpha) e_start``, plus for the midpoint rule the share
        ``MIDPOINT_DAMPING`` of the first half-step's move ``e - e_start - c`` (which damps the alternating mode),
        and the curvature term ``c``, each through the dead band."""
        target = (scalar(1.0) - alpha) * e_start
        if wp.static(midpoint):
            target += gamma * (e - e_start - c)
        return deadband(e - target, delta) + deadband(c, delta)

    return stabilisation_bias


@functools.cache
def curved_bias_func(np_dtype, midpoint: bool):
    """``curved_bias(row_body, row_J, r, nblk, e, e_start, e_pred, u, h, alpha, delta)``: row ``r``'s bias ``v*`` with
    the curvature term along the twists ``u`` (docs/formulation.md §5)."""
    scalar, vec6 = builder_types(np_dtype).take("scalar", "vec6")
    row_dot, stabilisation_bias = row_dot_func(np_dtype), stabilisation_bias_func(np_dtype, midpoint)

    @wp.func
    def curved_bias(row_body: wp.array(dtype=wp.int32), row_J: wp.array(dtype=vec6), r: int, nblk: int, e: scalar,
                    e_start: scalar, e_pred: scalar, u: wp.array(dtype=vec6), h: scalar, alpha: scalar, delta: scalar):
        """``v*`` of row ``r`` with the curvature term ``c = e_pred - e - h J_r u`` (the residual's second-order
        change along the step; ``e_pred`` at the pose predicted along ``u``)."""
        cv = e_pred - e - h * row_dot(row_body, row_J, r, nblk, u)
        return stabilisation_bias(e, e_start, cv, alpha, delta) / h

    return curved_bias


@functools.cache
def joint_start_residual_func(np_dtype, midpoint: bool):
    """``joint_start_residual(m, q, c, e)``: the residual of kinematic row ``c`` the bias aims from (§5)."""
    scalar, transform, M = builder_types(np_dtype).take("scalar", "transform", "M")
    cts_residual = cts_residual_func(np_dtype)

    @wp.func
    def joint_start_residual(m: M, q: wp.array(dtype=transform), c: int, e: scalar):
        """``e_start``: the residual at the start pose ``q`` for the midpoint rule, else ``e`` (at ``q_eval = q``)."""
        e_start = e
        if wp.static(midpoint):
            e_start = cts_residual(m, q, c)
        return e_start

    return joint_start_residual


@functools.cache
def coupling_start_residual_func(np_dtype, midpoint: bool):
    """``coupling_start_residual(m, q, k, e)``: the residual of coupling row ``k`` the bias aims from (§5)."""
    scalar, transform, M = builder_types(np_dtype).take("scalar", "transform", "M")
    coupling_residual, dof_position = coupling_residual_func(np_dtype), dof_position_func(np_dtype)

    @wp.func
    def coupling_start_residual(m: M, q: wp.array(dtype=transform), k: int, e: scalar):
        """``e_start``: the residual at the DoF positions of the start pose ``q`` for the midpoint rule (only it
        needs them), else ``e``."""
        e_start = e
        if wp.static(midpoint):
            db = m.cpl_dof_b[k]
            qb0 = scalar(0.0)
            if db >= 0:
                qb0 = dof_position(m, q, db)
            e_start, dp0 = coupling_residual(m, k, dof_position(m, q, m.cpl_dof_a[k]), qb0)
        return e_start

    return coupling_start_residual


@functools.cache
def joint_rows_kernel(np_dtype, curvature: bool, midpoint: bool):
    """The kinematic joint rows (docs/formulation.md §2.5, §5), with or without the curvature term."""
    scalar, vec6, transform, M, inf = builder_types(np_dtype).take("scalar", "vec6", "transform", "M", "inf")
    ix = index_funcs(np_dtype)
    ridx, pack_info = ix.ridx, ix.row_info
    cts_row, cts_residual = cts_row_func(np_dtype), cts_residual_func(np_dtype)
    set_blocks, set_row = set_blocks_func(np_dtype), set_row_func(np_dtype)
    stabilisation_bias, curved_bias = stabilisation_bias_func(np_dtype, midpoint), curved_bias_func(np_dtype, midpoint)
    joint_start_residual = joint_start_residual_func(np_dtype, midpoint)

    @wp.kernel(module="unique", enable_backward=False)
    def joint_rows(
        # model (read only)
        m: M,
        # in
        nblk: int,
        h: scalar,
        alpha: scalar,
        delta: scalar,
        row_stride: int,
        q_eval: wp.array(dtype=transform),
        q: wp.array(dtype=transform),
        q_pred: wp.array(dtype=transform),
        u_f: wp.array(dtype=vec6),
        kin_force: wp.array(dtype=scalar),
        # out
        row_body: wp.array(dtype=wp.int32),
        row_J: wp.array(dtype=vec6),
        vstar: wp.array(dtype=scalar),
        reg: wp.array(dtype=scalar),
        lo: wp.array(dtype=scalar),
        hi: wp.array(dtype=scalar),
        f0: wp.array(dtype=scalar),
        v0: wp.array(dtype=scalar),
        row_info: wp.array(dtype=wp.int32),
    ):
        """Kinematic joint rows: blocks and the stabilisation bias of ``joint_bias`` (docs/formulation.md §5;
        docs/conventions.md "Stabilisation")."""
        wid, i = wp.tid()
        if i >= m.cts_count[wid]:
            return
        c = m.cts_start[wid] + i
        r = ridx(m, row_stride, wid, m.dyn_count[wid] + i)
        j = m.cts_joint[c]
        e, JF, JB = cts_row(m, q_eval, c)
        set_blocks(row_body, row_J, r, nblk, m.joint_child[j], JF, m.joint_parent[j], JB)
        e_start = joint_start_residual(m, q, c, e)
        vs = scalar(0.0)
        if wp.static(curvature):
            vs = curved_bias(row_body, row_J, r, nblk, e, e_start, cts_residual(m, q_pred, c), u_f, h, alpha, delta)
        else:
            vs = stabilisation_bias(e, e_start, scalar(0.0), alpha, delta) / h
        set_row(vstar, reg, lo, hi, f0, v0, row_info, r, vs, scalar(0.0), -inf, inf, kin_force[c],
                pack_info(ROW_JOINT, c, scalar(1.0)))

    return joint_rows


@functools.cache
def coupling_rows_kernel(np_dtype, curvature: bool, midpoint: bool):
    """The coupling rows (docs/conventions.md "Couplings"; docs/formulation.md §5), with or without the curvature
    term."""
    scalar, vec6, transform, M, inf = builder_types(np_dtype).take("scalar", "vec6", "transform", "M", "inf")
    ix = index_funcs(np_dtype)
    ridx, pack_info = ix.ridx, ix.row_info
    coupling_residual = coupling_residual_func(np_dtype)
    dof_row, set_row = dof_row_func(np_dtype), set_row_func(np_dtype)
    stabilisation_bias, curved_bias = stabilisation_bias_func(np_dtype, midpoint), curved_bias_func(np_dtype, midpoint)
    coupling_start_residual = coupling_start_residual_func(np_dtype, midpoint)

    @wp.kernel(module="unique", enable_backward=False)
    def coupling_rows(
        # model (read only)
        m: M,
        # in
        nblk: int,
        h: scalar,
        alpha: scalar,
        delta: scalar,
        row_stride: int,
        dof_JF: wp.array(dtype=vec6),
        dof_JB: wp.array(dtype=vec6),
        q_dof: wp.array(dtype=scalar),
        q_dof_pred: wp.array(dtype=scalar),
        q: wp.array(dtype=transform),
        u_f: wp.array(dtype=vec6),
        cpl_force: wp.array(dtype=scalar),
        # out
        row_body: wp.array(dtype=wp.int32),
        row_J: wp.array(dtype=vec6),
        vstar: wp.array(dtype=scalar),
        reg: wp.array(dtype=scalar),
        lo: wp.array(dtype=scalar),
        hi: wp.array(dtype=scalar),
        f0: wp.array(dtype=scalar),
        v0: wp.array(dtype=scalar),
        row_info: wp.array(dtype=wp.int32),
    ):
        """Coupling rows ``q_a - p(q_b)``: blocks ``J_a - p'(q_b) J_b`` (four) and the bias of ``coupling_bias``."""
        wid, i = wp.tid()
        if i >= m.cpl_count[wid]:
            return
        k = m.cpl_start[wid] + i
        r = ridx(m, row_stride, wid, m.dyn_count[wid] + m.cts_count[wid] + i)
        da = m.cpl_dof_a[k]
        db = m.cpl_dof_b[k]
        qb = scalar(0.0)
        qb_pred = scalar(0.0)
        if db >= 0:
            qb = q_dof[db]
            qb_pred = q_dof_pred[db]
        e, dp = coupling_residual(m, k, q_dof[da], qb)
        dof_row(m, dof_JF, dof_JB, row_body, row_J, r, nblk, da, scalar(1.0))
        if db >= 0:
            jb = m.dof_joint[db]
            row_body[r * nblk + 2] = m.joint_child[jb]
            row_J[r * nblk + 2] = -dp * dof_JF[db]
            row_body[r * nblk + 3] = m.joint_parent[jb]
            row_J[r * nblk + 3] = -dp * dof_JB[db]
        e_start = coupling_start_residual(m, q, k, e)
        vs = scalar(0.0)
        if wp.static(curvature):
            e_pred, dp1 = coupling_residual(m, k, q_dof_pred[da], qb_pred)
            vs = curved_bias(row_body, row_J, r, nblk, e, e_start, e_pred, u_f, h, alpha, delta)
        else:
            vs = stabilisation_bias(e, e_start, scalar(0.0), alpha, delta) / h
        set_row(vstar, reg, lo, hi, f0, v0, row_info, r, vs, scalar(0.0), -inf, inf, cpl_force[k],
                pack_info(ROW_COUPLING, k, scalar(1.0)))

    return coupling_rows


# --- curvature refinement: the bias along the solved velocity (docs/formulation.md §5) -----------------------------

@functools.cache
def free_velocity_func(np_dtype):
    """``free_velocity(vstar, row_body, row_J, u_f, r, nblk)``: ``v_f = J u_f + v*`` of row ``r``
    (docs/formulation.md §7.1)."""
    scalar, vec6 = builder_types(np_dtype).take("scalar", "vec6")

    @wp.func
    def free_velocity(vstar: wp.array(dtype=scalar), row_body: wp.array(dtype=wp.int32), row_J: wp.array(dtype=vec6),
                      u_f: wp.array(dtype=vec6), r: int, nblk: int):
        """``v_f = J u_f + v*`` of row ``r`` (``solver.prebake``; recomputed, the same sums, by
        :func:`set_bias_func`)."""
        vf = vstar[r]
        for k in range(nblk):
            b = row_body[r * nblk + k]
            if b >= 0:
                vf += wp.dot(row_J[r * nblk + k], u_f[b])
        return vf

    return free_velocity


@functools.cache
def set_bias_func(np_dtype):
    """``set_bias(row_body, row_J, u_f, P, vstar, vt, r, nblk, vs)``: a new bias of row ``r`` and its scaled free
    velocity (docs/formulation.md §8)."""
    scalar, vec6 = builder_types(np_dtype).take("scalar", "vec6")
    free_velocity = free_velocity_func(np_dtype)

    @wp.func
    def set_bias(row_body: wp.array(dtype=wp.int32), row_J: wp.array(dtype=vec6), u_f: wp.array(dtype=vec6),
                 P: wp.array(dtype=scalar), vstar: wp.array(dtype=scalar), vt: wp.array(dtype=scalar), r: int,
                 nblk: int, vs: scalar):
        """Replace row ``r``'s bias and ``v~_f = P (v_f - v* + vs)``. ``v_f`` is not stored: it is recomputed from the
        row's blocks and ``u_f`` (unchanged since ``solver.prebake``) with the old bias, so that the sum equals the
        stored one's bit for bit."""
        vf = free_velocity(vstar, row_body, row_J, u_f, r, nblk) - vstar[r] + vs
        vt[r] = P[r] * vf
        vstar[r] = vs

    return set_bias


@functools.cache
def refine_joint_rows_kernel(np_dtype, midpoint: bool):
    """The joint rows' bias along the solved velocity (docs/formulation.md §5)."""
    scalar, vec6, transform, M = builder_types(np_dtype).take("scalar", "vec6", "transform", "M")
    ridx = index_funcs(np_dtype).ridx
    cts_residual = cts_residual_func(np_dtype)
    set_bias, curved_bias = set_bias_func(np_dtype), curved_bias_func(np_dtype, midpoint)
    joint_start_residual = joint_start_residual_func(np_dtype, midpoint)

    @wp.kernel(module="unique", enable_backward=False)
    def refine_joint_rows(
        # model (read only)
        m: M,
        # in
        nblk: int,
        h: scalar,
        alpha: scalar,
        delta: scalar,
        row_stride: int,
        q_eval: wp.array(dtype=transform),
        q: wp.array(dtype=transform),
        q_pred: wp.array(dtype=transform),
        u_new: wp.array(dtype=vec6),
        row_body: wp.array(dtype=wp.int32),
        row_J: wp.array(dtype=vec6),
        u_f: wp.array(dtype=vec6),
        P: wp.array(dtype=scalar),
        converged: wp.array(dtype=wp.int32),
        # out
        vstar: wp.array(dtype=scalar),
        vt: wp.array(dtype=scalar),
    ):
        """The joint rows' bias with the curvature term predicted along the solved velocity ``u_new``
        (``SolverConfig.stabilisation.curvature_refinement``; ``joint_bias`` of the JAX reference with
        ``u_pred = u+``), in the worlds whose first solve ``converged`` (the others keep their rows)."""
        wid, i = wp.tid()
        if i >= m.cts_count[wid] or converged[wid] == 0:
            return
        c = m.cts_start[wid] + i
        r = ridx(m, row_stride, wid, m.dyn_count[wid] + i)
        e = cts_residual(m, q_eval, c)
        e_start = joint_start_residual(m, q, c, e)
        vs = curved_bias(row_body, row_J, r, nblk, e, e_start, cts_residual(m, q_pred, c), u_new, h, alpha, delta)
        set_bias(row_body, row_J, u_f, P, vstar, vt, r, nblk, vs)

    return refine_joint_rows


@functools.cache
def refine_coupling_rows_kernel(np_dtype, midpoint: bool):
    """The coupling rows' bias along the solved velocity (docs/formulation.md §5)."""
    scalar, vec6, transform, M = builder_types(np_dtype).take("scalar", "vec6", "transform", "M")
    ridx = index_funcs(np_dtype).ridx
    coupling_residual, dof_position = coupling_residual_func(np_dtype), dof_position_func(np_dtype)
    set_bias, curved_bias = set_bias_func(np_dtype), curved_bias_func(np_dtype, midpoint)
    coupling_start_residual = coupling_start_residual_func(np_dtype, midpoint)

    @wp.kernel(module="unique", enable_backward=False)
    def refine_coupling_rows(
        # model (read only)
        m: M,
        # in
        nblk: int,
        h: scalar,
        alpha: scalar,
        delta: scalar,
        row_stride: int,
        q_dof: wp.array(dtype=scalar),
        q: wp.array(dtype=transform),
        q_pred: wp.array(dtype=transform),
        u_new: wp.array(dtype=vec6),
        row_body: wp.array(dtype=wp.int32),
        row_J: wp.array(dtype=vec6),
        u_f: wp.array(dtype=vec6),
        P: wp.array(dtype=scalar),
        converged: wp.array(dtype=wp.int32),
        # out
        vstar: wp.array(dtype=scalar),
        vt: wp.array(dtype=scalar),
    ):
        """The coupling rows' bias along the solved velocity (as :func:`refine_joint_rows_kernel`, in the worlds
        whose first solve ``converged``)."""
        wid, i = wp.tid()
        if i >= m.cpl_count[wid] or converged[wid] == 0:
            return
        k = m.cpl_start[wid] + i
        r = ridx(m, row_stride, wid, m.dyn_count[wid] + m.cts_count[wid] + i)
        da = m.cpl_dof_a[k]
        db = m.cpl_dof_b[k]
        qb = scalar(0.0)
        qb_pred = scalar(0.0)
        if db >= 0:
            qb = q_dof[db]
            qb_pred = dof_position(m, q_pred, db)
        e, dp = coupling_residual(m, k, q_dof[da], qb)
        e_start = coupling_start_residual(m, q, k, e)
        e_pred, dp1 = coupling_residual(m, k, dof_position(m, q_pred, da), qb_pred)
        vs = curved_bias(row_body, row_J, r, nblk, e, e_start, e_pred, u_new, h, alpha, delta)
        set_bias(row_body, row_J, u_f, P, vstar, vt, r, nblk, vs)

    return refine_coupling_rows


# --- limit rows (docs/formulation.md §4.1) -------------------------------------------------------------------------

@functools.cache
def limits_kernel(np_dtype):
    """Which limit rows are active, and their bias (docs/formulation.md §4.1)."""
    scalar, M = builder_types(np_dtype).take("scalar", "M")

    @wp.kernel(module="unique", enable_backward=False)
    def limits(
        # model (read only)
        m: M,
        # in
        dt: scalar,
        margin: scalar,
        beta: scalar,
        q_dof: wp.array(dtype=scalar),
        qd_free: wp.array(dtype=scalar),
        # out
        lim_side: wp.array(dtype=scalar),
        lim_active: wp.array(dtype=wp.int32),
        lim_bias: wp.array(dtype=scalar),
    ):
        """Which limit rows are active and their bias (docs/formulation.md §4.1; ``limit_rows`` of the JAX
        reference): the nearer limit, active when it can be reached within the step. Both integrators look one
        whole step ``dt`` ahead, to the pose at which the next step reads the row (the midpoint rule's next
        ``q_m`` is ``q_m ⊕ dt u+``): ``r + dt side qd+ >= (1 - beta) min(r, 0)``."""
        wid, i = wp.tid()
        if i >= m.lim_count[wid]:
            return
        k = m.lim_start[wid] + i
        d = m.lim_dof[k]
        q = q_dof[d]
        r_lo = q - m.lower[d]
        r_hi = m.upper[d] - q
        side = scalar(1.0)
        r = r_lo
        if r_lo > r_hi:
            side = scalar(-1.0)
            r = r_hi
        approach = wp.max(-side * qd_free[d], scalar(0.0))
        active = r < margin + dt * approach
        lim_side[k] = side
        if active:
            lim_active[k] = 1
            lim_bias[k] = (r - (scalar(1.0) - beta) * wp.min(r, scalar(0.0))) / dt
        else:
            lim_active[k] = 0
            lim_bias[k] = scalar(0.0)

    return limits


@functools.cache
def pack_limits_kernel(np_dtype):
    """The active limit rows, compacted after the fixed rows (docs/formulation.md §4.1)."""
    scalar, vec6, M, inf = builder_types(np_dtype).take("scalar", "vec6", "M", "inf")
    ix = index_funcs(np_dtype)
    ridx, pack_info = ix.ridx, ix.row_info
    dof_row, set_row = dof_row_func(np_dtype), set_row_func(np_dtype)

    @wp.kernel(module="unique", enable_backward=False)
    def pack_limits(
        # model (read only)
        m: M,
        # in
        nblk: int,
        row_stride: int,
        lim_active: wp.array(dtype=wp.int32),
        lim_side: wp.array(dtype=scalar),
        lim_bias: wp.array(dtype=scalar),
        lim_force: wp.array(dtype=scalar),
        dof_JF: wp.array(dtype=vec6),
        dof_JB: wp.array(dtype=vec6),
        # out
        row_body: wp.array(dtype=wp.int32),
        row_J: wp.array(dtype=vec6),
        vstar: wp.array(dtype=scalar),
        reg: wp.array(dtype=scalar),
        lo: wp.array(dtype=scalar),
        hi: wp.array(dtype=scalar),
        f0: wp.array(dtype=scalar),
        v0: wp.array(dtype=scalar),
        row_info: wp.array(dtype=wp.int32),
        n_lim: wp.array(dtype=wp.int32),
    ):
        """Append the active limit rows after the fixed rows, in DoF order (deterministic)."""
        wid = wp.tid()
        a0 = m.row_fixed[wid]
        n = int(0)
        for i in range(m.lim_count[wid]):
            k = m.lim_start[wid] + i
            if lim_active[k] != 0:
                d = m.lim_dof[k]
                side = lim_side[k]
                r = ridx(m, row_stride, wid, a0 + n)
                dof_row(m, dof_JF, dof_JB, row_body, row_J, r, nblk, d, side)
                set_row(vstar, reg, lo, hi, f0, v0, row_info, r, lim_bias[k], scalar(0.0), scalar(0.0), inf,
                        wp.max(side * lim_force[d], scalar(0.0)), pack_info(ROW_LIMIT, d, side))
                n += 1
        n_lim[wid] = n

    return pack_limits
