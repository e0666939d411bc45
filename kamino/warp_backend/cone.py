"""The Coulomb cone in Warp: projection and the De Saxcé correction (docs/formulation.md §4.2-§4.3)."""

import functools
from types import SimpleNamespace

import numpy as np
import warp as wp

from kamino.warp_backend.types import types_of


@functools.cache
def cone_funcs(np_dtype) -> SimpleNamespace:
    T = types_of(np_dtype)
    scalar, vec3 = T.scalar, T.vec3
    tiny = scalar(float(np.finfo(np_dtype).tiny))

    @wp.func
    def cone_project(t1: scalar, t2: scalar, n: scalar, mu: scalar):
        """Projection of ``(t1, t2, n)`` on ``||t|| <= mu n`` (``cone_project`` of the JAX reference): the
        polar-cone case is tested first, so ``mu = 0`` and ``t = 0`` never divide by zero."""
        s2 = t1 * t1 + t2 * t2
        s = scalar(0.0)
        if s2 > scalar(0.0):
            s = wp.sqrt(s2)
        if s <= mu * n:
            return vec3(t1, t2, n)
        if mu * s <= -n:
            return vec3()
        yn = (mu * s + n) / (scalar(1.0) + mu * mu)
        sc = scalar(0.0)
        if s > scalar(0.0):
            sc = mu * yn / s
        return vec3(t1 * sc, t2 * sc, yn)

    @wp.func
    def de_saxce(t1: scalar, t2: scalar, mu: scalar):
        """``Gamma(v)_n = mu ||v_t||`` (the tangential part is zero)."""
        return mu * wp.sqrt(t1 * t1 + t2 * t2 + tiny)

    return SimpleNamespace(cone_project=cone_project, de_saxce=de_saxce)
