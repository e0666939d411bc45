"""Host-side index tables derived from a :class:`~kamino.model.Model`, shared by both backends.

Both backends order a world's constraint rows the same way (docs/conventions.md, docs/formulation.md
§7.1): joint-dynamics rows (actuator rows, then passive rows), kinematic joint rows, coupling rows,
limit rows, contact triples. This module computes, once and in numpy, which DoF or joint each row
family refers to (global, flat indices) and how many rows of each family a world has. The JAX
reference pads these per world; the Warp backend uses them flat.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from kamino.config import HEALTH_SPEED, HEALTH_TURN
from kamino.model import (
    JOINT_CONSTRAINT_ROWS,
    JOINT_DOF_ROWS,
    ActuationMode,
    JointType,
    Model,
    derived,
    freeze_arrays,
)

DYN_ACTUATOR, DYN_PASSIVE = 0, 1


@dataclasses.dataclass(frozen=True)
class RowTables:
    """Flat per-row / per-DoF tables (global joint and DoF indices)."""

    cts_joint: np.ndarray  # [num_constraints] joint of each kinematic row
    cts_axis: np.ndarray  # [num_constraints] 0..5
    cts_kind: np.ndarray  # [num_constraints] kamino.model.RES_*
    dof_joint: np.ndarray  # [num_dofs] joint of each DoF
    dof_axis: np.ndarray  # [num_dofs]
    dof_kind: np.ndarray  # [num_dofs] kamino.model.DOF_*
    dyn_dof: np.ndarray  # [num_dyn] DoF of each joint-dynamics row, per world: actuator rows then passive rows
    dyn_kind: np.ndarray  # [num_dyn] DYN_ACTUATOR / DYN_PASSIVE
    world_dyn_count: np.ndarray  # [W]
    lim_dof: np.ndarray  # [num_lim] each DoF with a finite limit, per world in DoF order
    world_lim_count: np.ndarray  # [W]
    cpl_dof_a: np.ndarray  # [K] first DoF of joint a
    cpl_dof_b: np.ndarray  # [K] first DoF of joint b (-1: none)
    cpl_wrap: np.ndarray  # [K] bool: joint a is a hinge (residual wrapped to [-pi, pi])
    pair_kinds: tuple[tuple[int, int], ...]  # geom type combinations present, sorted
    pair_order: np.ndarray  # [P] the pairs grouped by kind (kind-major, then pair order): detection order
    pair_kind: np.ndarray  # [P] index into pair_kinds of each pair


def prefix(counts: np.ndarray) -> np.ndarray:
    """Exclusive prefix sum (the start of each segment)."""
    counts = np.asarray(counts, dtype=np.int64)
    return np.cumsum(counts) - counts


def row_tables(model: Model) -> RowTables:
    """The tables of ``model``, computed in numpy; a frozen model's once, kept on the model
    (:func:`kamino.model.derived`), their arrays read-only."""
    return derived(model, "row_tables", lambda: freeze_arrays(_row_tables(model)))


def _pair_kinds(model: Model) -> tuple[tuple[tuple[int, int], ...], np.ndarray]:
    """The geom type combinations of the candidate pairs, sorted, and the index of each pair's among them."""
    if not model.num_pairs:
        return (), np.zeros(0, np.int64)
    types = np.stack([model.geom_type[model.pair_geom_a], model.geom_type[model.pair_geom_b]], axis=1)
    kinds, pair_kind = np.unique(types, axis=0, return_inverse=True)
    return tuple((int(a), int(b)) for a, b in kinds), np.asarray(pair_kind, np.int64).reshape(-1)


def _row_tables(model: Model) -> RowTables:
    """The tables of ``model`` (uncached: :func:`row_tables`)."""
    W = model.num_worlds
    n_rows, n_dofs = model.num_constraints, model.num_dofs
    cts_joint, cts_axis, cts_kind = (np.zeros(n_rows, np.int64) for _ in range(3))
    dof_joint, dof_axis, dof_kind = (np.zeros(n_dofs, np.int64) for _ in range(3))
    for jt in JointType:
        sel = np.nonzero(model.joint_type == int(jt))[0]
        for k, (axis, kind) in enumerate(JOINT_CONSTRAINT_ROWS[jt]):
            rows = model.joint_cts_start[sel] + k
            cts_joint[rows], cts_axis[rows], cts_kind[rows] = sel, axis, kind
        for k, (axis, kind) in enumerate(JOINT_DOF_ROWS[jt]):
            dofs = model.joint_dof_start[sel] + k
            dof_joint[dofs], dof_axis[dofs], dof_kind[dofs] = sel, axis, kind

    # joint-dynamics rows: an actuator row per PD/velocity DoF, a passive row per DoF with armature,
    # damping or a spring (docs/formulation.md §3.2); per world actuator rows first, each family in DoF order
    dof_world = np.repeat(np.arange(W), model.world_dof_count)
    dof_ids = np.arange(n_dofs)
    is_pd = np.isin(model.dof_act_mode, (int(ActuationMode.POSITION), int(ActuationMode.VELOCITY)))
    is_passive = (model.dof_armature > 0) | (model.dof_damping > 0) | (model.dof_stiffness > 0)
    dyn_world = np.concatenate([dof_world[is_pd], dof_world[is_passive]])
    dyn_dof = np.concatenate([dof_ids[is_pd], dof_ids[is_passive]])
    dyn_kind = np.concatenate([np.full(int(is_pd.sum()), DYN_ACTUATOR), np.full(int(is_passive.sum()), DYN_PASSIVE)])
    order = np.lexsort((dyn_dof, dyn_kind, dyn_world))
    limited = np.isfinite(model.dof_lower) | np.isfinite(model.dof_upper)

    ja, jb = model.coupling_joint_a, model.coupling_joint_b
    cpl_a = model.joint_dof_start[ja] if model.num_couplings else np.zeros(0, np.int64)
    cpl_b = (np.where(jb >= 0, model.joint_dof_start[np.maximum(jb, 0)], -1) if model.num_couplings
             else np.zeros(0, np.int64))
    cpl_wrap = model.joint_type[ja] == int(JointType.REVOLUTE) if model.num_couplings else np.zeros(0, bool)

    kinds, pair_kind = _pair_kinds(model)
    pair_order = np.lexsort((np.arange(model.num_pairs), pair_kind, model.pair_world)) if model.num_pairs else (
        np.zeros(0, np.int64))
    return RowTables(
        cts_joint=cts_joint, cts_axis=cts_axis, cts_kind=cts_kind,
        dof_joint=dof_joint, dof_axis=dof_axis, dof_kind=dof_kind,
        dyn_dof=dyn_dof[order], dyn_kind=dyn_kind[order], world_dyn_count=np.bincount(dyn_world, minlength=W),
        lim_dof=dof_ids[limited], world_lim_count=np.bincount(dof_world[limited], minlength=W),
        cpl_dof_a=np.asarray(cpl_a, np.int64), cpl_dof_b=np.asarray(cpl_b, np.int64),
        cpl_wrap=np.asarray(cpl_wrap, bool),
        pair_kinds=kinds, pair_order=pair_order, pair_kind=pair_kind,
    )


def world_reach(model: Model) -> np.ndarray:
    """``[W]`` each world's sum of joint lever arms [m]: over its joints, the distance from the base body's CoM to the
    joint anchor (none for a joint on the world, whose anchor is a placement) plus the distance from the follower's
    CoM to it. No point of the world's articulation is farther than this from a joint anchor. The world-health speed
    bound scales with it (:func:`health_speed_bound`; both backends read this sum: the JAX reference as
    ``PaddedModel.reach``)."""
    arm = np.linalg.norm(model.joint_anchor_F, axis=-1) + np.where(
        model.joint_parent >= 0, np.linalg.norm(model.joint_anchor_B, axis=-1), 0.0)
    return np.bincount(model.joint_world, weights=arm, minlength=model.num_worlds)


def health_speed_bound(reach, dt: float):
    """The linear speed [m/s] past which a body fails its world's health check in a step of ``dt``:
    ``max(HEALTH_SPEED, HEALTH_TURN * reach / dt)`` (``kamino.config``), with ``reach`` from :func:`world_reach`.
    Takes and returns NumPy or JAX arrays (the Warp backend's ``speed_check`` reads it from NumPy, the JAX
    reference's ``too_fast`` from ``PaddedModel.reach``)."""
    return (HEALTH_TURN / dt * reach).clip(min=HEALTH_SPEED)
