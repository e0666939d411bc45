"""The four-bar with its coupler-rocker hinge tilted out of the plane (``kamino.models.fourbar(tilt_deg=...)``): a
rigid loop whose constraint Jacobian has a singular value of order ``sin(tilt)`` next to the planar mechanism's
motion. Started at rest under gravity, out of the planar equilibrium, a passive mechanism must not gain energy.

The smallest eigenvalue of the scaled Delassus matrix of the joint rows at the start pose, besides the two exact
redundancies of the loop (measured, float64): 1.2e-9 at 0.1°, 1.2e-7 at 1°, 1.2e-5 at 10°, 3.8e-4 at 45°. PADMM's
proximal shift of these rows is ``eta + rho_free`` (1.1e-4 at the defaults), so from 10° on the velocity solve locks
the loop within a few steps; these tilts are checked here.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
import pytest

import kamino

#: the tilts [deg] at which the loop locks at the defaults (module docstring)
LOCKED_TILTS = (10.0, 45.0)
#: energy allowance [J] over the run (the mechanism holds about 20 J of potential energy: float32 rounds it to 2e-6)
ENERGY_SLACK = 1e-3
#: simulated time [s]
DURATION = 5.0


def _tilted_fourbars(tilts: tuple[float, ...]) -> kamino.Model:
    """One world per tilt."""
    return kamino.concat([kamino.models.fourbar(tilt_deg=t) for t in tilts])


def _energies(model: kamino.Model, body_q: np.ndarray, body_u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Kinetic and potential energy ``[steps, worlds]`` of trajectory poses and twists ``[steps, bodies, 7 | 6]``
    (``kamino.metrics``' definitions, in float64 on the host)."""
    q, u = np.asarray(body_q, float), np.asarray(body_u, float)
    x, y, z, w = np.moveaxis(q[..., 3:], -1, 0)  # (x, y, z, w) order, docs/formulation.md §1.1
    R = np.stack([np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], -1),
                  np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], -1),
                  np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], -1)], -2)
    w_body = np.einsum("tbji,tbj->tbi", R, u[..., 3:])
    ke = 0.5 * model.body_mass * np.sum(u[..., :3] ** 2, -1) + 0.5 * np.einsum("tbi,bij,tbj->tb", w_body,
                                                                             model.body_inertia, w_body)
    pe = -model.body_mass * np.einsum("tbi,bi->tb", q[..., :3], model.gravity[model.body_world])
    worlds = model.body_world
    per_world = lambda x: np.stack([x[:, worlds == w].sum(1) for w in range(int(worlds.max()) + 1)], 1)  # noqa: E731
    return per_world(ke), per_world(pe)


def test_tilt_zero_is_the_planar_fourbar():
    """``tilt_deg=0`` builds the planar four-bar exactly (the same joint frames, bit for bit)."""
    planar, tilted = kamino.models.fourbar(), kamino.models.fourbar(tilt_deg=0.0)
    for field in ("joint_anchor_B", "joint_anchor_F", "joint_frame_B", "joint_frame_F", "body_q0"):
        np.testing.assert_array_equal(getattr(planar, field), getattr(tilted, field))


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64], ids=["float32", "float64"])
def test_locked_tilted_fourbar_gains_no_energy(dtype):
    """Warp backend, defaults (Euler, dt 1/240), 5 s at rest under gravity: kinetic plus potential energy stays
    within ``ENERGY_SLACK`` of its initial value at every step, and the mechanism stays locked: its kinetic energy
    below 1e-3 J (measured at most 5.6e-4 J at 10°, the first steps' settling, 6.6e-7 J at 45°; the energy change
    at most +5.6e-4 J, float64 at 10°, in the same steps, then back to within 1e-10 J)."""
    model = _tilted_fourbars(LOCKED_TILTS)
    cfg = kamino.SolverConfig()
    s0 = kamino.init_state(model, dtype)
    tr = kamino.rollout(model, s0, num_steps=round(DURATION / cfg.dt), config=cfg, backend="warp")
    ke0, pe0 = _energies(model, np.asarray(s0.body_q)[None], np.asarray(s0.body_u)[None])
    ke, pe = _energies(model, tr.body_q, tr.body_u)
    gain = (ke + pe - (ke0 + pe0)).max(axis=0)
    assert np.all(gain <= ENERGY_SLACK), f"energy gained [J] at tilts {LOCKED_TILTS}: {gain}"
    assert np.all(ke.max(axis=0) <= 1e-3), f"peak kinetic energy [J]: {ke.max(axis=0)}"
    assert not np.asarray(tr.info.failed).any()
    assert np.asarray(tr.info.converged).all()
