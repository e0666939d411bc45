"""``kamino.bench.roofline``: its counts come from the factor the Warp backend builds, agree with the textbook counts
on dense patterns, and its table is throughput x cost per world-step."""

import numpy as np
import pytest


@pytest.fixture(scope="module")
def roofline():
    pytest.importorskip("warp")
    from kamino.bench import roofline

    return roofline


def test_fourbar_counts_are_the_symbolic_factors(roofline):
    """The counts are read back from the stepper's ``linear_solve.Pattern``; they must be what
    ``linear_solve_pattern.symbolic``
    and ``tail_patterns`` give for the same world (the same hubs), with the tail at the capacity the stepper
    allocates: the four-bar's 3 limit rows on their own patterns, its 8 contact slots on the widest pair's."""
    from kamino.tables import row_tables
    from kamino.warp_backend import linear_solve_pattern

    shape = roofline.scene_shape("fourbar")
    model, _ = roofline.tb.load_scene("fourbar")
    rows = linear_solve_pattern.fixed_row_bodies(model)[0]
    sym = linear_solve_pattern.symbolic(rows, linear_solve_pattern.hub_bodies(rows, linear_solve_pattern.HUB_MIN_ROWS))
    f = shape.factor
    assert (f.n_fixed, f.nnz, f.n_upd) == (18, 146, 644)  # docs/warp_backend.md's table: nnz(L_f) = 146
    assert (f.n_fixed, f.n_pos, f.nnz, f.n_upd) == (sym.n_real, len(sym.perm), sym.nnz, len(sym.upd_a))
    assert roofline.fixed_factor_flops(f) == sym.nnz + 2 * len(sym.upd_a)
    lim, pairs = linear_solve_pattern.tail_row_bodies(model, row_tables(model), 0)
    pats = linear_solve_pattern.tail_patterns(rows, sym, lim, pairs)
    n_lim, slots = len(lim), int(model.world_contact_capacity[0])
    assert f.n_tail == n_lim + 3 * slots == 27
    for got, want in zip(f.tail[:n_lim], pats[:n_lim], strict=True):
        np.testing.assert_array_equal(got, want)
    widest = max(len(p) for p in pats[n_lim:])
    assert all(len(p) == widest for p in f.tail[n_lim:])
    assert shape.rows.n_rows == f.n_fixed + f.n_tail and roofline.is_upper_bound(shape)


@pytest.mark.parametrize("n", [1, 5, 12])
def test_dense_patterns_cost_the_textbook_counts(roofline, n):
    """On a dense pattern (every row on one body: nothing to skip) the sparse counts are the dense ones: ``L_f`` has
    ``n (n + 1) / 2`` entries and ``(n^3 - n) / 6`` multiply-adds, its two sweeps ``2 n (n + 1)`` FLOP (a reciprocal
    and a product per diagonal); a dense tail of ``n`` rows solves in ``2 n^2`` (a division per diagonal) and
    factorises in ``n`` shifts, ``n`` roots, ``n (n - 1) / 2`` divisions and ``(n^3 - n) / 6`` multiply-adds."""
    from kamino.warp_backend import linear_solve_pattern

    sym = linear_solve_pattern.symbolic(np.zeros((n, 2), np.int64) - np.array([0, 1]))  # bodies (0, -1) on every row
    f = roofline.FactorShape(n_fixed=n, n_pos=n, nnz=sym.nnz, n_upd=len(sym.fan_tgt))
    assert f.nnz == n * (n + 1) // 2 and f.n_upd == (n**3 - n) // 6
    assert roofline.solve_flops(f) == 2 * n * (n + 1)
    assert roofline.factor_flops(f) == n * (n + 1) // 2 + (n**3 - n) // 3
    empty = np.zeros(0, np.int64)
    tail = roofline.FactorShape(n_fixed=0, n_pos=0, nnz=0, n_upd=0, tail=(empty,) * n, tail_upd=(0,) * n,
                                tail_pid=(0,) * n)
    assert roofline.solve_flops(tail) == 2 * n * n
    assert roofline.factor_flops(tail) == 2 * n + n * (n - 1) // 2 + (n**3 - n) // 3


def test_tail_patterns_cost_their_overlaps(roofline):
    """Two tail rows on the patterns {0, 1, 2} (4 substitution pairs) and {1, 2} (1 pair) of a 3-position ``L_f``:
    ``L_tf`` costs a division per entry and 2 per pair (3 + 8 + 2 + 2), the Schur complement 2 per shared position of
    the pairs (0, 0), (1, 0), (1, 1) (2 x (3 + 2 + 2)); a solve costs 2 per entry of ``L_tf`` in each of its two
    passes and ``2 n_t^2`` for ``L_t``."""
    f = roofline.FactorShape(n_fixed=3, n_pos=3, nnz=6, n_upd=4, tail=(np.arange(3), np.array([1, 2])),
                             tail_upd=(4, 1), tail_pid=(0, 1))
    assert roofline.tail_factor_flops(f) == (3 + 8 + 2 + 2) + 2 * (3 + 2 + 2) + roofline.dense_cholesky_flops(2)
    assert roofline.dense_cholesky_flops(2) == 2 + 2 + 1 + 2  # shifts, roots, a division, one multiply-add
    assert roofline.solve_flops(f) == 4 * 6 + 4 * 5 + 2 * 4


def test_table_is_throughput_times_cost(roofline):
    """The table's achieved rates are the record's world-steps/s times the cost per world-step, that cost the
    factorisation plus the mean iterations times an iteration plus one pass over the world's memory; peers, other
    configurations and other world counts are left out, and a record without memory takes the counted one."""
    f = roofline.FactorShape(n_fixed=4, n_pos=4, nnz=10, n_upd=10)
    shape = roofline.SceneShape(factor=f, rows=roofline.RowShape(fixed_bounded=1, fixed_free=3, limits=0, contacts=0))
    rec = {"kamino": "warp", "config": "default", "scene": "ladder8", "num_worlds": 4096, "throughput": 2e6,
           "iterations_mean": 3.0, "memory_per_world_bytes": 5e4}
    results = {"records": [rec, dict(rec, config="sparse-cr"), dict(rec, num_worlds=1024),
                           {"peer": "mujoco_warp", "scene": "ladder8", "num_worlds": 4096, "throughput": 9e6}]}
    recs = roofline.kamino_records([results], [4096])
    assert recs == [rec]
    later = dict(rec, throughput=3e6)  # the same scene and size measured again in a later file: that one counts
    assert roofline.kamino_records([results, {"records": [later]}], [4096]) == [later]
    (row,) = roofline.roofline_rows(recs, lambda s: shape, lambda s: 0.0, peak_flops=1e13, peak_bandwidth=1e12)
    it = roofline.iteration_cost(shape)
    flop = roofline.factor_flops(f) + 3.0 * it.flops
    nbytes = 3.0 * it.bytes() + 5e4
    assert row["flop"] == pytest.approx(flop) and row["bytes"] == pytest.approx(nbytes)
    assert row["flops"] == pytest.approx(2e6 * flop) and row["flops_fraction"] == pytest.approx(2e6 * flop / 1e13)
    assert row["bandwidth_fraction"] == pytest.approx(2e6 * nbytes / 1e12)
    assert not row["upper_bound"] and "<=" not in roofline.markdown([row])
    (bare,) = roofline.roofline_rows([dict(rec, memory_per_world_bytes=0.0)], lambda s: shape, lambda s: 7e4)
    assert bare["bytes"] == pytest.approx(3.0 * it.bytes() + 7e4)
