"""Proximal-ADMM with one GPU warp (32 threads) per world on the sparse factor or with Conjugate Residual
(docs/formulation.md §7-§8.2; paper Alg. 1): the schedule for robot-sized worlds (``Stepper(padmm="warp")``).

One thread per world (``solver.padmm_iterate_kernel``) walks a world's factor and vectors alone: at 4096 worlds that
is one warp per multiprocessor, and every PADMM iteration of dr_legs is a chain of about 16,000 dependent loads. Here
the 32 threads of a block share one world and the chain is cut down to the rows:

- **Factorisation** (:func:`factor_kernel`, once per step). The fixed rows by columns ("fan-out"): for column ``q``,
  ``L_qq = sqrt(D~_qq)``, the column's entries ``L_pq = D~_pq / L_qq`` (threads over the entries), then every update
  ``D~_pr -= L_pq L_rq`` that column ``q`` feeds (threads over the precomputed triples, ``Symbolic.fan_*``: their
  targets are distinct, so no atomics). The tail rows (active limits and contacts): ``L_tf`` by a forward
  substitution per tail row (threads over tail rows), the Schur complement ``S_t`` (threads over all its entry
  pairs ``(t, j <= t)``) and its dense Cholesky by columns (:func:`factor_tail_func`). Same sums as
  ``linear_solve.factor``, in another order. ``L_f`` is stored once, in row order.
- **Solve** (:func:`solve_func`, every iteration). Column sweeps: the forward substitution of the fixed rows walks the
  columns of ``L_f`` (``x_q = b_q / L_qq``, then the column's entries update the rows below, threads over the
  entries; each entry's index in ``L_f``'s row order, ``cent``, is loaded two columns ahead, so that the value waits
  on no index load), the backward one walks its rows (``x_p``, then the entries of row ``p`` update the rows above);
  the tail's dense rows likewise, and the tail's share of the fixed rows is one parallel pass. One barrier per row;
  the right-hand side is updated in ``Work.y`` (free during the solve) and the solution lands in ``Work.x``. Where
  ``L_f^-1`` has at most ``linear_solve.INVERSE_MAX_FILL`` times ``L_f``'s entries, the factorisation ends with it
  (:func:`invert_func`, on ``linear_solve_pattern.inverse_pattern``) and the fixed rows' sweeps are two products
  with it, one barrier each.
  docs/warp_backend.md, "Where a PADMM iteration's time goes", has what each load ordering cost.
- **Iterations** (:func:`iterate_kernel`). Every rule of an iteration (right-hand side, projection, dual update,
  residuals, the penalty of the limit and contact rows, the null-direction test, momentum) is ``solver_rules.py``'s,
  as in the one-thread schedule; here the threads split the box rows and the contact triples and the world's maxima
  and sums are block reductions. Iteration counts equal the thread kernel's (``tests/test_warp_lane_padmm.py``).
- **Warm-start filter** (:func:`warm_start_filter_kernel`, once per step; docs/conventions.md "Warm start"): the
  filter's own factor of the fixed rows by :func:`factor_kernel` (launched with the fixed rows' count as the rows to
  factorise: no tail), then :func:`solve_func` on the shifted warm start and the clip, threads over rows.
- **Schur reduction** (``SolverConfig.reduction = "schur"``, docs/formulation.md §7.11; ``iterate_kernel(schur=True)``,
  :func:`schur_kernel`, :func:`schur_solve_kernel`). ``L_f`` becomes the elimination's factor: the fixed rows assembled
  with the shift ``eps = eta + rho_free`` (the reference's in either penalty mode), the effort-limited rows turned into
  identity rows of it (:func:`schur_decouple_kernel`: they belong to ``T``), and :func:`factor_kernel` on the fixed rows
  alone, so that ``L_f L_f^T = A + eps I`` on ``F`` (``A = P_F D_FF P_F``, the Jacobi scaling being the full ``D``'s on
  ``F``) with its hub unknowns. Once per step :func:`schur_kernel` lists ``T`` (effort-limited rows, then limit and
  contact rows), forms the scaled ``S~ = P_T S P_T = P_T D_TT P_T - B^T A^-1 B`` one column per thread (``B = P_F D_FT
  P_T``: its column ``b_c`` listed on the rows of ``F`` that share a body with row ``c``, through the bodies, ``J M^-1
  J^T``, so ``D_FT`` is never formed; the solve ``A^-1 b_c`` by the thread alone over ``L_f``, :func:`ff_solve_func`,
  with the reference's two refinement steps: ``L_f`` and the threads' vectors in shared memory where they fit, each
  row's entries loaded in batches; then its products with the lists) and ``P v'_T`` the same way, filters the
  effort-limited rows' warm start with ``S~``, and inverts ``S~ + diag(eta + rho)`` (:func:`schur_inverse_func`, in
  shared memory where it fits). An iteration's row passes then visit the rows of ``T`` alone, and its solve is one
  product with that inverse (:func:`schur_apply_func`: a barrier after the right-hand side, one after the product,
  instead of one per row of ``L_f``); a new penalty or a saturation recomputes the inverse inside the launch. After
  PADMM (and after the curvature refinement's new ``v_f``, ``v'_T`` again) ``lambda_F`` is recovered
  (:func:`schur_solve_kernel`: one vector's solve by the world's threads together, :func:`solve_func`'s sweeps).
  Iteration counts equal the JAX reference's (``tests/test_warp_lane_padmm.py``).
- **Conjugate Residual** (``iterate_kernel(cr=True)``: ``linear_solve_cr.cr_solve_func``, §8.2, instead of the factor).
  The operator ``P J M^-1 J^T P + diag(P^2 R + eta + rho)`` is applied matrix-free: the threads split the bodies for
  ``M^-1 J^T P v`` (each body's row blocks listed once per step by ``cr_pattern``, so that a body's sum needs no
  atomics and keeps the one-thread order), then the rows for ``J`` times it; CR's dot products are block sums.

Threads of a world meet at block barriers (``sync``); on the CPU the block runs as cooperative fibers
(``warp.config.enable_cpu_blocks``), which is how CI checks this kernel against the thread kernel.
"""

import functools
from types import SimpleNamespace

import numpy as np
import warp as wp

from kamino.config import SCHUR_REFINEMENT_STEPS
from kamino.warp_backend import solver_rules as rules
from kamino.warp_backend.indexing import index_funcs
from kamino.warp_backend.linear_solve import sparse_llt_kernels, vidx_func
from kamino.warp_backend.linear_solve_cr import cr_pattern_kernel, cr_solve_func
from kamino.warp_backend.solver_rules import LANES, sync
from kamino.warp_backend.types import types_of
from kamino.warp_backend.workspace import builder_types

#: Rounds of fan-out update triples (32 per round) whose indices a thread of :func:`factor_kernel` loads together.
FAN_BATCH = 4
FanIdx = wp.types.vector(length=FAN_BATCH, dtype=wp.int32)

#: The largest ``L_f`` (entries) that :func:`factor_kernel` factorises in shared memory; a larger one is factorised
#: in device memory (the animatronic's 43,000 entries would leave room for one world per multiprocessor).
STAGE_MAX_ENTRIES = 12288


def shared_rows(max_rows: int) -> int:
    """The length of the shared vectors for worlds of up to ``max_rows`` rows (a multiple of ``LANES``: one compiled
    module serves every size up to it)."""
    return LANES * max(1, -(-max_rows // LANES))


def shared_entries(max_nnz: int) -> int:
    """The entries of ``L_f`` that :func:`factor_kernel` stages in shared memory for factors of up to ``max_nnz``
    entries: ``max_nnz`` rounded up (so that similar scenes share a compiled module), or 0 above
    :data:`STAGE_MAX_ENTRIES`."""
    E = 256 * max(1, -(-max_nnz // 256))
    return E if E <= STAGE_MAX_ENTRIES else 0


#: Registers per thread of :func:`iterate_kernel`'s ``padmm_iterate`` for worlds of at least
#: :data:`REGISTER_CAP_MIN_ROWS` rows (CUDA ``__maxnreg__``). At 128 registers a multiprocessor holds 16 worlds
#: (65,536 registers / (128 x 32)) of the 32 blocks it could; at 72 it holds 28, at the cost of some spilling.
#: Measured on an H100 (benchmarks/README.md, the register cap): PPO's collection on dr_legs at 16384 worlds 137 -> 120
#: ms per step, the standing robots at 4096 worlds +1 %, the four-bar (117 rows) 12 % slower, hence the threshold.
ITERATE_MAX_REGISTERS: int | None = 72
REGISTER_CAP_MIN_ROWS = 200
#: Registers per thread of ``padmm_iterate`` for smaller worlds. Left to the compiler the kernel takes 124 on sm_90;
#: at 128 it spills nothing and runs the four-bar at 4096 worlds 0.4 % faster (H200: 3.52e6 world-steps/s against
#: 3.51e6, three interleaved runs each).
SMALL_WORLD_MAX_REGISTERS = 128


# --- shared memory ---------------------------------------------------------------------------------------------

@functools.cache
def shared_vector(np_dtype, length: int):
    """The type of a world's shared vector of ``length`` scalars.
    A ``wp.tile`` in shared memory, read and written entry by entry (:func:`shared_get_func`)."""
    return wp.tile(dtype=types_of(np_dtype).scalar, shape=(length,), storage="shared")


@functools.cache
def shared_set_func(np_dtype, length: int):
    """Write one entry of a :func:`shared_vector`.
    ``sset(t, i, v)``: the entry only, with no barrier of the block."""
    Vec = shared_vector(np_dtype, length)
    scalar = builder_types(np_dtype).scalar

    @wp.func_native("t.data(i) = v;")
    def sset(t: Vec, i: int, v: scalar):
        """``t[i] = v`` by one thread, no barrier (``t[i] = v`` on a tile synchronises the block)."""
        ...

    return sset


@functools.cache
def shared_get_func(np_dtype, length: int):
    """Read one entry of a :func:`shared_vector`.
    ``sget(t, i)``: the entry only, with no barrier of the block."""
    Vec = shared_vector(np_dtype, length)
    scalar = builder_types(np_dtype).scalar

    @wp.func_native("return t.data(i);")
    def sget(t: Vec, i: int) -> scalar:
        """``t[i]`` of a shared vector."""
        ...

    return sget


# --- factorisation (§8.1) --------------------------------------------------------------------------------------

@functools.cache
def staged_get_func(np_dtype, E: int):
    """Read an entry of the world's ``D~_f`` / ``L_f``, staged in shared memory (``E > 0`` entries) or in device
    memory."""
    scalar, SP = builder_types(np_dtype).take("scalar", "SP")
    LVec = shared_vector(np_dtype, max(E, 1))
    lget = shared_get_func(np_dtype, max(E, 1))

    @wp.func
    def fget(sp: SP, vb: int, k: int, lv: LVec) -> scalar:
        """Entry ``k`` (CSR order) of ``D~_f`` / ``L_f``."""
        if wp.static(E > 0):
            return lget(lv, k)
        return sp.val[vb + k * sp.val_stride]

    return fget


@functools.cache
def staged_set_func(np_dtype, E: int):
    """Write an entry of the world's ``L_f`` (staged, or in device memory: :func:`staged_get_func`).
    ``fset(sp, vb, k, v, lv)``, ``lv`` the staged copy (unused when ``E = 0``)."""
    scalar, SP = builder_types(np_dtype).take("scalar", "SP")
    LVec = shared_vector(np_dtype, max(E, 1))
    lset = shared_set_func(np_dtype, max(E, 1))

    @wp.func
    def fset(sp: SP, vb: int, k: int, v: scalar, lv: LVec):
        """Entry ``k`` (CSR order) of ``L_f`` := ``v``."""
        if wp.static(E > 0):
            lset(lv, k, v)
        else:
            sp.val[vb + k * sp.val_stride] = v

    return fset


@wp.func
def batch(a: wp.array(dtype=wp.int32), u: int, umax: int) -> FanIdx:
    """``a[u + r LANES]`` for the FAN_BATCH rounds ``r`` of a thread, loaded together (indices clamped to ``umax``)."""
    v = FanIdx()
    for r in range(FAN_BATCH):
        v[r] = a[wp.min(u + r * LANES, umax)]
    return v


@functools.cache
def fan_out_func(np_dtype, E: int):
    """The fan-out updates of a fixed column (``linear_solve.factor_fixed_rows``'s sums).
    ``fan_out(sp, vb, tv, av, bv, u, f1, lv, neg)``: a thread's FAN_BATCH rounds of update triples."""
    SP = builder_types(np_dtype).SP
    LVec = shared_vector(np_dtype, max(E, 1))
    fget, fset = staged_get_func(np_dtype, E), staged_set_func(np_dtype, E)

    @wp.func
    def fan_out(sp: SP, vb: int, tv: FanIdx, av: FanIdx, bv: FanIdx, u: int, f1: int, lv: LVec, neg: int):
        """The updates ``D~_tgt -= s_q L_a L_b`` of the thread's FAN_BATCH rounds from ``u`` that lie before ``f1``
        (``neg``: the column is a hub's unknown, ``s_q = -1``, ``linear_solve.factor_fixed_rows``)."""
        for r in range(FAN_BATCH):
            if u + r * LANES < f1:
                if neg != 0:
                    fset(sp, vb, tv[r], fget(sp, vb, tv[r], lv) + fget(sp, vb, av[r], lv) * fget(sp, vb, bv[r], lv),
                         lv)
                else:
                    fset(sp, vb, tv[r], fget(sp, vb, tv[r], lv) - fget(sp, vb, av[r], lv) * fget(sp, vb, bv[r], lv),
                         lv)

    return fan_out


@functools.cache
def ltf_batch_func(np_dtype, E: int):
    """A batch of the tail rows' ``L_tf`` updates (``linear_solve.factor_world``'s sums).
    ``ltf_batch(sp, vb, tr, tc, ub, u1, s, lv)``: FAN_BATCH update pairs of one entry of ``L_tf``."""
    scalar, SP = builder_types(np_dtype).take("scalar", "SP")
    LVec = shared_vector(np_dtype, max(E, 1))
    fget = staged_get_func(np_dtype, E)
    FanVal = wp.types.vector(length=FAN_BATCH, dtype=scalar)
    zero = scalar(0.0)

    @wp.func
    def ltf_batch(sp: SP, vb: int, tr: int, tc: int, ub: int, u1: int, s: scalar, lv: LVec) -> scalar:
        """``s - sum_u L_k(u) l_j(u)`` over the pattern's update pairs ``u = ub .. ub + FAN_BATCH - 1`` before ``u1``
        (``l``: the tail row at ``tr``; ``linear_solve.Pattern.pat_upd_*``): the FAN_BATCH pairs' indices, then their
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

    return ltf_batch


@functools.cache
def factor_tail_func(np_dtype):
    """The tail rows' dense Cholesky for a penalty (``kamino.jax_ref.solver.solve``, "Penalty").
    ``factor_tail(m, sp, row_stride, wid, n, shift, lane)``: by the world's threads (``factor_kernel`` and a new
    penalty in :func:`iterate_kernel`), into ``sp.tail``."""
    scalar, M, SP = builder_types(np_dtype).take("scalar", "M", "SP")
    bases = sparse_llt_kernels(np_dtype).bases
    tail_k = sparse_llt_kernels(np_dtype).tail_k
    sdiag_col = sparse_llt_kernels(np_dtype).sdiag_col
    tail_dot = rules.tail_dot_func(np_dtype)

    @wp.func
    def factor_tail(m: M, sp: SP, row_stride: int, wid: int, n: int, shift: scalar, lane: int):
        """``L_t = chol(S_t + shift I)`` by columns (left-looking: the entries of column ``j`` are independent dot
        products over the columns before it, :func:`solver_rules.tail_dot_func`), from ``S_t`` in the tail rows'
        upper slots (``S_t[t, j]`` at row ``j``, tail column ``K + t``) and its diagonal (column
        ``linear_solve.sdiag_col``); the sums of ``linear_solve.factor_tail``."""
        base = bases(m, sp, row_stride, wid)
        nt = n - sp.n_fixed[wid]
        kt = tail_k(sp, wid)
        col = sp.tail_stride  # the distance between a tail row's slots
        for j in range(nt):  # L_t[t, j] of the rows t >= j at tr (tail column kt + j), from row j at jr
            jr = base[2] + j * base[3]
            d = wp.sqrt(tail_dot(sp.tail, col, jr, jr, kt, j, sp.tail[jr + sdiag_col(sp, wid) * col] + shift))
            for t in range(j + 1 + lane, nt, LANES):
                tr = base[2] + t * base[3]
                sp.tail[tr + (kt + j) * col] = tail_dot(sp.tail, col, tr, jr, kt, j, sp.tail[jr + (kt + t) * col]) / d
            if lane == 0:
                sp.tail[jr + (kt + j) * col] = d
            sync()

    return factor_tail


@functools.cache
def invert_func(np_dtype, E: int):
    """``L_f^-1`` on its pattern (``linear_solve_pattern.InversePattern``) from the finished ``L_f``, by the world's
    threads: the forward substitutions ``L_f z_c = e_c`` of every column ``c`` at once, position by position.
    ``invert(sp, wid, vb, lv, lane)``; ``lv``: ``L_f`` staged in shared memory (``E > 0``) or unused."""
    scalar, SP = builder_types(np_dtype).take("scalar", "SP")
    LVec = shared_vector(np_dtype, max(E, 1))
    fget = staged_get_func(np_dtype, E)
    one = scalar(1.0)

    @wp.func
    def invert(sp: SP, wid: int, vb: int, lv: LVec, lane: int):
        """At position ``q`` every column ``c`` of the subtree of ``q`` (threads over them) has its entry ``z_qc``
        final: ``z_qc <- z_qc / L_qq``, then ``z_rc -= L_rq z_qc`` for the entries ``(r, q)`` of column ``q`` (all on
        the path of ``c``: slot ``slot(q, c) + cup``). One barrier per position; within a position each column is one
        thread's and the columns' slots are disjoint, so no two threads write one slot."""
        ib = sp.inv_start[wid]
        i0 = sp.inv_ent_start[wid]
        p0 = sp.ptr_start[wid]
        e0 = sp.ent_start[wid]
        npos = sp.n_pos[wid]
        for k in range(lane, sp.icol_ptr[p0 + npos], LANES):
            sp.inv[ib + k] = scalar(0.0)
        sync()
        for c in range(lane, npos, LANES):  # z_c = e_c: its first slot is its own row
            sp.inv[ib + sp.icol_ptr[p0 + c]] = one
        sync()
        for q in range(npos):
            dinv = one / fget(sp, vb, sp.row_ptr[p0 + q + 1] - 1, lv)
            c0 = sp.cptr[p0 + q]
            c1 = sp.cptr[p0 + q + 1]
            for k in range(sp.irow_ptr[p0 + q] + lane, sp.irow_ptr[p0 + q + 1], LANES):
                slot = ib + sp.irow_slot[i0 + k]
                z = sp.inv[slot] * dinv
                sp.inv[slot] = z
                for j in range(c0, c1):
                    sp.inv[slot + sp.cup[e0 + j]] -= fget(sp, vb, sp.cent[e0 + j], lv) * z
            sync()

    return invert


@functools.cache
def factor_kernel(np_dtype, E: int = 0, invert: bool = False):
    """Cholesky ``D~ = L L^T`` with the world's 32 threads (§8.1); with ``E > 0`` ``L_f`` staged in shared memory.
    ``factor(m, eta, pending_only, nblk, shift, shift_sat, row_stride, n_rows, row_body, row_J, row_info, ct_pair,
    reg, P, inertia_w, inv_inertia_w, rho_u, pending, sp)``, launched tiled: one block of ``LANES`` threads per
    world."""
    scalar, M, SP, vec6, mat33 = builder_types(np_dtype).take("scalar", "M", "SP", "vec6", "mat33")
    farr, iarr = wp.array(dtype=scalar), wp.array(dtype=wp.int32)
    bases = sparse_llt_kernels(np_dtype).bases
    schur_entry = sparse_llt_kernels(np_dtype).schur_entry
    fixed_entry = sparse_llt_kernels(np_dtype).fixed_entry
    tail_row = sparse_llt_kernels(np_dtype).tail_row
    tail_pattern = sparse_llt_kernels(np_dtype).tail_pattern
    EL = max(E, 1)  # staged length (1: not staged)
    lset, lget = shared_set_func(np_dtype, EL), shared_get_func(np_dtype, EL)
    fget, fset = staged_get_func(np_dtype, E), staged_set_func(np_dtype, E)
    fan_out = fan_out_func(np_dtype, E)
    ltf_batch = ltf_batch_func(np_dtype, E)
    factor_tail = factor_tail_func(np_dtype)
    invert_f = invert_func(np_dtype, E)
    zero = scalar(0.0)

    @wp.kernel(module="unique", enable_backward=False)
    def factor(
        # model (read only)
        m: M,
        # in
        eta: scalar, pending_only: int, nblk: int, shift: scalar, shift_sat: scalar,
        row_stride: int,
        n_rows: iarr, row_body: iarr, row_J: wp.array(dtype=vec6), row_info: iarr, ct_pair: iarr, reg: farr, P: farr,
        inertia_w: wp.array(dtype=mat33), inv_inertia_w: wp.array(dtype=mat33), rho_u: farr,
        # out
        pending: iarr,  # also read
        sp: SP,  # the factor values sp.val, sp.tail and sp.tail_pat (the pattern's index tables are read)
    ):
        """Cholesky ``D~ = L L^T`` in place (§8.1) with the world's 32 threads: the fixed rows by columns (fan-out
        updates), then the tail rows' ``L_tf``, their Schur complement and ``factor_tail`` with the world's
        penalty ``eta + rho_u``. With ``pending_only`` only the worlds whose effort-limited rows saturated in the
        last PADMM iteration (``pending``), which first assemble ``D~`` again with the shifts ``shift`` /
        ``shift_sat`` (``linear_solve.refactor``; kamino.jax_ref.solver.solve, "Saturation"). ``n_rows`` counts the
        rows factorised: with the fixed rows' count ``m.row_fixed``, on a factor built without tail rows (the
        warm-start filter's), it factorises ``L_f`` alone (the tail steps have no rows; ``rho_u`` plays no part)."""
        wid, lane = wp.tid()
        if pending_only != 0:
            if pending[wid] == 0:
                return
            for k in range(lane, sp.nnz[wid], LANES):
                fixed_entry(m, sp, row_stride, row_body, row_J, row_info, reg, P, inertia_w, inv_inertia_w, wid, k,
                            nblk, shift, shift_sat)
            for a in range(sp.n_fixed[wid] + lane, n_rows[wid], LANES):
                tail_row(m, sp, row_stride, row_body, row_J, row_info, ct_pair, reg, P, inv_inertia_w, wid, a, nblk)
            sync()
        base = bases(m, sp, row_stride, wid)
        rb, vb, tb, ts = base[0], base[1], base[2], base[3]
        tc = sp.tail_stride
        nf = sp.n_fixed[wid]
        npos = sp.n_pos[wid]  # the fixed rows, then the hubs' unknowns (sign s_q = -1: linear_solve.factor_fixed_rows)
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
        if wp.static(invert):
            invert_f(sp, wid, vb, lv, lane)
        if wp.static(E > 0):
            for k in range(lane, nnz, LANES):
                sp.val[vb + k * sp.val_stride] = lget(lv, k)
        sync()
        n = n_rows[wid]
        nt = n - nf
        for t in range(lane, nt, LANES):  # L_tf: row t solves L_f l = D~_ft over its pattern (each thread its rows)
            tr = tb + t * ts
            pt = tail_pattern(sp, wid, t)
            i0 = sp.pat_ptr[pt]
            for i in range(sp.pat_ptr[pt + 1] - i0):
                s = sp.tail[tr + i * tc]
                u1 = sp.pat_upd_ptr[i0 + i + 1]
                pos = sp.pat_pos[i0 + i]
                if pos >= nf:  # a hub position: the signed sum and divisor of linear_solve.factor_world
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
            schur_entry(sp, wid, rb, tb, ts, nf, t, j)
            j += LANES
            while j > t:
                j -= t + 1
                t += 1
        sync()
        factor_tail(m, sp, row_stride, wid, n, eta + rho_u[wid], lane)
        if pending_only != 0 and lane == 0:
            pending[wid] = 0

    return factor


# --- solve (§8.1) ------------------------------------------------------------------------------------------------

@functools.cache
def solve_func(np_dtype, R: int, inverse: bool = False):
    """The solve with the sparse factor and its tail by the world's threads (§8.1).
    ``solve(m, sp, row_stride, wid, n, lane, xs, ys)``, the vectors in shared memory (:func:`shared_vector` of
    ``R``). With ``inverse`` the fixed rows' sweeps are products with ``L_f^-1`` (:func:`invert_func`): threads
    over its rows forward, over its columns backward, one barrier each."""
    scalar, M, SP = builder_types(np_dtype).take("scalar", "M", "SP")
    Vec = shared_vector(np_dtype, R)
    sset, sget = shared_set_func(np_dtype, R), shared_get_func(np_dtype, R)
    bases = sparse_llt_kernels(np_dtype).bases
    tail_k = sparse_llt_kernels(np_dtype).tail_k
    tail_pattern = sparse_llt_kernels(np_dtype).tail_pattern
    zero = scalar(0.0)

    @wp.func
    def solve(m: M, sp: SP, row_stride: int, wid: int, n: int, lane: int, xs: Vec, ys: Vec):
        """``x <- L^-T L^-1 x`` with ``L_tf`` on its patterns and ``L_t`` dense, by column sweeps: one barrier per
        row (``linear_solve.solve_inplace``, the same products in another order; with hubs ``x <- L^-T S L^-1 x``, the
        hubs' unknowns in their virtual rows of ``xs`` / ``ys``). ``xs`` holds the right-hand side on entry and the
        solution on exit, ``ys`` is scratch: both in shared memory, indexed by row. The next column's (row's) factor
        entries are loaded before the barrier of the current one, unconditionally (clamped indices), so that their
        latency overlaps the barrier instead of preceding it (docs/warp_backend.md, "Where it goes, measured part by
        part")."""
        base = bases(m, sp, row_stride, wid)
        vb, tb, ts = base[1], base[2], base[3]
        tc = sp.tail_stride
        nf = sp.n_fixed[wid]
        e0 = sp.ent_start[wid]
        p0 = sp.ptr_start[wid]
        q0 = sp.perm_start[wid]
        nt = n - nf
        npos = sp.n_pos[wid]  # the fixed rows, then the hubs' unknowns (linear_solve.solve_inplace: x <- L^-T S L^-1 x)
        if npos > nf:  # the hubs' right-hand side: 0 in their virtual rows
            for p in range(nf + lane, npos, LANES):
                sset(xs, sp.perm[q0 + p], zero)
            sync()
        if wp.static(inverse):  # forward, fixed rows: y = L_f^-1 x, row r over the subtree of r
            ib = sp.inv_start[wid]
            iv0 = sp.inv_ent_start[wid]
            for p in range(lane, npos, LANES):
                s = zero
                for k in range(sp.irow_ptr[p0 + p], sp.irow_ptr[p0 + p + 1]):
                    s += sp.inv[ib + sp.irow_slot[iv0 + k]] * sget(xs, sp.irow_col[iv0 + k])
                sset(ys, sp.perm[q0 + p], s)
            sync()
        if wp.static(not inverse):
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
        if wp.static(inverse):  # backward, fixed rows: x = L_f^-T y, column c over the path of c
            for c in range(lane, npos, LANES):
                s = zero
                for k in range(sp.icol_ptr[p0 + c], sp.icol_ptr[p0 + c + 1]):
                    s += sp.inv[ib + k] * sget(ys, sp.ipath_row[iv0 + k])
                sset(xs, sp.perm[q0 + c], s)
            sync()
        if wp.static(not inverse):
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

    return solve


@functools.cache
def solve_fixed_kernel(np_dtype, R: int):
    """Post-stabilisation's solve with the fixed rows' factor, 32 threads per world.
    ``solve_fixed(m, extra, row_stride, sp, converged, reproject, P, x)``, launched tiled: one block of ``LANES``
    threads per world."""
    scalar, M, SP = builder_types(np_dtype).take("scalar", "M", "SP")
    farr, iarr = wp.array(dtype=scalar), wp.array(dtype=wp.int32)
    sset, sget = shared_set_func(np_dtype, R), shared_get_func(np_dtype, R)
    bases = sparse_llt_kernels(np_dtype).bases
    solve = solve_func(np_dtype, R)

    @wp.kernel(module="unique", enable_backward=False)
    def solve_fixed(
        # model (read only)
        m: M,
        # in
        extra: int,
        row_stride: int,
        sp: SP,  # the fixed rows' sparse factor (tables and values, read)
        converged: iarr, reproject: iarr, P: farr,
        # out
        x: farr,  # also read
    ):
        """``post_stabilisation.solve`` on this schedule: ``lambda = P (P D_ff P + s I)^-1 x`` into ``x``; in the
        ``extra`` pass only where PADMM did not converge or ``reproject`` is set."""
        rs = row_stride
        wid, lane = wp.tid()
        if extra != 0 and converged[wid] != 0 and reproject[wid] == 0:
            return
        rb = bases(m, sp, row_stride, wid)[0]
        nf = sp.n_fixed[wid]
        xs = wp.tile_zeros(shape=(R,), dtype=scalar, storage="shared")
        ys = wp.tile_zeros(shape=(R,), dtype=scalar, storage="shared")
        for a in range(lane, nf, LANES):
            sset(xs, a, x[rb + a * rs])
        sync()
        solve(m, sp, row_stride, wid, nf, lane, xs, ys)
        for a in range(lane, nf, LANES):
            x[rb + a * rs] = P[rb + a * rs] * sget(xs, a)

    return solve_fixed


@functools.cache
def warm_start_filter_kernel(np_dtype, R: int):
    """The warm-start filter with the world's 32 threads (``solver.warm_start_filter_kernel`` on this schedule;
    ``kamino.jax_ref.solver._Problem.filter_warm_start``, docs/conventions.md "Warm start").
    ``warm_start_filter(m, shift, row_stride, sp, frozen, lo_s, hi_s, x, x_p, y_p, y_hat)``, launched tiled: one block
    of ``LANES`` threads per world; ``sp`` holds the factor of ``P D_ff P + shift I`` (:func:`factor_kernel` on a
    factor built without tail rows), the vectors in shared memory (:func:`shared_vector` of ``R``)."""
    scalar, M, SP = builder_types(np_dtype).take("scalar", "M", "SP")
    farr, iarr = wp.array(dtype=scalar), wp.array(dtype=wp.int32)
    sset, sget = shared_set_func(np_dtype, R), shared_get_func(np_dtype, R)
    bases = sparse_llt_kernels(np_dtype).bases
    solve = solve_func(np_dtype, R)
    lane_max = rules.lane_reduce_func(np_dtype, LANES, "max")

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
        x: farr,  # equal to x_p on the fixed rows on entry and on exit
        x_p: farr, y_p: farr, y_hat: farr,  # the warm start (padmm_init), also read
    ):
        """``x_f <- clip(x_f - (P D_ff P + s I)^-1 s x_f)`` on the fixed rows of the warm start ``x_p``, copied to
        ``y_p``, ``y_hat`` and ``x``: the threads split the rows, the solve is :func:`solve_func`'s column sweeps; a
        world whose result is not finite (a block reduction) keeps its warm start."""
        rs = row_stride
        wid, lane = wp.tid()
        if frozen[wid] != 0:
            return
        rb = bases(m, sp, row_stride, wid)[0]
        nf = sp.n_fixed[wid]
        xs = wp.tile_zeros(shape=(R,), dtype=scalar, storage="shared")
        ys = wp.tile_zeros(shape=(R,), dtype=scalar, storage="shared")
        for a in range(lane, nf, LANES):
            sset(xs, a, shift * x_p[rb + a * rs])
        sync()
        solve(m, sp, row_stride, wid, nf, lane, xs, ys)
        bad = scalar(0.0)
        for a in range(lane, nf, LANES):
            r = rb + a * rs
            if not wp.isfinite(wp.clamp(x_p[r] - sget(xs, a), lo_s[r], hi_s[r])):
                bad = scalar(1.0)
        if lane_max(bad) == scalar(0.0):
            for a in range(lane, nf, LANES):
                r = rb + a * rs
                v = wp.clamp(x_p[r] - sget(xs, a), lo_s[r], hi_s[r])
                x_p[r] = v
                y_p[r] = v
                y_hat[r] = v
                x[r] = v

    return warm_start_filter


# --- the Schur reduction (§7.11; SolverConfig.reduction = "schur") -------------------------------------------------

@functools.cache
def schur_struct(np_dtype):
    """``Schur``: a world's reduced problem (docs/formulation.md §7.11) on the 32-thread schedule. Per world the rows
    ``T`` that PADMM solves (``rows``, ascending: the effort-limited fixed rows, then the limit and contact rows),
    the scaled ``S~ = P_T S P_T`` (``S``) and the factor of ``S~ + diag(eta + rho)`` (``L``), ``tm x tm`` row after
    row, and its inverse (``G``) column after column; the reduced right-hand side ``P v'_T`` in the row layout
    (``vt``, zero on ``F``); the elimination's right-hand sides ``b_c = P_F D_Fc P_c`` of the rows ``c`` of ``T`` as
    lists of their entries on the rows of ``F`` that share a body with row ``c`` (``bp`` positions, ``bv`` values,
    ``bn`` lengths; up to ``cap`` each); and the scratch of the elimination's solves, per thread (``sb``, ``sx``:
    ``np_max`` fixed positions; ``su``: ``nb_max`` bodies)."""
    T = builder_types(np_dtype)
    farr, iarr = wp.array(dtype=T.scalar), wp.array(dtype=wp.int32)

    @wp.struct
    class Schur:
        tm: int  # the reduced rows' capacity of a world
        np_max: int  # fixed positions (fixed rows and hub unknowns) of the largest world
        nb_max: int  # bodies of the largest world
        cap: int  # entries of a right-hand side's list
        eps: T.scalar  # the elimination's shift eta + rho_free
        filter_shift: T.scalar  # the warm-start filter's shift (0: no filter)
        rows: iarr  # [W tm]
        nt: iarr  # [W] the rows of T
        ne: iarr  # [W] its effort-limited fixed rows (the first ne)
        S: farr  # [W tm tm]
        L: farr
        G: farr
        vt: farr  # per row
        bp: iarr  # [W tm cap]
        bv: farr
        bn: iarr  # [W tm]
        sb: farr  # [W LANES np_max]
        sx: farr
        su: wp.array(dtype=T.vec6)  # [W LANES nb_max]

    return Schur


@functools.cache
def free_row_func(np_dtype):
    """Whether a fixed row belongs to ``F`` (§7.11).
    ``free_row(lo_s, hi_s, r)``."""
    scalar = builder_types(np_dtype).scalar
    farr = wp.array(dtype=scalar)

    @wp.func
    def free_row(lo_s: farr, hi_s: farr, r: int) -> bool:
        """A fixed row (``a < n_fixed``) is in ``F`` when both its bounds are infinite; an effort-limited one is not
        (``kamino.jax_ref.reduction.unbounded_rows``)."""
        return not (wp.isfinite(lo_s[r]) or wp.isfinite(hi_s[r]))

    return free_row


@functools.cache
def schur_decouple_kernel(np_dtype):
    """The fixed rows' block of the elimination (§7.11).
    ``schur_decouple(m, nblk, shift, shift_sat, row_stride, row_body, row_J, row_info, reg, P, inertia_w,
    inv_inertia_w, lo_s, hi_s, sp)``, on ``(worlds, max entries)``."""
    scalar, M, SP, vec6, mat33 = builder_types(np_dtype).take("scalar", "M", "SP", "vec6", "mat33")
    farr, iarr = wp.array(dtype=scalar), wp.array(dtype=wp.int32)
    row_base = index_funcs(np_dtype).row_base
    vidx = vidx_func(np_dtype)
    free_row = free_row_func(np_dtype)
    fixed_entry = sparse_llt_kernels(np_dtype).fixed_entry

    @wp.kernel(module="unique", enable_backward=False)
    def schur_decouple(m: M, nblk: int, shift: scalar, shift_sat: scalar, row_stride: int, row_body: iarr,
                       row_J: wp.array(dtype=vec6), row_info: iarr, reg: farr, P: farr,
                       inertia_w: wp.array(dtype=mat33), inv_inertia_w: wp.array(dtype=mat33), lo_s: farr,
                       hi_s: farr, sp: SP):
        """Entry ``k`` of ``D~_f`` (``linear_solve.assemble_fixed``'s, with the shift ``eps``), and on a row or
        column of an effort-limited row (a row of ``T``) the identity's entry instead, so that :func:`factor_kernel`
        factorises ``A + eps I`` on ``F`` (the Jacobi-scaled ``D_FF``, with its hub unknowns) and the identity on
        the effort-limited rows, on ``L_f``'s pattern."""
        wid, k = wp.tid()
        if k >= sp.nnz[wid]:
            return
        fixed_entry(m, sp, row_stride, row_body, row_J, row_info, reg, P, inertia_w, inv_inertia_w, wid, k, nblk,
                    shift, shift_sat)
        nf = sp.n_fixed[wid]
        e = sp.ent_start[wid] + k
        p = sp.row[e]
        q = sp.col[e]
        rb = row_base(m, row_stride, wid)
        q0 = sp.perm_start[wid]
        bounded = False
        if p < nf:
            bounded = not free_row(lo_s, hi_s, rb + sp.perm[q0 + p] * row_stride)
        if q < nf:
            bounded = bounded or not free_row(lo_s, hi_s, rb + sp.perm[q0 + q] * row_stride)
        if bounded:
            v = scalar(0.0)
            if p == q:
                v = scalar(1.0)
            sp.val[vidx(m, sp, wid, k)] = v

    return schur_decouple


#: Entries of a row of ``L_f`` whose indices, values and vector entries a thread of the elimination's sweeps
#: (:func:`lane_solve_func`) loads together.
SWEEP_BATCH = 8
SweepIdx = wp.types.vector(length=SWEEP_BATCH, dtype=wp.int32)

def schur_list_cap(row_bodies, blocks_per_row: int, np_max: int) -> int:
    """The entries of a right-hand side's list (``Schur.bp``, :func:`schur_kernel`): a row of ``T`` has up to
    ``blocks_per_row`` bodies, each on at most as many fixed rows as the busiest body of a world type (``row_bodies``:
    ``linear_solve_pattern.FixedRowTypes.rows``, each fixed row's moving bodies), and no more than ``np_max``."""
    busiest = 0
    for rows in row_bodies:
        if len(rows):  # a body counts once per row
            b = np.asarray(rows, np.int64).reshape(len(rows), -1)
            counts = np.bincount(np.concatenate([np.unique(r[r >= 0]) for r in b]))
            busiest = max(busiest, int(counts.max(initial=0)))
    return max(1, min(np_max, blocks_per_row * busiest))


@functools.cache
def lane_solve_func(np_dtype):
    """``x <- C^-1 x`` with the fixed rows' factor ``C = L_f L_f^T`` by one thread (§8.1).
    ``lane_solve(sp, wid, vb, sx, xi)``: ``L_f`` in device memory (``sp.val``), the thread's vector in ``sx``, entry
    ``p`` at ``xi + p LANES`` (the world's threads' vectors interleaved). Both stay in device memory: staged in
    shared memory, they cut the multiprocessor's resident worlds and the elimination took 1.6x as long (dr_legs,
    benchmarks/README.md)."""
    scalar, SP = builder_types(np_dtype).take("scalar", "SP")
    farr = wp.array(dtype=scalar)
    SweepVal = wp.types.vector(length=SWEEP_BATCH, dtype=scalar)
    zero = scalar(0.0)

    @wp.func
    def forward_batch(sp: SP, e0: int, vb: int, kb: int, k1: int, sx: farr, xi: int, s: scalar) -> scalar:
        """``s - sum_k L_k x_col(k)`` over the ``SWEEP_BATCH`` entries ``k`` of a row from ``kb`` that lie before its
        diagonal ``k1``, subtracted in the entries' order: the batch's column indices, then its values and vector
        entries, each loaded together (indices clamped to the row, the surplus values zero), so that the batch waits
        on two load latencies instead of two per entry."""
        cv = SweepIdx()
        for r in range(SWEEP_BATCH):
            cv[r] = sp.col[e0 + wp.min(kb + r, k1 - 1)]
        lvv = SweepVal()
        xvv = SweepVal()
        for r in range(SWEEP_BATCH):
            lvv[r] = wp.where(kb + r < k1, sp.val[vb + wp.min(kb + r, k1 - 1) * sp.val_stride], zero)
            xvv[r] = sx[xi + cv[r] * LANES]
        for r in range(SWEEP_BATCH):
            s -= lvv[r] * xvv[r]
        return s

    @wp.func
    def backward_batch(sp: SP, e0: int, vb: int, kb: int, k1: int, sx: farr, xi: int, xp: scalar):
        """``x_col(k) -= L_k x_p`` over the ``SWEEP_BATCH`` entries ``k`` of row ``p`` from ``kb`` that lie before its
        diagonal ``k1``, loaded together as in ``forward_batch`` (a row's columns are distinct, so its entries' updates
        are independent)."""
        cv = SweepIdx()
        for r in range(SWEEP_BATCH):
            cv[r] = sp.col[e0 + wp.min(kb + r, k1 - 1)]
        lvv = SweepVal()
        xvv = SweepVal()
        for r in range(SWEEP_BATCH):
            lvv[r] = sp.val[vb + wp.min(kb + r, k1 - 1) * sp.val_stride]
            xvv[r] = sx[xi + cv[r] * LANES]
        for r in range(SWEEP_BATCH):
            if kb + r < k1:
                sx[xi + cv[r] * LANES] = xvv[r] - lvv[r] * xp

    @wp.func
    def lane_solve(sp: SP, wid: int, vb: int, sx: farr, xi: int):
        """The forward and the backward substitution of ``linear_solve.solve_inplace`` on the fixed positions
        alone, by the calling thread, row by row in batches of ``SWEEP_BATCH`` entries: with hubs the right-hand side
        of their unknowns is 0 and ``y`` is negated there between the sweeps. The threads of a world each solve their
        own vector: no barrier; they walk the same pattern together, so their loads of ``L_f`` are one broadcast and
        those of their vectors one coalesced access."""
        npos = sp.n_pos[wid]
        nf = sp.n_fixed[wid]
        e0 = sp.ent_start[wid]
        p0 = sp.ptr_start[wid]
        # row p's entries are row_ptr[p] .. row_ptr[p + 1] - 1 (the diagonal last): each row's bound is the next's
        # other bound, and the one after is loaded a row ahead
        lo = sp.row_ptr[p0]
        hi = sp.row_ptr[p0 + wp.min(1, npos)]
        for p in range(npos):
            k0 = lo
            k1 = hi - 1
            lo = hi
            hi = sp.row_ptr[p0 + wp.min(p + 2, npos)]
            s = sx[xi + p * LANES]
            for kb in range(k0, k1, SWEEP_BATCH):
                s = forward_batch(sp, e0, vb, kb, k1, sx, xi, s)
            sx[xi + p * LANES] = s / sp.val[vb + k1 * sp.val_stride]
        for p in range(nf, npos):
            sx[xi + p * LANES] = -sx[xi + p * LANES]
        hi = sp.row_ptr[p0 + npos]
        lo = sp.row_ptr[p0 + wp.max(npos - 1, 0)]
        for pp in range(npos):
            p = npos - 1 - pp
            k0 = lo
            k1 = hi - 1
            hi = lo
            lo = sp.row_ptr[p0 + wp.max(p - 1, 0)]
            xp = sx[xi + p * LANES] / sp.val[vb + k1 * sp.val_stride]
            sx[xi + p * LANES] = xp
            for kb in range(k0, k1, SWEEP_BATCH):
                backward_batch(sp, e0, vb, kb, k1, sx, xi, xp)

    return lane_solve


@functools.cache
def ff_solve_func(np_dtype):
    """``A^-1 b`` on ``F`` with ``SCHUR_REFINEMENT_STEPS`` refinement steps by one thread (§7.11).
    ``ff_solve(sp, wid, vb, sb, sx, xi, eps)`` (:func:`lane_solve_func`)."""
    scalar, SP = builder_types(np_dtype).take("scalar", "SP")
    farr = wp.array(dtype=scalar)
    lane_solve = lane_solve_func(np_dtype)
    zero = scalar(0.0)

    @wp.func
    def ff_solve(sp: SP, wid: int, vb: int, sb: farr, sx: farr, xi: int, eps: scalar):
        """``x = A^-1 b`` (``b``: ``sb`` from ``xi``, zero off ``F``; ``x``: the thread's vector in ``sx``) with the
        factor ``C = A + eps I`` and the refinement of ``kamino.jax_ref.reduction.ff_solve``, ``x_{k+1} = x_k + C^-1
        (b - A x_k)``, written as ``x_{k+1} = C^-1 (b + eps x_k)`` (the same vector: ``A = C - eps I``), which needs no
        product with ``A``: ``x_0 = C^-1 b`` and ``SCHUR_REFINEMENT_STEPS`` more solves. The effort-limited rows'
        identity block keeps them at zero; the hubs' unknowns take a zero right-hand side in every solve."""
        npos = sp.n_pos[wid]
        nf = sp.n_fixed[wid]
        for p in range(npos):
            sx[xi + p * LANES] = sb[xi + p * LANES]
        lane_solve(sp, wid, vb, sx, xi)
        for _ in range(SCHUR_REFINEMENT_STEPS):
            for p in range(nf):
                sx[xi + p * LANES] = sb[xi + p * LANES] + eps * sx[xi + p * LANES]
            for p in range(nf, npos):
                sx[xi + p * LANES] = zero
            lane_solve(sp, wid, vb, sx, xi)

    return ff_solve


@functools.cache
def body_funcs(np_dtype):
    """A thread's body-space vector (``J^T`` of row values, ``M^-1`` of it, ``J`` of it) for the elimination's
    products with ``D = J M^-1 J^T + R`` (§7.1) without assembling ``D_FT``. ``SimpleNamespace(add_row, row_dot,
    row_u, row_dot_on, shares_body)``."""
    scalar, M, vec6, mat33 = builder_types(np_dtype).take("scalar", "M", "vec6", "mat33")
    iarr = wp.array(dtype=wp.int32)
    inv_mass_times = sparse_llt_kernels(np_dtype).inv_mass_times

    @wp.func
    def add_row(su: wp.array(dtype=vec6), ub: int, b0: int, row_body: iarr, row_J: wp.array(dtype=vec6), r: int,
                nblk: int, c: scalar):
        """``u += J_r^T c``: row ``r``'s blocks times ``c`` onto its bodies (``su[ub + (body - b0) LANES]``: the
        world's threads' vectors interleaved)."""
        for k in range(nblk):
            bk = row_body[r * nblk + k]
            if bk >= 0:
                su[ub + (bk - b0) * LANES] = su[ub + (bk - b0) * LANES] + c * row_J[r * nblk + k]

    @wp.func
    def row_dot(su: wp.array(dtype=vec6), ub: int, b0: int, row_body: iarr, row_J: wp.array(dtype=vec6), r: int,
                nblk: int) -> scalar:
        """``J_r u``."""
        s = scalar(0.0)
        for k in range(nblk):
            bk = row_body[r * nblk + k]
            if bk >= 0:
                s += wp.dot(row_J[r * nblk + k], su[ub + (bk - b0) * LANES])
        return s

    @wp.func
    def row_u(m: M, inv_inertia_w: wp.array(dtype=mat33), su: wp.array(dtype=vec6), ub: int, b0: int, row_body: iarr,
              row_J: wp.array(dtype=vec6), rc: int, nblk: int, c: scalar):
        """``u = M^-1 J_rc^T c`` on row ``rc``'s own bodies (zero, then ``add_row``, then ``M^-1`` once per body):
        its other bodies' entries of ``u`` are zero and not written, since :func:`row_dot_on` does not read them."""
        for k in range(nblk):
            bk = row_body[rc * nblk + k]
            if bk >= 0:
                su[ub + (bk - b0) * LANES] = vec6()
        add_row(su, ub, b0, row_body, row_J, rc, nblk, c)
        for k in range(nblk):
            bk = row_body[rc * nblk + k]
            first = int(bk >= 0)
            for l in range(k):
                if row_body[rc * nblk + l] == bk:
                    first = 0
            if first != 0:
                su[ub + (bk - b0) * LANES] = inv_mass_times(m, inv_inertia_w, bk, su[ub + (bk - b0) * LANES])

    @wp.func
    def shares_body(row_body: iarr, r: int, rc: int, nblk: int) -> int:
        """Whether row ``r`` has a body of row ``rc`` (1) or not (0)."""
        hit = int(0)
        for k in range(nblk):
            bk = row_body[r * nblk + k]
            if bk >= 0:
                for l in range(nblk):
                    if row_body[rc * nblk + l] == bk:
                        hit = 1
        return hit

    @wp.func
    def row_dot_on(su: wp.array(dtype=vec6), ub: int, b0: int, row_body: iarr, row_J: wp.array(dtype=vec6), r: int,
                   rc: int, nblk: int) -> scalar:
        """``J_r u`` for ``u`` of :func:`row_u` (nonzero on row ``rc``'s bodies alone): ``row_dot`` without the
        blocks of ``r`` on other bodies, whose terms are zeros (the same sum), so that a row sharing no body with
        ``rc`` reads no entry of ``u``."""
        s = scalar(0.0)
        for k in range(nblk):
            bk = row_body[r * nblk + k]
            shared = int(0)
            if bk >= 0:
                for l in range(nblk):
                    if row_body[rc * nblk + l] == bk:
                        shared = 1
            if shared != 0:
                s += wp.dot(row_J[r * nblk + k], su[ub + (bk - b0) * LANES])
        return s

    return SimpleNamespace(add_row=add_row, row_dot=row_dot, row_u=row_u, row_dot_on=row_dot_on,
                           shares_body=shares_body)


@functools.cache
def schur_inverse_func(np_dtype):
    """``G = (S~ + diag(eta + rho))^-1`` of a world's reduced problem by its threads (§7.11).
    ``schur_inverse(sch, wid, lane, row_info, rb, rs, nf, eta, rho_free, rho_box, rho_u)``, the factor in ``sch.L``
    and the inverse in ``sch.G`` (device memory: formed in shared memory, they cut the multiprocessor's resident
    worlds and the elimination took longer, benchmarks/README.md)."""
    scalar = builder_types(np_dtype).scalar
    Schur = schur_struct(np_dtype)
    row_penalty = rules.row_penalty_func(np_dtype)

    @wp.func
    def schur_inverse(sch: Schur, wid: int, lane: int, row_info: wp.array(dtype=wp.int32), rb: int, rs: int, nf: int,
                      eta: scalar, rho_free: scalar, rho_box: scalar, rho_u: scalar):
        """The Cholesky factor ``L`` of ``S~ + diag(eta + rho_i)`` (each row's penalty, ``solver_rules.row_penalty``:
        a saturated effort-limited row's ``rho_box``) by columns (threads over the rows below the diagonal, one
        barrier per column; ``S~`` is symmetric, so they read its column ``j`` as row ``j``: consecutive entries),
        then ``G``'s columns, ``L L^T g_c = e_c``, one thread per column (no barrier), each stored contiguously
        (``G_ic`` at ``c tm + i``: in the product with ``G`` the threads, one per row ``i``, read consecutive
        entries): every PADMM iteration's solve is then one product with ``G`` (:func:`schur_apply_func`). ``L_ik``
        at ``g0 + i tm + k``."""
        nt = sch.nt[wid]
        tm = sch.tm
        g0 = wid * tm * tm
        t0 = wid * tm
        for j in range(nt):
            aj = sch.rows[t0 + j]
            s = sch.S[g0 + j * tm + j] + eta + row_penalty(row_info, rb + aj * rs, aj, nf, rho_free, rho_box, rho_u)
            for k in range(j):
                s -= sch.L[g0 + j * tm + k] * sch.L[g0 + j * tm + k]
            d = wp.sqrt(s)
            for i in range(j + 1 + lane, nt, LANES):
                v = sch.S[g0 + j * tm + i]
                for k in range(j):
                    v -= sch.L[g0 + i * tm + k] * sch.L[g0 + j * tm + k]
                sch.L[g0 + i * tm + j] = v / d
            if lane == 0:  # no thread reads L_jj before the next column
                sch.L[g0 + j * tm + j] = d
            sync()
        for c in range(lane, nt, LANES):
            gc = g0 + c * tm
            for i in range(nt):  # L z = e_c, into column c of G
                v = scalar(0.0)
                if i == c:
                    v = scalar(1.0)
                if i >= c:
                    for k in range(c, i):
                        v -= sch.L[g0 + i * tm + k] * sch.G[gc + k]
                    v = v / sch.L[g0 + i * tm + i]
                sch.G[gc + i] = v
            for ii in range(nt):  # L^T g = z
                i = nt - 1 - ii
                v = sch.G[gc + i]
                for k in range(i + 1, nt):
                    v -= sch.L[g0 + k * tm + i] * sch.G[gc + k]
                sch.G[gc + i] = v / sch.L[g0 + i * tm + i]
        sync()

    return schur_inverse


@functools.cache
def schur_apply_func(np_dtype, R: int):
    """A PADMM iteration's linear solve on the reduced problem (§7.11).
    ``schur_apply(sch, wid, lane, xs, ys)``, the vectors in shared memory (:func:`shared_vector` of ``R``), after a
    barrier."""
    scalar = builder_types(np_dtype).scalar
    Schur = schur_struct(np_dtype)
    Vec = shared_vector(np_dtype, R)
    sset, sget = shared_set_func(np_dtype, R), shared_get_func(np_dtype, R)

    @wp.func
    def schur_apply(sch: Schur, wid: int, lane: int, xs: Vec, ys: Vec):
        """``x_T = G rhs_T`` (threads over the rows of ``T``): the right-hand side in ``ys`` by ``T``'s index (``ys[i]``
        for row ``sch.rows[i]``), the solution into ``xs`` by row. Off ``T`` nothing is written: the reduced problem
        keeps ``F`` at zero (``kamino.jax_ref.reduction``), and the iterations do not read it there."""
        nt = sch.nt[wid]
        tm = sch.tm
        g0 = wid * tm * tm
        t0 = wid * tm
        for i in range(lane, nt, LANES):
            s = scalar(0.0)
            for j in range(nt):
                s += sch.G[g0 + j * tm + i] * sget(ys, j)
            sset(xs, sch.rows[t0 + i], s)
        sync()

    return schur_apply


@functools.cache
def filter_effort_rows_func(np_dtype):
    """The warm-start filter of the reduced problem (§7.11; docs/conventions.md "Warm start").
    ``filter_effort_rows(sch, wid, rb, rs, xb, lo_s, hi_s, x, x_p, y_p, y_hat)``, by one thread."""
    scalar = builder_types(np_dtype).scalar
    farr = wp.array(dtype=scalar)
    Schur = schur_struct(np_dtype)

    @wp.func
    def filter_effort_rows(sch: Schur, wid: int, rb: int, rs: int, xb: int, lo_s: farr, hi_s: farr, x: farr,
                           x_p: farr, y_p: farr, y_hat: farr):
        """``x_E <- clip(x_E - (S~_EE + s I)^-1 s x_E)`` on the effort-limited rows ``E`` (the first ``ne`` of
        ``T``): ``kamino.jax_ref.solver._Problem.filter_warm_start`` on the reduced problem, whose fixed rows they
        are (``F``'s warm start is zero), by a dense Cholesky of ``S~_EE + s I`` in ``sch.L`` and the thread's
        scratch ``sch.sx``; the result goes to ``x_p``, ``y_p``, ``y_hat`` and ``x`` unless it is not finite (the
        world keeps its warm start)."""
        ne = sch.ne[wid]
        tm = sch.tm
        g0 = wid * tm * tm
        t0 = wid * tm
        s0 = sch.filter_shift
        for j in range(ne):
            d = sch.S[g0 + j * tm + j] + s0
            for k in range(j):
                d -= sch.L[g0 + j * tm + k] * sch.L[g0 + j * tm + k]
            d = wp.sqrt(d)
            sch.L[g0 + j * tm + j] = d
            for i in range(j + 1, ne):
                v = sch.S[g0 + i * tm + j]
                for k in range(j):
                    v -= sch.L[g0 + i * tm + k] * sch.L[g0 + j * tm + k]
                sch.L[g0 + i * tm + j] = v / d
        for i in range(ne):
            v = s0 * x_p[rb + sch.rows[t0 + i] * rs]
            for k in range(i):
                v -= sch.L[g0 + i * tm + k] * sch.sx[xb + k * LANES]
            sch.sx[xb + i * LANES] = v / sch.L[g0 + i * tm + i]
        for ii in range(ne):
            i = ne - 1 - ii
            v = sch.sx[xb + i * LANES]
            for k in range(i + 1, ne):
                v -= sch.L[g0 + k * tm + i] * sch.sx[xb + k * LANES]
            sch.sx[xb + i * LANES] = v / sch.L[g0 + i * tm + i]
        ok = int(1)
        for i in range(ne):
            r = rb + sch.rows[t0 + i] * rs
            v = wp.clamp(x_p[r] - sch.sx[xb + i * LANES], lo_s[r], hi_s[r])
            sch.sx[xb + i * LANES] = v
            if not wp.isfinite(v):
                ok = 0
        if ok != 0:
            for i in range(ne):
                r = rb + sch.rows[t0 + i] * rs
                x_p[r] = sch.sx[xb + i * LANES]
                y_p[r] = sch.sx[xb + i * LANES]
                y_hat[r] = sch.sx[xb + i * LANES]
                x[r] = sch.sx[xb + i * LANES]

    return filter_effort_rows


#: The Schur reduction's per-step launches: the elimination (:func:`schur_kernel`, once per step), the reduced
#: right-hand side again (after the curvature refinement changed ``v_f``) and the recovery of ``lambda_F`` (the modes
#: of :func:`schur_solve_kernel`)
SCHUR_ELIMINATE, SCHUR_RHS, SCHUR_RECOVER = 0, 1, 2


@functools.cache
def schur_kernel(np_dtype):
    """The Schur reduction's elimination with the world's 32 threads (§7.11), once per step.
    ``schur(m, nblk, eta, rho_free, rho_box, row_stride, sp, n_rows, frozen, row_body, row_J, reg, P, vt,
    inv_inertia_w, lo_s, hi_s, row_info, rho_u, sch, p_ref, x, x_p, y_p, y_hat, z_p, z_hat, impulse, velocity,
    failed)``, launched tiled: one block of ``LANES`` threads per world, without shared memory: ``L_f`` is read in
    ``sp.val``, the threads' solution vectors live in ``Schur.sx``, ``G`` in ``Schur.G``. The columns of ``B = P_F
    D_FT P_T`` are kept as lists of their entries (``Schur.bp``, ``bv``, ``bn``; :func:`schur_list_cap`)."""
    scalar, M, SP, vec6, mat33 = builder_types(np_dtype).take("scalar", "M", "SP", "vec6", "mat33")
    farr, iarr = wp.array(dtype=scalar), wp.array(dtype=wp.int32)
    Schur = schur_struct(np_dtype)
    bases = sparse_llt_kernels(np_dtype).bases
    delassus_entry = sparse_llt_kernels(np_dtype).delassus_entry
    free_row = free_row_func(np_dtype)
    ff_solve = ff_solve_func(np_dtype)
    bf = body_funcs(np_dtype)
    row_u, row_dot_on, shares_body = bf.row_u, bf.row_dot_on, bf.shares_body
    SweepVal = wp.types.vector(length=SWEEP_BATCH, dtype=scalar)
    schur_inverse = schur_inverse_func(np_dtype)
    filter_effort_rows = filter_effort_rows_func(np_dtype)
    lane_max = rules.lane_reduce_func(np_dtype, LANES, "max")
    zero = scalar(0.0)

    @wp.func
    def rhs_v(sch: Schur, sp: SP, wid: int, rb: int, rs: int, lo_s: farr, hi_s: farr, vt: farr, xb: int):
        """The thread's right-hand side ``P v_F`` on ``F`` (position order in ``sch.sb`` from ``xb``); zero on the
        effort-limited rows and the hubs' unknowns."""
        nf = sp.n_fixed[wid]
        q0 = sp.perm_start[wid]
        for p in range(sp.n_pos[wid]):
            v = zero
            if p < nf:
                r = rb + sp.perm[q0 + p] * rs
                if free_row(lo_s, hi_s, r):
                    v = vt[r]
            sch.sb[xb + p * LANES] = v

    @wp.func
    def rhs_list(m: M, sch: Schur, sp: SP, wid: int, rb: int, rs: int, lo_s: farr, hi_s: farr, P: farr,
                 row_body: iarr, row_J: wp.array(dtype=vec6), inv_inertia_w: wp.array(dtype=mat33), nblk: int,
                 b0: int, ub: int, c: int, failed: iarr):
        """Column ``c``'s right-hand side ``b_c = P_F D_Fc P_c`` (row ``c`` of ``T``) as its list: ``u = M^-1 J_c^T
        P_c`` on row ``c``'s bodies (``row_u``), then the entries ``P_p J_p u`` of the rows of ``F`` that share a body
        with row ``c`` (``row_dot_on``), in position order; its other entries are zero. A list longer than
        ``sch.cap`` (not expected: :func:`schur_list_cap` bounds it) fails the world."""
        nf = sp.n_fixed[wid]
        q0 = sp.perm_start[wid]
        rc = rb + sch.rows[wid * sch.tm + c] * rs
        row_u(m, inv_inertia_w, sch.su, ub, b0, row_body, row_J, rc, nblk, P[rc])
        lb = (wid * sch.tm + c) * sch.cap
        cnt = int(0)
        for p in range(nf):
            r = rb + sp.perm[q0 + p] * rs
            if shares_body(row_body, r, rc, nblk) != 0:
                if free_row(lo_s, hi_s, r):
                    if cnt < sch.cap:
                        sch.bp[lb + cnt] = p
                        sch.bv[lb + cnt] = P[r] * row_dot_on(sch.su, ub, b0, row_body, row_J, r, rc, nblk)
                    cnt += 1
        if cnt > sch.cap:
            failed[wid] = 1
        sch.bn[wid * sch.tm + c] = wp.min(cnt, sch.cap)

    @wp.func
    def list_dot(sch: Schur, lb: int, n: int, xi: int) -> scalar:
        """``b_i . x`` over the ``n`` entries of a right-hand side's list from ``lb`` and the thread's solution ``x``:
        ``SWEEP_BATCH`` entries' positions and values, then their entries of ``x``, loaded together (clamped, the
        surplus values zero), summed in the list's order."""
        s = zero
        for jb in range(0, n, SWEEP_BATCH):
            pv = SweepIdx()
            bv = SweepVal()
            for r in range(SWEEP_BATCH):
                j = lb + wp.min(jb + r, n - 1)
                pv[r] = sch.bp[j]
                bv[r] = wp.where(jb + r < n, sch.bv[j], zero)
            xw = SweepVal()
            for r in range(SWEEP_BATCH):
                xw[r] = sch.sx[xi + pv[r] * LANES]
            for r in range(SWEEP_BATCH):
                s += bv[r] * xw[r]
        return s

    @wp.func
    def columns(m: M, nblk: int, rs: int, sp: SP, row_body: iarr, row_J: wp.array(dtype=vec6), reg: farr, P: farr,
                vt: farr, inv_inertia_w: wp.array(dtype=mat33), lo_s: farr, hi_s: farr, sch: Schur, wid: int,
                lane: int, failed: iarr):
        """``S~`` (unsymmetrised) and ``P v'_T`` (§7.11 (S), ``S~ = P_T D_TT P_T - B^T A^-1 B`` with ``B = P_F D_FT
        P_T``): first the columns ``b_c`` of ``B`` as lists (``rhs_list``, thread ``c mod LANES``), then column ``c``
        of ``S~`` (``c < nt``) or the right-hand side (``c = nt``, ``b = P v_F``) by thread ``c mod LANES``: its
        solve ``x = A^-1 b`` (:func:`ff_solve_func`) and the products ``b_i . x`` with the lists of every row ``i``
        of ``T`` (``list_dot``: ``P_i D_iF P_F x``, ``D_TF`` never formed)."""
        base = bases(m, sp, rs, wid)
        rb, vb = base[0], base[1]
        tm = sch.tm
        t0 = wid * tm
        g0 = wid * tm * tm
        b0 = m.body_start[wid]
        npos = sp.n_pos[wid]
        xb = wid * LANES * sch.np_max + lane  # the thread's scratch vectors, interleaved with the world's others'
        ub = wid * LANES * sch.nb_max + lane
        nt = sch.nt[wid]
        for c in range(lane, nt, LANES):
            rhs_list(m, sch, sp, wid, rb, rs, lo_s, hi_s, P, row_body, row_J, inv_inertia_w, nblk, b0, ub, c, failed)
        sync()
        for c in range(lane, nt + 1, LANES):
            if c < nt:  # b_c from its list
                for p in range(npos):
                    sch.sb[xb + p * LANES] = zero
                lb = (t0 + c) * sch.cap
                for j in range(sch.bn[t0 + c]):
                    sch.sb[xb + sch.bp[lb + j] * LANES] = sch.bv[lb + j]
            else:
                rhs_v(sch, sp, wid, rb, rs, lo_s, hi_s, vt, xb)
            ff_solve(sp, wid, vb, sch.sb, sch.sx, xb, sch.eps)
            for i in range(nt):
                ai = sch.rows[t0 + i]
                ri = rb + ai * rs
                dx = list_dot(sch, (t0 + i) * sch.cap, sch.bn[t0 + i], xb)
                if c < nt:
                    ac = sch.rows[t0 + c]
                    sch.S[g0 + i * tm + c] = (P[ri] * delassus_entry(m, rs, row_body, row_J, reg, inv_inertia_w,
                                                                     wid, ai, ac, nblk) * P[rb + ac * rs] - dx)
                else:
                    sch.vt[ri] = vt[ri] - dx
        sync()

    @wp.kernel(module="unique", enable_backward=False)
    def schur(
        # model (read only)
        m: M,
        # in
        nblk: int, eta: scalar, rho_free: scalar, rho_box: scalar,
        row_stride: int,
        sp: SP,  # L_f of A + eps I (schur_decouple, factor_kernel on the fixed rows; read)
        n_rows: iarr, frozen: iarr, row_body: iarr, row_J: wp.array(dtype=vec6), reg: farr, P: farr, vt: farr,
        inv_inertia_w: wp.array(dtype=mat33), lo_s: farr, hi_s: farr, row_info: iarr, rho_u: farr,
        # out
        sch: Schur,
        p_ref: farr,
        x: farr, x_p: farr, y_p: farr, y_hat: farr, z_p: farr, z_hat: farr,  # the warm start (also read)
        impulse: farr, velocity: farr, failed: iarr,  # padmm_finish's (also read)
    ):
        """After ``padmm_init``: the rows of ``T``, the residual scale ``P_ref`` over them, the warm start zero on
        ``F``, ``S~ = P_T D_TT P_T - P_T D_TF A^-1 D_FT P_T`` symmetrised and ``P v'_T = P v_T - P_T D_TF A^-1 P v_F``
        (§7.11 (S), the columns of ``T`` and the right-hand side one per thread, :func:`ff_solve_func`), the
        warm-start filter of the effort-limited rows (:func:`filter_effort_rows_func`) and ``G``
        (:func:`schur_inverse_func`)."""
        rs = row_stride
        wid, lane = wp.tid()
        n = n_rows[wid]
        if frozen[wid] != 0 or n == 0:
            return
        rb = bases(m, sp, row_stride, wid)[0]
        nf = sp.n_fixed[wid]
        tm = sch.tm
        t0 = wid * tm
        g0 = wid * tm * tm
        xb = wid * LANES * sch.np_max + lane  # the thread's scratch vectors, interleaved with the world's others'
        if lane == 0:  # the rows of T, ascending: the effort-limited fixed rows, then the limit and contact rows
            cnt = int(0)
            for a in range(nf):
                if not free_row(lo_s, hi_s, rb + a * rs):
                    if cnt < tm:
                        sch.rows[t0 + cnt] = a
                    cnt += 1
            sch.ne[wid] = wp.min(cnt, tm)
            for a in range(nf, n):
                if cnt < tm:
                    sch.rows[t0 + cnt] = a
                cnt += 1
            if cnt > tm:  # more rows than the capacity (not expected: Stepper sizes it)
                failed[wid] = 1
            sch.nt[wid] = wp.min(cnt, tm)
        pref = zero
        for a in range(lane, nf, LANES):
            r = rb + a * rs
            if free_row(lo_s, hi_s, r):  # the reduced problem's rows off T: zero
                x[r] = zero
                x_p[r] = zero
                y_p[r] = zero
                y_hat[r] = zero
                z_p[r] = zero
                z_hat[r] = zero
                sch.vt[r] = zero
            else:
                pref = wp.max(pref, P[r])
        for a in range(nf + lane, n, LANES):
            pref = wp.max(pref, P[rb + a * rs])
        pref = lane_max(pref)
        if lane == 0:
            if pref <= zero:
                pref = scalar(1.0)
            p_ref[wid] = pref
        sync()
        columns(m, nblk, rs, sp, row_body, row_J, reg, P, vt, inv_inertia_w, lo_s, hi_s, sch, wid, lane, failed)
        nt = sch.nt[wid]
        for u in range(lane, nt * nt, LANES):  # S~ <- (S~ + S~^T) / 2
            i = u // nt
            j = u - i * nt
            if i < j:
                s = scalar(0.5) * (sch.S[g0 + i * tm + j] + sch.S[g0 + j * tm + i])
                sch.S[g0 + i * tm + j] = s
                sch.S[g0 + j * tm + i] = s
        sync()
        if lane == 0 and sch.filter_shift > zero:
            filter_effort_rows(sch, wid, rb, rs, xb, lo_s, hi_s, x, x_p, y_p, y_hat)
        sync()
        schur_inverse(sch, wid, lane, row_info, rb, rs, nf, eta, rho_free, rho_box, rho_u[wid])

    return schur


@functools.cache
def ff_solve_lanes_func(np_dtype, R: int):
    """``A^-1 b`` on ``F`` with ``SCHUR_REFINEMENT_STEPS`` refinement steps by the world's threads together (§7.11).
    ``ff_solve_lanes(m, sp, row_stride, wid, lane, eps, bs, xs, ys)``, the vectors in shared memory
    (:func:`shared_vector` of ``R``), indexed by row."""
    scalar, M, SP = builder_types(np_dtype).take("scalar", "M", "SP")
    Vec = shared_vector(np_dtype, R)
    sset, sget = shared_set_func(np_dtype, R), shared_get_func(np_dtype, R)
    solve = solve_func(np_dtype, R)

    @wp.func
    def ff_solve_lanes(m: M, sp: SP, row_stride: int, wid: int, lane: int, eps: scalar, bs: Vec, xs: Vec, ys: Vec):
        """``xs = A^-1 b`` on the fixed rows (``b``: ``bs``, zero off ``F``; ``ys``: scratch): :func:`ff_solve_func`'s
        refinement ``x_{k+1} = C^-1 (b + eps x_k)``, each solve with ``C = L_f L_f^T`` by :func:`solve_func`'s column
        sweeps on the fixed rows alone (one barrier per row of ``L_f``; the hubs' unknowns take a zero right-hand
        side there), the vectors' updates between them threads over rows."""
        nf = sp.n_fixed[wid]
        for a in range(lane, nf, LANES):
            sset(xs, a, sget(bs, a))
        sync()
        solve(m, sp, row_stride, wid, nf, lane, xs, ys)
        for _ in range(SCHUR_REFINEMENT_STEPS):
            for a in range(lane, nf, LANES):
                sset(xs, a, sget(bs, a) + eps * sget(xs, a))
            sync()
            solve(m, sp, row_stride, wid, nf, lane, xs, ys)

    return ff_solve_lanes


@functools.cache
def body_sum_func(np_dtype, R: int):
    """``u = M^-1 J^T c`` on a world's bodies by its threads (§7.1), for the reduced right-hand side and the recovery
    (§7.11). ``body_sum(m, inv_inertia_w, su, ub, b0, nb, row_body, row_J, rb, rs, n, nblk, cs, lane)``."""
    M, vec6, mat33 = builder_types(np_dtype).take("M", "vec6", "mat33")
    iarr = wp.array(dtype=wp.int32)
    Vec = shared_vector(np_dtype, R)
    sget = shared_get_func(np_dtype, R)
    inv_mass_times = sparse_llt_kernels(np_dtype).inv_mass_times

    @wp.func
    def body_sum(m: M, inv_inertia_w: wp.array(dtype=mat33), su: wp.array(dtype=vec6), ub: int, b0: int, nb: int,
                 row_body: iarr, row_J: wp.array(dtype=vec6), rb: int, rs: int, n: int, nblk: int, cs: Vec,
                 lane: int):
        """``u = M^-1 J^T c`` over the world's first ``n`` rows (``c_a``: ``cs[a]``, by row) into ``su[ub + i
        LANES]`` (body ``i``), then a barrier: threads over the bodies, each summing its blocks ``J_a^T c_a`` in row
        order (the order of :func:`body_funcs`' ``add_row`` over the rows), so that no two threads write one body."""
        for i in range(lane, nb, LANES):
            u = vec6()
            for a in range(n):
                r = rb + a * rs
                for k in range(nblk):
                    if row_body[r * nblk + k] == b0 + i:
                        u = u + sget(cs, a) * row_J[r * nblk + k]
            su[ub + i * LANES] = inv_mass_times(m, inv_inertia_w, b0 + i, u)
        sync()

    return body_sum


@functools.cache
def schur_solve_kernel(np_dtype, R: int):
    """The reduced right-hand side and the recovery of the Schur reduction with the world's 32 threads together
    (§7.11). ``schur_solve(m, mode, nblk, eta, rho_free, rho_box, row_stride, sp, n_rows, frozen, row_body, row_J,
    reg, P, vt, inv_inertia_w, lo_s, hi_s, row_info, rho_u, sch, p_ref, x, x_p, y_p, y_hat, z_p, z_hat, impulse,
    velocity, failed)`` (:func:`schur_kernel`'s arguments after ``mode``), launched tiled: one block of ``LANES``
    threads per world; three vectors of ``R`` rows in shared memory."""
    scalar, M, SP, vec6, mat33 = builder_types(np_dtype).take("scalar", "M", "SP", "vec6", "mat33")
    farr, iarr = wp.array(dtype=scalar), wp.array(dtype=wp.int32)
    Schur = schur_struct(np_dtype)
    Vec = shared_vector(np_dtype, R)
    sset, sget = shared_set_func(np_dtype, R), shared_get_func(np_dtype, R)
    bases = sparse_llt_kernels(np_dtype).bases
    free_row = free_row_func(np_dtype)
    ff_solve_lanes = ff_solve_lanes_func(np_dtype, R)
    body_sum = body_sum_func(np_dtype, R)
    row_dot = body_funcs(np_dtype).row_dot
    zero = scalar(0.0)

    @wp.func
    def fixed_rhs(sp: SP, wid: int, rb: int, rs: int, lo_s: farr, hi_s: farr, vt: farr, P: farr, su: wp.array(
            dtype=vec6), ub: int, b0: int, row_body: iarr, row_J: wp.array(dtype=vec6), nblk: int, lane: int,
            recover: int, bs: Vec):
        """The right-hand side on ``F`` into ``bs`` (by row, threads over the fixed rows): ``P v_F``, or with
        ``recover`` ``-(P v_F + P_F D_FT lambda_T)`` from ``u = M^-1 J_T^T lambda_T`` in ``su``; zero on the
        effort-limited rows."""
        for a in range(lane, sp.n_fixed[wid], LANES):
            r = rb + a * rs
            v = zero
            if free_row(lo_s, hi_s, r):
                if recover != 0:
                    v = -(vt[r] + P[r] * row_dot(su, ub, b0, row_body, row_J, r, nblk))
                else:
                    v = vt[r]
            sset(bs, a, v)
        sync()

    @wp.kernel(module="unique", enable_backward=False)
    def schur_solve(
        # model (read only)
        m: M,
        # in
        mode: int, nblk: int, eta: scalar, rho_free: scalar, rho_box: scalar,
        row_stride: int,
        sp: SP,  # L_f of A + eps I (schur_decouple, factor_kernel on the fixed rows; read)
        n_rows: iarr, frozen: iarr, row_body: iarr, row_J: wp.array(dtype=vec6), reg: farr, P: farr, vt: farr,
        inv_inertia_w: wp.array(dtype=mat33), lo_s: farr, hi_s: farr, row_info: iarr, rho_u: farr,
        # out
        sch: Schur,
        p_ref: farr,
        x: farr, x_p: farr, y_p: farr, y_hat: farr, z_p: farr, z_hat: farr,
        impulse: farr, velocity: farr, failed: iarr,  # padmm_finish's (also read)
    ):
        """``mode`` :data:`SCHUR_RHS`: ``P v'_T = P v_T - P_T D_TF A^-1 P v_F`` again (§7.11 (S); the curvature
        refinement changed ``v_f``). :data:`SCHUR_RECOVER` (after ``padmm_finish``): ``lambda_F = -P_F A^-1 (P v_F +
        P_F D_FT lambda_T)`` (§7.11 (R)) and ``v+ = D lambda + v_f`` on ``F``; a non-finite impulse fails the world.
        The solve is :func:`ff_solve_lanes_func`'s, the products with ``J`` threads over rows, those with ``J^T``
        threads over bodies (:func:`body_sum_func`, into the first thread's ``sch.su``)."""
        rs = row_stride
        wid, lane = wp.tid()
        n = n_rows[wid]
        if frozen[wid] != 0 or n == 0:
            return
        rb = bases(m, sp, row_stride, wid)[0]
        nf = sp.n_fixed[wid]
        t0 = wid * sch.tm
        b0 = m.body_start[wid]
        nb = m.body_count[wid]
        ub = wid * LANES * sch.nb_max  # the body vector u: the first thread's slots of sch.su
        bs = wp.tile_zeros(shape=(R,), dtype=scalar, storage="shared")  # b; then the rows' factors of J^T
        xs = wp.tile_zeros(shape=(R,), dtype=scalar, storage="shared")
        ys = wp.tile_zeros(shape=(R,), dtype=scalar, storage="shared")
        if mode == SCHUR_RHS:
            fixed_rhs(sp, wid, rb, rs, lo_s, hi_s, vt, P, sch.su, ub, b0, row_body, row_J, nblk, lane, 0, bs)
            ff_solve_lanes(m, sp, row_stride, wid, lane, sch.eps, bs, xs, ys)
            for a in range(lane, nf, LANES):  # u = M^-1 J_F^T P_F x
                r = rb + a * rs
                c = zero
                if free_row(lo_s, hi_s, r):
                    c = P[r] * sget(xs, a)
                sset(bs, a, c)
            sync()
            body_sum(m, inv_inertia_w, sch.su, ub, b0, nb, row_body, row_J, rb, rs, nf, nblk, bs, lane)
            for i in range(lane, sch.nt[wid], LANES):
                ri = rb + sch.rows[t0 + i] * rs
                sch.vt[ri] = vt[ri] - P[ri] * row_dot(sch.su, ub, b0, row_body, row_J, ri, nblk)
        else:
            for a in range(lane, n, LANES):  # u = M^-1 J_T^T lambda_T
                r = rb + a * rs
                c = impulse[r]
                if a < nf:
                    if free_row(lo_s, hi_s, r):
                        c = zero
                sset(bs, a, c)
            sync()
            body_sum(m, inv_inertia_w, sch.su, ub, b0, nb, row_body, row_J, rb, rs, n, nblk, bs, lane)
            fixed_rhs(sp, wid, rb, rs, lo_s, hi_s, vt, P, sch.su, ub, b0, row_body, row_J, nblk, lane, 1, bs)
            ff_solve_lanes(m, sp, row_stride, wid, lane, sch.eps, bs, xs, ys)
            for a in range(lane, n, LANES):  # lambda_F, then u = M^-1 J^T lambda over every row
                r = rb + a * rs
                c = impulse[r]
                if a < nf:
                    if free_row(lo_s, hi_s, r):
                        c = P[r] * sget(xs, a)
                        impulse[r] = c
                        if not wp.isfinite(c):
                            failed[wid] = 1
                sset(bs, a, c)
            sync()
            body_sum(m, inv_inertia_w, sch.su, ub, b0, nb, row_body, row_J, rb, rs, n, nblk, bs, lane)
            for a in range(lane, nf, LANES):  # v+ = D lambda + v_f on F
                r = rb + a * rs
                if free_row(lo_s, hi_s, r):
                    velocity[r] = (row_dot(sch.su, ub, b0, row_body, row_J, r, nblk) + reg[r] * impulse[r]
                                   + vt[r] / P[r])

    return schur_solve


# --- iterations (§7.3-§7.5) ----------------------------------------------------------------------------------------

@functools.cache
def lane_rhs_func(np_dtype):
    """§7.3 steps 1-2 on one row of the 32-thread schedule.
    ``lane_rhs(row_stride, row_info, ct_mu, vt, x_p, y_hat, z_hat, r, a, nf, n_box, rho_free, rho_box, rho_u, eta)``:
    ``solver_rules.row_rhs_func``, then the contact correction on a normal row."""
    scalar = builder_types(np_dtype).scalar
    farr = wp.array(dtype=scalar)
    row_penalty = rules.row_penalty_func(np_dtype)
    row_rhs = rules.row_rhs_func(np_dtype)
    contact_correction = rules.contact_correction_func(np_dtype)

    @wp.func
    def lane_rhs(row_stride: int, row_info: wp.array(dtype=wp.int32), ct_mu: farr, vt: farr, x_p: farr, y_hat: farr,
                 z_hat: farr, r: int, a: int, nf: int, n_box: int, rho_free: scalar, rho_box: scalar, rho_u: scalar,
                 eta: scalar):
        """Row ``a``'s right-hand side, the De Saxcé correction included on a contact's normal row (the thread that
        owns the row computes it, reading the contact's ``z_hat``)."""
        rs = row_stride
        rhs = row_rhs(vt, x_p, y_hat, z_hat, r, row_penalty(row_info, r, a, nf, rho_free, rho_box, rho_u), eta)
        if a >= n_box and (a - n_box) % 3 == 2:
            rhs -= contact_correction(ct_mu, row_info, z_hat, r - 2 * rs, rs)
        return rhs

    return lane_rhs


@functools.cache
def iterate_kernel(np_dtype, R: int, cr: bool, adaptive: bool, accelerate: bool, fixed_iterations: bool,
                   inverse: bool = False, schur: bool = False):
    """Accelerated PADMM with the world's 32 threads (§7.3-§7.5; the rules of ``solver_rules.py``), with the sparse
    factor (shared vectors of ``R`` rows) or with Conjugate Residual (``cr``), the adaptive penalty (``adaptive``),
    the momentum (``accelerate``), every world running to its cap (``fixed_iterations``), the solve with
    ``L_f^-1`` (``inverse``, :func:`solve_func`) and on the reduced problem of §7.11 (``schur``: the product with
    ``G``, :func:`schur_apply_func`): all compile-time.
    ``padmm_iterate``'s arguments are those of ``solver.padmm_iterate_kernel``'s kernel less ``D``, and the reduced
    problem (:func:`schur_struct`; unread unless ``schur``); launched tiled: one block of ``LANES`` threads per
    world."""
    scalar, M, SP, vec3, vec6 = builder_types(np_dtype).take("scalar", "M", "SP", "vec3", "vec6")
    farr, iarr = wp.array(dtype=scalar), wp.array(dtype=wp.int32)
    Problem, Carry = rules.problem_struct(np_dtype), rules.carry_struct(np_dtype)
    Residuals = rules.residuals_struct(np_dtype)
    row_base = index_funcs(np_dtype).row_base
    sset, sget = shared_set_func(np_dtype, R), shared_get_func(np_dtype, R)
    solve = solve_func(np_dtype, R, inverse)
    cr_solve = cr_solve_func(np_dtype, LANES)
    factor_tail = factor_tail_func(np_dtype)
    lane_rhs = lane_rhs_func(np_dtype)
    row_penalty = rules.row_penalty_func(np_dtype)
    box_row = rules.box_row_func(np_dtype, adaptive)
    contact_rows = rules.contact_rows_func(np_dtype)
    cr_residual = rules.cr_residual_func(np_dtype)
    reduce_residuals = rules.reduce_residuals_func(np_dtype, LANES)
    outcome = rules.outcome_func(np_dtype, adaptive, accelerate)
    mark_saturated = rules.mark_saturated_func(np_dtype)
    advance_row = rules.advance_row_func(np_dtype)
    store_world = rules.store_world_func(np_dtype)
    Schur = schur_struct(np_dtype)
    schur_apply = schur_apply_func(np_dtype, R)
    schur_inverse = schur_inverse_func(np_dtype)

    @wp.kernel(module="unique", enable_backward=False,
               cuda_max_registers=ITERATE_MAX_REGISTERS if R >= REGISTER_CAP_MIN_ROWS else SMALL_WORLD_MAX_REGISTERS)
    def padmm_iterate(
        m: M, problem: Problem, chunk: int,  # in: the model, the world's problem, the iterations of this launch
        carry: Carry,  # in and out: the iterate and the world's state
        sp: SP,  # out: the factor's tail values sp.tail (a new penalty; not under cr); its index tables are read
        row_info: iarr,  # out: a row's saturation flag (also read)
        x: farr, y: farr, z: farr, cr_r: farr, cr_p: farr, cr_Ap: farr, cr_Ar: farr, cr_w: wp.array(dtype=vec6),  # out
        sch: Schur,  # out: G (a new penalty or a saturation; schur only)
    ):
        """Up to ``chunk`` iterations of one world (``solver.padmm_iterate_kernel`` rule for rule), resuming from the
        stored iterate; a world that converges (unless ``fixed_iterations``) or reaches its cap is marked done and
        leaves ``remaining``. The threads split the box rows and the contact triples; the world's residuals are block
        reductions. Under ``cr`` (at most ``cr_budget`` iterations per solve) the solution lands in ``x`` (the
        factor's solve: in ``xs``), a new penalty refactorises nothing and a row that saturates takes ``rho_box`` in
        the next solve's operator without ending the launch. Under ``schur`` the row passes visit the rows of ``T``
        alone (``F``'s iterate is zero, as is its share of every residual), and a new penalty or a saturation
        recomputes ``G`` in place without ending the launch."""
        rs = problem.row_stride
        eta, rho_free, rho_box = problem.eta, problem.rho_free, problem.rho_box
        wid, lane = wp.tid()
        if carry.done[wid] != 0:
            return
        rb = row_base(m, rs, wid)
        n = problem.n_rows[wid]
        nb = problem.n_box[wid]
        nc = (n - nb) // 3
        nf = m.row_fixed[wid]
        pref = problem.p_ref[wid]
        rho_w = carry.rho_u[wid]
        if wp.static(not cr):
            xs = wp.tile_zeros(shape=(R,), dtype=scalar, storage="shared")
            ys = wp.tile_zeros(shape=(R,), dtype=scalar, storage="shared")
        # the rows that the row passes visit: every row, or under schur the rows of T alone (sch.rows; the first
        # n_tb of them are box rows), F's staying at zero
        n_t = n
        n_tb = nb
        t0 = wid * sch.tm
        if wp.static(schur):
            n_t = sch.nt[wid]
            n_tb = sch.ne[wid] + nb - nf
        for step in range(chunk):
            for i in range(lane, n_t, LANES):  # steps 1-2: right-hand side (into xs; CR's into y), linear solve
                a = i
                if wp.static(schur):
                    a = sch.rows[t0 + i]
                rhs = lane_rhs(rs, row_info, problem.ct_mu, problem.vt, carry.x_p, carry.y_hat, carry.z_hat,
                               rb + a * rs, a, nf, nb, rho_free, rho_box, rho_w, eta)
                if wp.static(cr):
                    y[rb + a * rs] = rhs
                elif wp.static(schur):
                    sset(ys, i, rhs)  # by T's index (schur_apply)
                else:
                    sset(xs, a, rhs)
            if wp.static(cr):
                cr_solve(m, rs, problem.row_body, problem.row_J, row_info, problem.reg, problem.P,
                         problem.inv_inertia_w, problem.cr_ent, problem.cr_end, carry.x_p, y, wid, rb, n, problem.nblk,
                         lane, eta + rho_free, eta + rho_box, eta + rho_w, problem.cr_budget, x, cr_r, cr_p, cr_Ap,
                         cr_Ar, cr_w)
            elif wp.static(schur):
                sync()
                schur_apply(sch, wid, lane, xs, ys)
            else:
                sync()
                solve(m, sp, rs, wid, n, lane, xs, ys)
            acc = Residuals()  # steps 3-4: projection, dual update and the residuals: box rows, then contact triples
            for i in range(lane, n_tb, LANES):
                a = i
                if wp.static(schur):
                    a = sch.rows[t0 + i]
                r = rb + a * rs
                if wp.static(cr):
                    xa = x[r]
                else:
                    xa = sget(xs, a)
                    x[r] = xa
                acc = box_row(row_info, problem.lo_s, problem.hi_s, carry.x_p, carry.y_hat, carry.z_hat, problem.P,
                              y, z, carry.e_p, r, a, nf, xa, row_penalty(row_info, r, a, nf, rho_free, rho_box, rho_w),
                              eta, pref, acc)
            inv_rho = scalar(1.0) / rho_w
            for c in range(lane, nc, LANES):
                a = nb + 3 * c
                r = rb + a * rs
                if wp.static(cr):
                    x3 = vec3(x[r], x[r + rs], x[r + 2 * rs])
                else:
                    x3 = vec3(sget(xs, a), sget(xs, a + 1), sget(xs, a + 2))
                    for t in range(3):
                        x[r + t * rs] = x3[t]
                acc = contact_rows(problem.ct_mu, row_info, carry.z_hat, x, carry.x_p, carry.y_hat, problem.P, y, z, r,
                                   rs, x3, inv_rho, rho_w, eta, pref, acc)
            if wp.static(cr):
                for a in range(lane, n, LANES):
                    acc = cr_residual(problem.P, cr_r, rb + a * rs, pref, acc)
            acc = reduce_residuals(acc)
            k = carry.iters[wid] + 1
            res = outcome(carry.a_p, carry.c_p, carry.k_rho, wid, acc, k, n, nf, rho_w, problem.tol, eta, rho_free,
                          problem.restart_tol)
            if wp.static(schur):
                # the saturated rows' flags, then G for the new penalties (kamino.jax_ref.solver._run refactorises
                # before the next iteration); the condition is the world's (block reductions), so every thread meets
                # the barriers
                if res.saturates != 0:  # the effort-limited rows: T's first
                    for i in range(lane, sch.ne[wid], LANES):
                        mark_saturated(problem.lo_s, problem.hi_s, x, carry.z_hat, y, row_info,
                                       rb + sch.rows[t0 + i] * rs, rho_free)
                if res.rho != rho_w or res.saturates != 0:
                    sync()  # every thread has read k_rho (outcome) and set its flags
                    if lane == 0 and res.rho != rho_w:
                        carry.rho_u[wid] = res.rho
                        carry.k_rho[wid] = k
                    rho_w = res.rho
                    schur_inverse(sch, wid, lane, row_info, rb, rs, nf, eta, rho_free, rho_box, rho_w)
            else:
                if res.rho != rho_w:  # a new penalty: the factor's tail again, unless a saturation redoes it all
                    rho_w = res.rho
                    sync()  # every thread has read k_rho (outcome) before it changes
                    if wp.static(not cr):
                        if res.saturates == 0:
                            factor_tail(m, sp, rs, wid, n, eta + rho_w, lane)
                    if lane == 0:
                        carry.rho_u[wid] = rho_w
                        carry.k_rho[wid] = k
                if res.saturates != 0:  # this thread's own rows of the projection loop above
                    for a in range(lane, nf, LANES):
                        mark_saturated(problem.lo_s, problem.hi_s, x, carry.z_hat, y, row_info, rb + a * rs, rho_free)
            for i in range(lane, n_t, LANES):
                a = i
                if wp.static(schur):
                    a = sch.rows[t0 + i]
                if wp.static(cr):
                    advance_row(y, z, carry.x_p, carry.y_p, carry.z_p, carry.y_hat, carry.z_hat, rb + a * rs,
                                x[rb + a * rs], res.mom)
                else:
                    advance_row(y, z, carry.x_p, carry.y_p, carry.z_p, carry.y_hat, carry.z_hat, rb + a * rs,
                                sget(xs, a), res.mom)
            finished = (res.converged != 0 and not wp.static(fixed_iterations)) or k >= problem.it_cap[wid]
            sync()  # every thread has read the world's scalars before they change
            if lane == 0:
                store_world(carry.a_p, carry.c_p, carry.iters, carry.r_p, carry.r_d, carry.r_c, carry.converged,
                            carry.done, carry.remaining, wid, k, acc, res, finished)
                if res.saturates != 0:  # the factor is redone after this launch (CR: the next operator takes rho_box)
                    carry.k_rho[wid] = k
                    if wp.static(not cr and not schur):
                        carry.pending[wid] = 1
            sync()
            if wp.static(cr or schur):
                if finished:
                    return
            elif finished or res.saturates != 0:
                return

    return padmm_iterate


def warp_kernels(np_dtype, R: int, E: int = 0, cr: bool = False, filter_E: int | None = None,
                 inverse: bool = False, schur: bool = False) -> SimpleNamespace:
    """``factor`` (not under ``cr``), ``solve_fixed`` (post-stabilisation) and ``cr_pattern`` (under ``cr``) for
    worlds of up to ``R`` rows; launch each 32-thread kernel with ``wp.launch_tiled(dim=[num_worlds],
    block_dim=LANES)``, ``cr_pattern`` with one thread per world (``wp.launch``). :func:`iterate_kernel` gives
    ``padmm_iterate``. The solve keeps two vectors of ``R`` rows in shared memory (2 R scalars per world). With ``E >
    0`` the factorisation copies the world's ``D~_f`` (up to ``E`` entries) into shared memory, factorises it there
    and writes ``L_f`` back: its chain of dependent read-modify-writes, one per update, then waits on shared memory
    instead of device memory. With ``cr`` the iterations solve with Conjugate Residual instead of the factor (§8.2,
    ``linear_solve_cr.py``: the vectors in the ``Work`` rows, no shared vectors), after ``cr_pattern`` has grouped the
    world's row blocks by body for the step. With ``filter_E`` (the warm-start filter's staged entries,
    :func:`shared_entries`; ``None``: no filter) also ``filter_factor``, :func:`factor_kernel` for the filter's
    factor of the fixed rows, and ``warm_start_filter`` (:func:`warm_start_filter_kernel`). With ``schur`` (§7.11)
    also ``schur_decouple`` (:func:`schur_decouple_kernel`, on ``(worlds, max entries)``), ``schur`` (the
    elimination, :func:`schur_kernel`) and ``schur_solve`` (:func:`schur_solve_kernel`)."""
    filtered = filter_E is not None
    return SimpleNamespace(factor=None if cr else factor_kernel(np_dtype, E, inverse), inverse=inverse,
                           solve_fixed=solve_fixed_kernel(np_dtype, R),
                           cr_pattern=cr_pattern_kernel(np_dtype) if cr else None, R=R, E=E, cr=cr,
                           filter_factor=factor_kernel(np_dtype, filter_E) if filtered else None,
                           warm_start_filter=warm_start_filter_kernel(np_dtype, R) if filtered else None,
                           schur_decouple=schur_decouple_kernel(np_dtype) if schur else None,
                           schur=schur_kernel(np_dtype) if schur else None,
                           schur_solve=schur_solve_kernel(np_dtype, R) if schur else None)


def schur_buffers(np_dtype, device, num_worlds: int, total_rows: int, tm: int, np_max: int, nb_max: int,
                  eps: float = 0.0, filter_shift: float = 0.0, cap: int = 0):
    """A zero-initialised :func:`schur_struct` for ``num_worlds`` worlds of up to ``tm`` reduced rows, ``np_max``
    fixed positions and ``nb_max`` bodies, over ``total_rows`` row slots (``Work``'s), the right-hand sides' lists
    of up to ``cap`` entries (:func:`schur_list_cap`); all sizes 0: the empty one that the iterations take when they
    do not reduce."""
    T = builder_types(np_dtype)
    out = schur_struct(np_dtype)()
    out.tm, out.np_max, out.nb_max, out.cap = tm, np_max, nb_max, cap
    out.eps, out.filter_shift = T.scalar(eps), T.scalar(filter_shift)
    per_lane = num_worlds * LANES

    def arr(n, dtype=T.scalar):
        return wp.zeros(max(int(n), 0), dtype=dtype, device=device)

    out.rows, out.nt, out.ne = arr(num_worlds * tm, wp.int32), arr(num_worlds, wp.int32), arr(num_worlds, wp.int32)
    out.S, out.L, out.G = (arr(num_worlds * tm * tm) for _ in range(3))
    out.vt = arr(total_rows)
    out.bp, out.bv, out.bn = arr(num_worlds * tm * cap, wp.int32), arr(num_worlds * tm * cap), arr(num_worlds * tm,
                                                                                                 wp.int32)
    out.sb, out.sx = arr(per_lane * np_max), arr(per_lane * np_max)
    out.su = arr(per_lane * nb_max, T.vec6)
    return out
