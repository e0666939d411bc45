"""The Conjugate Residual solve of PADMM's linear system (docs/formulation.md §8.2), for both PADMM schedules.

The operator ``A = P J M^-1 J^T P + diag(P^2 R + eta + rho)`` is applied matrix-free (:func:`apply_func`):
``cr_w = M^-1 J^T P v`` per body, then ``J cr_w`` and the diagonal row by row. One thread per world (``solver.py``)
sums a body's ``J^T P v`` by walking the rows in order; 32 threads per world (``solver_lanes.py``) split the bodies,
each summing its body's row blocks from the lists ``cr_pattern`` builds once per step, in the same row order, so
with no atomics and the same sums. :func:`cr_solve_func` is the one CR iteration of both, its vector updates split
over the world's threads and its dot products reduced over them.
"""

import functools

import warp as wp

from kamino.warp_backend.indexing import index_funcs
from kamino.warp_backend.linear_solve import sparse_llt_kernels
from kamino.warp_backend.solver_rules import LANES, lane_reduce_func, sync
from kamino.warp_backend.workspace import builder_types


@wp.func
def ent_slot(rb: int, rs: int, nblk: int, j: int) -> int:
    """Where entry ``j`` of a world's body-grouped row blocks (``Work.cr_ent``) is stored: in the slots of the world's
    row blocks (``w.row_body``'s layout), which hold as many."""
    return (rb + (j // nblk) * rs) * nblk + j % nblk


@functools.cache
def cr_pattern_kernel(np_dtype):
    """The world's row blocks grouped by body, for :func:`apply_func` on 32 threads (§8.2).
    ``cr_pattern(m, w, nblk)``, one thread per world (``wp.launch``), once per step."""
    scalar, M, Work, SP = builder_types(np_dtype).take("scalar", "M", "Work", "SP")
    row_base = index_funcs(np_dtype).row_base

    @wp.kernel(module="unique", enable_backward=False)
    def cr_pattern(m: M, w: Work, nblk: int):
        """A counting sort, one thread per world, once per step after the rows are assembled: ``w.cr_ent`` lists the
        blocks' indices ``r nblk + k`` body after body (in row order within a body), ``w.cr_end[b]`` where body
        ``b``'s list ends (it starts where the previous body's ends, or at 0)."""
        wid = wp.tid()
        rs = w.row_stride
        rb = row_base(m, w.row_stride, wid)
        b0 = m.body_start[wid]
        nb = m.body_count[wid]
        n = w.n_rows[wid]
        for i in range(nb):
            w.cr_end[b0 + i] = 0
        for a in range(n):
            r = rb + a * rs
            for k in range(nblk):
                b = w.row_body[r * nblk + k]
                if b >= 0:
                    w.cr_end[b] = w.cr_end[b] + 1
        start = int(0)
        for i in range(nb):  # counts -> starts
            c = w.cr_end[b0 + i]
            w.cr_end[b0 + i] = start
            start += c
        for a in range(n):  # starts -> ends
            r = rb + a * rs
            for k in range(nblk):
                b = w.row_body[r * nblk + k]
                if b >= 0:
                    j = w.cr_end[b]
                    w.cr_ent[ent_slot(rb, rs, nblk, j)] = r * nblk + k
                    w.cr_end[b] = j + 1

    return cr_pattern


@functools.cache
def apply_func(np_dtype, lanes: int):
    """``out = A v`` by a world's ``lanes`` threads (1 or ``LANES``; §8.2).
    ``apply(m, w, wid, rb, n, nblk, lane, shift_f, shift_b, shift_t, v, out)``."""
    vec6, scalar, M, Work, SP = builder_types(np_dtype).take("vec6", "scalar", "M", "Work", "SP")
    inv_mass_times = sparse_llt_kernels(np_dtype).inv_mass_times
    row_saturated = index_funcs(np_dtype).row_saturated

    @wp.func
    def apply(m: M, w: Work, wid: int, rb: int, n: int, nblk: int, lane: int, shift_f: scalar, shift_b: scalar,
              shift_t: scalar, v: wp.array(dtype=scalar), out: wp.array(dtype=scalar)):
        """``out = A v``, the diagonal's ``eta + rho`` being ``shift_f`` on the fixed rows (``shift_b`` on the
        saturated ones) and ``shift_t`` on the limit and contact rows. One thread sums ``cr_w = M^-1 J^T P v`` by
        walking the world's rows in order, each row adding its blocks to its bodies; 32 threads split the bodies,
        each summing its body's row blocks from ``cr_pattern``'s lists (the same sums), with a barrier before (every
        thread's rows of ``v``) and after (every body of ``cr_w``). Then each thread takes its rows of ``J cr_w``."""
        rs = w.row_stride
        b0 = m.body_start[wid]
        if wp.static(lanes == 1):
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
                w.cr_w[b0 + i] = inv_mass_times(m, w.inv_inertia_w, b0 + i, w.cr_w[b0 + i])
        else:
            sync()
            for i in range(lane, m.body_count[wid], LANES):
                b = b0 + i
                j0 = int(0)
                if i > 0:
                    j0 = w.cr_end[b - 1]
                acc = vec6()
                for j in range(j0, w.cr_end[b]):
                    e = w.cr_ent[ent_slot(rb, rs, nblk, j)]
                    r = e // nblk
                    acc = acc + (w.P[r] * v[r]) * w.row_J[e]
                w.cr_w[b] = inv_mass_times(m, w.inv_inertia_w, b, acc)
            sync()
        nf = m.row_fixed[wid]
        for a in range(lane, n, lanes):  # out_r = P_r J_r cr_w + (P_r^2 R_r + shift) v_r
            r = rb + a * rs
            s = scalar(0.0)
            for k in range(nblk):
                b = w.row_body[r * nblk + k]
                if b >= 0:
                    s += wp.dot(w.row_J[r * nblk + k], w.cr_w[b])
            Pa = w.P[r]
            shift = shift_t
            if a < nf:
                shift = wp.where(row_saturated(w.row_info, r) != 0, shift_b, shift_f)
            out[r] = Pa * s + (Pa * Pa * w.reg[r] + shift) * v[r]

    return apply


@functools.cache
def cr_solve_func(np_dtype, lanes: int):
    """Conjugate Residual by a world's ``lanes`` threads (1 or ``LANES``; §8.2).
    ``cr_solve(m, w, wid, rb, n, nblk, lane, shift_f, shift_b, shift_t, budget)``."""
    scalar, M, Work, SP = builder_types(np_dtype).take("scalar", "M", "Work", "SP")
    apply = apply_func(np_dtype, lanes)
    lane_sum = lane_reduce_func(np_dtype, lanes, "sum")
    zero = scalar(0.0)

    @wp.func
    def cr_solve(m: M, w: Work, wid: int, rb: int, n: int, nblk: int, lane: int, shift_f: scalar, shift_b: scalar,
                 shift_t: scalar, budget: int):
        """CR on ``A x = b`` (``b`` in ``y``) from ``x = x_p``: one operator application per iteration, at most
        ``budget`` iterations. It stops early only when the residual has vanished to rounding (``|r|^2 <= 1e-30
        |b|^2``, or exactly zero) or the recurrence breaks down (``|A p|^2 = 0`` or ``r^T A r = 0``): any looser
        stop would cap the accuracy of the linear solve at a level that, unscaled by ``1/P``, sits at PADMM's
        tolerance and stalls it. On exit ``cr_r`` holds the residual ``b - A x`` (the recurrence's, which follows
        the true one to rounding), which PADMM folds into the dual residual (``solver_rules.cr_residual_func``).
        Each thread updates its own rows (``lane``, ``lane + lanes``, ...); the dot products are reduced over the
        threads, so every thread takes the same branch."""
        rs = w.row_stride
        for a in range(lane, n, lanes):
            w.x[rb + a * rs] = w.x_p[rb + a * rs]
        apply(m, w, wid, rb, n, nblk, lane, shift_f, shift_b, shift_t, w.x, w.cr_Ar)
        bb = zero
        for a in range(lane, n, lanes):
            r = rb + a * rs
            w.cr_r[r] = w.y[r] - w.cr_Ar[r]
            w.cr_p[r] = w.cr_r[r]
            bb += w.y[r] * w.y[r]
        bb = lane_sum(bb)
        apply(m, w, wid, rb, n, nblk, lane, shift_f, shift_b, shift_t, w.cr_r, w.cr_Ar)
        zeta = zero
        for a in range(lane, n, lanes):
            r = rb + a * rs
            w.cr_Ap[r] = w.cr_Ar[r]
            zeta += w.cr_r[r] * w.cr_Ar[r]
        zeta = lane_sum(zeta)
        stop = scalar(1e-30) * bb
        for it in range(budget):
            rr = zero
            pp = zero
            for a in range(lane, n, lanes):
                r = rb + a * rs
                rr += w.cr_r[r] * w.cr_r[r]
                pp += w.cr_Ap[r] * w.cr_Ap[r]
            rr = lane_sum(rr)
            pp = lane_sum(pp)
            if rr <= stop or pp <= zero or zeta == zero:
                break
            alpha = zeta / pp
            for a in range(lane, n, lanes):
                r = rb + a * rs
                w.x[r] = w.x[r] + alpha * w.cr_p[r]
                w.cr_r[r] = w.cr_r[r] - alpha * w.cr_Ap[r]
            apply(m, w, wid, rb, n, nblk, lane, shift_f, shift_b, shift_t, w.cr_r, w.cr_Ar)
            zeta_new = zero
            for a in range(lane, n, lanes):
                zeta_new += w.cr_r[rb + a * rs] * w.cr_Ar[rb + a * rs]
            zeta_new = lane_sum(zeta_new)
            beta = zeta_new / zeta
            zeta = zeta_new
            for a in range(lane, n, lanes):
                r = rb + a * rs
                w.cr_p[r] = w.cr_r[r] + beta * w.cr_p[r]
                w.cr_Ap[r] = w.cr_Ar[r] + beta * w.cr_Ap[r]

    return cr_solve
