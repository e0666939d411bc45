"""Equivalent joint limits (``SolverConfig.redundant_limits``, ``kamino.jax_ref.solver.redundant_limits``).

A parallelogram loop driven into its +-45 deg hinge limits activates three limit rows whose Jacobian rows are
equal modulo the loop's bilateral rows: the split of the limit impulse between them is undetermined and PADMM
creeps along that null direction up to its iteration cap. Fixing ``lambda = 0`` on all but the row with the
smallest bias leaves the solution (``v+``, hence the bodies' velocities) unchanged and stops the creep.

The option is the JAX reference's only (float64; the Warp backend refuses it) and off by default, so its two
rollout tests (114 s of CI at c951ff7: the driven four-bar's compiles) are in the ``slow`` tier (README.md,
"Tests"); the rule's own tests on constructed rows stay in the default tier.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import kamino
from kamino import JointType
from kamino.bench import scene_path
from kamino.jax_ref import solver

FOURBAR_XML = scene_path("fourbar")
DT = 0.0025  # the benchmark's step and drive (kamino.bench.throughput)
# the benchmark's solver settings, with semi-implicit Euler: the steps below creep under it (the midpoint rule reads
# the limits at the midpoint pose, where these steps press them differently)
BENCH = dict(dt=DT, integrator="euler", tolerance=1e-5, max_iterations=200,
             penalty=kamino.Penalty(mode="fixed", rho=0.1, eta=1e-5),
             stabilisation=kamino.Stabilisation(baumgarte=1.0, post_stabilisation=0, curvature_refinement=False))


def _driven_fourbar_states(num_steps: int):
    """The benchmark four-bar (2 N m sin(2 pi t) on its first hinge) stepped ``num_steps`` times with the
    benchmark's settings (no rule: its warm starts carry the creeping split of the limit impulses)."""
    model = kamino.load_mjcf(FOURBAR_XML)
    dof = int(model.actuator_dof[model.world_actuator_start][0])
    cfg = kamino.SolverConfig(**BENCH)

    def control(i):
        return kamino.Control(dof_effort=jnp.zeros(model.num_dofs).at[dof].set(2.0 * jnp.sin(2 * jnp.pi * i * DT)))

    def step(s, i):  # kamino.step compiles once per configuration
        return kamino.step(model, s, control(i), config=cfg, backend="jax")

    states = [kamino.init_state(model, jnp.float64)]
    for i in range(num_steps):
        states.append(step(states[-1], i))
    return model, control, states


@pytest.fixture(scope="module")
def fourbar_in_limits():
    model, control, states = _driven_fourbar_states(113)
    return model, control, states


def _spy_on_the_rule(record):
    """A ``solver.solve`` that also reports (active limit rows, rows the rule fixes) to ``record`` at run time."""
    orig = solver.solve

    def solve(D, v_f, lo, hi, mu, row_mask, *args, **kw):
        P = solver.jacobi_preconditioner(D, row_mask, lo.shape[0])
        fixed = solver.redundant_limits(P[:, None] * D * P[None, :], jnp.where(row_mask, P * v_f, 0.0), lo, hi,
                                       row_mask)
        lim = row_mask[:lo.shape[0]] & (lo == 0) & jnp.isposinf(hi)
        jax.debug.callback(lambda a, b: record.append((int(np.sum(a)), int(np.sum(b)))), jnp.sum(lim), jnp.sum(fixed))
        return orig(D, v_f, lo, hi, mu, row_mask, *args, **kw)

    return solve


@pytest.mark.slow
def test_parallelogram_limits_stop_creeping_and_keep_the_solution(fourbar_in_limits, monkeypatch):
    model, control, states = fourbar_in_limits

    def stepper(**kw):
        cfg = kamino.SolverConfig(**{**BENCH, **kw})
        return lambda s, i: kamino.step(model, s, control(i), config=cfg, backend="jax")

    plain, rule = stepper(), stepper(redundant_limits=True)
    tight = dict(tolerance=1e-10, max_iterations=20000)
    exact, rule_exact = stepper(**tight), stepper(**tight, redundant_limits=True)
    seen = []
    it_plain, it_rule, du, du_exact = [], [], [], []
    for i in (88, 106, 112):  # the loop presses its three hinge limits together on these steps
        s = states[i]
        with monkeypatch.context() as m:  # rule's configuration is traced here first: through the spy
            m.setattr(solver, "solve", _spy_on_the_rule(seen))
            b = rule(s, i)
        a, ref, b_ref = plain(s, i), exact(s, i), rule_exact(s, i)
        it_plain.append(int(a.info.iterations[0]))
        it_rule.append(int(b.info.iterations[0]))
        assert bool(b.info.converged[0]) and bool(b_ref.info.converged[0])
        # the rule-free solve creeps: where even 20000 iterations do not reach 1e-10 its iterate still
        # violates a limit by the bias mismatch (up to 2.5e-4 m/s on recorded steps), so compare where it converged
        if bool(ref.info.converged[0]):
            du.append(np.abs(np.asarray(b.body_u) - np.asarray(ref.body_u)).max())
            du_exact.append(np.abs(np.asarray(b_ref.body_u) - np.asarray(ref.body_u)).max())
    # three active limit rows on every step, of which the rule fixes two (lambda = 0)
    assert seen == [(3, 2)] * len(it_rule), seen
    it_plain, it_rule = np.array(it_plain), np.array(it_rule)
    # without the rule most of these steps creep to the cap; with it every step converges, in a fraction
    assert np.mean(it_plain >= 200) > 0.5, it_plain
    assert it_rule.max() < 200 and it_rule.mean() < 0.6 * it_plain.mean(), (it_rule, it_plain)
    # same physics, u+ = u_f + M^-1 J^T lambda: solved to 1e-10 the rule and the rule-free problem agree to
    # the rounding of the solves (measured <= 4e-9; w agrees to 2e-7 on 134 recorded four-bar steps)
    assert len(du_exact) >= 3
    assert max(du_exact) < 1e-7, du_exact
    # at the benchmark's tol = 1e-5 (velocity residuals) the stopped iterate's u+ carries the solve's own
    # error, set by the tolerance rather than by the rule: on the recorded steps the constraint velocities of
    # converged rule-free solves are off by up to 7.5e-3 at this tolerance, those with the rule by no more;
    # here the rule's u+ is within 6.3e-4 (the rule-free one, where it converged: 1e-5 to 3e-4)
    assert max(du) < 2e-3, du


def _double_pendulum():
    """Two rods in series on hinges about +y, both limited to +-0.1 rad: gravity pushes both into a limit."""
    b = kamino.ModelBuilder(gravity=(0.0, 0.0, -9.81))
    r1 = b.add_body(mass=1.0, inertia=(0.001, 0.021, 0.021), pos=(0.25, 0, 1))
    r2 = b.add_body(mass=0.5, inertia=(0.0005, 0.01, 0.01), pos=(0.75, 0, 1))
    b.add_joint_at(JointType.REVOLUTE, -1, r1, anchor=(0, 0, 1), axis=(0, 1, 0), limits=(-0.1, 0.1))
    b.add_joint_at(JointType.REVOLUTE, r1, r2, anchor=(0.5, 0, 1), axis=(0, 1, 0), limits=(-0.1, 0.1))
    return b.finalize()


@pytest.mark.slow
@pytest.mark.default_xla  # a bitwise comparison of two programs (tests/conftest.py)
def test_independent_limits_are_left_alone():
    """A serial chain pressing two (independent) limits: the rule changes nothing, bitwise."""
    model = _double_pendulum()
    state = kamino.init_state(model)
    cfg = kamino.SolverConfig(dt=1.0 / 240.0, tolerance=1e-8)
    a = kamino.rollout(model, state, num_steps=120, config=cfg, backend="jax")
    b = kamino.rollout(model, state, num_steps=120, config=dataclasses.replace(cfg, redundant_limits=True),
                       backend="jax")
    assert np.all(np.count_nonzero(np.asarray(a.limit_force)[-20:], axis=1) == 2)  # both limits hold at the end
    np.testing.assert_array_equal(np.asarray(a.body_u), np.asarray(b.body_u))
    np.testing.assert_array_equal(np.asarray(a.info.iterations), np.asarray(b.info.iterations))


def test_rule_on_constructed_rows():
    """Rows built as ``J_t = c J_j + (bilateral rows)``: equal directions (``c > 0``) keep only the row with the
    smallest reduced bias, opposing ones (``c < 0``) and independent ones are kept."""
    rng = np.random.default_rng(0)
    J_b = rng.normal(size=(4, 8))  # bilateral rows
    J_b = np.vstack([J_b, J_b[0] + J_b[1]])  # ... with a redundant one (singular D_bb)
    base, other = rng.normal(size=8), rng.normal(size=8)
    mix = lambda: rng.normal(size=5) @ J_b  # noqa: E731
    J_l = np.stack([base + mix(), 2.0 * base + mix(), -0.5 * base + mix(), other, 0.7 * base + mix()])
    J = np.vstack([J_b, J_l])
    D = J @ J.T
    n_b = J_b.shape[0]
    # v_f consistent on the bilateral rows (v_b = J_b u for some u), arbitrary on the limit rows
    v_f = np.concatenate([J_b @ rng.normal(size=8), [-1.0, -1.9, -0.3, -1.0, -0.6]])
    lo = np.concatenate([np.full(n_b, -np.inf), np.zeros(5)])
    hi = np.full(n_b + 5, np.inf)
    mask = np.ones(n_b + 5, bool)
    P = 1.0 / np.sqrt(np.diag(D))
    fixed = np.asarray(solver.redundant_limits(jnp.asarray(P[:, None] * D * P[None, :]), jnp.asarray(P * v_f),
                                              jnp.asarray(lo), jnp.asarray(hi), jnp.asarray(mask)))
    # reduced biases of the class {0, 1, 4}: eps_t = n_t . v_f with n_t = e_t - c_t e_0 - (bilateral part)
    x = np.linalg.lstsq(J_b.T, np.stack([J_l[1] - 2.0 * J_l[0], J_l[4] - 0.7 * J_l[0]]).T, rcond=None)[0]
    g = [0.0, (v_f[n_b + 1] - 2.0 * v_f[n_b] - v_f[:n_b] @ x[:, 0]) / 2.0,
         (v_f[n_b + 4] - 0.7 * v_f[n_b] - v_f[:n_b] @ x[:, 1]) / 0.7]
    keep = [n_b, n_b + 1, n_b + 4][int(np.argmin(g))]
    expected = np.zeros(n_b + 5, bool)
    expected[[n_b, n_b + 1, n_b + 4]] = True
    expected[keep] = False
    np.testing.assert_array_equal(fixed, expected)


def test_rule_refuses_what_it_cannot_do():
    """float32 (equivalent rows are not separable from independent ones at its rounding) and the Warp backend
    (not implemented there) raise instead of silently solving without the rule."""
    model = _double_pendulum()
    cfg = kamino.SolverConfig(dt=1.0 / 240.0, redundant_limits=True)
    with pytest.raises(ValueError, match="float64"):
        kamino.step(model, kamino.init_state(model, dtype=np.float32), config=cfg, backend="jax")
    pytest.importorskip("warp")
    with pytest.raises(ValueError, match="JAX reference only"):
        kamino.step(model, kamino.init_state(model, dtype=np.float64), config=cfg, backend="warp")
