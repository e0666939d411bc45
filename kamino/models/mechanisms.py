"""Procedural mechanisms: pendulums, four-bar, slider-crank, the chain of loops, the Jansen walker and the Stewart
platform.

Every function returns a validated single-world :class:`kamino.Model`. All mechanisms but the Stewart platform move
in the world xz plane (hinges about world y, gravity along -z); all start at rest.
"""

from __future__ import annotations

import numpy as np

from kamino.model import Actuation, GeomType, JointType, Model, ModelBuilder
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
            kp: float = 50.0, kd: float = 2.0, effort_limit: float = float("inf"), tilt_deg: float = 0.0,
            damping: float = 0.0) -> Model:
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
    ``tilt_deg`` [deg] tilts the coupler-rocker hinge axis out of the plane (world y rotated about world x): the
    loop is then a spatial RRRR that is no Bennett linkage, rigid (mobility 0), and for a small tilt its constraint
    Jacobian has a singular value of order ``sin(tilt)`` near the planar mechanism's motion (a nearly singular
    rigid loop). Every anchor still coincides at the builder pose; only the axis is tilted.
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
    b.add_joint_at(JointType.REVOLUTE, g, cr, anchor=A, axis=Y, name="ground_crank", actuation=drive,
                   damping=damping)
    b.add_joint_at(JointType.REVOLUTE, cr, co, anchor=B, axis=Y, name="crank_coupler", damping=damping)
    tilt = np.deg2rad(float(tilt_deg))
    b.add_joint_at(JointType.REVOLUTE, co, ro, anchor=C, axis=(0.0, np.cos(tilt), np.sin(tilt)), name="coupler_rocker",
                   damping=damping)
    b.add_joint_at(JointType.REVOLUTE, ro, g, anchor=Dp, axis=Y, name="rocker_ground", damping=damping)
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


#: Jansen's link lengths ("holy numbers", in his units; :func:`jansen_walker` scales them by ``scale``)
JANSEN_LENGTHS = {"a": 38.0, "b": 41.5, "c": 39.3, "d": 40.1, "e": 55.8, "f": 39.4, "g": 36.7, "h": 65.7,
                  "i": 49.0, "j": 50.0, "k": 61.9, "l": 7.8, "m": 15.0}


def jansen_leg_points(crank_angle: float, scale: float = 0.01) -> dict[str, np.ndarray]:
    """The joint points of one Jansen leg in its plane (xz; crank axis at the origin, fixed pivot ``Y`` at
    ``(-a, -l)``), for the crank tip ``Z`` at ``crank_angle`` [rad] from +x about -y (counterclockwise in xz).

    Points: ``Z`` crank tip (radius ``m``); ``A`` = circles (Z, j) and (Y, b), upper; ``C`` = (Z, k) and
    (Y, c), lower; ``D`` apex of the rigid triangle ``Y A D`` (sides ``Y A = b``, ``A D = e``, ``Y D = d``)
    away from the crank; ``E`` = (D, f) and (C, g), away from the crank; ``F`` the foot, apex of the rigid
    triangle ``C E F`` (sides ``C E = g``, ``C F = i``, ``E F = h``), below."""
    L = {k: v * scale for k, v in JANSEN_LENGTHS.items()}
    Y = np.array([-L["a"], 0.0, -L["l"]])
    Z = L["m"] * np.array([np.cos(crank_angle), 0.0, np.sin(crank_angle)])
    A = _circle_intersection(Z, L["j"], Y, L["b"], upper=True)
    C = _circle_intersection(Z, L["k"], Y, L["c"], upper=False)
    D = _far_intersection(Y, L["d"], A, L["e"])
    E = _far_intersection(D, L["f"], C, L["g"])
    F = _circle_intersection(E, L["h"], C, L["i"], upper=False)
    return {"O": np.zeros(3), "Y": Y, "Z": Z, "A": A, "C": C, "D": D, "E": E, "F": F}


def _far_intersection(c0, r0, c1, r1) -> np.ndarray:
    """The intersection of two circles in the xz plane with the smaller x (away from a crank at the origin)."""
    p = _circle_intersection(c0, r0, c1, r1, upper=True)
    q = _circle_intersection(c0, r0, c1, r1, upper=False)
    return p if p[0] <= q[0] else q


def _add_triangle(b: ModelBuilder, pts, mass: float, name: str) -> int:
    """A rigid triangular plate with vertices ``pts`` (world), CoM at the centroid, the inertia of its three
    vertices' point masses plus a thin plate's own thickness term."""
    pts = np.asarray(pts, float)
    c = pts.mean(axis=0)
    r = pts - c
    inertia = (mass / 3.0) * sum(np.dot(v, v) * np.eye(3) - np.outer(v, v) for v in r)
    inertia = inertia + np.eye(3) * mass * 1e-4  # the plate's thickness: keeps every principal moment positive
    return b.add_body(mass=mass, inertia=inertia, pos=c, name=name)


def _phase_index(pair: int, phases: int) -> int:
    """The crank phase (of ``phases``) of leg pair ``pair``: consecutive pairs take opposite phases (``k`` and ``k +
    phases / 2`` for an even number of phases), so that either half of the walker holds opposite phases and keeps a
    foot on the ground at every crank angle; ``pair mod phases`` for an odd number."""
    p = pair % phases
    if phases % 2:
        return p
    return p // 2 + (p % 2) * (phases // 2)


def jansen_walker(legs: int = 8, phases: int | None = None, scale: float = 0.01, crank_angle: float = 0.0,
                  chassis_mass: float = 4.0,
                  linear_density: float = 0.5, radius: float = 0.03, foot_radius: float = 0.02,
                  leg_spacing: float = 0.1, drive_kd: float = 50.0, friction: float = 1.0,
                  gravity: float = 9.81) -> Model:
    """A walker of ``legs`` Jansen linkages (Strandbeest legs) on one crankshaft: a free chassis on a ground plane.

    Each leg is Jansen's linkage (:data:`JANSEN_LENGTHS` times ``scale`` [m]; :func:`jansen_leg_points`): 6 bodies
    (links ``j``, ``k``, ``c``, ``f`` as capsules of ``linear_density`` kg/m and ``radius``, the triangles ``b d e``
    and ``g h i`` as plates of the same mass per length of side) and 9 hinges about world y, so 3 planar loops per
    leg: in 3-D three rows of each loop are redundant. The legs come in mirrored pairs (the second one's x reversed);
    pair ``p`` has its crank tip at ``crank_angle + 2 pi k_p / phases`` (``phases``: a divisor of the number of
    pairs, by default the number of pairs: every pair its own phase), where consecutive pairs take opposite phases
    (:func:`_phase_index`: with four phases ``k = 0, 2, 1, 3``), so that either side of the chassis keeps a foot on
    the ground (in the order ``0, 1, 2, 3`` the feet on the ground can all lie on one side, and the four-phase walker
    rolls over within 2 s). Leg ``n`` lies in the plane ``y = (n - (legs - 1) / 2) leg_spacing``. Bodies:
    ``chassis`` (a box of ``chassis_mass``, FREE joint ``floating_base``), ``crank`` (all legs' crank tips, hinged
    to the chassis at the crank axis by the joint ``drive``), then the legs'. The drive is a VELOCITY actuator of gain
    ``drive_kd`` [N m s/rad] (its DoF is ``model.actuator_dof[0]``; a positive target turns the crank about +y, which
    walks the chassis towards +x). A SPHERE foot of ``foot_radius`` on each foot point ``F``; the lowest foot starts
    touching the ground plane (z = 0). The links' ``radius`` sets their inertia about their own axis (``m r^2 / 2``):
    at 0.01 m it is a ninth of that at 0.03 m, the Delassus rows of those spins are nine times lighter, and the
    eight-legged walker's loops closed to 2.8e-5 m over 3 s in float32 (the Warp LLT) against 7.7e-6 m at 0.03 m.

    ``legs=8`` is the 24-loop walker: 50 bodies, 74 joints, 365 joint rows."""
    if legs < 2 or legs % 2:
        raise ValueError(f"jansen_walker: legs must be an even number >= 2 (mirrored pairs), got {legs}")
    if scale <= 0:
        raise ValueError(f"jansen_walker: scale must be positive, got {scale}")
    pairs = legs // 2
    phases = pairs if phases is None else phases
    if phases < 1 or pairs % phases:
        raise ValueError(f"jansen_walker: phases must divide the {pairs} leg pairs, got {phases}")
    angles = [crank_angle + 2 * np.pi * _phase_index(p, phases) / phases for p in range(pairs)]
    leg_pts = []
    for n in range(legs):
        psi = angles[n // 2]
        if n % 2 == 0:
            leg_pts.append(jansen_leg_points(psi, scale))
        else:  # the mirrored leg: its own crank angle is pi - psi, then x -> -x
            mirror = np.array([-1.0, 1.0, 1.0])
            leg_pts.append({k: v * mirror for k, v in jansen_leg_points(np.pi - psi, scale).items()})
    lowest = min(p["F"][2] for p in leg_pts)
    height = foot_radius - lowest
    b = ModelBuilder(gravity=(0.0, 0.0, -gravity))
    width = leg_spacing * legs
    span = 2 * JANSEN_LENGTHS["a"] * scale
    O = np.array([0.0, 0.0, height])
    chassis = b.add_body(mass=chassis_mass, inertia=box_inertia(chassis_mass, (span, width, 0.05)), pos=O,
                         name="chassis")
    b.add_joint_at(JointType.FREE, -1, chassis, anchor=O, name="floating_base")
    rho = linear_density
    crank_mass = rho * (JANSEN_LENGTHS["m"] * scale * legs + width)
    crank = b.add_body(mass=crank_mass, inertia=box_inertia(crank_mass, (0.05, width, 0.05)), pos=O, name="crank")
    b.add_joint_at(JointType.REVOLUTE, chassis, crank, anchor=O, axis=Y, name="drive",
                   actuation=Actuation(mode="velocity", kd=drive_kd))
    L = {k: v * scale for k, v in JANSEN_LENGTHS.items()}
    for n, pts in enumerate(leg_pts):
        y = np.array([0.0, (n - (legs - 1) / 2) * leg_spacing, 0.0])
        P = {k: v + O + y for k, v in pts.items()}
        link_j = add_link(b, P["Z"], P["A"], rho * L["j"], radius, f"leg{n}_j")
        link_k = add_link(b, P["Z"], P["C"], rho * L["k"], radius, f"leg{n}_k")
        link_c = add_link(b, P["Y"], P["C"], rho * L["c"], radius, f"leg{n}_c")
        link_f = add_link(b, P["D"], P["E"], rho * L["f"], radius, f"leg{n}_f")
        upper = _add_triangle(b, (P["Y"], P["A"], P["D"]), rho * (L["b"] + L["d"] + L["e"]), f"leg{n}_bde")
        lower = _add_triangle(b, (P["C"], P["E"], P["F"]), rho * (L["g"] + L["h"] + L["i"]), f"leg{n}_ghi")
        for parent, child, at, name in ((crank, link_j, "Z", "crank_j"), (crank, link_k, "Z", "crank_k"),
                                        (link_j, upper, "A", "j_bde"), (chassis, upper, "Y", "frame_bde"),
                                        (chassis, link_c, "Y", "frame_c"), (link_k, link_c, "C", "k_c"),
                                        (link_c, lower, "C", "c_ghi"), (upper, link_f, "D", "bde_f"),
                                        (link_f, lower, "E", "f_ghi")):
            b.add_joint_at(JointType.REVOLUTE, parent, child, anchor=P[at], axis=Y, name=f"leg{n}_{name}")
        b.add_geom(GeomType.SPHERE, lower, size=(foot_radius, 0.0, 0.0), pos=P["F"] - (P["C"] + P["E"] + P["F"]) / 3,
                   friction=friction, group=2, mask=1, name=f"leg{n}_foot")
    b.add_geom(GeomType.PLANE, -1, friction=friction, group=1, name="ground")
    return b.finalize()


def stewart_platform(base_radius: float = 0.25, platform_radius: float = 0.15, base_height: float = 0.2,
                     platform_height: float = 0.65, base_spread_deg: float = 12.0, platform_spread_deg: float = 12.0,
                     platform_mass: float = 4.0, leg_mass: float = 0.4, radius: float = 0.015, kp: float = 2000.0,
                     kd: float = 100.0, damping: float = 0.1, gravity: float = 9.81) -> Model:
    """A Stewart platform (6-UPS): a platform carried by six legs on a base fixed to the world.

    Base anchors ``B_i`` on a circle of ``base_radius`` at ``base_height``, in pairs at ``120 k -+ base_spread_deg``
    [deg]; platform anchors ``P_i`` on a circle of ``platform_radius`` at ``platform_height``, in pairs at ``120 k +
    60 -+ (60 - platform_spread_deg)``, so that leg ``2k`` and leg ``2k - 1`` meet the platform side by side and
    every leg leans. Leg ``i``: a lower link ``leg{i}_lower`` from ``B_i`` to 55 % of the way to ``P_i`` on a
    UNIVERSAL joint ``leg{i}_base`` to the world (axes: horizontal and across the leg: the leg cannot spin about
    itself), an upper link ``leg{i}_upper`` from 45 % of the way to ``P_i`` on a PRISMATIC joint ``leg{i}_slide``
    along the leg (a POSITION actuator of gains ``kp`` [N/m], ``kd`` [N s/m]; its coordinate is the leg's
    extension from the builder pose), and a SPHERICAL joint ``leg{i}_top`` to the ``platform`` (a flat box of
    ``platform_mass``). Links are capsules of ``leg_mass`` kg and ``radius``; ``damping`` [N m s/rad] is a viscous
    damping on both DoFs of each universal joint.

    Bodies: 12 links and the platform (13); joints: 18 (6 legs of 3); 78 body coordinates, 72 constraint rows:
    six DoFs, the legs' extensions, and five independent loops through the platform (none redundant). With the
    actuators holding zero extension the platform sags under gravity by about its weight over ``6 kp``."""
    b = ModelBuilder(gravity=(0.0, 0.0, -gravity))
    ups = []
    for i in range(6):
        k, sign = divmod(i, 2)
        sign = 2 * sign - 1
        beta = np.deg2rad(120.0 * k + sign * base_spread_deg)
        if sign < 0:  # leg 2k meets leg 2k - 1 around 120 k - 60
            phi = np.deg2rad(120.0 * k - 60.0 + platform_spread_deg)
        else:  # leg 2k + 1 meets leg 2k + 2 around 120 k + 60
            phi = np.deg2rad(120.0 * k + 60.0 - platform_spread_deg)
        B = np.array([base_radius * np.cos(beta), base_radius * np.sin(beta), base_height])
        P = np.array([platform_radius * np.cos(phi), platform_radius * np.sin(phi), platform_height])
        ups.append((B, P))
    center = np.array([0.0, 0.0, platform_height])
    side = 2.0 * platform_radius
    platform = b.add_body(mass=platform_mass, inertia=box_inertia(platform_mass, (side, side, 0.03)), pos=center,
                          name="platform")
    drive = Actuation(mode="position", kp=kp, kd=kd)
    for i, (B, P) in enumerate(ups):
        d = (P - B) / np.linalg.norm(P - B)
        lower = add_link(b, B, B + 0.55 * (P - B), 0.5 * leg_mass, radius, f"leg{i}_lower")
        upper = add_link(b, B + 0.45 * (P - B), P, 0.5 * leg_mass, radius, f"leg{i}_upper")
        a1 = np.cross((0.0, 0.0, 1.0), d)
        a1 = a1 / np.linalg.norm(a1)
        a2 = np.cross(d, a1)
        b.add_joint_at(JointType.UNIVERSAL, -1, lower, anchor=B, axis=a1, axis2=a2, name=f"leg{i}_base",
                       damping=damping)
        b.add_joint_at(JointType.PRISMATIC, lower, upper, anchor=B + 0.5 * (P - B), axis=d, name=f"leg{i}_slide",
                       actuation=drive)
        b.add_joint_at(JointType.SPHERICAL, upper, platform, anchor=P, name=f"leg{i}_top")
    return b.finalize()
