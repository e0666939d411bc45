"""Delassus assembly and Proximal-ADMM in Warp, one thread per world (docs/formulation.md §7-§8; paper Alg. 1).

Per step: ``v_f = J u_f + v*`` (§5) of the rows' blocks (``M^-1 J^T`` is formed where it is read), then
either the dense Delassus ``D = J M^-1 J^T + R`` is assembled (from the block-sparse rows, or from a
dense per-world ``J``), scaled by the Jacobi preconditioner ``P`` (§7.2) and factorised once by a
Cholesky (§8.1), or PADMM runs matrix-free with a Conjugate Residual solve of the scaled operator
``P J M^-1 J^T P + diag(P^2 R + eta + rho)`` warm-started from the previous ADMM iterate (§8.2, ``linear_solve_cr.py``).

The PADMM iterations of a world run in one thread (all of a world's vectors stay in its own row
segment, cached near the thread); ``padmm_iterate_kernel``'s kernel runs up to ``chunk`` iterations and resumes from
the stored iterate, so the host — or ``wp.capture_while`` inside a CUDA graph — relaunches it until
every world has converged or reached its cap (``remaining`` counts the worlds still iterating).
Every rule of an iteration is ``solver_rules.py``'s, shared with the 32-thread schedule (``solver_lanes.py``) and
mirroring ``kamino/jax_ref/solver.py`` (accelerated PADMM with restart, §7.4; residuals, §7.5). Each kernel and
``wp.func`` comes from a small builder cached per precision; the linear solve and the penalty rule of
``padmm_iterate_kernel`` are compile-time.
"""
import functools
from types import SimpleNamespace

import numpy as np
import warp as wp

from kamino.config import SATURATION_MARGIN
from kamino.warp_backend import solver_rules as rules
from kamino.warp_backend.cone import cone_funcs
from kamino.warp_backend.indexing import index_funcs
from kamino.warp_backend.linear_solve import sparse_llt_kernels
from kamino.warp_backend.linear_solve_cr import cr_solve_func
from kamino.warp_backend.model_data import GROUP
from kamino.warp_backend.rows import row_kernels
from kamino.warp_backend.workspace import builder_types

#: ``padmm_iterate_kernel``'s linear solve: the dense Cholesky factor, Conjugate Residual, the sparse factor
LINEAR_DENSE, LINEAR_CR, LINEAR_SPARSE = 0, 1, 2


# --- rows, Delassus matrix, preconditioner (§5, §7.2, §8.1) -----------------------------------------------------

@functools.cache
def world_row_func(np_dtype):
    """Where an active row of a world is stored.
    ``world_row(m, row_stride, n_rows, wid, a)``: the row kernels launched over ``(worlds, max_rows)`` start with
    it."""
    M = builder_types(np_dtype).M
    ridx = index_funcs(np_dtype).ridx

    @wp.func
    def world_row(m: M, row_stride: int, n_rows: wp.array(dtype=wp.int32), wid: int, a: int):
        """Storage index of row ``a`` of world ``wid``, or -1 past the world's active rows (``n_rows``)."""
        if a >= n_rows[wid]:
            return -1
        return ridx(m, row_stride, wid, a)

    return world_row


@functools.cache
def count_rows_kernel(np_dtype):
    """The world's active rows (§7.1: the fixed and limit rows, then three per contact).
    ``count_rows(m, n_lim, n_con, frozen, n_box, n_rows, failed)``, one thread per world, after the limit rows are
    packed and the contacts counted."""
    M = builder_types(np_dtype).M
    iarr = wp.array(dtype=wp.int32)

    @wp.kernel(module="unique", enable_backward=False)
    def count_rows(
        # model (read only)
        m: M,
        # in
        n_lim: iarr, n_con: iarr, frozen: iarr,
        # out
        n_box: iarr, n_rows: iarr, failed: iarr,
    ):
        """``n_box`` (fixed and limit rows), ``n_rows``; a frozen world starts failed."""
        wid = wp.tid()
        nb = m.row_fixed[wid] + n_lim[wid]
        n_box[wid] = nb
        n_rows[wid] = nb + 3 * n_con[wid]
        failed[wid] = frozen[wid]

    return count_rows


@functools.cache
def prebake_kernel(np_dtype, dense: bool):
    """The free velocity ``v_f = J u_f + v*`` of the rows (§5), and with ``dense`` (compile-time) the dense ``J``.
    ``prebake(m, nblk, row_stride, n_rows, vstar, row_body, row_J, u_f, inv_inertia_w, vt, Jd, MJd)``, one thread per
    row slot ``(worlds, max_rows)``."""
    scalar, M, vec6, mat33 = builder_types(np_dtype).take("scalar", "M", "vec6", "mat33")
    farr, iarr = wp.array(dtype=scalar), wp.array(dtype=wp.int32)
    free_velocity = row_kernels(np_dtype).free_velocity
    jidx = index_funcs(np_dtype).jidx
    inv_mass_times = sparse_llt_kernels(np_dtype).inv_mass_times
    world_row = world_row_func(np_dtype)

    @wp.kernel(module="unique", enable_backward=False)
    def prebake(
        # model (read only)
        m: M,
        # in
        nblk: int,
        row_stride: int,
        n_rows: iarr, vstar: farr, row_body: iarr, row_J: wp.array(dtype=vec6), u_f: wp.array(dtype=vec6),
        inv_inertia_w: wp.array(dtype=mat33),
        # out
        vt: farr, Jd: farr, MJd: farr,
    ):
        """``v_f = J u_f + v*`` of each active row into ``vt`` (which ``scale`` scales in place); the dense ``J``
        and ``M^-1 J^T`` rows with ``dense``."""
        wid, i = wp.tid()
        r = world_row(m, row_stride, n_rows, wid, i)
        if r < 0:
            return
        vt[r] = free_velocity(vstar, row_body, row_J, u_f, r, nblk)
        if wp.static(dense):
            nc = 6 * m.body_count[wid]
            for c in range(nc):
                Jd[jidx(m, wid, i, c)] = scalar(0.0)
                MJd[jidx(m, wid, i, c)] = scalar(0.0)
            b0 = m.body_start[wid]
            for k in range(nblk):
                b = row_body[r * nblk + k]
                if b >= 0:
                    J = row_J[r * nblk + k]
                    MJ = inv_mass_times(m, inv_inertia_w, b, J)
                    for c in range(6):
                        Jd[jidx(m, wid, i, 6 * (b - b0) + c)] += J[c]
                        MJd[jidx(m, wid, i, 6 * (b - b0) + c)] += MJ[c]

    return prebake


@functools.cache
def delassus_sparse_kernel(np_dtype):
    """The dense Delassus matrix ``D = J M^-1 J^T + R`` from the block-sparse rows (§8.1).
    ``delassus_sparse(m, nblk, row_stride, n_rows, row_body, row_J, reg, inv_inertia_w, D)``, one thread per row
    slot: row ``a`` fills ``D_ab = D_ba``, ``b >= a``."""
    scalar, M, vec6, mat33 = builder_types(np_dtype).take("scalar", "M", "vec6", "mat33")
    farr, iarr = wp.array(dtype=scalar), wp.array(dtype=wp.int32)
    didx = index_funcs(np_dtype).didx
    delassus_entry = sparse_llt_kernels(np_dtype).delassus_entry

    @wp.kernel(module="unique", enable_backward=False)
    def delassus_sparse(
        # model (read only)
        m: M,
        # in
        nblk: int,
        row_stride: int,
        n_rows: iarr, row_body: iarr, row_J: wp.array(dtype=vec6), reg: farr, inv_inertia_w: wp.array(dtype=mat33),
        # out
        D: farr,
    ):
        """Row ``a`` of ``D`` from the block-sparse rows (blocks meet on shared bodies)."""
        wid, a = wp.tid()
        n = n_rows[wid]
        if a >= n:
            return
        for b in range(a, n):
            s = delassus_entry(m, row_stride, row_body, row_J, reg, inv_inertia_w, wid, a, b, nblk)
            D[didx(m, wid, a, b)] = s
            D[didx(m, wid, b, a)] = s

    return delassus_sparse


@functools.cache
def delassus_dense_kernel(np_dtype):
    """The dense Delassus matrix ``D = J M^-1 J^T + R`` from the dense per-world ``J`` (§8.1).
    ``delassus_dense(m, row_stride, n_rows, Jd, MJd, reg, D)``, one thread per row slot: row ``a`` fills ``D_ab =
    D_ba``, ``b >= a``."""
    scalar, M = builder_types(np_dtype).take("scalar", "M")
    farr, iarr = wp.array(dtype=scalar), wp.array(dtype=wp.int32)
    ridx = index_funcs(np_dtype).ridx
    didx = index_funcs(np_dtype).didx
    jidx = index_funcs(np_dtype).jidx

    @wp.kernel(module="unique", enable_backward=False)
    def delassus_dense(
        # model (read only)
        m: M,
        # in
        row_stride: int,
        n_rows: iarr, Jd: farr, MJd: farr, reg: farr,
        # out
        D: farr,
    ):
        """Row ``a`` of ``D`` from the dense ``J`` (``6 n_bodies`` columns), each entry ``(J_a M^-1 J_b^T + J_b M^-1
        J_a^T) / 2`` as the sparse rows' (``linear_solve``'s ``delassus_term``: so that the rounding of ``M^-1 J^T``
        vanishes on the null space of ``J^T``)."""
        wid, a = wp.tid()
        n = n_rows[wid]
        if a >= n:
            return
        nc = 6 * m.body_count[wid]
        for b in range(a, n):
            s = scalar(0.0)
            for c in range(nc):
                s += scalar(0.5) * (Jd[jidx(m, wid, a, c)] * MJd[jidx(m, wid, b, c)]
                                    + Jd[jidx(m, wid, b, c)] * MJd[jidx(m, wid, a, c)])
            if b == a:
                s += reg[ridx(m, row_stride, wid, a)]
            D[didx(m, wid, a, b)] = s
            D[didx(m, wid, b, a)] = s

    return delassus_dense


@functools.cache
def precondition_kernel(np_dtype, assembled: bool):
    """The Jacobi preconditioner ``P = diag(D)^-1/2`` (§7.2), its diagonal from the assembled ``D`` with
    ``assembled`` (compile-time), else from the rows' blocks.
    ``precondition(m, nblk, row_stride, n_rows, n_box, row_body, row_J, reg, inv_inertia_w, D, P)``, one thread per
    row slot."""
    scalar, M, vec6, mat33 = builder_types(np_dtype).take("scalar", "M", "vec6", "mat33")
    farr, iarr = wp.array(dtype=scalar), wp.array(dtype=wp.int32)
    didx = index_funcs(np_dtype).didx
    delassus_entry = sparse_llt_kernels(np_dtype).delassus_entry
    world_row = world_row_func(np_dtype)
    eps = scalar(float(np.finfo(np_dtype).eps))

    @wp.func
    def row_diag(m: M, row_stride: int, row_body: iarr, row_J: wp.array(dtype=vec6), reg: farr,
                 inv_inertia_w: wp.array(dtype=mat33), D: farr, wid: int, a: int, nblk: int):
        """``D_aa`` (from the assembled matrix ``D``, or from the row's blocks)."""
        if wp.static(assembled):
            return D[didx(m, wid, a, a)]
        else:
            return delassus_entry(m, row_stride, row_body, row_J, reg, inv_inertia_w, wid, a, a, nblk)

    @wp.kernel(module="unique", enable_backward=False)
    def precondition(
        # model (read only)
        m: M,
        # in
        nblk: int,
        row_stride: int,
        n_rows: iarr, n_box: iarr, row_body: iarr, row_J: wp.array(dtype=vec6), reg: farr,
        inv_inertia_w: wp.array(dtype=mat33), D: farr,
        # out
        P: farr,
    ):
        """``P_a`` of each active row; one value per contact from the largest of its three diagonal entries (keeps
        the Coulomb cone invariant)."""
        wid, a = wp.tid()
        r = world_row(m, row_stride, n_rows, wid, a)
        if r < 0:
            return
        nb = n_box[wid]
        d = scalar(0.0)
        if a < nb:
            d = wp.abs(row_diag(m, row_stride, row_body, row_J, reg, inv_inertia_w, D, wid, a, nblk))
        else:
            c0 = nb + 3 * ((a - nb) // 3)
            for t in range(3):
                d = wp.max(d, wp.abs(row_diag(m, row_stride, row_body, row_J, reg, inv_inertia_w, D, wid, c0 + t,
                                              nblk)))
        if d > eps:
            P[r] = scalar(1.0) / wp.sqrt(d + eps)
        else:
            P[r] = scalar(1.0)

    return precondition


@functools.cache
def scale_kernel(np_dtype, assembled: bool, always_sat: bool):
    """The scaled problem of §7.2 and the effort-limited rows' starting saturation ("Saturation"); compile-time:
    ``assembled``, the dense ``D`` is scaled too; ``always_sat``, every effort-limited row starts saturated.
    ``scale(m, shift, shift_sat, impulse_scale, row_stride, n_rows, P, lo, hi, f0, vt, lo_s, hi_s, row_info, D)``,
    one thread per row slot."""
    scalar, M = builder_types(np_dtype).take("scalar", "M")
    farr, iarr = wp.array(dtype=scalar), wp.array(dtype=wp.int32)
    ridx = index_funcs(np_dtype).ridx
    didx = index_funcs(np_dtype).didx
    set_saturated = index_funcs(np_dtype).set_saturated
    world_row = world_row_func(np_dtype)
    sat_margin = scalar(SATURATION_MARGIN)

    @wp.kernel(module="unique", enable_backward=False)
    def scale(
        # model (read only)
        m: M,
        # in
        shift: scalar, shift_sat: scalar, impulse_scale: scalar,
        row_stride: int,
        n_rows: iarr, P: farr, lo: farr, hi: farr, f0: farr,
        # out
        vt: farr,  # also read
        lo_s: farr, hi_s: farr, row_info: iarr,
        D: farr,  # also read
    ):
        """``v~_f = P v_f`` (in place: ``prebake`` wrote ``v_f`` into ``vt``), scaled bounds (in place: ``lo_s``/
        ``hi_s`` are ``lo``/``hi``, workspace.allocate), and whether an effort-limited fixed row starts saturated (the
        flag in ``row_info``, ``set_saturated``: its warm start ``impulse_scale f0 / P`` on a bound, to
        ``SATURATION_MARGIN``; kamino.jax_ref.solver.solve, "Saturation"; with ``always_sat``, every effort-limited
        row: the CR path, pipeline.Stepper); on the dense path ``D~ = P D P`` row by row with ``shift = eta +
        rho_free`` on the fixed rows' diagonal (``shift_sat`` on the saturated ones; ``padmm_init`` adds the world's
        penalty to the others)."""
        wid, a = wp.tid()
        r = world_row(m, row_stride, n_rows, wid, a)
        if r < 0:
            return
        Pa = P[r]
        vt[r] = Pa * vt[r]  # v_f from prebake
        lo_r = lo[r]
        hi_r = hi[r]
        if wp.isfinite(lo_r):
            lo_r = lo_r / Pa
        if wp.isfinite(hi_r):
            hi_r = hi_r / Pa
        lo_s[r] = lo_r
        hi_s[r] = hi_r
        sat = int(0)
        if a < m.row_fixed[wid]:
            x0 = impulse_scale * f0[r] / Pa
            if wp.isfinite(lo_r) and (wp.static(always_sat) or x0 <= lo_r + sat_margin * wp.abs(lo_r)):
                sat = 1
            if wp.isfinite(hi_r) and (wp.static(always_sat) or x0 >= hi_r - sat_margin * wp.abs(hi_r)):
                sat = 1
        set_saturated(row_info, r, sat)
        if wp.static(assembled):
            for b in range(n_rows[wid]):
                k = didx(m, wid, a, b)
                D[k] = Pa * D[k] * P[ridx(m, row_stride, wid, b)]
            if a < m.row_fixed[wid]:
                D[didx(m, wid, a, a)] += wp.where(sat != 0, shift_sat, shift)

    return scale


# --- the dense factor (§8.1) ---------------------------------------------------------------------------------

@functools.cache
def factor_tail_dense_func(np_dtype):
    """The dense factor's tail for a penalty (``kamino.jax_ref.solver.solve``, "Penalty").
    ``factor_tail_dense(m, row_stride, sdiag, D, wid, n, shift)``, by the world's thread."""
    scalar, M = builder_types(np_dtype).take("scalar", "M")
    didx = index_funcs(np_dtype).didx
    row_base = index_funcs(np_dtype).row_base

    @wp.func
    def factor_tail_dense(m: M, row_stride: int, sdiag: wp.array(dtype=scalar), D: wp.array(dtype=scalar), wid: int,
                          n: int, shift: scalar):
        """``L_t = chol(S_t + shift I)`` of the dense factor's tail (limit and contact rows) in ``D``: the Schur
        complement ``S_t`` is kept in the tail block's upper triangle and ``sdiag``, so that a new penalty only
        redoes this part."""
        rs = row_stride
        nf = m.row_fixed[wid]
        rb = row_base(m, row_stride, wid)
        for t in range(n - nf):
            for j in range(t + 1):
                s = scalar(0.0)
                if j == t:
                    s = sdiag[rb + (nf + t) * rs] + shift
                else:
                    s = D[didx(m, wid, nf + j, nf + t)]
                for i in range(j):
                    s -= D[didx(m, wid, nf + t, nf + i)] * D[didx(m, wid, nf + j, nf + i)]
                if j == t:
                    s = wp.sqrt(s)
                else:
                    s = s / D[didx(m, wid, nf + j, nf + j)]
                D[didx(m, wid, nf + t, nf + j)] = s

    return factor_tail_dense


@functools.cache
def factor_dense_func(np_dtype):
    """The dense Cholesky factor of ``D~`` (§8.1).
    ``factor_dense(m, row_stride, rho_u, sdiag, D, wid, n, eta)``, by the world's thread (``padmm_init``,
    ``refactor_dense``)."""
    scalar, M = builder_types(np_dtype).take("scalar", "M")
    didx = index_funcs(np_dtype).didx
    row_base = index_funcs(np_dtype).row_base
    factor_tail_dense = factor_tail_dense_func(np_dtype)

    @wp.func
    def factor_dense(m: M, row_stride: int, rho_u: wp.array(dtype=scalar), sdiag: wp.array(dtype=scalar),
                     D: wp.array(dtype=scalar), wid: int, n: int, eta: scalar):
        """The factor in place in ``D``: the fixed rows' columns, the tail's Schur complement ``S_t`` (upper
        triangle of the tail block and ``sdiag``), then ``L_t`` for the world's penalty ``rho_u``; ``L^T`` of the
        fixed columns is mirrored into the upper triangle so that the backward substitution reads rows."""
        rs = row_stride
        rb = row_base(m, row_stride, wid)
        nf = wp.min(m.row_fixed[wid], n)
        for j in range(nf):
            s = D[didx(m, wid, j, j)]
            for k in range(j):
                l = D[didx(m, wid, j, k)]
                s -= l * l
            ljj = wp.sqrt(s)
            D[didx(m, wid, j, j)] = ljj
            for i in range(j + 1, n):
                t = D[didx(m, wid, i, j)]
                for k in range(j):
                    t -= D[didx(m, wid, i, k)] * D[didx(m, wid, j, k)]
                D[didx(m, wid, i, j)] = t / ljj
        for t in range(n - nf):
            for jj in range(t + 1):
                s = D[didx(m, wid, nf + t, nf + jj)]
                for k in range(nf):
                    s -= D[didx(m, wid, nf + t, k)] * D[didx(m, wid, nf + jj, k)]
                if jj == t:
                    sdiag[rb + (nf + t) * rs] = s
                else:
                    D[didx(m, wid, nf + jj, nf + t)] = s
        factor_tail_dense(m, row_stride, sdiag, D, wid, n, eta + rho_u[wid])
        for i in range(n):
            for k in range(wp.min(i, nf)):
                D[didx(m, wid, k, i)] = D[didx(m, wid, i, k)]

    return factor_dense


@functools.cache
def refactor_dense_kernel(np_dtype):
    """The dense factor again after a saturation (``kamino.jax_ref.solver.solve``, "Saturation").
    ``refactor_dense(m, nblk, shift, shift_sat, eta, row_stride, n_rows, row_body, row_J, row_info, reg,
    inv_inertia_w, P, rho_u, pending, sdiag, D)``, one thread per world."""
    scalar, M, vec6, mat33 = builder_types(np_dtype).take("scalar", "M", "vec6", "mat33")
    farr, iarr = wp.array(dtype=scalar), wp.array(dtype=wp.int32)
    ridx = index_funcs(np_dtype).ridx
    didx = index_funcs(np_dtype).didx
    row_saturated = index_funcs(np_dtype).row_saturated
    delassus_entry = sparse_llt_kernels(np_dtype).delassus_entry
    factor_dense = factor_dense_func(np_dtype)

    @wp.kernel(module="unique", enable_backward=False)
    def refactor_dense(
        # model (read only)
        m: M,
        # in
        nblk: int, shift: scalar, shift_sat: scalar, eta: scalar,
        row_stride: int,
        n_rows: iarr, row_body: iarr, row_J: wp.array(dtype=vec6), row_info: iarr, reg: farr,
        inv_inertia_w: wp.array(dtype=mat33), P: farr, rho_u: farr,
        # out
        pending: iarr,  # also read
        sdiag: farr, D: farr,
    ):
        """For the worlds whose effort-limited rows saturated in the last PADMM iteration (``pending``): ``D~ =
        P D P`` from the rows' blocks with the new shifts, then ``factor_dense`` (one thread per world)."""
        wid = wp.tid()
        if pending[wid] == 0:
            return
        pending[wid] = 0
        n = n_rows[wid]
        nf = m.row_fixed[wid]
        for a in range(n):
            ra = ridx(m, row_stride, wid, a)
            for b in range(a, n):
                v = (P[ra]
                     * delassus_entry(m, row_stride, row_body, row_J, reg, inv_inertia_w, wid, a, b, nblk)
                     * P[ridx(m, row_stride, wid, b)])
                if b == a and a < nf:
                    v += wp.where(row_saturated(row_info, ra) != 0, shift_sat, shift)
                D[didx(m, wid, a, b)] = v
                D[didx(m, wid, b, a)] = v
        factor_dense(m, row_stride, rho_u, sdiag, D, wid, n, eta)

    return refactor_dense


@functools.cache
def cho_solve_func(np_dtype):
    """The solve with the dense factor (§8.1).
    ``cho_solve_inplace(m, row_stride, D, x, wid, n)``: ``x`` in place, by the world's thread."""
    scalar, M = builder_types(np_dtype).take("scalar", "M")
    row_base = index_funcs(np_dtype).row_base
    S = GROUP  # storage distance between consecutive entries of a world's dense Delassus matrix (D)

    @wp.func
    def cho_solve_inplace(m: M, row_stride: int, D: wp.array(dtype=scalar), x: wp.array(dtype=scalar), wid: int,
                          n: int):
        """``x <- L^-T L^-1 x`` with the factor in ``D`` (forward, then backward substitution reading ``L^T`` from
        the upper triangle, and from the lower one in the tail block)."""
        rs = row_stride
        rb = row_base(m, row_stride, wid)
        g = wid // GROUP
        db = m.grp_mat_start[g] + (wid - g * GROUP)  # didx(m, wid, i, k) = db + (i * md + k) * S
        md = m.grp_maxdim[g]
        for i in range(n):
            s = x[rb + i * rs]
            for k in range(i):
                s -= D[db + (i * md + k) * S] * x[rb + k * rs]
            x[rb + i * rs] = s / D[db + (i * md + i) * S]
        nf = m.row_fixed[wid]
        for ii in range(n):
            i = n - 1 - ii
            s = x[rb + i * rs]
            if i >= nf:  # the tail block keeps its Schur complement in the upper triangle: read L by columns
                for k in range(i + 1, n):
                    s -= D[db + (k * md + i) * S] * x[rb + k * rs]
            else:
                for k in range(i + 1, n):
                    s -= D[db + (i * md + k) * S] * x[rb + k * rs]
            x[rb + i * rs] = s / D[db + (i * md + i) * S]

    return cho_solve_inplace


# --- PADMM (§7.3-§7.8) ---------------------------------------------------------------------------------------

@functools.cache
def project_into_func(np_dtype):
    """The projection on the feasible set ``K`` (§7.3 step 3).
    ``project_into(m, row_stride, lo_s, hi_s, ct_mu, row_info, wid, n_box, n, src, shift, inv_rho, dst)``, by the
    world's thread."""
    scalar, M = builder_types(np_dtype).take("scalar", "M")
    row_base = index_funcs(np_dtype).row_base
    row_mu = index_funcs(np_dtype).row_mu
    cone_project = cone_funcs(np_dtype).cone_project

    @wp.func
    def project_into(m: M, row_stride: int, lo_s: wp.array(dtype=scalar), hi_s: wp.array(dtype=scalar),
                     ct_mu: wp.array(dtype=scalar), row_info: wp.array(dtype=wp.int32), wid: int, n_box: int, n: int,
                     src: wp.array(dtype=scalar), shift: wp.array(dtype=scalar), inv_rho: scalar,
                     dst: wp.array(dtype=scalar)):
        """``dst = Pi_K(src - inv_rho * shift)``: clip on box rows, cones on contacts."""
        rs = row_stride
        rb = row_base(m, row_stride, wid)
        for a in range(n_box):
            r = rb + a * rs
            dst[r] = wp.clamp(src[r] - inv_rho * shift[r], lo_s[r], hi_s[r])
        for c in range((n - n_box) // 3):
            r = rb + (n_box + 3 * c) * rs
            p = cone_project(src[r] - inv_rho * shift[r], src[r + rs] - inv_rho * shift[r + rs],
                             src[r + 2 * rs] - inv_rho * shift[r + 2 * rs], row_mu(ct_mu, row_info, r))
            dst[r] = p[0]
            dst[r + rs] = p[1]
            dst[r + 2 * rs] = p[2]

    return project_into


@functools.cache
def padmm_init_kernel(np_dtype, use_velocity: bool, factorize: bool, adaptive: bool):
    """PADMM's warm start (§7.8), the world's penalty and residual scale, and the dense factor; compile-time:
    ``use_velocity``, ``z0`` from the warm-start velocity (else 0); ``factorize``, the dense factor; ``adaptive``, a
    world keeps its positive penalty from the previous step.
    ``padmm_init(m, impulse_scale, max_iterations, eta, rho0, row_stride, ...)`` (the Work arrays it reads, then
    those it writes), one thread per world."""
    scalar, M = builder_types(np_dtype).take("scalar", "M")
    farr, iarr = wp.array(dtype=scalar), wp.array(dtype=wp.int32)
    row_base = index_funcs(np_dtype).row_base
    project_into = project_into_func(np_dtype)
    factor_dense = factor_dense_func(np_dtype)
    restart_world = restart_world_func(np_dtype)

    @wp.kernel(module="unique", enable_backward=False)
    def padmm_init(
        # model (read only)
        m: M,
        # in
        impulse_scale: scalar, max_iterations: int, eta: scalar, rho0: scalar,
        row_stride: int,
        n_rows: iarr, n_box: iarr, frozen: iarr, f0: farr, v0: farr, P: farr, lo_s: farr, hi_s: farr, ct_mu: farr,
        row_info: iarr,
        # out
        x: farr, x_p: farr, y_p: farr, y_hat: farr, z_p: farr, z_hat: farr,
        p_ref: farr, rho_u: farr, pending: iarr, iters: iarr, r_p: farr, r_d: farr, r_c: farr,
        a_p: farr, c_p: farr, it_cap: iarr, k_rho: iarr, converged: iarr, done: iarr, remaining: iarr,
        sdiag: farr, D: farr,
    ):
        """``x0 = Pi_K(impulse0 / P)``, ``z0 = P v0``, the world's penalty and residual scale, and with
        ``factorize`` the dense factor (``factor_dense``)."""
        rs = row_stride
        wid = wp.tid()
        rb = row_base(m, row_stride, wid)
        n = n_rows[wid]
        pref = scalar(0.0)
        for a in range(n):
            r = rb + a * rs
            x[r] = impulse_scale * f0[r] / P[r]
            z_p[r] = scalar(0.0)
            if wp.static(use_velocity):
                z_p[r] = P[r] * v0[r]
            z_hat[r] = z_p[r]
            pref = wp.max(pref, P[r])
        if pref <= scalar(0.0):
            pref = scalar(1.0)
        p_ref[wid] = pref
        if wp.static(adaptive):
            if not (rho_u[wid] > scalar(0.0)):
                rho_u[wid] = rho0
        else:
            rho_u[wid] = rho0
        pending[wid] = 0
        project_into(m, row_stride, lo_s, hi_s, ct_mu, row_info, wid, n_box[wid], n, x, x, scalar(0.0), x_p)
        for a in range(n):
            r = rb + a * rs
            y_p[r] = x_p[r]
            y_hat[r] = x_p[r]
        iters[wid] = 0
        r_p[wid] = scalar(0.0)
        r_d[wid] = scalar(0.0)
        r_c[wid] = scalar(0.0)
        restart_world(n_rows, frozen, a_p, c_p, it_cap, k_rho, converged, done, remaining, wid, 0, max_iterations)
        if wp.static(factorize):
            factor_dense(m, row_stride, rho_u, sdiag, D, wid, n, eta)

    return padmm_init


@functools.cache
def warm_start_filter_kernel(np_dtype):
    """The warm start without its part along the nearly null directions of the always-active rows' block
    (``kamino.jax_ref.solver._Problem.filter_warm_start``, docs/conventions.md "Warm start"), one thread per world
    (``padmm="thread"``; the 32-thread schedule's is ``solver_lanes.warm_start_filter_kernel``).
    ``warm_start_filter(m, shift, row_stride, sp, frozen, lo_s, hi_s, x, x_p, y_p, y_hat)``: ``sp`` holds the
    factor of ``P D_ff P + shift I`` (``linear_solve.factor_fixed``), ``x`` is scratch (left equal to ``x_p`` on the
    fixed rows)."""
    scalar, M, SP = builder_types(np_dtype).take("scalar", "M", "SP")
    farr, iarr = wp.array(dtype=scalar), wp.array(dtype=wp.int32)
    bases = sparse_llt_kernels(np_dtype).bases
    sparse_solve = sparse_llt_kernels(np_dtype).solve_inplace

    @wp.kernel(module="unique", enable_backward=False)
    def warm_start_filter(
        # model (read only)
        m: M,
        # in
        shift: scalar,
        row_stride: int,
        sp: SP,  # the factor of the fixed rows' block with the filter's shift (tables and values, read)
        frozen: iarr, lo_s: farr, hi_s: farr,
        # out
        x: farr,  # scratch
        x_p: farr, y_p: farr, y_hat: farr,  # the warm start (padmm_init), also read
    ):
        """``x_f <- clip(x_f - (P D_ff P + s I)^-1 s x_f)`` on the fixed rows (box rows) of the warm start ``x_p``,
        copied to ``y_p`` and ``y_hat``; a world whose result is not finite keeps its warm start."""
        wid = wp.tid()
        if frozen[wid] != 0:
            return
        rs = row_stride
        rb = bases(m, sp, row_stride, wid)[0]
        nf = sp.n_fixed[wid]
        for a in range(nf):
            x[rb + a * rs] = shift * x_p[rb + a * rs]
        sparse_solve(m, sp, row_stride, wid, nf, x)
        ok = int(1)
        for a in range(nf):
            r = rb + a * rs
            x[r] = wp.clamp(x_p[r] - x[r], lo_s[r], hi_s[r])
            if not wp.isfinite(x[r]):
                ok = 0
        for a in range(nf):
            r = rb + a * rs
            if ok != 0:
                x_p[r] = x[r]
                y_p[r] = x[r]
                y_hat[r] = x[r]
            x[r] = x_p[r]

    return warm_start_filter


@functools.cache
def restart_world_func(np_dtype):
    """A world's PADMM state at a (re)start.
    ``restart_world(n_rows, frozen, a_p, c_p, it_cap, k_rho, converged, done, remaining, wid, k, max_iterations)``
    (``padmm_init``, ``padmm_resume``)."""
    scalar = builder_types(np_dtype).scalar
    iarr = wp.array(dtype=wp.int32)
    big = scalar(float(np.finfo(np_dtype).max))

    @wp.func
    def restart_world(n_rows: iarr, frozen: iarr, a_p: wp.array(dtype=scalar), c_p: wp.array(dtype=scalar),
                      it_cap: iarr, k_rho: iarr, converged: iarr, done: iarr, remaining: iarr, wid: int, k: int,
                      max_iterations: int):
        """No momentum, the penalty unchanged since iteration ``k``, at most ``max_iterations`` iterations more; a
        world with no rows is done and converged, a frozen one done and not (neither iterates)."""
        n = n_rows[wid]
        a_p[wid] = scalar(1.0)
        c_p[wid] = big
        it_cap[wid] = k + max_iterations
        k_rho[wid] = k
        converged[wid] = int(n == 0 and frozen[wid] == 0)
        done[wid] = int(n == 0 or frozen[wid] != 0)
        if done[wid] != 0:
            wp.atomic_sub(remaining, 0, 1)

    return restart_world


@functools.cache
def linear_step_func(np_dtype, linear: int):
    """§7.3 steps 1-2 of one thread per world: the right-hand side and the linear solve ``linear``
    (``LINEAR_DENSE``, ``LINEAR_CR`` or ``LINEAR_SPARSE``: ``linear_solve.py``) of one iteration.
    ``linear_step(m, problem, carry, sp, row_info, D, x, y, cr_r, cr_p, cr_Ap, cr_Ar, cr_w, wid, rb, n, n_box,
    rho_u)`` (``solver_rules.problem_struct``, ``solver_rules.carry_struct``)."""
    M, SP, vec6 = builder_types(np_dtype).take("M", "SP", "vec6")
    farr, iarr = wp.array(dtype=builder_types(np_dtype).scalar), wp.array(dtype=wp.int32)
    Problem, Carry = rules.problem_struct(np_dtype), rules.carry_struct(np_dtype)
    scalar = builder_types(np_dtype).scalar
    row_penalty = rules.row_penalty_func(np_dtype)
    row_rhs = rules.row_rhs_func(np_dtype)
    contact_correction = rules.contact_correction_func(np_dtype)
    cr_solve = cr_solve_func(np_dtype, 1)
    sparse_solve = sparse_llt_kernels(np_dtype).solve_inplace
    cho_solve_inplace = cho_solve_func(np_dtype)

    @wp.func
    def linear_step(m: M, problem: Problem, carry: Carry, sp: SP, row_info: iarr, D: farr, x: farr, y: farr,
                    cr_r: farr, cr_p: farr, cr_Ap: farr, cr_Ar: farr, cr_w: wp.array(dtype=vec6), wid: int, rb: int,
                    n: int, n_box: int, rho_u: scalar):
        """``x`` of the iteration: the right-hand side (the De Saxcé correction ``Gamma(z_hat)`` on the contacts'
        normal rows) into ``x`` for the in-place factor solves, into ``y`` as CR's, then the solve (CR's scratch
        ``cr_*``)."""
        rs = problem.row_stride
        eta, rho_free, rho_box = problem.eta, problem.rho_free, problem.rho_box
        nf = m.row_fixed[wid]
        rhs = x
        if wp.static(linear == LINEAR_CR):
            rhs = y
        for a in range(n):
            r = rb + a * rs
            rhs[r] = row_rhs(problem.vt, carry.x_p, carry.y_hat, carry.z_hat, r,
                             row_penalty(row_info, r, a, nf, rho_free, rho_box, rho_u), eta)
        for c in range((n - n_box) // 3):
            r = rb + (n_box + 3 * c) * rs
            rhs[r + 2 * rs] -= contact_correction(problem.ct_mu, row_info, carry.z_hat, r, rs)
        if wp.static(linear == LINEAR_CR):
            cr_solve(m, rs, problem.row_body, problem.row_J, row_info, problem.reg, problem.P, problem.inv_inertia_w,
                     problem.cr_ent, problem.cr_end, carry.x_p, y, wid, rb, n, problem.nblk, 0, eta + rho_free,
                     eta + rho_box, eta + rho_u, problem.cr_budget, x, cr_r, cr_p, cr_Ap, cr_Ar, cr_w)
        elif wp.static(linear == LINEAR_SPARSE):
            sparse_solve(m, sp, rs, wid, n, x)
        else:
            cho_solve_inplace(m, rs, D, x, wid, n)

    return linear_step


@functools.cache
def project_rows_func(np_dtype, linear: int, adaptive: bool):
    """§7.3 steps 3-4 of one thread per world: every row's projection, dual update and residual terms.
    ``project_rows(m, problem, carry, row_info, x, cr_r, y, z, wid, rb, n, n_box, rho_u, p_ref)`` returns the
    world's ``solver_rules.residuals_struct``, writing ``y``, ``z`` and ``carry.e_p``; ``linear`` and ``adaptive`` as
    :func:`padmm_iterate_kernel`'s."""
    scalar, M, vec3 = builder_types(np_dtype).take("scalar", "M", "vec3")
    farr, iarr = wp.array(dtype=scalar), wp.array(dtype=wp.int32)
    Problem, Carry = rules.problem_struct(np_dtype), rules.carry_struct(np_dtype)
    Residuals = rules.residuals_struct(np_dtype)
    row_penalty = rules.row_penalty_func(np_dtype)
    box_row = rules.box_row_func(np_dtype, adaptive)
    contact_rows = rules.contact_rows_func(np_dtype)
    cr_residual = rules.cr_residual_func(np_dtype)

    @wp.func
    def project_rows(m: M, problem: Problem, carry: Carry, row_info: iarr, x: farr, cr_r: farr, y: farr, z: farr,
                     wid: int, rb: int, n: int, n_box: int, rho_u: scalar, p_ref: scalar) -> Residuals:
        """The box rows, then the contact triples (the linear solve's ``x``), into ``y``, ``z`` (and ``e_p``);
        under CR the inner solve's residual ``cr_r`` too."""
        rs = problem.row_stride
        eta, rho_free, rho_box = problem.eta, problem.rho_free, problem.rho_box
        nf = m.row_fixed[wid]
        acc = Residuals()
        for a in range(n_box):
            r = rb + a * rs
            acc = box_row(row_info, problem.lo_s, problem.hi_s, carry.x_p, carry.y_hat, carry.z_hat, problem.P, y, z,
                          carry.e_p, r, a, nf, x[r], row_penalty(row_info, r, a, nf, rho_free, rho_box, rho_u), eta,
                          p_ref, acc)
        inv_rho = scalar(1.0) / rho_u
        for c in range((n - n_box) // 3):
            r = rb + (n_box + 3 * c) * rs
            acc = contact_rows(problem.ct_mu, row_info, carry.z_hat, x, carry.x_p, carry.y_hat, problem.P, y, z, r, rs,
                               vec3(x[r], x[r + rs], x[r + 2 * rs]), inv_rho, rho_u, eta, p_ref, acc)
        if wp.static(linear == LINEAR_CR):
            for a in range(n):
                acc = cr_residual(problem.P, cr_r, rb + a * rs, p_ref, acc)
        return acc

    return project_rows


@functools.cache
def padmm_iterate_kernel(np_dtype, linear: int, adaptive: bool, accelerate: bool, fixed_iterations: bool):
    """Accelerated PADMM, one thread per world (§7.3-§7.5; the rules of ``solver_rules.py``), with the linear solve
    ``linear`` (``LINEAR_DENSE``, ``LINEAR_CR`` or ``LINEAR_SPARSE``), the adaptive penalty (``adaptive``), the
    momentum (``accelerate``) and every world running to its cap (``fixed_iterations``): all compile-time."""
    if linear not in (LINEAR_DENSE, LINEAR_CR, LINEAR_SPARSE):
        raise ValueError(f"padmm_iterate_kernel: linear must be LINEAR_DENSE, LINEAR_CR or LINEAR_SPARSE, got {linear}")
    scalar, M, SP, vec6 = builder_types(np_dtype).take("scalar", "M", "SP", "vec6")
    farr, iarr = wp.array(dtype=scalar), wp.array(dtype=wp.int32)
    Problem, Carry = rules.problem_struct(np_dtype), rules.carry_struct(np_dtype)
    row_base = index_funcs(np_dtype).row_base
    linear_step = linear_step_func(np_dtype, linear)
    project_rows = project_rows_func(np_dtype, linear, adaptive)
    outcome = rules.outcome_func(np_dtype, adaptive, accelerate)
    mark_saturated = rules.mark_saturated_func(np_dtype)
    advance_row = rules.advance_row_func(np_dtype)
    store_world = rules.store_world_func(np_dtype)
    factor_tail_sparse = sparse_llt_kernels(np_dtype).factor_tail
    factor_tail_dense = factor_tail_dense_func(np_dtype)

    @wp.kernel(module="unique", enable_backward=False)
    def padmm_iterate(
        m: M, problem: Problem, chunk: int,  # in: the model, the world's problem, the iterations of this launch
        carry: Carry,  # in and out: the iterate and the world's state
        sp: SP,  # out: the factor's tail values sp.tail under LINEAR_SPARSE (a new penalty); its tables are read
        D: farr,  # out: the dense factor's tail under LINEAR_DENSE (a new penalty)
        row_info: iarr,  # out: a row's saturation flag (also read)
        x: farr, y: farr, z: farr, cr_r: farr, cr_p: farr, cr_Ap: farr, cr_Ar: farr, cr_w: wp.array(dtype=vec6),  # out
    ):
        """Up to ``chunk`` iterations of one world (``padmm.solve`` of the JAX reference, its penalty rule and
        residuals included), resuming from the stored iterate; a world that converges (unless
        ``fixed_iterations``) or reaches its iteration cap ``it_cap`` is marked done and leaves ``remaining``. The
        fixed rows carry the penalty ``rho_free`` (``rho_box`` on a saturated effort-limited actuator), the limit and
        contact rows the world's ``rho_u``, rebalanced under ``adaptive`` (then the tail of the factor is
        recomputed). A row that saturates ends the launch with ``pending`` set: ``refactor`` (or
        ``refactor_dense``) redoes the factor before the next launch (kamino.jax_ref.solver.solve, "Saturation");
        CR's operator takes ``rho_box`` at its next solve."""
        rs = problem.row_stride
        eta, rho_free = problem.eta, problem.rho_free
        wid = wp.tid()
        rb = row_base(m, rs, wid)
        if carry.done[wid] != 0:
            return
        n = problem.n_rows[wid]
        nb = problem.n_box[wid]
        nf = m.row_fixed[wid]
        pref = problem.p_ref[wid]
        rho_w = carry.rho_u[wid]
        for step in range(chunk):
            linear_step(m, problem, carry, sp, row_info, D, x, y, cr_r, cr_p, cr_Ap, cr_Ar, cr_w, wid, rb, n, nb, rho_w)
            acc = project_rows(m, problem, carry, row_info, x, cr_r, y, z, wid, rb, n, nb, rho_w, pref)
            k = carry.iters[wid] + 1
            res = outcome(carry.a_p, carry.c_p, carry.k_rho, wid, acc, k, n, nf, rho_w, problem.tol, eta, rho_free,
                          problem.restart_tol)
            if res.rho != rho_w:  # a new penalty: the factor's tail again, unless a saturation redoes the whole factor
                rho_w = res.rho
                carry.rho_u[wid] = rho_w
                carry.k_rho[wid] = k
                if wp.static(linear == LINEAR_SPARSE):
                    if res.saturates == 0:
                        factor_tail_sparse(m, sp, rs, wid, n, eta + rho_w)
                elif wp.static(linear == LINEAR_DENSE):
                    if res.saturates == 0:
                        factor_tail_dense(m, rs, problem.sdiag, D, wid, n, eta + rho_w)
            if res.saturates != 0:  # rho_box on the rows that saturate; the factor is redone after this launch
                for a in range(nf):
                    mark_saturated(problem.lo_s, problem.hi_s, x, carry.z_hat, y, row_info, rb + a * rs, rho_free)
                carry.k_rho[wid] = k
                if wp.static(linear != LINEAR_CR):
                    carry.pending[wid] = 1
            for a in range(n):
                advance_row(y, z, carry.x_p, carry.y_p, carry.z_p, carry.y_hat, carry.z_hat, rb + a * rs,
                            x[rb + a * rs], res.mom)
            finished = (res.converged != 0 and not wp.static(fixed_iterations)) or k >= problem.it_cap[wid]
            store_world(carry.a_p, carry.c_p, carry.iters, carry.r_p, carry.r_d, carry.r_c, carry.converged,
                        carry.done, carry.remaining, wid, k, acc, res, finished)
            if finished or carry.pending[wid] != 0:
                return

    return padmm_iterate


@functools.cache
def padmm_resume_kernel(np_dtype):
    """PADMM again from its last iterate, after the right-hand side changed (curvature refinement).
    ``padmm_resume(m, max_iterations, row_stride, n_rows, frozen, iters, y_p, z_p, y_hat, z_hat, a_p, c_p, it_cap,
    k_rho, converged, done, remaining)``, one thread per world."""
    scalar, M = builder_types(np_dtype).take("scalar", "M")
    farr, iarr = wp.array(dtype=scalar), wp.array(dtype=wp.int32)
    row_base = index_funcs(np_dtype).row_base
    restart_world = restart_world_func(np_dtype)

    @wp.kernel(module="unique", enable_backward=False)
    def padmm_resume(
        # model (read only)
        m: M,
        # in
        max_iterations: int,
        row_stride: int,
        n_rows: iarr, frozen: iarr, iters: iarr, y_p: farr, z_p: farr,
        # out
        y_hat: farr, z_hat: farr, a_p: farr, c_p: farr, it_cap: iarr, k_rho: iarr, converged: iarr, done: iarr,
        remaining: iarr,
    ):
        """Restart from the last iterate (``y_hat = y``, ``z_hat = z``, no momentum) for up to ``max_iterations``
        more iterations, in the worlds whose first solve converged and that have joint or coupling rows (those
        whose right-hand side the refinement changed). Every other world is done and keeps its first solve
        untouched: a world's result does not depend on the worlds batched with it."""
        rs = row_stride
        wid = wp.tid()
        if converged[wid] == 0 or m.cts_count[wid] + m.cpl_count[wid] == 0:
            done[wid] = 1
            wp.atomic_sub(remaining, 0, 1)
            return
        rb = row_base(m, row_stride, wid)
        for a in range(n_rows[wid]):
            y_hat[rb + a * rs] = y_p[rb + a * rs]
            z_hat[rb + a * rs] = z_p[rb + a * rs]
        restart_world(n_rows, frozen, a_p, c_p, it_cap, k_rho, converged, done, remaining, wid, iters[wid],
                      max_iterations)

    return padmm_resume


@functools.cache
def padmm_finish_kernel(np_dtype):
    """PADMM's impulses and velocities, unscaled (§7.7).
    ``padmm_finish(m, row_stride, n_rows, n_box, P, y_p, z_p, ct_mu, row_info, impulse, velocity, failed)``, one
    thread per row slot."""
    scalar, M = builder_types(np_dtype).take("scalar", "M")
    farr, iarr = wp.array(dtype=scalar), wp.array(dtype=wp.int32)
    row_mu = index_funcs(np_dtype).row_mu
    de_saxce = cone_funcs(np_dtype).de_saxce
    world_row = world_row_func(np_dtype)

    @wp.kernel(module="unique", enable_backward=False)
    def padmm_finish(
        # model (read only)
        m: M,
        # in
        row_stride: int,
        n_rows: iarr, n_box: iarr, P: farr, y_p: farr, z_p: farr, ct_mu: farr, row_info: iarr,
        # out
        impulse: farr, velocity: farr, failed: iarr,
    ):
        """``lambda = P y``, ``v+ = (z - Gamma(z)) / P``; a non-finite impulse fails the world."""
        rs = row_stride
        wid, a = wp.tid()
        r = world_row(m, row_stride, n_rows, wid, a)
        if r < 0:
            return
        nb = n_box[wid]
        Pa = P[r]
        lam = Pa * y_p[r]
        z = z_p[r]
        if a >= nb and (a - nb) % 3 == 2:
            z -= de_saxce(z_p[r - 2 * rs], z_p[r - rs], row_mu(ct_mu, row_info, r))
        impulse[r] = lam
        velocity[r] = z / Pa
        if not wp.isfinite(lam):
            failed[wid] = 1

    return padmm_finish


def solver_kernels(np_dtype, dense: bool, assembled: bool, always_sat: bool, use_velocity: bool,
                   adaptive: bool) -> SimpleNamespace:
    """The one-thread-per-world kernels of a step (``padmm_iterate_kernel`` takes the linear solve and the penalty
    rule), with the stepper's compile-time modes: ``dense``, the dense per-world ``J`` (``prebake``); ``assembled``,
    the dense Delassus matrix (``precondition``, ``scale``, ``padmm_init``'s factor); ``always_sat``, every
    effort-limited row starts saturated (``scale``: the CR path); ``use_velocity``, the warm start's velocity
    (``padmm_init``); ``adaptive``, the adaptive penalty (``padmm_init``)."""
    return SimpleNamespace(count_rows=count_rows_kernel(np_dtype), prebake=prebake_kernel(np_dtype, dense),
                           delassus_sparse=delassus_sparse_kernel(np_dtype),
                           delassus_dense=delassus_dense_kernel(np_dtype),
                           precondition=precondition_kernel(np_dtype, assembled),
                           scale=scale_kernel(np_dtype, assembled, always_sat),
                           padmm_init=padmm_init_kernel(np_dtype, use_velocity, assembled, adaptive),
                           padmm_resume=padmm_resume_kernel(np_dtype), refactor_dense=refactor_dense_kernel(np_dtype),
                           padmm_finish=padmm_finish_kernel(np_dtype),
                           warm_start_filter=warm_start_filter_kernel(np_dtype))
