"""The JAX reference's types: the padded per-world layout of a :class:`kamino.Model` (``PaddedModel``, ``Layout``).

The model's storage is flat over worlds (sum-sized). The oracle pads every world to the
maximum count and ``vmap``s over worlds; padded bodies/rows are masked out and never touch
the real ones, so a world's result does not depend on its neighbours (docs/conventions.md).
This module also holds the gather tables between the flat and padded layouts.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from kamino.model import Model, derived
from kamino.tables import DYN_ACTUATOR, DYN_PASSIVE, row_tables, world_reach

__all__ = ["DYN_ACTUATOR", "DYN_PASSIVE", "Layout", "PaddedModel", "WorldCache", "layout_of", "to_flat",
           "to_padded"]


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class PairGroup:
    """The candidate contact pairs of one geom-type combination, per world (``[W, n]``, local geoms)."""

    geom_a: jax.Array
    geom_b: jax.Array
    pair: jax.Array  # world-local pair index (the warm-start key)
    mask: jax.Array


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class PaddedModel:
    """Per-world padded arrays (leading axis: world). Local indices; ``-1`` parent is the world."""

    body_mask: jax.Array  # [W, nb]
    mass: jax.Array  # [W, nb] (1 on padding)
    inertia: jax.Array  # [W, nb, 3, 3] body-frame inertia about the CoM (identity on padding)
    gravity: jax.Array  # [W, 3]
    reach: jax.Array  # [W] sum of joint lever arms [m] (kamino.tables.world_reach; the health speed bound)
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
    dof_act_mode: jax.Array  # [W, nd] kamino.ActuationMode
    dof_kp: jax.Array
    dof_kd: jax.Array
    dof_effort_limit: jax.Array
    dof_armature: jax.Array
    dof_damping: jax.Array
    dof_stiffness: jax.Array
    dof_springref: jax.Array
    dof_lower: jax.Array
    dof_upper: jax.Array
    # joint-dynamics rows (docs/formulation.md §3.2): one per DoF and kind (actuator / passive)
    dyn_dof: jax.Array  # [W, ndyn] local DoF
    dyn_kind: jax.Array  # [W, ndyn] DYN_ACTUATOR or DYN_PASSIVE
    dyn_mask: jax.Array
    # coupling rows: q_a = sum_k coef_k q_b^k (docs/conventions.md "Couplings"); local DoF indices
    cpl_dof_a: jax.Array  # [W, nk]
    cpl_dof_b: jax.Array  # [W, nk] (0 where there is no joint b)
    cpl_has_b: jax.Array  # [W, nk] bool
    cpl_wrap: jax.Array  # [W, nk] bool: joint a is an angle (residual wrapped to [-pi, pi])
    cpl_coef: jax.Array  # [W, nk, 5]
    cpl_mask: jax.Array  # [W, nk]
    # limit rows (§4.1): one per DoF with a finite limit
    lim_dof: jax.Array  # [W, nl]
    lim_mask: jax.Array
    # geoms (local body index, -1 the world) and candidate pairs grouped by type combination
    geom_type: jax.Array  # [W, ng]
    geom_body: jax.Array
    geom_pos: jax.Array
    geom_quat: jax.Array
    geom_size: jax.Array
    geom_friction: jax.Array
    geom_restitution: jax.Array
    geom_margin: jax.Array
    # heightfields (world-local indices; kamino.Model.hfield_*)
    geom_dataid: jax.Array  # [W, ng] local heightfield of an HFIELD geom (-1: none)
    hfield_nrow: jax.Array  # [W, nh]
    hfield_ncol: jax.Array  # [W, nh]
    hfield_size: jax.Array  # [W, nh, 4] (rx, ry, z_top, z_base)
    hfield_adr: jax.Array  # [W, nh] index of the grid's first height in hfield_data
    hfield_data: jax.Array  # [W, nhd] the world's normalised heights (0 on padding)
    pair_groups: tuple[PairGroup, ...]
    contact_capacity: jax.Array  # [W]
    pair_kinds: tuple[tuple[int, int], ...] = dataclasses.field(metadata={"static": True}, default=())
    max_contacts: int = dataclasses.field(metadata={"static": True}, default=0)


@dataclasses.dataclass(frozen=True, eq=False)
class Layout:
    """A padded model plus the host-side gather tables between flat and padded storage."""

    padded: PaddedModel
    num_worlds: int
    max_bodies: int
    max_joints: int
    max_rows: int
    max_dofs: int
    max_couplings: int
    body_gather: np.ndarray  # [W, nb] flat index of each padded body (0 on padding)
    body_scatter: np.ndarray  # [B] position of each flat body in the [W*nb] padded array
    row_gather: np.ndarray  # [W, nr]
    row_scatter: np.ndarray  # [C]
    dof_gather: np.ndarray  # [W, nd]
    dof_scatter: np.ndarray  # [D]
    coupling_gather: np.ndarray  # [W, nk]
    coupling_scatter: np.ndarray  # [K]
    max_contacts: int
    contact_gather: np.ndarray  # [W, C]
    contact_scatter: np.ndarray  # [total capacity]
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


def _prefix(counts: np.ndarray) -> np.ndarray:
    counts = np.asarray(counts, dtype=np.int64)
    return np.cumsum(counts) - counts


def _local_ranks(counts: np.ndarray) -> np.ndarray:
    total = int(counts.sum())
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    return np.arange(total) - np.repeat(starts, counts)


def layout_of(model: Model, dtype=None) -> Layout:
    """The padded layout of ``model`` in ``dtype`` (default: JAX's float dtype), built once per dtype and kept on the
    model (:func:`kamino.model.derived`).

    Built under ``jax.ensure_compile_time_eval()``: when the first call comes from inside a trace
    (``jax.jit`` of ``kamino.metrics``, say), ``jnp.asarray`` would otherwise return tracers of that
    trace, and the kept layout would hand them to every later call (``UnexpectedTracerError``). Its arrays are
    therefore always concrete device arrays, whatever traces the caller is in (tests/test_layout_cache.py).
    """
    dtype = np.dtype(dtype if dtype is not None else jnp.zeros(0).dtype)
    return derived(model, ("layout", dtype), lambda: build_layout(model, dtype))


def build_layout(model: Model, dtype: np.dtype) -> Layout:
    """:func:`layout_of` built anew (concrete arrays, whatever trace the caller is in)."""
    with jax.ensure_compile_time_eval():
        return _build_layout(model, np.dtype(dtype))


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

    tab = row_tables(model)
    joint_local = np.arange(model.num_joints) - (
        model.world_joint_start[model.joint_world] if model.num_joints else 0
    )
    row_joint, row_axis, row_kind = joint_local[tab.cts_joint], tab.cts_axis, tab.cts_kind
    dof_joint, dof_axis, dof_kind = joint_local[tab.dof_joint], tab.dof_axis, tab.dof_kind

    def take(arr, gather, mask, fill):
        out = arr[gather] if arr.size else np.zeros(gather.shape + arr.shape[1:], arr.dtype)
        m = mask.reshape(mask.shape + (1,) * (out.ndim - mask.ndim))
        return np.where(m, out, fill)

    # joint-dynamics, limit and coupling rows (kamino/tables.py), world-local DoF indices
    dof_local = _local_ranks(model.world_dof_count)
    dyn_count, lim_count = tab.world_dyn_count, tab.world_lim_count
    ndyn = int(dyn_count.max()) if dyn_count.size else 0
    yg, ymask, _ = _pad_index(_prefix(dyn_count), dyn_count, ndyn)
    nl = int(lim_count.max()) if lim_count.size else 0
    lg, lmask, _ = _pad_index(_prefix(lim_count), lim_count, nl)
    nk = int(model.world_coupling_count.max()) if model.num_couplings else 0
    ug, umask, usc = _pad_index(model.world_coupling_start, model.world_coupling_count, nk)
    has_b = tab.cpl_dof_b >= 0
    cpl_a = dof_local[tab.cpl_dof_a] if model.num_couplings else np.zeros(0, np.int64)
    cpl_b = np.where(has_b, dof_local[np.maximum(tab.cpl_dof_b, 0)], 0) if model.num_couplings else cpl_a
    cpl_wrap = tab.cpl_wrap

    # geoms and candidate pairs, grouped by type combination (static per model)
    ng = int(model.world_geom_count.max()) if model.num_geoms else 0
    gg, gmask, _ = _pad_index(model.world_geom_start, model.world_geom_count, ng)
    geom_body_local = np.where(model.geom_body >= 0, model.geom_body - model.world_body_start[model.geom_world], -1)
    pair_local = _local_ranks(model.world_pair_count)
    kinds = sorted({(int(model.geom_type[a]), int(model.geom_type[b]))
                    for a, b in zip(model.pair_geom_a, model.pair_geom_b, strict=True)})
    geom_local = np.arange(model.num_geoms) - model.world_geom_start[model.geom_world] if model.num_geoms else None
    groups = []
    for ta, tb in kinds:
        sel = np.nonzero((model.geom_type[model.pair_geom_a] == ta) & (model.geom_type[model.pair_geom_b] == tb))[0]
        cnt = np.bincount(model.pair_world[sel], minlength=W)
        kg, kmask, _ = _pad_index(_prefix(cnt), cnt, int(cnt.max()))
        groups.append(PairGroup(
            geom_a=jnp.asarray(np.where(kmask, geom_local[model.pair_geom_a[sel]][kg], 0), jnp.int32),
            geom_b=jnp.asarray(np.where(kmask, geom_local[model.pair_geom_b[sel]][kg], 0), jnp.int32),
            pair=jnp.asarray(np.where(kmask, pair_local[sel][kg], -1), jnp.int32),
            mask=jnp.asarray(kmask),
        ))
    nh = int(model.world_hfield_count.max()) if model.num_hfields else 0
    hg, hmask, _ = _pad_index(model.world_hfield_start, model.world_hfield_count, nh)
    nhd = int(model.world_hfield_data_count.max()) if model.num_hfields else 0
    hdg, hdmask, _ = _pad_index(model.world_hfield_data_start, model.world_hfield_data_count, nhd)
    dataid_local = np.where(model.geom_dataid >= 0, model.geom_dataid - model.world_hfield_start[model.geom_world],
                            -1)
    adr_local = model.hfield_adr - model.world_hfield_data_start[model.hfield_world]
    nc = int(model.world_contact_capacity.max()) if W else 0
    cg, cmask, csc = _pad_index(_prefix(model.world_contact_capacity), model.world_contact_capacity, nc)

    eye = np.eye(3)
    f = lambda a: jnp.asarray(a, dtype=dtype)  # noqa: E731
    i = lambda a: jnp.asarray(a, dtype=jnp.int32)  # noqa: E731
    dof_arr = lambda a, fill=0.0: take(a, dg, dmask, fill)  # noqa: E731
    geom_arr = lambda a, fill=0.0: take(a, gg, gmask, fill)  # noqa: E731
    padded = PaddedModel(
        body_mask=jnp.asarray(bmask),
        mass=f(take(model.body_mass, bg, bmask, 1.0)),
        inertia=f(take(model.body_inertia, bg, bmask, eye)),
        gravity=f(model.gravity),
        reach=f(world_reach(model)),
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
        dof_act_mode=i(dof_arr(model.dof_act_mode, 0)),
        dof_kp=f(dof_arr(model.dof_kp)),
        dof_kd=f(dof_arr(model.dof_kd)),
        dof_effort_limit=f(dof_arr(model.dof_effort_limit, np.inf)),
        dof_armature=f(dof_arr(model.dof_armature)),
        dof_damping=f(dof_arr(model.dof_damping)),
        dof_stiffness=f(dof_arr(model.dof_stiffness)),
        dof_springref=f(dof_arr(model.dof_springref)),
        dof_lower=f(dof_arr(model.dof_lower, -np.inf)),
        dof_upper=f(dof_arr(model.dof_upper, np.inf)),
        dyn_dof=i(take(dof_local[tab.dyn_dof] if tab.dyn_dof.size else tab.dyn_dof, yg, ymask, 0)),
        dyn_kind=i(take(tab.dyn_kind, yg, ymask, 0)),
        dyn_mask=jnp.asarray(ymask),
        cpl_dof_a=i(take(cpl_a, ug, umask, 0)),
        cpl_dof_b=i(take(cpl_b, ug, umask, 0)),
        cpl_has_b=jnp.asarray(take(has_b, ug, umask, False)),
        cpl_wrap=jnp.asarray(take(cpl_wrap, ug, umask, False)),
        cpl_coef=f(take(model.coupling_coef, ug, umask, 0.0)),
        cpl_mask=jnp.asarray(umask),
        lim_dof=i(take(dof_local[tab.lim_dof] if tab.lim_dof.size else tab.lim_dof, lg, lmask, 0)),
        lim_mask=jnp.asarray(lmask),
        geom_type=i(geom_arr(model.geom_type, 0)),
        geom_body=i(geom_arr(geom_body_local, -1)),
        geom_pos=f(geom_arr(model.geom_pos)),
        geom_quat=f(geom_arr(model.geom_quat, np.array([0, 0, 0, 1.0]))),
        geom_size=f(geom_arr(model.geom_size)),
        geom_friction=f(geom_arr(model.geom_friction)),
        geom_restitution=f(geom_arr(model.geom_restitution)),
        geom_margin=f(geom_arr(model.geom_margin)),
        geom_dataid=i(geom_arr(dataid_local, -1)),
        hfield_nrow=i(take(model.hfield_nrow, hg, hmask, 2)),
        hfield_ncol=i(take(model.hfield_ncol, hg, hmask, 2)),
        hfield_size=f(take(model.hfield_size, hg, hmask, 1.0)),
        hfield_adr=i(take(adr_local, hg, hmask, 0)),
        hfield_data=f(take(model.hfield_data, hdg, hdmask, 0.0)),
        pair_groups=tuple(groups),
        contact_capacity=i(model.world_contact_capacity),
        pair_kinds=tuple(kinds),
        max_contacts=nc,
    )
    return Layout(
        padded=padded, num_worlds=W, max_bodies=nb, max_joints=nj, max_rows=nr, max_dofs=nd, max_couplings=nk,
        body_gather=bg, body_scatter=bsc, row_gather=rg, row_scatter=rsc, dof_gather=dg, dof_scatter=dsc,
        coupling_gather=ug, coupling_scatter=usc,
        max_contacts=nc, contact_gather=cg, contact_scatter=csc,
        dtype=dtype,
        tables={"bg": jnp.asarray(bg), "bs": jnp.asarray(bsc), "rg": jnp.asarray(rg), "rs": jnp.asarray(rsc),
                "dg": jnp.asarray(dg), "ds": jnp.asarray(dsc), "ug": jnp.asarray(ug), "us": jnp.asarray(usc),
                "cg": jnp.asarray(cg), "cs": jnp.asarray(csc),
                "cm": jnp.asarray(cmask)},
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


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class WorldCache:
    """What a world carries from one step to the next: the reactions (warm start) and contacts.

    Forces are ``lambda / dt``: ``kin`` per kinematic row, ``actuator``/``passive``/``limit`` per DoF
    (generalized forces), contacts in world frame on geom b's body.
    """

    kin: jax.Array  # [nr]
    coupling: jax.Array  # [nk]
    actuator: jax.Array  # [nd]
    passive: jax.Array  # [nd]
    limit: jax.Array  # [nd] signed generalized force
    contact_pair: jax.Array  # [C]
    contact_pos: jax.Array  # [C, 3]
    contact_normal: jax.Array  # [C, 3]
    contact_dist: jax.Array  # [C]
    contact_force: jax.Array  # [C, 3]
    contact_velocity: jax.Array  # [C, 3]
    contact_point_b: jax.Array  # [C, 3]
    penalty: jax.Array  # [] the last solve's penalty on bounded rows (0: none yet; the next solve starts there)
