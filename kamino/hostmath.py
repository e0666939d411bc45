"""Host-side (NumPy) rotation helpers used when building models.

Quaternions are ``(x, y, z, w)`` (scalar last, Warp's order) everywhere in kamino.
The JAX reference has its own differentiable versions in ``kamino/spatial.py``;
these are only for model construction and validation on the host.
"""

from __future__ import annotations

import numpy as np

IDENTITY_QUAT = np.array([0.0, 0.0, 0.0, 1.0])


def quat_to_matrix(q: np.ndarray) -> np.ndarray:
    """Rotation matrix of a unit quaternion ``(x, y, z, w)`` (docs/formulation.md §1.1)."""
    x, y, z, w = np.asarray(q, dtype=float)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def matrix_to_quat(R: np.ndarray) -> np.ndarray:
    """Unit quaternion ``(x, y, z, w)`` with ``w >= 0`` of a rotation matrix (Shepperd's method)."""
    R = np.asarray(R, dtype=float)
    tr = np.trace(R)
    if tr > 0:
        s = 2.0 * np.sqrt(tr + 1.0)
        q = np.array([(R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s, 0.25 * s])
    else:
        i = int(np.argmax(np.diag(R)))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = 2.0 * np.sqrt(1.0 + R[i, i] - R[j, j] - R[k, k])
        q = np.zeros(4)
        q[i] = 0.25 * s
        q[j] = (R[j, i] + R[i, j]) / s
        q[k] = (R[k, i] + R[i, k]) / s
        q[3] = (R[k, j] - R[j, k]) / s
    q /= np.linalg.norm(q)
    return q if q[3] >= 0 else -q


def quat_mul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton product ``a ⊗ b`` of ``(x, y, z, w)`` quaternions."""
    ax, ay, az, aw = a
    bx, by, bz, bw = b
    return np.array(
        [
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
            aw * bw - ax * bx - ay * by - az * bz,
        ]
    )


def quat_from_axis_angle(axis, angle: float) -> np.ndarray:
    """Quaternion of a rotation by ``angle`` about ``axis`` (normalised here)."""
    axis = np.asarray(axis, dtype=float)
    axis = axis / np.linalg.norm(axis)
    return np.concatenate([np.sin(angle / 2) * axis, [np.cos(angle / 2)]])


def axis_frame(axis: np.ndarray, axis2: np.ndarray | None = None) -> np.ndarray:
    """Joint-axis frame ``A`` whose first column is the motion axis (docs/formulation.md §2.1).

    One axis: ``A = [a, b, a x b]`` with ``b = normalize(e_k x a)``, ``k = (argmax|a_i| + 2) mod 3``.
    Two axes (universal): ``A = [a1, a2', a1 x a2']`` with ``a2'`` made orthogonal to ``a1``.
    """
    a = np.asarray(axis, dtype=float)
    a = a / np.linalg.norm(a)
    if axis2 is None:
        k = (int(np.argmax(np.abs(a))) + 2) % 3
        e = np.zeros(3)
        e[k] = 1.0
        b = np.cross(e, a)
        b /= np.linalg.norm(b)
    else:
        b = np.asarray(axis2, dtype=float)
        b = b - np.dot(b, a) * a
        b /= np.linalg.norm(b)
    return np.column_stack([a, b, np.cross(a, b)])
