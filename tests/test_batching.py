"""Many worlds: replicated and heterogeneous worlds reproduce their standalone results."""

from __future__ import annotations

import jax
import numpy as np
import pytest

import kamino
from tests.helpers import BACKENDS

# a tight PADMM tolerance makes the answer independent of the iteration at which a world stops,
# so batched and standalone runs can be compared to rounding (1e-10 is the bound)
CFG = kamino.SolverConfig(dt=1.0 / 240.0, tolerance=1e-12, max_iterations=2000)


def _run(variant, model, n):
    return variant.rollout(model, kamino.init_state(model), num_steps=n, config=CFG)


@pytest.mark.parametrize("variant", BACKENDS)
def test_replicated_worlds_match_single_world(variant):
    single = kamino.models.fourbar()
    # Warp variants: 70 worlds instead of 256, for CI time (Warp's CPU device runs the worlds one after the
    # other); 70 spans two full groups of 32 worlds (the Warp layout interleaves worlds by 32) and a partial one
    n = 70 if variant.is_warp else 256
    many = kamino.replicate(single, n)
    ref = _run(variant, single, 60)
    out = _run(variant, many, 60)
    nb = single.num_bodies
    q = np.asarray(out.body_q[-1]).reshape(n, nb, 7)
    assert np.abs(q - np.asarray(ref.body_q[-1])[None]).max() < 1e-10
    assert np.all(np.asarray(out.info.converged))


@pytest.mark.parametrize("variant", BACKENDS)
def test_heterogeneous_worlds_match_standalone(variant):
    parts = [kamino.models.pendulum(), kamino.models.fourbar(), kamino.models.slider_crank()]
    mixed = kamino.concat(parts)
    out = _run(variant, mixed, 60)
    for w, part in enumerate(parts):
        ref = _run(variant, part, 60)
        s, c = int(mixed.world_body_start[w]), int(mixed.world_body_count[w])
        diff = np.abs(np.asarray(out.body_q[-1, s:s + c]) - np.asarray(ref.body_q[-1])).max()
        assert diff < 1e-10, (w, diff)
        np.testing.assert_array_equal(np.asarray(out.info.iterations[:, w]), np.asarray(ref.info.iterations[:, 0]))


@pytest.mark.parametrize("variant", BACKENDS)
def test_a_failing_world_is_flagged_and_isolated(variant):
    """A world pushed to a non-finite state keeps its previous state, is flagged, and its neighbour runs on."""
    model = kamino.replicate(kamino.models.pendulum(), 2)
    state = kamino.init_state(model)
    wrench = np.zeros((2, 6))
    wrench[1, 0] = np.inf
    nxt = variant.step(model, state, kamino.Control(body_wrench=wrench), config=CFG)
    assert list(np.asarray(nxt.info.failed)) == [False, True]
    assert np.all(np.isfinite(np.asarray(nxt.body_q)))
    np.testing.assert_array_equal(np.asarray(nxt.body_q[1]), np.asarray(state.body_q[1]))
    ref = variant.step(kamino.models.pendulum(), kamino.init_state(kamino.models.pendulum()), config=CFG)
    assert np.abs(np.asarray(nxt.body_q[0]) - np.asarray(ref.body_q[0])).max() < 1e-12
    assert jax.tree.structure(nxt) == jax.tree.structure(state)
