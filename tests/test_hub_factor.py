"""The hubs-last factorisation of the sparse LLT (``linear_solve_pattern.HUB_MIN_ROWS``, docs/warp_backend.md "Open
problems"): bodies on many fixed rows keep their 6 velocity unknowns in the factorised system, ordered after every fixed
row, and the factor is ``L S L^T`` with ``S = -1`` on those unknowns. dr_legs has no hub at the default threshold (48)
and two (bodies 4 and 19) at 24, which the tests use."""

import functools

import numpy as np
import pytest
import warp as wp
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

import kamino
from kamino.warp_backend import backend as wb
from kamino.warp_backend import linear_solve, linear_solve_pattern
from kamino.warp_backend.model_data import model_struct
from kamino.warp_backend.pipeline import Stepper
from kamino.warp_backend.types import types_of
from kamino.warp_backend.workspace import saturated_rows
from tests.helpers import stepper_delassus


def _stepper(model, cfg, dtype, padmm, hub_min_rows, monkeypatch, steps):
    monkeypatch.setattr(linear_solve_pattern, "HUB_MIN_ROWS", hub_min_rows)
    st = Stepper(model, cfg, dtype, "cpu", padmm=padmm)
    wb.load_state(st, kamino.init_state(model, dtype=dtype), None)
    st.run(steps)
    return st


def test_hub_entry_counts_match_the_counted_fill():
    # kamino bench memory_breakdown --hub-fill's greedy count with the hubs held back (docs/warp_backend.md: bdx 1645,
    # dr_legs 3271 with hubs of more than 24 rows); without hubs the order and pattern are today's, array for array
    for scene, hubs, nnz in [(kamino.models.bdx(), [0, 17], 1645), (kamino.models.dr_legs(), [4, 19], 3271)]:
        rows = linear_solve_pattern.fixed_row_bodies(scene)[0]
        assert list(linear_solve_pattern.hub_bodies(rows, 24)) == hubs
        assert len(linear_solve_pattern.hub_bodies(rows, linear_solve_pattern.HUB_MIN_ROWS)) == 0
        sym = linear_solve_pattern.symbolic(rows, linear_solve_pattern.hub_bodies(rows, 24), 1000)
        assert sym.nnz == nnz and sym.n_real == len(rows)
        assert list(sym.perm[len(rows):]) == list(range(1000, 1012))  # the hubs' virtual rows, in position order
        a, b = linear_solve_pattern.symbolic(rows), linear_solve_pattern.symbolic(rows, np.zeros(0, np.int64))
        for f in ("perm", "row_ptr", "col", "colrow", "div", "upd_a", "upd_b", "cent", "crow", "fan_tgt", "fan_a"):
            np.testing.assert_array_equal(getattr(a, f), getattr(b, f))


def _hub_bodies_loop(bodies, min_rows):
    """``linear_solve_pattern.hub_bodies`` as a plain loop (its former code): each row's bodies as a set, counted per
    body."""
    if min_rows is None or len(bodies) == 0:
        return np.zeros(0, np.int64)
    count: dict[int, int] = {}
    for row in bodies:
        for b in set(int(x) for x in row if x >= 0):
            count[b] = count.get(b, 0) + 1
    return np.asarray(sorted(b for b, c in count.items() if c > min_rows), np.int64)


@settings(max_examples=200, deadline=None, derandomize=True, database=None)
@given(bodies=hnp.arrays(np.int64, st.tuples(st.integers(0, 40), st.integers(1, 4)), elements=st.integers(-1, 7)),
       min_rows=st.one_of(st.none(), st.integers(0, 12)))
def test_hub_bodies_counts_each_body_once_per_row(bodies, min_rows):
    # random body tables: -1 padding anywhere, a body repeated within a row, rows of the width 4 of fixed_row_bodies
    # and narrower ones, no rows at all
    hubs = linear_solve_pattern.hub_bodies(bodies, min_rows)
    assert hubs.dtype == np.int64
    np.testing.assert_array_equal(hubs, _hub_bodies_loop(bodies, min_rows))


@functools.cache
def _solve_kernel(np_dtype):
    """``x <- A^-1 x`` on every world's rows with the sparse factor (``linear_solve.solve_inplace``)."""
    solve_inplace = linear_solve.sparse_llt_kernels(np_dtype).solve_inplace

    @wp.kernel(module="unique", enable_backward=False)
    def solve(m: model_struct(np_dtype), row_stride: int, n_rows: wp.array(dtype=wp.int32),
              sp: linear_solve.pattern_struct(np_dtype), x: wp.array(dtype=types_of(np_dtype).scalar)):
        wid = wp.tid()
        solve_inplace(m, sp, row_stride, wid, n_rows[wid], x)

    return solve


def _dense_A(st, shift_f, shift_b, eta):
    """World 0's ``A = P (J M^-1 J^T + R) P + shifts`` on its active rows, in float64, from the stepper's rows (the
    matrix that ``linear_solve`` assembles and factorises, without hubs)."""
    w, m = st.work, st.wm.arrays
    rs, n = w.row_stride, int(w.n_rows.numpy()[0])
    P = w.P.numpy().astype(np.float64)[: n * rs : rs]
    sat = saturated_rows(w.row_info.numpy())[: n * rs : rs]
    D = stepper_delassus(st, n, rs)
    nf = int(m.row_fixed.numpy()[0])
    shift = np.where(np.arange(n) < nf, np.where(sat != 0, shift_b, shift_f), eta + float(w.rho_u.numpy()[0]))
    return P[:, None] * D * P[None, :] + np.diag(shift), n, rs


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_hub_factor_solves_the_delassus_system(dtype, monkeypatch):
    # dr_legs standing after 12 steps, hubs of more than 24 rows: 204 fixed rows, 12 hub unknowns and a tail of
    # active limits and foot contacts. The factor is re-assembled and factorised with known shifts, solves four random
    # right-hand sides, and is compared with a float64 dense solve of the same A. The hubs' virtual rows are set to
    # NaN first: their right-hand side must be taken as 0, not read.
    # Tolerances: float64 to 1e-9 relative (cond(A) ~ 4e4, double rounding ~1e-16 per operation); float32 to 2e-3,
    # the bound cond(A) eps32 ~ 2.4e-3 of a backward-stable factor (docs/warp_backend.md measured 4.1e-4 for this
    # scene's hubs-last factor, 4.3e-4 for today's Cholesky), and no worse than twice today's factor's error.
    model = kamino.models.dr_legs()
    cfg = kamino.SolverConfig(dt=0.0025)
    errors = {}
    for hub_min_rows in (24, None):
        st = _stepper(model, cfg, dtype, "thread", hub_min_rows, monkeypatch, 12)
        assert st.sf.hubs == (2 if hub_min_rows else 0)
        shift_f, shift_b = st.padmm_shifts
        nblk = st.wm.blocks_per_row
        w = st.work
        st._launch(st.spk.assemble_fixed, (1, st.sf.max_nnz),
                      inputs=[nblk, shift_f, shift_b, w.row_stride, w.row_body, w.row_J, w.row_info, w.reg, w.P,
                              w.inertia_w, w.inv_inertia_w], outputs=[st.sp])
        st._launch(st.spk.assemble_tail, (1, st.wm.max_rows),
                      inputs=[nblk, w.row_stride, w.n_rows, w.row_body, w.row_J, w.row_info, w.ct_pair, w.reg, w.P,
                              w.inv_inertia_w], outputs=[st.sp])
        st._launch(st.spk.factor, 1, inputs=[cfg.penalty.eta, w.row_stride, w.n_rows, w.rho_u], outputs=[st.sp])
        A, n, rs = _dense_A(st, shift_f, shift_b, cfg.penalty.eta)
        assert n > 204  # active limits or contacts: the tail is exercised
        rng = np.random.default_rng(0)
        err = 0.0
        for _ in range(4):
            b = rng.standard_normal(n)
            x = st.work.x.numpy()
            x[:] = np.nan if hub_min_rows else 0.0
            x[: n * rs : rs] = b
            st.work.x.assign(x)
            wp.launch(_solve_kernel(np.dtype(dtype)), dim=1, inputs=[st.wm.arrays, w.row_stride, w.n_rows, st.sp, w.x],
                      device="cpu")
            got = st.work.x.numpy().astype(np.float64)[: n * rs : rs]
            ref = np.linalg.solve(A, b)
            err = max(err, np.linalg.norm(got - ref) / np.linalg.norm(ref))
        errors[hub_min_rows] = err
    tol = 1e-9 if dtype == np.float64 else 2e-3
    assert errors[24] < tol, errors
    assert errors[24] <= 2 * errors[None] + (1e-12 if dtype == np.float64 else 0.0), errors


@pytest.mark.parametrize("padmm", ["thread", "warp"])
def test_stepping_with_hubs_matches_stepping_without(padmm, monkeypatch):
    # dr_legs in float64 at a tight tolerance for 15 steps (feet contacts, limits, post-stabilisation with its own
    # fixed-rows factor, which has the hubs too): the two factorisations are the same float64 system eliminated in
    # different orders, so poses agree to rounding amplified by PADMM's iterations (measured 1.0e-11 m on both
    # schedules), checked to 1e-9 m, with the same iteration counts
    model = kamino.models.dr_legs()
    cfg = kamino.SolverConfig(dt=0.0025, tolerance=1e-8)
    out = {}
    for hub_min_rows in (24, None):
        st = _stepper(model, cfg, np.float64, padmm, hub_min_rows, monkeypatch, 15)
        assert st.sf.hubs == (2 if hub_min_rows else 0) and st.padmm == padmm
        assert int(st.work.n_rows.numpy()[0]) > 204
        assert bool(st.work.converged.numpy()[0]) and not bool(st.work.failed.numpy()[0])
        out[hub_min_rows] = (st.work.q.numpy().view(np.float64).reshape(-1, 7).copy(), st.work.iters.numpy().copy())
    np.testing.assert_allclose(out[24][0], out[None][0], rtol=0, atol=1e-9)
    np.testing.assert_array_equal(out[24][1], out[None][1])


def test_worlds_without_hubs_are_unchanged(monkeypatch):
    # dr_legs has no body on more than 48 fixed rows: at the default threshold its pattern is the hub-free one, array
    # for array, and the factor's values after 10 float32 steps are bit for bit those of hub_min_rows=None
    model = kamino.models.dr_legs()
    cfg = kamino.SolverConfig(dt=0.0025)
    a = _stepper(model, cfg, np.float32, "thread", linear_solve_pattern.HUB_MIN_ROWS, monkeypatch, 10)
    b = _stepper(model, cfg, np.float32, "thread", None, monkeypatch, 10)
    assert a.sf.hubs == 0 and a.wm.max_slots == a.wm.max_rows
    for f in ("perm", "row_ptr", "col", "div", "upd_a", "pat_pos", "pat_row", "n_fixed", "n_pos"):
        np.testing.assert_array_equal(getattr(a.sp, f).numpy(), getattr(b.sp, f).numpy())
    for f in ("val", "tail"):
        np.testing.assert_array_equal(getattr(a.sp, f).numpy(), getattr(b.sp, f).numpy())
    np.testing.assert_array_equal(a.work.q.numpy(), b.work.q.numpy())
