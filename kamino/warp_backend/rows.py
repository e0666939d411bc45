"""Body dynamics and the bilateral / limit constraint rows of a step, as Warp kernels.

Formulas of ``kamino/jax_ref/step.py`` and ``dynamics.py`` (docs/formulation.md §1.4, §3.2, §4.1, §5).
Kernels run on ``(num_worlds, max_count)`` grids; a world's rows are written into its segment:
``[joint-dynamics | kinematic | coupling | active limits (compacted) | contacts]``.
"""

import functools
from types import SimpleNamespace

import warp as wp

from kamino.config import GYRO_ITERATIONS, MIDPOINT_DAMPING
from kamino.model import ActuationMode
from kamino.tables import DYN_ACTUATOR
from kamino.warp_backend.indexing import index_funcs
from kamino.warp_backend.kinematics import kinematics_funcs
from kamino.warp_backend.model_data import model_struct
from kamino.warp_backend.spatial import spatial_funcs
from kamino.warp_backend.types import types_of
from kamino.warp_backend.workspace import work_struct

# row families (for splitting the solution into the State's force fields)
ROW_ACTUATOR, ROW_PASSIVE, ROW_JOINT, ROW_COUPLING, ROW_LIMIT, ROW_CONTACT = 0, 1, 2, 3, 4, 5
_PASSIVE, _EFFORT, _POSITION = int(ActuationMode.PASSIVE), int(ActuationMode.EFFORT), int(ActuationMode.POSITION)


@functools.cache
def row_kernels(np_dtype) -> SimpleNamespace:
    T = types_of(np_dtype)
    scalar, vec3, vec6, mat33 = T.scalar, T.vec3, T.vec6, T.mat33
    M = model_struct(np_dtype)
    Work = work_struct(np_dtype)
    sp = spatial_funcs(np_dtype)
    kf = kinematics_funcs(np_dtype)
    ix = index_funcs(np_dtype)
    ridx, row_info = ix.ridx, ix.row_info
    integrate_pose, deadband, lin, ang, twist = sp.integrate_pose, sp.deadband, sp.lin, sp.ang, sp.twist
    inverse_mass_times = sp.inverse_mass_times
    inf = scalar(wp.inf)

    @wp.func
    def body_dot(u: wp.array(dtype=vec6), b: int, J: vec6):
        if b < 0:
            return scalar(0.0)
        return wp.dot(J, u[b])

    @wp.func
    def set_blocks(w: Work, r: int, nblk: int, bF: int, JF: vec6, bB: int, JB: vec6):
        """Row ``r`` = blocks ``(bF, JF)``, ``(bB, JB)``; the other block slots empty."""
        for k in range(nblk):
            w.row_body[r * nblk + k] = -1
            w.row_J[r * nblk + k] = vec6()
        w.row_body[r * nblk] = bF
        w.row_J[r * nblk] = JF
        w.row_body[r * nblk + 1] = bB
        if bB >= 0:
            w.row_J[r * nblk + 1] = JB

    @wp.func
    def row_dot(w: Work, r: int, nblk: int, u: wp.array(dtype=vec6)):
        """``J_r u`` over the row's blocks."""
        s = scalar(0.0)
        for k in range(nblk):
            s += body_dot(u, w.row_body[r * nblk + k], w.row_J[r * nblk + k])
        return s

    @wp.kernel(module="unique", enable_backward=False)
    def half_step(m: M, w: Work, h: scalar):
        """Midpoint pose ``q_m = q ⊕ h u`` (docs/formulation.md §6.3)."""
        wid, i = wp.tid()
        if i >= m.body_count[wid]:
            return
        b = m.body_start[wid] + i
        w.q_eval[b] = integrate_pose(w.q[b], w.u[b], h)

    @wp.kernel(module="unique", enable_backward=False)
    def dof_blocks(m: M, w: Work):
        """``J_dofs`` blocks, DoF positions and the explicit efforts (docs/formulation.md §3.1) at ``q_eval``."""
        wid, i = wp.tid()
        if i >= m.dof_count[wid]:
            return
        d = m.dof_start[wid] + i
        JF, JB = kf.dof_blocks(m, w.q_eval, d)
        w.dof_JF[d] = JF
        w.dof_JB[d] = JB
        w.q_dof[d] = kf.dof_position(m, w.q_eval, d)
        mode = m.act_mode[d]
        tau = w.effort[d]
        if mode == _EFFORT:
            tau = wp.clamp(tau, -m.effort_limit[d], m.effort_limit[d])
        elif mode != _PASSIVE:
            tau = scalar(0.0)
        w.tau_explicit[d] = tau

    @wp.func
    def gyroscopic_correction(Ib: mat33, R: mat33, w0: vec3, we: vec3, dt: scalar):
        """World-frame correction ``R d`` from the explicit free angular velocity ``we`` to the implicit-midpoint one
        (body frame: ``Ī (w_f - w0) = dt (tau_b - w̄ x Ī w̄)``, ``w̄ = (w0 + w_f) / 2``): ``GYRO_ITERATIONS`` Newton
        steps on ``F(d) = Ī d + dt (w̄ x Ī' w̄ - w0 x Ī' w0)``, ``w̄ = R^T (w0 + we) / 2 + d / 2``, ``Ī' = Ī - Ī_00 1``
        (exactly zero correction for a spherical inertia). docs/conventions.md, "Gyroscopic term";
        ``kamino.jax_ref.dynamics.gyroscopic_correction`` does the same operations."""
        Dv = Ib - Ib[0, 0] * wp.identity(n=3, dtype=scalar)
        Rt = wp.transpose(R)
        a = Rt * w0
        mid = Rt * (scalar(0.5) * (w0 + we))
        g0 = wp.cross(a, Dv * a)
        d = vec3()
        for _k in range(GYRO_ITERATIONS):
            wm = mid + scalar(0.5) * d
            Dw = Dv * wm
            F = Ib * d + dt * (wp.cross(wm, Dw) - g0)
            Jac = Ib + (scalar(0.5) * dt) * (wp.skew(wm) * Dv - wp.skew(Dw))
            d = d - wp.inverse(Jac) * F
        return R * d

    @wp.kernel(module="unique", enable_backward=False)
    def bodies(m: M, w: Work, dt: scalar, h: scalar):
        """World inertia, ``h = (m g, -w x I w) + w_ext + J_dofs^T tau`` (§1.4), free velocity
        ``u_f = u + dt M^-1 h`` with the implicit-midpoint gyroscopic term (:func:`gyroscopic_correction`,
        docs/conventions.md "Gyroscopic term") and the predicted pose ``q_eval ⊕ h u_f`` (curvature term, §5)."""
        wid, i = wp.tid()
        if i >= m.body_count[wid]:
            return
        b = m.body_start[wid] + i
        x = w.q_eval[b]
        R = wp.quat_to_matrix(wp.transform_get_rotation(x))
        I = R * m.inertia[b] * wp.transpose(R)
        I = scalar(0.5) * (I + wp.transpose(I))
        Ii = R * m.inv_inertia[b] * wp.transpose(R)
        Ii = scalar(0.5) * (Ii + wp.transpose(Ii))
        w.inertia_w[b] = I
        w.inv_inertia_w[b] = Ii
        # explicit joint efforts on this body (deterministic: scan the world's DoFs)
        ext = w.wrench[b]
        d0 = m.dof_start[wid]
        for k in range(m.dof_count[wid]):
            d = d0 + k
            tau = w.tau_explicit[d]
            if tau != scalar(0.0):
                j = m.dof_joint[d]
                if m.joint_child[j] == b:
                    ext += tau * w.dof_JF[d]
                if m.joint_parent[j] == b:
                    ext += tau * w.dof_JB[d]
        u = w.u[b]
        om = ang(u)
        hf = twist(m.mass[b] * m.gravity[wid], -wp.cross(om, I * om)) + ext
        uf = u + dt * inverse_mass_times(m.inv_mass[b], Ii, hf)
        uf = twist(lin(uf), ang(uf) + gyroscopic_correction(m.inertia[b], R, om, ang(uf), dt))
        w.u_f[b] = uf
        w.q_pred[b] = integrate_pose(x, uf, h)

    @wp.kernel(module="unique", enable_backward=False)
    def dof_rates(m: M, w: Work):
        """DoF velocities before the step and of the free motion, DoF positions at the predicted pose."""
        wid, i = wp.tid()
        if i >= m.dof_count[wid]:
            return
        d = m.dof_start[wid] + i
        j = m.dof_joint[d]
        bF = m.joint_child[j]
        bB = m.joint_parent[j]
        w.qd_minus[d] = body_dot(w.u, bF, w.dof_JF[d]) + body_dot(w.u, bB, w.dof_JB[d])
        w.qd_free[d] = body_dot(w.u_f, bF, w.dof_JF[d]) + body_dot(w.u_f, bB, w.dof_JB[d])
        w.q_dof_pred[d] = kf.dof_position(m, w.q_pred, d)

    @wp.func
    def dof_row(m: M, w: Work, r: int, nblk: int, d: int, sign: scalar):
        j = m.dof_joint[d]
        set_blocks(w, r, nblk, m.joint_child[j], sign * w.dof_JF[d], m.joint_parent[j], sign * w.dof_JB[d])

    @wp.kernel(module="unique", enable_backward=False)
    def dyn_rows(m: M, w: Work, nblk: int, dt: scalar, h: scalar):
        """Joint-dynamics rows (docs/formulation.md §3.2; ``dynamics_rows`` of the JAX reference): implicit inertia
        ``m`` (``R = 1/m``), bias ``-p0/m`` and the effort bound of actuator rows."""
        wid, i = wp.tid()
        if i >= m.dyn_count[wid]:
            return
        k = m.dyn_start[wid] + i
        d = m.dyn_dof[k]
        r = ridx(m, w, wid, i)
        dof_row(m, w, r, nblk, d, scalar(1.0))
        q = w.q_dof[d]
        mi = scalar(0.0)
        p0 = scalar(0.0)
        bound = inf
        if m.dyn_kind[k] == DYN_ACTUATOR:
            kp = scalar(0.0)
            if m.act_mode[d] == _POSITION:
                kp = m.kp[d]
            kd = m.kd[d]
            mi = dt * (kd + h * kp)
            p0 = dt * (w.effort[d] + kp * (w.position_target[d] - q) + kd * w.velocity_target[d])
            bound = dt * m.effort_limit[d]
            w.row_info[r] = row_info(ROW_ACTUATOR, d, scalar(1.0))
            w.f0[r] = w.act_force[d]
        else:
            a = m.armature[d]
            ks = m.stiffness[d]
            mi = a + dt * m.damping[d] + dt * h * ks
            p0 = a * w.qd_minus[d] + dt * ks * (m.springref[d] - q)
            w.row_info[r] = row_info(ROW_PASSIVE, d, scalar(1.0))
            w.f0[r] = w.pas_force[d]
        mi = wp.max(mi, scalar(1e-30))
        w.reg[r] = scalar(1.0) / mi
        w.vstar[r] = -p0 / mi
        w.lo[r] = -bound
        w.hi[r] = bound
        w.v0[r] = scalar(0.0)

    gamma = scalar(MIDPOINT_DAMPING)

    @wp.func
    def stabilisation_bias(e: scalar, e_start: scalar, c: scalar, alpha: scalar, delta: scalar, midpoint: int):
        """``h v*`` of a joint or coupling row (``joint_bias`` of the JAX reference; docs/conventions.md
        "Stabilisation"): the end-of-step target ``(1 - alpha) e_start``, plus for the midpoint rule the share
        ``MIDPOINT_DAMPING`` of the first half-step's move ``e - e_start - c`` (which damps the alternating mode),
        and the curvature term ``c``, each through the dead band."""
        target = (scalar(1.0) - alpha) * e_start
        if midpoint != 0:
            target += gamma * (e - e_start - c)
        return deadband(e - target, delta) + deadband(c, delta)

    @wp.kernel(module="unique", enable_backward=False)
    def joint_rows(m: M, w: Work, nblk: int, h: scalar, alpha: scalar, delta: scalar, curvature: int,
                   midpoint: int):
        """Kinematic joint rows: blocks and the stabilisation bias of ``joint_bias`` (docs/formulation.md §5;
        docs/conventions.md "Stabilisation")."""
        wid, i = wp.tid()
        if i >= m.cts_count[wid]:
            return
        c = m.cts_start[wid] + i
        r = ridx(m, w, wid, m.dyn_count[wid] + i)
        j = m.cts_joint[c]
        e, JF, JB = kf.cts_row(m, w.q_eval, c)
        set_blocks(w, r, nblk, m.joint_child[j], JF, m.joint_parent[j], JB)
        e_start = e
        if midpoint != 0:
            e_start = kf.cts_residual(m, w.q, c)
        cv = scalar(0.0)
        if curvature != 0:
            e_pred = kf.cts_residual(m, w.q_pred, c)
            cv = e_pred - e - h * row_dot(w, r, nblk, w.u_f)
        w.vstar[r] = stabilisation_bias(e, e_start, cv, alpha, delta, midpoint) / h
        w.reg[r] = scalar(0.0)
        w.lo[r] = -inf
        w.hi[r] = inf
        w.f0[r] = w.kin_force[c]
        w.v0[r] = scalar(0.0)
        w.row_info[r] = row_info(ROW_JOINT, c, scalar(1.0))

    @wp.kernel(module="unique", enable_backward=False)
    def predict_with(m: M, w: Work, h: scalar):
        """``q_pred = q_eval ⊕ h u_new``: the predicted pose along the solved velocity (curvature refinement)."""
        wid, i = wp.tid()
        if i >= m.body_count[wid]:
            return
        b = m.body_start[wid] + i
        w.q_pred[b] = integrate_pose(w.q_eval[b], w.u_new[b], h)

    @wp.func
    def free_velocity(w: Work, r: int, nblk: int):
        """``v_f = J u_f + v*`` of row ``r`` (``solver.prebake``; recomputed, the same sums, by :func:`set_bias`)."""
        vf = w.vstar[r]
        for k in range(nblk):
            b = w.row_body[r * nblk + k]
            if b >= 0:
                vf += wp.dot(w.row_J[r * nblk + k], w.u_f[b])
        return vf

    @wp.func
    def set_bias(w: Work, r: int, nblk: int, vs: scalar):
        """Replace row ``r``'s bias and ``v~_f = P (v_f - v* + vs)``. ``v_f`` is not stored: it is recomputed from the
        row's blocks and ``u_f`` (unchanged since ``solver.prebake``) with the old bias, so that the sum equals the
        stored one's bit for bit."""
        vf = free_velocity(w, r, nblk) - w.vstar[r] + vs
        w.vt[r] = w.P[r] * vf
        w.vstar[r] = vs

    @wp.kernel(module="unique", enable_backward=False)
    def refine_joint_rows(m: M, w: Work, nblk: int, h: scalar, alpha: scalar, delta: scalar, midpoint: int):
        """The joint rows' bias with the curvature term predicted along the solved velocity ``u_new``
        (``SolverConfig.curvature_refinement``; ``joint_bias`` of the JAX reference with ``u_pred = u+``)."""
        wid, i = wp.tid()
        if i >= m.cts_count[wid]:
            return
        c = m.cts_start[wid] + i
        r = ridx(m, w, wid, m.dyn_count[wid] + i)
        e = kf.cts_residual(m, w.q_eval, c)
        e_start = e
        if midpoint != 0:
            e_start = kf.cts_residual(m, w.q, c)
        e_pred = kf.cts_residual(m, w.q_pred, c)
        cv = e_pred - e - h * row_dot(w, r, nblk, w.u_new)
        set_bias(w, r, nblk, stabilisation_bias(e, e_start, cv, alpha, delta, midpoint) / h)

    @wp.kernel(module="unique", enable_backward=False)
    def refine_coupling_rows(m: M, w: Work, nblk: int, h: scalar, alpha: scalar, delta: scalar, midpoint: int):
        """The coupling rows' bias along the solved velocity (as :func:`refine_joint_rows`)."""
        wid, i = wp.tid()
        if i >= m.cpl_count[wid]:
            return
        k = m.cpl_start[wid] + i
        r = ridx(m, w, wid, m.dyn_count[wid] + m.cts_count[wid] + i)
        da = m.cpl_dof_a[k]
        db = m.cpl_dof_b[k]
        qb = scalar(0.0)
        qb_pred = scalar(0.0)
        qb0 = scalar(0.0)
        if db >= 0:
            qb = w.q_dof[db]
            qb_pred = kf.dof_position(m, w.q_pred, db)
            qb0 = kf.dof_position(m, w.q, db)
        e, dp = kf.coupling_residual(m, k, w.q_dof[da], qb)
        e_start = e
        if midpoint != 0:
            e_start, dp0 = kf.coupling_residual(m, k, kf.dof_position(m, w.q, da), qb0)
        e_pred, dp1 = kf.coupling_residual(m, k, kf.dof_position(m, w.q_pred, da), qb_pred)
        cv = e_pred - e - h * row_dot(w, r, nblk, w.u_new)
        set_bias(w, r, nblk, stabilisation_bias(e, e_start, cv, alpha, delta, midpoint) / h)

    @wp.kernel(module="unique", enable_backward=False)
    def coupling_rows(m: M, w: Work, nblk: int, h: scalar, alpha: scalar, delta: scalar, curvature: int,
                      midpoint: int):
        """Coupling rows ``q_a - p(q_b)``: blocks ``J_a - p'(q_b) J_b`` (four) and the bias of ``coupling_bias``."""
        wid, i = wp.tid()
        if i >= m.cpl_count[wid]:
            return
        k = m.cpl_start[wid] + i
        r = ridx(m, w, wid, m.dyn_count[wid] + m.cts_count[wid] + i)
        da = m.cpl_dof_a[k]
        db = m.cpl_dof_b[k]
        qb = scalar(0.0)
        qb_pred = scalar(0.0)
        if db >= 0:
            qb = w.q_dof[db]
            qb_pred = w.q_dof_pred[db]
        e, dp = kf.coupling_residual(m, k, w.q_dof[da], qb)
        dof_row(m, w, r, nblk, da, scalar(1.0))
        if db >= 0:
            jb = m.dof_joint[db]
            w.row_body[r * nblk + 2] = m.joint_child[jb]
            w.row_J[r * nblk + 2] = -dp * w.dof_JF[db]
            w.row_body[r * nblk + 3] = m.joint_parent[jb]
            w.row_J[r * nblk + 3] = -dp * w.dof_JB[db]
        e_start = e
        if midpoint != 0:
            # DoF positions at the start pose: only needed by the midpoint rule
            qa0 = kf.dof_position(m, w.q, da)
            qb0 = scalar(0.0)
            if db >= 0:
                qb0 = kf.dof_position(m, w.q, db)
            e_start, dp0 = kf.coupling_residual(m, k, qa0, qb0)
        cv = scalar(0.0)
        if curvature != 0:
            e_pred, dp1 = kf.coupling_residual(m, k, w.q_dof_pred[da], qb_pred)
            cv = e_pred - e - h * row_dot(w, r, nblk, w.u_f)
        w.vstar[r] = stabilisation_bias(e, e_start, cv, alpha, delta, midpoint) / h
        w.reg[r] = scalar(0.0)
        w.lo[r] = -inf
        w.hi[r] = inf
        w.f0[r] = w.cpl_force[k]
        w.v0[r] = scalar(0.0)
        w.row_info[r] = row_info(ROW_COUPLING, k, scalar(1.0))

    @wp.kernel(module="unique", enable_backward=False)
    def limits(m: M, w: Work, h: scalar, margin: scalar, beta: scalar):
        """Which limit rows are active and their bias (docs/formulation.md §4.1; ``limit_rows`` of the JAX
        reference): the nearer limit, active when it can be reached within the step."""
        wid, i = wp.tid()
        if i >= m.lim_count[wid]:
            return
        k = m.lim_start[wid] + i
        d = m.lim_dof[k]
        q = w.q_dof[d]
        r_lo = q - m.lower[d]
        r_hi = m.upper[d] - q
        side = scalar(1.0)
        r = r_lo
        if r_lo > r_hi:
            side = scalar(-1.0)
            r = r_hi
        approach = wp.max(-side * w.qd_free[d], scalar(0.0))
        active = r < margin + h * approach
        w.lim_side[k] = side
        if active:
            w.lim_active[k] = 1
            w.lim_bias[k] = (r - (scalar(1.0) - beta) * wp.min(r, scalar(0.0))) / h
        else:
            w.lim_active[k] = 0
            w.lim_bias[k] = scalar(0.0)

    @wp.kernel(module="unique", enable_backward=False)
    def pack_limits(m: M, w: Work, nblk: int):
        """Append the active limit rows after the fixed rows, in DoF order (deterministic)."""
        wid = wp.tid()
        a0 = m.row_fixed[wid]
        n = int(0)
        for i in range(m.lim_count[wid]):
            k = m.lim_start[wid] + i
            if w.lim_active[k] != 0:
                d = m.lim_dof[k]
                side = w.lim_side[k]
                r = ridx(m, w, wid, a0 + n)
                dof_row(m, w, r, nblk, d, side)
                w.vstar[r] = w.lim_bias[k]
                w.reg[r] = scalar(0.0)
                w.lo[r] = scalar(0.0)
                w.hi[r] = inf
                w.f0[r] = wp.max(side * w.lim_force[d], scalar(0.0))
                w.v0[r] = scalar(0.0)
                w.row_info[r] = row_info(ROW_LIMIT, d, side)
                n += 1
        w.n_lim[wid] = n

    return SimpleNamespace(half_step=half_step, dof_blocks=dof_blocks, bodies=bodies, dof_rates=dof_rates,
                           dyn_rows=dyn_rows, joint_rows=joint_rows, coupling_rows=coupling_rows, limits=limits,
                           pack_limits=pack_limits, predict_with=predict_with, refine_joint_rows=refine_joint_rows,
                           refine_coupling_rows=refine_coupling_rows, set_blocks=set_blocks, row_dot=row_dot,
                           body_dot=body_dot, free_velocity=free_velocity, gyroscopic_correction=gyroscopic_correction)
