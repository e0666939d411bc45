"""The Moreau-Jean midpoint rule (docs/formulation.md §6.3) on a four-bar whose crank a motor whips round, and on
impacts against a joint limit and the ground (at the end of this file).

docs/conventions.md, "Stabilisation": the end-of-step target of the joint rows reverses the start pose's
constraint velocity ``w- = J(q-) u-`` every step unless it keeps the share ``gamma = MIDPOINT_DAMPING`` of it. With
``gamma = 0`` the alternating mode is undamped, the curvature term (predicted along ``u_f``, which carries the mode)
pumps it by ``O(h omega)`` per step, and the four-bar below diverged after 349 steps (1.45 s) with stiff
stabilisation, whatever the PADMM tolerance; with post-stabilisation and soft Baumgarte the projection hid the
closure error but the mode still grew (e-fold in ~1.5 s) until the hard case of ``kamino.models.fourbar``'s
docstring blew up after 5.4 s. Float64 throughout (tests/conftest.py).
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import kamino
from kamino.jax_ref.jacobians import constraint_jacobian, joint_frames
from kamino.jax_ref.types import layout_of
from tests.helpers import BACKENDS, JAX

DT = 1.0 / 240.0
STEPS = 480  # 2 s: past the 349 steps the undamped rule survived
TAU = 0.5  # N m on the crank: it spins up to 11.3 rad/s; its free spin-up dt tau / I_cm is 2.1 rad/s per step
#: stiff velocity-level stabilisation (the former defaults; converged solves: rho 0.05, tolerance 1e-6 in float64)
STIFF = kamino.SolverConfig(dt=DT, integrator="midpoint", tolerance=1e-6,
                            stabilisation=kamino.Stabilisation(baumgarte=1.0, post_stabilisation=0),
                            penalty=kamino.Penalty(rho=0.05))
#: post-stabilisation with soft Baumgarte: the direction of the project's defaults
POST = kamino.SolverConfig(dt=DT, integrator="midpoint", tolerance=1e-6,
                           stabilisation=kamino.Stabilisation(baumgarte=0.01, post_stabilisation=1),
                           penalty=kamino.Penalty(rho=0.05))
CONFIGS = {"stiff": STIFF, "post": POST}


@functools.cache
def _driven_fourbar():
    """The model, its crank joint, the motor's controls and the initial state (built once: the jitted analysis
    below is traced for this model)."""
    model = kamino.models.fourbar()
    crank = int(model.joint_index("ground_crank"))
    effort = jnp.zeros((STEPS, model.num_dofs)).at[:, int(model.joint_dof_start[crank])].set(TAU)
    return model, crank, kamino.Control(dof_effort=effort), kamino.init_state(model)


@functools.cache
def _analysis():
    """Per state of a trajectory: closure, kinetic and total energy, crank angle, and ``max |J(q+) u+|`` over the
    joint rows (the end pose's constraint velocity [m/s, rad/s]), in one jitted function."""
    model, crank, _, state = _driven_fourbar()
    pm = jax.tree_util.tree_map(lambda x: x[0], layout_of(model, state.body_q.dtype).padded)  # one world
    nb = pm.body_mask.shape[0]
    c0 = int(model.joint_coord_start[crank])

    def one(q, u):
        s = state.replace(body_q=q, body_u=u)
        met = kamino.metrics(model, s)
        w = jnp.max(jnp.abs(constraint_jacobian(pm, joint_frames(pm, q), nb) @ u.reshape(-1)))
        return (met["constraint_violation"][0], met["kinetic_energy"][0], met["total_energy"][0],
                kamino.joint_positions(model, s)[c0], w)

    return jax.jit(jax.vmap(one))


def _run(variant, name: str) -> kamino.State:
    model, _, ctrl, state = _driven_fourbar()
    return variant.rollout(model, state, ctrl, config=CONFIGS[name])


@pytest.fixture(scope="module")
def jax_runs() -> dict:
    """The JAX reference's trajectories (the oracle of the Warp variants), each computed once."""
    return {}


def _jax_run(jax_runs: dict, name: str) -> kamino.State:
    if name not in jax_runs:
        jax_runs[name] = _run(JAX, name)
    return jax_runs[name]


def test_damping_lies_strictly_between_its_undamped_ends():
    """Both backends read ``kamino.config.MIDPOINT_DAMPING``; at 0 the alternating mode is undamped, at 1 the target
    is ``e+ = h w-``, ``h w+ = -e-`` (a rotation, undamped too)."""
    from kamino.config import MIDPOINT_DAMPING

    assert 0.0 < MIDPOINT_DAMPING < 1.0


@pytest.mark.parametrize("name", list(CONFIGS))
@pytest.mark.parametrize("variant", BACKENDS)
def test_driven_fourbar_midpoint_is_stable(variant, name, jax_runs):
    traj = _run(variant, name) if variant.is_warp else _jax_run(jax_runs, name)
    model, crank, _, state = _driven_fourbar()
    assert not bool(np.any(traj.info.failed)) and bool(np.all(np.isfinite(traj.body_q)))
    assert bool(np.all(traj.info.converged)), "PADMM must reach its tolerance on every step"
    closure, kinetic, total, theta, w = (np.asarray(x) for x in _analysis()(traj.body_q, traj.body_u))
    omega = np.asarray(traj.body_u[:, model.body_index("crank"), 4])
    assert np.abs(omega).max() > 10.0  # the crank really whips round (11.3 rad/s)

    # loop closure. stiff: each step leaves O(h^2 |u+ - u_f| |u|) of the curvature term predicted along the free
    # velocity: (1/480 s)^2 x 2.1 rad/s x 11.3 rad/s x 0.09 m = 9e-6 m with the crank's explicit torque; measured
    # 1.15e-5 m (Euler: 3.5e-5 m), bound 3e-5 m. post: one Gauss-Newton projection of that error; measured 1.3e-7 m,
    # bound the passive four-bar's 1e-6 m (test_physics.py)
    assert closure.max() < {"stiff": 3e-5, "post": 1e-6}[name], closure.max()

    # energy balance against the motor's work tau (theta - theta_0), relative to the peak kinetic energy (0.62 J;
    # the motor puts in 1.2 J). Measured: stiff 0.13 % (Euler 2.1 %), post 1.3 % (Euler 4.7 %: the projection
    # moves the bodies without doing work); bounds 0.5 % (the passive four-bar's issue bound) and 3 %
    theta0 = float(kamino.joint_positions(model, state)[int(model.joint_coord_start[crank])])
    theta = np.unwrap(np.concatenate([[theta0], theta]))[1:]
    E0 = float(kamino.metrics(model, state)["total_energy"][0])
    balance = np.abs(total - E0 - TAU * (theta - theta0)).max() / kinetic.max()
    assert balance < {"stiff": 5e-3, "post": 3e-2}[name], balance

    # the alternating mode: the end pose's constraint velocity stays at the level that the curvature prediction's
    # error feeds (measured 3.5e-3 m/s) instead of growing (undamped, with post-stabilisation: 3e-3 m/s in the first
    # second, 1.6e-2 m/s in the next; with stiff stabilisation it diverges)
    half = STEPS // 2
    assert w[half:].max() < 1.5 * w[:half].max() and w.max() < 1e-2, (w[:half].max(), w[half:].max())

    if variant.is_warp and not variant.is_cr:
        # the oracle's computation, up to rounding (CR solves each PADMM iteration inexactly: cr_iterations)
        ref = _jax_run(jax_runs, name)
        assert np.abs(np.asarray(traj.body_q) - np.asarray(ref.body_q)).max() < 1e-9
        assert np.abs(np.asarray(traj.body_u) - np.asarray(ref.body_u)).max() < 1e-9


# ---------------------------------------------------------------------------------------------
# Limits and contacts on impact (docs/conventions.md, "Joint limits"): the unilateral rows aim one step dt ahead, at
# the pose where the next step reads them (the midpoint rule's next q_m is q_m ⊕ dt u+), so no first half-step
# overshoots into a limit or the ground, and nothing has to be undone with an outward velocity
# ---------------------------------------------------------------------------------------------

#: converged solves (the rule, not PADMM's stop, is checked); the default tolerance 1e-3 adds up to dt x 1e-3 per step
IMPACT = kamino.SolverConfig(dt=DT, integrator="midpoint", tolerance=1e-6)
LIMIT = 0.2  # [rad] upper limit of the pendulum below
ROD = 0.5  # [m] the pendulum's rod, hinged at its end
#: share of the first half-step's reach ``h |v|`` (``h = dt/2``) that an impact may end inside the limit or the ground:
#: reading the rows with the half step keeps 77 % of it on the pendulum and 27 % on the box
OVERSHOOT = 0.01


def _pendulum_onto_its_limit() -> kamino.Model:
    """A 1 kg rod of length ``ROD`` hinged at its end about +y, released horizontal: gravity raises its angle onto the
    upper limit ``LIMIT``."""
    b = kamino.ModelBuilder(gravity=(0.0, 0.0, -9.81))
    rod = b.add_body(mass=1.0, inertia=(0.001, 0.021, 0.021), pos=(0.5 * ROD, 0, 1))
    b.add_joint_at(kamino.JointType.REVOLUTE, -1, rod, anchor=(0, 0, 1), axis=(0, 1, 0), limits=(-1.0, LIMIT))
    return b.finalize()


def test_midpoint_rule_stops_a_pendulum_at_its_limit_without_overshoot_or_rebound():
    """The pendulum reaches its limit at ``sqrt(2 m g (ROD/2) sin(LIMIT) / I_hinge)`` = 3.4 rad/s: the first half-step
    could overshoot by ``h |omega|`` = 7e-3 rad (reading the rows with the half step keeps 5.4e-3 rad; asking the end
    pose to undo it instead rebounds at 3.2 rad/s). The limit holds to ``OVERSHOOT`` of that reach (measured 1.3e-7 rad;
    1.2e-5 rad at the default tolerance, Euler 1.5e-5 rad), the impact is inelastic: no outward speed above what the
    Baumgarte term asks of such a violation, ``LIMIT_BAUMGARTE x violation / dt`` (measured 5.9e-6 rad/s), and the
    limit at rest carries the gravity torque ``m g (ROD/2) cos(LIMIT)`` to 1e-4 on every step."""
    from kamino.config import LIMIT_BAUMGARTE

    model = _pendulum_onto_its_limit()
    traj = kamino.rollout(model, kamino.init_state(model), num_steps=int(1.0 / DT), config=IMPACT, backend="warp")
    quat = np.asarray(traj.body_q)[:, 0, 3:]  # (x, y, z, w): a rotation about +y from the identity
    theta = 2.0 * np.arctan2(quat[:, 1], quat[:, 3])
    omega = np.asarray(traj.body_u)[:, 0, 4]  # the hinge rate (about +y)
    impact = int(np.argmax(theta > LIMIT - 1e-3))
    speed = float(np.sqrt(2.0 * 9.81 * 0.5 * ROD * np.sin(LIMIT) / (0.021 + 0.25 * ROD**2)))
    assert 0 < impact < len(theta) // 2 and omega.max() > 0.9 * speed  # it does hit, at full speed
    bound = OVERSHOOT * 0.5 * DT * speed
    assert theta.max() - LIMIT < bound, theta.max() - LIMIT
    assert -omega[impact:].min() < LIMIT_BAUMGARTE * bound / DT, omega[impact:].min()
    force = np.asarray(traj.limit_force)[-int(0.5 / DT):, 0]  # the last half second, at rest
    assert np.allclose(force, -9.81 * 0.5 * ROD * np.cos(LIMIT), rtol=1e-4), (force.min(), force.max())


def test_midpoint_rule_lands_a_dropped_box_without_sinking():
    """tests/test_free_joint_contact.py's 0.2 m box dropped 2 cm lands at ``sqrt(2 g DROP)`` = 0.63 m/s: the first
    half-step could sink it by ``h |v|`` = 1.3e-3 m (reading the contacts with the half step keeps 3.5e-4 m). It sinks
    less than ``OVERSHOOT`` of that reach (measured: it stays 1e-6 m above, the contact dead band; 2.5e-6 m deep at the
    default tolerance, Euler 2.7e-6 m), does not bounce (upward speed below what the Baumgarte term asks of such a
    penetration; measured 4e-11 m/s) and rests on the plane."""
    from kamino.config import CONTACT_BAUMGARTE
    from tests.test_free_joint_contact import DROP, HALF, _free_box_over_plane

    model = _free_box_over_plane()
    traj = kamino.rollout(model, kamino.init_state(model), num_steps=int(0.25 / DT), config=IMPACT, backend="warp")
    z = np.asarray(traj.body_q)[:, 0, 2]
    vz = np.asarray(traj.body_u)[:, 0, 2]
    bound = OVERSHOOT * 0.5 * DT * float(np.sqrt(2.0 * 9.81 * DROP))
    assert (HALF - z).max() < bound, (HALF - z).max()
    assert vz.max() < CONTACT_BAUMGARTE * bound / DT, vz.max()
    assert np.abs(z[-10:] - HALF).max() < bound  # resting on the plane
