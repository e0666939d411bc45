"""``SolverConfig.reduction = "schur"``: PADMM on the Schur complement of the unbounded always-active rows
(kamino/jax_ref/reduction.py, docs/formulation.md §7.11) solves the same problem as PADMM on every row."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import kamino
from kamino.jax_ref import reduction, solver
from tests.helpers import JAX_GPU_TIER


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


@pytest.mark.parametrize(("dtype", "penalty"), [(np.float64, "adaptive"), (np.float32, "adaptive"),
                                              (np.float64, "fixed")])
def test_schur_solve_matches_the_full_solve(dtype, penalty):
    """On :func:`_loop_problem` the reduced solve's body velocities ``M^-1 J^T lambda`` (the impulses themselves are
    not unique along the redundant rows) and constraint velocities equal the full solve's, and its residual on the
    eliminated rows, ``|P (D lambda + v_f)|`` on ``F``, is no larger. Bounds: both solves stop at the residual
    ``tolerance`` (1e-8 in float64; 1e-4 in float32, ~1e3 float32 rounding of the unit-diagonal scaled problem),
    and a velocity error ``tol`` on a row of effective mass ``1 / D_ii`` is an impulse error ``tol / D_ii`` that moves
    the bodies by ``M^-1 J^T`` of it: 100 ``tol`` leaves a margin for the conditioning of ``D`` (measured: float64
    2.7e-9, float32 1.2e-5; the eliminated rows' residual 1.1e-10 against 2.2e-10, float32 1.5e-7 against 2.4e-6).
    Under the fixed penalty the elimination keeps its small shift (with PADMM's ``eta + rho`` the two solves differed
    by 0.12)."""
    tol = 1e-8 if dtype == np.float64 else 1e-4
    args, n_fixed, Minv, J = _loop_problem(dtype)
    cfg = kamino.SolverConfig(tolerance=tol, max_iterations=1000).replace(**{"penalty.mode": penalty})
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
    full solve as in :func:`test_schur_solve_matches_the_full_solve` (float64, tolerance 1e-8; bound 100 ``tol``,
    measured 2.7e-8)."""
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
    """A reduction other than ``"none"``/``"schur"`` raises naming the field; the Warp backend refuses ``"schur"`` on
    the schedules that do not reduce (one thread per world; Conjugate Residual) instead of silently solving the full
    problem."""
    with pytest.raises(ValueError, match="reduction"):
        kamino.SolverConfig(reduction="lu")
    pytest.importorskip("warp")
    from kamino.warp_backend.pipeline import Stepper

    model = kamino.models.pendulum()
    cfg = kamino.SolverConfig(reduction="schur")
    for padmm, c in (("thread", cfg), ("warp", cfg.replace(**{"warp.linear_solver": "cr"}))):
        with pytest.raises(ValueError, match="reduction='schur' runs on the Warp backend's 32-thread schedule"):
            Stepper(model, c, np.float32, "cpu", padmm=padmm)


def _dr_legs_rollout(reduction: str, worlds: int = 4, steps: int = 32, seed: int = 0, backend: str = "jax",
                     random_start: bool = True):
    """dr_legs in ``worlds`` loop-closed random configurations (``kamino.bench.loads.random_configurations``, half
    the actuator ranges; with ``random_start=False`` its standing pose) under random PD targets redrawn every 8 steps
    (the RL load of ``kamino.bench.loads.rl_control_map``), float32, ``steps`` steps of 2.5 ms on ``backend``: the
    first step's ``body_u``, the largest anchor distance over the rollout, the failed worlds and the mean
    iterations."""
    from kamino.bench import loads
    from kamino.bench.convergence import ClosureProbe

    base = kamino.models.dr_legs()
    model = kamino.replicate(base, worlds)
    cfg = kamino.SolverConfig(dt=0.0025, reduction=reduction)
    state = kamino.init_state(model, np.float32)
    if random_start:
        state = state.replace(body_q=jnp.asarray(loads.random_configurations(base, model, loads.RL_FRACTION, seed,
                                                                             np.float32)))
    probe = ClosureProbe(base)
    offset, scale, _ = loads.rl_control_map(base)
    rng = np.random.default_rng(seed)
    dofs = base.actuator_dof[None, :] + base.num_dofs * np.arange(worlds)[:, None]
    closure, u_first, iters = [probe(np.asarray(state.body_q))], None, []
    for k in range(steps):
        if k % 8 == 0:
            target = np.zeros(model.num_dofs, np.float32)
            target[dofs.reshape(-1)] = (offset + scale * rng.uniform(-1, 1, (worlds, base.num_actuators))).reshape(-1)
            control = kamino.Control(position_target=jnp.asarray(target))
        state = kamino.step(model, state, control, config=cfg, backend=backend)
        u_first = np.asarray(state.body_u) if u_first is None else u_first
        closure.append(probe(np.asarray(state.body_q)))
        iters.append(np.asarray(state.info.iterations))
    return u_first, float(np.max(closure)), int(np.sum(np.asarray(state.info.failed))), float(np.mean(iters))


@pytest.mark.gpu
@JAX_GPU_TIER[1]
def test_schur_rollout_of_dr_legs_keeps_its_loops_closed():
    """dr_legs under an RL-like load (:func:`_dr_legs_rollout`, 4 worlds x 32 steps, float32): with the reduction the
    loops stay as closed as with the full solve (largest anchor distance within 2x; measured on the CPU: 1.84e-6 m for
    both, and on 16 worlds x 64 steps 2.09e-6 m against 2.14e-6 m) and no world fails. The first step's body
    velocities agree to the solves' stopping error: ``tolerance`` (1e-3) on the heaviest row, up to
    ``RESIDUAL_LOOSENING_MAX`` (30) times it on a light row.
    In the gpu tier: dr_legs' JAX step compiles for ~20 s per configuration on CI's CPU."""
    u_full, closure_full, failed_full, _ = _dr_legs_rollout("none")
    u_red, closure_red, failed_red, _ = _dr_legs_rollout("schur")
    assert failed_full == 0 and failed_red == 0
    assert closure_red <= 2.0 * closure_full, (closure_red, closure_full)
    assert np.abs(u_red - u_full).max() <= 30 * 1e-3, np.abs(u_red - u_full).max()  # measured 6.8e-3 (CPU)


@pytest.mark.gpu
@JAX_GPU_TIER[1]
def test_schur_gradient_of_a_four_bar_step_is_the_full_solves():
    """``jax.grad`` of a readout of one four-bar step (a planar loop: three redundant rows in ``F``; curvature
    refinement: two chained roots) with respect to a crank effort, the coupler's mass and the crank hinge's damping
    is the full solve's: the implicit derivative is the full problem's natural map at either solution, which differ
    by the solves' stopping error (``tolerance = 1e-6``), so the gradients agree to 1e-4 relative (measured 5e-6 at
    ``tolerance = 1e-3``). In the gpu tier: the two reverse passes compile for ~50 s on CI's CPU."""
    import dataclasses

    model = kamino.models.fourbar(damping=0.05)
    s0 = kamino.init_state(model)
    rng = np.random.default_rng(0)
    wq, wu = jnp.asarray(rng.standard_normal(s0.body_q.shape)), jnp.asarray(rng.standard_normal(s0.body_u.shape))
    coupler = model.body_names.index("coupler")
    grads = []
    for reduction_ in ("none", "schur"):
        sim = kamino.Simulator(model, kamino.SolverConfig(dt=0.01, tolerance=1e-6, reduction=reduction_),
                               backend="jax")
        pm, tables = sim.parameters(jnp.float64)

        def readout(theta, sim=sim, pm=pm, tables=tables):
            control = kamino.Control(dof_effort=jnp.zeros(model.num_dofs).at[0].set(theta[0]))
            p = (dataclasses.replace(pm, mass=pm.mass.at[0, coupler].multiply(1.0 + theta[1]),
                                     dof_damping=pm.dof_damping.at[0, 0].add(theta[2])), tables)
            s = sim.step_with(p, s0, control)
            return jnp.sum(wq * s.body_q) + 0.1 * jnp.sum(wu * s.body_u)

        grads.append(np.asarray(jax.jit(jax.grad(readout))(jnp.zeros(3))))
    assert np.all(np.abs(grads[0]) > 1e-4), grads  # every input moves the readout
    np.testing.assert_allclose(grads[1], grads[0], rtol=1e-4, atol=0.0)


def test_schur_rollout_on_the_warp_lanes_keeps_the_loops_closed():
    """The Warp backend's 32-thread schedule under ``reduction="schur"`` (solver_lanes.py; the threads run as fibers
    on the CPU) on :func:`_dr_legs_rollout` from the standing pose (2 worlds x 24 steps, float32): the loops stay as
    closed as with the full solve (largest anchor distance within 2x, the bound of the JAX reference's test above;
    measured 1.88e-6 m against 1.88e-6 m, the JAX reference's 1.86e-6 m and 1.88e-6 m), no world fails, the first
    step's body velocities agree with the full solve's to twice ``RESIDUAL_LOOSENING_MAX`` (30) times ``tolerance``
    (1e-3): each solve stops within its own 30 tolerances on a light row, so the two may differ by twice that
    (measured 0.031 rad/s; the JAX reference's two solves 0.036), and the reduced solve takes the full solve's
    iterations to 1.5x (measured 28.7 against 21.4 on average; the JAX reference 28.8 against 21.9: the reduced
    problem's iterations are the reference's, docs/formulation.md §7.11)."""
    pytest.importorskip("warp")
    u_full, closure_full, failed_full, it_full = _dr_legs_rollout("none", 2, 24, backend="warp", random_start=False)
    u_red, closure_red, failed_red, it_red = _dr_legs_rollout("schur", 2, 24, backend="warp", random_start=False)
    assert failed_full == 0 and failed_red == 0
    assert closure_red <= 2.0 * closure_full, (closure_red, closure_full)
    assert np.abs(u_red - u_full).max() <= 2 * 30 * 1e-3, np.abs(u_red - u_full).max()
    assert it_red <= 1.5 * it_full, (it_red, it_full)


@pytest.mark.gpu
@pytest.mark.skipif(not __import__("warp").is_cuda_available(), reason="needs a CUDA device for Warp")
def test_schur_rollout_of_dr_legs_on_the_warp_lanes_keeps_its_loops_closed():
    """The Warp backend's 32-thread schedule under ``reduction="schur"`` on :func:`_dr_legs_rollout` (4 worlds x 32
    steps, float32): its loops stay as closed as with the full solve (largest anchor distance within 2x, as the JAX
    reference's test above; measured on the CPU 1.84e-6 m against 1.83e-6 m, the JAX reference's reduced solve 1.84e-6
    m) and no world fails; the first step's body velocities agree with the full solve's to the solves' stopping error,
    ``RESIDUAL_LOOSENING_MAX`` (30) times ``tolerance`` (1e-3) on a light row (measured 6.8e-3 on the CPU, as on the
    JAX reference). In the gpu tier: the random configurations' inverse kinematics take ~4 s on CI's CPU."""
    u_full, closure_full, failed_full, _ = _dr_legs_rollout("none", backend="warp")
    u_red, closure_red, failed_red, _ = _dr_legs_rollout("schur", backend="warp")
    assert failed_full == 0 and failed_red == 0
    assert closure_red <= 2.0 * closure_full, (closure_red, closure_full)
    assert np.abs(u_red - u_full).max() <= 30 * 1e-3, np.abs(u_red - u_full).max()
