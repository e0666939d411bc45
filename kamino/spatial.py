"""Quaternion and SO(3) helpers in JAX (docs/formulation.md §1.1, §2.3, §6.1).

Quaternions are ``(x, y, z, w)``. Every function is differentiable everywhere it is used,
including at zero rotation (the "double where" trick keeps gradients finite).
"""

from __future__ import annotations

import jax.numpy as jnp


def quat_mul(a: jnp.ndarray, b: jnp.ndarray) -> jnp.ndarray:
    """Hamilton product ``a ⊗ b`` (§1.1)."""
    ax, ay, az, aw = a[..., 0], a[..., 1], a[..., 2], a[..., 3]
    bx, by, bz, bw = b[..., 0], b[..., 1], b[..., 2], b[..., 3]
    return jnp.stack(
        [
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
            aw * bw - ax * bx - ay * by - az * bz,
        ],
        axis=-1,
    )


def quat_conj(q: jnp.ndarray) -> jnp.ndarray:
    """Conjugate (the inverse of a unit quaternion)."""
    return q * jnp.array([-1.0, -1.0, -1.0, 1.0], dtype=q.dtype)


def quat_to_matrix(q: jnp.ndarray) -> jnp.ndarray:
    """Rotation matrix ``R(q)`` of a unit quaternion (§1.1)."""
    x, y, z, w = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    r0 = jnp.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], axis=-1)
    r1 = jnp.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], axis=-1)
    r2 = jnp.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], axis=-1)
    return jnp.stack([r0, r1, r2], axis=-2)


def quat_exp(phi: jnp.ndarray) -> jnp.ndarray:
    """``Exp(phi) = (sin(|phi|/2) phi/|phi|, cos(|phi|/2))``, ``(phi/2, 1)`` near zero (§6.1)."""
    sq = jnp.sum(phi * phi, axis=-1, keepdims=True)
    small = sq < 1e-12
    n = jnp.sqrt(jnp.where(small, 1.0, sq))
    half = 0.5 * n
    vec = jnp.where(small, 0.5 * phi * (1.0 - sq / 24.0), jnp.sin(half) / n * phi)
    w = jnp.where(small, 1.0 - sq / 8.0, jnp.cos(half))
    return jnp.concatenate([vec, w], axis=-1)


def quat_log(q: jnp.ndarray) -> jnp.ndarray:
    """Rotation vector ``Log(q)`` of a unit quaternion, shortest way round (§2.3 "log")."""
    q = jnp.where(q[..., 3:4] < 0, -q, q)
    v, w = q[..., :3], q[..., 3:4]
    sq = jnp.sum(v * v, axis=-1, keepdims=True)
    small = sq < 1e-12
    s = jnp.sqrt(jnp.where(small, 1.0, sq))
    angle = 2.0 * jnp.arctan2(s, w)
    w_safe = jnp.where(small, w, 1.0)
    series = (2.0 - (2.0 / 3.0) * sq / (w_safe * w_safe)) * v / w_safe
    return jnp.where(small, series, angle / s * v)


def quat_normalize(q: jnp.ndarray) -> jnp.ndarray:
    return q / jnp.linalg.norm(q, axis=-1, keepdims=True)


def rotate(q: jnp.ndarray, v: jnp.ndarray) -> jnp.ndarray:
    """``R(q) v``."""
    return jnp.einsum("...ij,...j->...i", quat_to_matrix(q), v)


def integrate_pose(q: jnp.ndarray, u: jnp.ndarray, h) -> jnp.ndarray:
    """Exponential-map pose update ``r+ = r + h v``, ``q+ = Exp(h w) ⊗ q`` (docs/formulation.md §6.1).

    ``q`` is ``[..., 7]`` (CoM position, quaternion), ``u`` is ``[..., 6]`` (v, w in world). The
    quaternion is renormalised (changes results only at rounding level).
    """
    r = q[..., :3] + h * u[..., :3]
    rot = quat_normalize(quat_mul(quat_exp(h * u[..., 3:]), q[..., 3:]))
    return jnp.concatenate([r, rot], axis=-1)
