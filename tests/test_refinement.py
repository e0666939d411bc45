"""Curvature refinement (``Stabilisation.curvature_refinement``): the bilateral rows' second-order term
re-evaluated along the solved velocity (docs/conventions.md, "Stabilisation")."""


import jax
import numpy as np
import pytest

import kamino
from kamino.bench import scene_path

LADDER = scene_path("ladder8")


def _drive(model, num_steps: int) -> kamino.Control:
    """The benchmark drive: 2 N m sin(2 pi t) on the ladder's motor (``kamino bench``)."""
    t = np.arange(num_steps) * 0.0025
    return kamino.Control.from_ctrl(model, (2.0 * np.sin(2 * np.pi * t))[:, None])


def _max_violation(model, traj) -> float:
    viol = jax.vmap(lambda q, u: kamino.metrics(model, kamino.init_state(model).replace(body_q=q, body_u=u))[
        "constraint_violation"])(traj.body_q, traj.body_u)
    return float(np.max(viol))


# the JAX variant is in the slow tier, as tests/helpers.py tier_marks puts every JAX variant
@pytest.mark.parametrize("backend", [pytest.param("jax", marks=pytest.mark.slow), "warp"])
def test_refinement_cuts_the_loop_closure_error_of_a_swinging_ladder(backend):
    # the driven ladder of 8 parallelogram loops swings from 30 deg at up to ~14 rad/s; at dt = 2.5 ms the
    # curvature predicted along the free velocity misses the constraint impulse's share, O(h^2 |du| |u|)
    model = kamino.load_mjcf(LADDER)
    state = kamino.init_state(model)
    ctrl = _drive(model, 150)
    # the stiff stabilisation the refinement was built for (joint Baumgarte 1, no post-stabilisation), solved to
    # 1e-6 as when it was measured
    base = kamino.SolverConfig(dt=0.0025, tolerance=1e-6, penalty=kamino.Penalty(rho=0.01),
                               stabilisation=kamino.Stabilisation(baumgarte=1.0, post_stabilisation=0),
                               warp=kamino.WarpSettings(jacobian="sparse" if backend == "warp" else "dense"))
    plain = kamino.rollout(model, state, ctrl, config=base, backend=backend)
    refined = kamino.rollout(model, state, ctrl,
                             config=base.replace(**{"stabilisation.curvature_refinement": True}),
                             backend=backend)
    e_plain, e_refined = _max_violation(model, plain), _max_violation(model, refined)
    # measured (float64): 1.2e-4 m without, 4.9e-7 m with; bounds with a margin of 10 both ways
    assert e_plain > 1e-5
    assert e_refined < 5e-6
    assert bool(np.all(np.asarray(refined.info.converged)))


def test_refinement_is_the_same_physics_in_both_backends():
    model = kamino.load_mjcf(LADDER)
    state = kamino.init_state(model)
    cfg = kamino.SolverConfig(dt=0.0025, tolerance=1e-6, penalty=kamino.Penalty(rho=0.01),
                              stabilisation=kamino.Stabilisation(baumgarte=1.0, post_stabilisation=0,
                                                                 curvature_refinement=True))
    ctrl = _drive(model, 40)
    a = kamino.rollout(model, state, ctrl, config=cfg, backend="jax")
    b = kamino.rollout(model, state, ctrl, config=cfg, backend="warp")
    # float64, same formulas and iteration rule: only the order of floating-point operations differs
    # (measured 2e-15 m); 1e-9 m leaves room for PADMM's stopping test to fall one iteration apart
    assert float(np.max(np.abs(np.asarray(a.body_q) - np.asarray(b.body_q)))) < 1e-9
    np.testing.assert_array_equal(np.asarray(a.info.iterations), np.asarray(b.info.iterations))
