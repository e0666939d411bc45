"""Full float32 precision for the reference's matrix products on GPUs.

JAX lowers a float32 ``dot_general`` at its default precision, which on NVIDIA GPUs since Ampere is TF32: a
10-bit mantissa, relative error about 1e-3 per product. The step's Delassus operator, its Cholesky factor and the
PADMM residuals (formulation.md, the dual problem) need the full 24 bits: at TF32 the tolerance of 1e-6 is out of
reach and ``dr_legs`` diverged in 2.5 s (on an H200: loop closure 1.5e5 m). :func:`full_precision` traces a
function under ``jax.default_matmul_precision("highest")``; the precision is fixed when each product is traced, so
it holds inside a caller's ``jax.jit``, ``vmap`` or ``scan`` too. CPUs compute float32 products in full either way.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import TypeVar

import jax

F = TypeVar("F", bound=Callable)


def full_precision(fn: F) -> F:
    """``fn`` traced with every float32 matrix product at full precision (no TF32)."""

    @functools.wraps(fn)
    def wrapped(*args, **kwargs):
        with jax.default_matmul_precision("highest"):
            return fn(*args, **kwargs)

    return wrapped  # type: ignore[return-value]
