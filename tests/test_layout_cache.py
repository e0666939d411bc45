"""The JAX reference's cached padded layout (``kamino/jax_ref/types.py``, ``layout_of``) never holds tracers:
a first call of ``kamino.metrics`` / ``kamino.joint_positions`` under ``jax.jit`` must not poison later eager
calls, nor an eager first call later jitted ones."""

from __future__ import annotations

import jax
import numpy as np
import pytest

import kamino
from kamino.jax_ref.types import layout_of


def _fns():
    return {"metrics": kamino.metrics, "joint_positions": kamino.joint_positions}


@pytest.mark.parametrize("fn", ["metrics", "joint_positions"])
@pytest.mark.parametrize("jit_first", [True, False], ids=["jit-first", "eager-first"])
def test_layout_cache_serves_jit_and_eager_calls_alike(fn, jit_first):
    # a fresh model: its layout is not cached yet, so the first call below builds it
    model = kamino.models.fourbar()
    state = kamino.init_state(model)
    f = _fns()[fn]
    jitted = jax.jit(lambda s: f(model, s))
    eager = lambda s: f(model, s)  # noqa: E731
    first, second = (jitted, eager) if jit_first else (eager, jitted)
    a, b = first(state), second(state)
    lay = layout_of(model, state.body_q.dtype)
    leaves = jax.tree_util.tree_leaves((lay.padded, lay.tables))
    assert not any(isinstance(x, jax.core.Tracer) for x in leaves)
    # a third call on the other path again, then compare: the same formulas on the same inputs, XLA fusing
    # the jitted ones differently, so equal up to a few float64 roundings (1e-12 relative is ~4500 ulp)
    c = first(state)
    for other in (b, c):
        for x, y in zip(jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(other), strict=True):
            np.testing.assert_allclose(np.asarray(x), np.asarray(y), rtol=1e-12, atol=1e-12)
    if fn == "metrics":  # the four-bar at rest in its reference pose: joint rows closed to float64 round-off
        assert float(np.asarray(a["constraint_violation"]).max()) < 1e-9


def test_forward_kinematics_tables_survive_a_jitted_first_call():
    # kamino.kinematics caches its FK row tables per model; a first call inside jax.jit (an environment's reset)
    # must not cache tracers that a second, different jit of the same model then trips on.
    model = kamino.models.fourbar(actuated=True)
    q = np.array([0.3])
    first = jax.jit(lambda a: kamino.forward_kinematics(model, actuated_positions=a).body_q)(q)
    second = jax.jit(lambda a: kamino.forward_kinematics(model, actuated_positions=2.0 * a).residual)(q / 2.0)
    eager = kamino.forward_kinematics(model, actuated_positions=q)
    np.testing.assert_allclose(np.asarray(first), np.asarray(eager.body_q), atol=1e-9)
    assert float(np.max(np.asarray(second))) < 1e-8
