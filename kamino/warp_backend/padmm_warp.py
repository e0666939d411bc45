"""Proximal-ADMM with one GPU warp per world (formulation.md §7-§8.1; paper Alg. 1).

The LLT solve for worlds of tens to a few hundred rows. A world is one block of 32 threads; thread
``l`` owns the rows ``a = l, l + 32, ...`` and keeps their PADMM vectors in registers. The scaled
Delassus matrix ``D~ = P D P + (eta + rho) I`` of the world's ``n`` active rows is copied to a
world-contiguous ``n x n`` slot and factorised in place, ``D~ = U^T U`` (right-looking, row ``k`` of
``U`` then the trailing rows, the 32 threads splitting each row), with ``U^T`` mirrored into the lower
triangle so that both substitutions read contiguous rows. Every PADMM iteration solves with the factor
(forward then backward substitution: one row per step, the 32 threads updating the rest of the
right-hand side), exchanges a contact's three rows through a small per-world scratch, and reduces the
residuals (§7.5) across the 32 threads. A world iterates until it converges or reaches its cap inside
one launch.

Work and memory traffic scale with the active rows ``n`` (not the capacity): a four-bar resting on a
plane with 117 rows of capacity and 33 active rows factorises a 33 x 33 matrix. Threads of a world meet
at block barriers (``sync``); on the CPU the block runs as cooperative fibers
(``warp.config.enable_cpu_blocks``), so CI checks this kernel too. Every iteration computes what
``padmm_iterate`` (``solver.py``) and ``kamino/jax_ref/padmm.py`` compute; only the ownership of the work
and the order of the factorisation's sums differ.
"""

import functools

import warp as wp

from kamino.warp_backend.cone import cone_funcs
from kamino.warp_backend.indexing import index_funcs
from kamino.warp_backend.model_data import model_struct
from kamino.warp_backend.padmm_rules import padmm_funcs
from kamino.warp_backend.types import types_of
from kamino.warp_backend.workspace import work_struct

#: Threads per world (one GPU warp).
LANES = 32


@wp.func_native("WP_TILE_SYNC();")
def sync():
    """Barrier of the threads of a block (``__syncthreads`` on CUDA, the fiber barrier on the CPU)."""
    ...


def warp_slots(max_rows: int) -> int:
    """Rows per thread for worlds of up to ``max_rows`` rows."""
    return max(1, -(-max_rows // LANES))


@functools.cache
def warp_kernels(np_dtype, NJ: int):
    """``(to_dense, padmm_warp)`` for worlds of up to ``32 NJ`` rows (launch ``padmm_warp`` with
    ``wp.launch_tiled(dim=num_worlds, block_dim=32)``)."""
    T = types_of(np_dtype)
    scalar = T.scalar
    vecJ = wp.types.vector(length=NJ, dtype=scalar)
    M = model_struct(np_dtype)
    Work = work_struct(np_dtype)
    cf = cone_funcs(np_dtype)
    cone_project, de_saxce = cf.cone_project, cf.de_saxce
    ix = index_funcs(np_dtype)
    ridx, didx = ix.ridx, ix.didx
    pf = padmm_funcs(np_dtype)
    momentum, extrapolated, box_complementarity = pf.momentum, pf.extrapolated, pf.box_complementarity
    store_row, store_world, dual_update = pf.store_row, pf.store_world, pf.dual_update
    zero = scalar(0.0)
    one = scalar(1.0)

    @wp.kernel(module="unique", enable_backward=False)
    def to_dense(m: M, w: Work, A: wp.array3d(dtype=scalar)):
        """Row ``a`` of the scaled ``D~`` (active rows only) into the world's contiguous slot."""
        wid, a = wp.tid()
        n = w.n_rows[wid]
        if a >= n:
            return
        for b in range(n):
            A[wid, a, b] = w.D[didx(m, wid, a, b)]

    @wp.func
    def factorize(A: wp.array2d(dtype=scalar), n: int, lane: int):
        """``A = U^T U`` in place (upper triangle), ``U^T`` mirrored into the lower triangle."""
        for k in range(n):
            sync()
            ukk = wp.sqrt(A[k, k])
            sync()
            for j in range(k + lane, n, LANES):
                u = A[k, j] / ukk
                if j == k:
                    u = ukk
                A[k, j] = u
                if j > k:
                    A[j, k] = u
            sync()
            for i in range(k + 1, n):
                uki = A[k, i]
                for j in range(i + lane, n, LANES):
                    A[i, j] = A[i, j] - uki * A[k, j]

    @wp.func
    def solve(A: wp.array2d(dtype=scalar), b: wp.array(dtype=scalar), y: wp.array(dtype=scalar),
              x: wp.array(dtype=scalar), n: int, lane: int):
        """``x = A^-1 b`` with the factor of :func:`factorize` (``b`` and ``y`` are overwritten)."""
        for i in range(n):  # U^T y = b, column by column
            sync()
            yi = b[i] / A[i, i]
            for j in range(i + 1 + lane, n, LANES):
                b[j] = b[j] - A[i, j] * yi
            if lane == i % LANES:
                y[i] = yi
        for ii in range(n):  # U x = y, from the last row up, reading U's columns as rows of U^T
            i = n - 1 - ii
            sync()
            xi = y[i] / A[i, i]
            for k in range(lane, i, LANES):
                y[k] = y[k] - A[i, k] * xi
            if lane == i % LANES:
                x[i] = xi
        sync()

    @wp.func
    def block_max(red: wp.array(dtype=scalar), v: scalar, lane: int):
        red[lane] = v
        sync()
        r = red[0]
        for l in range(1, LANES):
            r = wp.max(r, red[l])
        sync()
        return r

    @wp.func
    def block_sum(red: wp.array(dtype=scalar), v: scalar, lane: int):
        red[lane] = v
        sync()
        r = red[0]
        for l in range(1, LANES):
            r += red[l]
        sync()
        return r

    @wp.kernel(module="unique", enable_backward=False)
    def padmm_warp(m: M, w: Work, A: wp.array3d(dtype=scalar), S: wp.array3d(dtype=scalar),
                   red: wp.array2d(dtype=scalar), factor: int, eta: scalar, rho: scalar, tol: scalar,
                   restart_tol: scalar, accelerate: int, fixed: int):
        """Accelerated PADMM with restart (§7.3-§7.5), one world per block of 32 threads, from the stored
        iterate until convergence (unless ``fixed``) or the cap ``it_cap``; ``factor`` factorises ``A``
        first (a refinement pass reuses the factor)."""
        wid, lane = wp.tid()
        if w.done[wid] != 0:
            return
        n = w.n_rows[wid]
        n_box = w.n_box[wid]
        Aw = A[wid]
        sb = S[wid, 0]
        sy = S[wid, 1]
        sx = S[wid, 2]
        sv = S[wid, 3]
        rw = red[wid]
        if factor != 0:
            factorize(Aw, n, lane)
        x_p = vecJ()
        y_p = vecJ()
        z_p = vecJ()
        y_hat = vecJ()
        z_hat = vecJ()
        vt = vecJ()
        lo = vecJ()
        hi = vecJ()
        P = vecJ()
        mu = vecJ()
        for j in range(NJ):
            a = lane + LANES * j
            P[j] = one
            if a < n:
                r = ridx(m, wid, a)
                x_p[j] = w.x_p[r]
                y_p[j] = w.y_p[r]
                z_p[j] = w.z_p[r]
                y_hat[j] = w.y_hat[r]
                z_hat[j] = w.z_hat[r]
                vt[j] = w.vt[r]
                P[j] = w.P[r]
                if a < n_box:
                    lo[j] = w.lo_s[r]
                    hi[j] = w.hi_s[r]
                else:
                    mu[j] = w.mu[ridx(m, wid, n_box + 3 * ((a - n_box) // 3))]
        p_ref = w.p_ref[wid]
        a_p = w.a_p[wid]
        c_p = w.c_p[wid]
        k = w.iters[wid]
        cap = w.it_cap[wid]
        x = vecJ()
        y = vecJ()
        z = vecJ()
        r_p = zero
        r_d = zero
        r_c = zero
        converged = bool(False)
        while k < cap:
            # steps 1-2: De Saxcé correction on contact normal rows, rhs, linear solve with the factor
            for j in range(NJ):
                a = lane + LANES * j
                if a < n:
                    sv[a] = z_hat[j]
            sync()
            for j in range(NJ):
                a = lane + LANES * j
                if a < n:
                    rhs = -vt[j] + eta * x_p[j] + rho * y_hat[j] + z_hat[j]
                    if a >= n_box and (a - n_box) % 3 == 2:
                        rhs -= de_saxce(sv[a - 2], sv[a - 1], mu[j])
                    sb[a] = rhs
            solve(Aw, sb, sy, sx, n, lane)
            # step 3: projection (clip on box rows, the cone on a contact's three rows)
            for j in range(NJ):
                a = lane + LANES * j
                if a < n:
                    x[j] = sx[a]
                    sv[a] = x[j] - z_hat[j] / rho
            sync()
            rp_l = zero
            rd_l = zero
            rc_l = zero
            cs_l = zero
            for j in range(NJ):
                a = lane + LANES * j
                if a < n:
                    if a < n_box:
                        y[j] = wp.clamp(sv[a], lo[j], hi[j])
                    else:
                        c0 = n_box + 3 * ((a - n_box) // 3)
                        p = cone_project(sv[c0], sv[c0 + 1], sv[c0 + 2], mu[j])
                        y[j] = p[a - c0]
                    # step 4: dual update and the residuals of §7.5 (unscaled units)
                    du = dual_update(x[j], y[j], x_p[j], y_hat[j], z_hat[j], P[j], eta, rho, p_ref)
                    z[j] = du[0]
                    rp_l = wp.max(rp_l, du[1])
                    rd_l = wp.max(rd_l, du[2])
                    cs_l += du[3]
                    if a < n_box:
                        rc_l = wp.max(rc_l, box_complementarity(y[j], z[j], lo[j], hi[j]))
                    sb[a] = y[j] * z[j]
            sync()
            for j in range(NJ):
                a = lane + LANES * j
                if a < n and a >= n_box and (a - n_box) % 3 == 0:
                    rc_l = wp.max(rc_l, wp.abs(sb[a] + sb[a + 1] + sb[a + 2]))
            r_p = block_max(rw, rp_l, lane)
            r_d = block_max(rw, rd_l, lane)
            r_c = block_max(rw, rc_l, lane)
            c_sum = block_sum(rw, cs_l, lane)
            k += 1
            converged = k >= 2 and r_p <= tol and r_d <= tol and r_c <= tol
            # §7.4: fast ADMM with restart
            mom = momentum(a_p, c_p, c_sum, restart_tol, accelerate)
            a_p = mom[0]
            c_p = mom[1]
            beta = mom[2]
            mode = int(mom[3])
            for j in range(NJ):
                y_hat[j] = extrapolated(y[j], y_p[j], beta, mode)
                z_hat[j] = extrapolated(z[j], z_p[j], beta, mode)
                x_p[j] = x[j]
                y_p[j] = y[j]
                z_p[j] = z[j]
            if converged and fixed == 0:
                break
        for j in range(NJ):
            a = lane + LANES * j
            if a < n:
                store_row(w, ridx(m, wid, a), x[j], y[j], z[j], x_p[j], y_p[j], z_p[j], y_hat[j], z_hat[j])
        if lane == 0:
            store_world(w, wid, a_p, c_p, k, r_p, r_d, r_c, converged)

    return to_dense, padmm_warp
