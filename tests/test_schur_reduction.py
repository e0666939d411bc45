"""``SolverConfig.reduction = "schur"``: PADMM on the Schur complement of the unbounded always-active rows
(kamino/jax_ref/reduction.py, docs/formulation.md §7.11) solves the same problem as PADMM on every row."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import kamino
from kamino.jax_ref import reduction, solver


def _loop_problem(dtype=np.float64):
    """One world's dual problem with the structure of a robot with loops standing on the ground: four free bodies
    (random masses and inertias), 11 unbounded fixed rows of which 2 are sums of others (the redundant rows of a
    closed loop: ``D_FF`` has two null eigenvalues) and one an actuator row with regularisation ``R``, one
    effort-limited actuator row (fixed, bounded), one active and one inactive (padded) limit row, and two contacts
    (``mu = 0.8``) that the free velocity drives into the ground; ``v_f = J u_f`` (the redundant rows' right-hand side
    lies in the range of ``D_FF``, as a step's does). Returns the solver's arguments and ``(M^-1,
    J)``."""
    rng = np.random.default_rng(3)
    nb = 4
    blocks = []
    for _ in range(nb):
        m = rng.uniform(0.5, 2.0)
        R = np.linalg.qr(rng.standard_normal((3, 3)))[0]
        blocks.append(np.diag(np.concatenate([np.full(3, 1.0 / m), 1.0 / rng.uniform(0.005, 0.05, 3)])))
        blocks[-1][3:, 3:] = R @ blocks[-1][3:, 3:] @ R.T
    Minv = np.zeros((6 * nb, 6 * nb))
    for i, b in enumerate(blocks):
        Minv[6 * i:6 * i + 6, 6 * i:6 * i + 6] = b
    J_b = rng.standard_normal((8, 6 * nb))
    J_red = np.stack([J_b[0] + 0.5 * J_b[3], J_b[5] - J_b[7]])  # redundant loop rows
    J_act = rng.standard_normal((1, 6 * nb))
    J_eff = rng.standard_normal((1, 6 * nb))
    J_lim = rng.standard_normal((2, 6 * nb))
    J_con = rng.standard_normal((6, 6 * nb))
    J = np.concatenate([J_act, J_eff, J_b, J_red, J_lim, J_con])
    n, n_fixed, n_box = J.shape[0], 12, 14
    row_mask = np.ones(n, bool)
    row_mask[n_fixed + 1] = False  # an inactive limit row: a zero row of J, as the step assembles it
    J[~row_mask] = 0.0
    Rreg = np.zeros(n)
    Rreg[0], Rreg[1] = 0.05, 0.05
    D = J @ Minv @ J.T + np.diag(Rreg)
    v_f = J @ (0.3 * rng.standard_normal(6 * nb))  # J u_f: consistent on the redundant rows, as in a step
    v_f[n_box + 2::3] = -np.abs(v_f[n_box + 2::3]) - 0.2  # approaching contacts
    v_f[n_fixed] = -3.0  # an approaching limit
    lo = np.concatenate([[-np.inf, -0.01], np.full(10, -np.inf), [0.0, 0.0]])
    hi = np.concatenate([[np.inf, 0.01], np.full(10, np.inf), [np.inf, np.inf]])
    mu = np.full(2, 0.8)
    args = (D, v_f, lo, hi, mu, row_mask, np.zeros(n), np.zeros(n))
    return tuple(np.asarray(a, dtype) if a.dtype != bool else a for a in args), n_fixed, Minv, J


def _solve(args, n_fixed, cfg, refine=None):
    return jax.jit(lambda *a: solver.solve(*a, cfg, refine, None, n_fixed))(*args)


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_schur_solve_matches_the_full_solve(dtype):
    """On :func:`_loop_problem` the reduced solve's body velocities ``M^-1 J^T lambda`` (the impulses themselves are
    not unique along the redundant rows) and constraint velocities equal the full solve's, and its residual on the
    eliminated rows, ``|P (D lambda + v_f)|`` on ``F``, is no larger. Bounds: both solves stop at the residual
    ``tolerance`` (1e-8 in float64; 1e-4 in float32, ~1e3 float32 rounding of the unit-diagonal scaled problem),
    and a velocity error ``tol`` on a row of effective mass ``1 / D_ii`` is an impulse error ``tol / D_ii`` that moves
    the bodies by ``M^-1 J^T`` of it: 100 ``tol`` leaves a margin for the conditioning of ``D`` (measured: float64
    2e-9, float32 2e-5)."""
    tol = 1e-8 if dtype == np.float64 else 1e-4
    args, n_fixed, Minv, J = _loop_problem(dtype)
    cfg = kamino.SolverConfig(tolerance=tol, max_iterations=1000)
    full = _solve(args, n_fixed, cfg)
    red = _solve(args, n_fixed, cfg.replace(reduction="schur"))
    D, v_f, lo, hi, _, row_mask = (np.asarray(a, np.float64) for a in args[:6])
    row_mask = row_mask.astype(bool)
    assert bool(full.converged) and bool(red.converged)
    lam_a, lam_b = np.asarray(full.impulse, np.float64), np.asarray(red.impulse, np.float64)
    assert np.all(lam_b[~row_mask] == 0.0)
    assert lam_b[n_fixed] > 0.0 and np.all(lam_b[14 + 2::3] > 0.0)  # the limit and both contacts push
    du = Minv @ J.T @ (lam_a - lam_b)
    assert np.abs(du).max() <= 100 * tol, np.abs(du).max()
    dv = np.asarray(full.velocity, np.float64) - np.asarray(red.velocity, np.float64)
    assert np.abs(dv).max() <= 100 * tol, np.abs(dv).max()
    f = np.asarray(reduction.unbounded_rows(jnp.asarray(lo), jnp.asarray(hi), jnp.asarray(row_mask), n_fixed))
    assert f.sum() == 11  # the actuator row and every bilateral row; the effort-limited row stays in T
    ps = 1.0 / np.sqrt(np.where(row_mask, np.diag(D), 1.0))
    res_a = np.abs(ps * (D @ lam_a + v_f))[f].max()
    res_b = np.abs(ps * (D @ lam_b + v_f))[f].max()
    assert res_b <= res_a, (res_b, res_a)


def test_schur_solve_refines_and_runs_fixed_iterations_like_the_full_solve():
    """The curvature refinement (a ``refine`` map of the impulses to a new ``v_f``; here a linear one, ``J`` times a
    velocity change that every impulse moves) restarts the reduced solve on the refined ``v'_T`` and recovers
    ``lambda_F`` from the refined ``v_f``; ``fixed_iterations`` runs the same path unrolled. Both agree with the
    full solve as in :func:`test_schur_solve_matches_the_full_solve` (float64, tolerance 1e-8; measured 3e-9)."""
    args, n_fixed, Minv, J = _loop_problem()
    D, v_f = args[0], args[1]
    G = 0.02 * np.random.default_rng(5).standard_normal((J.shape[1], D.shape[0]))

    def refine(lam):
        return v_f + J @ (G @ lam)  # a change of u_f: consistent on the redundant rows

    cfg = kamino.SolverConfig(tolerance=1e-8, max_iterations=1000)
    for c in (cfg, cfg.replace(fixed_iterations=True, max_iterations=600)):
        full = _solve(args, n_fixed, c, refine)
        red = _solve(args, n_fixed, c.replace(reduction="schur"), refine)
        lam_a, lam_b = np.asarray(full.impulse), np.asarray(red.impulse)
        assert np.abs(Minv @ J.T @ (lam_a - lam_b)).max() <= 1e-6
        assert np.abs(np.asarray(full.velocity) - np.asarray(red.velocity)).max() <= 1e-6


def test_bad_reduction_is_refused():
    """A reduction other than ``"none"``/``"schur"`` raises naming the field; the Warp backend refuses ``"schur"``
    (not implemented there) instead of silently solving the full problem."""
    with pytest.raises(ValueError, match="reduction"):
        kamino.SolverConfig(reduction="lu")
    pytest.importorskip("warp")
    model = kamino.models.pendulum()
    cfg = kamino.SolverConfig(reduction="schur")
    with pytest.raises(ValueError, match="reduction='schur' is implemented in the JAX reference only"):
        kamino.step(model, kamino.init_state(model), config=cfg, backend="warp")
