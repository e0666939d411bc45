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
    out = kamino.step(model, state, config=kamino.SolverConfig(), backend="warp")
    it = np.asarray(out.info.iterations)
    assert it[0] < it[1]
