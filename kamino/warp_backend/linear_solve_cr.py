"""The Conjugate Residual solve of PADMM's linear system (docs/formulation.md §8.2), for both PADMM schedules.

The operator ``A = P J M^-1 J^T P + diag(P^2 R + eta + rho)`` is applied matrix-free (:func:`apply_func`):
``cr_w = M^-1 J^T P v`` per body, then ``J cr_w`` and the diagonal row by row. One thread per world (``solver.py``)
sums a body's ``J^T P v`` by walking the rows in order; 32 threads per world (``solver_lanes.py``) split the bodies,
each summing its body's row blocks from the lists ``cr_pattern`` builds once per step, in the same row order, so
with no atomics and the same sums. :func:`cr_solve_func` is the one CR iteration of both, its vector updates split
over the world's threads and its dot products reduced over them.
"""

import functools

import numpy as np
import warp as wp

from kamino.warp_backend.indexing import index_funcs
from kamino.warp_backend.linear_solve import sparse_llt_kernels
from kamino.warp_backend.solver_rules import LANES, lane_reduce_func, sync
from kamino.warp_backend.workspace import builder_types


@wp.func
def ent_slot(rb: int, rs: int, nblk: int, j: int) -> int:
    """Where entry ``j`` of a world's body-grouped row blocks (``Work.cr_ent``) is stored: in the slots of the world's
    row blocks (``Work.row_body``'s layout), which hold as many."""
    return (rb + (j // nblk) * rs) * nblk + j % nblk


@functools.cache
def cr_pattern_kernel(np_dtype):
    """The world's row blocks grouped by body, for :func:`apply_func` on 32 threads (§8.2).
    ``cr_pattern(m, nblk, row_stride, n_rows, row_body, cr_end, cr_ent)``, one thread per world (``wp.launch``), once
    per step."""
    M = builder_types(np_dtype).M
    row_base = index_funcs(np_dtype).row_base

    @wp.kernel(module="unique", enable_backward=False)
    def cr_pattern(
        # model (read only)
        m: M,
        # in
        nblk: int,
        row_stride: int,
        n_rows: wp.array(dtype=wp.int32),
        row_body: wp.array(dtype=wp.int32),
        # out
        cr_end: wp.array(dtype=wp.int32),  # also read
        cr_ent: wp.array(dtype=wp.int32),
    ):
        """A counting sort, one thread per world, once per step after the rows are assembled: ``cr_ent`` lists the
        blocks' indices ``r nblk + k`` body after body (in row order within a body), ``cr_end[b]`` where body
        ``b``'s list ends (it starts where the previous body's ends, or at 0)."""
        wid = wp.tid()
        rs = row_stride
        rb = row_base(m, row_stride, wid)
        b0 = m.body_start[wid]
        nb = m.body_count[wid]
        n = n_rows[wid]
        for i in range(nb):
            cr_end[b0 + i] = 0
        for a in range(n):
            r = rb + a * rs
            for k in range(nblk):
                b = row_body[r * nblk + k]
                if b >= 0:
                    cr_end[b] = cr_end[b] + 1
        start = int(0)
        for i in range(nb):  # counts -> starts
            c = cr_end[b0 + i]
            cr_end[b0 + i] = start
            start += c
        for a in range(n):  # starts -> ends
            r = rb + a * rs
            for k in range(nblk):
                b = row_body[r * nblk + k]
                if b >= 0:
                    j = cr_end[b]
                    cr_ent[ent_slot(rb, rs, nblk, j)] = r * nblk + k
                    cr_end[b] = j + 1

    return cr_pattern


@functools.cache
def apply_func(np_dtype, lanes: int):
    """``out = A v`` by a world's ``lanes`` threads (1 or ``LANES``; §8.2).
    ``apply(m, row_stride, row_body, row_J, row_info, reg, P, inv_inertia_w, cr_ent, cr_end, wid, rb, n, nblk, lane,
    shift_f, shift_b, shift_t, v, cr_w, out)``."""
    vec6, scalar, mat33, M = builder_types(np_dtype).take("vec6", "scalar", "mat33", "M")
    inv_mass_times = sparse_llt_kernels(np_dtype).inv_mass_times
    row_saturated = index_funcs(np_dtype).row_saturated

    @wp.func
    def apply(m: M, row_stride: int, row_body: wp.array(dtype=wp.int32), row_J: wp.array(dtype=vec6),
              row_info: wp.array(dtype=wp.int32), reg: wp.array(dtype=scalar), P: wp.array(dtype=scalar),
              inv_inertia_w: wp.array(dtype=mat33), cr_ent: wp.array(dtype=wp.int32), cr_end: wp.array(dtype=wp.int32),
              wid: int, rb: int, n: int, nblk: int, lane: int, shift_f: scalar, shift_b: scalar, shift_t: scalar,
              v: wp.array(dtype=scalar), cr_w: wp.array(dtype=vec6), out: wp.array(dtype=scalar)):
        """``out = A v``, the diagonal's ``eta + rho`` being ``shift_f`` on the fixed rows (``shift_b`` on the
        saturated ones) and ``shift_t`` on the limit and contact rows. One thread sums ``cr_w = M^-1 J^T P v`` by
        walking the world's rows in order, each row adding its blocks to its bodies; 32 threads split the bodies,
        each summing its body's row blocks from ``cr_pattern``'s lists (the same sums), with a barrier before (every
        thread's rows of ``v``) and after (every body of ``cr_w``). Then each thread takes its rows of ``J cr_w``
        (``cr_w``: ``Work.cr_w``, the scratch it writes)."""
        rs = row_stride
        b0 = m.body_start[wid]
        if wp.static(lanes == 1):
            for i in range(m.body_count[wid]):
                cr_w[b0 + i] = vec6()
            for a in range(n):
                r = rb + a * rs
                pv = P[r] * v[r]
                for k in range(nblk):
                    b = row_body[r * nblk + k]
                    if b >= 0:
                        cr_w[b] = cr_w[b] + pv * row_J[r * nblk + k]
            for i in range(m.body_count[wid]):
                cr_w[b0 + i] = inv_mass_times(m, inv_inertia_w, b0 + i, cr_w[b0 + i])
        else:
            sync()
            for i in range(lane, m.body_count[wid], LANES):
                b = b0 + i
                j0 = int(0)
                if i > 0:
                    j0 = cr_end[b - 1]
                acc = vec6()
                for j in range(j0, cr_end[b]):
                    e = cr_ent[ent_slot(rb, rs, nblk, j)]
                    r = e // nblk
                    acc = acc + (P[r] * v[r]) * row_J[e]
                cr_w[b] = inv_mass_times(m, inv_inertia_w, b, acc)
            sync()
        nf = m.row_fixed[wid]
        for a in range(lane, n, lanes):  # out_r = P_r J_r cr_w + (P_r^2 R_r + shift) v_r
            r = rb + a * rs
            s = scalar(0.0)
            for k in range(nblk):
                b = row_body[r * nblk + k]
                if b >= 0:
                    s += wp.dot(row_J[r * nblk + k], cr_w[b])
            Pa = P[r]
            shift = shift_t
            if a < nf:
                shift = wp.where(row_saturated(row_info, r) != 0, shift_b, shift_f)
            out[r] = Pa * s + (Pa * Pa * reg[r] + shift) * v[r]

    return apply


@functools.cache
def cr_solve_func(np_dtype, lanes: int):
    """Conjugate Residual by a world's ``lanes`` threads (1 or ``LANES``; §8.2).
    ``cr_solve(m, row_stride, row_body, row_J, row_info, reg, P, inv_inertia_w, cr_ent, cr_end, x_p, y, wid, rb, n,
    nblk, lane, shift_f, shift_b, shift_t, budget, x, cr_r, cr_p, cr_Ap, cr_Ar, cr_w)``."""
    vec6, scalar, mat33, M = builder_types(np_dtype).take("vec6", "scalar", "mat33", "M")
    apply = apply_func(np_dtype, lanes)
    lane_sum = lane_reduce_func(np_dtype, lanes, "sum")
    zero = scalar(0.0)
    rr_floor = scalar(float(np.finfo(np_dtype).tiny) / float(np.finfo(np_dtype).eps) ** 2)  # subnormal-free stop

    @wp.func
    def cr_solve(m: M, row_stride: int, row_body: wp.array(dtype=wp.int32), row_J: wp.array(dtype=vec6),
                 row_info: wp.array(dtype=wp.int32), reg: wp.array(dtype=scalar), P: wp.array(dtype=scalar),
                 inv_inertia_w: wp.array(dtype=mat33), cr_ent: wp.array(dtype=wp.int32),
                 cr_end: wp.array(dtype=wp.int32), x_p: wp.array(dtype=scalar), y: wp.array(dtype=scalar), wid: int,
                 rb: int, n: int, nblk: int, lane: int, shift_f: scalar, shift_b: scalar, shift_t: scalar, budget: int,
                 x: wp.array(dtype=scalar), cr_r: wp.array(dtype=scalar), cr_p: wp.array(dtype=scalar),
                 cr_Ap: wp.array(dtype=scalar), cr_Ar: wp.array(dtype=scalar), cr_w: wp.array(dtype=vec6)):
        """CR on ``A x = b`` (``b`` in ``y``) from ``x = x_p``: one operator application per iteration, at most
        ``budget`` iterations. It stops early only when the residual has vanished to rounding (``|r|^2 <= 1e-30
        |b|^2``, or exactly zero) or the recurrence breaks down (``|A p|^2 = 0`` or ``r^T A r = 0``): any looser
        stop would cap the accuracy of the linear solve at a level that, unscaled by ``1/P``, sits at PADMM's
        tolerance and stalls it. It also stops at ``|r|^2 <= tiny / eps^2`` of the dtype, which keeps the recurrence
        out of subnormal numbers: XLA's CPU threads flush them to zero and a Python thread does not, and the
        jitted step on the CPU reproduces the eager one bit for bit. On exit ``cr_r`` holds the residual ``b - A x``
        (the recurrence's, which follows the true one to rounding), which PADMM folds into the dual residual
        (``solver_rules.cr_residual_func``). Each thread updates its own rows (``lane``, ``lane + lanes``, ...); the
        dot products are reduced over the threads, so every thread takes the same branch."""
        rs = row_stride
        for a in range(lane, n, lanes):
            x[rb + a * rs] = x_p[rb + a * rs]
        apply(m, row_stride, row_body, row_J, row_info, reg, P, inv_inertia_w, cr_ent, cr_end, wid, rb, n, nblk, lane,
              shift_f, shift_b, shift_t, x, cr_w, cr_Ar)
        bb = zero
        for a in range(lane, n, lanes):
            r = rb + a * rs
            cr_r[r] = y[r] - cr_Ar[r]
            cr_p[r] = cr_r[r]
            bb += y[r] * y[r]
        bb = lane_sum(bb)
        apply(m, row_stride, row_body, row_J, row_info, reg, P, inv_inertia_w, cr_ent, cr_end, wid, rb, n, nblk, lane,
              shift_f, shift_b, shift_t, cr_r, cr_w, cr_Ar)
        zeta = zero
        for a in range(lane, n, lanes):
            r = rb + a * rs
            cr_Ap[r] = cr_Ar[r]
            zeta += cr_r[r] * cr_Ar[r]
        zeta = lane_sum(zeta)
        stop = wp.max(scalar(1e-30) * bb, rr_floor)
        for it in range(budget):
            rr = zero
            pp = zero
            for a in range(lane, n, lanes):
                r = rb + a * rs
                rr += cr_r[r] * cr_r[r]
                pp += cr_Ap[r] * cr_Ap[r]
            rr = lane_sum(rr)
            pp = lane_sum(pp)
            if rr <= stop or pp <= zero or zeta == zero:
                break
            alpha = zeta / pp
            for a in range(lane, n, lanes):
                r = rb + a * rs
                x[r] = x[r] + alpha * cr_p[r]
                cr_r[r] = cr_r[r] - alpha * cr_Ap[r]
            apply(m, row_stride, row_body, row_J, row_info, reg, P, inv_inertia_w, cr_ent, cr_end, wid, rb, n, nblk,
                  lane, shift_f, shift_b, shift_t, cr_r, cr_w, cr_Ar)
            zeta_new = zero
            for a in range(lane, n, lanes):
                zeta_new += cr_r[rb + a * rs] * cr_Ar[rb + a * rs]
            zeta_new = lane_sum(zeta_new)
            beta = zeta_new / zeta
            zeta = zeta_new
            for a in range(lane, n, lanes):
                r = rb + a * rs
                cr_p[r] = cr_r[r] + beta * cr_p[r]
                cr_Ap[r] = cr_Ar[r] + beta * cr_Ap[r]

    return cr_solve
