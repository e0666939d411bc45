"""The host's symbolic analysis for the sparse Cholesky factor (``linear_solve.py``; docs/formulation.md §8.1): which
bodies each always-active row of a world moves (:func:`fixed_row_bodies`), the worlds grouped by that structure
(:func:`fixed_row_types`), the hubs whose unknowns stay in the factorised system (:func:`hub_bodies`), the factor's
pattern in minimum-degree order with the update list of every entry (:func:`symbolic`), and the patterns a tail row
(an active limit or a contact) can take (:func:`tail_patterns`). Host NumPy, computed once per model.
"""

import dataclasses
import itertools

import numpy as np

from kamino.model import Model, derived
from kamino.tables import prefix, row_tables


def segments(start: np.ndarray, count: np.ndarray) -> np.ndarray:
    """The indices ``start[i] .. start[i] + count[i] - 1`` of every segment ``i``, segment after segment."""
    start = np.asarray(start, np.int64).reshape(-1)
    count = np.asarray(count, np.int64).reshape(-1)
    return np.repeat(start - prefix(count), count) + np.arange(int(count.sum()), dtype=np.int64)


def _local(bodies: np.ndarray, body_start: np.ndarray) -> np.ndarray:
    """Global body indices ``bodies`` (``-1``: the world or padding) made world-local by subtracting their row's world's
    first body ``body_start`` (one per row)."""
    start = np.asarray(body_start, np.int64)
    return np.where(bodies >= 0, bodies - (start[:, None] if bodies.ndim > 1 else start), -1).astype(np.int64)


def _fixed_row_bodies_of(model: Model, w0: int, w1: int) -> tuple[np.ndarray, np.ndarray]:
    """The moving bodies (world-local, ``-1`` padding) of the always-active rows of worlds ``w0 .. w1 - 1``, world
    after world, each world's in row order (:func:`fixed_row_bodies`): ``[sum n_fixed, 4]``, and each world's
    ``n_fixed``.

    A row's bodies are the parent and child of its joint ``a`` (a joint-dynamics row's DoF's, a joint row's, a coupling
    row's first), then those of a coupling row's joint ``b`` (``-1`` without one)."""
    tab = row_tables(model)
    jp, jc = np.asarray(model.joint_parent), np.asarray(model.joint_child)
    dof_joint = np.asarray(tab.dof_joint)
    ws = slice(w0, w1)
    n_dyn, n_cts, n_cpl = (np.asarray(c[ws], np.int64) for c in (tab.world_dyn_count, model.world_cts_count,
                                                                     model.world_coupling_count))
    dyn0 = int(np.sum(tab.world_dyn_count[:w0]))  # the joint-dynamics rows are stored world after world
    dyn = np.asarray(tab.dyn_dof)[dyn0:dyn0 + int(n_dyn.sum())]
    cts = segments(model.world_cts_start[ws], n_cts)
    cpl = segments(model.world_coupling_start[ws], n_cpl)
    # joints a and b of the worlds' joint-dynamics, joint and coupling rows, family after family
    joint_a = np.concatenate([dof_joint[dyn], np.asarray(tab.cts_joint)[cts], dof_joint[tab.cpl_dof_a[cpl]]])
    cpl_b = np.asarray(tab.cpl_dof_b)[cpl]
    joint_b = np.where(cpl_b >= 0, dof_joint[np.maximum(cpl_b, 0)], -1)
    # each world's rows: segments (world, family) of those
    count = np.stack([n_dyn, n_cts, n_cpl], axis=1)
    start = np.stack([prefix(n_dyn), len(dyn) + prefix(n_cts), len(dyn) + len(cts) + prefix(n_cpl)], axis=1)
    rows = segments(start, count)
    n_fixed = count.sum(axis=1)
    b0 = np.repeat(np.asarray(model.world_body_start[ws], np.int64), n_fixed)
    out = np.full((len(rows), 4), -1, np.int64)
    ja = joint_a[rows]
    out[:, 0], out[:, 1] = _local(jp[ja], b0), _local(jc[ja], b0)
    on_b = np.flatnonzero(rows >= len(dyn) + len(cts))  # coupling rows: joint b's bodies where it has one
    jb = joint_b[rows[on_b] - len(dyn) - len(cts)]
    on_b, jb = on_b[jb >= 0], jb[jb >= 0]
    out[on_b, 2], out[on_b, 3] = _local(jp[jb], b0[on_b]), _local(jc[jb], b0[on_b])
    return out, n_fixed


def fixed_row_bodies(model: Model) -> list[np.ndarray]:
    """Per world, the moving bodies (world-local indices, ``-1`` padding) of each always-active row, in row
    order: joint-dynamics rows, joint rows, coupling rows (``kamino/warp_backend/rows.py``). Shape
    ``[n_fixed, 4]`` per world (views into one array of all worlds')."""
    rows, n_fixed = _fixed_row_bodies_of(model, 0, model.num_worlds)
    return np.split(rows, np.cumsum(n_fixed)[:-1]) if model.num_worlds else []


#: :func:`fixed_row_types` computes the worlds' rows this many at a time (a few MB of buffers, reused: the arrays of
#: all worlds at once would take most of the time in first touches of fresh memory)
CHUNK_ROWS = 1 << 17


def _world_chunks(n_rows: np.ndarray, chunk: int) -> list[tuple[int, int]]:
    """Consecutive ranges ``(w0, w1)`` of worlds covering all, each of at most ``chunk`` rows or of one world."""
    ends = np.cumsum(n_rows)
    bounds = [0]
    while bounds[-1] < len(n_rows):
        w0 = bounds[-1]
        w1 = int(np.searchsorted(ends, (ends[w0 - 1] if w0 else 0) + chunk, side="right"))
        bounds.append(max(w1, w0 + 1))
    return list(itertools.pairwise(bounds))


@dataclasses.dataclass(frozen=True)
class FixedRowTypes:
    """The distinct fixed-row structures of a model's worlds (:func:`fixed_row_bodies`)."""

    rows: tuple[np.ndarray, ...]  # each distinct structure's moving bodies [n_fixed, 4], in order of first appearance
    world_type: np.ndarray  # [W] each world's structure: an index into rows
    n_fixed: np.ndarray  # [W] each world's fixed rows


def fixed_row_types(model: Model) -> FixedRowTypes:
    """The worlds of ``model`` grouped by the moving bodies of their fixed rows (equal arrays: one type). A frozen
    model's are computed once and kept on the model (:func:`kamino.model.derived`); the arrays of all worlds are
    not kept."""
    return derived(model, "fixed_row_types", lambda: _fixed_row_types(model))


def _fixed_row_types(model: Model) -> FixedRowTypes:
    tab = row_tables(model)
    n_fixed = (tab.world_dyn_count + model.world_cts_count + model.world_coupling_count).astype(np.int64)
    types: dict[bytes, int] = {}
    reps: list[np.ndarray] = []
    world_type = np.empty(model.num_worlds, np.int64)
    for w0, w1 in _world_chunks(n_fixed, CHUNK_ROWS):
        rows, n = _fixed_row_bodies_of(model, w0, w1)
        ends = np.cumsum(n)
        for w in range(w0, w1):
            r = rows[ends[w - w0] - n[w - w0]:ends[w - w0]]
            t = types.setdefault(r.tobytes(), len(reps))  # the width is 4: the bytes fix the shape
            if t == len(reps):
                reps.append(r.copy())
            world_type[w] = t
    for a in (*reps, world_type, n_fixed):
        a.flags.writeable = False  # shared by every caller of a cached entry
    return FixedRowTypes(rows=tuple(reps), world_type=world_type, n_fixed=n_fixed)


#: A body is a *hub* when more than this many fixed rows have it among their moving bodies: its 6 velocity unknowns
#: then stay in the factorised system, ordered after every fixed row (:func:`symbolic`; docs/warp_backend.md, "Open
#: problems": the animatronic's ``L_f`` 43,210 -> 16,678 entries at the same float32 accuracy). ``None``: no hubs.
HUB_MIN_ROWS: int | None = 48


def hub_bodies(bodies: np.ndarray, min_rows: int | None) -> np.ndarray:
    """The hubs (world-local body indices, ascending) of a world whose fixed rows have the moving bodies ``bodies``
    (:func:`fixed_row_bodies`): bodies on more than ``min_rows`` rows (``None``: none). A body counts once per row
    however often the row lists it; ``-1`` (padding, the world) is no body."""
    if min_rows is None or len(bodies) == 0:
        return np.zeros(0, np.int64)
    b = np.sort(np.asarray(bodies, np.int64).reshape(len(bodies), -1), axis=1)
    first = np.ones(b.shape, bool)  # the first of each run of equal bodies in a (sorted) row
    first[:, 1:] = b[:, 1:] != b[:, :-1]
    body, rows = np.unique(b[first & (b >= 0)], return_counts=True)
    return body[rows > min_rows].astype(np.int64)


def hub_counts(model: Model, min_rows: int | None) -> np.ndarray:
    """Per world, its number of hubs (:func:`hub_bodies`): the world has ``6 x`` that many virtual rows after its
    row capacity (``model_data``), where the hubs' unknowns live during a solve."""
    ft = fixed_row_types(model)
    per_type = np.array([len(hub_bodies(r, min_rows)) for r in ft.rows], np.int64)
    return per_type[ft.world_type].reshape(-1)


@dataclasses.dataclass(frozen=True)
class Symbolic:
    """The factor pattern of one world type (positions ``p`` = rows in elimination order; with hubs, the ``n_real``
    fixed rows first, then 6 positions per hub, whose "rows" are the world's virtual rows)."""

    perm: np.ndarray  # [n] row of position p
    row_ptr: np.ndarray  # [n + 1] entries of factor row p (columns ascending, the diagonal last)
    col: np.ndarray  # [nnz] column position of each entry
    colrow: np.ndarray  # [nnz] the row (original numbering) of each entry's column: perm[col]
    row: np.ndarray  # [nnz] row position of each entry
    div: np.ndarray  # [nnz] entry holding L_qq for entry (p, q) (itself on the diagonal)
    upd_ptr: np.ndarray  # [nnz + 1] update pairs of each entry
    upd_a: np.ndarray  # [n_upd] entry L_pr
    upd_b: np.ndarray  # [n_upd] entry L_qr
    # the same pattern by columns, for the 32-lane kernels (solver_lanes.py): column sweeps and the fan-out factor
    cptr: np.ndarray  # [n + 1] below-diagonal entries of column q: cent[cptr[q]:cptr[q + 1]] (rows ascending)
    cent: np.ndarray  # [nnz] entry index (world-type-local); the last n slots are padding
    crow: np.ndarray  # [nnz] the row (original numbering) of each cent entry: perm[row[cent]]
    fan_ptr: np.ndarray  # [n + 1] update triples of column r: fan_*[fan_ptr[r]:fan_ptr[r + 1]]
    fan_tgt: np.ndarray  # [n_upd] entry (p, q) that L_pr L_qr is subtracted from
    fan_a: np.ndarray  # [n_upd] entry L_pr
    fan_b: np.ndarray  # [n_upd] entry L_qr
    n_real: int = -1  # the fixed rows (positions 0 .. n_real - 1); the positions after them are the hubs' unknowns
    node: np.ndarray | None = None  # [n] graph node of position p: a fixed row, or n_real + 6 h + c (component c of
    # the h-th hub of the hubs as given to symbolic)
    hubs: np.ndarray | None = None  # the hubs (world-local bodies) in position order: position n_real + 6 k + c is
    # component c of hubs[k]

    @property
    def nnz(self) -> int:
        return len(self.col)


def symbolic(bodies: np.ndarray, hubs: np.ndarray | None = None, hub_row0: int = 0) -> Symbolic:
    """Minimum-degree ordering and the factor pattern of rows coupled through shared bodies (``bodies``:
    ``[n, k]`` moving bodies per row, ``-1`` padding).

    With ``hubs`` (world-local bodies, :func:`hub_bodies`) the system is the quasi-definite one of
    docs/warp_backend.md ("Open problems"), ``[[A0, Jh], [Jh^T, -Mh]]``: rows couple only through a shared body that
    is not a hub, and each hub adds 6 nodes (its velocity components), adjacent to each other and to the rows on the
    hub. The rows are ordered by minimum degree first, the hubs' nodes last (hub order, components 0..5), so the fill
    is that of ``memory_breakdown.min_degree_order(..., last=hubs)``; the hub positions' rows are the world's virtual
    rows ``hub_row0 + 6 h + c``. Without hubs: the order and pattern as before, bit for bit."""
    n = len(bodies)
    hubs = np.zeros(0, np.int64) if hubs is None else np.asarray(hubs, np.int64)
    hub_of = {int(b): h for h, b in enumerate(hubs)}
    nh = 6 * len(hubs)
    N = n + nh
    adj: list[set[int]] = [set() for _ in range(N)]
    by_body: dict[int, list[int]] = {}
    for a in range(n):
        for b in set(int(x) for x in bodies[a] if x >= 0):
            by_body.setdefault(b, []).append(a)
    for b, rows in by_body.items():
        if b in hub_of:
            hn = [n + 6 * hub_of[b] + c for c in range(6)]
            for a in rows:
                adj[a].update(hn)
            for v in hn:
                adj[v].update(rows)
                adj[v].update(hn)
        else:
            for a in rows:
                adj[a].update(rows)
    for a in range(N):
        adj[a].discard(a)
    alive = set(range(n))
    order: list[int] = []
    below: list[set[int]] = []  # rows (original) below the diagonal in the eliminated column

    def eliminate(v: int):
        nb = set(adj[v])
        order.append(v)
        below.append(nb)
        for a in nb:
            adj[a] |= nb
            adj[a].discard(a)
            adj[a].discard(v)
        alive.discard(v)

    while alive:
        eliminate(min(alive, key=lambda a: (len(adj[a]), a)))
    # then the hubs, each its 6 components in order, the hub of fewest neighbours first
    alive_hubs = set(range(len(hubs)))
    while alive_hubs:
        h = min(alive_hubs, key=lambda h: (len(adj[n + 6 * h]), h))
        for c in range(6):
            eliminate(n + 6 * h + c)
        alive_hubs.discard(h)
    hubs = hubs[(np.asarray(order[n::6], np.int64) - n) // 6] if nh else hubs  # in position order
    n_real, n = n, N
    pos = np.empty(n, np.int64)
    pos[np.asarray(order, np.int64)] = np.arange(n)
    cols: list[list[int]] = [[] for _ in range(n)]
    for j, nb in enumerate(below):
        for a in nb:
            cols[int(pos[a])].append(j)
    row_ptr, col, row = [0], [], []
    for p in range(n):
        cs = [*sorted(cols[p]), p]
        col += cs
        row += [p] * len(cs)
        row_ptr.append(len(col))
    index = {(r, c): k for k, (r, c) in enumerate(zip(row, col, strict=True))}
    diag = [row_ptr[p + 1] - 1 for p in range(n)]
    div, upd_ptr, upd_a, upd_b = [], [0], [], []
    for k, (p, q) in enumerate(zip(row, col, strict=True)):
        div.append(diag[q])
        shared = set(col[row_ptr[q]:row_ptr[q + 1] - 1]) if q != p else None
        for kk in range(row_ptr[p], row_ptr[p + 1] - 1):
            r = col[kk]
            if r >= q:
                break
            if q == p:
                upd_a.append(kk)
                upd_b.append(kk)
            elif r in shared:
                upd_a.append(kk)
                upd_b.append(index[(q, r)])
        upd_ptr.append(len(upd_a))
    i64 = lambda a: np.asarray(a, np.int64)  # noqa: E731
    node = i64(order)
    # the row of each position: a hub position's is the world's virtual row hub_row0 + (p - n_real)
    prow = np.where(np.arange(n) < n_real, node, hub_row0 + np.arange(n) - n_real)
    col_a, row_a = i64(col), i64(row)
    below = np.flatnonzero(row_a != col_a)
    cent = below[np.lexsort((row_a[below], col_a[below]))]  # by column, rows ascending
    cptr = np.searchsorted(col_a[cent], np.arange(n + 1))
    upd_tgt = np.repeat(np.arange(len(col)), np.diff(i64(upd_ptr)))
    fan = np.argsort(col_a[i64(upd_a)], kind="stable") if upd_a else np.zeros(0, np.int64)
    fan_r = col_a[i64(upd_a)][fan] if upd_a else np.zeros(0, np.int64)
    pad = np.zeros(n, np.int64)
    return Symbolic(perm=prow, row_ptr=i64(row_ptr), col=col_a, colrow=prow[col_a], row=row_a,
                    div=i64(div),
                    upd_ptr=i64(upd_ptr), upd_a=i64(upd_a), upd_b=i64(upd_b),
                    cptr=i64(cptr), cent=np.concatenate([cent, pad]),
                    crow=np.concatenate([prow[row_a[cent]], pad]),
                    fan_ptr=np.searchsorted(fan_r, np.arange(n + 1)), fan_tgt=upd_tgt[fan],
                    fan_a=i64(upd_a)[fan] if upd_a else fan, fan_b=i64(upd_b)[fan] if upd_a else fan,
                    n_real=n_real, node=node, hubs=hubs)


def elimination_parents(sym: Symbolic) -> np.ndarray:
    """The elimination tree of ``L_f``: the parent of position ``q`` is the first row below the diagonal in column
    ``q`` (``n`` for a root)."""
    n = len(sym.perm)
    parent = np.full(n, n, np.int64)
    off = sym.row != sym.col
    np.minimum.at(parent, sym.col[off], sym.row[off])
    return parent


@dataclasses.dataclass(frozen=True)
class InversePattern:
    """The pattern of ``L_f^-1`` (positions as in :class:`Symbolic`): column ``c`` is nonzero on the path from ``c``
    up the elimination tree to its root, stored as slots ``icol_ptr[c] ..`` in that order (the slot of ancestor
    ``r`` is ``icol_ptr[c] + depth(c) - depth(r)``); row ``r`` is nonzero on the subtree of ``r``."""

    icol_ptr: np.ndarray  # [n + 1] the slots of column c: icol_ptr[c] .. icol_ptr[c + 1] - 1, c first, its root last
    ipath_row: np.ndarray  # [nnz] the row (original numbering, Symbolic.perm) of each slot
    irow_ptr: np.ndarray  # [n + 1] row r's entries: irow_slot / irow_col[irow_ptr[r] .. irow_ptr[r + 1] - 1]
    irow_slot: np.ndarray  # [nnz] the slot of each entry of row r (its columns ascending)
    irow_col: np.ndarray  # [nnz] the column (original numbering) of each entry of row r
    cup: np.ndarray  # [len(Symbolic.cent)] per below-diagonal entry (r, q) of L_f in column order: depth(q) - depth(r)

    @property
    def nnz(self) -> int:
        return len(self.ipath_row)


def inverse_pattern(sym: Symbolic) -> InversePattern:
    """The pattern of ``L_f^-1`` (:class:`InversePattern`): entry ``(r, c)`` is structurally nonzero exactly when
    ``r`` is ``c`` or one of its ancestors in the elimination tree (:func:`elimination_parents`), since the
    forward substitution ``L z = e_c`` reaches only those rows."""
    n = len(sym.perm)
    parent = elimination_parents(sym)
    depth = np.zeros(n + 1, np.int64)  # depth[n]: above the roots
    depth[n] = -1
    for p in range(n - 1, -1, -1):  # parents come after their children
        depth[p] = depth[parent[p]] + 1
    depth = depth[:n]
    icol_ptr = np.concatenate([[0], np.cumsum(depth + 1)])
    path_pos = np.empty(int(icol_ptr[-1]), np.int64)
    for c in range(n):
        r, k = c, int(icol_ptr[c])
        while r < n:
            path_pos[k] = r
            r, k = int(parent[r]), k + 1
    col_of = np.repeat(np.arange(n), depth + 1)
    by_row = np.lexsort((col_of, path_pos))  # slots by row, columns ascending
    irow_ptr = np.searchsorted(path_pos[by_row], np.arange(n + 1))
    below = sym.cent[:int(sym.cptr[-1])]
    cup = np.zeros(len(sym.cent), np.int64)
    cup[:len(below)] = depth[sym.col[below]] - depth[sym.row[below]]
    return InversePattern(icol_ptr=icol_ptr, ipath_row=sym.perm[path_pos], irow_ptr=irow_ptr, irow_slot=by_row,
                          irow_col=sym.perm[col_of[by_row]], cup=cup)


def tail_row_bodies(model: Model, tab, w: int) -> tuple[np.ndarray, np.ndarray | None]:
    """The moving bodies (world-local, ``-1``: the world) of world ``w``'s tail rows: ``[n_lim, 2]`` for its limited
    DoFs in DoF order (the joint's parent and child; ``tab``: :func:`kamino.tables.row_tables`), and ``[n_pairs, 2]``
    for its contact pairs in the model's order (the warm-start key ``Contacts.pair``), or ``None`` without a contact
    capacity."""
    b0 = int(model.world_body_start[w])
    l0 = int(prefix(tab.world_lim_count)[w])
    joints = np.asarray(tab.dof_joint)[np.asarray(tab.lim_dof)[l0:l0 + int(tab.world_lim_count[w])]]
    lim = np.stack([np.asarray(model.joint_parent)[joints], np.asarray(model.joint_child)[joints]], axis=-1)
    lim = np.where(lim >= 0, lim - b0, -1).astype(np.int64).reshape(-1, 2)
    if int(model.world_contact_capacity[w]) == 0:
        return lim, None
    p0, pc = int(model.world_pair_start[w]), int(model.world_pair_count[w])
    geoms = np.concatenate([model.pair_geom_a[p0:p0 + pc], model.pair_geom_b[p0:p0 + pc]]).astype(np.int64)
    gb = np.asarray(model.geom_body)[geoms]
    return lim, np.where(gb >= 0, gb - b0, -1).astype(np.int64).reshape(2, pc).T.copy()


def all_tail_row_bodies(model: Model, tab) -> list[tuple[np.ndarray, np.ndarray | None]]:
    """:func:`tail_row_bodies` of every world, computed for all worlds at once (views into two arrays)."""
    W = model.num_worlds
    jp, jc = np.asarray(model.joint_parent), np.asarray(model.joint_child)
    n_lim = np.asarray(tab.world_lim_count, np.int64)
    joints = np.asarray(tab.dof_joint)[np.asarray(tab.lim_dof)[:int(n_lim.sum())]]
    lim = _local(np.stack([jp[joints], jc[joints]], axis=-1).reshape(-1, 2),
                 np.repeat(model.world_body_start, n_lim))
    n_pair = np.asarray(model.world_pair_count, np.int64)
    pairs = segments(model.world_pair_start, n_pair)
    gb = np.asarray(model.geom_body)
    con = _local(np.stack([gb[model.pair_geom_a[pairs]], gb[model.pair_geom_b[pairs]]], axis=-1).reshape(-1, 2),
                 np.repeat(model.world_body_start, n_pair))
    l0, p0 = prefix(n_lim), prefix(n_pair)
    cap = np.asarray(model.world_contact_capacity)
    return [(lim[l0[w]:l0[w] + n_lim[w]], con[p0[w]:p0[w] + n_pair[w]] if cap[w] != 0 else None) for w in range(W)]


def tail_patterns(bodies: np.ndarray, sym: Symbolic, lim_bodies: np.ndarray,
                  contact_bodies: np.ndarray | None) -> list[np.ndarray]:
    """The ``L_tf`` pattern (fixed positions, ascending) of each kind of tail row: one per limited DoF (``lim_bodies``,
    in the order the active limits are packed), then one per contact pair (``contact_bodies``; a contact row takes
    its pair's). A pattern is the union of the elimination-tree paths from the fixed rows on the row's bodies to the
    root (``bodies``: the fixed rows' moving bodies; ``sym``: their factor pattern; :func:`tail_row_bodies`)."""
    n = len(sym.perm)
    parent = elimination_parents(sym)
    nr = sym.n_real if sym.n_real >= 0 else n
    hubs = set() if sym.hubs is None else {int(b) for b in sym.hubs}
    node = np.arange(n) if sym.node is None else sym.node
    # each position's bodies: a fixed row's other than hubs (it meets a hub through the hub's unknowns), a hub
    # unknown's its hub
    pos_sets = [set(int(b) for b in bodies[v] if b >= 0 and int(b) not in hubs) if v < nr
                else {int(sym.hubs[(q - nr) // 6])} for q, v in enumerate(int(x) for x in node)]

    def reach(body_set: set[int]) -> np.ndarray:
        seen: set[int] = set()
        for q0 in range(n):
            if body_set & pos_sets[q0]:
                q = q0
                while q < n and q not in seen:
                    seen.add(q)
                    q = int(parent[q])
        return np.asarray(sorted(seen), np.int64)

    pairs = [*lim_bodies, *(contact_bodies if contact_bodies is not None else [])]
    return [reach({int(b) for b in pair if b >= 0}) for pair in pairs]
