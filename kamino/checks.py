"""Validation of the State / Control a caller passes to ``kamino.step`` / ``rollout`` (both backends)."""

from __future__ import annotations

import jax
import jax.numpy as jnp

from kamino.model import Model
from kamino.state import Control, State


def check_state(model: Model, state: State) -> None:
    nb = model.num_bodies
    if state.body_q.shape != (nb, 7):
        raise ValueError(f"state.body_q has shape {state.body_q.shape}, expected ({nb}, 7) for this model")
    if state.body_u.shape != (nb, 6):
        raise ValueError(f"state.body_u has shape {state.body_u.shape}, expected ({nb}, 6) for this model")
    for field in ("actuator_force", "passive_force", "limit_force"):
        if getattr(state, field).shape != (model.num_dofs,):
            raise ValueError(f"state.{field} has shape {getattr(state, field).shape}, expected ({model.num_dofs},)")
    if state.coupling_force.shape != (model.num_couplings,):
        raise ValueError(f"state.coupling_force has shape {state.coupling_force.shape}, expected "
                         f"({model.num_couplings},) for this model")
    if state.contacts.pair.shape != (model.num_contacts,):
        raise ValueError(f"state.contacts has capacity {state.contacts.pair.shape[0]}, expected {model.num_contacts} "
                         "for this model (create the state with kamino.init_state(model))")
    if state.constraint_force.shape != (model.num_constraints,):
        raise ValueError(
            f"state.constraint_force has shape {state.constraint_force.shape}, expected "
            f"({model.num_constraints},) for this model"
        )


def check_control(model: Model, control: Control | None) -> None:
    if control is None:
        return
    if control.dof_effort is not None and jnp.shape(control.dof_effort)[-1:] != (model.num_dofs,):
        raise ValueError(
            f"control.dof_effort has shape {jnp.shape(control.dof_effort)}, expected ({model.num_dofs},)"
        )
    if control.body_wrench is not None and jnp.shape(control.body_wrench)[-2:] != (model.num_bodies, 6):
        raise ValueError(
            f"control.body_wrench has shape {jnp.shape(control.body_wrench)}, expected ({model.num_bodies}, 6)"
        )
    for field in ("position_target", "velocity_target"):
        value = getattr(control, field)
        if value is not None and jnp.shape(value)[-1:] != (model.num_dofs,):
            raise ValueError(f"control.{field} has shape {jnp.shape(value)}, expected ({model.num_dofs},)")


def check_rollout_controls(model: Model, controls: Control | None, num_steps: int | None) -> int:
    """The number of steps of a rollout, after checking that the controls share one leading time axis."""
    if controls is None:
        if num_steps is None:
            raise ValueError("rollout: give controls with a leading time axis, or num_steps")
        return int(num_steps)
    check_control(model, controls)
    lengths = {x.shape[0] for x in jax.tree_util.tree_leaves(controls)}
    if len(lengths) != 1:
        raise ValueError(f"rollout: controls must share one leading time axis, got lengths {lengths}")
    n = lengths.pop()
    if num_steps is not None and num_steps != n:
        raise ValueError(f"rollout: num_steps={num_steps} but controls hold {n} steps")
    return int(n)
