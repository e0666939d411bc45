"""The cooperative PADMM kernels — 32 threads per world (``Stepper(padmm="warp")``, padmm_warp.py) and one tile
block per world (``padmm="block"``, padmm_tile.py) — against the one-thread-per-world kernel, on Warp's CPU
device (cooperative CPU blocks)."""

import numpy as np
import pytest

import kamino
from kamino.warp_backend import backend as wb
from kamino.warp_backend.pipeline import Stepper


def _run(model, cfg, padmm, steps):
    st = Stepper(model, cfg, np.float64, "cpu", padmm=padmm)
    wb.load_state(st, kamino.init_state(model, dtype=np.float64), None)
    iters, forces = [], []
    for _ in range(steps):
        st.run(1)
        iters.append(st.work.iters.numpy().copy())
        forces.append(st.work.impulse.numpy().copy())
    return st.work.q.numpy().view(np.float64).reshape(-1, 7), np.array(iters), st


@pytest.mark.parametrize("padmm", ["warp", "block"])
def test_cooperative_kernels_solve_what_the_thread_kernel_solves(padmm):
    # a loop (four-bar) and a contact world (two stacked boxes: cone projection on contact triples, De Saxcé)
    # in one heterogeneous model, with curvature refinement (a second PADMM pass on the same factor); float64
    # at a tight tolerance, so the kernels, which differ only in who does the arithmetic (and in the order of
    # the factorisation's sums), agree to rounding (1e-12 m over 40 steps) and take the same iterations
    model = kamino.concat([kamino.models.fourbar(), kamino.models.box_stack(2)])
    cfg = kamino.SolverConfig(dt=1.0 / 240.0, tolerance=1e-9, curvature_refinement=True, penalty="fixed")
    q_thread, it_thread, _ = _run(model, cfg, "thread", 40)
    q_block, it_block, st = _run(model, cfg, padmm, 40)
    if padmm == "block":
        assert st.tile_R == 64  # box_stack(2): 48 rows of capacity, padded to 64 threads
    np.testing.assert_allclose(q_block, q_thread, rtol=0, atol=1e-12)
    np.testing.assert_array_equal(it_block, it_thread)
    assert it_block.min() >= 2 and it_block.max() < cfg.max_iterations  # converged, not capped
    assert bool(np.all(st.work.converged.numpy()))


def test_block_kernel_rejects_what_it_cannot_solve():
    model = kamino.models.fourbar()
    for padmm in ("block", "warp"):
        with pytest.raises(ValueError, match="linear_solver='cr'"):
            Stepper(model, kamino.SolverConfig(jacobian="sparse", linear_solver="cr"), np.float32, "cpu", padmm=padmm)
    with pytest.raises(ValueError, match="shared memory"):
        Stepper(kamino.models.chain_of_loops(8), kamino.SolverConfig(), np.float64, "cpu", padmm="block")
    with pytest.raises(ValueError, match="padmm must be"):
        Stepper(model, kamino.SolverConfig(), np.float32, "cpu", padmm="tile")
