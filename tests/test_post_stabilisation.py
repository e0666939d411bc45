"""Post-stabilisation (``Stabilisation.post_stabilisation``): projecting the poses onto the joints after a step.

The reference is ``kamino/jax_ref/post_stabilisation.py``; the Warp backend factorises the same block on the
fixed rows' sparse pattern (``kamino/warp_backend/post_stabilisation.py``). Float64 throughout: the bounds are
about the projection, not float32 rounding.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import JAX, WARP_DENSE_LLT, WARP_VARIANTS, trajectory_metrics

import kamino
from kamino import JointType as JT
from kamino.config import REPROJECTION_GAP
from kamino.models.shapes import box_inertia

DT = 0.0025
#: a soft velocity-level stabilisation, as in the benchmark with SolverKamino's settings: the loop drifts
SOFT = kamino.SolverConfig(dt=DT, tolerance=1e-9, max_iterations=300, penalty=kamino.Penalty(rho=0.1),
                           stabilisation=kamino.Stabilisation(baumgarte=0.01, curvature_correction=False,
                                                              post_stabilisation=0))
STEPS = 300


def _drive(steps: int, num_dofs: int) -> jnp.ndarray:
    """Crank target (DoF 0; the other hinges are passive): a 2 Hz sine of 0.6 rad around the builder pose
    (joint coordinates are zero there)."""
    t = DT * np.arange(1, steps + 1)
    target = np.zeros((steps, num_dofs))
    target[:, 0] = 0.6 * np.sin(2 * np.pi * 2.0 * t)
    return jnp.asarray(target)


def _fourbar_run(cfg: kamino.SolverConfig, variant=JAX):
    model = kamino.models.fourbar(actuated=True, kp=200.0, kd=5.0)
    state = kamino.init_state(model)
    traj = variant.rollout(model, state, kamino.Control(position_target=_drive(STEPS, model.num_dofs)), config=cfg)
    return model, state, traj


@pytest.fixture(scope="module")
def fourbar_runs():
    """The three stabilisations on the Warp backend (dense LLT): the production path. That its projection is the
    reference's, step for step, is test_warp_projects_as_the_reference; running these on Warp spares CI three
    compiles of the reference's rollout (31 s at 1946dfb)."""
    soft = _fourbar_run(SOFT, WARP_DENSE_LLT)
    post = _fourbar_run(SOFT.replace(**{"stabilisation.post_stabilisation": 2}), WARP_DENSE_LLT)
    # stiff velocity-level stabilisation alone: curvature refinement (closure 4e-9 m here) is a further step
    stiff = _fourbar_run(SOFT.replace(**{"stabilisation.baumgarte": 1.0, "stabilisation.curvature_correction": True,
                                         "stabilisation.curvature_refinement": False}), WARP_DENSE_LLT)
    return soft, post, stiff


def test_post_stabilisation_closes_the_loop(fourbar_runs):
    (model, state, soft), (_, _, post), (_, _, stiff) = fourbar_runs
    closure = {k: trajectory_metrics(model, state, t)["constraint_violation"].max()
               for k, t in (("soft", soft), ("post", post), ("stiff", stiff))}
    # the soft stabilisation lets the loop open (the drift it has to beat is real) ...
    assert closure["soft"] > 1e-4, closure
    # ... and two projections per step hold it far below what the stiff velocity-level stabilisation reaches
    # (7.8e-7 m here). Measured 1.4e-9 m: the first pass is a Gauss-Newton step (leaves ~1e-7 m, quadratic in the
    # step's drift of ~1e-4 m), the second, with the step's Jacobian, a chord step on that remainder
    assert closure["post"] < 1e-8, closure
    assert closure["post"] < 1e-2 * closure["stiff"], closure
    assert np.asarray(post.info.converged).all()


def test_post_stabilisation_keeps_the_motion(fourbar_runs):
    """The projection moves the bodies by the drift it removes, nothing more: the crank follows the same path as
    under stiff velocity-level stabilisation (both close the loop; they differ by O(dt) in how they do it)."""
    (model, state, _), (_, _, post), (_, _, stiff) = fourbar_runs
    crank = lambda t: np.asarray(kamino.joint_positions(model, state.replace(body_q=t.body_q[-1])))[0]  # noqa: E731
    path = lambda t: np.stack([np.asarray(kamino.joint_positions(model, state.replace(body_q=q)))[0]  # noqa: E731
                               for q in t.body_q[::30]])
    np.testing.assert_allclose(path(post), path(stiff), atol=2e-3)
    assert abs(crank(post) - crank(stiff)) < 2e-3
    # the crank really moves over the run (0.6 rad amplitude)
    assert np.ptp(path(post)) > 0.5


def _coupled_hinges() -> kamino.Model:
    """Two hinged bars, the second driven, the first coupled to it as ``q_a = 2 q_b`` (a mimic joint)."""
    b = kamino.ModelBuilder()
    la = b.add_body(1.0, box_inertia(1.0, (0.1, 0.1, 1.0)), pos=(0, 0, 0.5))
    lb = b.add_body(1.0, box_inertia(1.0, (0.1, 0.1, 1.0)), pos=(1, 0, 0.5))
    ja = b.add_joint_at(JT.REVOLUTE, -1, la, anchor=(0, 0, 1), axis=(0, 1, 0))
    jb = b.add_joint_at(JT.REVOLUTE, -1, lb, anchor=(1, 0, 1), axis=(0, 1, 0),
                        actuation=kamino.Actuation("position", kp=20.0, kd=1.0))
    b.add_coupling(ja, jb, (0.0, 2.0))
    return b.finalize()


def test_warp_projects_as_the_reference():
    """Loops, a coupling, actuators and contacts in one heterogeneous model, float64: the Warp backend's projection
    (a sparse Cholesky on the fixed rows' pattern) reproduces the reference's (a dense Cholesky of the same
    matrix) to rounding, amplified over 40 steps of a four-bar and a box stack: 1e-9 m. The PADMM tolerance
    (1e-10) keeps the CR variant's inexact solves below that too. Every Warp variant in one test: the reference's
    rollout, most of the test's time (40-54 s on CI), is compiled once (parametrized, xdist ran it on both
    workers)."""
    model = kamino.concat([kamino.models.fourbar(actuated=True), _coupled_hinges(), kamino.models.box_stack(2),
                           kamino.models.chain_of_loops(3)])
    cfg = kamino.SolverConfig(dt=DT, tolerance=1e-10, max_iterations=300, penalty=kamino.Penalty(rho=0.1),
                              stabilisation=kamino.Stabilisation(baumgarte=0.01, post_stabilisation=2))
    state = kamino.init_state(model, actuated_positions=[-1.0, 0.3])
    steps = 40
    ref = JAX.rollout(model, state, num_steps=steps, config=cfg)
    ref = jax.tree.map(lambda x: x[-1], ref)
    assert (np.asarray(ref.body_q) != np.asarray(state.body_q)).any()  # the model moved
    for variant in WARP_VARIANTS:
        warp = state
        for _ in range(steps):
            warp = kamino.step(model, warp, config=variant.config(cfg), backend="warp")
        np.testing.assert_allclose(np.asarray(warp.body_q), np.asarray(ref.body_q), atol=1e-9, err_msg=variant.id)
        np.testing.assert_allclose(np.asarray(warp.body_u), np.asarray(ref.body_u), atol=1e-7, err_msg=variant.id)
        closure = np.asarray(kamino.metrics(model, warp)["constraint_violation"])
        assert closure.max() < 1e-9, (variant.id, closure)


def test_bad_settings_are_refused():
    for bad in (-1, 1.5):
        with pytest.raises(ValueError, match=r"SolverConfig\.stabilisation\.post_stabilisation: must be an integer"):
            kamino.Stabilisation(post_stabilisation=bad)


def _heavy_tip_pendulum() -> kamino.Model:
    """Two slender links hinged about y in series, 0.01 kg at the pivot and 100 kg at the tip (no loop): the
    scaled fixed-row block has curvatures down to ~1e-5 (docs/conventions.md, "Post-stabilisation")."""
    b = kamino.ModelBuilder()
    light = b.add_body(0.01, box_inertia(0.01, (0.02, 0.02, 0.5)), pos=(0.0, 0.0, 0.75))
    heavy = b.add_body(100.0, box_inertia(100.0, (0.02, 0.02, 0.5)), pos=(0.0, 0.0, 0.25))
    b.add_joint_at(JT.REVOLUTE, -1, light, anchor=(0, 0, 1), axis=(0, 1, 0))
    b.add_joint_at(JT.REVOLUTE, light, heavy, anchor=(0, 0, 0.5), axis=(0, 1, 0))
    return b.finalize()


def test_projection_shift_is_honoured_by_both_backends():
    """``Stabilisation.projection_shift`` sets the projection's diagonal shift (default PADMM's ``eta + rho_free``):
    a shift of 1e-2 leaves ``s / (sigma + s)`` of the error along the heavy tip's slow directions (``sigma`` ~ 1e-5),
    so the joints stay open by far more than with a shift of ``sqrt(eps)`` (1.5e-8). The Warp backend reproduces the
    reference with that shift to rounding (as test_warp_projects_as_the_reference). Measured: 1.3e-8 m with 1.5e-8,
    2.2e-6 m with 1e-2."""
    model = _heavy_tip_pendulum()
    state = kamino.init_state(model)
    state = state.replace(body_u=state.body_u.at[:, 3].set(2.0))  # a spin about x: the hinges' rows are loaded
    cfg = SOFT.replace(tolerance=1e-10, **{"stabilisation.post_stabilisation": 1})
    closure = {}
    for shift in (1.5e-8, 1e-2):
        c = cfg.replace(**{"stabilisation.projection_shift": shift})
        traj = JAX.rollout(model, state, num_steps=20, config=c)
        closure[shift] = trajectory_metrics(model, state, traj)["constraint_violation"].max()
        if shift == 1e-2:
            warp = WARP_DENSE_LLT.rollout(model, state, num_steps=20, config=WARP_DENSE_LLT.config(c))
            np.testing.assert_allclose(np.asarray(warp.body_q), np.asarray(traj.body_q), atol=1e-9)
    assert closure[1e-2] > 10 * closure[1.5e-8], closure


def test_a_gap_left_open_gets_one_pass_more():
    """A world whose passes leave an anchor gap above ``REPROJECTION_GAP`` (1e-5 m) gets one pass more, as an
    unconverged one does, on both backends. The light slider with its hinged 1 kg load (test_cross_backend.py) at
    ``rho_free = 1e-3`` and a projection shift of 1.5e-8 (the default follows ``rho_free``, and a shift of 1e-3 holds
    the projection back along the load's slow directions: 1.8e-4 m), float64, 100 steps: every step converges, the
    proximal shift leaves velocity errors that open the joints by 4.6e-4 m without projection and by 2.7e-5 m after
    one pass (measured without the extra pass); with it, by 9.9e-6 m (two passes everywhere: 5.4e-7 m). The Warp
    backend (the dense LLT) reproduces the reference's poses to rounding, amplified over 100 steps: 1e-9 m."""
    from test_cross_backend import _slider_with_a_hinged_load

    model = _slider_with_a_hinged_load()
    state = kamino.init_state(model)
    cfg = kamino.SolverConfig(penalty=kamino.Penalty(rho_free=1e-3),
                              stabilisation=kamino.Stabilisation(post_stabilisation=1, projection_shift=1.5e-8))
    ref = JAX.rollout(model, state, num_steps=100, config=cfg)
    warp = WARP_DENSE_LLT.rollout(model, state, num_steps=100, config=WARP_DENSE_LLT.config(cfg))
    for traj in (ref, warp):
        assert np.asarray(traj.info.converged).all()
        assert trajectory_metrics(model, state, traj)["constraint_violation"].max() <= REPROJECTION_GAP
    np.testing.assert_allclose(np.asarray(warp.body_q), np.asarray(ref.body_q), atol=1e-9)
