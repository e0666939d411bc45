"""Proximal-ADMM with one thread block per world (formulation.md §7-§8.1; paper Alg. 1).

An alternative to the one-thread-per-world LLT solve of ``solver.py``, selected with
``Stepper(padmm="block")``. Every world is one block of ``R`` threads, ``R`` its padded row capacity:
thread ``a`` owns constraint row ``a`` and keeps that row's PADMM vectors in registers for the whole
solve; the Cholesky factor of the scaled Delassus matrix ``D~ = P D P + (eta + rho) I`` lives in shared
memory (``wp.tile_cholesky``, cuSolverDx on CUDA) and every iteration's linear solve (§8.1) is one
cooperative ``wp.tile_cholesky_solve``. Rows talk to each other only where the physics couples them:
a contact's three rows for the De Saxcé correction and the cone projection, and the block-wide
reductions of the residuals (§7.5). A world iterates until it converges or reaches its cap inside one
launch, so converged worlds stop working without any host or device-flag round trip.

Unused rows (``a >= n``, padding to ``R``) are identity rows with zero data: their iterates stay zero.
Every iteration computes what ``padmm_iterate`` (``kamino/warp_backend/solver.py``) and
``kamino/jax_ref/padmm.py`` compute; only the ownership of the work differs (in float64 the iterates
agree with the one-thread-per-world kernel to rounding, with the same iteration counts).

Measured on an H100 (docs/warp_backend.md, "One block per world"): it pays only where the worlds' row
capacity is filled by active rows (ladder8, 144 rows: 1.6x the one-thread-per-world throughput at 4096
worlds); the factorisation and each solve cost the padded ``R``, so a world whose capacity is mostly
unused contact rows (the MJCF four-bar: 117 rows of capacity, about 33 active) runs 7x slower.
"""

import functools

import numpy as np
import warp as wp

from kamino.warp_backend.cone import cone_funcs
from kamino.warp_backend.indexing import index_funcs
from kamino.warp_backend.model_data import model_struct
from kamino.warp_backend.padmm_rules import padmm_funcs
from kamino.warp_backend.types import types_of
from kamino.warp_backend.workspace import work_struct

#: Largest padded row count solved by the block-per-world kernel, per precision: the factor (``R^2``
#: entries) must fit in a block's shared memory (227 KiB on sm_90) next to the small exchange tiles.
TILE_MAX_ROWS = {np.dtype(np.float32): 160, np.dtype(np.float64): 96}
#: Rows are padded to a multiple of this (a GPU warp).
TILE_ROW_QUANTUM = 32


def tile_rows(max_rows: int) -> int:
    """Padded row count ``R`` (block size) for worlds of up to ``max_rows`` rows."""
    return max(TILE_ROW_QUANTUM, -(-max_rows // TILE_ROW_QUANTUM) * TILE_ROW_QUANTUM)


def max_tile_rows(np_dtype) -> int:
    """Largest row count per world of the block-per-world kernel in ``np_dtype``."""
    return TILE_MAX_ROWS[np.dtype(np_dtype)]


def tile_fits(max_rows: int, np_dtype) -> bool:
    """Whether worlds of up to ``max_rows`` rows run on the block-per-world kernel."""
    return tile_rows(max_rows) <= TILE_MAX_ROWS[np.dtype(np_dtype)]


@functools.cache
def tile_kernels(np_dtype, R: int):
    """``(to_tile, padmm_tile)`` for worlds padded to ``R`` rows (launch ``padmm_tile`` with
    ``wp.launch_tiled(dim=num_worlds, block_dim=R)``)."""
    T = types_of(np_dtype)
    scalar = T.scalar
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
    def to_tile(m: M, w: Work, Dt: wp.array3d(dtype=scalar)):
        """Row ``a`` of the scaled ``D~`` into the world's contiguous ``R x R`` slot, identity padded."""
        wid, a = wp.tid()
        n = w.n_rows[wid]
        for b in range(R):
            v = zero
            if a < n and b < n:
                v = w.D[didx(m, wid, a, b)]
            elif a == b:
                v = one
            Dt[wid, a, b] = v

    @wp.func
    def contact_base(a: int, n_box: int):
        return n_box + 3 * ((a - n_box) // 3)

    @wp.kernel(module="unique", enable_backward=False)
    def padmm_tile(m: M, w: Work, Dt: wp.array3d(dtype=scalar), eta: scalar, rho: scalar, tol: scalar,
                   restart_tol: scalar, accelerate: int, fixed: int):
        """Accelerated PADMM with restart (§7.3-§7.5) of one world per block, row ``a`` per thread, from the
        stored iterate until convergence (unless ``fixed``) or the cap ``it_cap``."""
        wid, a = wp.tid()
        n = w.n_rows[wid]
        n_box = w.n_box[wid]
        if w.done[wid] != 0:
            return
        L = wp.tile_load(Dt[wid], shape=(R, R), storage="shared")
        wp.tile_cholesky_inplace(L)
        active = a < n
        is_box = a < n_box
        c0 = contact_base(a, n_box)
        j = a - c0  # 0, 1: tangential rows; 2: normal row (contacts only)
        r = int(0)
        x_p = zero
        y_p = zero
        z_p = zero
        y_hat = zero
        z_hat = zero
        vt = zero
        lo = zero
        hi = zero
        P = one
        mu = zero
        if active:
            r = ridx(m, wid, a)
            x_p = w.x_p[r]
            y_p = w.y_p[r]
            z_p = w.z_p[r]
            y_hat = w.y_hat[r]
            z_hat = w.z_hat[r]
            vt = w.vt[r]
            P = w.P[r]
            if is_box:
                lo = w.lo_s[r]
                hi = w.hi_s[r]
            else:
                mu = w.mu[ridx(m, wid, c0)]
        cont = active and not is_box
        shift_inv_rho = one / rho
        a_p = w.a_p[wid]
        c_p = w.c_p[wid]
        p_ref = w.p_ref[wid]
        k = w.iters[wid]
        cap = w.it_cap[wid]
        x = zero
        y = zero
        z = zero
        r_p = zero
        r_d = zero
        r_c = zero
        converged = bool(False)
        while k < cap:
            # steps 1-2: De Saxcé correction on the normal row, rhs, linear solve with the cached factor
            rhs = -vt + eta * x_p + rho * y_hat + z_hat
            zt = wp.tile(z_hat)
            if cont and j == 2:
                rhs -= de_saxce(wp.tile_extract(zt, c0), wp.tile_extract(zt, c0 + 1), mu)
            x = wp.untile(wp.tile_cholesky_solve(L, wp.tile(rhs)))
            # step 3: projection (clip on box rows, the cone on a contact's three rows)
            v = x - shift_inv_rho * z_hat
            vtile = wp.tile(v)
            if cont:
                p = cone_project(wp.tile_extract(vtile, c0), wp.tile_extract(vtile, c0 + 1),
                                 wp.tile_extract(vtile, c0 + 2), mu)
                y = p[j]
            else:
                y = wp.clamp(v, lo, hi)
            # step 4: dual update and the residuals of §7.5 (unscaled units)
            du = dual_update(x, y, x_p, y_hat, z_hat, P, eta, rho, p_ref)
            z = du[0]
            rc_row = zero
            if is_box:
                rc_row = box_complementarity(y, z, lo, hi)
            yz = wp.tile(y * z)
            if cont and j == 0:
                rc_row = wp.abs(wp.tile_extract(yz, c0) + wp.tile_extract(yz, c0 + 1) + wp.tile_extract(yz, c0 + 2))
            r_p = wp.tile_extract(wp.tile_max(wp.tile(du[1])), 0)
            r_d = wp.tile_extract(wp.tile_max(wp.tile(du[2])), 0)
            r_c = wp.tile_extract(wp.tile_max(wp.tile(rc_row)), 0)
            c_sum = wp.tile_extract(wp.tile_sum(wp.tile(du[3])), 0)
            k += 1
            converged = k >= 2 and r_p <= tol and r_d <= tol and r_c <= tol
            # §7.4: fast ADMM with restart
            mom = momentum(a_p, c_p, c_sum, restart_tol, accelerate)
            a_p = mom[0]
            c_p = mom[1]
            y_hat = extrapolated(y, y_p, mom[2], int(mom[3]))
            z_hat = extrapolated(z, z_p, mom[2], int(mom[3]))
            x_p = x
            y_p = y
            z_p = z
            if converged and fixed == 0:
                break
        if active:
            store_row(w, r, x, y, z, x_p, y_p, z_p, y_hat, z_hat)
        if a == 0:
            store_world(w, wid, a_p, c_p, k, r_p, r_d, r_c, converged)

    return to_tile, padmm_tile
