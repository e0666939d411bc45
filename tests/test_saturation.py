"""The saturation-switched penalty of effort-limited actuator rows (``kamino.jax_ref.solver.solve``, "Saturation"): a
row starts a solve with ``rho`` when its warm start lies on its bound, else with ``rho_free``, and switches to ``rho``
at the first iteration whose projection clips it (the factor redone, the momentum restarted). Both backends and every
Warp linear path must take the same decisions, so that the iteration counts agree exactly in float64."""

from __future__ import annotations

import numpy as np
import pytest

import kamino

pytest.importorskip("warp")

from kamino.warp_backend import backend as wb
from kamino.warp_backend.pipeline import Stepper
from kamino.warp_backend.workspace import saturated_rows

EFFORT = 0.3  # N m: a tenth of what the PD asks for at the targets below, so the crank's row saturates


def _driven_fourbars() -> kamino.Model:
    """Two actuated four-bars (different starting angles), crank PD with a small effort limit."""
    return kamino.concat([kamino.models.fourbar(actuated=True, kp=50.0, kd=2.0, effort_limit=EFFORT),
                          kamino.models.fourbar(actuated=True, kp=50.0, kd=2.0, effort_limit=EFFORT, crank_angle=-0.5)])


def _targets(model: kamino.Model, steps: int) -> np.ndarray:
    """Crank targets of +-2.5 rad, flipped every 10 steps: the actuator saturates, and each flip moves it to its
    other bound."""
    sign = np.where(np.arange(steps) % 20 < 10, 1.0, -1.0)
    return np.repeat(2.5 * sign[:, None], model.num_dofs, axis=1)


def _warp_run(model, cfg, s0, targets, padmm):
    st = Stepper(model, cfg, np.float64, "cpu", padmm=padmm)
    wb.load_state(st, s0, None)
    iters, saturated, force = [], [], []
    # each world's row 0 is its actuator's joint-dynamics row; both worlds are in the first group of 32, where
    # row a of world w is stored at a * 32 + w (interleaved) or w * maxdim + a (the 32-thread schedule's layout,
    # kamino/warp_backend/indexing.py)
    maxdim = int(st.wm.arrays.grp_maxdim.numpy()[0])
    act_rows = [w if st.work.row_stride != 1 else w * maxdim for w in range(model.num_worlds)]
    for t in range(len(targets)):
        wb.load_control(st, kamino.Control(position_target=targets[t]))
        st.run(1)
        iters.append(st.work.iters.numpy().copy())
        saturated.append(saturated_rows(st.work.row_info.numpy())[act_rows])
        force.append(st.work.act_force.numpy().copy())
    return np.array(iters), np.array(saturated), np.array(force)


def test_saturation_decisions_agree_across_backends_and_linear_paths():
    """Float64 at a tight tolerance: the JAX reference, Warp's sparse factor (one thread and 32 threads per world)
    and its dense factor take the same iterations on every step (the switch is a float decision, ``y != x - z_hat /
    rho``, which the same arithmetic takes the same way; before the rule existed they agreed exactly too). The
    crank's row switches inside the first solve and starts the later ones saturated (from its warm start, including
    after each flip of the target, which takes it from one bound to the other), and the effort limit holds to
    rounding."""
    model = _driven_fourbars()
    cfg = kamino.SolverConfig(dt=0.01, tolerance=1e-8)
    T = 40
    targets = _targets(model, T)
    s0 = kamino.init_state(model, dtype=np.float64)
    traj = kamino.rollout(model, s0, kamino.Control(position_target=targets), config=cfg, backend="jax")
    it_ref = np.asarray(traj.info.iterations)
    runs = {"sparse, thread": _warp_run(model, cfg, s0, targets, "thread"),
            "sparse, 32 threads": _warp_run(model, cfg, s0, targets, "warp"),
            "dense": _warp_run(model, cfg.replace(**{"warp.jacobian": "dense"}), s0, targets, "thread")}
    for name, (iters, saturated, force) in runs.items():
        np.testing.assert_array_equal(iters, it_ref, err_msg=name)
        # the first step starts from rest (no warm start, so no row starts saturated) and ends saturated: its
        # crank rows switched inside the solve
        assert saturated[0].all(), name
        assert np.abs(force).max() <= EFFORT * (1 + 1e-9), name
    assert it_ref.max() < cfg.max_iterations  # every solve converged


def test_saturation_rule_cuts_the_iterations_of_a_robot_under_random_targets():
    """dr_legs (12 effort-limited actuators) with random PD targets redrawn every 5 steps, PPO's exploration
    regime, float32 at the defaults, Warp's CPU device. With the constant penalty ``rho`` on every effort-limited
    row (before the rule) the solves took 45 iterations on average in this run (float64; 52 under
    ``kamino.bench.ppo_collect``); with the rule 27 (float64) and 20.6. The bound 35 sits between the two, above
    float32's spread. The solve is PADMM's first one: curvature refinement's restart after it (on by default) adds
    its own iterations (40.7 on average in this run)."""
    model = kamino.replicate(kamino.models.dr_legs(), 4)
    cfg = kamino.SolverConfig(dt=0.004, stabilisation=kamino.Stabilisation(curvature_refinement=False))
    T = 30
    rng = np.random.default_rng(0)
    act = np.asarray(model.dof_act_mode) == int(kamino.ActuationMode.POSITION)
    targets = np.zeros((T, model.num_dofs))
    targets[:, act] = np.repeat(rng.uniform(-0.8, 0.8, (T // 5, int(act.sum()))), 5, axis=0)
    st = Stepper(model, cfg, np.float32, "cpu", padmm="thread")
    wb.load_state(st, kamino.init_state(model, dtype=np.float32), None)
    iters = []
    for t in range(T):
        wb.load_control(st, kamino.Control(position_target=targets[t]))
        st.run(1)
        iters.append(st.work.iters.numpy().copy())
        assert not st.work.failed.numpy().any()
    iters = np.array(iters)
    assert iters.mean() < 35.0, iters.mean()
