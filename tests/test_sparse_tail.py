"""The tail's ``L_tf`` patterns (kamino/warp_backend/sparse_llt.py, ``tail_patterns``): each limit or contact row
stores ``L_tf = D~_tf L_f^-T`` only on the fixed positions its bodies' rows reach up the elimination tree of ``L_f``.
The storage is right only if no nonzero falls outside the pattern; it is tight if none of the pattern is
structurally zero. Both are checked numerically on a Delassus-like matrix of the robot's structure with random
values (``J M^-1 J^T + I`` with random 6-vector blocks per row and body, ``M = I``), where structural nonzeros are
numerically nonzero with probability one."""

import sys
from pathlib import Path

import numpy as np
import pytest

import kamino
from kamino.tables import row_tables
from kamino.warp_backend import sparse_llt
from kamino.warp_backend.model_data import warp_model
from kamino.warp_backend.sparse_llt import fixed_row_bodies, symbolic, tail_patterns, tail_row_bodies

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
import memory_breakdown as mb  # the counts it predicts with


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
    # benchmarks/memory_breakdown.py's predictions are read against what is built: without hubs its minimum-degree
    # count is the built L_f's entry count (the same greedy order), and "as stored" is the built tail's K per row.
    # A drift between the counter and sparse_llt would make its predictions for new layouts (--hub-fill) meaningless.
    for scene in ("bdx", "fourbar"):
        no_hubs = mb.hub_fill(scene, thresholds=(None,))[0]
        fill = mb.tail_fill(scene)
        model, _ = mb.tb.load_scene(scene)
        maxdim = warp_model(model, np.float32, "cpu").arrays.row_maxdim.numpy()
        built = sparse_llt.build(model, np.float32, "cpu", maxdim)
        assert no_hubs["factor_entries"] == built.nnz_total == fill["L_f"]
        assert fill["widest_pattern"] == int(built.arrays.grp_tail_k.numpy()[0])
        assert fill["tail_rows"] == built.max_tail
