"""A :class:`kamino.Model` uploaded to Warp arrays: flat over worlds, per-world starts and counts.

Storage is sized by the **sum** of the per-world counts; kernels launch on ``(num_worlds,
max_count)`` grids and threads past their world's count return at once (docs/architecture.md, "Data
layout"). Entity indices are global (flat). Each world owns a segment of constraint rows of length
``maxdim_w = n_dyn + n_joint + n_coupling + n_limit + 3 capacity`` (docs/formulation.md §10.1); the
first ``n_fixed = n_dyn + n_joint + n_coupling`` rows are always active, the active limit and
contact rows follow, compacted, so a step only works on the rows it uses. Row data, the dense
Delassus matrix and the dense Jacobian are interleaved over groups of 32 worlds
(``kamino/warp_backend/indexing.py``).

Heightfield heights are the exception to per-world storage: ``hfield_data`` holds each distinct grid once
(:func:`hfield_grids`), and every world's heightfields (``hfield_nrow``, ``hfield_ncol``, ``hfield_size``, per
heightfield) point into it through ``hfield_adr``, so the worlds of ``kamino.replicate`` share one copy of their
terrain.
"""

import dataclasses
import functools

import numpy as np
import warp as wp

from kamino.model import CONTACT_POINTS, GeomType, Model, derived
from kamino.tables import prefix, row_tables
from kamino.warp_backend import linear_solve_pattern
from kamino.warp_backend.linear_solve_pattern import hub_counts
from kamino.warp_backend.types import types_of

GROUP = 32  # worlds per interleaved storage group (kamino/warp_backend/indexing.py)


def group_sizes(per_world: np.ndarray) -> np.ndarray:
    """``max`` of ``per_world`` over each group of :data:`GROUP` consecutive worlds."""
    W = len(per_world)
    padded = np.zeros(((W + GROUP - 1) // GROUP) * GROUP, np.int64)
    padded[:W] = per_world
    return padded.reshape(-1, GROUP).max(axis=1)


@functools.cache
def model_struct(np_dtype):
    """The Warp struct type holding a model's arrays in one precision."""
    T = types_of(np_dtype)
    scalar, vec3, vec4, quat, mat33 = T.scalar, T.vec3, T.vec4, T.quat, T.mat33
    iarr = wp.array(dtype=wp.int32)
    farr = wp.array(dtype=scalar)

    @wp.struct
    class ModelArrays:
        # per world
        body_start: iarr
        body_count: iarr
        joint_start: iarr
        joint_count: iarr
        dof_start: iarr
        dof_count: iarr
        cts_start: iarr
        cts_count: iarr
        dyn_start: iarr
        dyn_count: iarr
        cpl_start: iarr
        cpl_count: iarr
        lim_start: iarr
        lim_count: iarr
        pair_start: iarr  # into the detection-ordered pair list
        pair_count: iarr
        cand_start: iarr  # candidate contact points
        cand_count: iarr
        con_start: iarr  # contact slots (capacity)
        con_capacity: iarr
        row_fixed: iarr  # n_dyn + n_joint + n_coupling
        row_maxdim: iarr
        # per group of 32 worlds (kamino/warp_backend/indexing.py): interleaved row, Delassus, dense-J storage
        grp_row_start: iarr
        grp_maxdim: iarr
        grp_mat_start: iarr
        grp_jd_start: iarr
        grp_ncol: iarr  # 6 x the group's largest body count
        gravity: wp.array(dtype=vec3)
        # bodies
        mass: farr
        inv_mass: farr
        inertia: wp.array(dtype=mat33)  # body frame, about the CoM
        inv_inertia: wp.array(dtype=mat33)
        body_world: iarr
        # joints
        joint_type: iarr
        joint_parent: iarr  # -1: the world
        joint_child: iarr
        anchor_B: wp.array(dtype=vec3)
        anchor_F: wp.array(dtype=vec3)
        frame_B: wp.array(dtype=quat)
        frame_F: wp.array(dtype=quat)
        # kinematic rows and DoFs
        cts_joint: iarr
        cts_axis: iarr
        cts_kind: iarr
        dof_joint: iarr
        dof_axis: iarr
        dof_kind: iarr
        act_mode: iarr
        kp: farr
        kd: farr
        effort_limit: farr
        armature: farr
        damping: farr
        stiffness: farr
        springref: farr
        lower: farr
        upper: farr
        # joint-dynamics, coupling and limit rows
        dyn_dof: iarr
        dyn_kind: iarr
        cpl_dof_a: iarr
        cpl_dof_b: iarr  # -1: no joint b
        cpl_wrap: iarr
        cpl_coef: wp.array2d(dtype=scalar)
        lim_dof: iarr
        # geoms and candidate pairs (detection order: kind-major, then pair order)
        geom_type: iarr
        geom_body: iarr  # -1: the world
        geom_pos: wp.array(dtype=vec3)
        geom_quat: wp.array(dtype=quat)
        geom_size: wp.array(dtype=vec3)
        geom_friction: farr
        geom_restitution: farr
        geom_margin: farr
        geom_radius: farr  # bounding distance from the body's CoM (planes: offset only)
        pair_geom_a: iarr
        pair_geom_b: iarr
        pair_key: iarr  # world-local pair index (the warm-start key)
        pair_cand: iarr  # first candidate slot
        pair_points: iarr
        # heightfields (GeomType.HFIELD): per heightfield over all worlds, the heights once per distinct grid
        geom_dataid: iarr  # the heightfield of an HFIELD geom, -1 for the other types
        hfield_nrow: iarr
        hfield_ncol: iarr
        hfield_size: wp.array(dtype=vec4)  # (rx, ry, z_top, z_base)
        hfield_adr: iarr  # the grid's first height in hfield_data
        hfield_data: farr  # normalised heights, each distinct grid once (hfield_grids)

    return ModelArrays


@dataclasses.dataclass(frozen=True, eq=False)
class WarpModel:
    """A model on one Warp device in one precision, with the sizes the launches need."""

    model: Model
    device: str
    np_dtype: np.dtype
    arrays: object  # ModelArrays
    num_worlds: int
    max_bodies: int
    max_joints: int
    max_dofs: int
    max_cts: int
    max_dyn: int
    max_cpl: int
    max_lim: int
    max_pairs: int
    max_contacts: int
    max_rows: int  # max over worlds of maxdim_w
    max_slots: int  # max over worlds of maxdim_w + its virtual rows (6 per hub body, linear_solve_pattern.hub_bodies)
    total_rows: int
    total_mat: int
    total_jd: int
    total_cand: int
    blocks_per_row: int  # 2, or 4 when a coupling row spans two joints
    #: the hub threshold the virtual rows were laid out for (linear_solve_pattern.HUB_MIN_ROWS)
    hub_min_rows: int | None = None


def _bounding_radius(model: Model) -> np.ndarray:
    s = model.geom_size
    t = model.geom_type
    r = np.select(
        [t == GeomType.SPHERE, t == GeomType.CAPSULE, (t == GeomType.BOX) | (t == GeomType.HFIELD),
         t == GeomType.CYLINDER, t == GeomType.ELLIPSOID],
        [s[:, 0], s[:, 0] + s[:, 1], np.linalg.norm(s, axis=-1), np.hypot(s[:, 0], s[:, 1]), np.max(s, axis=-1)],
        0.0,
    ) if model.num_geoms else np.zeros(0)
    return r + np.linalg.norm(model.geom_pos, axis=-1) if model.num_geoms else r


@dataclasses.dataclass(frozen=True)
class HFieldGrids:
    """The distinct heightfield grids of a model: what the device stores of ``Model.hfield_data``."""

    data: np.ndarray  # [D] the heights of each distinct grid once, grid after grid
    adr: np.ndarray  # [H] each heightfield's first height in data
    grid: np.ndarray  # [H] each heightfield's distinct grid (in order of first appearance)


def hfield_grids(model: Model) -> HFieldGrids:
    """The distinct grids of ``model``'s heightfields: two heightfields share a grid when their ``nrow``, ``ncol``
    and normalised heights are equal (their ``size`` may differ: it stays per heightfield). ``kamino.replicate(m,
    4096)`` of a model with one 800 x 800 terrain stores 640,000 heights, not 4096 copies of them. A frozen model's
    are computed once and kept on the model (:func:`kamino.model.derived`)."""
    return derived(model, "hfield_grids", lambda: _hfield_grids(model))


def _hfield_grids(model: Model) -> HFieldGrids:
    H = model.num_hfields
    reps: list[np.ndarray] = []  # the distinct grids' heights (views of model.hfield_data)
    by_key: dict[tuple, list[int]] = {}  # a cheap key (shape and a sample of heights) -> candidate distinct grids
    grid = np.empty(H, np.int64)
    for h in range(H):
        nrow, ncol, adr = int(model.hfield_nrow[h]), int(model.hfield_ncol[h]), int(model.hfield_adr[h])
        d = model.hfield_data[adr:adr + nrow * ncol]
        key = (nrow, ncol, d[::max(1, d.size // 16)].tobytes())
        same = by_key.setdefault(key, [])
        t = next((t for t in same if np.array_equal(reps[t], d)), None)
        if t is None:
            t = len(reps)
            reps.append(d)
            same.append(t)
        grid[h] = t
    sizes = np.array([r.size for r in reps], np.int64)
    data = np.concatenate(reps) if reps else np.zeros(0)
    adr = prefix(sizes)[grid] if H else np.zeros(0, np.int64)
    for a in (data, adr, grid):
        a.flags.writeable = False  # shared by every caller of a cached entry
    return HFieldGrids(data=data, adr=adr, grid=grid)


def warp_model(model: Model, np_dtype, device) -> WarpModel:
    """The :class:`WarpModel` of ``model`` in ``np_dtype`` on ``device``, uploaded (each call uploads anew: the
    owner, a ``kamino.Simulator``'s engine, keeps one per precision and device)."""
    return _upload(model, np.dtype(np_dtype), str(wp.get_device(device)), linear_solve_pattern.HUB_MIN_ROWS)


def _upload(model: Model, np_dtype: np.dtype, device: str, hub_min_rows: int | None = None) -> WarpModel:
    T = types_of(np_dtype)
    W = model.num_worlds
    tab = row_tables(model)
    S = model_struct(np_dtype)()

    def i32(a):
        return wp.array(np.asarray(a, np.int32).reshape(-1), dtype=wp.int32, device=device)

    def flt(a, dtype=None, shape_tail=()):
        a = np.asarray(a, np_dtype)
        if dtype is None:
            return wp.array(a.reshape(-1), dtype=T.scalar, device=device)
        return wp.array(a.reshape((-1, *shape_tail)), dtype=dtype, device=device)

    nb, nj, nd = model.world_body_count, model.world_joint_count, model.world_dof_count
    ncts, ncpl = model.world_cts_count, model.world_coupling_count
    ndyn, nlim = tab.world_dyn_count, tab.world_lim_count
    cap = model.world_contact_capacity
    n_fixed = ndyn + ncts + ncpl
    maxdim = n_fixed + nlim + 3 * cap
    # 6 virtual rows per hub body after the row capacity: the hubs' unknowns during the sparse factor's solves
    # (linear_solve_pattern.hub_bodies; never real rows)
    slots = maxdim + 6 * hub_counts(model, hub_min_rows) if W else maxdim
    g_dim = group_sizes(slots)
    g_col = 6 * group_sizes(nb)
    # candidate contact points, in detection order
    order = tab.pair_order
    kinds = tab.pair_kinds
    kind_points = np.array([CONTACT_POINTS[tuple(GeomType(t) for t in kind)] for kind in kinds], np.int64)
    pair_points = kind_points[tab.pair_kind[order]] if order.size else np.zeros(0, np.int64)
    pair_world = model.pair_world[order]
    pair_count = np.bincount(pair_world, minlength=W)
    cand_count = np.bincount(pair_world, weights=pair_points, minlength=W).astype(np.int64)
    grids = hfield_grids(model)
    if grids.data.size > np.iinfo(np.int32).max:
        raise ValueError(f"Warp backend: the model's distinct heightfield grids hold {grids.data.size:,} heights, more "
                         "than an int32 index reaches; split the batch into fewer worlds or share the terrains")
    pair_local = np.arange(model.num_pairs) - model.world_pair_start[model.pair_world] if model.num_pairs else order

    for name, val in dict(
        body_start=model.world_body_start, body_count=nb, joint_start=model.world_joint_start, joint_count=nj,
        dof_start=model.world_dof_start, dof_count=nd, cts_start=model.world_cts_start, cts_count=ncts,
        dyn_start=prefix(ndyn), dyn_count=ndyn, cpl_start=model.world_coupling_start, cpl_count=ncpl,
        lim_start=prefix(nlim), lim_count=nlim, pair_start=prefix(pair_count), pair_count=pair_count,
        cand_start=prefix(cand_count), cand_count=cand_count, con_start=prefix(cap), con_capacity=cap,
        row_fixed=n_fixed, row_maxdim=maxdim, grp_row_start=prefix(GROUP * g_dim), grp_maxdim=g_dim,
        grp_mat_start=prefix(GROUP * g_dim * g_dim), grp_jd_start=prefix(GROUP * g_dim * g_col), grp_ncol=g_col,
        body_world=model.body_world,
        joint_type=model.joint_type, joint_parent=model.joint_parent, joint_child=model.joint_child,
        cts_joint=tab.cts_joint, cts_axis=tab.cts_axis, cts_kind=tab.cts_kind,
        dof_joint=tab.dof_joint, dof_axis=tab.dof_axis, dof_kind=tab.dof_kind, act_mode=model.dof_act_mode,
        dyn_dof=tab.dyn_dof, dyn_kind=tab.dyn_kind, cpl_dof_a=tab.cpl_dof_a, cpl_dof_b=tab.cpl_dof_b,
        cpl_wrap=tab.cpl_wrap, lim_dof=tab.lim_dof, geom_type=model.geom_type, geom_body=model.geom_body,
        pair_geom_a=model.pair_geom_a[order], pair_geom_b=model.pair_geom_b[order], pair_key=pair_local[order],
        pair_cand=prefix(pair_points), pair_points=pair_points, geom_dataid=model.geom_dataid,
        hfield_nrow=model.hfield_nrow, hfield_ncol=model.hfield_ncol, hfield_adr=grids.adr,
    ).items():
        setattr(S, name, i32(val))
    inertia = model.body_inertia
    for name, val in dict(
        mass=model.body_mass, inv_mass=1.0 / model.body_mass, kp=model.dof_kp, kd=model.dof_kd,
        effort_limit=model.dof_effort_limit, armature=model.dof_armature, damping=model.dof_damping,
        stiffness=model.dof_stiffness, springref=model.dof_springref, lower=model.dof_lower, upper=model.dof_upper,
        geom_friction=model.geom_friction, geom_restitution=model.geom_restitution, geom_margin=model.geom_margin,
        geom_radius=_bounding_radius(model), hfield_data=grids.data,
    ).items():
        setattr(S, name, flt(val))
    S.hfield_size = flt(model.hfield_size, T.vec4, (4,))
    S.gravity = flt(model.gravity, T.vec3, (3,))
    S.inertia = flt(inertia, T.mat33, (3, 3))
    S.inv_inertia = flt(np.linalg.inv(inertia) if len(inertia) else inertia, T.mat33, (3, 3))
    S.anchor_B = flt(model.joint_anchor_B, T.vec3, (3,))
    S.anchor_F = flt(model.joint_anchor_F, T.vec3, (3,))
    S.frame_B = flt(model.joint_frame_B, T.quat, (4,))
    S.frame_F = flt(model.joint_frame_F, T.quat, (4,))
    S.cpl_coef = wp.array(np.asarray(model.coupling_coef, np_dtype).reshape(-1, 5), dtype=T.scalar, device=device)
    S.geom_pos = flt(model.geom_pos, T.vec3, (3,))
    S.geom_quat = flt(model.geom_quat, T.quat, (4,))
    S.geom_size = flt(model.geom_size, T.vec3, (3,))

    two_joint_couplings = model.num_couplings and bool(np.any(model.coupling_joint_b >= 0))
    mx = lambda c: int(np.max(c)) if len(c) else 0  # noqa: E731
    return WarpModel(
        model=model, device=device, np_dtype=np_dtype, arrays=S, num_worlds=W,
        max_bodies=mx(nb), max_joints=mx(nj), max_dofs=mx(nd), max_cts=mx(ncts), max_dyn=mx(ndyn),
        max_cpl=mx(ncpl), max_lim=mx(nlim), max_pairs=mx(pair_count), max_contacts=mx(cap), max_rows=mx(maxdim),
        max_slots=mx(slots),
        total_rows=int(GROUP * g_dim.sum()), total_mat=int(GROUP * (g_dim * g_dim).sum()),
        total_jd=int(GROUP * (g_dim * g_col).sum()),
        total_cand=int(cand_count.sum()), blocks_per_row=4 if two_joint_couplings else 2,
        hub_min_rows=hub_min_rows,
    )
