"""Procedural contact scenes: boxes, spheres, an incline and Newton's cradle.

Every function returns a validated single-world :class:`kamino.Model` whose ground is a PLANE geom
on the world; body 0 is the object the scene is about. Gravity is along -z unless stated.
"""

from __future__ import annotations

import numpy as np

from kamino.model import GeomType, JointType, Model, ModelBuilder
from kamino.models.shapes import box_inertia


def _sphere_inertia(mass: float, radius: float) -> np.ndarray:
    return 0.4 * mass * radius * radius * np.eye(3)


def box_on_plane(mass: float = 1.0, size: float = 0.2, mu: float = 0.8, velocity=(0.0, 0.0, 0.0),
                 gravity: float = 9.81) -> Model:
    """A cube of edge ``size`` [m] (body 0, geom ``box``) resting on the ground plane (z = 0) at rest,
    or sliding with the initial ``velocity``; friction ``mu`` on both geoms."""
    b = ModelBuilder(gravity=(0.0, 0.0, -gravity))
    h = 0.5 * size
    box = b.add_body(mass=mass, inertia=box_inertia(mass, (size,) * 3), pos=(0.0, 0.0, h), velocity=velocity,
                     name="box")
    b.add_geom(GeomType.BOX, box, size=(h, h, h), friction=mu, name="box")
    b.add_geom(GeomType.PLANE, -1, friction=mu, name="ground")
    return b.finalize()


def box_stack(n: int = 5, mass: float = 1.0, size: float = 0.2, mu: float = 0.8, gravity: float = 9.81) -> Model:
    """``n`` cubes of edge ``size`` stacked on the ground plane, at rest (body 0 at the bottom).

    The contact capacity is ``8 n``: the 4 face-corner contacts of every resting interface plus
    room for as many more; a toppled stack that needs more reports ``state.info.contact_overflow``.
    """
    if n < 1:
        raise ValueError(f"box_stack: n must be >= 1, got {n}")
    b = ModelBuilder(gravity=(0.0, 0.0, -gravity))
    h = 0.5 * size
    b.add_geom(GeomType.PLANE, -1, friction=mu, name="ground")
    for k in range(n):
        body = b.add_body(mass=mass, inertia=box_inertia(mass, (size,) * 3), pos=(0.0, 0.0, h + k * size),
                          name=f"box{k}")
        b.add_geom(GeomType.BOX, body, size=(h, h, h), friction=mu, name=f"box{k}")
    return b.finalize(contact_capacity=8 * n)


def sphere_drop(restitution: float = 0.5, height: float = 1.0, radius: float = 0.05, mass: float = 0.2,
                gravity: float = 9.81) -> Model:
    """A sphere (body 0) whose lowest point starts ``height`` [m] above the ground plane, at rest.
    Both geoms have ``restitution`` (a pair uses the larger value)."""
    b = ModelBuilder(gravity=(0.0, 0.0, -gravity))
    s = b.add_body(mass=mass, inertia=_sphere_inertia(mass, radius), pos=(0.0, 0.0, height + radius), name="sphere")
    b.add_geom(GeomType.SPHERE, s, size=radius, restitution=restitution, name="sphere")
    b.add_geom(GeomType.PLANE, -1, restitution=restitution, name="ground")
    return b.finalize()


def incline(angle_deg: float = 20.0, mu: float = 0.5, mass: float = 1.0, size: float = 0.2,
            gravity: float = 9.81) -> Model:
    """A cube (body 0) resting at rest on a plane through the origin tilted by ``angle_deg`` about
    world y (downhill is +x); friction ``mu`` on both geoms."""
    b = ModelBuilder(gravity=(0.0, 0.0, -gravity))
    th = np.deg2rad(angle_deg)
    q = np.array([0.0, np.sin(th / 2), 0.0, np.cos(th / 2)])  # rotation about +y: plane normal tilts to +x
    normal = np.array([np.sin(th), 0.0, np.cos(th)])
    h = 0.5 * size
    box = b.add_body(mass=mass, inertia=box_inertia(mass, (size,) * 3), pos=h * normal, quat=q, name="box")
    b.add_geom(GeomType.BOX, box, size=(h, h, h), friction=mu, name="box")
    b.add_geom(GeomType.PLANE, -1, quat=q, friction=mu, name="slope")
    return b.finalize()


def newtons_cradle(n: int = 3, radius: float = 0.02, mass: float = 0.1, length: float = 0.3, gap: float = 1e-3,
                   release_angle: float = np.deg2rad(30.0), hanging: bool = True, speed: float = 0.5,
                   gravity: float = 9.81) -> Model:
    """Newton's cradle: ``n`` steel-like spheres (restitution 1, no friction) in a row along x, ``gap``
    [m] apart.

    ``hanging=True``: each sphere hangs on a REVOLUTE joint (about y) from a pivot ``length`` above
    its centre; sphere 0 (body 0) starts pulled back by ``release_angle`` at rest. ``hanging=False``:
    free spheres without gravity, sphere 0 moving towards the others at ``speed`` [m/s].
    """
    if n < 2:
        raise ValueError(f"newtons_cradle: n must be >= 2, got {n}")
    b = ModelBuilder(gravity=(0.0, 0.0, -gravity if hanging else 0.0))
    pitch = 2.0 * radius + gap
    for k in range(n):
        pivot = np.array([k * pitch, 0.0, length + radius])
        centre = pivot - np.array([0.0, 0.0, length])
        vel = (0.0, 0.0, 0.0)
        if k == 0:
            if hanging:
                centre = pivot + length * np.array([-np.sin(release_angle), 0.0, -np.cos(release_angle)])
            else:
                vel = (speed, 0.0, 0.0)
        s = b.add_body(mass=mass, inertia=_sphere_inertia(mass, radius), pos=centre, velocity=vel, name=f"ball{k}")
        b.add_geom(GeomType.SPHERE, s, size=radius, friction=0.0, restitution=1.0, name=f"ball{k}")
        if hanging:
            b.add_joint_at(JointType.REVOLUTE, -1, s, anchor=pivot, axis=(0.0, 1.0, 0.0), name=f"string{k}")
    return b.finalize()
