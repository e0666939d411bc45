"""Many worlds: replicated and heterogeneous worlds reproduce their standalone results (issue 2)."""

from __future__ import annotations

import jax
import numpy as np

import kamino

# a tight PADMM tolerance makes the answer independent of the iteration at which a world stops,
# so batched and standalone runs can be compared to rounding (1e-10 is the bound)
CFG = kamino.SolverConfig(dt=1.0 / 240.0, tolerance=1e-12, max_iterations=2000)


def _run(model, n):
    return kamino.rollout(model, kamino.init_state(model), num_steps=n, config=CFG)


def test_replicated_worlds_match_single_world():
    single = kamino.models.fourbar()
    many = kamino.replicate(single, 256)
    ref = _run(single, 60)
    out = _run(many, 60)
    nb = single.num_bodies
    q = np.asarray(out.body_q[-1]).reshape(256, nb, 7)
    assert np.abs(q - np.asarray(ref.body_q[-1])[None]).max() < 1e-10
    assert np.all(np.asarray(out.info.converged))


def test_heterogeneous_worlds_match_standalone():
    parts = [kamino.models.pendulum(), kamino.models.fourbar(), kamino.models.slider_crank()]
    mixed = kamino.concat(parts)
    out = _run(mixed, 60)
    for w, part in enumerate(parts):
        ref = _run(part, 60)
        s, c = int(mixed.world_body_start[w]), int(mixed.world_body_count[w])
        diff = np.abs(np.asarray(out.body_q[-1, s:s + c]) - np.asarray(ref.body_q[-1])).max()
        assert diff < 1e-10, (w, diff)
        np.testing.assert_array_equal(np.asarray(out.info.iterations[:, w]), np.asarray(ref.info.iterations[:, 0]))


def test_a_failing_world_is_flagged_and_isolated():
    """A world pushed to a non-finite state keeps its previous state, is flagged, and its neighbour runs on."""
    model = kamino.replicate(kamino.models.pendulum(), 2)
    state = kamino.init_state(model)
    wrench = np.zeros((2, 6))
    wrench[1, 0] = np.inf
    nxt = kamino.step(model, state, kamino.Control(body_wrench=wrench), config=CFG)
    assert list(np.asarray(nxt.info.failed)) == [False, True]
    assert np.all(np.isfinite(np.asarray(nxt.body_q)))
    np.testing.assert_array_equal(np.asarray(nxt.body_q[1]), np.asarray(state.body_q[1]))
    ref = kamino.step(kamino.models.pendulum(), kamino.init_state(kamino.models.pendulum()), config=CFG)
    assert np.abs(np.asarray(nxt.body_q[0]) - np.asarray(ref.body_q[0])).max() < 1e-12
    assert jax.tree.structure(nxt) == jax.tree.structure(state)
