"""``kamino.Simulator``: the object that owns what stepping builds, safe across threads, freed when dropped; and the
one-call entry points ``kamino.step`` / ``rollout`` over it."""

from __future__ import annotations

import gc
import threading
import weakref

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import kamino
from tests.helpers import JAX_GPU_TIER

STEPS = 30


@pytest.fixture(scope="module")
def fourbar():
    """The four-bar with its crank under PD (target 0): a start with the crank turned swings back."""
    return kamino.models.fourbar(actuated=True)


def _start(model, crank: float):
    """The four-bar at rest, its crank turned by ``crank`` rad (forward kinematics closes the loop)."""
    return kamino.init_state(model, jnp.float64, actuated_positions=[crank])


def _final(traj: kamino.State) -> np.ndarray:
    return np.concatenate([np.asarray(traj.body_q[-1]).ravel(), np.asarray(traj.body_u[-1]).ravel()])


def _in_threads(work, count: int) -> dict[int, np.ndarray]:
    """``work(i)`` for ``i < count``, each in its own thread, all started before any is joined."""
    results: dict[int, np.ndarray] = {}
    threads = [threading.Thread(target=lambda i=i: results.__setitem__(i, work(i))) for i in range(count)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    return results


@pytest.mark.parametrize("backend", ["warp", "jax"])
def test_threads_with_their_own_simulators_match_one_thread_bit_for_bit(fourbar, backend):
    # Each thread holds its own simulator of the same Model and rolls out its own start; every result must equal,
    # bit for bit, the same rollout run alone on the main thread: the simulators share nothing but the model.
    with jax.enable_x64(True):
        starts = [_start(fourbar, c) for c in (0.0, 0.2, -0.3, 0.4)]
        alone = [_final(kamino.Simulator(fourbar, backend=backend).rollout(s, num_steps=STEPS)) for s in starts]
        results = _in_threads(lambda i: _final(kamino.Simulator(fourbar, backend=backend).rollout(
            starts[i], num_steps=STEPS)), len(starts))
    for i, expected in enumerate(alone):
        np.testing.assert_array_equal(results[i], expected)
    assert not np.array_equal(alone[0], alone[1])  # the starts differ, so equal results would mean a mix-up


def test_a_shared_simulator_gives_every_thread_its_own_result(fourbar):
    # One Warp simulator (one set of device buffers) stepped by four threads at once, each from its own start and
    # many single steps, interleaved: each thread's trajectory must be bit-identical to the same steps run alone.
    # Without the simulator's lock the threads' loads and reads interleave in the shared buffers.
    with jax.enable_x64(True):
        sim = kamino.Simulator(fourbar, backend="warp")
        starts = [_start(fourbar, c) for c in (0.0, 0.2, -0.3, 0.4)]

        def walk(state):
            for _ in range(STEPS):
                state = sim.step(state)
            return np.concatenate([np.asarray(state.body_q).ravel(), np.asarray(state.body_u).ravel()])

        alone = [walk(s) for s in starts]
        results = _in_threads(lambda i: walk(starts[i]), len(starts))
    for i, expected in enumerate(alone):
        np.testing.assert_array_equal(results[i], expected)


def test_kamino_step_is_the_simulator_a_model_keeps(fourbar):
    # The one-call entry points step with one simulator per (backend, configuration), kept on the model: the same
    # object on every call, and the same numbers as a simulator held by hand.
    from kamino.simulator import simulator_of

    cfg = kamino.SolverConfig(dt=1.0 / 240.0)
    sim = simulator_of(fourbar, cfg, "warp", "step")
    assert simulator_of(fourbar, cfg, "warp", "step") is sim
    assert simulator_of(fourbar, kamino.SolverConfig(dt=1.0 / 120.0), "warp", "step") is not sim
    state = kamino.init_state(fourbar)
    a = kamino.step(fourbar, state, config=cfg, backend="warp")
    b = kamino.Simulator(fourbar, cfg, backend="warp").step(state)
    np.testing.assert_array_equal(np.asarray(a.body_q), np.asarray(b.body_q))


def test_dropping_a_simulator_frees_its_stepper(fourbar):
    sim = kamino.Simulator(fourbar, backend="warp")
    sim.step(kamino.init_state(fourbar))
    stepper = weakref.ref(sim.engine.stepper(np.float32))
    assert stepper() is not None
    del sim
    gc.collect()
    assert stepper() is None


def test_a_model_s_simulators_go_with_the_model():
    model = kamino.models.pendulum()
    kamino.step(model, kamino.init_state(model), backend="warp")
    gone = weakref.ref(model)
    del model
    gc.collect()
    assert gone() is None


@pytest.mark.gpu
@JAX_GPU_TIER[1]
def test_the_warp_backend_differentiates_a_step(fourbar):
    """d(final x of the coupler) / d(a push along x on it), through one Warp step: ``jax.jvp`` of a ``jax.vmap`` over
    two pushes (the batched Warp call's value, the JAX reference's tangent at its solution: kamino/warp_backend/jit.py),
    and ``jax.vmap`` of ``jax.grad`` (the other order, reverse mode) to rounding,
    matches central differences of the same batched step, step 0.1 N, to 1e-8 relative (8e-12 measured: one step is
    nearly linear in the push, and the solves' error, 1e-10 m/s, moves x by 4e-13 m against the 8e-7 m of the
    difference), and is nonzero: the push moves the loop. In the gpu tier: on the CPU of a CI worker the batched
    Warp call after the derivative's program once stopped inside XLA's execution (not understood)."""
    state = kamino.init_state(fourbar)
    warp = kamino.Simulator(fourbar, kamino.SolverConfig(tolerance=1e-10), backend="warp")

    def final_x(f):
        push = jnp.zeros((fourbar.num_bodies, 6)).at[2, 0].set(f)
        return warp.step(state, kamino.Control(body_wrench=push)).body_q[2, 0]

    pushes, h = jnp.array([1.0, -2.0]), 0.1
    x, dx, g = jax.jit(lambda f: (*jax.jvp(jax.vmap(final_x), (f,), (jnp.ones_like(f),)),
                                  jax.vmap(jax.grad(final_x))(f)))(pushes)
    np.testing.assert_allclose(np.asarray(g), np.asarray(dx), rtol=1e-12)  # reverse mode: the transposed tangent
    forward = jax.jit(jax.vmap(final_x))
    fd = (np.asarray(forward(pushes + h)) - np.asarray(forward(pushes - h))) / (2 * h)
    np.testing.assert_allclose(np.asarray(x), np.asarray(forward(pushes)), rtol=0, atol=0)  # the Warp step's value
    assert np.all(np.abs(fd) > 1e-6), fd
    np.testing.assert_allclose(np.asarray(dx), fd, rtol=1e-8)


def test_bad_arguments_are_named():
    model = kamino.models.pendulum()
    with pytest.raises(TypeError, match="Simulator"):
        kamino.Simulator("pendulum.xml")
    with pytest.raises(ValueError, match="unknown backend 'nope'"):
        kamino.Simulator(model, backend="nope")
    reference = kamino.Simulator(model, backend="jax")
    with pytest.raises(TypeError, match=r"Warp backend takes a WorldParameters.*got tuple"):
        kamino.Simulator(model, backend="warp").step_with(reference.parameters(jnp.float32), kamino.init_state(model))
    with pytest.raises(ValueError, match=r"control.position_target has shape \(4,\), expected \(1,\)"):
        # a [num_worlds]-shaped target where [num_dofs] belongs: caught at trace time, before any step
        reference.step_with(reference.parameters(jnp.float32), kamino.init_state(model),
                            kamino.Control(position_target=jnp.zeros(4)))
    sim = kamino.Simulator(model)
    assert sim.model is model and sim.backend == "warp" and isinstance(sim.config, kamino.SolverConfig)
    with pytest.raises(ValueError, match="rollout"):
        sim.rollout(kamino.init_state(model))
