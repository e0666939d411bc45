"""State, Control and StepInfo: JAX pytrees shared by both backends (docs/conventions.md)."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class StepInfo:
    """Per-world report of the last step's constraint solve (all arrays ``[num_worlds]``).

    ``failed`` marks a world whose new state was non-finite: that world keeps its previous
    state (it never contaminates other worlds and never silently holds NaN).
    """

    iterations: jax.Array
    primal_residual: jax.Array
    dual_residual: jax.Array
    complementarity_residual: jax.Array
    converged: jax.Array
    failed: jax.Array

    @staticmethod
    def empty(num_worlds: int, dtype=jnp.float32) -> StepInfo:
        z = jnp.zeros(num_worlds, dtype)
        return StepInfo(
            iterations=jnp.zeros(num_worlds, jnp.int32),
            primal_residual=z,
            dual_residual=z,
            complementarity_residual=z,
            converged=jnp.ones(num_worlds, bool),
            failed=jnp.zeros(num_worlds, bool),
        )


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class State:
    """Simulation state of all worlds (flat storage, world 0's entities first).

    Attributes:
        body_q: ``[total_bodies, 7]`` CoM poses ``(px, py, pz, qx, qy, qz, qw)`` in world.
        body_u: ``[total_bodies, 6]`` twists ``(v, w)``: CoM linear then angular velocity, world frame.
        time: ``[num_worlds]`` simulated time [s].
        constraint_force: ``[total_constraint_rows]`` last step's joint-row reactions ``lambda/dt``
            (the warm start of the next solve), in the row order of docs/conventions.md.
        info: the last solve's :class:`StepInfo`.
    """

    body_q: jax.Array
    body_u: jax.Array
    time: jax.Array
    constraint_force: jax.Array
    info: StepInfo

    def replace(self, **changes) -> State:
        return dataclasses.replace(self, **changes)


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Control:
    """Inputs of one step. ``None`` fields mean zero.

    Attributes:
        dof_effort: ``[total_dofs]`` generalized joint efforts (N for translational DoFs, N m for
            rotational ones; a FREE joint's six are a world-aligned force and torque at the child CoM),
            applied explicitly as body wrenches ``J_dofs^T tau`` (formulation.md §3.1).
        body_wrench: ``[total_bodies, 6]`` external wrenches ``(f, tau)`` in world, torque about the CoM.
    """

    dof_effort: jax.Array | None = None
    body_wrench: jax.Array | None = None
