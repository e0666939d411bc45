"""The tail's ``L_tf`` patterns (kamino/warp_backend/linear_solve.py, ``tail_patterns``): each limit or contact row
stores ``L_tf = D~_tf L_f^-T`` only on the fixed positions its bodies' rows reach up the elimination tree of ``L_f``.
The storage is right only if no nonzero falls outside the pattern; it is tight if none of the pattern is
structurally zero. Both are checked numerically on a Delassus-like matrix of the robot's structure with random
values (``J M^-1 J^T + I`` with random 6-vector blocks per row and body, ``M = I``), where structural nonzeros are
numerically nonzero with probability one."""


import numpy as np
import pytest
import warp as wp

import kamino
from kamino.bench import memory_breakdown as mb  # the counts it predicts with
from kamino.tables import row_tables
from kamino.warp_backend import linear_solve, linear_solve_pattern
from kamino.warp_backend.linear_solve_pattern import fixed_row_bodies, symbolic, tail_patterns, tail_row_bodies
from kamino.warp_backend.model_data import warp_model


@pytest.mark.parametrize("name", ["dr_legs", "bdx"])
def test_tail_patterns_hold_every_nonzero_of_L_tf_and_no_more(name):
    model = getattr(kamino.models, name)()
    bodies = fixed_row_bodies(model)[0]
    sym = symbolic(bodies)
    n = len(sym.perm)
    rng = np.random.default_rng(0)
    nb = int(model.world_body_count[0])

    def blocks(body_rows):  # a random 6-vector per (row, moving body): [rows, bodies, 6], zero off the row's bodies
        J = np.zeros((len(body_rows), nb, 6))
        for a, row in enumerate(body_rows):
            for b in row:
                if b >= 0:
                    J[a, b] = rng.standard_normal(6)
        return J

    J_f = blocks(bodies).reshape(n, -1)
    P = sym.perm  # elimination order
    L = np.linalg.cholesky((J_f @ J_f.T + np.eye(n))[np.ix_(P, P)])
    lim, pairs = tail_row_bodies(model, row_tables(model), 0)
    assert len(lim) > 0 and pairs is not None and len(pairs) > 0  # both kinds of tail row are exercised
    sources = [*lim, *pairs]
    patterns = tail_patterns(bodies, sym, lim, pairs)
    assert len(patterns) == len(sources)
    for src, pattern in zip(sources, patterns, strict=True):
        J_t = blocks([src]).reshape(1, -1)
        l_tf = np.linalg.solve(L, (J_f @ J_t.T)[P, 0])  # one row of L_tf: L_f l = D_ft
        nonzero = np.flatnonzero(np.abs(l_tf) > 1e-12 * np.abs(l_tf).max())
        assert set(nonzero.tolist()) <= set(pattern.tolist()), f"{name}: L_tf of a row on {src} leaves its pattern"
        assert len(nonzero) == len(pattern), f"{name}: the pattern of a row on {src} is wider than its L_tf"
        assert np.all(np.diff(pattern) > 0)  # ascending: the sums run in the dense loops' order


def test_memory_breakdown_counts_match_the_built_factor():
    # kamino.bench.memory_breakdown's predictions are read against what is built: without hubs its minimum-degree
    # count is the built L_f's entry count (the same greedy order), and "as stored" is the built tail's K per row.
    # A drift between the counter and linear_solve would make its predictions for new layouts (--hub-fill) meaningless.
    for scene in ("bdx", "fourbar"):
        no_hubs = mb.hub_fill(scene, thresholds=(None,))[0]
        fill = mb.tail_fill(scene)
        model, _ = mb.tb.load_scene(scene)
        maxdim = warp_model(model, np.float32, "cpu").arrays.row_maxdim.numpy()
        built = linear_solve.build(model, np.float32, "cpu", maxdim)
        assert no_hubs["factor_entries"] == built.nnz_total == fill["L_f"]
        assert fill["widest_pattern"] == int(built.arrays.grp_tail_k.numpy()[0])
        assert fill["tail_rows"] == built.max_tail


def _world_pattern(S, model: kamino.Model, w: int) -> dict[str, np.ndarray]:
    """World ``w``'s share of a built ``linear_solve.Pattern`` ``S``, in world-local numbering: its factor pattern
    (entry
    indices relative to the world's type), hubs, and the ``L_tf`` pattern of each limited DoF and contact pair."""
    a = {name: getattr(S, name).numpy() for name in dir(S) if isinstance(getattr(S, name), wp.array)}
    n, nnz = int(a["n_pos"][w]), int(a["nnz"][w])
    p0, q0, e0 = int(a["perm_start"][w]), int(a["ptr_start"][w]), int(a["ent_start"][w])
    upd = a["upd_ptr"][2 * e0:2 * (e0 + nnz)]
    h0, b0, nb = int(a["hub_start"][w]), int(model.world_body_start[w]), int(model.world_body_count[w])
    hubs = a["hub_body"][h0:h0 + np.count_nonzero(a["body_hub"][b0:b0 + nb] >= 0)]
    out = dict(n_fixed=a["n_fixed"][w:w + 1], perm=a["perm"][p0:p0 + n], row_ptr=a["row_ptr"][q0:q0 + n + 1],
               upd_ptr=upd - (upd[0] if len(upd) else 0), hub_body=hubs - b0,
               body_hub=a["body_hub"][b0:b0 + nb])
    for f in ("col", "colrow", "row", "div"):
        out[f] = a[f][e0:e0 + nnz]
    if len(upd):
        for f in ("upd_a", "upd_b"):
            out[f] = a[f][upd[0]:upd[-1]]

    def pattern(pid: int) -> np.ndarray:
        return a["pat_pos"][a["pat_ptr"][pid]:a["pat_ptr"][pid + 1]]

    d0, nd = int(model.world_dof_start[w]), int(model.world_dof_count[w])
    for d in range(d0, d0 + nd):
        if len(a["dof_pat"]) > d and a["dof_pat"][d] >= 0:
            out[f"dof{d - d0}"] = pattern(int(a["dof_pat"][d]))
    if a["con_pat"][w] >= 0:
        for k in range(int(model.world_pair_count[w])):
            out[f"pair{k}"] = pattern(int(a["con_pat"][w]) + k)
    return out


def _reference_pattern(robot: kamino.Model, n_rows: int, hub_min_rows: int | None, hub_row0: int) -> dict:
    """What :func:`_world_pattern` must find for a one-world ``robot`` factorising ``n_rows`` rows, straight from
    ``symbolic`` and ``tail_patterns`` (the per-world path)."""
    rows = fixed_row_bodies(robot)[0]
    sym = symbolic(rows, linear_solve_pattern.hub_bodies(rows, hub_min_rows), hub_row0)
    out = dict(n_fixed=[len(rows)], perm=sym.perm, row_ptr=sym.row_ptr, upd_ptr=np.stack(
        [sym.upd_ptr[:-1], sym.upd_ptr[1:]], axis=1).reshape(-1), hub_body=sym.hubs, col=sym.col,
        colrow=sym.colrow, row=sym.row, div=sym.div)
    if len(sym.upd_a):
        out.update(upd_a=sym.upd_a, upd_b=sym.upd_b)
    body_hub = np.full(int(robot.world_body_count[0]), -1)
    body_hub[sym.hubs] = np.arange(len(sym.hubs))
    out["body_hub"] = body_hub
    if n_rows > len(rows):  # tail rows: a pattern per limited DoF, then per contact pair
        lim, pairs = tail_row_bodies(robot, row_tables(robot), 0)
        pats = tail_patterns(rows, sym, lim, pairs)
        lim_dofs = np.flatnonzero(np.isfinite(robot.dof_lower) | np.isfinite(robot.dof_upper))
        out.update({f"dof{d}": p for d, p in zip(lim_dofs, pats, strict=False)})
        out.update({f"pair{k}": p for k, p in enumerate(pats[len(lim_dofs):])})
    return out


def test_heterogeneous_model_builds_each_robots_patterns(monkeypatch):
    # Stepper construction analyses each distinct world structure once (linear_solve_pattern.fixed_row_types,
    # world_types) and
    # lays the worlds' arrays out with numpy over all worlds. In a model of several robot types (concat), every world
    # must get the factor pattern, hubs and L_tf patterns that its robot alone gets. Small chunks make
    # fixed_row_types compute the worlds' rows in several pieces; hubs of more than 24 rows (dr_legs, bdx: two each)
    # exercise the hub tables.
    monkeypatch.setattr(linear_solve_pattern, "CHUNK_ROWS", 100)
    robots = [kamino.models.dr_legs(), kamino.models.bdx(), kamino.models.fourbar(), kamino.models.olaf()]
    order = [0, 1, 0, 2, 3, 1, 0]
    model = kamino.concat([robots[k] for k in order])
    tab = row_tables(model)
    ft = linear_solve_pattern.fixed_row_types(model)
    assert len(ft.rows) == len(robots)  # one analysis per robot type, not per world
    for w, (rows, tails) in enumerate(zip(fixed_row_bodies(model), linear_solve_pattern.all_tail_row_bodies(model, tab),
                                          strict=True)):
        np.testing.assert_array_equal(ft.rows[ft.world_type[w]], rows)
        lim, pairs = tail_row_bodies(model, tab, w)
        np.testing.assert_array_equal(tails[0], lim)
        assert (tails[1] is None) == (pairs is None)
        if pairs is not None:
            np.testing.assert_array_equal(tails[1], pairs)
    for hub_min_rows in (None, 24):
        for maxdim_of in ("row_maxdim", "row_fixed"):  # PADMM's factor with its tail rows; post-stabilisation's
            alone = []
            for robot in robots:
                wm = warp_model(robot, np.float32, "cpu").arrays
                built = linear_solve.build(robot, np.float32, "cpu", getattr(wm, maxdim_of).numpy(),
                                         hub_min_rows=hub_min_rows, hub_row0=wm.row_maxdim.numpy())
                alone.append(_world_pattern(built.arrays, robot, 0))
                ref = _reference_pattern(robot, int(getattr(wm, maxdim_of).numpy()[0]), hub_min_rows,
                                         int(wm.row_maxdim.numpy()[0]))
                assert alone[-1].keys() == ref.keys()
                for name, expected in ref.items():
                    np.testing.assert_array_equal(alone[-1][name], expected, err_msg=name)
            wm = warp_model(model, np.float32, "cpu").arrays
            built = linear_solve.build(model, np.float32, "cpu", getattr(wm, maxdim_of).numpy(),
                                     hub_min_rows=hub_min_rows, hub_row0=wm.row_maxdim.numpy())
            assert built.hubs == sum(len(alone[k]["hub_body"]) for k in order)
            if hub_min_rows is not None:
                assert built.hubs > 0
            for w, k in enumerate(order):
                got = _world_pattern(built.arrays, model, w)
                assert got.keys() == alone[k].keys(), (w, k)
                for name, expected in alone[k].items():
                    np.testing.assert_array_equal(got[name], expected, err_msg=f"world {w} ({k}), {name}")


def test_setup_tables_are_cached_only_under_frozen_models():
    # row_tables and fixed_row_types are cached under the model object only when the model's arrays are read-only
    # (as every built, concatenated or replicated model's are): such an entry cannot go stale. A model whose arrays
    # are writeable gets fresh tables on every call. A copy of the model (pickle, copy.copy) builds its own.
    import copy
    import dataclasses

    from kamino.model import is_frozen

    model = kamino.replicate(kamino.models.bdx(), 3)
    assert is_frozen(model)
    tab, ft = row_tables(model), linear_solve_pattern.fixed_row_types(model)
    assert row_tables(model) is tab and linear_solve_pattern.fixed_row_types(model) is ft
    assert not tab.cts_joint.flags.writeable and not ft.world_type.flags.writeable
    assert list(ft.world_type) == [0, 0, 0] and len(ft.rows) == 1
    twin = copy.copy(model)
    assert row_tables(twin) is not tab and linear_solve_pattern.fixed_row_types(twin) is not ft
    loose = dataclasses.replace(model, **{f.name: np.array(getattr(model, f.name)) for f in dataclasses.fields(model)
                                          if isinstance(getattr(model, f.name), np.ndarray)})
    assert not is_frozen(loose)
    assert row_tables(loose) is not row_tables(loose)
    assert linear_solve_pattern.fixed_row_types(loose) is not linear_solve_pattern.fixed_row_types(loose)
    np.testing.assert_array_equal(row_tables(loose).cts_joint, tab.cts_joint)


def test_build_uploads_only_the_tables_its_kernels_read():
    # memory: the one-thread factor kernels read the row-order update pairs (upd_*), solver_lanes.factor the
    # column-order triples (fan_*), and only the 32-thread kernels the column index (cptr, cent, crow); each build
    # holds its schedule's, the other tables a single 0. Both lists count the same fill-in updates (a type's, shared
    # by its worlds), and the values they give are checked by the factor tests of each schedule.
    model = kamino.replicate(kamino.models.dr_legs(), 3)
    maxdim = warp_model(model, np.float32, "cpu").arrays.row_maxdim.numpy()
    thread = linear_solve.build(model, np.float32, "cpu", maxdim).arrays
    warp = linear_solve.build(model, np.float32, "cpu", maxdim, per_world=True).arrays
    post = linear_solve.build(model, np.float32, "cpu", maxdim, per_world=True, fan=False).arrays  # factor_fixed's
    n_upd = thread.upd_a.shape[0]
    assert n_upd > 1000 and thread.nnz.numpy()[0] == warp.nnz.numpy()[0]
    assert warp.fan_a.shape[0] == warp.fan_tgt.shape[0] == n_upd + 1  # + the clamped loads' trailing 0
    for name in ("fan_ptr", "fan_tgt", "fan_a", "fan_b", "cptr", "cent", "crow"):
        assert getattr(thread, name).shape[0] == 1, name
    for name in ("upd_ptr", "upd_a", "upd_b"):
        assert getattr(warp, name).shape[0] == 1, name
        assert getattr(post, name).shape[0] == getattr(thread, name).shape[0], name
    for name in ("cptr", "cent", "crow"):
        assert getattr(post, name).shape[0] == getattr(warp, name).shape[0] > 1, name
    assert post.fan_a.shape[0] == 1
