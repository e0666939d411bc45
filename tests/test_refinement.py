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
    plain = kamino.rollout(model, state, ctrl, config=base.replace(**{"stabilisation.curvature_refinement": False}),
                           backend=backend)
    refined = kamino.rollout(model, state, ctrl, config=base, backend=backend)
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


def _world(model: kamino.Model, w: int, x) -> np.ndarray:
    """World ``w``'s rows of a per-body array ``x``."""
    s = int(model.world_body_start[w])
    return np.asarray(x)[s:s + int(model.world_body_count[w])]


# the reference's variant in the gpu tier (its compiles cost CI 44 s), on the CPU device: there its programs with and
# without refinement round alike, while on a GPU two different XLA programs need not (1e-18 apart)
@pytest.mark.parametrize("backend", [pytest.param("jax", marks=[pytest.mark.gpu, pytest.mark.skipif(
    not any(d.platform == "gpu" for d in jax.devices()), reason="the reference's variant runs in the gpu tier")]),
    "warp"])
def test_refinement_leaves_the_other_worlds_of_a_batch_alone(backend):
    with jax.default_device(jax.devices("cpu")[0]):
        _check_refinement_leaves_the_other_worlds_alone(backend)


def _check_refinement_leaves_the_other_worlds_alone(backend: str) -> None:
    """Only a world whose first solve converged and that has joint or coupling rows refines: a box stack (contacts,
    no joints) batched with a four-bar, and an unconverged world, keep their first solve bit for bit. So a world
    steps the same whatever it is batched with (on the Warp backend exactly as alone: its threads run the same
    operations, tests/test_cross_backend.py::test_heterogeneous_worlds_match_standalone_on_warp)."""
    parts = [kamino.models.fourbar(), kamino.models.box_stack(3)]
    mixed = kamino.concat(parts)
    on = kamino.SolverConfig(dt=1.0 / 240.0)
    assert on.stabilisation.curvature_refinement  # the default
    off = on.replace(**{"stabilisation.curvature_refinement": False})
    steps = 30  # the four-bar falls from rest, the boxes settle on the plane

    def run(model, cfg, state=None, num_steps=steps):
        state = kamino.init_state(model) if state is None else state
        traj = kamino.rollout(model, state, num_steps=num_steps, config=cfg, backend=backend)
        return jax.tree.map(lambda x: x[-1], traj)

    a, b = run(mixed, on), run(mixed, off)
    assert bool(np.all(np.asarray(a.info.converged))) and bool(np.all(np.asarray(b.info.converged)))
    # the boxes: the same with and without refinement (their world has no joint rows)
    np.testing.assert_array_equal(_world(mixed, 1, a.body_q), _world(mixed, 1, b.body_q))
    np.testing.assert_array_equal(_world(mixed, 1, a.body_u), _world(mixed, 1, b.body_u))
    assert int(a.info.iterations[1]) == int(b.info.iterations[1])
    # the four-bar refines: a different step (float64 moves it by ~1e-5 m over 30 steps)
    assert np.abs(_world(mixed, 0, a.body_q) - _world(mixed, 0, b.body_q)).max() > 1e-9
    if backend == "warp":  # each world as alone, bit for bit
        for w, part in enumerate(parts):
            alone = run(part, on)
            np.testing.assert_array_equal(_world(mixed, w, a.body_q), np.asarray(alone.body_q), err_msg=f"world {w}")
            assert int(a.info.iterations[w]) == int(alone.info.iterations[0])
    # both worlds unconverged (one PADMM iteration from a moving state): no refinement anywhere
    capped = {"max_iterations": 1}
    x, y = run(mixed, on.replace(**capped), b, 1), run(mixed, off.replace(**capped), b, 1)
    assert not bool(np.any(np.asarray(x.info.converged)))
    np.testing.assert_array_equal(np.asarray(x.body_q), np.asarray(y.body_q))
    np.testing.assert_array_equal(np.asarray(x.body_u), np.asarray(y.body_u))
