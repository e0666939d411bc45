"""The implicit-midpoint gyroscopic term (docs/conventions.md, "Gyroscopic term (departure from formulation.md
§1.4)").

A free body (no joint, gravity off) spinning about its intermediate principal axis, slightly perturbed (the
Dzhanibekov case): the explicit term ``-w x I w`` of docs/formulation.md §1.4 pumps energy into it (MuJoCo's Euler
integrator, the same scheme: +82 % after 5 s); MuJoCo's ``implicitfast`` loses energy (-37 %). kamino solves the
free angular velocity from the implicit midpoint rule of the body-frame Euler equation, which keeps the kinetic
energy and ``|L|`` of a torque-free body exactly in exact arithmetic, also through the exponential-map pose update
(it rotates the body about ``w+`` itself, so ``R+^T w+ = R^T w+``).
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import kamino
from kamino.jax_ref import dynamics
from kamino.jax_ref.types import layout_of
from kamino.spatial import quat_to_matrix
from tests.helpers import BACKENDS, JAX, Variant

jax.config.update("jax_enable_x64", True)  # tests in this project run in float64 unless stated

IB = np.array([0.01, 0.02, 0.03])  # principal moments [kg m^2]: a 1 kg rectangular plate 0.49 m x 0.35 m
W0_BODY = np.array([0.05, 30.0, 0.05])  # [rad/s], body frame: 30 rad/s about the intermediate axis, perturbed
Q0 = np.array([0.1, 0.2, 0.3, 0.9]) / np.linalg.norm([0.1, 0.2, 0.3, 0.9])  # a generic orientation (x, y, z, w)
DT = 2.5e-3
NUM_STEPS = 2000  # 5 s: the body flips over and back ~4 times (growth rate 17 /s from the 0.05 rad/s)
#: float64 rounding: ~1e-16 per step over 2000 steps (measured 1.2e-14 on all variants over 10 s); the
#: Newton error left after GYRO_ITERATIONS = 4 iterations from the explicit guess is below rounding here (one
#: iteration alone leaves 8e-8 of the energy over 10 s, two reach rounding)
INVARIANT_TOL = 1e-11


def _rot(q: np.ndarray) -> np.ndarray:
    """Rotation matrices of unit quaternions ``(x, y, z, w)`` ``[..., 4]``."""
    x, y, z, w = np.moveaxis(q, -1, 0)
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], -1),
        np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], -1),
        np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], -1)], -2)


def _invariants(quat: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Kinetic energy ``1/2 w_b . Ī w_b`` and world angular momentum ``L = R Ī w_b`` (``w_b = R^T w``)."""
    R = _rot(quat)
    wb = np.einsum("...ji,...j->...i", R, w)
    return 0.5 * np.sum(wb * IB * wb, -1), np.einsum("...ij,...j->...i", R, IB * wb)


def _deviations(quat: np.ndarray, w: np.ndarray) -> tuple[float, float, float]:
    """Max relative deviation over a trajectory of the kinetic energy, of ``|L|`` and of the vector ``L``."""
    ke0, L0 = _invariants(Q0, _rot(Q0) @ W0_BODY)
    ke, L = _invariants(quat, w)
    n0 = np.linalg.norm(L0)
    return (float(np.max(np.abs(ke / ke0 - 1))), float(np.max(np.abs(np.linalg.norm(L, axis=-1) / n0 - 1))),
            float(np.max(np.linalg.norm(L - L0, axis=-1) / n0)))


def _spinning_plate() -> tuple[kamino.Model, kamino.State]:
    b = kamino.ModelBuilder(gravity=(0.0, 0.0, 0.0))
    b.add_body(mass=1.0, inertia=IB, quat=Q0, angular_velocity=_rot(Q0) @ W0_BODY)
    model = b.finalize()
    return model, kamino.init_state(model)


def _mujoco_deviations(integrator: str) -> tuple[float, float, float]:
    """The same body in MuJoCo (free joint, ``diaginertia``), ``NUM_STEPS`` steps of ``DT`` (~10 ms)."""
    mujoco = pytest.importorskip("mujoco")
    quat_wxyz, inertia = " ".join(repr(float(x)) for x in np.roll(Q0, 1)), " ".join(repr(float(x)) for x in IB)
    xml = f"""<mujoco><option timestep="{DT}" gravity="0 0 0" integrator="{integrator}"/>
      <worldbody><body quat="{quat_wxyz}"><freejoint/>
      <inertial pos="0 0 0" mass="1" diaginertia="{inertia}"/></body></worldbody></mujoco>"""
    m = mujoco.MjModel.from_xml_string(xml)
    d = mujoco.MjData(m)
    d.qvel[3:6] = W0_BODY  # a free joint's angular velocity is in the body frame
    quat, w = np.zeros((NUM_STEPS, 4)), np.zeros((NUM_STEPS, 3))
    for k in range(NUM_STEPS):
        mujoco.mj_step(m, d)
        quat[k] = np.roll(d.qpos[3:7], -1)  # (w, x, y, z) -> (x, y, z, w)
        w[k] = _rot(quat[k]) @ d.qvel[3:6]
    return _deviations(quat, w)


@pytest.fixture(scope="module")
def jax_trajectory() -> kamino.State:
    model, state = _spinning_plate()
    return JAX.rollout(model, state, num_steps=NUM_STEPS, config=kamino.SolverConfig(dt=DT))


@pytest.mark.parametrize("variant", BACKENDS)
def test_intermediate_axis_spin_keeps_energy_and_momentum(variant: Variant, jax_trajectory: kamino.State) -> None:
    model, state = _spinning_plate()
    traj = jax_trajectory if not variant.is_warp else variant.rollout(
        model, state, num_steps=NUM_STEPS, config=kamino.SolverConfig(dt=DT))
    assert not np.any(np.asarray(traj.info.failed))
    quat, w = np.asarray(traj.body_q[:, 0, 3:]), np.asarray(traj.body_u[:, 0, 3:])
    wb = np.einsum("tji,tj->ti", _rot(quat), w)
    assert wb[:, 1].min() < -25.0  # it does flip over: the intermediate axis is unstable
    d_ke, d_l, d_lvec = _deviations(quat, w)
    assert d_ke < INVARIANT_TOL and d_l < INVARIANT_TOL, (d_ke, d_l)
    # The direction of L is not an invariant of the scheme: the body frame is frozen at the step's evaluation pose,
    # so L turns by O(dt) per flip and turns back (bounded, measured 2.19e-2 over 5 s, 10 s and 60 s alike;
    # 3.9e-4 with integrator="midpoint"). 3e-2 is that measurement with margin.
    assert d_lvec < 3e-2, d_lvec
    mj_euler, mj_implicitfast = _mujoco_deviations("Euler"), _mujoco_deviations("implicitfast")
    assert mj_euler[0] > 0.5  # the explicit term (MuJoCo Euler = kamino before, same numbers): measured +82 %
    assert d_ke < mj_implicitfast[0] and d_l < mj_implicitfast[1] and d_lvec < mj_implicitfast[2], mj_implicitfast
    if variant.is_warp:
        # the same rule in both backends: rounding differences (~1e-15 per step) grow along the unstable
        # intermediate-axis motion (x75 in 0.25 s at 17 /s); measured 5.3e-13 rad/s after 100 steps (|w| = 30)
        n = 100
        np.testing.assert_allclose(np.asarray(traj.body_u[:n]), np.asarray(jax_trajectory.body_u[:n]), rtol=0,
                                   atol=1e-11)
        np.testing.assert_allclose(np.asarray(traj.body_q[:n]), np.asarray(jax_trajectory.body_q[:n]), rtol=0,
                                   atol=1e-13)  # the pose integrates w: dt * 1e-11


def test_midpoint_integrator_keeps_energy_and_momentum() -> None:
    """Under the midpoint rule the evaluation frame is the midpoint pose, and ``Exp(dt/2 w)`` rotates about ``w``
    itself on both half steps: the invariants are kept as well, and the direction of L to second order."""
    model, state = _spinning_plate()
    traj = JAX.rollout(model, state, num_steps=NUM_STEPS, config=kamino.SolverConfig(dt=DT, integrator="midpoint"))
    d_ke, d_l, d_lvec = _deviations(np.asarray(traj.body_q[:, 0, 3:]), np.asarray(traj.body_u[:, 0, 3:]))
    assert d_ke < INVARIANT_TOL and d_l < INVARIANT_TOL, (d_ke, d_l)
    assert d_lvec < 1e-3, d_lvec  # measured 3.9e-4 (second order in dt), see the test above


def _random_inputs(rng: np.random.Generator, n: int) -> tuple[np.ndarray, ...]:
    """Rotations, initial and explicit angular velocities (world), ``|w| dt`` up to 0.35 at ``DT``."""
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=-1, keepdims=True)
    R = np.asarray(quat_to_matrix(jnp.asarray(q)))
    w0 = rng.normal(size=(n, 3)) * rng.uniform(1.0, 70.0, size=(n, 1))
    we = w0 + rng.normal(size=(n, 3))
    return R, w0, we


def test_spherical_inertia_gives_exactly_the_explicit_result() -> None:
    """``w x (c w) = 0``: with ``Ī' = Ī - Ī_00 1 = 0`` the correction is exactly zero, so the free velocity is the
    explicit ``u + dt M^-1 h`` bit for bit (and a spherical body's step is unchanged)."""
    rng = np.random.default_rng(0)
    R, w0, we = _random_inputs(rng, 64)
    Ib = np.eye(3) * rng.uniform(1e-3, 10.0, size=(64, 1, 1))
    corr = np.asarray(dynamics.gyroscopic_correction(jnp.asarray(Ib), jnp.asarray(R), jnp.asarray(w0),
                                                     jnp.asarray(we), DT))
    assert np.all(corr == 0.0)
    assert np.all(_warp_correction(Ib, R, w0, we) == 0.0)
    # the whole free velocity, with gravity and external wrenches on bodies of different spherical inertias
    b = kamino.ModelBuilder(gravity=(0.0, 0.0, -9.81))
    for k in range(5):
        quat = rng.normal(size=4)
        b.add_body(mass=1.0 + k, inertia=np.eye(3) * (0.1 + 0.3 * k), pos=(k, 0, 0), quat=quat / np.linalg.norm(quat),
                   angular_velocity=rng.normal(size=3) * 20.0, velocity=rng.normal(size=3))
    model = b.finalize()
    state = kamino.init_state(model)
    pm = jax.tree.map(lambda x: x[0], layout_of(model, np.float64).padded)
    q, u = state.body_q[:5], state.body_u[:5]
    bd = dynamics.body_dynamics(pm, q)
    h = dynamics.nonlinear_force(pm, bd, u, pm.gravity, jnp.asarray(rng.normal(size=(5, 6))))
    explicit = u + DT * dynamics.apply_inv_mass(bd, h)
    assert np.array_equal(np.asarray(dynamics.free_velocity(pm, bd, q, u, h, DT)), np.asarray(explicit))


def _warp_correction(Ib: np.ndarray, R: np.ndarray, w0: np.ndarray, we: np.ndarray) -> np.ndarray:
    """The Warp backend's ``gyroscopic_correction`` wp.func on the CPU, float64."""
    import warp as wp

    from kamino.warp_backend.dynamics import gyroscopic_correction_func
    from kamino.warp_backend.types import types_of

    T = types_of(np.float64)
    fn = gyroscopic_correction_func(np.float64)

    @wp.kernel(module="unique", enable_backward=False)
    def run(Ib: wp.array(dtype=T.mat33), R: wp.array(dtype=T.mat33), w0: wp.array(dtype=T.vec3),
            we: wp.array(dtype=T.vec3), dt: T.scalar, out: wp.array(dtype=T.vec3)):
        i = wp.tid()
        out[i] = fn(Ib[i], R[i], w0[i], we[i], dt)

    arr = lambda x, t: wp.array(np.ascontiguousarray(x), dtype=t, device="cpu")  # noqa: E731
    out = wp.zeros(len(Ib), dtype=T.vec3, device="cpu")
    wp.launch(run, dim=len(Ib), inputs=[arr(Ib, T.mat33), arr(R, T.mat33), arr(w0, T.vec3), arr(we, T.vec3),
                                        T.scalar(DT), out], device="cpu")
    return out.numpy()


def test_correction_solves_the_implicit_midpoint_rule_in_both_backends() -> None:
    """Full (non-diagonal) inertias (principal ratios up to 70), ``|w| dt`` up to 0.35 (the explicit guess off by up
    to 120 % of ``|w|``): ``w_f = w_e + correction`` satisfies
    ``Ī (w_f - w0) = dt (tau_b - w̄ x Ī w̄)`` to rounding, and the Warp wp.func gives the JAX function's result."""
    rng = np.random.default_rng(1)
    n = 64
    R, w0, _ = _random_inputs(rng, n)
    A = rng.normal(size=(n, 3, 3))
    Ib = A @ np.swapaxes(A, -1, -2) * 0.01 + np.eye(3) * 1e-3  # symmetric positive definite
    tau = rng.normal(size=(n, 3)) * 0.5  # world torque [N m]
    # explicit free angular velocity (docs/formulation.md §1.4) in world coordinates
    Iw = R @ Ib @ np.swapaxes(R, -1, -2)
    we = w0 + DT * np.linalg.solve(Iw, (tau - np.cross(w0, np.einsum("nij,nj->ni", Iw, w0)))[..., None])[..., 0]
    corr = np.asarray(dynamics.gyroscopic_correction(jnp.asarray(Ib), jnp.asarray(R), jnp.asarray(w0),
                                                     jnp.asarray(we), DT))
    wf = we + corr
    to_b = lambda x: np.einsum("nji,nj->ni", R, x)  # noqa: E731
    wbar = to_b(0.5 * (w0 + wf))
    change = np.einsum("nij,nj->ni", Ib, to_b(wf - w0))
    gyro = np.cross(wbar, np.einsum("nij,nj->ni", Ib, wbar))
    res = change - DT * (to_b(tau) - gyro)
    nrm = lambda x: np.linalg.norm(x, axis=-1)  # noqa: E731
    scale = nrm(np.einsum("nij,nj->ni", Ib, to_b(w0)))  # |L|: wf - w0 is rounded to ~1e-16 |w0|
    # Newton from the explicit guess: 4 iterations reach rounding (measured 6e-16 of |L|; 3 leave 3e-12)
    assert np.max(nrm(res) / scale) < 1e-14
    assert np.max(np.linalg.norm(corr, axis=-1) / np.linalg.norm(w0, axis=-1)) > 1e-3  # the correction is not small
    # Warp: same operations, LU solve vs 3x3 inverse, so agreement to rounding of |w| (~1e-16 relative)
    np.testing.assert_allclose(_warp_correction(Ib, R, w0, we), corr, rtol=0, atol=1e-13)


def test_correction_is_differentiable() -> None:
    """A fixed Newton count: ``jax.grad`` through the correction matches central differences."""
    rng = np.random.default_rng(2)
    R, w0, we = _random_inputs(rng, 1)
    Ib = jnp.asarray(np.diag(IB)[None])
    c = jnp.asarray(rng.normal(size=(1, 3)))
    f = jax.jit(lambda w: jnp.sum(c * dynamics.gyroscopic_correction(Ib, jnp.asarray(R), w, we + (w - w0), DT)))
    x = jnp.asarray(w0)
    g = np.asarray(jax.grad(f)(x))
    h = 1e-6
    fd = np.array([(f(x.at[0, i].add(h)) - f(x.at[0, i].add(-h))) / (2 * h) for i in range(3)])
    # central differences: O(h^2 f''') truncation plus ~1e-16 |f| / h rounding, well below 1e-6 of |g|
    np.testing.assert_allclose(g[0], fd, rtol=1e-6, atol=1e-9 * np.abs(g).max())
