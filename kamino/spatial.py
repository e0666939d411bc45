"""Quaternion and SO(3) helpers in JAX (docs/formulation.md §1.1, §2.3, §6.1).

Quaternions are ``(x, y, z, w)``. Every function is differentiable everywhere it is used,
including at zero rotation (the "double where" trick keeps gradients finite).
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

#: ``a ⊗ b`` component ``k`` is ``sum_m s[k, m] a[i[k, m]] b[j[k, m]]`` (§1.1), the terms in this order
_X, _Y, _Z, _W = range(4)
_MUL_I = np.array([[_W, _X, _Y, _Z]] * 4)
_MUL_J = np.array([[_X, _W, _Z, _Y], [_Y, _Z, _W, _X], [_Z, _Y, _X, _W], [_W, _X, _Y, _Z]])
#: the gathers' indices into :func:`_products`, int32 (an int64 constant fails to index with JAX's x64 mode off)
_MUL_IDX = (4 * _MUL_I + _MUL_J).astype(np.int32)
_MUL_S = np.array([[1, 1, 1, -1], [1, -1, 1, 1], [1, 1, -1, 1], [1, -1, -1, -1]], float)


def _products(a: jnp.ndarray, b: jnp.ndarray) -> jnp.ndarray:
    """The 16 products ``a_i b_j`` of two 4-vectors, flat at ``4 i + j`` (``[..., 16]``)."""
    p = a[..., :, None] * b[..., None, :]
    return p.reshape((*p.shape[:-2], 16))


def quat_mul(a: jnp.ndarray, b: jnp.ndarray) -> jnp.ndarray:
    """Hamilton product ``a ⊗ b`` (§1.1)::

        x = aw bx + ax bw + ay bz - az by,    y = aw by - ax bz + ay bw + az bx,
        z = aw bz + ax by - ay bx + az bw,    w = aw bw - ax bx - ay by - az bz,

    summed left to right. The 16 products come from one outer product and the terms from one gather, signs applied
    by multiplying with +-1 (``u + (-v)`` is ``u - v`` exactly in IEEE arithmetic): the same floating-point
    operations as the formula written out component by component, in a few traced operations instead of about
    fifty (the step traces this dozens of times)."""
    t = _products(a, b)[..., _MUL_IDX] * jnp.asarray(_MUL_S, a.dtype)
    return ((t[..., 0] + t[..., 1]) + t[..., 2]) + t[..., 3]


def quat_conj(q: jnp.ndarray) -> jnp.ndarray:
    """Conjugate (the inverse of a unit quaternion)."""
    return q * jnp.array([-1.0, -1.0, -1.0, 1.0], dtype=q.dtype)


#: ``R(q)`` row-major entry ``e``: ``1 - 2 t_e`` on the diagonal, ``2 t_e`` off it, ``t_e = q_a q_b + s q_c q_d`` with
#: the products at ``_ROT_A[e] = 4 a + b`` and ``_ROT_B[e] = 4 c + d`` of :func:`_products`
_ROT_A = np.array([4 * a + b for a, b in ((_Y, _Y), (_X, _Y), (_X, _Z), (_X, _Y), (_X, _X), (_Y, _Z), (_X, _Z),
                                          (_Y, _Z), (_X, _X))], np.int32)
_ROT_B = np.array([4 * a + b for a, b in ((_Z, _Z), (_Z, _W), (_Y, _W), (_Z, _W), (_Z, _Z), (_X, _W), (_Y, _W),
                                          (_X, _W), (_Y, _Y))], np.int32)
_ROT_S = np.array([1, -1, 1, 1, 1, -1, -1, 1, 1], float)
_ROT_DIAG = np.eye(3, dtype=bool).reshape(9)


def quat_to_matrix(q: jnp.ndarray) -> jnp.ndarray:
    """Rotation matrix ``R(q)`` of a unit quaternion (§1.1)::

        [[1 - 2 (y y + z z),  2 (x y - z w),      2 (x z + y w)],
         [2 (x y + z w),      1 - 2 (x x + z z),  2 (y z - x w)],
         [2 (x z - y w),      2 (y z + x w),      1 - 2 (x x + y y)]]

    evaluated as written (one outer product for the products, one gather per term: the same floating-point
    operations as the entries written out one by one, in a few traced operations; :func:`quat_mul`)."""
    p = _products(q, q)
    t = p[..., _ROT_A] + jnp.asarray(_ROT_S, q.dtype) * p[..., _ROT_B]
    return jnp.where(_ROT_DIAG, 1 - 2 * t, 2 * t).reshape((*q.shape[:-1], 3, 3))


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
