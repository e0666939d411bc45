"""The Warp backend's step pipeline on Warp's CPU device (what CI can check without a GPU)."""

import jax.numpy as jnp
import numpy as np

import kamino


def test_worlds_stop_iterating_when_they_converge():
    # one world at rest converges in 2 iterations, a thrown one needs more: per-world convergence
    model = kamino.concat([kamino.models.fourbar(), kamino.models.fourbar()])
    state = kamino.init_state(model, jnp.float32)
    u = np.array(state.body_u)
    u[model.world_body_start[1]:, 3:] = 3.0
    state = state.replace(body_u=jnp.asarray(u))
    # a tolerance far below the default, so that the thrown world's solve takes more than the minimum 2 iterations
    out = kamino.step(model, state, config=kamino.SolverConfig(tolerance=1e-7), backend="warp")
    it = np.asarray(out.info.iterations)
    assert it[0] < it[1]


def test_the_warp_step_runs_inside_jax_jit_and_scan():
    # through Warp's JAX FFI (kamino/warp_backend/jit.py): the same kernels on XLA's buffers, so the
    # result is bitwise the eager call's
    import jax

    model = kamino.models.box_stack(2)
    state = kamino.init_state(model)
    cfg = kamino.SolverConfig()
    step = jax.jit(lambda s: kamino.step(model, s, config=cfg, backend="warp"))
    jitted = step(step(state))
    eager = kamino.step(model, kamino.step(model, state, config=cfg, backend="warp"), config=cfg, backend="warp")
    np.testing.assert_array_equal(np.asarray(jitted.body_q), np.asarray(eager.body_q))
    np.testing.assert_array_equal(np.asarray(jitted.contacts.force), np.asarray(eager.contacts.force))
    assert int(jitted.info.num_contacts[0]) == int(eager.info.num_contacts[0]) > 0
    traj = jax.jit(lambda s: kamino.rollout(model, s, num_steps=10, config=cfg, backend="warp"))(state)
    ref = kamino.rollout(model, state, num_steps=10, config=cfg, backend="warp")
    np.testing.assert_array_equal(np.asarray(traj.body_q), np.asarray(ref.body_q))
