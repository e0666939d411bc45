"""Differentiating through ``step``: unrolled fixed iterations, and implicit gradients at the default config."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import kamino
from kamino.bench.stress_models import serial_chain
from tests.helpers import JAX_GPU_TIER, SPIN_RATES, spinning_chain


@pytest.mark.gpu
@JAX_GPU_TIER[1]
def test_grad_of_pendulum_angle_matches_finite_differences():
    """The reverse-mode derivative of a pendulum's angle after 50 steps with respect to its initial rate, through
    ``fixed_iterations=True`` (the unrolled iterations), against a central difference of the same function. In the gpu
    tier: the unrolled iterations' reverse pass compiles for 22 s on CI's CPU; the default (implicit) derivative is
    checked here. The two function values of the difference come from the program
    that ``jax.value_and_grad`` compiles (its forward pass computes the rollout itself): compiling the plain
    rollout as a third program would add its compile to the test's time and check nothing more."""
    model = kamino.models.pendulum(angle=0.3)
    state0 = kamino.init_state(model)
    # without curvature refinement, whose second solve doubles the unrolled iterations (this checks the gradient's
    # machinery, not the step's physics)
    cfg = kamino.SolverConfig(dt=1.0 / 240.0, fixed_iterations=True, max_iterations=30).replace(
        **{"stabilisation.curvature_refinement": False})

    lever = state0.body_q[0, :3] - jnp.array([0.0, 0.0, 1.0])  # CoM relative to the pivot

    def final_angle(w0):
        omega = jnp.array([0.0, 1.0, 0.0]) * w0
        twist = jnp.concatenate([jnp.cross(omega, lever), omega])  # rigid rotation about the pivot
        s = state0.replace(body_u=twist[None, :])
        traj = kamino.rollout(model, s, num_steps=50, config=cfg, backend="jax")  # the differentiable one
        return kamino.joint_positions(model, jax.tree.map(lambda x: x[-1], traj))[0]

    angle_and_grad = jax.value_and_grad(final_angle)
    w0 = 0.7
    g = float(angle_and_grad(jnp.asarray(w0))[1])
    h = 1e-5
    fd = (float(angle_and_grad(jnp.asarray(w0 + h))[0]) - float(angle_and_grad(jnp.asarray(w0 - h))[0])) / (2 * h)
    # central difference error O(h^2) ~ 1e-10 relative; the bound is 1e-4 relative
    assert abs(g - fd) <= 1e-4 * abs(fd), (g, fd)
    assert abs(fd) > 0.05  # the angle really depends on the initial speed


# Gradients at the default SolverConfig (early exit): the implicit function theorem at each solve's solution
# (kamino/jax_ref/solver.py, ``_implicit``; docs/formulation.md §7.10). The forward solves run to
# ``tolerance=1e-10`` only for the finite differences: a difference quotient divides the change of an early-exit
# solve by the step, so the solve's error must stay far below the step times the derivative.


def _rollout_with(sim: kamino.Simulator, state, control, params, num_steps: int):
    """``num_steps`` steps with the padded-model ``params`` (``Simulator.step_with``), a control held throughout."""
    def body(s, _):
        return sim.step_with(params, s, control), None

    return jax.lax.scan(body, state, None, length=num_steps)[0]


def _central_differences(value_and_grad, x0: jnp.ndarray, h: float) -> np.ndarray:
    """Central differences at ``x0`` along each axis, step ``h``, of the value that the compiled ``value_and_grad``
    returns first (its forward pass is the plain rollout: a separately compiled forward program would only add its
    compile)."""
    out = []
    for k in range(x0.shape[0]):
        e = jnp.zeros_like(x0).at[k].set(h)
        value = lambda x: float(jax.tree.leaves(value_and_grad(x)[0])[0])  # noqa: E731
        out.append((value(x0 + e) - value(x0 - e)) / (2 * h))
    return np.asarray(out)


def test_implicit_grad_of_a_box_sliding_down_an_incline():
    """A box sliding down a 30° slope (mu = 0.5 < tan 30°: it slides throughout, four contacts on its face): the
    downhill distance after 0.1 s, differentiated at the default config with respect to the initial downhill speed
    and the friction coefficient (both geoms' ``mu`` scaled by ``1 + a``). Coulomb sliding: the distance is
    ``v0 T + a T^2 / 2`` with ``a = g (sin 30° - mu cos 30°)``, so ``d/dv0 = T`` and ``d/d log mu = -g mu cos 30°
    T^2 / 2`` for the exact integrator; the step's discretisation (10 steps) changes the second by its
    ``1 / N`` error (bound 15 %), the first by the contacts' stabilisation (bound 1 %). The gradient matches
    central differences to 1e-4 relative (their noise: the solves' error 1e-10 over the step 1e-4), and ``jax.jvp``
    gives the same derivative as ``jax.grad``."""
    model = kamino.models.incline(angle_deg=30.0, mu=0.5)
    th = np.pi / 6
    downhill = jnp.array([np.cos(th), 0.0, -np.sin(th)])
    sim = kamino.Simulator(model, kamino.SolverConfig(dt=0.01, tolerance=1e-10), backend="jax")
    pm, tables = sim.parameters(jnp.float64)
    s0 = kamino.init_state(model)
    s0 = s0.replace(body_u=s0.body_u.at[0, :3].set(0.3 * downhill))
    T, N = 0.1, 10

    def distance(theta):
        s = s0.replace(body_u=s0.body_u.at[0, :3].add(theta[0] * downhill))
        p = dataclasses.replace(pm, geom_friction=pm.geom_friction * (1.0 + theta[1]))
        sT = _rollout_with(sim, s, None, (p, tables), N)
        return jnp.dot(sT.body_q[0, :3] - s0.body_q[0, :3], downhill), sT.info

    value_and_grad = jax.jit(jax.value_and_grad(distance, has_aux=True))
    (_, info), g = value_and_grad(jnp.zeros(2))
    assert int(info.num_contacts[0]) == 4 and bool(info.converged[0])  # face contact, early exit
    assert int(info.iterations[0]) < 200
    fd = _central_differences(value_and_grad, jnp.zeros(2), 1e-4)
    assert np.allclose(np.asarray(g), fd, rtol=1e-4, atol=0.0), (g, fd)
    assert abs(float(g[0]) - T) <= 0.01 * T, g
    slope = -9.81 * 0.5 * np.cos(th) * T * T / 2
    assert abs(float(g[1]) - slope) <= 0.15 * abs(slope), (g, slope)
    # forward mode through the same roots: the directional derivative along the initial speed, to rounding
    _, tangent = jax.jvp(lambda t: distance(t)[0], (jnp.zeros(2),), (jnp.array([1.0, 0.0]),))
    assert abs(float(tangent) - float(g[0])) <= 1e-9 * abs(float(g[0])), (tangent, g)


def _closed_loop_readout():
    """The four-bar (damped hinges) swinging from rest for 8 steps of 0.01 s at the default config with ``tolerance =
    1e-10``, and ``readout(theta, backend)``: a fixed random projection of the final poses and twists as a function
    of a crank effort held throughout, the coupler's relative mass change and the crank hinge's added damping (on the
    Warp backend through ``Simulator.step_with`` as ``WorldParameters``)."""
    model = kamino.models.fourbar(damping=0.05)
    cfg = kamino.SolverConfig(dt=0.01, tolerance=1e-10)
    sim, warp = (kamino.Simulator(model, cfg, backend=b) for b in ("jax", "warp"))
    pm, tables = sim.parameters(jnp.float64)
    world = warp.parameters(jnp.float64)  # the Warp backend's WorldParameters, flat over worlds
    s0 = kamino.init_state(model)
    coupler = model.body_names.index("coupler")
    rng = np.random.default_rng(0)
    wq, wu = jnp.asarray(rng.standard_normal(s0.body_q.shape)), jnp.asarray(rng.standard_normal(s0.body_u.shape))

    def readout(theta, backend="jax"):
        control = kamino.Control(dof_effort=jnp.zeros(model.num_dofs).at[0].set(theta[0]))
        if backend == "jax":
            p = (dataclasses.replace(pm, mass=pm.mass.at[0, coupler].multiply(1.0 + theta[1]),
                                     dof_damping=pm.dof_damping.at[0, 0].add(theta[2])), tables)
        else:
            p = world._replace(body_mass=world.body_mass.at[coupler].multiply(1.0 + theta[1]),
                               dof_damping=world.dof_damping.at[0].add(theta[2]))
        sT = _rollout_with(sim if backend == "jax" else warp, s0, control, p, 8)
        return jnp.sum(wq * sT.body_q) + 0.1 * jnp.sum(wu * sT.body_u)

    return readout


def test_implicit_grad_through_a_closed_loop():
    """The rollout of :func:`_closed_loop_readout` (a planar loop: its out-of-plane rows are redundant, the natural
    map's Jacobian singular along them; curvature refinement: two chained roots per step; post-stabilisation): the
    gradient with respect to the crank effort, the coupler's mass and the crank hinge's damping matches central
    differences to 1e-4 relative (the solves' error, 1e-10, over the step 1e-5)."""
    readout = _closed_loop_readout()
    theta0 = jnp.zeros(3)
    value_and_grad = jax.jit(jax.value_and_grad(readout))
    g = np.asarray(value_and_grad(theta0)[1])
    fd = _central_differences(value_and_grad, theta0, 1e-5)
    assert np.all(np.abs(fd) > 1e-3), fd  # every input moves the readout
    assert np.allclose(g, fd, rtol=1e-4, atol=0.0), (g, fd)


def test_grad_of_a_step_whose_projection_passes_run():
    """A 4-link chain whose links turn at up to 200 rad/s relative to each other (:data:`tests.helpers.SPIN_RATES`):
    one step leaves the step's Jacobian behind, and post-stabilisation's Gauss-Newton passes close the anchors
    (tests/test_fast_motion.py). The gradient of a readout of the final poses and twists with respect to the spin's
    speed (every twist scaled by ``1 + a``, consistent with the joints) matches a central difference to 1e-4 relative.
    The passes are differentiated as the projection they converge to (docs/formulation.md §7.10): measured 6.7e-6
    from the difference, against 2.0e-3 with the identity for their derivative and 5e-10 with their selecting loop
    differentiated as it runs; the differences at ``h = 1e-4`` and ``1e-5`` agree to 3e-8."""
    chain = serial_chain(len(SPIN_RATES))
    state0 = spinning_chain(chain, kamino.init_state(chain, dtype=jnp.float64), SPIN_RATES)
    sim = kamino.Simulator(chain, kamino.SolverConfig(tolerance=1e-12), backend="jax")
    rng = np.random.default_rng(0)
    wq = jnp.asarray(rng.standard_normal(state0.body_q.shape))
    wu = jnp.asarray(0.01 * rng.standard_normal(state0.body_u.shape))

    def readout(a):
        s = sim.step(state0.replace(body_u=state0.body_u * (1.0 + a)))
        return jnp.sum(wq * s.body_q) + jnp.sum(wu * s.body_u)

    value_and_grad = jax.jit(jax.value_and_grad(readout))
    g = float(value_and_grad(0.0)[1])
    h = 1e-5
    fd = (float(value_and_grad(h)[0]) - float(value_and_grad(-h)[0])) / (2 * h)
    assert abs(fd) > 0.1, fd  # the readout moves with the spin
    assert abs(g - fd) <= 1e-4 * abs(fd), (g, fd)


@pytest.mark.gpu
@JAX_GPU_TIER[1]
def test_the_warp_gradient_of_a_closed_loop_is_the_reference_s():
    """The Warp backend's gradient of :func:`_closed_loop_readout`'s rollout (the reference's tangent at the Warp
    solution, kamino/warp_backend/jit.py) is the reference's to 1e-6 relative: at ``tolerance = 1e-10`` the two
    backends' solutions, so their trajectories, agree to about 1e-9, and the derivative moves by about that times the
    loop's condition (tests/test_simulator.py differentiates the Warp step under ``vmap``). In the gpu tier: on CI's
    CPU it costs 30 s (a second compile of the reference's linearised step); measured there at the same bar."""
    readout = _closed_loop_readout()
    theta0 = jnp.zeros(3)
    g = np.asarray(jax.jit(jax.grad(readout))(theta0))
    g_warp = np.asarray(jax.jit(jax.grad(lambda t: readout(t, "warp")))(theta0))
    assert np.allclose(g_warp, g, rtol=1e-6, atol=0.0), (g_warp, g)


def test_stewart_platform_forward_kinematics_closes_its_loops():
    """The Stewart platform's six leg extensions place the platform: forward kinematics from actuated positions
    closes the five loops through it (every joint residual below 1e-9 m in float64, where the solve's
    tolerance is 1e-10), and each slide reads its target extension. The same lift of every leg raises the platform
    without turning it, by the lift over the cosine of the legs' tilt from the vertical (19.1°: 2 cm -> 2.116 cm,
    to 0.5 mm for the change of the tilt over the lift)."""
    model = kamino.models.stewart_platform()
    assert model.num_bodies == 13 and model.num_dofs == 36
    targets = jnp.array([0.02, -0.01, 0.03, 0.0, 0.01, -0.02])
    fk = kamino.forward_kinematics(model, actuated_positions=targets, tolerance=1e-10, dtype=jnp.float64)
    assert bool(fk.converged[0])
    state = kamino.init_state(model).replace(body_q=fk.body_q)
    assert float(kamino.metrics(model, state)["constraint_violation"][0]) < 1e-9
    positions, _ = kamino.dof_state(model, state)
    assert np.allclose(np.asarray(positions)[np.asarray(model.actuator_dof)], targets, atol=1e-9)
    lift = kamino.forward_kinematics(model, actuated_positions=jnp.full(6, 0.02), tolerance=1e-10,
                                     dtype=jnp.float64)
    platform = model.body_names.index("platform")
    rise = float(lift.body_q[platform, 2] - model.body_q0[platform, 2])
    assert abs(rise - 0.02 / np.cos(np.arctan2(0.1558, 0.45))) < 5e-4, rise
    assert np.allclose(np.asarray(lift.body_q[platform, 3:]), np.asarray(model.body_q0[platform, 3:]), atol=1e-6)

