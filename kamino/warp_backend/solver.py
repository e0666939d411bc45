"""Delassus assembly and Proximal-ADMM in Warp (docs/formulation.md §7-§8; paper Alg. 1).

Per step: ``v_f = J u_f + v*`` (§5) of the rows' blocks (``M^-1 J^T`` is formed where it is read), then
either the dense Delassus ``D = J M^-1 J^T + R`` is assembled (from the block-sparse rows, or from a
dense per-world ``J``), scaled by the Jacobi preconditioner ``P`` (§7.2) and factorised once by a
Cholesky (§8.1), or PADMM runs matrix-free with a Conjugate Residual solve of the scaled operator
``P J M^-1 J^T P + diag(P^2 R + eta + rho)`` warm-started from the previous ADMM iterate (§8.2).

The PADMM iterations of a world run in one thread (all of a world's vectors stay in its own row
segment, cached near the thread); ``padmm_iterate`` runs up to ``chunk`` iterations and resumes from
the stored iterate, so the host — or ``wp.capture_while`` inside a CUDA graph — relaunches it until
every world has converged or reached its cap (``remaining`` counts the worlds still iterating).
Every step mirrors ``kamino/jax_ref/padmm.py`` (accelerated PADMM with restart, §7.4; residuals,
§7.5).
"""

import functools
from types import SimpleNamespace

import numpy as np
import warp as wp

from kamino.config import NULL_DIRECTION_RATIO, SATURATION_MARGIN
from kamino.warp_backend.cone import cone_funcs
from kamino.warp_backend.indexing import index_funcs
from kamino.warp_backend.model_data import GROUP, model_struct
from kamino.warp_backend.padmm_rules import padmm_funcs
from kamino.warp_backend.rows import row_kernels
from kamino.warp_backend.sparse_llt import pattern_struct, sparse_llt_kernels
from kamino.warp_backend.types import types_of
from kamino.warp_backend.workspace import work_struct

#: ``padmm_iterate``'s linear solve: the dense Cholesky factor, Conjugate Residual, the sparse factor
LINEAR_DENSE, LINEAR_CR, LINEAR_SPARSE = 0, 1, 2
#: ``padmm_iterate``: a new penalty restarts the momentum at the current iterate (``y_hat = y``, ``z_hat = z``)
RESTART_HERE = 3


@functools.cache
def solver_kernels(np_dtype) -> SimpleNamespace:
    T = types_of(np_dtype)
    scalar, vec6 = T.scalar, T.vec6
    M = model_struct(np_dtype)
    Work = work_struct(np_dtype)
    cf = cone_funcs(np_dtype)
    cone_project, de_saxce = cf.cone_project, cf.de_saxce
    ix = index_funcs(np_dtype)
    free_velocity = row_kernels(np_dtype).free_velocity
    ridx, didx, jidx, row_base = ix.ridx, ix.didx, ix.jidx, ix.row_base
    row_saturated, set_saturated, row_mu = ix.row_saturated, ix.set_saturated, ix.row_mu
    pf = padmm_funcs(np_dtype)
    momentum, extrapolated, box_complementarity = pf.momentum, pf.extrapolated, pf.box_complementarity
    balanced_penalty, saturates = pf.balanced_penalty, pf.saturates
    dual_update = pf.dual_update
    residual_weight = pf.residual_weight
    SP = pattern_struct(np_dtype)
    sparse_solve = sparse_llt_kernels(np_dtype).solve_inplace
    factor_tail_sparse = sparse_llt_kernels(np_dtype).factor_tail
    delassus_entry = sparse_llt_kernels(np_dtype).delassus_entry
    inv_mass_times = sparse_llt_kernels(np_dtype).inv_mass_times
    S = GROUP  # storage distance between consecutive entries of a world's dense Delassus matrix (w.D)
    eps = scalar(float(np.finfo(np_dtype).eps))
    big = scalar(float(np.finfo(np_dtype).max))
    null_ratio = scalar(NULL_DIRECTION_RATIO)
    sat_margin = scalar(SATURATION_MARGIN)

    @wp.kernel(module="unique", enable_backward=False)
    def count_rows(m: M, w: Work):
        wid = wp.tid()
        n_box = m.row_fixed[wid] + w.n_lim[wid]
        w.n_box[wid] = n_box
        w.n_rows[wid] = n_box + 3 * w.n_con[wid]
        w.failed[wid] = w.frozen[wid]

    @wp.kernel(module="unique", enable_backward=False)
    def prebake(m: M, w: Work, nblk: int, dense: int):
        """``v_f = J u_f + v*`` of each active row into ``vt`` (which :func:`scale` scales in place); the dense ``J``
        and ``M^-1 J^T`` rows on request."""
        wid, i = wp.tid()
        if i >= w.n_rows[wid]:
            return
        r = ridx(m, w, wid, i)
        w.vt[r] = free_velocity(w, r, nblk)
        if dense != 0:
            nc = 6 * m.body_count[wid]
            for c in range(nc):
                w.Jd[jidx(m, wid, i, c)] = scalar(0.0)
                w.MJd[jidx(m, wid, i, c)] = scalar(0.0)
            b0 = m.body_start[wid]
            for k in range(nblk):
                b = w.row_body[r * nblk + k]
                if b >= 0:
                    J = w.row_J[r * nblk + k]
                    MJ = inv_mass_times(m, w, b, J)
                    for c in range(6):
                        w.Jd[jidx(m, wid, i, 6 * (b - b0) + c)] += J[c]
                        w.MJd[jidx(m, wid, i, 6 * (b - b0) + c)] += MJ[c]

    @wp.kernel(module="unique", enable_backward=False)
    def delassus_sparse(m: M, w: Work, nblk: int):
        """Row ``a`` of ``D = J M^-1 J^T + R`` from the block-sparse rows (blocks meet on shared bodies)."""
        wid, a = wp.tid()
        n = w.n_rows[wid]
        if a >= n:
            return
        for b in range(a, n):
            s = delassus_entry(m, w, wid, a, b, nblk)
            w.D[didx(m, wid, a, b)] = s
            w.D[didx(m, wid, b, a)] = s

    @wp.kernel(module="unique", enable_backward=False)
    def delassus_dense(m: M, w: Work):
        """Row ``a`` of ``D = J M^-1 J^T + R`` from the dense per-world ``J`` (``6 n_bodies`` columns), each entry
        ``(J_a M^-1 J_b^T + J_b M^-1 J_a^T) / 2`` as the sparse rows' (``sparse_llt``'s ``delassus_term``: so that the
        rounding of ``M^-1 J^T`` vanishes on the null space of ``J^T``)."""
        wid, a = wp.tid()
        n = w.n_rows[wid]
        if a >= n:
            return
        nc = 6 * m.body_count[wid]
        for b in range(a, n):
            s = scalar(0.0)
            for c in range(nc):
                s += scalar(0.5) * (w.Jd[jidx(m, wid, a, c)] * w.MJd[jidx(m, wid, b, c)]
                                    + w.Jd[jidx(m, wid, b, c)] * w.MJd[jidx(m, wid, a, c)])
            if b == a:
                s += w.reg[ridx(m, w, wid, a)]
            w.D[didx(m, wid, a, b)] = s
            w.D[didx(m, wid, b, a)] = s

    @wp.func
    def row_diag(m: M, w: Work, wid: int, a: int, nblk: int, assembled: int):
        """``D_aa`` (from the assembled matrix, or from the row's blocks)."""
        if assembled != 0:
            return w.D[didx(m, wid, a, a)]
        return delassus_entry(m, w, wid, a, a, nblk)

    @wp.kernel(module="unique", enable_backward=False)
    def precondition(m: M, w: Work, nblk: int, assembled: int, enabled: int):
        """Jacobi preconditioner ``P = diag(D)^-1/2`` (§7.2); one value per contact from the largest of its
        three diagonal entries (keeps the Coulomb cone invariant)."""
        wid, a = wp.tid()
        n = w.n_rows[wid]
        if a >= n:
            return
        r = ridx(m, w, wid, a)
        if enabled == 0:
            w.P[r] = scalar(1.0)
            return
        n_box = w.n_box[wid]
        d = scalar(0.0)
        if a < n_box:
            d = wp.abs(row_diag(m, w, wid, a, nblk, assembled))
        else:
            c0 = n_box + 3 * ((a - n_box) // 3)
            for t in range(3):
                d = wp.max(d, wp.abs(row_diag(m, w, wid, c0 + t, nblk, assembled)))
        if d > eps:
            w.P[r] = scalar(1.0) / wp.sqrt(d + eps)
        else:
            w.P[r] = scalar(1.0)

    @wp.kernel(module="unique", enable_backward=False)
    def scale(m: M, w: Work, shift: scalar, shift_sat: scalar, impulse_scale: scalar, assembled: int,
              always_sat: int):
        """``v~_f = P v_f`` (in place: ``prebake`` wrote ``v_f`` into ``vt``), scaled bounds (in place: ``lo_s``/
        ``hi_s`` are ``lo``/``hi``, workspace.allocate), and whether an effort-limited fixed row starts saturated (the
        flag in ``w.row_info``, ``set_saturated``: its warm start ``impulse_scale f0 / P`` on a bound, to
        ``SATURATION_MARGIN``; kamino.jax_ref.padmm.solve, "Saturation"; with ``always_sat``, every effort-limited
        row: the CR path, pipeline.Stepper); on the dense path ``D~ = P D P`` row by row with ``shift = eta +
        rho_free`` on the fixed rows' diagonal (``shift_sat`` on the saturated ones; ``padmm_init`` adds the world's
        penalty to the others)."""
        wid, a = wp.tid()
        n = w.n_rows[wid]
        if a >= n:
            return
        r = ridx(m, w, wid, a)
        Pa = w.P[r]
        w.vt[r] = Pa * w.vt[r]  # v_f from prebake
        lo = w.lo[r]
        hi = w.hi[r]
        if wp.isfinite(lo):
            lo = lo / Pa
        if wp.isfinite(hi):
            hi = hi / Pa
        w.lo_s[r] = lo
        w.hi_s[r] = hi
        sat = int(0)
        if a < m.row_fixed[wid]:
            x0 = impulse_scale * w.f0[r] / Pa
            if wp.isfinite(lo) and (always_sat != 0 or x0 <= lo + sat_margin * wp.abs(lo)):
                sat = 1
            if wp.isfinite(hi) and (always_sat != 0 or x0 >= hi - sat_margin * wp.abs(hi)):
                sat = 1
        set_saturated(w, r, sat)
        if assembled != 0:
            for b in range(n):
                k = didx(m, wid, a, b)
                w.D[k] = Pa * w.D[k] * w.P[ridx(m, w, wid, b)]
            if a < m.row_fixed[wid]:
                w.D[didx(m, wid, a, a)] += wp.where(sat != 0, shift_sat, shift)

    @wp.func
    def project_into(m: M, w: Work, wid: int, n_box: int, n: int, src: wp.array(dtype=scalar),
                     shift: wp.array(dtype=scalar), inv_rho: scalar, dst: wp.array(dtype=scalar)):
        """``dst = Pi_K(src - inv_rho * shift)`` (§7.3 step 3): clip on box rows, cones on contacts."""
        rs = w.row_stride
        rb = row_base(m, w, wid)
        for a in range(n_box):
            r = rb + a * rs
            dst[r] = wp.clamp(src[r] - inv_rho * shift[r], w.lo_s[r], w.hi_s[r])
        for c in range((n - n_box) // 3):
            r = rb + (n_box + 3 * c) * rs
            p = cone_project(src[r] - inv_rho * shift[r], src[r + rs] - inv_rho * shift[r + rs],
                             src[r + 2 * rs] - inv_rho * shift[r + 2 * rs], row_mu(w, r))
            dst[r] = p[0]
            dst[r + rs] = p[1]
            dst[r + 2 * rs] = p[2]

    @wp.func
    def factor_tail_dense(m: M, w: Work, wid: int, n: int, shift: scalar):
        """``L_t = chol(S_t + shift I)`` of the dense factor's tail (limit and contact rows): the Schur
        complement ``S_t`` is kept in the tail block's upper triangle and ``sdiag``, so that a new penalty only
        redoes this part (``kamino.jax_ref.padmm.solve``, "Penalty")."""
        rs = w.row_stride
        nf = m.row_fixed[wid]
        rb = row_base(m, w, wid)
        for t in range(n - nf):
            for j in range(t + 1):
                s = scalar(0.0)
                if j == t:
                    s = w.sdiag[rb + (nf + t) * rs] + shift
                else:
                    s = w.D[didx(m, wid, nf + j, nf + t)]
                for i in range(j):
                    s -= w.D[didx(m, wid, nf + t, nf + i)] * w.D[didx(m, wid, nf + j, nf + i)]
                if j == t:
                    s = wp.sqrt(s)
                else:
                    s = s / w.D[didx(m, wid, nf + j, nf + j)]
                w.D[didx(m, wid, nf + t, nf + j)] = s

    @wp.func
    def factor_dense(m: M, w: Work, wid: int, n: int, eta: scalar):
        """The dense Cholesky factor of ``D~`` in place (§8.1): the fixed rows' columns, the tail's Schur
        complement ``S_t`` (upper triangle of the tail block and ``sdiag``), then ``L_t`` for the world's penalty;
        ``L^T`` of the fixed columns is mirrored into the upper triangle so that the backward substitution reads
        rows."""
        rs = w.row_stride
        rb = row_base(m, w, wid)
        nf = wp.min(m.row_fixed[wid], n)
        for j in range(nf):
            s = w.D[didx(m, wid, j, j)]
            for k in range(j):
                l = w.D[didx(m, wid, j, k)]
                s -= l * l
            ljj = wp.sqrt(s)
            w.D[didx(m, wid, j, j)] = ljj
            for i in range(j + 1, n):
                t = w.D[didx(m, wid, i, j)]
                for k in range(j):
                    t -= w.D[didx(m, wid, i, k)] * w.D[didx(m, wid, j, k)]
                w.D[didx(m, wid, i, j)] = t / ljj
        for t in range(n - nf):
            for jj in range(t + 1):
                s = w.D[didx(m, wid, nf + t, nf + jj)]
                for k in range(nf):
                    s -= w.D[didx(m, wid, nf + t, k)] * w.D[didx(m, wid, nf + jj, k)]
                if jj == t:
                    w.sdiag[rb + (nf + t) * rs] = s
                else:
                    w.D[didx(m, wid, nf + jj, nf + t)] = s
        factor_tail_dense(m, w, wid, n, eta + w.rho_u[wid])
        for i in range(n):
            for k in range(wp.min(i, nf)):
                w.D[didx(m, wid, k, i)] = w.D[didx(m, wid, i, k)]

    @wp.kernel(module="unique", enable_backward=False)
    def refactor_dense(m: M, w: Work, nblk: int, shift: scalar, shift_sat: scalar, eta: scalar):
        """The dense factor again for the worlds whose effort-limited rows saturated in the last PADMM iteration
        (``w.pending``; kamino.jax_ref.padmm.solve, "Saturation"): ``D~ = P D P`` from the rows' blocks with the
        new shifts, then :func:`factor_dense` (one thread per world)."""
        wid = wp.tid()
        if w.pending[wid] == 0:
            return
        w.pending[wid] = 0
        n = w.n_rows[wid]
        nf = m.row_fixed[wid]
        for a in range(n):
            ra = ridx(m, w, wid, a)
            for b in range(a, n):
                v = w.P[ra] * delassus_entry(m, w, wid, a, b, nblk) * w.P[ridx(m, w, wid, b)]
                if b == a and a < nf:
                    v += wp.where(row_saturated(w, ra) != 0, shift_sat, shift)
                w.D[didx(m, wid, a, b)] = v
                w.D[didx(m, wid, b, a)] = v
        factor_dense(m, w, wid, n, eta)

    @wp.kernel(module="unique", enable_backward=False)
    def padmm_init(m: M, w: Work, impulse_scale: scalar, use_velocity: int, factorize: int, max_iterations: int,
                   eta: scalar, rho0: scalar, adaptive: int):
        """Warm start (§7.8: ``x0 = Pi_K(impulse0 / P)``, ``z0 = P v0``), the world's penalty and residual scale,
        and with ``factorize`` the dense factor (:func:`factor_dense`)."""
        rs = w.row_stride
        wid = wp.tid()
        rb = row_base(m, w, wid)
        n = w.n_rows[wid]
        p_ref = scalar(0.0)
        for a in range(n):
            r = rb + a * rs
            w.x[r] = impulse_scale * w.f0[r] / w.P[r]
            w.z_p[r] = scalar(0.0)
            if use_velocity != 0:
                w.z_p[r] = w.P[r] * w.v0[r]
            w.z_hat[r] = w.z_p[r]
            p_ref = wp.max(p_ref, w.P[r])
        if p_ref <= scalar(0.0):
            p_ref = scalar(1.0)
        w.p_ref[wid] = p_ref
        if adaptive == 0 or not (w.rho_u[wid] > scalar(0.0)):
            w.rho_u[wid] = rho0
        w.k_rho[wid] = 0
        w.pending[wid] = 0
        project_into(m, w, wid, w.n_box[wid], n, w.x, w.x, scalar(0.0), w.x_p)
        for a in range(n):
            r = rb + a * rs
            w.y_p[r] = w.x_p[r]
            w.y_hat[r] = w.x_p[r]
        w.a_p[wid] = scalar(1.0)
        w.c_p[wid] = big
        w.iters[wid] = 0
        w.it_cap[wid] = max_iterations
        w.r_p[wid] = scalar(0.0)
        w.r_d[wid] = scalar(0.0)
        w.r_c[wid] = scalar(0.0)
        w.converged[wid] = int(n == 0 and w.frozen[wid] == 0)
        w.done[wid] = int(n == 0 or w.frozen[wid] != 0)  # a frozen world does not iterate
        if w.done[wid] != 0:
            wp.atomic_sub(w.remaining, 0, 1)
        if factorize != 0:
            factor_dense(m, w, wid, n, eta)

    @wp.func
    def cho_solve_inplace(m: M, w: Work, wid: int, n: int):
        """``x <- L^-T L^-1 x`` with the cached factor (forward, then backward substitution reading ``L^T``
        from the upper triangle, and from the lower one in the tail block)."""
        rs = w.row_stride
        rb = row_base(m, w, wid)
        g = wid // GROUP
        db = m.grp_mat_start[g] + (wid - g * GROUP)  # didx(m, wid, i, k) = db + (i * md + k) * S
        md = m.grp_maxdim[g]
        for i in range(n):
            s = w.x[rb + i * rs]
            for k in range(i):
                s -= w.D[db + (i * md + k) * S] * w.x[rb + k * rs]
            w.x[rb + i * rs] = s / w.D[db + (i * md + i) * S]
        nf = m.row_fixed[wid]
        for ii in range(n):
            i = n - 1 - ii
            s = w.x[rb + i * rs]
            if i >= nf:  # the tail block keeps its Schur complement in the upper triangle: read L by columns
                for k in range(i + 1, n):
                    s -= w.D[db + (k * md + i) * S] * w.x[rb + k * rs]
            else:
                for k in range(i + 1, n):
                    s -= w.D[db + (i * md + k) * S] * w.x[rb + k * rs]
            w.x[rb + i * rs] = s / w.D[db + (i * md + i) * S]

    @wp.func
    def apply_operator(m: M, w: Work, wid: int, n: int, nblk: int, shift_f: scalar, shift_b: scalar,
                       shift_t: scalar, v: wp.array(dtype=scalar), out: wp.array(dtype=scalar)):
        """``out = (P J M^-1 J^T P + diag(P^2 R + eta + rho)) v`` matrix-free (§8.2): ``cr_w = M^-1 J^T P v`` per
        body, then ``J cr_w``; with ``eta + rho = shift_f`` on the fixed rows (``shift_b`` on those with a finite
        bound) and ``shift_t`` on the limit and contact rows."""
        rs = w.row_stride
        rb = row_base(m, w, wid)
        b0 = m.body_start[wid]
        for i in range(m.body_count[wid]):
            w.cr_w[b0 + i] = vec6()
        for a in range(n):
            r = rb + a * rs
            pv = w.P[r] * v[r]
            for k in range(nblk):
                b = w.row_body[r * nblk + k]
                if b >= 0:
                    w.cr_w[b] = w.cr_w[b] + pv * w.row_J[r * nblk + k]
        for i in range(m.body_count[wid]):
            w.cr_w[b0 + i] = inv_mass_times(m, w, b0 + i, w.cr_w[b0 + i])
        for a in range(n):
            r = rb + a * rs
            s = scalar(0.0)
            for k in range(nblk):
                b = w.row_body[r * nblk + k]
                if b >= 0:
                    s += wp.dot(w.row_J[r * nblk + k], w.cr_w[b])
            Pa = w.P[r]
            shift = shift_t
            if a < m.row_fixed[wid]:
                shift = wp.where(row_saturated(w, r) != 0, shift_b, shift_f)
            out[r] = Pa * s + (Pa * Pa * w.reg[r] + shift) * v[r]

    @wp.func
    def cr_solve(m: M, w: Work, wid: int, n: int, nblk: int, shift_f: scalar, shift_b: scalar, shift_t: scalar,
                 budget: int):
        """Conjugate Residual on ``A x = b`` (``b`` in ``y``), from ``x = x_p`` (§8.2): one operator
        application per iteration, at most ``budget`` iterations. It stops early only when the residual has
        vanished to rounding (``|r|^2 <= 1e-30 |b|^2``, or exactly zero) or the recurrence breaks down
        (``|A p|^2 = 0`` or ``r^T A r = 0``): any looser stop would cap the accuracy of the linear solve at a
        level that, unscaled by ``1/P``, sits at PADMM's tolerance and stalls it. On exit ``cr_r`` holds the
        residual ``b - A x`` (the recurrence's, which follows the true one to rounding); ``padmm_iterate``
        folds it into the dual residual, so a world converges only when its linear solves are accurate to
        the tolerance too."""
        rs = w.row_stride
        rb = row_base(m, w, wid)
        for a in range(n):
            w.x[rb + a * rs] = w.x_p[rb + a * rs]
        apply_operator(m, w, wid, n, nblk, shift_f, shift_b, shift_t, w.x, w.cr_Ar)
        bb = scalar(0.0)
        for a in range(n):
            r = rb + a * rs
            w.cr_r[r] = w.y[r] - w.cr_Ar[r]
            w.cr_p[r] = w.cr_r[r]
            bb += w.y[r] * w.y[r]
        apply_operator(m, w, wid, n, nblk, shift_f, shift_b, shift_t, w.cr_r, w.cr_Ar)
        zeta = scalar(0.0)
        for a in range(n):
            r = rb + a * rs
            w.cr_Ap[r] = w.cr_Ar[r]
            zeta += w.cr_r[r] * w.cr_Ar[r]
        stop = scalar(1e-30) * bb
        for it in range(budget):
            rr = scalar(0.0)
            pp = scalar(0.0)
            for a in range(n):
                r = rb + a * rs
                rr += w.cr_r[r] * w.cr_r[r]
                pp += w.cr_Ap[r] * w.cr_Ap[r]
            if rr <= stop or pp <= scalar(0.0) or zeta == scalar(0.0):
                break
            alpha = zeta / pp
            for a in range(n):
                r = rb + a * rs
                w.x[r] += alpha * w.cr_p[r]
                w.cr_r[r] -= alpha * w.cr_Ap[r]
            apply_operator(m, w, wid, n, nblk, shift_f, shift_b, shift_t, w.cr_r, w.cr_Ar)
            zeta_new = scalar(0.0)
            for a in range(n):
                zeta_new += w.cr_r[rb + a * rs] * w.cr_Ar[rb + a * rs]
            beta = zeta_new / zeta
            zeta = zeta_new
            for a in range(n):
                r = rb + a * rs
                w.cr_p[r] = w.cr_r[r] + beta * w.cr_p[r]
                w.cr_Ap[r] = w.cr_Ar[r] + beta * w.cr_Ap[r]

    @wp.func
    def row_penalty(w: Work, r: int, a: int, nf: int, rho_free: scalar, rho_box: scalar, rho_u: scalar):
        """Row ``a``'s penalty (``kamino.jax_ref.padmm.solve``, "Penalty" and "Saturation"): ``rho_free`` on a fixed
        row, ``rho_box`` on a saturated effort-limited one (a flag), the world's ``rho_u`` on limit and contact
        rows."""
        if a >= nf:
            return rho_u
        if row_saturated(w, r) != 0:
            return rho_box
        return rho_free

    @wp.kernel(module="unique", enable_backward=False)
    def padmm_iterate(m: M, w: Work, sp: SP, chunk: int, nblk: int, linear: int, cr_budget: int,
                      eta: scalar, rho_free: scalar, rho_box: scalar, tol: scalar, restart_tol: scalar,
                      accelerate: int, fixed: int, adaptive: int):
        """Up to ``chunk`` accelerated PADMM iterations of one world (§7.3-§7.5; ``padmm.solve`` of the JAX
        reference, its penalty rule and residuals included), resuming from the stored iterate; a world that
        converges (unless ``fixed``) or reaches its iteration cap ``it_cap`` is marked done and leaves
        ``remaining``. The fixed rows carry the penalty ``rho_free`` (``rho_box`` on a saturated effort-limited
        actuator), the limit and contact rows the world's ``rho_u``, rebalanced when ``adaptive`` (then
        the tail of the factor is recomputed). A row that saturates ends the launch with ``w.pending`` set:
        ``refactor`` (or ``refactor_dense``) redoes the factor before the next launch (kamino.jax_ref.padmm.solve,
        "Saturation"). ``linear``: ``LINEAR_DENSE``, ``LINEAR_CR`` or ``LINEAR_SPARSE`` (``sparse_llt.py``)."""
        rs = w.row_stride
        wid = wp.tid()
        rb = row_base(m, w, wid)
        if w.done[wid] != 0:
            return
        n = w.n_rows[wid]
        n_box = w.n_box[wid]
        nf = m.row_fixed[wid]
        p_ref = w.p_ref[wid]
        rho_u = w.rho_u[wid]
        for step in range(chunk):
            # steps 1-2: De Saxcé correction s = Gamma(z_hat), rhs (into x for the in-place LLT solves, into y
            # as CR's right-hand side), linear solve
            rhs = w.x
            if linear == LINEAR_CR:
                rhs = w.y
            for a in range(n):
                r = rb + a * rs
                rho = row_penalty(w, r, a, nf, rho_free, rho_box, rho_u)
                rhs[r] = -w.vt[r] + eta * w.x_p[r] + rho * w.y_hat[r] + w.z_hat[r]
            for c in range((n - n_box) // 3):
                r = rb + (n_box + 3 * c) * rs
                rhs[r + 2 * rs] -= de_saxce(w.z_hat[r], w.z_hat[r + rs], row_mu(w, r))
            if linear == LINEAR_CR:
                cr_solve(m, w, wid, n, nblk, eta + rho_free, eta + rho_box, eta + rho_u, cr_budget)
            elif linear == LINEAR_SPARSE:
                sparse_solve(m, w, sp, wid, n)
            else:
                cho_solve_inplace(m, w, wid, n)
            # steps 3-4: projection, dual update and the residuals (complementarity is scaling-invariant), one
            # pass over the box rows and one over the contact triples
            r_p = scalar(0.0)
            r_d = scalar(0.0)
            r_c = scalar(0.0)
            c_sum = scalar(0.0)
            # the null-direction test (kamino.jax_ref.padmm.solve, "Null directions"): the dual residual of the
            # rows that are not free (penalty rho_free), and on the free rows the change of the residual vector e
            # against the change of the impulse
            r_tail = scalar(0.0)
            de = scalar(0.0)
            dx = scalar(0.0)
            hit = int(0)  # effort-limited rows inside their box whose projection clips them ("Saturation")
            for a in range(n_box):
                r = rb + a * rs
                rho = row_penalty(w, r, a, nf, rho_free, rho_box, rho_u)
                x = w.x[r]
                z_hat = w.z_hat[r]
                lo = w.lo_s[r]
                hi = w.hi_s[r]
                v = x - z_hat / rho
                y = wp.clamp(v, lo, hi)
                w.y[r] = y
                if a < nf and saturates(row_saturated(w, r), lo, hi, v, y):
                    hit = 1
                du = dual_update(x, y, w.x_p[r], w.y_hat[r], z_hat, w.P[r], eta, rho, p_ref)
                w.z[r] = du[0]
                r_p = wp.max(r_p, du[1])
                r_d = wp.max(r_d, du[2])
                c_sum += du[3]
                r_c = wp.max(r_c, box_complementarity(y, du[0], lo, hi))
                if adaptive != 0 and a < nf and not (wp.isfinite(lo) or wp.isfinite(hi)):
                    e = eta * (x - w.x_p[r]) + rho * (y - w.y_hat[r])
                    de = wp.max(de, wp.abs(e - w.e_p[r]))
                    dx = wp.max(dx, wp.abs(x - w.x_p[r]))
                    w.e_p[r] = e
                else:
                    r_tail = wp.max(r_tail, du[2])
            inv_rho = scalar(1.0) / rho_u
            for c in range((n - n_box) // 3):
                r = rb + (n_box + 3 * c) * rs
                cp = cone_project(w.x[r] - inv_rho * w.z_hat[r], w.x[r + rs] - inv_rho * w.z_hat[r + rs],
                                  w.x[r + 2 * rs] - inv_rho * w.z_hat[r + 2 * rs], row_mu(w, r))
                yz = scalar(0.0)
                for t in range(3):
                    rt = r + t * rs
                    y = cp[t]
                    w.y[rt] = y
                    du = dual_update(w.x[rt], y, w.x_p[rt], w.y_hat[rt], w.z_hat[rt], w.P[rt], eta, rho_u, p_ref)
                    w.z[rt] = du[0]
                    r_p = wp.max(r_p, du[1])
                    r_d = wp.max(r_d, du[2])
                    r_tail = wp.max(r_tail, du[2])
                    c_sum += du[3]
                    yz += y * du[0]
                r_c = wp.max(r_c, wp.abs(yz))
            if linear == LINEAR_CR:
                # the inner solve's residual b - A x, a scaled velocity like the dual residual's rows: an
                # inexact solve (a small cr_iterations budget) must not let the world report convergence
                for a in range(n):
                    r_d = wp.max(r_d, residual_weight(w.P[rb + a * rs], p_ref) * wp.abs(w.cr_r[rb + a * rs]))
                    r_tail = wp.max(r_tail, residual_weight(w.P[rb + a * rs], p_ref) * wp.abs(w.cr_r[rb + a * rs]))
            k = w.iters[wid] + 1
            converged = k >= 2 and r_p <= tol and r_d <= tol and r_c <= tol
            # or a least-squares solution along a numerically null direction (e_p of iteration 1 is stale: k >= 2)
            if k >= 2 and r_p <= tol and r_tail <= tol and r_c <= tol and dx > scalar(0.0):
                if de <= null_ratio * (eta + rho_free) * dx:
                    converged = True
            # §7.4: Fast ADMM with restart
            mom = momentum(w.a_p[wid], w.c_p[wid], c_sum, restart_tol, accelerate)
            beta = mom[2]
            mode = int(mom[3])
            a_new = mom[0]
            c_new = mom[1]
            # the limit and contact rows' penalty (residual balancing); a change restarts the momentum from
            # this iterate and refactorises the tail. An effort-limited row that saturates takes rho_box from now
            # on: the momentum restarts, and the whole factor is redone before the next iteration (w.pending:
            # refactor / refactor_dense after this launch; kamino.jax_ref.padmm.solve, "Saturation")
            switch = adaptive != 0 and hit != 0 and not converged
            if adaptive != 0 and n > nf and not converged:
                rho_n = balanced_penalty(rho_u, r_p, r_d, k, w.k_rho[wid])
                if rho_n != rho_u:
                    rho_u = rho_n
                    w.rho_u[wid] = rho_n
                    w.k_rho[wid] = k
                    mode = RESTART_HERE
                    a_new = scalar(1.0)
                    c_new = big
                    if linear == LINEAR_SPARSE and not switch:
                        factor_tail_sparse(m, w, sp, wid, n, eta + rho_u)
                    elif linear == LINEAR_DENSE and not switch:
                        factor_tail_dense(m, w, wid, n, eta + rho_u)
            if switch:
                for a in range(nf):
                    r = rb + a * rs
                    if saturates(row_saturated(w, r), w.lo_s[r], w.hi_s[r], w.x[r] - w.z_hat[r] / rho_free, w.y[r]):
                        set_saturated(w, r, 1)
                mode = RESTART_HERE
                a_new = scalar(1.0)
                c_new = big
                w.k_rho[wid] = k
                if linear != LINEAR_CR:
                    w.pending[wid] = 1
            for a in range(n):
                r = rb + a * rs
                y = w.y[r]
                z = w.z[r]
                if mode == RESTART_HERE:
                    w.y_hat[r] = y
                    w.z_hat[r] = z
                else:
                    w.y_hat[r] = extrapolated(y, w.y_p[r], beta, mode)
                    w.z_hat[r] = extrapolated(z, w.z_p[r], beta, mode)
                w.x_p[r] = w.x[r]
                w.y_p[r] = y
                w.z_p[r] = z
            w.a_p[wid] = a_new
            w.c_p[wid] = c_new
            w.iters[wid] = k
            w.r_p[wid] = r_p
            w.r_d[wid] = r_d
            w.r_c[wid] = r_c
            if (converged and fixed == 0) or k >= w.it_cap[wid]:
                w.converged[wid] = int(converged)
                w.done[wid] = 1
                wp.atomic_sub(w.remaining, 0, 1)
                return
            if w.pending[wid] != 0:
                return

    @wp.kernel(module="unique", enable_backward=False)
    def padmm_resume(m: M, w: Work, max_iterations: int):
        """Restart PADMM from its last iterate (``y_hat = y``, ``z_hat = z``, no momentum) for up to
        ``max_iterations`` more iterations, after the right-hand side changed (curvature refinement)."""
        wid = wp.tid()
        n = w.n_rows[wid]
        for a in range(n):
            r = ridx(m, w, wid, a)
            w.y_hat[r] = w.y_p[r]
            w.z_hat[r] = w.z_p[r]
        w.a_p[wid] = scalar(1.0)
        w.c_p[wid] = big
        w.it_cap[wid] = w.iters[wid] + max_iterations
        w.k_rho[wid] = w.iters[wid]
        w.converged[wid] = int(n == 0 and w.frozen[wid] == 0)
        w.done[wid] = int(n == 0 or w.frozen[wid] != 0)
        if w.done[wid] != 0:
            wp.atomic_sub(w.remaining, 0, 1)

    @wp.kernel(module="unique", enable_backward=False)
    def padmm_finish(m: M, w: Work):
        """Unscale (§7.7): ``lambda = P y``, ``v+ = (z - Gamma(z)) / P``; a non-finite impulse fails the world."""
        rs = w.row_stride
        wid, a = wp.tid()
        n = w.n_rows[wid]
        if a >= n:
            return
        r = ridx(m, w, wid, a)
        n_box = w.n_box[wid]
        Pa = w.P[r]
        lam = Pa * w.y_p[r]
        z = w.z_p[r]
        if a >= n_box and (a - n_box) % 3 == 2:
            z -= de_saxce(w.z_p[r - 2 * rs], w.z_p[r - rs], row_mu(w, r))
        w.impulse[r] = lam
        w.velocity[r] = z / Pa
        if not wp.isfinite(lam):
            w.failed[wid] = 1

    return SimpleNamespace(count_rows=count_rows, prebake=prebake, delassus_sparse=delassus_sparse,
                           delassus_dense=delassus_dense, precondition=precondition, scale=scale,
                           padmm_init=padmm_init, padmm_resume=padmm_resume, padmm_iterate=padmm_iterate,
                           refactor_dense=refactor_dense,
                           padmm_finish=padmm_finish)
