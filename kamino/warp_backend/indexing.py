"""Where a world's constraint rows, Delassus entries and dense-Jacobian entries live in device memory.

Worlds are taken in *groups* of :data:`GROUP` consecutive worlds (one GPU warp of the one-thread-per-
world kernels). Inside a group the per-row data are interleaved by world: entry ``a`` of the world in
lane ``l`` is at ``group_start + a * GROUP + l``. When the 32 threads of a warp walk their worlds' rows
in step (the PADMM iterations, the factorisation), each load is one contiguous 128-byte line instead of
32 scattered ones. A group reserves ``GROUP * maxdim_g`` rows with ``maxdim_g`` the largest row capacity
of its worlds, so storage is the per-world sum for identical worlds and stays close to it for mixed
worlds ordered by size (docs/warp_backend.md, "Memory layout"). Under the 32-threads-per-world schedule
(solver_lanes.py) the rows are stored world after world instead (``Work.row_stride = 1``: the world in lane ``l``
starts at ``group_start + l * maxdim_g``), so that the 32 threads of one world read consecutive rows.

Each ``wp.func`` comes from its own builder, cached per precision (``np_dtype``); :func:`index_funcs` names them all.
"""

import functools
from types import SimpleNamespace

import warp as wp

from kamino.warp_backend.model_data import GROUP
from kamino.warp_backend.workspace import (
    ROW_KIND_SHIFT,
    ROW_NEG_BIT,
    ROW_SAT_BIT,
    ROW_SRC_BITS,
    ROW_SRC_MASK,
    builder_types,
)

_SRC_MASK, _SAT_BIT, _NEG_BIT = wp.constant(ROW_SRC_MASK), wp.constant(ROW_SAT_BIT), wp.constant(ROW_NEG_BIT)
_SAT_SHIFT = wp.constant(ROW_SRC_BITS)
_KIND_SHIFT, _NOT_SAT = wp.constant(ROW_KIND_SHIFT), wp.constant(~ROW_SAT_BIT)


def index_funcs(np_dtype) -> SimpleNamespace:
    """The indexing ``wp.func``s by name, each from its builder (cached per precision, ``np_dtype``)."""
    return SimpleNamespace(row_base=row_base_func(np_dtype), ridx=ridx_func(np_dtype), didx=didx_func(np_dtype),
                           jidx=jidx_func(np_dtype), row_info=row_info_func(np_dtype),
                           row_kind=row_kind_func(np_dtype), row_source=row_source_func(np_dtype),
                           row_side=row_side_func(np_dtype), row_saturated=row_saturated_func(np_dtype),
                           set_saturated=set_saturated_func(np_dtype), row_mu=row_mu_func(np_dtype))


@functools.cache
def row_base_func(np_dtype):
    """Where a world's rows start (the layouts of the module docstring)."""
    M = builder_types(np_dtype).M

    @wp.func
    def row_base(m: M, row_stride: int, wid: int):
        """``ridx(m, row_stride, wid, a) = row_base(m, row_stride, wid) + a * row_stride``: hoisted out of a world's
        row loops (a kernel that also stores to arrays cannot have the compiler prove the start unchanged, so it would
        reload it). ``row_stride``: ``Work.row_stride``."""
        g = wid // GROUP
        if row_stride == 1:
            return m.grp_row_start[g] + (wid - g * GROUP) * m.grp_maxdim[g]
        return m.grp_row_start[g] + (wid - g * GROUP)

    return row_base


@functools.cache
def ridx_func(np_dtype):
    """The storage index of a world's row (the layouts of the module docstring)."""
    M = builder_types(np_dtype).M
    row_base = row_base_func(np_dtype)

    @wp.func
    def ridx(m: M, row_stride: int, wid: int, a: int):
        """Storage index of row ``a`` of world ``wid`` (interleaved over the group, or the world's rows contiguous:
        ``row_stride``, ``Work.row_stride``)."""
        return row_base(m, row_stride, wid) + a * row_stride

    return ridx


@functools.cache
def didx_func(np_dtype):
    """The storage index of a world's Delassus entry."""
    M = builder_types(np_dtype).M

    @wp.func
    def didx(m: M, wid: int, a: int, b: int):
        """Storage index of the Delassus entry ``(a, b)`` of world ``wid``."""
        g = wid // GROUP
        return m.grp_mat_start[g] + (a * m.grp_maxdim[g] + b) * GROUP + (wid - g * GROUP)

    return didx


@functools.cache
def jidx_func(np_dtype):
    """The storage index of a world's dense-Jacobian entry."""
    M = builder_types(np_dtype).M

    @wp.func
    def jidx(m: M, wid: int, a: int, c: int):
        """Storage index of the dense-Jacobian entry ``(a, c)`` (column ``c`` = 6 x local body + axis)."""
        g = wid // GROUP
        return m.grp_jd_start[g] + (a * m.grp_ncol[g] + c) * GROUP + (wid - g * GROUP)

    return jidx


@functools.cache
def row_info_func(np_dtype):
    """A row's packed description ``Work.row_info`` (``workspace.ROW_SRC_BITS``)."""
    scalar = builder_types(np_dtype).scalar

    @wp.func
    def row_info(kind: int, src: int, side: scalar):
        """The ``Work.row_info`` of a row of family ``kind`` (rows.ROW_*) from source ``src``; ``side < 0``: a limit
        row on its upper limit. Not saturated (``solver.scale`` sets the flag)."""
        info = (kind << _KIND_SHIFT) | src
        if side < scalar(0.0):
            info = info | _NEG_BIT
        return info

    return row_info


@functools.cache
def row_kind_func(np_dtype):
    """A row's family, from ``Work.row_info``."""
    @wp.func
    def row_kind(row_info: wp.array(dtype=wp.int32), r: int):
        """The family of row ``r`` (rows.ROW_*)."""
        return row_info[r] >> _KIND_SHIFT

    return row_kind


@functools.cache
def row_source_func(np_dtype):
    """A row's source, from ``Work.row_info``."""
    @wp.func
    def row_source(row_info: wp.array(dtype=wp.int32), r: int):
        """The source of row ``r``: its DoF (joint-dynamics and limit rows), kinematic constraint, coupling or
        contact slot (global indices)."""
        return row_info[r] & _SRC_MASK

    return row_source


@functools.cache
def row_side_func(np_dtype):
    """A limit row's sign, from ``Work.row_info``."""
    scalar = builder_types(np_dtype).scalar

    @wp.func
    def row_side(row_info: wp.array(dtype=wp.int32), r: int):
        """``+1`` or ``-1``: the sign of a limit row (``-1`` on the upper limit); ``+1`` on the other rows."""
        if (row_info[r] & _NEG_BIT) != 0:
            return scalar(-1.0)
        return scalar(1.0)

    return row_side


@functools.cache
def row_saturated_func(np_dtype):
    """A row's saturation flag, from ``Work.row_info``."""
    @wp.func
    def row_saturated(row_info: wp.array(dtype=wp.int32), r: int):
        """1 if row ``r`` is an effort-limited fixed row that carries ``rho`` (kamino.jax_ref.solver.solve,
        "Saturation"), else 0."""
        return (row_info[r] >> _SAT_SHIFT) & 1

    return row_saturated


@functools.cache
def set_saturated_func(np_dtype):
    """A row's saturation flag set or cleared in ``Work.row_info``."""
    @wp.func
    def set_saturated(row_info: wp.array(dtype=wp.int32), r: int, sat: int):
        """Set (``sat != 0``) or clear row ``r``'s saturation flag (only row ``r``'s own thread writes it)."""
        info = row_info[r] & _NOT_SAT
        if sat != 0:
            info = info | _SAT_BIT
        row_info[r] = info

    return set_saturated


@functools.cache
def row_mu_func(np_dtype):
    """A contact row's friction coefficient."""
    scalar = builder_types(np_dtype).scalar

    @wp.func
    def row_mu(ct_mu: wp.array(dtype=scalar), row_info: wp.array(dtype=wp.int32), r: int):
        """The friction coefficient of a contact row ``r`` (any of its three): its contact slot's."""
        return ct_mu[row_info[r] & _SRC_MASK]

    return row_mu
