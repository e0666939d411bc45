"""Padded per-world layout of a :class:`kamino.Model` for the JAX reference.

The model's storage is flat over worlds (sum-sized). The oracle pads every world to the
maximum count and ``vmap``s over worlds; padded bodies/rows are masked out and never touch
the real ones, so a world's result does not depend on its neighbours (docs/conventions.md).
This module also holds the gather tables between the flat and padded layouts.
"""

from __future__ import annotations

import dataclasses
import weakref

import jax
import jax.numpy as jnp
import numpy as np

from kamino.model import JOINT_CONSTRAINT_ROWS, JOINT_DOF_ROWS, JointType, Model


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class PaddedModel:
    """Per-world padded arrays (leading axis: world). Local indices; ``-1`` parent is the world."""

    body_mask: jax.Array  # [W, nb]
    mass: jax.Array  # [W, nb] (1 on padding)
    inertia: jax.Array  # [W, nb, 3, 3] body-frame inertia about the CoM (identity on padding)
    gravity: jax.Array  # [W, 3]
    joint_parent: jax.Array  # [W, nj]
    joint_child: jax.Array  # [W, nj]
    joint_type: jax.Array  # [W, nj]
    anchor_B: jax.Array  # [W, nj, 3]
    anchor_F: jax.Array  # [W, nj, 3]
    frame_B: jax.Array  # [W, nj, 4]
    frame_F: jax.Array  # [W, nj, 4]
    row_joint: jax.Array  # [W, nr] local joint of each kinematic constraint row
    row_axis: jax.Array  # [W, nr] 0..5
    row_kind: jax.Array  # [W, nr] residual kind (kamino.model.RES_*)
    row_mask: jax.Array  # [W, nr]
    dof_joint: jax.Array  # [W, nd]
    dof_axis: jax.Array  # [W, nd]
    dof_kind: jax.Array  # [W, nd] (kamino.model.DOF_*)
    dof_mask: jax.Array  # [W, nd]


@dataclasses.dataclass(frozen=True, eq=False)
class Layout:
    """A padded model plus the host-side gather tables between flat and padded storage."""

    padded: PaddedModel
    num_worlds: int
    max_bodies: int
    max_joints: int
    max_rows: int
    max_dofs: int
    body_gather: np.ndarray  # [W, nb] flat index of each padded body (0 on padding)
    body_scatter: np.ndarray  # [B] position of each flat body in the [W*nb] padded array
    row_gather: np.ndarray  # [W, nr]
    row_scatter: np.ndarray  # [C]
    dof_gather: np.ndarray  # [W, nd]
    dof_scatter: np.ndarray  # [D]
    dtype: np.dtype
    tables: dict  # the gather/scatter tables above as device arrays (jit arguments)


def _pad_index(starts: np.ndarray, counts: np.ndarray, width: int):
    """Gather table [W, width] (0 where padded), mask, and the scatter positions of flat entries."""
    W = len(starts)
    local = np.arange(max(width, 0))[None, :]
    mask = local < counts[:, None]
    gather = np.where(mask, starts[:, None] + local, 0).astype(np.int64)
    scatter = (np.repeat(np.arange(W) * width, counts) + _local_ranks(counts)).astype(np.int64)
    return gather, mask, scatter


def _local_ranks(counts: np.ndarray) -> np.ndarray:
    total = int(counts.sum())
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    return np.arange(total) - np.repeat(starts, counts)


_CACHE: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def layout_of(model: Model, dtype=None) -> Layout:
    """The (cached) padded layout of ``model`` in ``dtype`` (default: JAX's float dtype)."""
    dtype = np.dtype(dtype if dtype is not None else jnp.zeros(0).dtype)
    per_model = _CACHE.setdefault(model, {})
    if dtype not in per_model:
        per_model[dtype] = _build_layout(model, dtype)
    return per_model[dtype]


def _build_layout(model: Model, dtype: np.dtype) -> Layout:
    W = model.num_worlds
    nb = int(model.world_body_count.max())
    nj = int(model.world_joint_count.max()) if model.num_joints else 0
    nr = int(model.world_cts_count.max()) if model.num_joints else 0
    nd = int(model.world_dof_count.max()) if model.num_joints else 0

    bg, bmask, bsc = _pad_index(model.world_body_start, model.world_body_count, nb)
    jg, jmask, _ = _pad_index(model.world_joint_start, model.world_joint_count, nj)
    rg, rmask, rsc = _pad_index(model.world_cts_start, model.world_cts_count, nr)
    dg, dmask, dsc = _pad_index(model.world_dof_start, model.world_dof_count, nd)

    body_start_of_joint = model.world_body_start[model.joint_world] if model.num_joints else np.zeros(0, int)
    parent_local = np.where(model.joint_parent >= 0, model.joint_parent - body_start_of_joint, -1)
    child_local = model.joint_child - body_start_of_joint

    # per flat row / dof: owning joint (world-local), axis, kind
    n_rows, n_dofs = model.num_constraints, model.num_dofs
    row_joint, row_axis, row_kind = (np.zeros(n_rows, np.int64) for _ in range(3))
    dof_joint, dof_axis, dof_kind = (np.zeros(n_dofs, np.int64) for _ in range(3))
    joint_local = np.arange(model.num_joints) - (
        model.world_joint_start[model.joint_world] if model.num_joints else 0
    )
    for jt in JointType:
        sel = np.nonzero(model.joint_type == int(jt))[0]
        for k, (axis, kind) in enumerate(JOINT_CONSTRAINT_ROWS[jt]):
            rows = model.joint_cts_start[sel] + k
            row_joint[rows], row_axis[rows], row_kind[rows] = joint_local[sel], axis, kind
        for k, (axis, kind) in enumerate(JOINT_DOF_ROWS[jt]):
            dofs = model.joint_dof_start[sel] + k
            dof_joint[dofs], dof_axis[dofs], dof_kind[dofs] = joint_local[sel], axis, kind

    def take(arr, gather, mask, fill):
        out = arr[gather] if arr.size else np.zeros(gather.shape + arr.shape[1:], arr.dtype)
        m = mask.reshape(mask.shape + (1,) * (out.ndim - mask.ndim))
        return np.where(m, out, fill)

    eye = np.eye(3)
    f = lambda a: jnp.asarray(a, dtype=dtype)  # noqa: E731
    i = lambda a: jnp.asarray(a, dtype=jnp.int32)  # noqa: E731
    padded = PaddedModel(
        body_mask=jnp.asarray(bmask),
        mass=f(take(model.body_mass, bg, bmask, 1.0)),
        inertia=f(take(model.body_inertia, bg, bmask, eye)),
        gravity=f(model.gravity),
        joint_parent=i(take(parent_local, jg, jmask, -1)),
        joint_child=i(take(child_local, jg, jmask, 0)),
        joint_type=i(take(model.joint_type, jg, jmask, 0)),
        anchor_B=f(take(model.joint_anchor_B, jg, jmask, 0.0)),
        anchor_F=f(take(model.joint_anchor_F, jg, jmask, 0.0)),
        frame_B=f(take(model.joint_frame_B, jg, jmask, np.array([0, 0, 0, 1.0]))),
        frame_F=f(take(model.joint_frame_F, jg, jmask, np.array([0, 0, 0, 1.0]))),
        row_joint=i(take(row_joint, rg, rmask, 0)),
        row_axis=i(take(row_axis, rg, rmask, 0)),
        row_kind=i(take(row_kind, rg, rmask, 0)),
        row_mask=jnp.asarray(rmask),
        dof_joint=i(take(dof_joint, dg, dmask, 0)),
        dof_axis=i(take(dof_axis, dg, dmask, 0)),
        dof_kind=i(take(dof_kind, dg, dmask, 0)),
        dof_mask=jnp.asarray(dmask),
    )
    return Layout(
        padded=padded, num_worlds=W, max_bodies=nb, max_joints=nj, max_rows=nr, max_dofs=nd,
        body_gather=bg, body_scatter=bsc, row_gather=rg, row_scatter=rsc, dof_gather=dg, dof_scatter=dsc,
        dtype=dtype,
        tables={"bg": jnp.asarray(bg), "bs": jnp.asarray(bsc), "rg": jnp.asarray(rg), "rs": jnp.asarray(rsc),
                "dg": jnp.asarray(dg)},
    )


def to_padded(flat: jax.Array, gather: np.ndarray, mask: jax.Array | np.ndarray, fill=0.0) -> jax.Array:
    """Flat ``[N, ...]`` -> padded ``[W, width, ...]`` (``fill`` on padding)."""
    if flat.shape[0] == 0:
        return jnp.full(gather.shape + flat.shape[1:], fill, flat.dtype)
    out = flat[gather]
    m = jnp.asarray(mask).reshape(mask.shape + (1,) * (out.ndim - mask.ndim))
    return jnp.where(m, out, jnp.asarray(fill, flat.dtype))


def to_flat(padded: jax.Array, scatter: np.ndarray) -> jax.Array:
    """Padded ``[W, width, ...]`` -> flat ``[N, ...]``."""
    W, width = padded.shape[:2]
    return padded.reshape((W * width, *padded.shape[2:]))[scatter]
