"""Per-step device buffers of the Warp backend (one struct, allocated once per model and config).

The kernels take these buffers one by one, by their field names (``m``, then what a kernel reads, then what it
writes: docs/warp_backend.md, "Modules"); the struct stays on the host, where its typed fields check each buffer's
dtype when :func:`allocate` assigns it.

The state the step reads (``q``, ``u``, the previous step's reactions and contacts, the controls)
is held in persistent buffers, so that a captured CUDA graph always sees the same addresses; the
step writes its results into ``*_new`` buffers and a final commit copies them over the state
(keeping the previous state of a world whose result is not finite).
"""

import dataclasses
import functools

import numpy as np
import warp as wp

from kamino.warp_backend.model_data import GROUP, WarpModel, model_struct
from kamino.warp_backend.types import Types, types_of

#: ``Work.row_info``: one int32 per row packs what the row assembly knows about a row besides its numbers: its
#: source (the DoF, kinematic constraint, coupling or contact slot it comes from; a global index) in the low
#: :data:`ROW_SRC_BITS` bits, then the saturation flag of an effort-limited fixed row (kamino.jax_ref.solver
#: "Saturation"), the sign of a limit row (set: the upper limit, ``side = -1``) and the row family (rows.ROW_*)
#: in the top bits. The accessors are ``indexing.index_funcs``' ``row_kind``, ``row_source``, ``row_side``,
#: ``row_saturated``, ``set_saturated``, ``row_mu`` and ``row_info``.
ROW_SRC_BITS = 26
ROW_SRC_MASK = (1 << ROW_SRC_BITS) - 1
ROW_SAT_BIT = 1 << ROW_SRC_BITS
ROW_NEG_BIT = 1 << (ROW_SRC_BITS + 1)
ROW_KIND_SHIFT = ROW_SRC_BITS + 2


def saturated_rows(info: np.ndarray) -> np.ndarray:
    """The saturation flags (0/1) of ``Work.row_info`` read back to the host."""
    return (np.asarray(info) >> ROW_SRC_BITS) & 1


@functools.cache
def work_struct(np_dtype):
    """The ``Work`` struct of one precision: every per-step buffer, by name."""
    T = types_of(np_dtype)
    scalar, vec3, vec6, mat33, transform = T.scalar, T.vec3, T.vec6, T.mat33, T.transform
    iarr = wp.array(dtype=wp.int32)
    farr = wp.array(dtype=scalar)
    v3 = wp.array(dtype=vec3)
    v6 = wp.array(dtype=vec6)

    @wp.struct
    class Work:
        # storage distance between consecutive rows of a world: GROUP (rows interleaved over groups of 32 worlds,
        # for the one-thread-per-world kernels) or 1 (each world's rows contiguous, for solver_lanes.py's threads)
        row_stride: int
        # state (persistent) and controls
        q: wp.array(dtype=transform)
        u: v6
        time: farr
        kin_force: farr  # [num_constraints] lambda/dt of the kinematic rows
        cpl_force: farr  # [num_couplings]
        act_force: farr  # [num_dofs]
        pas_force: farr
        lim_force: farr
        con_pair: iarr  # [capacity] previous/committed contacts
        con_pos: v3
        con_normal: v3
        con_dist: farr
        con_force: v3
        con_velocity: v3
        con_point_b: v3
        effort: farr  # controls [num_dofs]
        position_target: farr
        velocity_target: farr
        wrench: v6  # [num_bodies]
        # body quantities of this step
        q_eval: wp.array(dtype=transform)
        q_pred: wp.array(dtype=transform)
        u_f: v6
        inertia_w: wp.array(dtype=mat33)
        inv_inertia_w: wp.array(dtype=mat33)
        body_impulse: v6
        # DoF quantities
        dof_JF: v6
        dof_JB: v6
        q_dof: farr
        q_dof_pred: farr
        qd_minus: farr
        qd_free: farr
        tau_explicit: farr
        # limits (candidates, before compaction)
        lim_side: farr
        lim_active: iarr
        lim_bias: farr
        # contacts of this step (capacity slots) and narrow-phase candidates
        cand_pos: v3
        cand_normal: v3
        cand_dist: farr
        cand_valid: iarr
        ct_pair: iarr
        ct_body_a: iarr
        ct_body_b: iarr
        ct_pos: v3
        ct_normal: v3
        ct_dist: farr
        ct_mu: farr
        ct_restitution: farr
        ct_found: iarr  # number of active contacts found (may exceed capacity) per world
        # constraint rows (segment of maxdim rows per world)
        row_body: iarr  # [rows * nblk]
        row_J: v6
        row_info: iarr  # family, source, limit sign and saturation flag, packed (ROW_SRC_BITS)
        vstar: farr
        reg: farr  # R (joint-dynamics regularisation)
        lo: farr  # impulse bounds; ``solver.scale`` divides them by P in place (``lo_s``/``hi_s`` alias them)
        hi: farr
        f0: farr  # warm-start force (lambda/dt); the same array as ``impulse`` (see :func:`allocate`)
        v0: farr  # warm-start velocity; the same array as ``velocity``
        # per world row counts
        n_lim: iarr
        n_con: iarr
        n_box: iarr
        n_rows: iarr
        # dense Jacobian and Delassus
        Jd: farr
        MJd: farr
        D: farr
        # PADMM
        P: farr
        vt: farr
        lo_s: farr  # the scaled bounds: the same arrays as ``lo``, ``hi``
        hi_s: farr
        x: farr
        y: farr
        z: farr
        x_p: farr
        y_p: farr
        z_p: farr
        y_hat: farr
        z_hat: farr
        e_p: farr  # the free rows' dual residual vector of the previous iteration (the null-direction test)
        impulse: farr
        velocity: farr
        a_p: farr  # per world
        c_p: farr
        iters: iarr
        it_cap: iarr  # per world: iteration count at which the current PADMM phase stops
        r_p: farr
        r_d: farr
        r_c: farr
        rho_u: farr  # per world: the penalty of the limit and contact rows (persists from step to step)
        k_rho: iarr  # per world: the iteration of the last penalty change
        p_ref: farr  # per world: the largest P of the active rows (the residuals' velocity scale)
        sdiag: farr  # [rows] the dense factor's diagonal of the tail rows' Schur complement (refactorisation on a
        # new penalty); empty on the sparse factor's paths, which keep it in a column of the tail rows (linear_solve)
        pending: iarr  # per world: a row saturated in the last iteration; the factor is redone before the next
        converged: iarr
        reproject: iarr  # per world: the passes left an anchor gap open (post-stabilisation's extra pass)
        done: iarr  # per world: 1 once converged or at the iteration cap
        remaining: iarr  # [1] worlds still iterating (the capture_while condition)
        # Conjugate Residual scratch
        cr_r: farr
        cr_p: farr
        cr_Ap: farr
        cr_Ar: farr
        cr_w: v6  # [bodies] M^-1 J^T P x (the Conjugate Residual operator)
        cr_ent: iarr  # [rows * nblk] the row blocks grouped by body (solver_lanes.cr_pattern; 32-thread schedule)
        cr_end: iarr  # [bodies] where each body's row blocks end in cr_ent
        # results
        q_new: wp.array(dtype=transform)
        u_new: v6
        failed: iarr  # per world: this step failed (non-finite) or the world is frozen
        unconverged: iarr  # per world: consecutive steps whose PADMM did not converge (persistent)
        frozen: iarr  # per world: failed earlier, kept at its state until the caller resets it (persistent)

    return Work


@functools.cache
def pattern_struct(np_dtype):
    """The Warp struct of the factor patterns (shared by worlds of one type) and the factor's values."""
    scalar = types_of(np_dtype).scalar
    iarr = wp.array(dtype=wp.int32)

    @wp.struct
    class Pattern:
        # per world: where its type's pattern starts in the arrays below
        perm_start: iarr  # into perm and row_ptr (row_ptr has one more per type: at perm_start + type index)
        ptr_start: iarr
        ent_start: iarr  # into col, row, div, upd_ptr
        nnz: iarr
        n_fixed: iarr  # the fixed rows (the first tail row's index)
        # positions of L_f: the fixed rows, then 6 per hub (their unknowns; n_pos = n_fixed without hubs)
        n_pos: iarr
        # hubs (symbolic): body_hub[b] = hub index of global body b in its world, or -1; a world's hubs are the global
        # bodies hub_body[hub_start[wid] ..], in position order
        body_hub: iarr
        hub_start: iarr
        hub_body: iarr
        perm: iarr
        row_ptr: iarr  # world-type-local entry indices
        col: iarr
        colrow: iarr
        row: iarr
        div: iarr
        upd_ptr: iarr  # [2 nnz]: (start, end) of each entry's update pairs in upd_a / upd_b
        upd_a: iarr  # world-type-local entry indices
        upd_b: iarr
        # by columns (Symbolic.cptr ...): cptr like row_ptr, cent / crow like col, fan_ptr like row_ptr with global
        # indices into fan_tgt / fan_a / fan_b (whose values are world-type-local entry indices)
        cptr: iarr
        cent: iarr
        crow: iarr
        fan_ptr: iarr
        fan_tgt: iarr
        fan_a: iarr
        fan_b: iarr
        # per group of 32 worlds: the value storage, interleaved over the group's worlds (val_stride = GROUP: the
        # one-thread-per-world kernels read a row of 32 worlds at once) or world after world (val_stride = 1: the
        # 32 threads of one world read consecutive entries, solver_lanes.py); grp_nnz: the group's entries per world
        grp_val_start: iarr
        grp_nnz: iarr
        val_stride: int
        grp_tail_start: iarr
        # the tail rows: entry (t, c) of a world at tail + t stride + c tail_stride, interleaved over the group's
        # worlds like val (tail_stride = GROUP, stride = GROUP * dim) or world after world (tail_stride = 1,
        # stride = dim: solver_lanes.py's threads read consecutive entries of a row); grp_tail_size: the group's
        # entries per world
        tail_stride: int
        grp_tail_size: iarr
        grp_tail_k: iarr  # per group: K, the stored entries of a tail row's L_tf (its tail columns start there)
        grp_tail_dim: iarr  # per group: K + the tail rows, the entries of a tail row
        # the L_tf patterns of all world types (tail_patterns), by global pattern id: pattern P's entries are
        # pat_ptr[P] .. pat_ptr[P + 1] - 1 of pat_pos (fixed positions, ascending) and pat_row (their rows, perm[pos])
        pat_ptr: iarr
        pat_pos: iarr
        pat_row: iarr
        # L_tf's forward substitution: entry i of a pattern subtracts L_pk l_j for the pairs u in
        # pat_upd_ptr[i] .. pat_upd_ptr[i + 1] - 1: k = pat_upd_k[u] (entry of L_f, world-type-local) and j =
        # pat_upd_j[u] (the compressed index of column col[k] in the pattern; columns outside it hold zeros)
        pat_upd_ptr: iarr
        pat_upd_k: iarr
        pat_upd_j: iarr
        # pattern P's lookup: pat_lut[P pat_lut_stride + p] = compressed index of fixed position p, or -1 (one stride,
        # the most fixed rows of any world type, so the solve finds a row's lookup from its pattern id without a load)
        pat_lut_stride: int
        pat_lut: iarr
        dof_pat: iarr  # [num_dofs] the pattern of a limit row on DoF d (global pattern id; -1: no limit)
        con_pat: iarr  # [W] the pattern of the world's first contact pair (-1: none); pair k's is con_pat + k
        tail_max: int  # tail rows per world in tail_pat
        tail_pat: iarr  # [W tail_max] the pattern of each tail row, set by tail_row at assembly
        val: wp.array(dtype=scalar)  # the fixed rows' factor
        tail: wp.array(dtype=scalar)  # the tail rows (fixed positions, then tail columns)
        # L_f^-1 on its pattern (linear_solve_pattern.InversePattern; only when built with ``inverse``): icol_ptr and
        # irow_ptr like row_ptr (per type, type-local slots), the slot tables from inv_ent_start[wid], cup like cent;
        # a world's values are inv[inv_start[wid] + slot]
        inv_ent_start: iarr
        inv_start: iarr
        icol_ptr: iarr
        ipath_row: iarr
        irow_ptr: iarr
        irow_slot: iarr
        irow_col: iarr
        cup: iarr
        inv: wp.array(dtype=scalar)

    return Pattern


@dataclasses.dataclass(frozen=True)
class BuilderTypes(Types):
    """What a kernel builder of one precision closes over: the :class:`~kamino.warp_backend.types.Types`, the
    structs the kernels take (the model ``M``, the sparse factor's pattern ``SP``) and the precision's ``inf``."""

    M: type
    SP: type
    inf: object

    def take(self, *names: str) -> tuple:
        """The entries ``names``, in order, for a builder's one-line preamble
        (``scalar, M = builder_types(np_dtype).take("scalar", "M")``)."""
        fields = [f.name for f in dataclasses.fields(self)]
        unknown = [n for n in names if n not in fields]
        if unknown:
            raise ValueError(f"BuilderTypes.take: unknown entries {unknown}; the entries are {fields}")
        return tuple(getattr(self, n) for n in names)


@functools.cache
def builder_types(np_dtype) -> BuilderTypes:
    """The :class:`BuilderTypes` of ``float32`` or ``float64``, which every kernel builder reads its types, structs
    and ``inf`` from (cached per precision, so the builders of a precision close over the same objects)."""
    T = types_of(np_dtype)
    fields = {f.name: getattr(T, f.name) for f in dataclasses.fields(T)}
    return BuilderTypes(**fields, M=model_struct(np_dtype), SP=pattern_struct(np_dtype), inf=T.scalar(wp.inf))


def allocate(wm: WarpModel, euler: bool, dense: bool, delassus: bool = True, rows_per_world: bool = False,
             cr: bool = False):
    """A zero-initialised :func:`work_struct` for ``wm`` (``q_eval`` aliases ``q`` for Euler); ``dense``: the
    dense per-world Jacobian, ``delassus``: the dense Delassus matrix (not needed by CR or the sparse factor);
    ``rows_per_world``: each world's rows contiguous (``Work.row_stride = 1``) instead of interleaved; ``cr``: the
    Conjugate Residual solve's scratch (``cr_*``; empty for the LLT paths, which never read it), with the row blocks
    grouped by body (``cr_ent``, ``cr_end``) where ``rows_per_world`` (the 32-thread schedule's operator)."""
    T = types_of(wm.np_dtype)
    m = wm.model
    dev = wm.device
    W = work_struct(wm.np_dtype)()
    B, D, C, K, cap = m.num_bodies, m.num_dofs, m.num_constraints, m.num_couplings, m.num_contacts
    R, nblk = wm.total_rows, wm.blocks_per_row
    L = int(np.sum(wm_lim_counts(wm)))
    if max(D, C, K, cap) > ROW_SRC_MASK + 1:
        raise ValueError(f"Warp backend: the batch has {max(D, C, K, cap):,} DoFs, constraints, couplings or contact "
                         f"slots over all worlds, more than the {ROW_SRC_MASK + 1:,} a row's source index can hold "
                         f"(Work.row_info, ROW_SRC_BITS = {ROW_SRC_BITS}); split the batch into fewer worlds")
    sizes = {
        "q": (B, T.transform), "u": (B, T.vec6), "time": (m.num_worlds, T.scalar),
        "kin_force": (C, T.scalar), "cpl_force": (K, T.scalar), "act_force": (D, T.scalar), "pas_force": (D, T.scalar),
        "lim_force": (D, T.scalar), "con_pair": (cap, wp.int32), "con_pos": (cap, T.vec3), "con_normal": (cap, T.vec3),
        "con_dist": (cap, T.scalar), "con_force": (cap, T.vec3), "con_velocity": (cap, T.vec3),
        "con_point_b": (cap, T.vec3), "effort": (D, T.scalar), "position_target": (D, T.scalar),
        "velocity_target": (D, T.scalar), "wrench": (B, T.vec6),
        "q_pred": (B, T.transform), "u_f": (B, T.vec6), "inertia_w": (B, T.mat33),
        "inv_inertia_w": (B, T.mat33), "body_impulse": (B, T.vec6),
        "dof_JF": (D, T.vec6), "dof_JB": (D, T.vec6), "q_dof": (D, T.scalar), "q_dof_pred": (D, T.scalar),
        "qd_minus": (D, T.scalar), "qd_free": (D, T.scalar), "tau_explicit": (D, T.scalar),
        "lim_side": (L, T.scalar), "lim_active": (L, wp.int32), "lim_bias": (L, T.scalar),
        "cand_pos": (wm.total_cand, T.vec3), "cand_normal": (wm.total_cand, T.vec3),
        "cand_dist": (wm.total_cand, T.scalar), "cand_valid": (wm.total_cand, wp.int32),
        "ct_pair": (cap, wp.int32), "ct_body_a": (cap, wp.int32), "ct_body_b": (cap, wp.int32),
        "ct_pos": (cap, T.vec3), "ct_normal": (cap, T.vec3), "ct_dist": (cap, T.scalar), "ct_mu": (cap, T.scalar),
        "ct_restitution": (cap, T.scalar), "ct_found": (m.num_worlds, wp.int32),
        "row_body": (R * nblk, wp.int32), "row_J": (R * nblk, T.vec6),
        "row_info": (R, wp.int32),
        "Jd": (wm.total_jd if dense else 0, T.scalar), "MJd": (wm.total_jd if dense else 0, T.scalar),
        "D": (wm.total_mat if delassus else 0, T.scalar), "sdiag": (R if delassus else 0, T.scalar),
        "cr_w": (B if cr else 0, T.vec6), "cr_ent": (R * nblk if cr and rows_per_world else 0, wp.int32),
        "cr_end": (B if cr and rows_per_world else 0, wp.int32), "q_new": (B, T.transform), "u_new": (B, T.vec6),
    }
    for name in ("vstar", "reg", "lo", "hi", "P", "vt", "x", "y", "z", "x_p", "y_p", "z_p", "y_hat",
                 "z_hat", "e_p", "impulse", "velocity"):
        sizes[name] = (R, T.scalar)
    for name in ("cr_r", "cr_p", "cr_Ap", "cr_Ar"):
        sizes[name] = (R if cr else 0, T.scalar)
    for name in ("a_p", "c_p", "r_p", "r_d", "r_c", "rho_u", "p_ref"):
        sizes[name] = (m.num_worlds, T.scalar)
    for name in ("n_lim", "n_con", "n_box", "n_rows", "iters", "it_cap", "converged", "reproject", "done", "failed",
                 "k_rho", "unconverged", "frozen", "pending"):
        sizes[name] = (m.num_worlds, wp.int32)
    sizes["remaining"] = (1, wp.int32)
    for name, (n, dtype) in sizes.items():
        setattr(W, name, wp.zeros(max(n, 0), dtype=dtype, device=dev))
    # Per-row vectors: 22 names, 18 allocations. Those whose lives do not overlap share storage:
    # the warm start (``f0``, ``v0``) is written by the row assembly and read by ``solver.scale`` and ``padmm_init``;
    # the solve's ``impulse`` and ``velocity`` are written by ``padmm_finish``, after both, and read until the step
    # ends. ``solver.scale`` is the only reader of the unscaled bounds and divides them by ``P`` in place, once per
    # step; everything after it reads the scaled ones. Six vectors are not stored, their information being elsewhere,
    # bit for bit: the row family, source, limit sign and saturation flag are packed in ``row_info`` (4 -> 1); a
    # contact row's friction is its slot's ``ct_mu`` (``mu``); ``prebake`` writes ``v_f`` into ``vt``, which
    # ``scale`` scales in place, and ``rows.set_bias`` recomputes it with the same sums (``vf``); the diagonal of the
    # tail's Schur complement is a column of the sparse tail (``sdiag``, allocated only for the dense factor).
    W.f0, W.v0 = W.impulse, W.velocity
    W.lo_s, W.hi_s = W.lo, W.hi
    W.row_stride = 1 if rows_per_world else GROUP
    W.con_pair.fill_(-1)
    W.q_eval = W.q if euler else wp.zeros(B, dtype=T.transform, device=dev)
    return W


def wm_lim_counts(wm: WarpModel) -> np.ndarray:
    return wm.arrays.lim_count.numpy()
