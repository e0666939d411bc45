"""Procedural planar mechanisms: pendulums, four-bar, slider-crank and the chain of loops.

Every function returns a validated single-world :class:`kamino.Model`. All mechanisms move in
the world xz plane (hinges about world y, gravity along -z) and start at rest.
"""

from __future__ import annotations

import numpy as np

from kamino.model import Actuation, JointType, Model, ModelBuilder
from kamino.models.shapes import add_link, box_inertia

Y = (0.0, 1.0, 0.0)


def _down(angle: float, length: float) -> np.ndarray:
    """Vector of ``length`` hanging from a pivot, rotated by ``angle`` [rad] about +y from straight down."""
    return length * np.array([-np.sin(angle), 0.0, -np.cos(angle)])


def pendulum(length: float = 1.0, mass: float = 1.0, width: float = 0.02, angle: float = 0.5,
             pivot: tuple[float, float, float] = (0.0, 0.0, 1.0), gravity: float = 9.81) -> Model:
    """Physical pendulum: a slender box of ``length`` x ``width`` x ``width`` hinged at its top end
    about world y at ``pivot``, released from rest at ``angle`` [rad] from the vertical.

    The joint (``"hinge"``) coordinate is the angle from the vertical (0 hanging straight down).
    """
    b = ModelBuilder(gravity=(0.0, 0.0, -gravity))
    pivot = np.asarray(pivot, float)
    rot = np.array([0.0, np.sin(angle / 2), 0.0, np.cos(angle / 2)])  # about +y
    link = b.add_body(mass=mass, inertia=box_inertia(mass, (width, width, length)),
                      pos=pivot + _down(angle, length / 2), quat=rot, name="link")
    # joint frame orientation = world at angle 0, so the hinge coordinate reads the angle itself
    b.add_joint(JointType.REVOLUTE, -1, link, parent_frame=(pivot, (0, 0, 0, 1)),
                child_frame=((0.0, 0.0, length / 2), (0, 0, 0, 1)), axis=Y, name="hinge")
    return b.finalize()


def double_pendulum(lengths: tuple[float, float] = (1.0, 1.0), masses: tuple[float, float] = (1.0, 1.0),
                    width: float = 0.02, angles: tuple[float, float] = (0.5, 0.3),
                    pivot: tuple[float, float, float] = (0.0, 0.0, 2.0), gravity: float = 9.81) -> Model:
    """Two slender boxes in series, hinged about world y (a tree). ``angles`` are the absolute angles of
    the links from the vertical; the joint coordinates are the relative angles (MuJoCo convention)."""
    b = ModelBuilder(gravity=(0.0, 0.0, -gravity))
    p0 = np.asarray(pivot, float)
    p1 = p0 + _down(angles[0], lengths[0])
    links = []
    for k, (p, L, m, a) in enumerate(zip((p0, p1), lengths, masses, angles, strict=True)):
        rot = np.array([0.0, np.sin(a / 2), 0.0, np.cos(a / 2)])
        links.append(b.add_body(mass=m, inertia=box_inertia(m, (width, width, L)), pos=p + _down(a, L / 2),
                                quat=rot, name=f"link{k + 1}"))
    b.add_joint(JointType.REVOLUTE, -1, links[0], parent_frame=(p0, (0, 0, 0, 1)),
                child_frame=((0.0, 0.0, lengths[0] / 2), (0, 0, 0, 1)), axis=Y, name="hinge1")
    # both joint frames world-aligned at angle 0, so hinge2 reads the relative angle (MuJoCo's qpos)
    b.add_joint(JointType.REVOLUTE, links[0], links[1], parent_frame=((0.0, 0.0, -lengths[0] / 2), (0, 0, 0, 1)),
                child_frame=((0.0, 0.0, lengths[1] / 2), (0, 0, 0, 1)), axis=Y, name="hinge2")
    return b.finalize()


def _circle_intersection(c0, r0, c1, r1, upper: bool = True) -> np.ndarray:
    """Intersection of two circles in the xz plane (``upper``: the one with the larger z)."""
    c0, c1 = np.asarray(c0, float), np.asarray(c1, float)
    d = np.linalg.norm(c1 - c0)
    if d > r0 + r1 or d < abs(r0 - r1):
        raise ValueError("the links cannot be assembled in this configuration")
    a = (r0 * r0 - r1 * r1 + d * d) / (2 * d)
    h = np.sqrt(max(r0 * r0 - a * a, 0.0))
    mid = c0 + a * (c1 - c0) / d
    perp = np.array([-(c1 - c0)[2], 0.0, (c1 - c0)[0]]) / d
    p1, p2 = mid + h * perp, mid - h * perp
    return p1 if (p1[2] >= p2[2]) == upper else p2


def fourbar(ground: float = 0.3, crank: float = 0.18, coupler: float = 0.26, rocker: float = 0.24,
            crank_angle: float = -1.2, coupler_above: bool = True, linear_density: float = 2.0,
            radius: float = 0.01, height: float = 1.0, gravity: float = 9.81, actuated: bool = False,
            kp: float = 50.0, kd: float = 2.0, effort_limit: float = float("inf")) -> Model:
    """Planar four-bar linkage in the xz plane (a Grashof crank-rocker: shortest link = crank).

    Bodies: ``ground`` (fixed to the world by a FIXED joint), ``crank``, ``coupler``, ``rocker``,
    all capsules of ``linear_density`` kg/m. Joints: ``fix``, then revolutes about world y
    ``ground_crank``, ``crank_coupler``, ``coupler_rocker`` and ``rocker_ground``; none is special,
    the last one listed closes the loop. The crank starts at rest at ``crank_angle`` [rad] from the
    ground line (default: hanging below it) with the coupler-rocker joint on the upper branch
    (``coupler_above``), out of equilibrium, so the linkage swings under gravity.
    ``fourbar(crank=0.1, coupler=0.3, rocker=0.2, crank_angle=np.pi / 3, coupler_above=True)`` is
    a hard case: released above, the light crank whips round at up to 25 rad/s.
    With ``actuated=True`` the crank joint ``ground_crank`` is driven by an implicit PD position
    actuator (``kp`` [N m/rad], ``kd`` [N m s/rad], ``effort_limit`` [N m]); its target is
    ``kamino.Control.position_target`` (DoF 0 of the model).
    """
    b = ModelBuilder(gravity=(0.0, 0.0, -gravity))
    A = np.array([0.0, 0.0, height])
    Dp = A + np.array([ground, 0.0, 0.0])
    B = A + crank * np.array([np.cos(crank_angle), 0.0, np.sin(crank_angle)])
    C = _circle_intersection(B, coupler, Dp, rocker, upper=coupler_above)
    g = add_link(b, A, Dp, linear_density * ground, radius, "ground")
    cr = add_link(b, A, B, linear_density * crank, radius, "crank")
    co = add_link(b, B, C, linear_density * coupler, radius, "coupler")
    ro = add_link(b, Dp, C, linear_density * rocker, radius, "rocker")
    b.add_joint_at(JointType.FIXED, -1, g, anchor=0.5 * (A + Dp), name="fix")
    drive = Actuation(mode="position", kp=kp, kd=kd, effort_limit=effort_limit) if actuated else None
    b.add_joint_at(JointType.REVOLUTE, g, cr, anchor=A, axis=Y, name="ground_crank", actuation=drive)
    b.add_joint_at(JointType.REVOLUTE, cr, co, anchor=B, axis=Y, name="crank_coupler")
    b.add_joint_at(JointType.REVOLUTE, co, ro, anchor=C, axis=Y, name="coupler_rocker")
    b.add_joint_at(JointType.REVOLUTE, ro, g, anchor=Dp, axis=Y, name="rocker_ground")
    return b.finalize()


def slider_crank(crank: float = 0.1, rod: float = 0.3, crank_angle: float = np.deg2rad(60.0),
                 linear_density: float = 2.0, radius: float = 0.01, slider_mass: float = 0.5,
                 slider_size: float = 0.05, height: float = 1.0, gravity: float = 9.81) -> Model:
    """Slider-crank in the xz plane: a crank hinged to the world, a connecting rod, and a box slider
    on a horizontal PRISMATIC joint along x through the crank pivot. Joints ``crank_pivot``,
    ``crank_rod``, ``rod_slider`` (revolutes about y) and ``slide`` (prismatic) form one loop."""
    b = ModelBuilder(gravity=(0.0, 0.0, -gravity))
    O = np.array([0.0, 0.0, height])
    B = O + crank * np.array([np.cos(crank_angle), 0.0, np.sin(crank_angle)])
    dz = B[2] - O[2]
    S = np.array([B[0] + np.sqrt(rod * rod - dz * dz), 0.0, O[2]])
    cr = add_link(b, O, B, linear_density * crank, radius, "crank")
    ro = add_link(b, B, S, linear_density * rod, radius, "rod")
    sl = b.add_body(mass=slider_mass, inertia=box_inertia(slider_mass, (slider_size,) * 3), pos=S, name="slider")
    b.add_joint_at(JointType.REVOLUTE, -1, cr, anchor=O, axis=Y, name="crank_pivot")
    b.add_joint_at(JointType.REVOLUTE, cr, ro, anchor=B, axis=Y, name="crank_rod")
    b.add_joint_at(JointType.REVOLUTE, ro, sl, anchor=S, axis=Y, name="rod_slider")
    b.add_joint_at(JointType.PRISMATIC, -1, sl, anchor=S, axis=(1.0, 0.0, 0.0), name="slide")
    return b.finalize()


def chain_of_loops(n: int = 8, rung: float = 0.2, rail: float = 0.1, tilt: float = np.deg2rad(30.0),
                   rung_mass: float = 0.5, rail_mass: float = 0.2, radius: float = 0.005,
                   height: float = 1.0, closure: str = "revolute", gravity: float = 9.81) -> Model:
    """The planar ladder of ``n`` parallelogram loops (``benchmarks`` scene ``ladder8.xml`` for n = 8).

    A fixed top rung ``R0`` (FIXED joint to the world) at ``height``; for k = 1..n a left rail ``A{k}``
    and a right rail ``B{k}`` hang from rung ``R{k-1}``, tilted by ``tilt``, and rung ``R{k}`` hangs
    from ``A{k}``; the loop is closed by joint ``close{k}`` between ``B{k}`` and the right end of
    ``R{k}`` (``closure="revolute"``, as the other hinges, or ``"spherical"`` like MJCF's
    ``<connect>``). All hinges are about world y. In 3-D the loop closures are redundant (planar
    loops), a hard case by design; rows grow linearly with ``n``. Starts at rest, swings under gravity.
    """
    if n < 1:
        raise ValueError(f"chain_of_loops: n must be >= 1, got {n}")
    if closure not in ("revolute", "spherical"):
        raise ValueError(f"chain_of_loops: closure must be 'revolute' or 'spherical', got {closure!r}")
    b = ModelBuilder(gravity=(0.0, 0.0, -gravity))
    d = rail * np.array([np.sin(tilt), 0.0, -np.cos(tilt)])
    w = np.array([rung, 0.0, 0.0])
    left = np.array([0.0, 0.0, height])
    prev = add_link(b, left, left + w, rung_mass, radius, "R0")
    b.add_joint_at(JointType.FIXED, -1, prev, anchor=left, name="fix")
    close_type = JointType.REVOLUTE if closure == "revolute" else JointType.SPHERICAL
    for k in range(1, n + 1):
        a = add_link(b, left, left + d, rail_mass, radius, f"A{k}")
        bb = add_link(b, left + w, left + w + d, rail_mass, radius, f"B{k}")
        r = add_link(b, left + d, left + d + w, rung_mass, radius, f"R{k}")
        b.add_joint_at(JointType.REVOLUTE, prev, a, anchor=left, axis=Y, name=f"jA{k}")
        b.add_joint_at(JointType.REVOLUTE, a, r, anchor=left + d, axis=Y, name=f"jR{k}")
        b.add_joint_at(JointType.REVOLUTE, prev, bb, anchor=left + w, axis=Y, name=f"jB{k}")
        b.add_joint_at(close_type, bb, r, anchor=left + d + w, axis=Y, name=f"close{k}")
        left, prev = left + d, r
    return b.finalize()
