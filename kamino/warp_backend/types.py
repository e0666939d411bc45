"""Warp value types for one floating-point precision (float32 or float64).

Every kernel and ``wp.func`` of the Warp backend comes from a small builder cached per precision; it
closes over the :class:`Types` below (read, with the structs the kernels take, from
``workspace.builder_types``), so one source serves both precisions and a process compiles only the
precisions it uses. Poses are ``transform`` (``p``, then the quaternion ``(x, y, z, w)``:
exactly the layout of ``State.body_q``), twists are ``vec6`` ``(v, w)`` as ``State.body_u``.
"""

from __future__ import annotations

import dataclasses
import functools

import numpy as np
import warp as wp


@dataclasses.dataclass(frozen=True)
class Types:
    """The Warp types of one precision."""

    scalar: type
    vec2: type
    vec3: type
    vec4: type
    vec6: type
    quat: type
    mat33: type
    transform: type
    np_dtype: np.dtype


@functools.cache
def types_of(np_dtype) -> Types:
    """The :class:`Types` for ``float32`` or ``float64`` (anything ``np.dtype`` accepts)."""
    dt = np.dtype(np_dtype)
    if dt == np.float32:
        s = wp.float32
    elif dt == np.float64:
        s = wp.float64
    else:
        raise ValueError(f"the Warp backend supports float32 and float64 states, got {dt}")
    return Types(
        scalar=s,
        vec2=wp.types.vector(2, s),
        vec3=wp.types.vector(3, s),
        vec4=wp.types.vector(4, s),
        vec6=wp.types.vector(6, s),
        quat=wp.types.quaternion(s),
        mat33=wp.types.matrix((3, 3), s),
        transform=wp.types.transformation(s),
        np_dtype=dt,
    )
