"""Implicit PD actuation, armature, damping, effort limits and joint limits (docs/formulation.md §3-§4.1)."""

from __future__ import annotations

import numpy as np
import pytest

import kamino
from kamino import Actuation, JointType
from tests.helpers import BACKENDS, trajectory_joint_positions, trajectory_metrics

DT = 1.0 / 240.0


def _turntable(inertia=0.1, armature=0.02, damping=0.0, actuation=None, velocity=0.0, limits=None):
    """A body on a vertical-axis hinge through its CoM: gravity exerts no torque, so the hinge obeys
    ``(I + a) qdd = tau`` exactly."""
    b = kamino.ModelBuilder(gravity=(0.0, 0.0, -9.81))
    body = b.add_body(mass=1.0, inertia=(inertia,) * 3, pos=(0, 0, 1), angular_velocity=(0, 0, velocity))
    b.add_joint_at(JointType.REVOLUTE, -1, body, anchor=(0, 0, 1), axis=(0, 0, 1), actuation=actuation,
                   armature=armature, damping=damping, limits=limits)
    return b.finalize()


def _angles(model, traj):
    return trajectory_joint_positions(model, kamino.init_state(model), traj)[:, 0]


@pytest.mark.parametrize("variant", BACKENDS)
def test_pd_step_response_matches_the_analytic_second_order_response(variant):
    I, a, kp, kd = 0.1, 0.02, 10.0, 1.2
    model = _turntable(I, a, actuation=Actuation("position", kp=kp, kd=kd))
    T = int(2.0 / DT)
    traj = variant.rollout(model, kamino.init_state(model), kamino.Control(position_target=np.ones((T, 1))),
                           config=kamino.SolverConfig(dt=DT))
    theta = _angles(model, traj)
    t = DT * np.arange(1, T + 1)
    J = I + a
    wn, zeta = np.sqrt(kp / J), kd / (2.0 * np.sqrt(kp * J))
    wd = wn * np.sqrt(1 - zeta**2)
    exact = 1.0 - np.exp(-zeta * wn * t) * (np.cos(wd * t) + zeta / np.sqrt(1 - zeta**2) * np.sin(wd * t))
    # backward-Euler PD deviates from the continuous response by O(wn dt) = 0.038 of its transient
    # (measured 1.3% of the step); the bound is 2% of the step
    assert np.max(np.abs(theta - exact)) < 0.02


@pytest.mark.parametrize("variant", BACKENDS)
def test_stiff_pd_gain_is_stable_and_converges(variant):
    model = _turntable(actuation=Actuation("position", kp=1e5, kd=0.0))
    T = int(10.0 / DT)
    traj = variant.rollout(model, kamino.init_state(model), kamino.Control(position_target=np.ones((T, 1))),
                           config=kamino.SolverConfig(dt=DT))
    err = np.abs(_angles(model, traj) - 1.0)
    assert np.all(np.isfinite(err))
    second = int(1.0 / DT)
    # no growth: an explicit PD at kp dt^2 / J = 14.5 would blow up in a few steps; the implicit
    # one is dissipative, so the error of the last second is below the first second's
    assert err[-second:].max() <= err[:second].max()
    assert err[-1] < 1e-6  # and it settles on the target


@pytest.mark.parametrize("variant", BACKENDS)
def test_effort_limit_holds_even_when_the_target_is_unreachable(variant):
    # the hinge limit at 0.5 rad makes the 2 rad target unreachable: the PD saturates against it
    limit = 0.3
    model = _turntable(actuation=Actuation("position", kp=50.0, kd=1.0, effort_limit=limit), limits=(-1.0, 0.5))
    T = int(3.0 / DT)
    traj = variant.rollout(model, kamino.init_state(model),
                           kamino.Control(position_target=np.full((T, 1), 2.0)),
                           config=kamino.SolverConfig(dt=DT, tolerance=1e-8))  # the rtol below is the solver's
    tau = np.asarray(traj.actuator_force)[:, 0]
    # the bound is enforced by the PADMM projection: exact up to rounding
    assert np.max(np.abs(tau)) <= limit * (1 + 1e-9)
    assert np.isclose(tau[-1], limit, rtol=1e-6)  # saturated at the end, pressing on the joint limit
    theta = _angles(model, traj)
    assert theta.max() < 0.5 + 1e-4
    # saturated from the start: (I + a) qdd = limit, a constant acceleration, which the midpoint rule integrates
    # exactly: theta_n = alpha (n dt)^2 / 2 (PADMM tolerance 1e-6 on the impulses)
    n = np.arange(1, 11)
    assert np.allclose(theta[:10], limit / 0.12 * (n * DT) ** 2 / 2, rtol=1e-5)


@pytest.mark.parametrize("variant", BACKENDS)
def test_effort_mode_clips_the_commanded_effort(variant):
    model = _turntable(armature=0.0, actuation=Actuation("effort", effort_limit=0.5))
    traj = variant.rollout(model, kamino.init_state(model), kamino.Control(dof_effort=np.full((24, 1), 3.0)),
                           config=kamino.SolverConfig(dt=DT))
    assert np.allclose(np.asarray(traj.actuator_force), 0.5)
    w = np.asarray(traj.body_u)[:, 0, 5]
    assert np.allclose(w, 0.5 / 0.1 * DT * np.arange(1, 25), rtol=1e-9)  # semi-implicit Euler: exact


@pytest.mark.parametrize("variant", BACKENDS)
def test_armature_and_damping_decay_matches_backward_euler(variant):
    I, a, b, w0 = 0.1, 0.05, 0.3, 2.0
    model = _turntable(I, a, damping=b, velocity=w0)
    # a tight PADMM tolerance so that the comparison checks the row's formula, not the solver's stop
    cfg = kamino.SolverConfig(dt=DT, tolerance=1e-11)
    traj = variant.rollout(model, kamino.init_state(model), num_steps=240, config=cfg)
    w = np.asarray(traj.body_u)[:, 0, 5]
    # the passive row is backward Euler: (I + a)(w+ - w) = -dt b w+  =>  w_n = w0 (1 + dt b / (I + a))^-n
    n = np.arange(1, 241)
    assert np.allclose(w, w0 * (1.0 + DT * b / (I + a)) ** -n, rtol=1e-8)
    # the armature is reflected inertia: over 1 s the decay is that of exp(-b t / (I + a)), within the
    # backward-Euler error O(dt b / (I + a)) per unit time (1%)
    assert np.allclose(w, w0 * np.exp(-b / (I + a) * DT * n), rtol=0.01)


@pytest.mark.parametrize("variant", BACKENDS)
def test_passive_spring_is_an_implicit_spring(variant):
    I, k, q_s = 0.1, 4.0, 0.3
    b = kamino.ModelBuilder(gravity=(0.0, 0.0, -9.81))
    body = b.add_body(mass=1.0, inertia=(I,) * 3, pos=(0, 0, 1))
    b.add_joint_at(JointType.REVOLUTE, -1, body, anchor=(0, 0, 1), axis=(0, 0, 1), stiffness=k, springref=q_s)
    model = b.finalize()
    T = int(2.0 / DT)
    traj = variant.rollout(model, kamino.init_state(model), num_steps=T,
                           config=kamino.SolverConfig(dt=DT, tolerance=1e-11))
    theta = _angles(model, traj)
    # docs/formulation.md §3.2 passive row at the midpoint pose q_m = q + h w (§6.3, h = dt / 2):
    # I (w+ - w) = dt k (q_s - q_m - h w+), then q+ = q_m + h w+
    h = DT / 2
    q, w, expected = 0.0, 0.0, []
    for _ in range(T):
        q_m = q + h * w
        w = (I * w + DT * k * (q_s - q_m)) / (I + DT * h * k)
        q = q_m + h * w
        expected.append(q)
    assert np.allclose(theta, expected, rtol=1e-7, atol=1e-10)
    # physics: it oscillates about springref with the natural period 2 pi sqrt(I / k) (within 1%)
    crossings = np.nonzero(np.diff(np.sign(theta - q_s)) > 0)[0]
    period = DT * (crossings[1] - crossings[0])
    assert abs(period - 2 * np.pi * np.sqrt(I / k)) < 0.01 * 2 * np.pi * np.sqrt(I / k) + DT


def _limited_pendulum(limits, omega0=0.0):
    """A 0.5 m rod hinged at its end about +y, horizontal along +x at theta = 0; gravity raises theta."""
    b = kamino.ModelBuilder(gravity=(0.0, 0.0, -9.81))
    rod = b.add_body(mass=1.0, inertia=(0.001, 0.021, 0.021), pos=(0.25, 0, 1),
                     velocity=(0, 0, -0.25 * omega0), angular_velocity=(0, omega0, 0))
    b.add_joint_at(JointType.REVOLUTE, -1, rod, anchor=(0, 0, 1), axis=(0, 1, 0), limits=limits)
    return b.finalize()


@pytest.mark.parametrize("variant", BACKENDS)
@pytest.mark.parametrize("integrator", ["euler"])  # midpoint: tests/test_midpoint.py
def test_pendulum_held_by_a_limit_violates_it_by_less_than_1e4(integrator, variant):
    model = _limited_pendulum((-1.0, 0.2))
    T = int(5.0 / DT)
    traj = variant.rollout(model, kamino.init_state(model), num_steps=T,
                           config=kamino.SolverConfig(dt=DT, integrator=integrator))
    theta = _angles(model, traj)
    assert theta.max() - 0.2 < 1e-4
    assert abs(theta[-1] - 0.2) < 1e-4  # resting on the limit
    # the limit carries the gravity torque m g l cos(0.2) at rest (negative: it pushes theta down)
    tau = np.asarray(traj.limit_force)[-1, 0]
    assert np.isclose(tau, -9.81 * 0.25 * np.cos(0.2), rtol=1e-4)


@pytest.mark.parametrize("variant", BACKENDS)
def test_pendulum_leaves_its_limit_freely(variant):
    # starting on the upper limit and moving away from it: identical to the pendulum without limits
    # tight PADMM tolerance: a spurious limit impulse would show above the solver's stop
    kw = {"num_steps": 30, "config": kamino.SolverConfig(dt=DT, tolerance=1e-11)}
    free = _limited_pendulum(None, omega0=-3.0)
    held = _limited_pendulum((-1.0, 0.0), omega0=-3.0)
    a = _angles(free, variant.rollout(free, kamino.init_state(free), **kw))
    traj = variant.rollout(held, kamino.init_state(held), **kw)
    b = _angles(held, traj)
    assert np.all(a < 0)  # moving away all along
    assert np.max(np.abs(a - b)) < 1e-9
    assert np.max(np.abs(np.asarray(traj.limit_force))) < 1e-6


@pytest.mark.parametrize("variant", BACKENDS)
@pytest.mark.parametrize("integrator", ["euler", "midpoint"])
def test_actuated_fourbar_tracks_a_1hz_sinusoid(integrator, variant):
    model = kamino.models.fourbar(actuated=True, kp=500.0, kd=10.0)
    cfg = kamino.SolverConfig(dt=DT, integrator=integrator)
    T = int(3.0 / DT)
    t = DT * np.arange(1, T + 1)
    amp = 0.4
    pos = np.zeros((T, model.num_dofs))
    vel = np.zeros((T, model.num_dofs))
    # a 1 Hz sinusoid that starts at rest where the linkage is (no step in the reference)
    pos[:, 0], vel[:, 0] = amp * (1 - np.cos(2 * np.pi * t)), amp * 2 * np.pi * np.sin(2 * np.pi * t)
    state = kamino.init_state(model)
    traj = variant.rollout(model, state, kamino.Control(position_target=pos, velocity_target=vel), config=cfg)
    theta = trajectory_joint_positions(model, state, traj)[:, 0]
    rms = float(np.sqrt(np.mean((theta - pos[:, 0])[T // 3:] ** 2)))
    closure = trajectory_metrics(model, state, traj)["constraint_violation"].max()
    print(f"actuated four-bar ({integrator}): RMS tracking error {rms:.3e} rad, closure {closure:.2e} m")
    assert rms < 0.01 * amp  # stiff PD (kp 500) on a 0.2 kg m^2-class linkage: sub-percent tracking
    assert closure < 1e-6  # issue: loop closure < 1e-6 m
