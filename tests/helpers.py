"""Small utilities shared by the tests."""

from __future__ import annotations

import jax
import numpy as np

import kamino


def trajectory_metrics(model: kamino.Model, state: kamino.State, traj: kamino.State) -> dict[str, np.ndarray]:
    """``kamino.metrics`` on every state of a rollout trajectory: arrays ``[T, num_worlds]``."""
    out = jax.vmap(lambda q, u: kamino.metrics(model, state.replace(body_q=q, body_u=u)))(traj.body_q, traj.body_u)
    return {k: np.asarray(v) for k, v in out.items()}


def trajectory_joint_positions(model: kamino.Model, state: kamino.State, traj: kamino.State) -> np.ndarray:
    """``kamino.joint_positions`` on every state of a trajectory: ``[T, num_coords]``."""
    return np.asarray(jax.vmap(lambda q: kamino.joint_positions(model, state.replace(body_q=q)))(traj.body_q))
