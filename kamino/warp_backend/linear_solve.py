"""Sparse Cholesky of the scaled Delassus matrix (docs/formulation.md §8.1) with a static pattern.

The always-active rows of a world (joint-dynamics, joint and coupling rows: the first ``n_fixed``) touch
fixed pairs of bodies, so the sparsity of ``D~ = P J M^-1 J^T P + (eta + rho) I`` on them is known when the
model is built: rows ``a`` and ``b`` couple only when they share a moving body. The host orders those rows
by minimum degree (fewest fill-ins first; a tree is factorised without fill, a ladder of loops with a
little), computes the pattern of the factor ``L`` and, for every entry, the list of products its update
needs (``L_pq = (D~_pq - sum_r L_pr L_qr) / L_qq``, ``r`` over the columns the rows ``p`` and ``q``
share). On the device, a world's thread factorises by walking that list — no searches, no branches on
values — and the PADMM iterations solve with the sparse factor.

The rows that change from step to step (active limits, contacts; their bodies are only known at run
time) form a *tail*: ``L = [[L_f, 0], [L_tf, L_t]]`` with ``L_tf = D~_tf L_f^-T`` (sparse forward
substitutions) and ``L_t = chol(D~_t - L_tf L_tf^T)``, dense. A tail row's ``L_tf`` can be nonzero only on the
fixed positions its bodies' rows reach up the elimination tree of ``L_f`` (the reach of a sparse triangular
solve), known when the model is built: a limit row's from its joint's bodies, a contact row's from its pair's.
Limits and contacts are packed, so a tail slot may hold any of them: each tail row is stored as ``K`` entries (the
world's widest pattern), then its tail columns, and the row's pattern is chosen at run time from its source
(:func:`tail_patterns`). Stored values and sums are those of the dense rows with their
exact zeros left out. The rows are interleaved over groups of 32 worlds like the other row data.

Measured on ladder8 (144 fixed rows): 1688 factor entries instead of 10440 for the dense factor, 18k
multiply-adds to factorise instead of 498k (docs/warp_backend.md, "Sparse factor").
"""

import dataclasses
import functools
from types import SimpleNamespace

import numpy as np
import warp as wp

from kamino.model import Model
from kamino.tables import prefix, row_tables
from kamino.warp_backend.indexing import index_funcs
from kamino.warp_backend.linear_solve_pattern import (
    HUB_MIN_ROWS,
    FixedRowTypes,
    Symbolic,
    all_tail_row_bodies,
    fixed_row_types,
    hub_bodies,
    inverse_pattern,
    segments,
    symbolic,
    tail_patterns,
)
from kamino.warp_backend.model_data import GROUP, group_sizes
from kamino.warp_backend.rows import ROW_LIMIT
from kamino.warp_backend.spatial import spatial_funcs
from kamino.warp_backend.types import types_of
from kamino.warp_backend.workspace import builder_types, pattern_struct

# --- host: symbolic analysis ---------------------------------------------------------------------------
#
# Everything here that depends on a world's structure runs once per distinct structure, not once per world: worlds
# made by ``kamino.replicate`` (or a few robot types put together by ``kamino.concat``) share a handful. The per-world
# work is numpy over all worlds at once (the tables below), or one dictionary look-up per world.

#: The 32-thread PADMM iterations solve with ``L_f^-1`` (``build(inverse=True)``) when every world type's inverse has
#: at most this many times the entries of its ``L_f``: then its two products read about what the sweeps read, with
#: two barriers instead of two per row. Measured on an H200 (4096 worlds, float32, defaults, benchmarks/README.md):
#: the four-bar (inverse 1.17x its factor's entries) steps 13 % faster under the gentle load and 18 % under rl;
#: dr_legs (2.8x; 141,000 updates to invert against the factor's 30,000) 39 % and 19 % slower, ladder8 (5.6x) and olaf
#: (4.3x) slower too.
INVERSE_MAX_FILL = 1.5


@dataclasses.dataclass(frozen=True, eq=False)
class SparseFactor:
    """A model's factor patterns and value storage on one device."""

    arrays: object  # Pattern
    max_nnz: int
    max_tail: int
    nnz_total: int  # factor entries summed over worlds (fixed rows)
    hubs: int = 0  # hubs summed over worlds
    inv_total: int = 0  # entries of L_f^-1 summed over worlds (0: built without ``inverse``)


def pattern_tables(sym: Symbolic, pattern: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """For one ``L_tf`` pattern (fixed positions, ascending) of a world type with factor pattern ``sym``: the
    forward substitution's pairs, ``(ptr [len + 1], k, j)`` (for entry ``i`` at position ``p``, each entry ``k`` of
    row ``p`` of ``L_f`` before its diagonal whose column lies in the pattern, at compressed index ``j``; ascending
    ``k``, the dense loop's order), and the lookup ``[n]``: compressed index of each fixed position, or -1."""
    lut = np.full(len(sym.perm), -1, np.int64)
    lut[pattern] = np.arange(len(pattern))
    ks = [np.arange(sym.row_ptr[p], sym.row_ptr[p + 1] - 1) for p in pattern]
    ks = [k[lut[sym.col[k]] >= 0] for k in ks]
    ptr = np.concatenate([[0], np.cumsum([len(k) for k in ks], dtype=np.int64)]).astype(np.int64)
    k = np.concatenate(ks).astype(np.int64) if ks else np.zeros(0, np.int64)
    return ptr, k, lut[sym.col[k]], lut


def world_types(model: Model, tab, ft: FixedRowTypes, tail_rows: np.ndarray, h0: np.ndarray,
                hub_min_rows: int | None) -> tuple[np.ndarray, list[Symbolic], list[list[np.ndarray]]]:
    """The world types of :func:`build`: ``(world_type [W], the factor pattern of each type, its L_tf patterns)``.

    A type is the fixed rows' bodies (``ft``, :func:`fixed_row_types`), with tail rows (``tail_rows > 0``) the tail
    rows' bodies (:func:`tail_row_bodies`), and with hubs the first virtual row ``h0`` of the world; types are
    numbered in order of first appearance. :func:`hub_bodies` runs once per fixed-row structure, :func:`symbolic` once
    per structure and ``h0``, :func:`tail_patterns` once per type; per world there is one dictionary look-up."""
    hubs = [hub_bodies(r, hub_min_rows) for r in ft.rows]
    tails = all_tail_row_bodies(model, tab) if (tail_rows > 0).any() else []
    no_tail = (np.zeros((0, 2), np.int64), None)
    types: dict[tuple, int] = {}
    by_structure: dict[tuple[int, int | None], Symbolic] = {}
    syms: list[Symbolic] = []
    pats: list[list[np.ndarray]] = []
    world_type = np.empty(model.num_worlds, np.int64)
    for w in range(model.num_worlds):
        f = int(ft.world_type[w])
        lim, con = tails[w] if tail_rows[w] > 0 else no_tail
        row0 = int(h0[w]) if len(hubs[f]) else None  # the hubs' virtual rows: part of the type only with hubs
        key = (f, lim.tobytes(), None if con is None else con.tobytes(), row0)
        t = types.get(key)
        if t is None:
            t = types[key] = len(syms)
            if (f, row0) not in by_structure:
                by_structure[f, row0] = symbolic(ft.rows[f], hubs[f], int(h0[w]))
            syms.append(by_structure[f, row0])
            pats.append(tail_patterns(ft.rows[f], syms[-1], lim, con) if tail_rows[w] > 0 else [])
        world_type[w] = t
    return world_type, syms, pats


def _hub_tables(model: Model, world_type: np.ndarray, syms: list[Symbolic]) -> tuple[np.ndarray, np.ndarray,
                                                                                       np.ndarray]:
    """Every world's hubs: ``(hub_body, hub_n, body_hub)``, the hubs as global bodies world after world (each world's
    in its type's position order), each world's count, and per global body its hub index in its world or -1."""
    hub_n_t = np.array([len(s.hubs) for s in syms], np.int64)
    hub0_t = prefix(hub_n_t)
    hub_n = hub_n_t[world_type]
    hubs_t = np.concatenate([s.hubs for s in syms]) if syms else np.zeros(0, np.int64)
    k = segments(hub0_t[world_type], hub_n)  # into hubs_t
    hub_body = hubs_t[k] + np.repeat(np.asarray(model.world_body_start, np.int64), hub_n)
    body_hub = np.full(max(model.num_bodies, 1), -1, np.int64)
    body_hub[hub_body] = k - np.repeat(hub0_t[world_type], hub_n)
    return hub_body, hub_n, body_hub


def _tail_pattern_ids(model: Model, tab, world_type: np.ndarray, pats: list[list[np.ndarray]],
                      pat0_t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The global ``L_tf`` pattern ids of :func:`build`: ``dof_pat`` (per DoF, its limit row's; -1: none) and
    ``con_pat`` (per world, its first contact pair's; -1: none), type ``t``'s patterns being ``pat0_t[t] ..``: a
    world's limited DoFs first, in order, then its pairs."""
    W = model.num_worlds
    n_pat = np.array([len(p) for p in pats], np.int64)[world_type]
    n_lim = np.asarray(tab.world_lim_count, np.int64)
    lim_world = np.repeat(np.arange(W), n_lim)
    k = np.arange(len(lim_world)) - np.repeat(prefix(n_lim), n_lim)  # each limit's index in its world
    on = (n_pat > 0)[lim_world]  # worlds whose type has patterns (tail rows)
    dof_pat = np.full(max(len(tab.dof_joint), 1), -1, np.int64)
    dof_pat[np.asarray(tab.lim_dof)[:len(lim_world)][on]] = pat0_t[world_type[lim_world[on]]] + k[on]
    con_pat = np.full(W, -1, np.int64)
    has_con = n_pat > n_lim
    con_pat[has_con] = pat0_t[world_type[has_con]] + n_lim[has_con]
    return dof_pat, con_pat


def build(model: Model, np_dtype, device, row_maxdim: np.ndarray, *, per_world: bool = False, fan: bool | None = None,
          hub_min_rows: int | None = HUB_MIN_ROWS, hub_row0: np.ndarray | None = None,
          inverse: bool = False) -> SparseFactor:
    """Symbolic analysis of every world type of ``model`` and the device storage of the factors (``per_world``: each
    world's values contiguous, for the 32-threads-per-world schedule; else interleaved over groups of worlds). A
    world type is the fixed rows' bodies and its tail rows' (:func:`tail_row_bodies`). ``row_maxdim``: the rows each
    world factorises (its tail rows are those after the fixed ones). ``hub_min_rows``: the hub threshold
    (:func:`hub_bodies`; ``None``: no hubs); a hub's unknowns use the world's virtual rows from ``hub_row0`` (the
    world's row capacity, ``model_data``; default ``row_maxdim``). ``inverse`` (with ``per_world``): the pattern and
    storage of ``L_f^-1`` too (``linear_solve_pattern.inverse_pattern``; the 32-thread iterations solve with it).

    Only the tables the kernels read are uploaded; the others hold a single 0. The update lists: ``fan`` (default
    ``per_world``), the column-order triples ``fan_*`` of ``solver_lanes.factor``; else the row-order pairs ``upd_*``
    of the one-thread kernels (:func:`factor`, ``refactor``, ``factor_fixed``; post-stabilisation's Gauss-Newton
    factor is built with ``fan=False`` under either schedule). The column index ``cptr``, ``cent``, ``crow`` is read
    by the 32-thread kernels only (``per_world``). Both lists of a type are as long as its fill-in updates (the
    animatronic's: 132,568 entries, 0.5 MB each)."""
    W = model.num_worlds
    tab = row_tables(model)
    ft = fixed_row_types(model)
    tail_rows = np.asarray(row_maxdim, np.int64) - ft.n_fixed if W else np.zeros(0, np.int64)
    h0 = np.asarray(row_maxdim if hub_row0 is None else hub_row0, np.int64).reshape(-1)
    world_type, syms, pats = world_types(model, tab, ft, tail_rows, h0, hub_min_rows)
    n_t = np.array([len(s.perm) for s in syms], np.int64)
    nnz_t = np.array([s.nnz for s in syms], np.int64)
    upd_t = np.array([len(s.upd_a) for s in syms], np.int64)
    perm_t, ptr_t, ent_t, upd0_t = prefix(n_t), prefix(n_t + 1), prefix(nnz_t), prefix(upd_t)
    cat = lambda f: np.concatenate([f(s) for s in syms]) if syms else np.zeros(0, np.int64)  # noqa: E731
    n_fixed = np.array([s.n_real for s in syms], np.int64)[world_type]
    nnz = nnz_t[world_type]
    # the L_tf patterns, by global id: type t's are pat0_t .. pat0_t + len(pats[t]) - 1
    pat0_t = prefix(np.array([len(p) for p in pats], np.int64))
    flat = [(s, p) for s, ps in zip(syms, pats, strict=True) for p in ps]
    tables = [pattern_tables(s, p) for s, p in flat]
    lens = np.array([len(p) for _, p in flat], np.int64)
    k_t = np.array([max((len(p) for p in ps), default=0) for ps in pats], np.int64)
    K = k_t[world_type]
    g_nnz, g_tail, g_k = group_sizes(nnz), group_sizes(tail_rows), group_sizes(K)
    g_dim = g_k + g_tail + (g_tail > 0)  # the last column: the diagonal of the tail's Schur complement (sdiag_col)
    S = pattern_struct(np.dtype(np_dtype))()

    def i32(a):
        return wp.array(np.asarray(a, np.int32).reshape(-1), dtype=wp.int32, device=device)

    S.perm_start, S.ptr_start, S.ent_start = i32(perm_t[world_type]), i32(ptr_t[world_type]), i32(ent_t[world_type])
    S.nnz, S.n_fixed, S.n_pos = i32(nnz), i32(n_fixed), i32(n_t[world_type])
    hub_body, hub_n, body_hub = _hub_tables(model, world_type, syms)
    S.body_hub, S.hub_start = i32(body_hub), i32(prefix(hub_n))
    S.hub_body = i32(hub_body if hub_n.sum() else [0])
    S.perm, S.row_ptr, S.col, S.colrow, S.row, S.div = (i32(cat(lambda s, f=f: getattr(s, f)))
                                              for f in ("perm", "row_ptr", "col", "colrow", "row", "div"))
    fan = per_world if fan is None else fan
    unread = [0]  # a table no kernel of this schedule reads
    # (start, end) of each entry's update pairs, as global indices into upd_a / upd_b
    S.upd_ptr = i32(np.concatenate([np.stack([s.upd_ptr[:-1], s.upd_ptr[1:]], axis=1) + o
                                    for s, o in zip(syms, upd0_t, strict=True)]) if syms and not fan else unread)
    S.upd_a, S.upd_b = (i32(unread if fan else cat(lambda s, f=f: getattr(s, f))) for f in ("upd_a", "upd_b"))
    S.cptr, S.cent, S.crow = (i32(cat(lambda s, f=f: getattr(s, f)) if per_world else unread)
                              for f in ("cptr", "cent", "crow"))
    S.fan_ptr = i32(np.concatenate([s.fan_ptr + o for s, o in zip(syms, upd0_t, strict=True)]) if syms and fan
                    else unread)
    # one trailing 0 each, so that solver_lanes.factor's clamped batch loads have an entry to read in any model
    S.fan_tgt, S.fan_a, S.fan_b = (i32(np.append(cat(lambda s, f=f: getattr(s, f)), 0) if fan else unread)
                                   for f in ("fan_tgt", "fan_a", "fan_b"))
    S.grp_val_start = i32(prefix(GROUP * g_nnz))
    S.grp_nnz = i32(g_nnz)
    S.val_stride = 1 if per_world else GROUP
    S.grp_tail_start = i32(prefix(GROUP * g_tail * g_dim))
    S.tail_stride = 1 if per_world else GROUP
    S.grp_tail_size = i32(g_tail * g_dim)
    S.grp_tail_k = i32(g_k)
    S.grp_tail_dim = i32(g_dim)
    S.pat_ptr = i32(np.append(prefix(lens), lens.sum()))
    S.pat_pos = i32(np.concatenate([p for _, p in flat]) if flat else [])
    S.pat_row = i32(np.concatenate([s.perm[p] for s, p in flat]) if flat else [])
    n_upd = np.array([len(t[1]) for t in tables], np.int64)
    S.pat_upd_ptr = i32(np.append(np.concatenate([t[0][:-1] + o for t, o in zip(tables, prefix(n_upd), strict=True)])
                                  if flat else np.zeros(0, np.int64), n_upd.sum()))
    # one trailing 0 each, for solver_lanes.factor's clamped batch loads
    S.pat_upd_k = i32(np.append(np.concatenate([t[1] for t in tables]) if flat else [], 0))
    S.pat_upd_j = i32(np.append(np.concatenate([t[2] for t in tables]) if flat else [], 0))
    S.pat_lut_stride = max(int(n_t.max()) if len(n_t) else 0, 1)
    S.pat_lut = i32(np.concatenate([np.pad(t[3], (0, S.pat_lut_stride - len(t[3])), constant_values=-1)
                                    for t in tables]) if flat else [])
    dof_pat, con_pat = _tail_pattern_ids(model, tab, world_type, pats, pat0_t)
    S.dof_pat = i32(dof_pat if (dof_pat >= 0).any() else dof_pat[:1])  # read only on limit rows
    S.con_pat = i32(con_pat)
    mx = lambda a: int(a.max()) if len(a) else 0  # noqa: E731
    S.tail_max = max(mx(tail_rows), 1)
    S.tail_pat = wp.zeros(W * S.tail_max, dtype=wp.int32, device=device)
    scalar = types_of(np.dtype(np_dtype)).scalar
    S.val = wp.zeros(int(GROUP * g_nnz.sum()), dtype=scalar, device=device)
    S.tail = wp.zeros(int(GROUP * (g_tail * g_dim).sum()), dtype=scalar, device=device)
    invs = [inverse_pattern(s) for s in syms] if inverse and per_world else []
    if invs and any(ip.nnz > INVERSE_MAX_FILL * s.nnz for ip, s in zip(invs, syms, strict=True)):
        invs = []
    ni_t = np.array([ip.nnz for ip in invs], np.int64)
    ni = ni_t[world_type] if invs else np.zeros(0, np.int64)
    icat = lambda f: np.concatenate([getattr(ip, f) for ip in invs])  # noqa: E731
    S.inv_ent_start = i32(prefix(ni_t)[world_type] if invs else unread)
    S.inv_start = i32(prefix(ni) if invs else unread)
    S.icol_ptr, S.irow_ptr = (i32(icat(f) if invs else unread) for f in ("icol_ptr", "irow_ptr"))
    S.ipath_row, S.irow_slot, S.irow_col, S.cup = (i32(icat(f) if invs else unread)
                                                   for f in ("ipath_row", "irow_slot", "irow_col", "cup"))
    S.inv = wp.zeros(max(int(ni.sum()), 1), dtype=scalar, device=device)
    return SparseFactor(arrays=S, max_nnz=mx(nnz), max_tail=mx(tail_rows), nnz_total=int(nnz.sum()),
                        hubs=int(hub_n.sum()), inv_total=int(ni.sum()))


def empty(np_dtype, device) -> object:
    """A pattern struct with no worlds (the argument of kernels that take the dense or CR path)."""
    S = pattern_struct(np.dtype(np_dtype))()
    scalar = builder_types(np_dtype).scalar
    for name in ("perm_start", "ptr_start", "ent_start", "nnz", "n_fixed", "n_pos", "body_hub", "hub_start",
                 "hub_body", "perm", "row_ptr", "col", "colrow", "row",
                 "div", "upd_ptr", "upd_a", "upd_b", "cptr", "cent", "crow", "fan_ptr", "fan_tgt", "fan_a", "fan_b",
                 "grp_val_start", "grp_nnz", "grp_tail_start", "grp_tail_size", "grp_tail_k", "grp_tail_dim",
                 "pat_ptr", "pat_pos",
                 "pat_row", "pat_upd_ptr", "pat_upd_k", "pat_upd_j", "pat_lut", "dof_pat", "con_pat",
                 "tail_pat", "inv_ent_start", "inv_start", "icol_ptr", "ipath_row", "irow_ptr", "irow_slot",
                 "irow_col", "cup"):
        setattr(S, name, wp.zeros(0, dtype=wp.int32, device=device))
    S.val_stride = GROUP
    S.tail_stride = GROUP
    S.tail_max = 1
    S.pat_lut_stride = 1
    S.val = wp.zeros(0, dtype=scalar, device=device)
    S.tail = wp.zeros(0, dtype=scalar, device=device)
    S.inv = wp.zeros(0, dtype=scalar, device=device)
    return S


# --- device: assembly, factorisation, solve ---------------------------------------------------------------
#
# Each kernel and each ``wp.func`` comes from its own builder, cached per precision (``np_dtype``);
# :func:`sparse_llt_kernels` names them all.

@functools.cache
def vidx_func(np_dtype):
    """The storage index of a factor entry (docs/formulation.md §8.1; the layout of :func:`build`)."""
    M, SP = builder_types(np_dtype).take("M", "SP")

    @wp.func
    def vidx(m: M, sp: SP, wid: int, k: int):
        """Storage index of factor entry ``k`` (world-type-local) of world ``wid``."""
        g = wid // GROUP
        lane = wid - g * GROUP
        if sp.val_stride == 1:
            return sp.grp_val_start[g] + lane * sp.grp_nnz[g] + k
        return sp.grp_val_start[g] + k * GROUP + lane

    return vidx


@functools.cache
def bases_func(np_dtype):
    """The hoisted storage starts of a world's rows, factor values and tail rows (§8.1)."""
    M, SP = builder_types(np_dtype).take("M", "SP")
    row_base = index_funcs(np_dtype).row_base

    @wp.func
    def bases(m: M, sp: SP, row_stride: int, wid: int):
        """Hoisted storage starts of world ``wid``: rows, factor values, tail rows, and the tail row stride
        (``ridx = rows + a row_stride``, ``vidx = vals + k sp.val_stride``, ``tidx = tail + t stride + c
        sp.tail_stride``; ``row_stride``: ``Work.row_stride``)."""
        g = wid // GROUP
        lane = wid - g * GROUP
        vb = sp.grp_val_start[g] + lane
        if sp.val_stride == 1:
            vb = sp.grp_val_start[g] + lane * sp.grp_nnz[g]
        if sp.tail_stride == 1:
            return wp.vec4i(row_base(m, row_stride, wid), vb, sp.grp_tail_start[g] + lane * sp.grp_tail_size[g],
                            sp.grp_tail_dim[g])
        return wp.vec4i(row_base(m, row_stride, wid), vb, sp.grp_tail_start[g] + lane, sp.grp_tail_dim[g] * GROUP)

    return bases


@functools.cache
def tail_k_func(np_dtype):
    """Where a tail row's tail columns start (§8.1)."""
    SP = builder_types(np_dtype).SP

    @wp.func
    def tail_k(sp: SP, wid: int):
        """Where the tail columns of a tail row of world ``wid`` start (after its ``K`` ``L_tf`` entries)."""
        return sp.grp_tail_k[wid // GROUP]

    return tail_k


@functools.cache
def sdiag_col_func(np_dtype):
    """The column that keeps the diagonal of the tail's Schur complement (§8.1)."""
    SP = builder_types(np_dtype).SP

    @wp.func
    def sdiag_col(sp: SP, wid: int):
        """The column of a tail row of world ``wid`` that keeps the diagonal of the tail's Schur complement ``S_t``
        (the last one, after the tail columns: the square's lower triangle holds ``L_t``, its upper ``S_t``)."""
        return sp.grp_tail_dim[wid // GROUP] - 1

    return sdiag_col


@functools.cache
def tidx_func(np_dtype):
    """The storage index of a tail-row entry (§8.1)."""
    M, SP = builder_types(np_dtype).take("M", "SP")
    bases = bases_func(np_dtype)

    @wp.func
    def tidx(m: M, sp: SP, row_stride: int, wid: int, t: int, c: int):
        """Storage index of entry ``c`` (``L_tf``'s compressed index below ``K``, then ``K`` + tail row index) of
        tail row ``t`` (the layout of :func:`bases`)."""
        base = bases(m, sp, row_stride, wid)
        return base[2] + t * base[3] + c * sp.tail_stride

    return tidx


@functools.cache
def tail_pattern_func(np_dtype):
    """A tail row's ``L_tf`` pattern (§8.1)."""
    SP = builder_types(np_dtype).SP

    @wp.func
    def tail_pattern(sp: SP, wid: int, t: int):
        """The ``L_tf`` pattern (global id) of tail row ``t`` of world ``wid``, as :func:`tail_row` recorded it."""
        return sp.tail_pat[wid * sp.tail_max + t]

    return tail_pattern


@functools.cache
def inv_mass_times_func(np_dtype):
    """``M_b^-1 J`` for a 1x6 block on one body (docs/formulation.md §1.3)."""
    vec6, mat33, M = builder_types(np_dtype).take("vec6", "mat33", "M")
    sf = spatial_funcs(np_dtype)

    @wp.func
    def inv_mass_times(m: M, inv_inertia_w: wp.array(dtype=mat33), b: int, J: vec6):
        """``M_b^-1 J`` for a 1x6 block (or a wrench) on body ``b``, from the model's inverse masses and the
        world-frame inverse inertias ``inv_inertia_w`` (``Work.inv_inertia_w``; ``spatial.inverse_mass_times``). The
        ``M^-1 J^T`` blocks are formed with it where they are read (the Delassus entries here, the dense ``M^-1 J^T``
        and the Conjugate Residual operator in ``solver.py``), not stored."""
        return sf.inverse_mass_times(m.inv_mass[b], inv_inertia_w[b], J)

    return inv_mass_times


@functools.cache
def delassus_term_func(np_dtype):
    """One body's share of a Delassus entry (docs/formulation.md §7.1)."""
    scalar, vec6, mat33, M = builder_types(np_dtype).take("scalar", "vec6", "mat33", "M")
    inv_mass_times = inv_mass_times_func(np_dtype)

    @wp.func
    def delassus_term(m: M, inv_inertia_w: wp.array(dtype=mat33), body: int, Ja: vec6, Jb: vec6):
        """One body's share of a Delassus entry, ``(J_a M^-1 J_b^T + J_b M^-1 J_a^T) / 2`` (docs/formulation.md
        §7.1; the JAX reference symmetrises ``D`` the same way, ``jax_ref.dynamics.delassus``). The rounding of the
        formed ``M^-1 J^T`` then enters as ``(J E^T + E J^T) / 2``, which vanishes on the null space of ``J^T``: the
        redundant rows of planar loops keep their eigenvalues of ``D`` at zero to the rounding of the sums. Taken
        from one side only, ``J_a (M^-1 J_b^T + E_b)``, it does not: on the eight-legged walker the scaled ``D``
        had eigenvalues down to -2.4e-6, and PADMM's proximal shift does not hold such a direction
        (docs/warp_backend.md, "Redundant planar loops in float32")."""
        half = scalar(0.5)
        return half * (wp.dot(Ja, inv_mass_times(m, inv_inertia_w, body, Jb))
                       + wp.dot(Jb, inv_mass_times(m, inv_inertia_w, body, Ja)))

    return delassus_term


@functools.cache
def delassus_sum_func(np_dtype):
    """``(J M^-1 J^T + R)_ab`` from the block-sparse rows (docs/formulation.md §7.1)."""
    scalar, vec6, mat33, M = builder_types(np_dtype).take("scalar", "vec6", "mat33", "M")
    ridx = index_funcs(np_dtype).ridx
    delassus_term = delassus_term_func(np_dtype)

    @wp.func
    def delassus_sum(m: M, row_stride: int, row_body: wp.array(dtype=wp.int32), row_J: wp.array(dtype=vec6),
                     reg: wp.array(dtype=scalar), inv_inertia_w: wp.array(dtype=mat33), wid: int, a: int, b: int,
                     nblk: int, body_hub: wp.array(dtype=wp.int32), skip_hubs: int):
        """``(J M^-1 J^T + R)_ab`` from the block-sparse rows (blocks meet on shared bodies; each meeting adds
        :func:`delassus_term`); with ``skip_hubs`` over the bodies that are not hubs (``body_hub[b] < 0``): ``D0 =
        sum_{b not a hub} J_b M_b^-1 J_b^T + R``, the hubs' share being in the factor through their unknowns
        (docs/warp_backend.md "Open problems"). The same sum, term for term, when no body is skipped."""
        ra = ridx(m, row_stride, wid, a)
        rb = ridx(m, row_stride, wid, b)
        s = scalar(0.0)
        for k in range(nblk):
            bk = row_body[ra * nblk + k]
            if bk >= 0:
                skip = False
                if skip_hubs != 0:
                    skip = body_hub[bk] >= 0
                if not skip:
                    for l in range(nblk):
                        if row_body[rb * nblk + l] == bk:
                            s += delassus_term(m, inv_inertia_w, bk, row_J[ra * nblk + k], row_J[rb * nblk + l])
        if a == b:
            s += reg[ra]
        return s

    return delassus_sum


@functools.cache
def delassus_entry_func(np_dtype):
    """``(J M^-1 J^T + R)_ab`` over every body (docs/formulation.md §7.1)."""
    scalar, vec6, mat33, M = builder_types(np_dtype).take("scalar", "vec6", "mat33", "M")
    delassus_sum = delassus_sum_func(np_dtype)

    @wp.func
    def delassus_entry(m: M, row_stride: int, row_body: wp.array(dtype=wp.int32), row_J: wp.array(dtype=vec6),
                       reg: wp.array(dtype=scalar), inv_inertia_w: wp.array(dtype=mat33), wid: int, a: int, b: int,
                       nblk: int):
        """``(J M^-1 J^T + R)_ab`` over every body (:func:`delassus_sum`; ``row_body`` stands in for the unread hub
        table)."""
        return delassus_sum(m, row_stride, row_body, row_J, reg, inv_inertia_w, wid, a, b, nblk, row_body, 0)

    return delassus_entry


@functools.cache
def delassus0_func(np_dtype):
    """``D0_ab``: the Delassus entry without the world's hubs (§7.1; docs/warp_backend.md "Open problems")."""
    scalar, vec6, mat33, M, SP = builder_types(np_dtype).take("scalar", "vec6", "mat33", "M", "SP")
    delassus_sum = delassus_sum_func(np_dtype)

    @wp.func
    def delassus0(m: M, sp: SP, row_stride: int, row_body: wp.array(dtype=wp.int32), row_J: wp.array(dtype=vec6),
                  reg: wp.array(dtype=scalar), inv_inertia_w: wp.array(dtype=mat33), wid: int, a: int, b: int,
                  nblk: int):
        """``D0_ab``: :func:`delassus_sum` without the world's hubs (every body in a world without hubs)."""
        return delassus_sum(m, row_stride, row_body, row_J, reg, inv_inertia_w, wid, a, b, nblk, sp.body_hub,
                            int(sp.n_pos[wid] != sp.n_fixed[wid]))

    return delassus0


@functools.cache
def row_on_body_func(np_dtype):
    """A row's blocks on one body, summed (§2.5)."""
    vec6 = builder_types(np_dtype).vec6

    @wp.func
    def row_on_body(row_body: wp.array(dtype=wp.int32), row_J: wp.array(dtype=vec6), r: int, body: int, nblk: int):
        """``J_a`` on body ``body``: the sum of row ``a``'s blocks there (``r``: the row's storage index)."""
        J = vec6()
        for l in range(nblk):
            if row_body[r * nblk + l] == body:
                J += row_J[r * nblk + l]
        return J

    return row_on_body


@functools.cache
def hub_entry_func(np_dtype):
    """An entry of the hub block rows of the quasi-definite system (docs/warp_backend.md "Open problems")."""
    scalar, vec6, mat33, M, SP = builder_types(np_dtype).take("scalar", "vec6", "mat33", "M", "SP")
    ridx = index_funcs(np_dtype).ridx
    row_on_body = row_on_body_func(np_dtype)

    @wp.func
    def hub_entry(m: M, sp: SP, row_stride: int, row_body: wp.array(dtype=wp.int32), row_J: wp.array(dtype=vec6),
                  P: wp.array(dtype=scalar), inertia_w: wp.array(dtype=mat33), wid: int, p: int, q: int, nblk: int):
        """Entry ``(p, q)``, ``q <= p``, of the hub block rows of the quasi-definite system (``p`` the hub position
        ``n_fixed + 6 h + c``: component ``c`` of hub ``h``): ``P_b (J_b on the hub)_c`` against fixed row ``b`` (at
        position ``q``), ``-M_h[c, c']`` against component ``c'`` of the same hub (``M_h = diag(m I, I_w)``, the
        body's spatial inertia in the world frame, in the ``(linear, angular)`` order of ``spatial.twist``), 0 against
        another hub. No shift, regularisation or scaling on the hubs' unknowns."""
        nf = sp.n_fixed[wid]
        j = p - nf
        h = j // 6
        c = j - 6 * h
        body = sp.hub_body[sp.hub_start[wid] + h]
        s = scalar(0.0)
        if q < nf:
            rb = ridx(m, row_stride, wid, sp.perm[sp.perm_start[wid] + q])
            s = P[rb] * row_on_body(row_body, row_J, rb, body, nblk)[c]
        elif (q - nf) // 6 == h:
            c2 = q - nf - 6 * h
            if c < 3 and c2 < 3:
                if c == c2:
                    s = -m.mass[body]
            elif c >= 3 and c2 >= 3:
                s = -inertia_w[body][c - 3, c2 - 3]
        return s

    return hub_entry


@functools.cache
def fixed_entry_func(np_dtype):
    """An entry of the fixed rows' scaled Delassus pattern, ``D~_pq`` (docs/formulation.md §8.1)."""
    scalar, vec6, mat33, M, SP = builder_types(np_dtype).take("scalar", "vec6", "mat33", "M", "SP")
    ix = index_funcs(np_dtype)
    ridx, row_saturated = ix.ridx, ix.row_saturated
    vidx, delassus0 = vidx_func(np_dtype), delassus0_func(np_dtype)
    hub_entry = hub_entry_func(np_dtype)

    @wp.func
    def fixed_entry(m: M, sp: SP, row_stride: int, row_body: wp.array(dtype=wp.int32), row_J: wp.array(dtype=vec6),
                    row_info: wp.array(dtype=wp.int32), reg: wp.array(dtype=scalar), P: wp.array(dtype=scalar),
                    inertia_w: wp.array(dtype=mat33), inv_inertia_w: wp.array(dtype=mat33), wid: int, k: int,
                    nblk: int, shift: scalar, shift_sat: scalar):
        """Entry ``k`` of the fixed rows' pattern into ``sp.val``: ``D~_pq = P_a D0_ab P_b`` (``+ shift`` on the
        diagonal, ``shift_sat`` on a saturated effort-limited row, ``row_saturated``: the penalty,
        kamino.jax_ref.solver.solve, "Saturation"; ``D0``: :func:`delassus0`), or on a hub position's row
        :func:`hub_entry`."""
        e = sp.ent_start[wid] + k
        p = sp.row[e]
        q = sp.col[e]
        if p >= sp.n_fixed[wid]:
            sp.val[vidx(m, sp, wid, k)] = hub_entry(m, sp, row_stride, row_body, row_J, P, inertia_w, wid, p, q, nblk)
            return
        a = sp.perm[sp.perm_start[wid] + p]
        b = sp.perm[sp.perm_start[wid] + q]
        s = (P[ridx(m, row_stride, wid, a)]
             * delassus0(m, sp, row_stride, row_body, row_J, reg, inv_inertia_w, wid, a, b, nblk)
             * P[ridx(m, row_stride, wid, b)])
        if p == q:
            if row_saturated(row_info, ridx(m, row_stride, wid, a)) != 0:
                s += shift_sat
            else:
                s += shift
        sp.val[vidx(m, sp, wid, k)] = s

    return fixed_entry


@functools.cache
def assemble_fixed_kernel(np_dtype):
    """The fixed rows' pattern of ``D~`` of every world (docs/formulation.md §8.1)."""
    scalar, vec6, mat33, M, SP = builder_types(np_dtype).take("scalar", "vec6", "mat33", "M", "SP")
    fixed_entry = fixed_entry_func(np_dtype)

    @wp.kernel(module="unique", enable_backward=False)
    def assemble_fixed(
        # model (read only)
        m: M,
        # in
        nblk: int, shift: scalar, shift_sat: scalar,
        row_stride: int,
        row_body: wp.array(dtype=wp.int32),
        row_J: wp.array(dtype=vec6),
        row_info: wp.array(dtype=wp.int32),
        reg: wp.array(dtype=scalar),
        P: wp.array(dtype=scalar),
        inertia_w: wp.array(dtype=mat33),
        inv_inertia_w: wp.array(dtype=mat33),
        # out: the factor values sp.val (the pattern's index tables are read)
        sp: SP,
    ):
        """:func:`fixed_entry` ``k`` of every world (docs/formulation.md §8.1)."""
        wid, k = wp.tid()
        if k >= sp.nnz[wid]:
            return
        fixed_entry(m, sp, row_stride, row_body, row_J, row_info, reg, P, inertia_w, inv_inertia_w, wid, k, nblk,
                    shift, shift_sat)

    return assemble_fixed


@functools.cache
def tail_row_func(np_dtype):
    """A tail row's entries of ``D~`` (docs/formulation.md §8.1)."""
    scalar, vec6, mat33, M, SP = builder_types(np_dtype).take("scalar", "vec6", "mat33", "M", "SP")
    ix = index_funcs(np_dtype)
    ridx, row_kind, row_source = ix.ridx, ix.row_kind, ix.row_source
    tail_k, tidx = tail_k_func(np_dtype), tidx_func(np_dtype)
    delassus0, row_on_body = delassus0_func(np_dtype), row_on_body_func(np_dtype)

    @wp.func
    def tail_row(m: M, sp: SP, row_stride: int, row_body: wp.array(dtype=wp.int32), row_J: wp.array(dtype=vec6),
                 row_info: wp.array(dtype=wp.int32), ct_pair: wp.array(dtype=wp.int32), reg: wp.array(dtype=scalar),
                 P: wp.array(dtype=scalar), inv_inertia_w: wp.array(dtype=mat33), wid: int, a: int, nblk: int):
        """Tail row ``a`` (an active limit or contact row) into ``sp.tail``: ``D~_ab`` for every fixed row ``b`` of
        its ``L_tf`` pattern (chosen by the row's source and recorded in ``sp.tail_pat``; the others are zero) and
        every tail row ``b <= a`` (no shift: :func:`factor` adds the world's penalty)."""
        nf = sp.n_fixed[wid]
        t = a - nf
        ra = ridx(m, row_stride, wid, a)
        Pa = P[ra]
        pat = int(0)
        src = row_source(row_info, ra)
        if row_kind(row_info, ra) == ROW_LIMIT:
            pat = sp.dof_pat[src]
        else:  # a contact row: its pair's
            pat = sp.con_pat[wid] + ct_pair[src]
        sp.tail_pat[wid * sp.tail_max + t] = pat
        i0 = sp.pat_ptr[pat]
        for i in range(sp.pat_ptr[pat + 1] - i0):
            pos = sp.pat_pos[i0 + i]
            if pos >= nf:  # a hub's unknown (component c of hub h): P_a (J_a on the hub)_c
                h = (pos - nf) // 6
                sp.tail[tidx(m, sp, row_stride, wid, t, i)] = Pa * row_on_body(
                    row_body, row_J, ra, sp.hub_body[sp.hub_start[wid] + h], nblk)[pos - nf - 6 * h]
            else:
                b = sp.pat_row[i0 + i]
                sp.tail[tidx(m, sp, row_stride, wid, t, i)] = (
                    Pa * delassus0(m, sp, row_stride, row_body, row_J, reg, inv_inertia_w, wid, a, b, nblk)
                    * P[ridx(m, row_stride, wid, b)])
        kt = tail_k(sp, wid) - nf
        for b in range(nf, a + 1):
            sp.tail[tidx(m, sp, row_stride, wid, t, kt + b)] = (
                Pa * delassus0(m, sp, row_stride, row_body, row_J, reg, inv_inertia_w, wid, a, b, nblk)
                * P[ridx(m, row_stride, wid, b)])

    return tail_row


@functools.cache
def assemble_tail_kernel(np_dtype):
    """The tail rows' entries of ``D~`` of every world (docs/formulation.md §8.1)."""
    scalar, vec6, mat33, M, SP = builder_types(np_dtype).take("scalar", "vec6", "mat33", "M", "SP")
    tail_row = tail_row_func(np_dtype)

    @wp.kernel(module="unique", enable_backward=False)
    def assemble_tail(
        # model (read only)
        m: M,
        # in
        nblk: int,
        row_stride: int,
        n_rows: wp.array(dtype=wp.int32),
        row_body: wp.array(dtype=wp.int32),
        row_J: wp.array(dtype=vec6),
        row_info: wp.array(dtype=wp.int32),
        ct_pair: wp.array(dtype=wp.int32),
        reg: wp.array(dtype=scalar),
        P: wp.array(dtype=scalar),
        inv_inertia_w: wp.array(dtype=mat33),
        # out: the tail rows' values sp.tail and patterns sp.tail_pat (the pattern's index tables are read)
        sp: SP,
    ):
        """:func:`tail_row` ``a`` of every world (docs/formulation.md §8.1)."""
        wid, a = wp.tid()
        if a < sp.n_fixed[wid] or a >= n_rows[wid]:
            return
        tail_row(m, sp, row_stride, row_body, row_J, row_info, ct_pair, reg, P, inv_inertia_w, wid, a, nblk)

    return assemble_tail


@functools.cache
def factor_fixed_rows_func(np_dtype):
    """``L_f`` in place by the precomputed update lists (docs/formulation.md §8.1)."""
    SP = builder_types(np_dtype).SP

    @wp.func
    def factor_fixed_rows(sp: SP, wid: int, vb: int):
        """``L_f`` in place: the fixed rows' entries by the precomputed update lists. With hubs, their positions
        (the last rows, from entry ``kh`` on) take the signs of ``L S L^T``, ``S = diag(s)``, ``s = -1`` on a hub
        position and +1 on a fixed row: ``L_pq = (A_pq - sum_r L_pr s_r L_qr) / (s_q L_qq)``, ``L_pp = sqrt(s_p
        (A_pp - sum_r s_r L_pr^2))`` (``A``'s hub block is negative definite, so both roots are real); the fixed
        rows' entries, whose updates come from fixed rows only, are today's Cholesky, operation for operation."""
        e0 = sp.ent_start[wid]
        nf = sp.n_fixed[wid]
        kh = sp.nnz[wid]
        if sp.n_pos[wid] != nf:
            kh = sp.row_ptr[sp.ptr_start[wid] + nf]
        for k in range(kh):
            s = sp.val[vb + k * sp.val_stride]
            for u in range(sp.upd_ptr[2 * (e0 + k)], sp.upd_ptr[2 * (e0 + k) + 1]):
                s -= sp.val[vb + sp.upd_a[u] * sp.val_stride] * sp.val[vb + sp.upd_b[u] * sp.val_stride]
            d = sp.div[e0 + k]
            if d == k:
                s = wp.sqrt(s)
            else:
                s = s / sp.val[vb + d * sp.val_stride]
            sp.val[vb + k * sp.val_stride] = s
        for k in range(kh, sp.nnz[wid]):
            s = sp.val[vb + k * sp.val_stride]
            for u in range(sp.upd_ptr[2 * (e0 + k)], sp.upd_ptr[2 * (e0 + k) + 1]):
                ua = sp.upd_a[u]
                if sp.col[e0 + ua] >= nf:
                    s += sp.val[vb + ua * sp.val_stride] * sp.val[vb + sp.upd_b[u] * sp.val_stride]
                else:
                    s -= sp.val[vb + ua * sp.val_stride] * sp.val[vb + sp.upd_b[u] * sp.val_stride]
            d = sp.div[e0 + k]
            if d == k:
                s = wp.sqrt(-s)
            elif sp.col[e0 + k] >= nf:
                s = -s / sp.val[vb + d * sp.val_stride]
            else:
                s = s / sp.val[vb + d * sp.val_stride]
            sp.val[vb + k * sp.val_stride] = s

    return factor_fixed_rows


@functools.cache
def factor_fixed_kernel(np_dtype):
    """The Cholesky factor of the fixed rows only (post-stabilisation; docs/formulation.md §8.1)."""
    M, SP = builder_types(np_dtype).take("M", "SP")
    bases, factor_fixed_rows = bases_func(np_dtype), factor_fixed_rows_func(np_dtype)

    @wp.kernel(module="unique", enable_backward=False)
    def factor_fixed(
        # model (read only)
        m: M,
        # in
        row_stride: int,
        # out: the factor values sp.val, in place (the pattern's index tables are read)
        sp: SP,
    ):
        """Cholesky of the fixed rows only (``D~_ff = L_f L_f^T``; post-stabilisation; docs/formulation.md §8.1)."""
        wid = wp.tid()
        factor_fixed_rows(sp, wid, bases(m, sp, row_stride, wid)[1])

    return factor_fixed


@functools.cache
def factor_tail_func(np_dtype):
    """``L_t``, the tail rows' dense Cholesky with the world's penalty (docs/formulation.md §8.1)."""
    scalar, M, SP = builder_types(np_dtype).take("scalar", "M", "SP")
    bases, tail_k = bases_func(np_dtype), tail_k_func(np_dtype)
    sdiag_col = sdiag_col_func(np_dtype)

    @wp.func
    def factor_tail(m: M, sp: SP, row_stride: int, wid: int, n: int, shift: scalar):
        """``L_t = chol(S_t + shift I)``: the tail rows' Cholesky from their Schur complement ``S_t = D~_t -
        L_tf L_tf^T``, kept by :func:`factor` in the tail rows' upper slots (``S_t[t, j]`` at row ``j``, tail
        column ``K + t``) and its diagonal in column :func:`sdiag_col`; a new penalty of the limit and contact rows
        redoes only this (``kamino.jax_ref.solver.solve``, "Penalty"). Writes ``sp.tail``."""
        base = bases(m, sp, row_stride, wid)
        tb, ts = base[2], base[3]
        tc = sp.tail_stride
        nf = sp.n_fixed[wid]
        kt = tail_k(sp, wid)
        kd = sdiag_col(sp, wid)
        for t in range(n - nf):
            tr = tb + t * ts
            for j in range(t + 1):
                jr = tb + j * ts
                s = scalar(0.0)
                if j == t:
                    s = sp.tail[tr + kd * tc] + shift
                else:
                    s = sp.tail[jr + (kt + t) * tc]
                for i in range(j):
                    s -= sp.tail[tr + (kt + i) * tc] * sp.tail[jr + (kt + i) * tc]
                if j == t:
                    s = wp.sqrt(s)
                else:
                    s = s / sp.tail[jr + (kt + j) * tc]
                sp.tail[tr + (kt + j) * tc] = s

    return factor_tail


@functools.cache
def schur_entry_func(np_dtype):
    """An entry of the tail rows' Schur complement ``S_t`` (docs/formulation.md §8.1)."""
    SP = builder_types(np_dtype).SP
    tail_k, sdiag_col = tail_k_func(np_dtype), sdiag_col_func(np_dtype)
    tail_pattern = tail_pattern_func(np_dtype)

    @wp.func
    def schur_entry(sp: SP, wid: int, rb: int, tb: int, ts: int, nf: int, t: int, j: int):
        """``S_t[t, j] = D~_tj - L_t. L_j.`` (``j <= t``, tail rows, ``L_tf`` done) into row ``j``'s upper slot
        (tail column ``K + t``), or into column :func:`sdiag_col` for ``j == t``: it reads only lower slots, so
        entries are independent. The dot runs over row ``t``'s pattern, ascending, finding each position in row
        ``j``'s through its lookup (the dense sum without its zero terms); a hub position's term carries its sign
        ``s_r = -1`` (:func:`factor_fixed_rows`)."""
        tr = tb + t * ts
        jr = tb + j * ts
        tc = sp.tail_stride
        kt = tail_k(sp, wid)
        pt = tail_pattern(sp, wid, t)
        lut = tail_pattern(sp, wid, j) * sp.pat_lut_stride
        i0 = sp.pat_ptr[pt]
        s = sp.tail[tr + (kt + j) * tc]
        for i in range(sp.pat_ptr[pt + 1] - i0):
            pos = sp.pat_pos[i0 + i]
            c = sp.pat_lut[lut + pos]
            if c >= 0:
                if pos >= nf:  # a hub's unknown: s_r = -1 in S_tj = D~_tj - sum_r L_tr s_r L_jr
                    s += sp.tail[tr + i * tc] * sp.tail[jr + c * tc]
                else:
                    s -= sp.tail[tr + i * tc] * sp.tail[jr + c * tc]
        if j == t:
            sp.tail[tr + sdiag_col(sp, wid) * tc] = s
        else:
            sp.tail[jr + (kt + t) * tc] = s

    return schur_entry


@functools.cache
def factor_world_func(np_dtype):
    """A world's whole Cholesky factor ``D~ = L L^T`` (docs/formulation.md §8.1)."""
    scalar, M, SP = builder_types(np_dtype).take("scalar", "M", "SP")
    bases, tail_pattern = bases_func(np_dtype), tail_pattern_func(np_dtype)
    factor_fixed_rows, factor_tail = factor_fixed_rows_func(np_dtype), factor_tail_func(np_dtype)
    schur_entry = schur_entry_func(np_dtype)

    @wp.func
    def factor_world(m: M, sp: SP, row_stride: int, n_rows: wp.array(dtype=wp.int32), rho_u: wp.array(dtype=scalar),
                     wid: int, eta: scalar):
        """Cholesky ``D~ = L L^T`` in place in ``sp.val`` and ``sp.tail`` (§8.1): the fixed rows by the precomputed
        update lists, then the tail rows (forward substitution against the fixed rows, their Schur complement, and
        its dense Cholesky with the world's penalty ``eta + rho_u``, :func:`factor_tail`)."""
        base = bases(m, sp, row_stride, wid)
        rb, vb, tb, ts = base[0], base[1], base[2], base[3]
        tc = sp.tail_stride
        nf = sp.n_fixed[wid]
        factor_fixed_rows(sp, wid, vb)
        n = n_rows[wid]
        p0 = sp.ptr_start[wid]
        for t in range(n - nf):
            tr = tb + t * ts
            # L_tf: row t solves L_f l = D~_ft over its pattern (forward substitution over the sparse rows; the
            # columns outside the pattern hold zeros and are left out)
            pt = tail_pattern(sp, wid, t)
            i0 = sp.pat_ptr[pt]
            for i in range(sp.pat_ptr[pt + 1] - i0):
                s = sp.tail[tr + i * tc]
                pos = sp.pat_pos[i0 + i]
                k1 = sp.row_ptr[p0 + pos + 1] - 1
                if pos >= nf:  # a hub position: L_tp = (D~_tp - sum_r L_tr s_r L_pr) / (s_p L_pp), s = -1 on hubs
                    for u in range(sp.pat_upd_ptr[i0 + i], sp.pat_upd_ptr[i0 + i + 1]):
                        uk = sp.pat_upd_k[u]
                        if sp.col[sp.ent_start[wid] + uk] >= nf:
                            s += sp.val[vb + uk * sp.val_stride] * sp.tail[tr + sp.pat_upd_j[u] * tc]
                        else:
                            s -= sp.val[vb + uk * sp.val_stride] * sp.tail[tr + sp.pat_upd_j[u] * tc]
                    sp.tail[tr + i * tc] = -s / sp.val[vb + k1 * sp.val_stride]
                else:
                    for u in range(sp.pat_upd_ptr[i0 + i], sp.pat_upd_ptr[i0 + i + 1]):
                        s -= sp.val[vb + sp.pat_upd_k[u] * sp.val_stride] * sp.tail[tr + sp.pat_upd_j[u] * tc]
                    sp.tail[tr + i * tc] = s / sp.val[vb + k1 * sp.val_stride]
            for j in range(t + 1):  # S_t row t
                schur_entry(sp, wid, rb, tb, ts, nf, t, j)
        factor_tail(m, sp, row_stride, wid, n, eta + rho_u[wid])

    return factor_world


@functools.cache
def factor_kernel(np_dtype):
    """Every world's Cholesky factor (docs/formulation.md §8.1)."""
    scalar, M, SP = builder_types(np_dtype).take("scalar", "M", "SP")
    factor_world = factor_world_func(np_dtype)

    @wp.kernel(module="unique", enable_backward=False)
    def factor(
        # model (read only)
        m: M,
        # in
        eta: scalar,
        row_stride: int,
        n_rows: wp.array(dtype=wp.int32),
        rho_u: wp.array(dtype=scalar),
        # out: the factor values sp.val and sp.tail, in place (the pattern's index tables are read)
        sp: SP,
    ):
        """:func:`factor_world` of every world (docs/formulation.md §8.1)."""
        factor_world(m, sp, row_stride, n_rows, rho_u, wp.tid(), eta)

    return factor


@functools.cache
def refactor_kernel(np_dtype):
    """The factor again of the worlds whose effort-limited rows saturated (docs/formulation.md §8.1)."""
    scalar, vec6, mat33, M, SP = builder_types(np_dtype).take("scalar", "vec6", "mat33", "M", "SP")
    fixed_entry, tail_row = fixed_entry_func(np_dtype), tail_row_func(np_dtype)
    factor_world = factor_world_func(np_dtype)

    @wp.kernel(module="unique", enable_backward=False)
    def refactor(
        # model (read only)
        m: M,
        # in
        nblk: int, shift: scalar, shift_sat: scalar, eta: scalar,
        row_stride: int,
        n_rows: wp.array(dtype=wp.int32),
        row_body: wp.array(dtype=wp.int32),
        row_J: wp.array(dtype=vec6),
        row_info: wp.array(dtype=wp.int32),
        ct_pair: wp.array(dtype=wp.int32),
        reg: wp.array(dtype=scalar),
        P: wp.array(dtype=scalar),
        inertia_w: wp.array(dtype=mat33),
        inv_inertia_w: wp.array(dtype=mat33),
        rho_u: wp.array(dtype=scalar),
        # out
        pending: wp.array(dtype=wp.int32),  # also read
        sp: SP,  # the factor values sp.val, sp.tail and sp.tail_pat (the pattern's index tables are read)
    ):
        """The whole factor again for the worlds whose effort-limited rows saturated in the last PADMM iteration
        (``pending``; kamino.jax_ref.solver.solve, "Saturation"): assembly with the new shifts, then
        :func:`factor_world` (one thread per world; docs/formulation.md §8.1)."""
        wid = wp.tid()
        if pending[wid] == 0:
            return
        pending[wid] = 0
        for k in range(sp.nnz[wid]):
            fixed_entry(m, sp, row_stride, row_body, row_J, row_info, reg, P, inertia_w, inv_inertia_w, wid, k, nblk,
                        shift, shift_sat)
        for a in range(sp.n_fixed[wid], n_rows[wid]):
            tail_row(m, sp, row_stride, row_body, row_J, row_info, ct_pair, reg, P, inv_inertia_w, wid, a, nblk)
        factor_world(m, sp, row_stride, n_rows, rho_u, wid, eta)

    return refactor


@functools.cache
def solve_inplace_func(np_dtype):
    """``x <- L^-T L^-1 x`` with the sparse factor and its tail (docs/formulation.md §8.1)."""
    scalar, M, SP = builder_types(np_dtype).take("scalar", "M", "SP")
    bases, tail_k = bases_func(np_dtype), tail_k_func(np_dtype)
    tail_pattern = tail_pattern_func(np_dtype)

    @wp.func
    def solve_inplace(m: M, sp: SP, row_stride: int, wid: int, n: int, x: wp.array(dtype=scalar)):
        """``x <- L^-T L^-1 x`` (``x``: ``Work.x``) with the sparse factor and its tail (each sum as the dense
        tail's, without its zero terms). With hubs ``A = L S L^T`` (:func:`factor_fixed_rows`) and ``x <- L^-T S L^-1
        x``: the hub positions' right-hand side is 0 (their virtual rows), ``y`` is negated there between the sweeps
        (after the tail's forward sweep, which reads the unsigned ``y``), and their solution is left in the virtual
        rows, unused."""
        rs = row_stride
        base = bases(m, sp, row_stride, wid)
        rb, vb, tb, ts = base[0], base[1], base[2], base[3]
        tc = sp.tail_stride
        nf = sp.n_fixed[wid]
        npos = sp.n_pos[wid]
        e0 = sp.ent_start[wid]
        p0 = sp.ptr_start[wid]
        q0 = sp.perm_start[wid]
        nt = n - nf
        # forward: fixed rows (and the hubs' unknowns, right-hand side 0), then tail rows
        for p in range(npos):
            r = rb + sp.perm[q0 + p] * rs
            s = scalar(0.0)
            if p < nf:
                s = x[r]
            k1 = sp.row_ptr[p0 + p + 1] - 1
            for k in range(sp.row_ptr[p0 + p], k1):
                s -= sp.val[vb + k * sp.val_stride] * x[rb + sp.colrow[e0 + k] * rs]
            x[r] = s / sp.val[vb + k1 * sp.val_stride]
        kt = tail_k(sp, wid)
        for t in range(nt):
            tr = tb + t * ts
            s = x[rb + (nf + t) * rs]
            pt = tail_pattern(sp, wid, t)
            i0 = sp.pat_ptr[pt]
            for i in range(sp.pat_ptr[pt + 1] - i0):
                s -= sp.tail[tr + i * tc] * x[rb + sp.pat_row[i0 + i] * rs]
            for i in range(t):
                s -= sp.tail[tr + (kt + i) * tc] * x[rb + (nf + i) * rs]
            x[rb + (nf + t) * rs] = s / sp.tail[tr + (kt + t) * tc]
        for p in range(nf, npos):  # y <- S y: the hubs' sign
            r = rb + sp.perm[q0 + p] * rs
            x[r] = -x[r]
        # backward: tail rows, their share of the fixed rows, then the fixed rows (column sweeps of L_f)
        for tt in range(nt):
            t = nt - 1 - tt
            s = x[rb + (nf + t) * rs]
            for i in range(t + 1, nt):
                s -= sp.tail[tb + i * ts + (kt + t) * tc] * x[rb + (nf + i) * rs]
            x[rb + (nf + t) * rs] = s / sp.tail[tb + t * ts + (kt + t) * tc]
        if nt > 0:
            for p in range(npos):
                r = rb + sp.perm[q0 + p] * rs
                s = x[r]
                for t in range(nt):
                    c = sp.pat_lut[tail_pattern(sp, wid, t) * sp.pat_lut_stride + p]
                    if c >= 0:
                        s -= sp.tail[tb + t * ts + c * tc] * x[rb + (nf + t) * rs]
                x[r] = s
        for pp in range(npos):
            p = npos - 1 - pp
            r = rb + sp.perm[q0 + p] * rs
            k1 = sp.row_ptr[p0 + p + 1] - 1
            xp = x[r] / sp.val[vb + k1 * sp.val_stride]
            x[r] = xp
            for k in range(sp.row_ptr[p0 + p], k1):
                rq = rb + sp.colrow[e0 + k] * rs
                x[rq] = x[rq] - sp.val[vb + k * sp.val_stride] * xp

    return solve_inplace


def sparse_llt_kernels(np_dtype) -> SimpleNamespace:
    """The sparse factor's kernels and ``wp.func``s by name (the launches in ``pipeline.py``, the callers in
    ``solver.py``, ``post_stabilisation.py`` and ``solver_lanes.py``), each from its builder."""
    return SimpleNamespace(assemble_fixed=assemble_fixed_kernel(np_dtype),
                           assemble_tail=assemble_tail_kernel(np_dtype), factor=factor_kernel(np_dtype),
                           factor_fixed=factor_fixed_kernel(np_dtype), refactor=refactor_kernel(np_dtype),
                           bases=bases_func(np_dtype), factor_tail=factor_tail_func(np_dtype),
                           factor_world=factor_world_func(np_dtype), fixed_entry=fixed_entry_func(np_dtype),
                           tail_row=tail_row_func(np_dtype), solve_inplace=solve_inplace_func(np_dtype),
                           delassus_entry=delassus_entry_func(np_dtype), schur_entry=schur_entry_func(np_dtype),
                           inv_mass_times=inv_mass_times_func(np_dtype), tail_k=tail_k_func(np_dtype),
                           tail_pattern=tail_pattern_func(np_dtype), sdiag_col=sdiag_col_func(np_dtype))
