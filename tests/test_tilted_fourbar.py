"""The four-bar with its coupler-rocker hinge tilted out of the plane (``kamino.models.fourbar(tilt_deg=...)``): a
rigid loop whose constraint Jacobian has a singular value of order ``sin(tilt)`` next to the planar mechanism's
motion. Started at rest under gravity, out of the planar equilibrium, a passive mechanism must not gain energy.

The smallest eigenvalue of the scaled Delassus matrix of the joint rows at the start pose, besides the two exact
redundancies of the loop (measured, float64): 1.2e-9 at 0.1°, 1.2e-7 at 1°, 1.2e-5 at 10°, 3.8e-4 at 45°. PADMM's
proximal shift of these rows is ``eta + rho_free`` (1.1e-4 at the defaults): a solve of a few iterations barely
moves the impulse along the first three, which only the warm start carries from step to step. The warm-start filter
(``kamino.config.WARM_START_FILTER_SHIFT``, 1e-6) drops the warm start along the directions far below it (0.1°, 1°:
there the mechanism swings as a planar one would, and dissipates) and keeps it along the others (10°, 45°: the loop
stays locked); post-stabilisation holds back along the same directions as the solve (docs/conventions.md,
"Post-stabilisation", "Warm start"). Without them the mechanism gained up to 2.0 J in 5 s (0.1°, float64) and 1.8 J
(1°, float32).

At 0° and 0.1° the explicit Euler step adds its own small energy wobble to the planar swing (3.7e-3 J in float64,
3.5e-3 J in float32 at 0°; the midpoint rule: 6e-5 J): the 0.1° loop may gain what the planar one gains, and no more.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
import pytest

import kamino

#: the tilts [deg] at which the loop locks at the defaults (module docstring)
LOCKED_TILTS = (10.0, 45.0)
#: the tilts [deg] checked: the planar four-bar first (the integrator's reference), then the nearly singular loops
TILTS = (0.0, 0.1, 1.0, *LOCKED_TILTS)
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


def _check_no_energy_gain(backend: str, dtype, integrator: str = "euler") -> None:
    """``backend``, defaults (Euler unless ``integrator``, dt 1/240), 5 s at rest under gravity, one world per tilt of
    ``TILTS``: kinetic plus potential energy stays within ``ENERGY_SLACK`` of its initial value at every step (with
    Euler at 0.1°: within ``ENERGY_SLACK`` of the planar four-bar's gain, the Euler step's wobble); the locked tilts
    keep their kinetic energy below 1e-3 J; every step converges and no world fails."""
    model = _tilted_fourbars(TILTS)
    cfg = kamino.SolverConfig(integrator=integrator)
    s0 = kamino.init_state(model, dtype)
    tr = kamino.rollout(model, s0, num_steps=round(DURATION / cfg.dt), config=cfg, backend=backend)
    ke0, pe0 = _energies(model, np.asarray(s0.body_q)[None], np.asarray(s0.body_u)[None])
    ke, pe = _energies(model, tr.body_q, tr.body_u)
    gain = dict(zip(TILTS, (ke + pe - (ke0 + pe0)).max(axis=0), strict=True))
    peak = dict(zip(TILTS, ke.max(axis=0), strict=True))
    assert gain[0.1] <= gain[0.0] + ENERGY_SLACK, gain
    if integrator == "midpoint":
        assert all(gain[t] <= ENERGY_SLACK for t in TILTS), gain
    assert all(gain[t] <= ENERGY_SLACK for t in TILTS[2:]), gain
    assert all(peak[t] <= 1e-3 for t in LOCKED_TILTS), peak
    assert not np.asarray(tr.info.failed).any()
    assert np.asarray(tr.info.converged).all()


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64], ids=["float32", "float64"])
def test_tilted_fourbar_gains_no_energy(dtype):
    """The Warp backend (:func:`_check_no_energy_gain`). Measured gains [J] at 0°, 0.1°, 1°, 10°, 45°: float32 3.5e-3,
    3.1e-3, -2.6e-4, -2.1e-4, 2.8e-6; float64 3.7e-3, 3.2e-3, -2.6e-4, -2.1e-4, -9e-9 (before the warm-start filter
    and the projection's shift: 4.2e-2, 0.86 at 0.1°, 1° in float32; 2.0, 0.11 in float64). Peak kinetic energy at
    10°: 6.0e-4 J (the first steps' settling)."""
    _check_no_energy_gain("warp", dtype)


def _cuda() -> bool:
    """Whether Warp sees a CUDA device (the ``gpu`` tier's machine)."""
    import warp as wp

    return wp.is_cuda_available()


@pytest.mark.gpu
@pytest.mark.skipif(not _cuda(), reason="the gpu tier (CI skips it: a JAX compile per dtype)")
@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64], ids=["float32", "float64"])
def test_tilted_fourbar_gains_no_energy_on_the_reference(dtype):
    """The JAX reference (:func:`_check_no_energy_gain`; a compile per dtype, too slow for CI). Measured gains [J] at
    0°, 0.1°, 1°, 10°, 45°: float32 3.5e-3, 3.1e-3, -2.6e-4, -2.1e-4, 2.5e-6; float64 as the Warp backend's."""
    _check_no_energy_gain("jax", dtype)


@pytest.mark.gpu
@pytest.mark.skipif(not _cuda(), reason="the gpu tier (CI skips it)")
@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64], ids=["float32", "float64"])
def test_tilted_fourbar_gains_no_energy_with_the_midpoint_rule(dtype):
    """The Warp backend with the midpoint rule (:func:`_check_no_energy_gain`): without Euler's wobble every tilt, 0°
    and 0.1° included, stays within ``ENERGY_SLACK``. Measured gains [J] at 0°, 0.1°, 1°, 10°, 45°: float32 -3.8e-7,
    -1.8e-7, -4.3e-7, -2.1e-5, -3.3e-6; float64 6.3e-5, 2.2e-6, -2.0e-7, -1.9e-5, 4.4e-7."""
    _check_no_energy_gain("warp", dtype, "midpoint")
