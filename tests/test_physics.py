"""Physics of the JAX reference on jointed mechanisms without contacts."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
import pytest

import kamino
from tests.helpers import (
    BACKENDS,
    JAX,
    WARP_SPARSE_LLT,
    tier_marks,
    trajectory_joint_positions,
    trajectory_metrics,
)


def _period_from_crossings(t: np.ndarray, x: np.ndarray) -> float:
    """Mean period from linearly interpolated downward zero crossings."""
    idx = np.nonzero((x[:-1] > 0) & (x[1:] <= 0))[0]
    tc = t[idx] + x[idx] / (x[idx] - x[idx + 1]) * (t[idx + 1] - t[idx])
    return float(np.mean(np.diff(tc)))


@pytest.mark.parametrize("variant", BACKENDS)
def test_pendulum_period_matches_physical_pendulum(variant):
    L, m, w, theta0, g = 1.0, 1.0, 0.02, np.deg2rad(5.0), 9.81
    model = kamino.models.pendulum(length=L, mass=m, width=w, angle=theta0, gravity=g)
    dt = 2e-3
    state = kamino.init_state(model)
    # Warp variants: 4 s (two periods of 1.64 s, three downward crossings) instead of 18 s, for CI time
    # (3 x 9000 steps of ~1 ms on the CPU); same bound
    duration = 4.0 if variant.is_warp else 18.0
    traj = variant.rollout(model, state, num_steps=int(duration / dt), config=kamino.SolverConfig(dt=dt))
    angle = trajectory_joint_positions(model, state, traj)[:, 0]
    t = dt * np.arange(1, angle.size + 1)
    d = L / 2
    I_pivot = m * (L * L + w * w) / 12 + m * d * d
    T0 = 2 * np.pi * np.sqrt(I_pivot / (m * g * d))
    T_analytic = T0 * (1 + theta0**2 / 16 + 11 * theta0**4 / 3072)
    T = _period_from_crossings(t, angle)
    # issue bound 0.2%; semi-implicit Euler's period error at this dt is O((w dt)^2) ~ 1e-5
    assert abs(T - T_analytic) / T_analytic < 2e-3, (T, T_analytic)
    assert bool(np.all(traj.info.converged))


@pytest.mark.parametrize("variant", BACKENDS)
@pytest.mark.parametrize("integrator, closure_bound", [("midpoint", 1e-6), ("euler", 1e-4)])
def test_fourbar_stays_closed_and_conserves_energy(integrator, closure_bound, variant):
    model = kamino.models.fourbar()
    state = kamino.init_state(model)
    dt = 1.0 / 240.0
    # Warp variants: the first 2 s (a full swing) instead of 10 s, for CI time (3 configurations x 2 integrators
    # x 2400 steps); same bounds
    duration = 2.0 if variant.is_warp else 10.0
    traj = variant.rollout(model, state, num_steps=round(duration / dt),
                           config=kamino.SolverConfig(dt=dt, integrator=integrator))
    met = trajectory_metrics(model, state, traj)
    # issue bounds: closure < 1e-6 m (midpoint), < 1e-4 m (Euler), over 10 s at dt = 1/240
    assert met["constraint_violation"].max() < closure_bound
    assert bool(np.all(traj.info.converged)), "PADMM must reach its tolerance on every step"
    assert float(np.max(traj.info.dual_residual)) <= kamino.SolverConfig().tolerance  # the stopping test held
    if integrator == "midpoint":
        E0 = float(kamino.metrics(model, state)["total_energy"][0])
        drift = np.abs(met["total_energy"][:, 0] - E0).max()
        # issue bound 0.5%, measured against the peak kinetic energy of the swing (the energy that
        # moves), which is stricter than against the total energy (its potential datum is arbitrary)
        assert drift / met["kinetic_energy"].max() < 5e-3
        assert met["kinetic_energy"].max() > 0.05  # it really swings (about 0.19 J)


#: (integrator, bound on the float32 four-bar's energy drift against its peak kinetic energy): measured 7.2 % with
#: semi-implicit Euler on both backends and 12.4 % with the midpoint rule; each bound a little above, so that a further
#: loss fails
FOURBAR_FLOAT32_DRIFT = {"euler": 0.1, "midpoint": 0.15}


@pytest.mark.parametrize("variant, integrator", [
    pytest.param(JAX, "euler", id="jax-euler", marks=tier_marks(JAX)),
    pytest.param(WARP_SPARSE_LLT, "euler", id="warp-euler", marks=tier_marks(WARP_SPARSE_LLT)),
    pytest.param(WARP_SPARSE_LLT, "midpoint", id="warp-midpoint", marks=tier_marks(WARP_SPARSE_LLT))])
def test_fourbar_keeps_its_energy_in_float32(variant, integrator):
    """The passive four-bar keeps its total energy within 1 % over 10 s, float32, dt 2.5 ms, with post-stabilisation.
    Measured: within 0.07 % with semi-implicit Euler (both backends). Against the peak kinetic energy (the energy that
    moves) the float32 run loses 7.2 % with Euler (float64: 1.2 %) and 12.4 % with the default midpoint rule (float64:
    0.01 %): the joint dead band shrinks the curvature term every step (docs/conventions.md, "Stabilisation", an open
    problem); bounded by ``FOURBAR_FLOAT32_DRIFT``."""
    model = kamino.models.fourbar()
    state = kamino.init_state(model, jnp.float32)
    dt = 0.0025
    traj = variant.rollout(model, state, num_steps=round(10.0 / dt),
                           config=kamino.SolverConfig(dt=dt, integrator=integrator))
    met = trajectory_metrics(model, state, traj)
    E0 = float(kamino.metrics(model, state)["total_energy"][0])
    drift = np.abs(np.asarray(met["total_energy"][:, 0]) - E0).max()
    ke_max = float(np.asarray(met["kinetic_energy"]).max())
    assert ke_max > 0.1  # it swings (0.185 J)
    assert drift / abs(E0) < 1e-2
    assert drift / ke_max < FOURBAR_FLOAT32_DRIFT[integrator], drift / ke_max
    assert float(np.asarray(met["constraint_violation"]).max()) < 1e-5


@pytest.mark.parametrize("variant", BACKENDS)
@pytest.mark.parametrize("integrator", ["euler", "midpoint"])
def test_chain_of_loops_float32_stays_closed(integrator, variant):
    model = kamino.models.chain_of_loops(8)
    state = kamino.init_state(model, dtype=jnp.float32)
    dt = 1.0 / 240.0
    # float32: velocities of ~1 m/s carry ~1e-7 rounding and the thin rails' axial inertia makes
    # rotational rows stiff, so PADMM runs at the 1e-4 tolerance the paper's examples use in float32
    cfg = kamino.SolverConfig(dt=dt, integrator=integrator, tolerance=1e-4)
    # Warp variants: the first 1 s (the ladder's first swing down) instead of 10 s, for CI time (a Warp step
    # of this 28-body ladder costs 10-35 ms on the CPU); same bounds
    duration = 1.0 if variant.is_warp else 10.0
    traj = variant.rollout(model, state, num_steps=round(duration / dt), config=cfg)
    assert traj.body_q.dtype == jnp.float32
    met = trajectory_metrics(model, state, traj)
    assert met["constraint_violation"].max() < 1e-5  # issue bound, metres/radians
    assert bool(np.all(traj.info.converged))
    assert met["kinetic_energy"].max() > 1.0  # the ladder swings (about 4 J)


@pytest.mark.parametrize("variant", BACKENDS)
def test_free_fall_and_spin_are_exact(variant):
    """A free body (no joint): v(t) = v0 + g t exactly; a spherical body keeps its angular velocity."""
    b = kamino.ModelBuilder(gravity=(0.0, 0.0, -9.81))
    b.add_body(mass=2.0, inertia=np.eye(3) * 0.1, pos=(0, 0, 1), velocity=(1.0, 0.5, 2.0),
               angular_velocity=(3.0, -1.0, 2.0))
    model = b.finalize()
    state = kamino.init_state(model)
    dt, n = 0.01, 100
    traj = variant.rollout(model, state, num_steps=n, config=kamino.SolverConfig(dt=dt))
    v = np.asarray(traj.body_u[-1, 0, :3])
    np.testing.assert_allclose(v, [1.0, 0.5, 2.0 - 9.81 * n * dt], atol=1e-12)  # rounding only
    np.testing.assert_allclose(np.asarray(traj.body_u[-1, 0, 3:]), [3.0, -1.0, 2.0], atol=1e-12)
    # the midpoint rule's position (docs/formulation.md §6.3): r0 + v0 t + g t^2 / 2, exact under a constant force
    t = n * dt
    np.testing.assert_allclose(float(traj.body_q[-1, 0, 2]), 1.0 + 2.0 * t - 9.81 * t * t / 2, atol=1e-10)


@pytest.mark.parametrize("variant", BACKENDS)
def test_effort_on_a_revolute_joint_spins_it_up(variant):
    """A hinge with no gravity, driven by a constant torque: angular acceleration = tau / I_axis."""
    model = kamino.models.pendulum(angle=0.0, gravity=0.0)
    state = kamino.init_state(model)
    tau, dt, n = 0.2, 1e-3, 200
    controls = kamino.Control(dof_effort=jnp.full((n, 1), tau))
    traj = variant.rollout(model, state, controls, config=kamino.SolverConfig(dt=dt))
    I_pivot = 1.0 * (1.0 + 0.02**2) / 12 + 0.25
    omega = float(traj.body_u[-1, 0, 4])
    # exact for the discrete scheme up to the solver tolerance (1e-6 m/s on a 0.5 m lever)
    assert abs(omega - tau / I_pivot * n * dt) < 1e-5
