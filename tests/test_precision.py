"""The JAX reference traces its float32 matrix products at full precision (kamino/jax_ref/precision.py).

On NVIDIA GPUs JAX's default float32 product is TF32 (10-bit mantissa). At that precision ``dr_legs`` on the JAX
backend diverged within 2.5 s on an H200 (loop closure 1.5e5 m); with every product of the step at
``Precision.HIGHEST`` the same run closed its loops to 4.4e-6 m. A CPU computes float32 products in full either way,
so CI cannot see the divergence itself. It checks the cause instead: every ``dot_general`` traced by
the step, a rollout inside a user's ``jax.jit``, the metrics and forward kinematics carries ``HIGHEST``.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import pytest

import kamino


def _dot_precisions(jaxpr) -> list:
    """The ``precision`` parameter of every ``dot_general`` in ``jaxpr`` and in the jaxprs nested in it."""
    found = []
    for eqn in jaxpr.eqns:
        if eqn.primitive.name == "dot_general":
            found.append(eqn.params["precision"])
        for value in eqn.params.values():
            for sub in value if isinstance(value, (tuple, list)) else (value,):
                inner = getattr(sub, "jaxpr", sub)
                if hasattr(inner, "eqns"):
                    found.extend(_dot_precisions(inner))
    return found


def _assert_all_highest(fn, *args) -> None:
    precisions = _dot_precisions(jax.make_jaxpr(fn)(*args).jaxpr)
    assert precisions, "no matrix product traced: the check would be vacuous"
    highest = (jax.lax.Precision.HIGHEST, jax.lax.Precision.HIGHEST)
    bad = [p for p in precisions if p != highest]
    assert not bad, f"{len(bad)} of {len(precisions)} products below full precision, e.g. {bad[0]}"


@pytest.fixture(scope="module")
def fourbar():
    model = kamino.replicate(kamino.models.fourbar(), 2)
    return model, kamino.init_state(model, jnp.float32)


def test_step_and_rollout_products_are_full_precision(fourbar):
    model, state = fourbar
    _assert_all_highest(lambda s: kamino.step(model, s, backend="jax"), state)
    _assert_all_highest(jax.jit(lambda s: kamino.rollout(model, s, num_steps=3, backend="jax")), state)


def test_metrics_and_forward_kinematics_products_are_full_precision(fourbar):
    model, state = fourbar
    _assert_all_highest(lambda q: kamino.metrics(model, dataclasses.replace(state, body_q=q))["constraint_violation"],
                        state.body_q)
    angles = jnp.zeros(model.num_actuators, jnp.float32)
    _assert_all_highest(lambda a: kamino.forward_kinematics(model, actuated_positions=a).body_q, angles)
