"""``kamino.step(..., backend="warp")`` of a one-world model, batchable by ``jax.vmap`` (issue 18, "Backends").

Inside ``jax.jit`` the Warp step is one XLA FFI call (``kamino/warp_backend/jit.py``, ``wp.jax_callable``) made
with ``vmap_method=None``: JAX refuses to ``vmap`` it. Brax vmaps an environment over its batch, so the
environment's physics step is wrapped in ``jax.custom_batching.custom_vmap``, whose batching rule does what a
multi-world model does anyway: a batch of ``B`` copies of an ``n``-world state *is* the flat state of
``kamino.replicate(model, n * B)`` (storage is flat over worlds, world 0's entities first: docs/conventions.md
"Data layout"), so the rule reshapes ``[B, N, ...]`` to ``[B * N, ...]``, makes one Warp call for all worlds and
reshapes back. Nested ``vmap`` (brax's evaluator inside ``pmap``, a ``vmap`` of a ``vmap``) recurses: the rule's
own call is again a ``custom_vmap`` function of the larger model. No physics here, only the layout.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from kamino.api import step as kamino_step
from kamino.config import SolverConfig
from kamino.model import Model, replicate
from kamino.state import Control, State


class WarpBatchedStep:
    """``step(state, control)`` of the one-world ``model`` on the Warp backend, with a ``vmap`` rule.

    Keeps the replicated models alive (the Warp backend caches its steppers per model, weakly): one per batch size
    seen, so a training run compiles and allocates once per distinct batch size.
    """

    def __init__(self, model: Model, config: SolverConfig):
        if model.num_worlds != 1:
            raise ValueError(f"WarpBatchedStep: model has {model.num_worlds} worlds, expected 1")
        self._model = model
        self._config = config
        self._models: dict[int, Model] = {1: model}
        self._fns: dict[int, object] = {}

    def __call__(self, state: State, control: Control) -> State:
        return self._fn(1)(state, control)

    def _model_of(self, n: int) -> Model:
        if n not in self._models:
            self._models[n] = replicate(self._model, n)
        return self._models[n]

    def _fn(self, n: int):
        """The ``custom_vmap`` step of the ``n``-world replica (cached)."""
        if n in self._fns:
            return self._fns[n]
        model, config = self._model_of(n), self._config

        @jax.custom_batching.custom_vmap
        def f(state: State, control: Control) -> State:
            return kamino_step(model, state, control, config=config, backend="warp")

        @f.def_vmap
        def rule(axis_size: int, in_batched, state: State, control: Control):
            def lift(x, batched):
                return x if batched else jnp.broadcast_to(x, (axis_size, *jnp.shape(x)))

            state = jax.tree.map(lift, state, in_batched[0])
            control = jax.tree.map(lift, control, in_batched[1])
            merge = lambda x: x.reshape((axis_size * x.shape[1], *x.shape[2:]))  # noqa: E731
            out = self._fn(n * axis_size)(jax.tree.map(merge, state), jax.tree.map(merge, control))
            split = lambda x: x.reshape((axis_size, x.shape[0] // axis_size, *x.shape[1:]))  # noqa: E731
            out = jax.tree.map(split, out)
            return out, jax.tree.map(lambda _: True, out)

        self._fns[n] = f
        return f


__all__ = ["WarpBatchedStep"]
