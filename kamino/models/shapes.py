"""Mass properties of simple solids and slender links, for the procedural models."""

from __future__ import annotations

import numpy as np

from kamino.hostmath import matrix_to_quat
from kamino.model import ModelBuilder


def box_inertia(mass: float, size: tuple[float, float, float]) -> np.ndarray:
    """Inertia about the CoM of a solid box with full edge lengths ``size`` (principal axes = box axes)."""
    a, b, c = size
    return mass / 12.0 * np.diag([b * b + c * c, a * a + c * c, a * a + b * b])


def capsule_inertia(mass: float, radius: float, length: float) -> np.ndarray:
    """Inertia about the CoM of a solid capsule (cylinder of ``length`` plus two hemispheres),
    symmetry axis along local x; mass split between the parts by volume."""
    r, h = radius, length
    v_cyl, v_sph = np.pi * r * r * h, 4.0 / 3.0 * np.pi * r**3
    m_cyl, m_sph = mass * v_cyl / (v_cyl + v_sph), mass * v_sph / (v_cyl + v_sph)
    axial = 0.5 * m_cyl * r * r + 0.4 * m_sph * r * r
    # hemispheres: own transverse inertia 83/320 m r^2 (per pair), centroid at h/2 + 3r/8
    transverse = m_cyl * (r * r / 4 + h * h / 12) + m_sph * (83.0 / 320.0 * r * r + (h / 2 + 3 * r / 8) ** 2)
    return np.diag([axial, transverse, transverse])


def frame_along(direction) -> np.ndarray:
    """Quaternion of a frame whose x axis is ``direction`` and whose y axis is as close as possible to world y."""
    x = np.asarray(direction, dtype=float)
    x = x / np.linalg.norm(x)
    ref = np.array([0.0, 1.0, 0.0]) if abs(x[1]) < 0.9 else np.array([0.0, 0.0, 1.0])
    y = ref - np.dot(ref, x) * x
    y /= np.linalg.norm(y)
    return matrix_to_quat(np.column_stack([x, y, np.cross(x, y)]))


def add_link(builder: ModelBuilder, p0, p1, mass: float, radius: float, name: str) -> int:
    """Add a capsule link from ``p0`` to ``p1`` (world) as a body: CoM at the midpoint, x along the link."""
    p0, p1 = np.asarray(p0, float), np.asarray(p1, float)
    length = float(np.linalg.norm(p1 - p0))
    return builder.add_body(
        mass=mass, inertia=capsule_inertia(mass, radius, length), pos=0.5 * (p0 + p1),
        quat=frame_along(p1 - p0), name=name,
    )
