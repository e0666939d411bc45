"""Where a world's constraint rows, Delassus entries and dense-Jacobian entries live in device memory.

Worlds are taken in *groups* of :data:`GROUP` consecutive worlds (one GPU warp of the one-thread-per-
world kernels). Inside a group the per-row data are interleaved by world: entry ``a`` of the world in
lane ``l`` is at ``group_start + a * GROUP + l``. When the 32 threads of a warp walk their worlds' rows
in step (the PADMM iterations, the factorisation), each load is one contiguous 128-byte line instead of
32 scattered ones. A group reserves ``GROUP * maxdim_g`` rows with ``maxdim_g`` the largest row capacity
of its worlds, so storage is the per-world sum for identical worlds and stays close to it for mixed
worlds ordered by size (docs/warp_backend.md, "Memory layout"). Under the 32-threads-per-world schedule
(padmm_warp.py) the rows are stored world after world instead (``Work.row_stride = 1``: the world in lane ``l``
starts at ``group_start + l * maxdim_g``), so that the 32 threads of one world read consecutive rows.
"""

import functools
from types import SimpleNamespace

import warp as wp

from kamino.warp_backend.model_data import GROUP, model_struct
from kamino.warp_backend.workspace import work_struct


@functools.cache
def index_funcs(np_dtype) -> SimpleNamespace:
    M = model_struct(np_dtype)
    Work = work_struct(np_dtype)

    @wp.func
    def row_base(m: M, w: Work, wid: int):
        """``ridx(m, w, wid, a) = row_base(m, w, wid) + a * w.row_stride``: hoisted out of a world's row loops (a
        kernel that also stores to arrays cannot have the compiler prove the start unchanged, so it would reload
        it)."""
        g = wid // GROUP
        if w.row_stride == 1:
            return m.grp_row_start[g] + (wid - g * GROUP) * m.grp_maxdim[g]
        return m.grp_row_start[g] + (wid - g * GROUP)

    @wp.func
    def ridx(m: M, w: Work, wid: int, a: int):
        """Storage index of row ``a`` of world ``wid`` (interleaved over the group, or the world's rows contiguous:
        ``w.row_stride``)."""
        return row_base(m, w, wid) + a * w.row_stride

    @wp.func
    def didx(m: M, wid: int, a: int, b: int):
        """Storage index of the Delassus entry ``(a, b)`` of world ``wid``."""
        g = wid // GROUP
        return m.grp_mat_start[g] + (a * m.grp_maxdim[g] + b) * GROUP + (wid - g * GROUP)

    @wp.func
    def jidx(m: M, wid: int, a: int, c: int):
        """Storage index of the dense-Jacobian entry ``(a, c)`` (column ``c`` = 6 x local body + axis)."""
        g = wid // GROUP
        return m.grp_jd_start[g] + (a * m.grp_ncol[g] + c) * GROUP + (wid - g * GROUP)

    return SimpleNamespace(ridx=ridx, row_base=row_base, didx=didx, jidx=jidx)
