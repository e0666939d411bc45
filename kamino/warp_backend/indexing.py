"""Where a world's constraint rows, Delassus entries and dense-Jacobian entries live in device memory.

Worlds are taken in *groups* of :data:`GROUP` consecutive worlds (one GPU warp of the one-thread-per-
world kernels). Inside a group the per-row data are interleaved by world: entry ``a`` of the world in
lane ``l`` is at ``group_start + a * GROUP + l``. When the 32 threads of a warp walk their worlds' rows
in step (the PADMM iterations, the factorisation), each load is one contiguous 128-byte line instead of
32 scattered ones. A group reserves ``GROUP * maxdim_g`` rows with ``maxdim_g`` the largest row capacity
of its worlds, so storage is the per-world sum for identical worlds and stays close to it for mixed
worlds ordered by size (docs/warp_backend.md, "Memory layout").
"""

import functools
from types import SimpleNamespace

import warp as wp

from kamino.warp_backend.model_data import GROUP, model_struct


@functools.cache
def index_funcs(np_dtype) -> SimpleNamespace:
    M = model_struct(np_dtype)

    @wp.func
    def ridx(m: M, wid: int, a: int):
        """Storage index of row ``a`` of world ``wid``."""
        g = wid // GROUP
        return m.grp_row_start[g] + a * GROUP + (wid - g * GROUP)

    @wp.func
    def row_base(m: M, wid: int):
        """``ridx(m, wid, a) = row_base(m, wid) + a * GROUP``: hoisted out of a world's row loops (a kernel that
        also stores to arrays cannot have the compiler prove the start unchanged, so it would reload it)."""
        g = wid // GROUP
        return m.grp_row_start[g] + (wid - g * GROUP)

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
