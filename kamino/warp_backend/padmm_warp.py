"""Proximal-ADMM with one GPU warp (32 threads) per world on the sparse factor or with Conjugate Residual
(docs/formulation.md §7-§8.2; paper Alg. 1): the schedule for robot-sized worlds (``Stepper(padmm="warp")``).

One thread per world (``solver.padmm_iterate``) walks a world's factor and vectors alone: at 4096 worlds that is one
warp per multiprocessor, and every PADMM iteration of dr_legs is a chain of about 16,000 dependent loads. Here the
32 threads of a block share one world and the chain is cut down to the rows:

- **Factorisation** (:func:`factor`, once per step). The fixed rows by columns ("fan-out"): for column ``q``,
  ``L_qq = sqrt(D~_qq)``, the column's entries ``L_pq = D~_pq / L_qq`` (threads over the entries), then every update
  ``D~_pr -= L_pq L_rq`` that column ``q`` feeds (threads over the precomputed triples, ``Symbolic.fan_*``: their
  targets are distinct, so no atomics). The tail rows (active limits and contacts): ``L_tf`` by a forward
  substitution per tail row (threads over tail rows), the Schur complement ``S_t`` (threads over all its entry
  pairs ``(t, j <= t)``) and its dense Cholesky by columns (:func:`factor_tail`). Same sums as
  ``sparse_llt.factor``, in another order. ``L_f`` is stored once, in row order.
- **Solve** (:func:`solve`, every iteration). Column sweeps: the forward substitution of the fixed rows walks the
  columns of ``L_f`` (``x_q = b_q / L_qq``, then the column's entries update the rows below, threads over the
  entries; each entry's index in ``L_f``'s row order, ``cent``, is loaded two columns ahead, so that the value waits
  on no index load), the backward one walks its rows (``x_p``, then the entries of row ``p`` update the rows above);
  the tail's dense rows likewise, and the tail's share of the fixed rows is one parallel pass. One barrier per row;
  the right-hand side is updated in ``w.y`` (free during the solve) and the solution lands in ``w.x``.
  docs/warp_backend.md, "Where a PADMM iteration's time goes", has what each load ordering cost.
- **Iterations** (:func:`padmm_iterate`). Every per-row rule (projection, dual update, residuals, the penalty of
  the limit and contact rows, the null-direction test, momentum) is ``padmm_rules.py``'s, the threads splitting the
  box rows and the contact triples; the world's maxima and sums are block reductions. Iteration counts equal the
  thread kernel's (``tests/test_warp_lane_padmm.py``).
- **Conjugate Residual** (``warp_kernels(cr=True)``: :func:`cr_solve`, §8.2, instead of the factor). The operator
  ``P J M^-1 J^T P + diag(P^2 R + eta + rho)`` is applied matrix-free: the threads split the bodies for ``M^-1 J^T P
  v`` (each body's row blocks listed once per step by ``cr_pattern``, so that a body's sum needs no atomics and
  keeps ``solver.apply_operator``'s order), then the rows for ``J`` times it; CR's dot products are block sums.

Threads of a world meet at block barriers (``sync``); on the CPU the block runs as cooperative fibers
(``warp.config.enable_cpu_blocks``), which is how CI checks this kernel against the thread kernel.
"""

import functools
from types import SimpleNamespace

import numpy as np
import warp as wp

from kamino.config import NULL_DIRECTION_RATIO
from kamino.warp_backend.cone import cone_funcs
from kamino.warp_backend.indexing import index_funcs
from kamino.warp_backend.model_data import model_struct
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


#: Rounds of fan-out update triples (32 per round) whose indices a thread of :func:`factor` loads together.
FAN_BATCH = 4
FanIdx = wp.types.vector(length=FAN_BATCH, dtype=wp.int32)

#: The largest ``L_f`` (entries) that :func:`factor` factorises in shared memory; a larger one is factorised in
#: device memory (the animatronic's 43,000 entries would leave room for one world per multiprocessor).
STAGE_MAX_ENTRIES = 12288


def shared_rows(max_rows: int) -> int:
    """The length of the shared vectors for worlds of up to ``max_rows`` rows (a multiple of ``LANES``: one compiled
    module serves every size up to it)."""
    return LANES * max(1, -(-max_rows // LANES))


def shared_entries(max_nnz: int) -> int:
    """The entries of ``L_f`` that :func:`factor` stages in shared memory for factors of up to ``max_nnz`` entries:
    ``max_nnz`` rounded up (so that similar scenes share a compiled module), or 0 above
    :data:`STAGE_MAX_ENTRIES`."""
    E = 256 * max(1, -(-max_nnz // 256))
    return E if E <= STAGE_MAX_ENTRIES else 0


#: Registers per thread of :func:`warp_kernels`' ``padmm_iterate`` for worlds of at least
#: :data:`REGISTER_CAP_MIN_ROWS` rows (CUDA ``__maxnreg__``; ``None``: the compiler's choice). Left to the compiler it
#: takes 122 on sm_90, so a multiprocessor holds 16 worlds (65,536 registers / (128 x 32)) of the 32 blocks it could;
#: at 72 it holds 28, at the cost of some spilling. Measured on an H100 (benchmarks/README.md, the register cap): PPO's
#: collection on dr_legs at 16384 worlds 137 -> 120 ms per step, the standing robots at 4096 worlds +1 %, the
#: four-bar (117 rows) 12 % slower, hence the threshold.
ITERATE_MAX_REGISTERS: int | None = 72
REGISTER_CAP_MIN_ROWS = 200


@functools.cache
def warp_kernels(np_dtype, R: int, E: int = 0, cr: bool = False) -> SimpleNamespace:
    """``factor``, ``padmm_iterate`` and ``solve_fixed`` (post-stabilisation) for worlds of up to ``R`` rows; launch
    each with ``wp.launch_tiled(dim=[num_worlds], block_dim=LANES)``. The solve keeps two vectors of ``R`` rows in
    shared memory (2 R scalars per world). With ``E > 0`` the factorisation copies the world's ``D~_f`` (up to ``E``
    entries) into shared memory, factorises it there and writes ``L_f`` back: its chain of dependent
    read-modify-writes, one per update, then waits on shared memory instead of device memory.

    With ``cr`` the iterations solve with Conjugate Residual instead of the factor (§8.2: :func:`cr_solve`, the
    vectors in the ``Work`` rows, no shared vectors), after ``cr_pattern`` (one thread per world, ``wp.launch``) has
    grouped the world's row blocks by body for the step; ``factor`` is not launched then."""
    T = types_of(np_dtype)
    scalar, vec6 = T.scalar, T.vec6
    M = model_struct(np_dtype)
    Work = work_struct(np_dtype)
    SP = pattern_struct(np_dtype)
    cf = cone_funcs(np_dtype)
    cone_project, de_saxce = cf.cone_project, cf.de_saxce
    pf = padmm_funcs(np_dtype)
    momentum, extrapolated, box_complementarity = pf.momentum, pf.extrapolated, pf.box_complementarity
    balanced_penalty, dual_update, saturates = pf.balanced_penalty, pf.dual_update, pf.saturates
    slk = sparse_llt_kernels(np_dtype)
    bases, schur_entry, fixed_entry, tail_row = slk.bases, slk.schur_entry, slk.fixed_entry, slk.tail_row
    tail_k, tail_pattern, sdiag_col = slk.tail_k, slk.tail_pattern, slk.sdiag_col
    inv_mass_times, residual_weight = slk.inv_mass_times, pf.residual_weight
    ix = index_funcs(np_dtype)
    row_saturated, set_saturated, row_mu, row_base = ix.row_saturated, ix.set_saturated, ix.row_mu, ix.row_base
    big = scalar(float(np.finfo(np_dtype).max))
    null_ratio = scalar(NULL_DIRECTION_RATIO)
    zero = scalar(0.0)
    FanVal = wp.types.vector(length=FAN_BATCH, dtype=scalar)

    @wp.func
    def lane_max(v: scalar):
        return wp.tile_extract(wp.tile_max(wp.tile(v)), 0)

    @wp.func
    def lane_sum(v: scalar):
        return wp.tile_extract(wp.tile_sum(wp.tile(v)), 0)

    # --- factorisation ------------------------------------------------------------------------------------
    EL = max(E, 1)  # staged length (1: not staged)
    LVec = wp.tile(dtype=scalar, shape=(EL,), storage="shared")

    @wp.func_native("t.data(i) = v;")
    def lset(t: LVec, i: int, v: scalar):
        """``t[i] = v`` by one thread, no barrier (``t[i] = v`` on a tile synchronises the block)."""
        ...

    @wp.func_native("return t.data(i);")
    def lget(t: LVec, i: int) -> scalar:
        """``t[i]`` of a shared vector."""
        ...

    @wp.func
    def fget(sp: SP, vb: int, k: int, lv: LVec) -> scalar:
        """Entry ``k`` (CSR order) of the world's ``D~_f`` / ``L_f``: staged in shared memory, or in device memory."""
        if wp.static(E > 0):
            return lget(lv, k)
        return sp.val[vb + k * sp.val_stride]

    @wp.func
    def fset(sp: SP, vb: int, k: int, v: scalar, lv: LVec):
        """Entry ``k`` of ``L_f`` := ``v`` (staged or in device memory)."""
        if wp.static(E > 0):
            lset(lv, k, v)
        else:
            sp.val[vb + k * sp.val_stride] = v

    @wp.func
    def batch(a: wp.array(dtype=wp.int32), u: int, umax: int) -> FanIdx:
        """``a[u + r LANES]`` for the FAN_BATCH rounds ``r`` of a thread, loaded together (indices clamped to
        ``umax``)."""
        v = FanIdx()
        for r in range(FAN_BATCH):
            v[r] = a[wp.min(u + r * LANES, umax)]
        return v

    @wp.func
    def ltf_batch(sp: SP, vb: int, tr: int, tc: int, ub: int, u1: int, s: scalar, lv: LVec) -> scalar:
        """``s - sum_u L_k(u) l_j(u)`` over the pattern's update pairs ``u = ub .. ub + FAN_BATCH - 1`` before ``u1``
        (``l``: the tail row at ``tr``; ``sparse_llt.Pattern.pat_upd_*``): the FAN_BATCH pairs' indices, then their
        values, each batch loaded together (indices clamped, the surplus multiplied by zero), so that the sum waits
        on two load latencies per batch instead of two per entry."""
        kv = FanIdx()
        jv = FanIdx()
        for r in range(FAN_BATCH):
            kv[r] = sp.pat_upd_k[wp.min(ub + r, u1 - 1)]
            jv[r] = sp.pat_upd_j[wp.min(ub + r, u1 - 1)]
        tv = FanVal()
        for r in range(FAN_BATCH):
            tv[r] = sp.tail[tr + jv[r] * tc]
        for r in range(FAN_BATCH):
            lk = fget(sp, vb, kv[r], lv)
            s -= wp.where(ub + r < u1, lk * tv[r], zero)
        return s

    @wp.func
    def fan_out(sp: SP, vb: int, tv: FanIdx, av: FanIdx, bv: FanIdx, u: int, f1: int, lv: LVec, neg: int):
        """The updates ``D~_tgt -= s_q L_a L_b`` of the thread's FAN_BATCH rounds from ``u`` that lie before ``f1``
        (``neg``: the column is a hub's unknown, ``s_q = -1``, ``sparse_llt.factor_fixed_rows``)."""
        for r in range(FAN_BATCH):
            if u + r * LANES < f1:
                if neg != 0:
                    fset(sp, vb, tv[r], fget(sp, vb, tv[r], lv) + fget(sp, vb, av[r], lv) * fget(sp, vb, bv[r], lv),
                         lv)
                else:
                    fset(sp, vb, tv[r], fget(sp, vb, tv[r], lv) - fget(sp, vb, av[r], lv) * fget(sp, vb, bv[r], lv),
                         lv)

    @wp.func
    def factor_tail(m: M, w: Work, sp: SP, wid: int, n: int, shift: scalar, lane: int):
        """``L_t = chol(S_t + shift I)`` by columns (left-looking: the entries of column ``j`` are independent dot
        products over the columns before it), from ``S_t`` in the tail rows' upper slots (``S_t[t, j]`` at row
        ``j``, tail column ``K + t``) and its diagonal (column ``sparse_llt.sdiag_col``); the sums of
        ``sparse_llt.factor_tail``."""
        base = bases(m, w, sp, wid)
        tb, ts = base[2], base[3]
        tc = sp.tail_stride
        nf = sp.n_fixed[wid]
        kt = tail_k(sp, wid)
        kd = sdiag_col(sp, wid)
        for j in range(n - nf):
            jr = tb + j * ts
            d = sp.tail[jr + kd * tc] + shift
            for i in range(j):
                d -= sp.tail[jr + (kt + i) * tc] * sp.tail[jr + (kt + i) * tc]
            d = wp.sqrt(d)
            for t in range(j + 1 + lane, n - nf, LANES):
                tr = tb + t * ts
                s = sp.tail[jr + (kt + t) * tc]
                for i in range(j):
                    s -= sp.tail[tr + (kt + i) * tc] * sp.tail[jr + (kt + i) * tc]
                sp.tail[tr + (kt + j) * tc] = s / d
            if lane == 0:
                sp.tail[jr + (kt + j) * tc] = d
            sync()

    @wp.kernel(module="unique", enable_backward=False)
    def factor(m: M, w: Work, sp: SP, eta: scalar, pending_only: int, nblk: int, shift: scalar, shift_sat: scalar):
        """Cholesky ``D~ = L L^T`` in place (§8.1) with the world's 32 threads: the fixed rows by columns (fan-out
        updates), then the tail rows' ``L_tf``, their Schur complement and :func:`factor_tail` with the world's
        penalty ``eta + rho_u``. With ``pending_only`` only the worlds whose effort-limited rows saturated in the
        last PADMM iteration (``w.pending``), which first assemble ``D~`` again with the shifts ``shift`` /
        ``shift_sat`` (``sparse_llt.refactor``; kamino.jax_ref.padmm.solve, "Saturation")."""
        wid, lane = wp.tid()
        if pending_only != 0:
            if w.pending[wid] == 0:
                return
            for k in range(lane, sp.nnz[wid], LANES):
                fixed_entry(m, w, sp, wid, k, nblk, shift, shift_sat)
            for a in range(sp.n_fixed[wid] + lane, w.n_rows[wid], LANES):
                tail_row(m, w, sp, wid, a, nblk)
            sync()
        base = bases(m, w, sp, wid)
        rb, vb, tb, ts = base[0], base[1], base[2], base[3]
        tc = sp.tail_stride
        nf = sp.n_fixed[wid]
        npos = sp.n_pos[wid]  # the fixed rows, then the hubs' unknowns (sign s_q = -1: sparse_llt.factor_fixed_rows)
        e0 = sp.ent_start[wid]
        p0 = sp.ptr_start[wid]
        nnz = sp.nnz[wid]
        lv = wp.tile_zeros(shape=(EL,), dtype=scalar, storage="shared")
        if wp.static(E > 0):
            for k in range(lane, nnz, LANES):
                lset(lv, k, sp.val[vb + k * sp.val_stride])
            sync()
        # Column q's pointers are loaded during column q - 1, and its indices (two rounds of entries, FAN_BATCH
        # rounds of update triples) together at its start, unconditionally (indices clamped to the world's): a
        # column then waits on about one load latency instead of one per round (docs/warp_backend.md, "Where it
        # goes, measured part by part")
        cmax = e0 + nnz - 1
        fmax = wp.max(sp.fan_ptr[p0 + npos] - 1, 0)
        kd_n = int(0)
        c0_n = int(0)
        c1_n = int(0)
        f0_n = int(0)
        f1_n = int(0)
        if npos > 0:
            kd_n = sp.row_ptr[p0 + 1] - 1
            c0_n = sp.cptr[p0]
            c1_n = sp.cptr[p0 + 1]
            f0_n = sp.fan_ptr[p0]
            f1_n = sp.fan_ptr[p0 + 1]
        for q in range(npos):
            kd = kd_n
            c0 = c0_n
            c1 = c1_n
            f0 = f0_n
            f1 = f1_n
            qn = wp.min(q + 1, npos - 1)
            kd_n = sp.row_ptr[p0 + qn + 1] - 1
            c0_n = sp.cptr[p0 + qn]
            c1_n = sp.cptr[p0 + qn + 1]
            f0_n = sp.fan_ptr[p0 + qn]
            f1_n = sp.fan_ptr[p0 + qn + 1]
            ja = c0 + lane
            ka = sp.cent[wp.min(e0 + ja, cmax)]
            kb = sp.cent[wp.min(e0 + ja + LANES, cmax)]
            ua = f0 + lane
            tv = batch(sp.fan_tgt, ua, fmax)
            av = batch(sp.fan_a, ua, fmax)
            bv = batch(sp.fan_b, ua, fmax)
            neg = int(q >= nf)
            d = zero
            dv = zero  # s_q L_qq, the divisor of column q
            if neg != 0:
                d = wp.sqrt(-fget(sp, vb, kd, lv))
                dv = -d
            else:
                d = wp.sqrt(fget(sp, vb, kd, lv))
                dv = d
            sync()  # every thread has read D~_qq before it becomes L_qq
            if lane == 0:
                fset(sp, vb, kd, d, lv)
            if ja < c1:
                fset(sp, vb, ka, fget(sp, vb, ka, lv) / dv, lv)
            if ja + LANES < c1:
                fset(sp, vb, kb, fget(sp, vb, kb, lv) / dv, lv)
            for j in range(ja + 2 * LANES, c1, LANES):
                k = sp.cent[e0 + j]
                fset(sp, vb, k, fget(sp, vb, k, lv) / dv, lv)
            sync()
            fan_out(sp, vb, tv, av, bv, ua, f1, lv, neg)
            for ub in range(ua + FAN_BATCH * LANES, f1, FAN_BATCH * LANES):
                fan_out(sp, vb, batch(sp.fan_tgt, ub, fmax), batch(sp.fan_a, ub, fmax), batch(sp.fan_b, ub, fmax),
                        ub, f1, lv, neg)
            sync()
        if wp.static(E > 0):
            for k in range(lane, nnz, LANES):
                sp.val[vb + k * sp.val_stride] = lget(lv, k)
        sync()
        n = w.n_rows[wid]
        nt = n - nf
        for t in range(lane, nt, LANES):  # L_tf: row t solves L_f l = D~_ft over its pattern (each thread its rows)
            tr = tb + t * ts
            pt = tail_pattern(sp, wid, t)
            i0 = sp.pat_ptr[pt]
            for i in range(sp.pat_ptr[pt + 1] - i0):
                s = sp.tail[tr + i * tc]
                u1 = sp.pat_upd_ptr[i0 + i + 1]
                pos = sp.pat_pos[i0 + i]
                if pos >= nf:  # a hub position: the signed sum and divisor of sparse_llt.factor_world
                    for u in range(sp.pat_upd_ptr[i0 + i], u1):
                        uk = sp.pat_upd_k[u]
                        if sp.col[e0 + uk] >= nf:
                            s += fget(sp, vb, uk, lv) * sp.tail[tr + sp.pat_upd_j[u] * tc]
                        else:
                            s -= fget(sp, vb, uk, lv) * sp.tail[tr + sp.pat_upd_j[u] * tc]
                    sp.tail[tr + i * tc] = -s / fget(sp, vb, sp.row_ptr[p0 + pos + 1] - 1, lv)
                else:
                    for ub in range(sp.pat_upd_ptr[i0 + i], u1, FAN_BATCH):
                        s = ltf_batch(sp, vb, tr, tc, ub, u1, s, lv)
                    sp.tail[tr + i * tc] = s / fget(sp, vb, sp.row_ptr[p0 + pos + 1] - 1, lv)
        sync()
        # S_t = D~_t - L_tf L_tf^T: the entries (t, j <= t), threads over all nt (nt + 1) / 2 of them (pair u is
        # (t, j) with u = t (t + 1) / 2 + j); each reads lower slots and writes an upper slot or the diagonal column,
        # so no pair reads what another writes
        t = int(0)
        j = lane
        while j > t:  # the lane's first pair
            j -= t + 1
            t += 1
        while t < nt:
            schur_entry(w, sp, wid, rb, tb, ts, nf, t, j)
            j += LANES
            while j > t:
                j -= t + 1
                t += 1
        sync()
        factor_tail(m, w, sp, wid, n, eta + w.rho_u[wid], lane)
        if pending_only != 0 and lane == 0:
            w.pending[wid] = 0

    # --- solve --------------------------------------------------------------------------------------------
    Vec = wp.tile(dtype=scalar, shape=(R,), storage="shared")

    @wp.func_native("t.data(i) = v;")
    def sset(t: Vec, i: int, v: scalar):
        """``t[i] = v`` by one thread, no barrier (``t[i] = v`` on a tile synchronises the block)."""
        ...

    @wp.func_native("return t.data(i);")
    def sget(t: Vec, i: int) -> scalar:
        """``t[i]`` of a shared vector."""
        ...

    @wp.func
    def solve(m: M, w: Work, sp: SP, wid: int, n: int, lane: int, xs: Vec, ys: Vec):
        """``x <- L^-T L^-1 x`` with the sparse factor and its tail (``L_tf`` on its patterns, ``L_t`` dense), by
        column sweeps: one barrier per row (``sparse_llt.solve_inplace``, the same products in another order; with
        hubs ``x <- L^-T S L^-1 x``, the hubs' unknowns in their virtual rows of ``xs`` / ``ys``).
        ``xs`` holds the right-hand side on entry and the solution on exit, ``ys`` is scratch: both in shared memory,
        indexed by row. The next column's (row's) factor entries are loaded before the barrier of the current one,
        unconditionally (clamped indices), so that their latency overlaps the barrier instead of preceding it
        (docs/warp_backend.md, "Where it goes, measured part by part")."""
        base = bases(m, w, sp, wid)
        vb, tb, ts = base[1], base[2], base[3]
        tc = sp.tail_stride
        nf = sp.n_fixed[wid]
        e0 = sp.ent_start[wid]
        p0 = sp.ptr_start[wid]
        q0 = sp.perm_start[wid]
        nt = n - nf
        npos = sp.n_pos[wid]  # the fixed rows, then the hubs' unknowns (sparse_llt.solve_inplace: x <- L^-T S L^-1 x)
        if npos > nf:  # the hubs' right-hand side: 0 in their virtual rows
            for p in range(nf + lane, npos, LANES):
                sset(xs, sp.perm[q0 + p], zero)
            sync()
        # forward, fixed rows, by columns: y_q = x_q / L_qq (x_q final once the columns before q have updated it),
        # then column q updates the rows below. This thread's entry of the next column is loaded during column q,
        # without a branch: its index is clamped to the world's entries, so that nothing (a select, a branch) waits
        # for the load before the barrier, and the load's latency overlaps the rest of the step
        a_n = int(0)
        d_n = zero
        j0_n = int(0)
        j1_n = int(0)
        l_n = zero
        r_n = int(0)
        vs = sp.val_stride
        kmax = sp.nnz[wid] - 1  # the world's last entry: where the clamped loads stop
        j1_nn = int(0)  # the end of column q + 2's entries (its start is column q + 1's end): loaded two ahead
        c_nn = int(0)  # the entry index (cent) of this thread's entry of column q + 1: loaded two ahead
        kd_nn = int(0)  # the diagonal entry of column q + 1: loaded two ahead
        if npos > 0:
            a_n = sp.perm[q0]
            d_n = scalar(1.0) / sp.val[vb + (sp.row_ptr[p0 + 1] - 1) * vs]
            j0_n = sp.cptr[p0]
            j1_n = sp.cptr[p0 + 1]
            kn = wp.min(j0_n + lane, kmax)
            l_n = sp.val[vb + sp.cent[e0 + kn] * vs]
            r_n = sp.crow[e0 + kn]
            j1_nn = sp.cptr[p0 + wp.min(2, npos)]
            c_nn = sp.cent[e0 + wp.min(j1_n + lane, kmax)]
            kd_nn = sp.row_ptr[p0 + wp.min(2, npos)] - 1
        for q in range(npos):
            a_q = a_n
            yq = sget(xs, a_q) * d_n
            j0 = j0_n
            j1 = j1_n
            l_q = l_n
            r_q = r_n
            qn = wp.min(q + 1, npos - 1)
            a_n = sp.perm[q0 + qn]
            d_n = scalar(1.0) / sp.val[vb + kd_nn * vs]
            kd_nn = sp.row_ptr[p0 + wp.min(q + 3, npos)] - 1
            j0_n = j1_n
            j1_n = j1_nn
            l_n = sp.val[vb + c_nn * vs]
            r_n = sp.crow[e0 + wp.min(j0_n + lane, kmax)]
            c_nn = sp.cent[e0 + wp.min(j1_n + lane, kmax)]
            j1_nn = sp.cptr[p0 + wp.min(q + 3, npos)]
            if lane == 0:
                sset(ys, a_q, yq)
            if j0 + lane < j1:
                sset(xs, r_q, sget(xs, r_q) - l_q * yq)
            for j in range(j0 + lane + LANES, j1, LANES):
                rp = sp.crow[e0 + j]
                sset(xs, rp, sget(xs, rp) - sp.val[vb + sp.cent[e0 + j] * vs] * yq)
            sync()
        # forward, tail rows: the fixed columns in parallel, then the dense tail by columns
        kt = tail_k(sp, wid)
        for t in range(lane, nt, LANES):
            tr = tb + t * ts
            s = sget(xs, nf + t)
            pt = tail_pattern(sp, wid, t)
            i0 = sp.pat_ptr[pt]
            for i in range(sp.pat_ptr[pt + 1] - i0):
                s -= sp.tail[tr + i * tc] * sget(ys, sp.pat_row[i0 + i])
            sset(xs, nf + t, s)
        sync()
        for t in range(nt):
            yt = sget(xs, nf + t) / sp.tail[tb + t * ts + (kt + t) * tc]
            if lane == 0:
                sset(ys, nf + t, yt)
            for i in range(t + 1 + lane, nt, LANES):
                sset(xs, nf + i, sget(xs, nf + i) - sp.tail[tb + i * ts + (kt + t) * tc] * yt)
            sync()
        if npos > nf:  # y <- S y: the hubs' sign, after the tail's forward sweep read their unsigned y
            for p in range(nf + lane, npos, LANES):
                a = sp.perm[q0 + p]
                sset(ys, a, -sget(ys, a))
            sync()
        # backward, tail rows: x_t = y_t / L_tt (y_t final once the rows after t have updated it), then row t of
        # L_t updates the tail rows before it; then the tail's share of the fixed rows in parallel, each thread
        # finding its fixed positions in the tail rows' patterns through their lookups
        for tt in range(nt):
            t = nt - 1 - tt
            tr = tb + t * ts
            xt = sget(ys, nf + t) / sp.tail[tr + (kt + t) * tc]
            if lane == 0:
                sset(xs, nf + t, xt)
            for i in range(lane, t, LANES):
                sset(ys, nf + i, sget(ys, nf + i) - sp.tail[tr + (kt + i) * tc] * xt)
            sync()
        if nt > 0:
            for p in range(lane, npos, LANES):
                a = sp.perm[q0 + p]
                s = sget(ys, a)
                for t in range(nt):
                    c = sp.pat_lut[tail_pattern(sp, wid, t) * sp.pat_lut_stride + p]
                    if c >= 0:
                        s -= sp.tail[tb + t * ts + c * tc] * sget(xs, nf + t)
                sset(ys, a, s)
            sync()
        # backward, fixed rows, by rows: x_p = y_p / L_pp, then row p of L_f updates the rows before it (loaded
        # ahead like the forward sweep)
        j0_nn = int(0)  # the start of row p - 2's entries (its end is row p - 1's start): loaded two ahead
        if npos > 0:
            a_n = sp.perm[q0 + npos - 1]
            j0_n = sp.row_ptr[p0 + npos - 1]
            j1_n = sp.row_ptr[p0 + npos] - 1
            d_n = scalar(1.0) / sp.val[vb + j1_n * vs]
            kn = wp.min(j0_n + lane, kmax)
            l_n = sp.val[vb + kn * vs]
            r_n = sp.colrow[e0 + kn]
            j0_nn = sp.row_ptr[p0 + wp.max(npos - 2, 0)]
        for pp in range(npos):
            p = npos - 1 - pp
            a_p = a_n
            xp = sget(ys, a_p) * d_n
            j0 = j0_n
            j1 = j1_n
            l_p = l_n
            r_p = r_n
            a_n = sp.perm[q0 + wp.max(p - 1, 0)]
            j1_n = j0_n - 1
            j0_n = j0_nn
            d_n = scalar(1.0) / sp.val[vb + wp.max(j1_n, 0) * vs]  # row p - 1's diagonal (unused at p = 0)
            kn = wp.min(j0_n + lane, kmax)
            l_n = sp.val[vb + kn * vs]
            r_n = sp.colrow[e0 + kn]
            j0_nn = sp.row_ptr[p0 + wp.max(p - 2, 0)]
            if lane == 0:
                sset(xs, a_p, xp)
            if j0 + lane < j1:
                sset(ys, r_p, sget(ys, r_p) - l_p * xp)
            for k in range(j0 + lane + LANES, j1, LANES):
                rq = sp.colrow[e0 + k]
                sset(ys, rq, sget(ys, rq) - sp.val[vb + k * vs] * xp)
            sync()

    @wp.kernel(module="unique", enable_backward=False)
    def solve_fixed(m: M, w: Work, sp: SP, extra: int):
        """Post-stabilisation's solve with the fixed rows' factor, 32 threads per world (``post_stabilisation.solve``
        on this schedule): ``lambda = P (P D_ff P + s I)^-1 x`` into ``x``; in the ``extra`` pass only where PADMM
        did not converge or ``reproject`` is set."""
        rs = w.row_stride
        wid, lane = wp.tid()
        if extra != 0 and w.converged[wid] != 0 and w.reproject[wid] == 0:
            return
        rb = bases(m, w, sp, wid)[0]
        nf = sp.n_fixed[wid]
        xs = wp.tile_zeros(shape=(R,), dtype=scalar, storage="shared")
        ys = wp.tile_zeros(shape=(R,), dtype=scalar, storage="shared")
        for a in range(lane, nf, LANES):
            sset(xs, a, w.x[rb + a * rs])
        sync()
        solve(m, w, sp, wid, nf, lane, xs, ys)
        for a in range(lane, nf, LANES):
            w.x[rb + a * rs] = w.P[rb + a * rs] * sget(xs, a)

    # --- Conjugate Residual (§8.2) ------------------------------------------------------------------------
    @wp.func
    def ent_slot(rb: int, rs: int, nblk: int, j: int) -> int:
        """Where entry ``j`` of a world's body-grouped row blocks (``Work.cr_ent``) is stored: in the slots of the
        world's row blocks (``w.row_body``'s layout), which hold as many."""
        return (rb + (j // nblk) * rs) * nblk + j % nblk

    @wp.kernel(module="unique", enable_backward=False)
    def cr_pattern(m: M, w: Work, nblk: int):
        """The world's row blocks grouped by body, in row order within a body (a counting sort, one thread per
        world, once per step after the rows are assembled): ``w.cr_ent`` lists the blocks' indices ``r nblk + k``
        body after body, ``w.cr_end[b]`` where body ``b``'s list ends (it starts where the previous body's ends, or
        at 0). :func:`cr_apply` sums a body's share of ``J^T`` from it in the order of ``solver.apply_operator``,
        with no atomics."""
        wid = wp.tid()
        rs = w.row_stride
        rb = row_base(m, w, wid)
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

    @wp.func
    def cr_apply(m: M, w: Work, wid: int, rb: int, n: int, nblk: int, lane: int, shift_f: scalar, shift_b: scalar,
                 shift_t: scalar, v: wp.array(dtype=scalar), out: wp.array(dtype=scalar)):
        """``out = (P J M^-1 J^T P + diag(P^2 R + eta + rho)) v`` matrix-free with the world's threads (§8.2;
        ``solver.apply_operator``, the same sums in the same order): the threads split the bodies for ``cr_w =
        M^-1 J^T P v`` (each body's row blocks from ``cr_pattern``'s lists), then the rows for ``J cr_w`` and the
        diagonal (``shift_f`` on the fixed rows, ``shift_b`` on the saturated ones, ``shift_t`` on the limit and
        contact rows). A barrier before each phase: every thread's rows of ``v``, then every body of ``cr_w``."""
        rs = w.row_stride
        b0 = m.body_start[wid]
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
            w.cr_w[b] = inv_mass_times(m, w, b, acc)
        sync()
        nf = m.row_fixed[wid]
        for a in range(lane, n, LANES):
            r = rb + a * rs
            s = zero
            for k in range(nblk):
                b = w.row_body[r * nblk + k]
                if b >= 0:
                    s += wp.dot(w.row_J[r * nblk + k], w.cr_w[b])
            Pa = w.P[r]
            shift = shift_t
            if a < nf:
                shift = wp.where(row_saturated(w, r) != 0, shift_b, shift_f)
            out[r] = Pa * s + (Pa * Pa * w.reg[r] + shift) * v[r]

    @wp.func
    def cr_solve(m: M, w: Work, wid: int, rb: int, n: int, nblk: int, lane: int, shift_f: scalar, shift_b: scalar,
                 shift_t: scalar, budget: int):
        """Conjugate Residual on ``A x = b`` (``b`` in ``y``) from ``x = x_p`` with the world's threads (§8.2;
        ``solver.cr_solve`` rule for rule: at most ``budget`` iterations, stopping early only when
        ``|r|^2 <= 1e-30 |b|^2`` or the recurrence breaks down, ``cr_r`` the residual on exit). Each thread updates
        its own rows of the vectors; the dot products are block sums, so every thread takes the same branch."""
        rs = w.row_stride
        for a in range(lane, n, LANES):
            r = rb + a * rs
            w.x[r] = w.x_p[r]
        cr_apply(m, w, wid, rb, n, nblk, lane, shift_f, shift_b, shift_t, w.x, w.cr_Ar)
        bb = zero
        for a in range(lane, n, LANES):
            r = rb + a * rs
            w.cr_r[r] = w.y[r] - w.cr_Ar[r]
            w.cr_p[r] = w.cr_r[r]
            bb += w.y[r] * w.y[r]
        bb = lane_sum(bb)
        cr_apply(m, w, wid, rb, n, nblk, lane, shift_f, shift_b, shift_t, w.cr_r, w.cr_Ar)
        zeta = zero
        for a in range(lane, n, LANES):
            r = rb + a * rs
            w.cr_Ap[r] = w.cr_Ar[r]
            zeta += w.cr_r[r] * w.cr_Ar[r]
        zeta = lane_sum(zeta)
        stop = scalar(1e-30) * bb
        for it in range(budget):
            rr = zero
            pp = zero
            for a in range(lane, n, LANES):
                r = rb + a * rs
                rr += w.cr_r[r] * w.cr_r[r]
                pp += w.cr_Ap[r] * w.cr_Ap[r]
            rr = lane_sum(rr)
            pp = lane_sum(pp)
            if rr <= stop or pp <= zero or zeta == zero:
                break
            alpha = zeta / pp
            for a in range(lane, n, LANES):
                r = rb + a * rs
                w.x[r] = w.x[r] + alpha * w.cr_p[r]
                w.cr_r[r] = w.cr_r[r] - alpha * w.cr_Ap[r]
            cr_apply(m, w, wid, rb, n, nblk, lane, shift_f, shift_b, shift_t, w.cr_r, w.cr_Ar)
            zeta_new = zero
            for a in range(lane, n, LANES):
                zeta_new += w.cr_r[rb + a * rs] * w.cr_Ar[rb + a * rs]
            zeta_new = lane_sum(zeta_new)
            beta = zeta_new / zeta
            zeta = zeta_new
            for a in range(lane, n, LANES):
                r = rb + a * rs
                w.cr_p[r] = w.cr_r[r] + beta * w.cr_p[r]
                w.cr_Ap[r] = w.cr_Ar[r] + beta * w.cr_Ap[r]

    # --- iterations ---------------------------------------------------------------------------------------
    @wp.func
    def row_penalty(w: Work, r: int, a: int, nf: int, rho_free: scalar, rho_box: scalar, rho_u: scalar):
        """Row ``a``'s penalty (``solver.row_penalty``)."""
        if a >= nf:
            return rho_u
        if row_saturated(w, r) != 0:
            return rho_box
        return rho_free

    @wp.kernel(module="unique", enable_backward=False,
               cuda_max_registers=ITERATE_MAX_REGISTERS if R >= REGISTER_CAP_MIN_ROWS else None)
    def padmm_iterate(m: M, w: Work, sp: SP, chunk: int, nblk: int, cr_budget: int, eta: scalar, rho_free: scalar,
                      rho_box: scalar, tol: scalar, restart_tol: scalar, accelerate: int, fixed: int, adaptive: int):
        """Up to ``chunk`` accelerated PADMM iterations of one world with its 32 threads (``solver.padmm_iterate``
        with the sparse factor, or with Conjugate Residual under ``cr`` (at most ``cr_budget`` iterations per
        solve), rule for rule: §7.3-§7.5, the penalty of the limit and contact rows, the null-direction test),
        resuming from the stored iterate; a world that converges (unless ``fixed``) or reaches its cap is marked
        done and leaves ``remaining``. Under ``cr`` the solution lands in ``w.x`` (the factor's solve: in
        ``xs``), CR's exit residual joins the dual residual, a new penalty refactorises nothing and a row that
        saturates takes ``rho_box`` in the next solve's operator without ending the launch."""
        rs = w.row_stride
        wid, lane = wp.tid()
        if w.done[wid] != 0:
            return
        rb = row_base(m, w, wid)
        n = w.n_rows[wid]
        n_box = w.n_box[wid]
        nc = (n - n_box) // 3
        nf = m.row_fixed[wid]
        p_ref = w.p_ref[wid]
        rho_u = w.rho_u[wid]
        if wp.static(not cr):
            xs = wp.tile_zeros(shape=(R,), dtype=scalar, storage="shared")
            ys = wp.tile_zeros(shape=(R,), dtype=scalar, storage="shared")
        for step in range(chunk):
            # steps 1-2: De Saxcé correction, right-hand side (into xs; CR's into y), linear solve
            for a in range(lane, n, LANES):
                r = rb + a * rs
                rho = row_penalty(w, r, a, nf, rho_free, rho_box, rho_u)
                rhs = -w.vt[r] + eta * w.x_p[r] + rho * w.y_hat[r] + w.z_hat[r]
                if a >= n_box and (a - n_box) % 3 == 2:
                    rhs -= de_saxce(w.z_hat[r - 2 * rs], w.z_hat[r - rs], row_mu(w, r - 2 * rs))
                if wp.static(cr):
                    w.y[r] = rhs
                else:
                    sset(xs, a, rhs)
            if wp.static(cr):
                cr_solve(m, w, wid, rb, n, nblk, lane, eta + rho_free, eta + rho_box, eta + rho_u, cr_budget)
            else:
                sync()
                solve(m, w, sp, wid, n, lane, xs, ys)
            # steps 3-4: projection, dual update and the residuals: box rows, then contact triples
            r_p = zero
            r_d = zero
            r_c = zero
            c_sum = zero
            r_tail = zero
            de = zero
            dx = zero
            hit = zero  # effort-limited rows inside their box whose projection clips them ("Saturation")
            for a in range(lane, n_box, LANES):
                r = rb + a * rs
                rho = row_penalty(w, r, a, nf, rho_free, rho_box, rho_u)
                x = zero
                if wp.static(cr):
                    x = w.x[r]
                else:
                    x = sget(xs, a)
                    w.x[r] = x
                z_hat = w.z_hat[r]
                lo = w.lo_s[r]
                hi = w.hi_s[r]
                v = x - z_hat / rho
                y = wp.clamp(v, lo, hi)
                w.y[r] = y
                if a < nf and saturates(row_saturated(w, r), lo, hi, v, y):
                    hit = scalar(1.0)
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
                a = n_box + 3 * c
                r = rb + a * rs
                x0 = zero
                x1 = zero
                x2 = zero
                if wp.static(cr):
                    x0 = w.x[r]
                    x1 = w.x[r + rs]
                    x2 = w.x[r + 2 * rs]
                else:
                    x0 = sget(xs, a)
                    x1 = sget(xs, a + 1)
                    x2 = sget(xs, a + 2)
                cp = cone_project(x0 - inv_rho * w.z_hat[r], x1 - inv_rho * w.z_hat[r + rs],
                                  x2 - inv_rho * w.z_hat[r + 2 * rs], row_mu(w, r))
                if wp.static(not cr):
                    w.x[r] = x0
                    w.x[r + rs] = x1
                    w.x[r + 2 * rs] = x2
                yz = zero
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
            if wp.static(cr):
                # the inner solve's residual b - A x, a scaled velocity like the dual residual's rows: an inexact
                # solve must not let the world report convergence (solver.padmm_iterate)
                for a in range(lane, n, LANES):
                    r = rb + a * rs
                    e_cr = residual_weight(w.P[r], p_ref) * wp.abs(w.cr_r[r])
                    r_d = wp.max(r_d, e_cr)
                    r_tail = wp.max(r_tail, e_cr)
            r_p = lane_max(r_p)
            r_d = lane_max(r_d)
            r_c = lane_max(r_c)
            c_sum = lane_sum(c_sum)
            r_tail = lane_max(r_tail)
            de = lane_max(de)
            dx = lane_max(dx)
            hit = lane_max(hit)
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
            # an effort-limited row that saturates: rho_box from now on, the momentum restarts, and the factor is
            # redone before the next iteration (w.pending: factor with pending_only after this launch)
            switch = adaptive != 0 and hit > zero and not converged
            if adaptive != 0 and n > nf and not converged:
                rho_n = balanced_penalty(rho_u, r_p, r_d, k, w.k_rho[wid])
                if rho_n != rho_u:
                    rho_u = rho_n
                    mode = RESTART_HERE
                    a_new = scalar(1.0)
                    c_new = big
                    sync()  # every thread has read k_rho (balanced_penalty) before it changes
                    if wp.static(not cr):
                        if not switch:
                            factor_tail(m, w, sp, wid, n, eta + rho_u, lane)
                    if lane == 0:
                        w.rho_u[wid] = rho_n
                        w.k_rho[wid] = k
            if switch:
                for a in range(lane, nf, LANES):  # this thread's own rows of the projection loop above
                    r = rb + a * rs
                    if saturates(row_saturated(w, r), w.lo_s[r], w.hi_s[r], w.x[r] - w.z_hat[r] / rho_free, w.y[r]):
                        set_saturated(w, r, 1)
                mode = RESTART_HERE
                a_new = scalar(1.0)
                c_new = big
            for a in range(lane, n, LANES):
                r = rb + a * rs
                y = w.y[r]
                z = w.z[r]
                if mode == RESTART_HERE:
                    w.y_hat[r] = y
                    w.z_hat[r] = z
                else:
                    w.y_hat[r] = extrapolated(y, w.y_p[r], beta, mode)
                    w.z_hat[r] = extrapolated(z, w.z_p[r], beta, mode)
                if wp.static(cr):
                    w.x_p[r] = w.x[r]
                else:
                    w.x_p[r] = sget(xs, a)
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
                if switch:
                    w.k_rho[wid] = k
                    if wp.static(not cr):  # CR has no factor to redo: the next solve's operator takes rho_box
                        w.pending[wid] = 1
                if done:
                    w.converged[wid] = int(converged)
                    w.done[wid] = 1
                    wp.atomic_sub(w.remaining, 0, 1)
            sync()
            if wp.static(cr):
                if done:
                    return
            elif done or switch:
                return

    return SimpleNamespace(factor=factor, factor_tail=factor_tail, solve=solve,
                           solve_fixed=solve_fixed, cr_pattern=cr_pattern,
                           padmm_iterate=padmm_iterate, R=R, E=E, cr=cr)
