"""Proximal-ADMM with one GPU warp (32 threads) per world on the sparse factor (formulation.md §7-§8.1; paper
Alg. 1): the schedule for robot-sized worlds (``Stepper(padmm="warp")``).

One thread per world (``solver.padmm_iterate``) walks a world's factor and vectors alone: at 4096 worlds that is one
warp per multiprocessor, and every PADMM iteration of dr_legs is a chain of about 16,000 dependent loads. Here the
32 threads of a block share one world and the chain is cut down to the rows:

- **Factorisation** (:func:`factor`, once per step). The fixed rows by columns ("fan-out"): for column ``q``,
  ``L_qq = sqrt(D~_qq)``, the column's entries ``L_pq = D~_pq / L_qq`` (threads over the entries), then every update
  ``D~_pr -= L_pq L_rq`` that column ``q`` feeds (threads over the precomputed triples, ``Symbolic.fan_*``: their
  targets are distinct, so no atomics). The tail rows (active limits and contacts): ``L_tf`` by a forward
  substitution per tail row (threads over tail rows), the Schur complement ``S_t`` (threads over pairs) and its
  dense Cholesky by columns (:func:`factor_tail`). Same sums as ``sparse_llt.factor``, in another order.
- **Solve** (:func:`solve`, every iteration). Column sweeps: the forward substitution of the fixed rows walks the
  columns of ``L_f`` (``x_q = b_q / L_qq``, then the column's entries update the rows below, threads over the
  entries), the backward one walks its rows (``x_p``, then the entries of row ``p`` update the rows above); the
  tail's dense rows likewise, and the tail's share of the fixed rows is one parallel pass. One barrier per row;
  the right-hand side is updated in ``w.y`` (free during the solve) and the solution lands in ``w.x``.
- **Iterations** (:func:`padmm_iterate`). Every per-row rule (projection, dual update, residuals, the penalty of
  the limit and contact rows, the null-direction test, momentum) is ``padmm_rules.py``'s, the threads splitting the
  box rows and the contact triples; the world's maxima and sums are block reductions. Iteration counts equal the
  thread kernel's (``tests/test_warp_lane_padmm.py``).

Threads of a world meet at block barriers (``sync``); on the CPU the block runs as cooperative fibers
(``warp.config.enable_cpu_blocks``), which is how CI checks this kernel against the thread kernel.
"""

import functools
from types import SimpleNamespace

import numpy as np
import warp as wp

from kamino.config import NULL_DIRECTION_RATIO
from kamino.warp_backend.cone import cone_funcs
from kamino.warp_backend.model_data import GROUP, model_struct
from kamino.warp_backend.padmm_rules import padmm_funcs
from kamino.warp_backend.sparse_llt import pattern_struct, sparse_llt_kernels
from kamino.warp_backend.types import types_of
from kamino.warp_backend.workspace import work_struct

#: Threads per world (one GPU warp).
LANES = 32
#: ``padmm_iterate``: a new penalty restarts the momentum at the current iterate (solver.RESTART_HERE)
RESTART_HERE = 3


@wp.func_native("WP_TILE_SYNC();")
def sync():
    """Barrier of the threads of a block (``__syncthreads`` on CUDA, the fiber barrier on the CPU)."""
    ...


@functools.cache
def warp_kernels(np_dtype) -> SimpleNamespace:
    """``factor`` and ``padmm_iterate`` (launch both with ``wp.launch_tiled(dim=[num_worlds], block_dim=LANES)``)
    and the cooperative ``solve`` of the fixed rows (post-stabilisation)."""
    T = types_of(np_dtype)
    scalar = T.scalar
    M = model_struct(np_dtype)
    Work = work_struct(np_dtype)
    SP = pattern_struct(np_dtype)
    cf = cone_funcs(np_dtype)
    cone_project, de_saxce = cf.cone_project, cf.de_saxce
    pf = padmm_funcs(np_dtype)
    momentum, extrapolated, box_complementarity = pf.momentum, pf.extrapolated, pf.box_complementarity
    balanced_penalty, dual_update = pf.balanced_penalty, pf.dual_update
    bases = sparse_llt_kernels(np_dtype).bases
    S = GROUP  # storage distance between consecutive rows (entries) of a world
    big = scalar(float(np.finfo(np_dtype).max))
    null_ratio = scalar(NULL_DIRECTION_RATIO)
    zero = scalar(0.0)

    @wp.func
    def lane_max(v: scalar):
        return wp.tile_extract(wp.tile_max(wp.tile(v)), 0)

    @wp.func
    def lane_sum(v: scalar):
        return wp.tile_extract(wp.tile_sum(wp.tile(v)), 0)

    # --- factorisation ------------------------------------------------------------------------------------
    @wp.func
    def factor_tail(m: M, w: Work, sp: SP, wid: int, n: int, shift: scalar, lane: int):
        """``L_t = chol(S_t + shift I)`` by columns (left-looking: the entries of column ``j`` are independent dot
        products over the columns before it), from ``S_t`` in the tail rows' upper slots (``S_t[t, j]`` at row
        ``j``, column ``nf + t``) and ``w.sdiag``; the sums of ``sparse_llt.factor_tail``."""
        base = bases(m, sp, wid)
        rb, tb, ts = base[0], base[2], base[3]
        nf = sp.n_fixed[wid]
        for j in range(n - nf):
            jr = tb + j * ts
            d = w.sdiag[rb + (nf + j) * S] + shift
            for i in range(j):
                d -= sp.tail[jr + (nf + i) * S] * sp.tail[jr + (nf + i) * S]
            d = wp.sqrt(d)
            for t in range(j + 1 + lane, n - nf, LANES):
                tr = tb + t * ts
                s = sp.tail[jr + (nf + t) * S]
                for i in range(j):
                    s -= sp.tail[tr + (nf + i) * S] * sp.tail[jr + (nf + i) * S]
                sp.tail[tr + (nf + j) * S] = s / d
            if lane == 0:
                sp.tail[jr + (nf + j) * S] = d
            sync()

    @wp.kernel(module="unique", enable_backward=False)
    def factor(m: M, w: Work, sp: SP, eta: scalar):
        """Cholesky ``D~ = L L^T`` in place (§8.1) with the world's 32 threads: the fixed rows by columns (fan-out
        updates), then the tail rows' ``L_tf``, their Schur complement and :func:`factor_tail` with the world's
        penalty ``eta + rho_u``."""
        wid, lane = wp.tid()
        base = bases(m, sp, wid)
        rb, vb, tb, ts = base[0], base[1], base[2], base[3]
        nf = sp.n_fixed[wid]
        e0 = sp.ent_start[wid]
        p0 = sp.ptr_start[wid]
        for q in range(nf):
            kd = sp.row_ptr[p0 + q + 1] - 1
            d = wp.sqrt(sp.val[vb + kd * S])
            sync()  # every thread has read D~_qq before it becomes L_qq
            if lane == 0:
                sp.val[vb + kd * S] = d
            for j in range(sp.cptr[p0 + q] + lane, sp.cptr[p0 + q + 1], LANES):
                k = sp.cent[e0 + j]
                sp.val[vb + k * S] = sp.val[vb + k * S] / d
            sync()
            for u in range(sp.fan_ptr[p0 + q] + lane, sp.fan_ptr[p0 + q + 1], LANES):
                tgt = vb + sp.fan_tgt[u] * S
                sp.val[tgt] = sp.val[tgt] - sp.val[vb + sp.fan_a[u] * S] * sp.val[vb + sp.fan_b[u] * S]
            sync()
        n = w.n_rows[wid]
        nt = n - nf
        for t in range(lane, nt, LANES):  # L_tf: row t solves L_f l = D~_ft (each thread its own tail rows)
            tr = tb + t * ts
            for p in range(nf):
                s = sp.tail[tr + p * S]
                k1 = sp.row_ptr[p0 + p + 1] - 1
                for k in range(sp.row_ptr[p0 + p], k1):
                    s -= sp.val[vb + k * S] * sp.tail[tr + sp.col[e0 + k] * S]
                sp.tail[tr + p * S] = s / sp.val[vb + k1 * S]
        sync()
        for t in range(nt):  # S_t = D~_t - L_tf L_tf^T: row t's entries j <= t (upper slots and sdiag)
            tr = tb + t * ts
            for j in range(lane, t + 1, LANES):
                jr = tb + j * ts
                s = sp.tail[tr + (nf + j) * S]
                for p in range(nf):
                    s -= sp.tail[tr + p * S] * sp.tail[jr + p * S]
                if j == t:
                    w.sdiag[rb + (nf + t) * S] = s
                else:
                    sp.tail[jr + (nf + t) * S] = s
        sync()
        factor_tail(m, w, sp, wid, n, eta + w.rho_u[wid], lane)

    # --- solve --------------------------------------------------------------------------------------------
    @wp.func
    def solve(m: M, w: Work, sp: SP, wid: int, n: int, lane: int):
        """``x <- L^-T L^-1 x`` (``w.x``; ``w.y`` is overwritten) with the sparse factor and its dense tail, by
        column sweeps: one barrier per row (``sparse_llt.solve_inplace``, the same products in another order)."""
        base = bases(m, sp, wid)
        rb, vb, tb, ts = base[0], base[1], base[2], base[3]
        nf = sp.n_fixed[wid]
        e0 = sp.ent_start[wid]
        p0 = sp.ptr_start[wid]
        q0 = sp.perm_start[wid]
        nt = n - nf
        # forward, fixed rows: y_q = x_q / L_qq (x_q final once the columns before q have updated it), then column
        # q updates the rows below; the solution of L y = b collects in y
        for q in range(nf):
            rq = rb + sp.perm[q0 + q] * S
            yq = w.x[rq] / sp.val[vb + (sp.row_ptr[p0 + q + 1] - 1) * S]
            if lane == 0:
                w.y[rq] = yq
            for j in range(sp.cptr[p0 + q] + lane, sp.cptr[p0 + q + 1], LANES):
                rp = rb + sp.crow[e0 + j] * S
                w.x[rp] = w.x[rp] - sp.val[vb + sp.cent[e0 + j] * S] * yq
            sync()
        # forward, tail rows: the fixed columns in parallel, then the dense tail by columns
        for t in range(lane, nt, LANES):
            tr = tb + t * ts
            s = w.x[rb + (nf + t) * S]
            for p in range(nf):
                s -= sp.tail[tr + p * S] * w.y[rb + sp.perm[q0 + p] * S]
            w.x[rb + (nf + t) * S] = s
        sync()
        for t in range(nt):
            yt = w.x[rb + (nf + t) * S] / sp.tail[tb + t * ts + (nf + t) * S]
            if lane == 0:
                w.y[rb + (nf + t) * S] = yt
            for i in range(t + 1 + lane, nt, LANES):
                ri = rb + (nf + i) * S
                w.x[ri] = w.x[ri] - sp.tail[tb + i * ts + (nf + t) * S] * yt
            sync()
        # backward, tail rows: x_t = y_t / L_tt (y_t final once the rows after t have updated it), then row t of
        # L_t updates the tail rows before it; then the tail's share of the fixed rows in parallel
        for tt in range(nt):
            t = nt - 1 - tt
            tr = tb + t * ts
            xt = w.y[rb + (nf + t) * S] / sp.tail[tr + (nf + t) * S]
            if lane == 0:
                w.x[rb + (nf + t) * S] = xt
            for i in range(lane, t, LANES):
                ri = rb + (nf + i) * S
                w.y[ri] = w.y[ri] - sp.tail[tr + (nf + i) * S] * xt
            sync()
        if nt > 0:
            for p in range(lane, nf, LANES):
                r = rb + sp.perm[q0 + p] * S
                s = w.y[r]
                for t in range(nt):
                    s -= sp.tail[tb + t * ts + p * S] * w.x[rb + (nf + t) * S]
                w.y[r] = s
            sync()
        # backward, fixed rows: x_p = y_p / L_pp, then row p of L_f updates the rows before it
        for pp in range(nf):
            p = nf - 1 - pp
            r = rb + sp.perm[q0 + p] * S
            k1 = sp.row_ptr[p0 + p + 1] - 1
            xp = w.y[r] / sp.val[vb + k1 * S]
            if lane == 0:
                w.x[r] = xp
            for k in range(sp.row_ptr[p0 + p] + lane, k1, LANES):
                rq = rb + sp.colrow[e0 + k] * S
                w.y[rq] = w.y[rq] - sp.val[vb + k * S] * xp
            sync()

    @wp.kernel(module="unique", enable_backward=False)
    def solve_fixed(m: M, w: Work, sp: SP, unconverged_only: int):
        """Post-stabilisation's solve with the fixed rows' factor, 32 threads per world (``post_stabilisation.solve``
        on this schedule): ``lambda = P (P D_ff P + s I)^-1 x`` into ``x``."""
        wid, lane = wp.tid()
        if unconverged_only != 0 and w.converged[wid] != 0:
            return
        solve(m, w, sp, wid, sp.n_fixed[wid], lane)
        sync()
        rb = bases(m, sp, wid)[0]
        for a in range(lane, sp.n_fixed[wid], LANES):
            w.x[rb + a * S] = w.P[rb + a * S] * w.x[rb + a * S]

    # --- iterations ---------------------------------------------------------------------------------------
    @wp.func
    def row_penalty(w: Work, r: int, a: int, nf: int, rho_free: scalar, rho_box: scalar, rho_u: scalar):
        """Row ``a``'s penalty (``solver.row_penalty``)."""
        if a >= nf:
            return rho_u
        if wp.isfinite(w.lo_s[r]) or wp.isfinite(w.hi_s[r]):
            return rho_box
        return rho_free

    @wp.kernel(module="unique", enable_backward=False)
    def padmm_iterate(m: M, w: Work, sp: SP, chunk: int, eta: scalar, rho_free: scalar, rho_box: scalar,
                      tol: scalar, restart_tol: scalar, accelerate: int, fixed: int, adaptive: int):
        """Up to ``chunk`` accelerated PADMM iterations of one world with its 32 threads (``solver.padmm_iterate``
        with the sparse factor, rule for rule: §7.3-§7.5, the penalty of the limit and contact rows, the
        null-direction test), resuming from the stored iterate; a world that converges (unless ``fixed``) or
        reaches its cap is marked done and leaves ``remaining``."""
        wid, lane = wp.tid()
        if w.done[wid] != 0:
            return
        rb = bases(m, sp, wid)[0]
        n = w.n_rows[wid]
        n_box = w.n_box[wid]
        nc = (n - n_box) // 3
        nf = m.row_fixed[wid]
        p_ref = w.p_ref[wid]
        rho_u = w.rho_u[wid]
        for step in range(chunk):
            # steps 1-2: De Saxcé correction, right-hand side (into x), linear solve
            for a in range(lane, n, LANES):
                r = rb + a * S
                rho = row_penalty(w, r, a, nf, rho_free, rho_box, rho_u)
                rhs = -w.vt[r] + eta * w.x_p[r] + rho * w.y_hat[r] + w.z_hat[r]
                if a >= n_box and (a - n_box) % 3 == 2:
                    rhs -= de_saxce(w.z_hat[r - 2 * S], w.z_hat[r - S], w.mu[r - 2 * S])
                w.x[r] = rhs
            sync()
            solve(m, w, sp, wid, n, lane)
            sync()
            # steps 3-4: projection, dual update and the residuals: box rows, then contact triples
            r_p = zero
            r_d = zero
            r_c = zero
            c_sum = zero
            r_tail = zero
            de = zero
            dx = zero
            for a in range(lane, n_box, LANES):
                r = rb + a * S
                rho = row_penalty(w, r, a, nf, rho_free, rho_box, rho_u)
                x = w.x[r]
                z_hat = w.z_hat[r]
                lo = w.lo_s[r]
                hi = w.hi_s[r]
                y = wp.clamp(x - z_hat / rho, lo, hi)
                w.y[r] = y
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
            for c in range(lane, nc, LANES):
                r = rb + (n_box + 3 * c) * S
                cp = cone_project(w.x[r] - inv_rho * w.z_hat[r], w.x[r + S] - inv_rho * w.z_hat[r + S],
                                  w.x[r + 2 * S] - inv_rho * w.z_hat[r + 2 * S], w.mu[r])
                yz = zero
                for t in range(3):
                    rt = r + t * S
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
            r_p = lane_max(r_p)
            r_d = lane_max(r_d)
            r_c = lane_max(r_c)
            c_sum = lane_sum(c_sum)
            r_tail = lane_max(r_tail)
            de = lane_max(de)
            dx = lane_max(dx)
            k = w.iters[wid] + 1
            converged = k >= 2 and r_p <= tol and r_d <= tol and r_c <= tol
            if k >= 2 and r_p <= tol and r_tail <= tol and r_c <= tol and dx > zero:
                if de <= null_ratio * (eta + rho_free) * dx:
                    converged = True
            # §7.4: fast ADMM with restart
            mom = momentum(w.a_p[wid], w.c_p[wid], c_sum, restart_tol, accelerate)
            beta = mom[2]
            mode = int(mom[3])
            a_new = mom[0]
            c_new = mom[1]
            if adaptive != 0 and n > nf and not converged:
                rho_n = balanced_penalty(rho_u, r_p, r_d, k, w.k_rho[wid])
                if rho_n != rho_u:
                    rho_u = rho_n
                    mode = RESTART_HERE
                    a_new = scalar(1.0)
                    c_new = big
                    sync()
                    factor_tail(m, w, sp, wid, n, eta + rho_u, lane)
                    if lane == 0:
                        w.rho_u[wid] = rho_n
                        w.k_rho[wid] = k
            for a in range(lane, n, LANES):
                r = rb + a * S
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
            done = (converged and fixed == 0) or k >= w.it_cap[wid]
            sync()  # every thread has read the world's scalars before they change
            if lane == 0:
                w.a_p[wid] = a_new
                w.c_p[wid] = c_new
                w.iters[wid] = k
                w.r_p[wid] = r_p
                w.r_d[wid] = r_d
                w.r_c[wid] = r_c
                if done:
                    w.converged[wid] = int(converged)
                    w.done[wid] = 1
                    wp.atomic_sub(w.remaining, 0, 1)
            sync()
            if done:
                return

    return SimpleNamespace(factor=factor, factor_tail=factor_tail, solve=solve, solve_fixed=solve_fixed,
                           padmm_iterate=padmm_iterate)
