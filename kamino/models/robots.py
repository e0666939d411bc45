"""Procedural robots of the four robot classes of the Kamino paper (Table 1).

Each function returns a validated single-world :class:`kamino.Model` built in code. We do not have
the real robots' data: each model is *of the class of* the robot it is named after (same counts of
bodies, actuated and passive joints and independent loops, plausible dimensions and masses), not a
replica. docs/robots.md describes the topologies, dimensions, masses, gains and actuated ranges.

Conventions shared by all four: x forward, y left, z up, gravity -z, every joint added with
:meth:`ModelBuilder.add_joint_at`, so every joint coordinate is zero at the builder pose, which is
the nominal pose (position targets 0 hold it). Every loop closes exactly at that pose. Actuated
joints are revolute with an implicit PD position actuator (``kamino.Actuation("position", kp, kd,
effort_limit)``), armature and limits; the mechanisms assemble over the whole box of actuated
limits (each planar four-bar is checked at build time to keep its transmission angle within
[30, 150] deg over its crank range). Floating robots stand on a ground PLANE at z = 0 with their
feet just touching it; their collision geoms collide with the ground only (no self-collision).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

import numpy as np

from kamino.hostmath import matrix_to_quat
from kamino.model import Actuation, GeomType, JointType, Model, ModelBuilder
from kamino.models.shapes import box_inertia, capsule_inertia, frame_along

X = np.array([1.0, 0.0, 0.0])
Y = np.array([0.0, 1.0, 0.0])
Z = np.array([0.0, 0.0, 1.0])

#: Collision groups: robot geoms (group 2) only touch geoms whose group has bit 1 (the ground).
_GROUND_GROUP, _ROBOT_GROUP = 1, 2
_MIN_TRANSMISSION_DEG = 30.0


def _v(*xyz: float) -> np.ndarray:
    return np.array(xyz, dtype=float)


def _unit(v) -> np.ndarray:
    v = np.asarray(v, dtype=float)
    return v / np.linalg.norm(v)


def _rotate(v, axis, angle: float) -> np.ndarray:
    """``v`` rotated by ``angle`` about the unit ``axis`` (Rodrigues)."""
    v, k = np.asarray(v, float), _unit(axis)
    return v * np.cos(angle) + np.cross(k, v) * np.sin(angle) + k * np.dot(k, v) * (1.0 - np.cos(angle))


@dataclasses.dataclass(frozen=True)
class _Servo:
    """An actuated revolute joint's drive: PD gains, effort limit, symmetric range [rad], armature."""

    kp: float
    kd: float
    effort: float
    range: float
    armature: float = 0.02

    def joint_args(self) -> dict:
        return {"actuation": Actuation("position", kp=self.kp, kd=self.kd, effort_limit=self.effort),
                "limits": (-self.range, self.range), "armature": self.armature}


def _check_fourbar(A, B, C, D, axis, crank_range: tuple[float, float], name: str,
                   min_deg: float = _MIN_TRANSMISSION_DEG) -> None:
    """Raise ``ValueError`` unless the planar four-bar ground ``A-D``, crank ``A-B``, coupler ``B-C`` and
    rocker ``D-C`` (hinges along ``axis``; points projected on the plane normal to it) assembles on the
    builder's branch with a transmission angle in ``[min_deg, 180 - min_deg]`` for every crank
    rotation in ``crank_range`` [rad] about ``A``, relative to the builder pose. A transmission angle
    bounded away from 0 and 180 deg along the range also keeps the linkage on its builder branch."""
    n = _unit(axis)
    P = [np.asarray(p, float) - np.dot(np.asarray(p, float), n) * n for p in (A, B, C, D)]
    A, B, C, D = P
    b, c = np.linalg.norm(C - B), np.linalg.norm(C - D)
    lo_cos = np.cos(np.deg2rad(180.0 - min_deg))
    hi_cos = np.cos(np.deg2rad(min_deg))
    for th in np.linspace(crank_range[0], crank_range[1], 61):
        Bt = A + _rotate(B - A, n, th)
        d = np.linalg.norm(Bt - D)
        cos_mu = (b * b + c * c - d * d) / (2.0 * b * c)
        if not (lo_cos <= cos_mu <= hi_cos):
            mu = np.degrees(np.arccos(np.clip(cos_mu, -1.0, 1.0))) if abs(cos_mu) <= 1 else float("nan")
            raise ValueError(f"four-bar {name!r}: transmission angle {mu:.1f} deg at crank rotation {th:+.2f} rad "
                             f"is outside [{min_deg}, {180 - min_deg}] deg (or the loop cannot assemble)")


class _Parts:
    """A :class:`ModelBuilder` with shape helpers; bodies are placed at their CoM in world coordinates."""

    def __init__(self, gravity: float):
        self.b = ModelBuilder(gravity=(0.0, 0.0, -gravity))
        self.com: dict[int, np.ndarray] = {}

    # -- bodies ----------------------------------------------------------------------
    def box(self, name: str, center, size, mass: float) -> int:
        i = self.b.add_body(mass=mass, inertia=box_inertia(mass, tuple(size)), pos=center, name=name)
        self.com[i] = np.asarray(center, float)
        return i

    def rod(self, name: str, p0, p1, mass: float, radius: float, com: float = 0.5) -> int:
        """A capsule-like link from ``p0`` to ``p1`` whose CoM is at fraction ``com`` along it (a motor
        near one end); inertia of the uniform capsule about its CoM, local x along the link."""
        p0, p1 = np.asarray(p0, float), np.asarray(p1, float)
        c = p0 + com * (p1 - p0)
        length = float(np.linalg.norm(p1 - p0))
        i = self.b.add_body(mass=mass, inertia=capsule_inertia(mass, radius, length), pos=c,
                            quat=frame_along(p1 - p0), name=name)
        self.com[i] = c
        return i

    def crank(self, name: str, pivot, tip, axis, mass: float, hub: float) -> int:
        """A servo output crank: a hub disc of radius ``hub`` about ``axis`` at ``pivot`` (the gear
        output stage) with a lever to ``tip``; CoM a quarter of the way to the tip."""
        pivot, tip = np.asarray(pivot, float), np.asarray(tip, float)
        a = float(np.linalg.norm(tip - pivot))
        n = _unit(axis)
        lever = tip - pivot - np.dot(tip - pivot, n) * n
        u = lever / np.linalg.norm(lever)
        R = np.column_stack([n, u, np.cross(n, u)])
        t = 0.5 * hub  # hub thickness
        inertia = mass * np.array([hub * hub / 2 + a * a / 16, hub * hub / 4 + t * t / 12,
                                   hub * hub / 4 + t * t / 12 + a * a / 16])
        c = pivot + 0.25 * (tip - pivot)
        i = self.b.add_body(mass=mass, inertia=inertia, pos=c, quat=matrix_to_quat(R), name=name)
        self.com[i] = c
        return i

    def blob(self, name: str, center, radii, mass: float) -> int:
        """A solid ellipsoid with semi-axes ``radii`` along x, y, z."""
        a, b, c = radii
        inertia = 0.2 * mass * np.array([b * b + c * c, a * a + c * c, a * a + b * b])
        i = self.b.add_body(mass=mass, inertia=inertia, pos=center, name=name)
        self.com[i] = np.asarray(center, float)
        return i

    # -- joints ----------------------------------------------------------------------
    def hinge(self, name: str, parent: int, child: int, anchor, axis, servo: _Servo | None = None) -> int:
        extra = servo.joint_args() if servo is not None else {}
        return self.b.add_joint_at(JointType.REVOLUTE, parent, child, anchor=anchor, axis=_unit(axis), name=name,
                                   **extra)

    def fixed(self, name: str, parent: int, child: int) -> int:
        return self.b.add_joint_at(JointType.FIXED, parent, child, anchor=self.com[child], name=name)

    def ball(self, name: str, parent: int, child: int, anchor) -> int:
        return self.b.add_joint_at(JointType.SPHERICAL, parent, child, anchor=anchor, name=name)

    def cardan(self, name: str, parent: int, child: int, anchor, axis, axis2) -> int:
        return self.b.add_joint_at(JointType.UNIVERSAL, parent, child, anchor=anchor, axis=_unit(axis),
                                   axis2=_unit(axis2), name=name)

    # -- linkages --------------------------------------------------------------------
    def fourbar(self, name: str, ground: int, output: int, A, B, C, D, axis, servo: _Servo | None,
                crank_mass: float, rod_mass: float, radius: float, hub: float = 0.0, crank: int | None = None,
                crank_range: tuple[float, float] | None = None, pivot: str | None = None) -> tuple[int, int]:
        """A planar four-bar on ``ground``: crank ``A->B`` (a new body hinged at ``A``, driven by ``servo``;
        or, with ``crank=``, an existing body already hinged to ``ground`` at ``A``: a follower linkage),
        coupler ``B->C`` (a new body) and ``output`` hinged to ``ground`` at ``D`` and to the coupler at
        ``C``. All hinges along ``axis``; ``pivot`` names the output hinge (default ``<name>_pivot``).
        Returns ``(crank, coupler)``; checks the transmission angle over the crank range first."""
        rng = crank_range if crank_range is not None else ((-servo.range, servo.range) if servo else (-0.6, 0.6))
        _check_fourbar(A, B, C, D, axis, rng, name)
        if crank is None:
            crank = (self.crank(f"{name}_crank", A, B, axis, crank_mass, hub) if hub > 0
                     else self.rod(f"{name}_crank", A, B, crank_mass, radius))
            self.hinge(f"{name}_drive", ground, crank, A, axis, servo)
        coupler = self.rod(f"{name}_rod", B, C, rod_mass, radius)
        self.hinge(f"{name}_crank_rod", crank, coupler, B, axis)
        self.hinge(f"{name}_rod_out", coupler, output, C, axis)
        self.hinge(pivot or f"{name}_pivot", ground, output, D, axis)
        return crank, coupler

    # -- geoms -----------------------------------------------------------------------
    def ground(self, friction: float) -> None:
        self.b.add_geom(GeomType.PLANE, -1, friction=friction, group=_GROUND_GROUP, name="ground")

    def foot(self, name: str, body: int, center, half, friction: float) -> None:
        """A BOX contact geom with half extents ``half`` centred at world ``center`` (body axes = world)."""
        self.b.add_geom(GeomType.BOX, body, size=half, pos=np.asarray(center, float) - self.com[body],
                        friction=friction, group=_ROBOT_GROUP, mask=_GROUND_GROUP, name=name)

    def finalize(self) -> Model:
        return self.b.finalize()


def _free_base(p: _Parts, base: int) -> None:
    p.b.add_joint_at(JointType.FREE, -1, base, anchor=p.com[base], name="floating_base")


# ---------------------------------------------------------------------------------------
# DR Legs: biped with serial-parallel hybrid legs
# ---------------------------------------------------------------------------------------

def dr_legs(ground: bool | Callable[[ModelBuilder], object] = True, hip_gains: tuple[float, float] = (300.0, 8.0),
            knee_gains: tuple[float, float] = (300.0, 8.0), ankle_gains: tuple[float, float] = (150.0, 4.0),
            armature: float = 0.03, friction: float = 1.0, gravity: float = 9.81) -> Model:
    """A biped of the class of Disney Research's legged robots with parallel leg mechanisms ("DR Legs"):
    serial hips, then four-bar driven knee and ankle (serial-parallel hybrid legs), about 17 kg, 0.84 m.

    Counts: 31 bodies (pelvis + 15 per leg); 37 joints: a FREE joint world -> pelvis, 12 actuated
    and 24 passive REVOLUTE joints; 6 independent loops (3 per leg). Per leg (``l_``/``r_`` prefix):

    - ``hip_yaw`` (z), ``hip_roll`` (x), ``hip_pitch`` (y): serial, actuated at the hip.
    - knee: ``knee_drive`` crank on the thigh next to the hip (actuated), rod to a lever behind the
      knee on the shank; with the passive ``knee`` hinge a planar four-bar (loop 1).
    - ankle pitch: ``ankle_pitch_drive`` crank on the upper shank (actuated), rod to a lever on the
      ankle cross, which pitches on the passive ``ankle_pitch`` hinge: a planar four-bar (loop 2).
    - ankle roll: the foot rolls on the cross (passive ``ankle_roll``). ``ankle_roll_drive`` crank on
      the shank (actuated) pushes a rod with a cardan (2 revolutes) at the crank and a gimbal
      (3 revolutes) at the foot: a spatial loop of 8 revolutes through the cross (loop 3).

    Box foot contact geoms rest on the ground plane (``ground=True``; ``False``: no ground; a callable adds its own
    ground geoms to the builder instead, at z = 0 under the feet, e.g. a heightfield:
    ``lambda b: kamino.envs.terrain.add_terrain(b, terrain)``). Actuated ranges [rad]:
    hip yaw ±0.5, hip roll ±0.4, hip pitch ±1.0, knee drive ±0.6, ankle pitch drive ±0.6, ankle
    roll drive ±0.5. Gains ``(kp [N m/rad], kd [N m s/rad])`` per group; effort limits 80 N m
    (hip, knee) and 40 N m (ankle); ``armature`` [kg m^2] on every actuated joint; ``friction`` of
    the foot and ground geoms; ``gravity`` [m/s^2].
    """
    p = _Parts(gravity)
    hip = _Servo(hip_gains[0], hip_gains[1], 80.0, 1.0, armature)
    knee = _Servo(knee_gains[0], knee_gains[1], 80.0, 0.6, armature)
    ankle = _Servo(ankle_gains[0], ankle_gains[1], 40.0, 0.6, armature)

    pelvis = p.box("pelvis", _v(0.0, 0.0, 0.77), (0.16, 0.32, 0.14), 6.0)
    _free_base(p, pelvis)
    beta = np.deg2rad(15.0)  # thigh forward / shank backward from the vertical
    L = 0.28  # thigh and shank length
    e_t = _v(np.sin(beta), 0.0, -np.cos(beta))  # hip -> knee
    e_s = _v(-np.sin(beta), 0.0, -np.cos(beta))  # knee -> ankle
    back_t = _v(-np.cos(beta), 0.0, -np.sin(beta))  # backwards, normal to the thigh
    back_s = _v(-np.cos(beta), 0.0, np.sin(beta))  # backwards, normal to the shank
    ankle_z = 0.075
    for side, s in (("l", 1.0), ("r", -1.0)):
        y = s * 0.10
        A = _v(0.0, y, ankle_z)
        K = A - L * e_s
        H = K - L * e_t
        top = _v(0.0, y, 0.70)
        hip_yaw = p.rod(f"{side}_hip_yaw_link", top, H, 0.6, 0.035)
        p.hinge(f"{side}_hip_yaw", pelvis, hip_yaw, top, Z, dataclasses.replace(hip, range=0.5))
        hip_roll = p.box(f"{side}_hip_roll_link", H, (0.09, 0.07, 0.09), 1.0)
        p.hinge(f"{side}_hip_roll", hip_yaw, hip_roll, H, X, dataclasses.replace(hip, range=0.4))
        thigh = p.rod(f"{side}_thigh", H, K, 1.5, 0.04, com=0.35)
        p.hinge(f"{side}_hip_pitch", hip_roll, thigh, H, Y, hip)
        shank = p.rod(f"{side}_shank", K, A, 1.0, 0.03, com=0.3)
        # loop 1: knee four-bar on the thigh (inner side), crank next to the hip, lever behind the knee
        dy = _v(0.0, -s * 0.035, 0.0)
        Q = H + 0.06 * e_t + dy
        p.fourbar(f"{side}_knee", thigh, shank, Q, Q + 0.045 * back_t, K + 0.05 * back_t + dy, K + dy, Y, knee,
                  crank_mass=0.25, rod_mass=0.08, radius=0.012, hub=0.035, pivot=f"{side}_knee")
        cross = p.box(f"{side}_ankle_cross", A, (0.05, 0.05, 0.05), 0.2)
        # loop 2: ankle pitch four-bar on the shank (inner side)
        dy = _v(0.0, -s * 0.03, 0.0)
        C1 = K + 0.06 * e_s + dy
        p.fourbar(f"{side}_ankle_pitch", shank, cross, C1, C1 + 0.04 * back_s, A + 0.045 * back_s + dy, A + dy, Y,
                  ankle, crank_mass=0.15, rod_mass=0.06, radius=0.01, hub=0.03, pivot=f"{side}_ankle_pitch")
        foot_c = _v(0.025, y, 0.0175)
        foot = p.box(f"{side}_foot", foot_c, (0.20, 0.09, 0.035), 0.45)
        p.hinge(f"{side}_ankle_roll", cross, foot, A, X)
        p.foot(f"{side}_sole", foot, foot_c, (0.10, 0.045, 0.0175), friction)
        # loop 3: spatial ankle roll drive on the outer side: crank (x) -> cardan -> rod -> gimbal -> foot
        C2 = A - 0.13 * e_s
        T = C2 + _v(0.0, s * 0.035, 0.0)
        P = A + _v(0.0, s * 0.04, 0.0)
        d = _unit(P - T)
        crank = p.crank(f"{side}_ankle_roll_crank", C2, T, X, 0.15, 0.03)
        p.hinge(f"{side}_ankle_roll_drive", shank, crank, C2, X, dataclasses.replace(ankle, range=0.5))
        ucross = p.box(f"{side}_roll_cardan", T, (0.03, 0.03, 0.03), 0.06)
        p.hinge(f"{side}_roll_cardan_x", crank, ucross, T, X)
        rod = p.rod(f"{side}_roll_rod", T, P, 0.05, 0.008)
        p.hinge(f"{side}_roll_cardan_y", ucross, rod, T, np.cross(X, d))
        g1 = p.box(f"{side}_roll_gimbal_outer", P, (0.03, 0.03, 0.03), 0.06)
        p.hinge(f"{side}_roll_gimbal_spin", rod, g1, P, d)
        g2 = p.box(f"{side}_roll_gimbal_inner", P, (0.03, 0.03, 0.03), 0.06)
        p.hinge(f"{side}_roll_gimbal_y", g1, g2, P, np.cross(d, X))
        p.hinge(f"{side}_roll_gimbal_x", g2, foot, P, X)
    if callable(ground):
        ground(p.b)
    elif ground:
        p.ground(friction)
    return p.finalize()


# ---------------------------------------------------------------------------------------
# BD-X: 14-DoF tree biped
# ---------------------------------------------------------------------------------------

def bdx(ground: bool = True, leg_gains: tuple[float, float] = (400.0, 8.0),
        neck_gains: tuple[float, float] = (150.0, 3.0), armature: float = 0.02, friction: float = 1.0,
        gravity: float = 9.81) -> Model:
    """A tree biped of the class of Disney's BD-X character robot: about 15.5 kg, 0.97 m to the top of the head.

    Counts: 21 bodies; 21 joints: a FREE joint world -> ``pelvis``, 14 actuated REVOLUTE joints (per
    leg ``hip_yaw`` z, ``hip_roll`` x, ``hip_pitch`` y, ``knee`` y, ``ankle`` y; in the neck
    ``neck_pitch`` y, ``head_pitch`` y, ``head_yaw`` z, ``head_roll`` x) and 6 passive FIXED joints
    attaching ``battery``, ``electronics`` and ``speaker`` to the pelvis, a ``visor`` and two
    ``antenna`` links to the head; no loops (a tree). The feet carry BOX contact geoms resting on the
    ground plane (``ground=True``).

    Actuated ranges [rad]: hip yaw ±0.6, hip roll ±0.4, hip pitch ±1.2, knee ±1.2, ankle ±0.8,
    neck and head pitch ±0.8, head yaw ±1.2, head roll ±0.5. Gains ``(kp [N m/rad], kd [N m s/rad])``
    for the legs and the neck; effort limits 40 N m (legs) and 10 N m (neck); ``armature`` [kg m^2] on
    every actuated joint; ``friction`` of the foot and ground geoms; ``gravity`` [m/s^2].
    """
    p = _Parts(gravity)
    leg = _Servo(leg_gains[0], leg_gains[1], 40.0, 1.2, armature)
    neck = _Servo(neck_gains[0], neck_gains[1], 10.0, 0.8, armature)

    pelvis = p.box("pelvis", _v(0.0, 0.0, 0.58), (0.26, 0.20, 0.12), 4.5)
    _free_base(p, pelvis)
    battery = p.box("battery", _v(-0.10, 0.0, 0.63), (0.08, 0.14, 0.08), 1.2)
    p.fixed("battery_mount", pelvis, battery)
    electronics = p.box("electronics", _v(0.02, 0.0, 0.665), (0.14, 0.12, 0.05), 0.6)
    p.fixed("electronics_mount", pelvis, electronics)
    speaker = p.box("speaker", _v(0.0, 0.0, 0.50), (0.08, 0.08, 0.04), 0.2)
    p.fixed("speaker_mount", pelvis, speaker)
    for side, s in (("l", 1.0), ("r", -1.0)):
        y = s * 0.07
        hy = _v(0.0, y, 0.52)
        hp = _v(0.0, y, 0.46)
        K = _v(0.04, y, 0.26)
        A = _v(0.0, y, 0.06)
        hip_yaw = p.rod(f"{side}_hip_yaw_link", hy, hp, 0.5, 0.035)
        p.hinge(f"{side}_hip_yaw", pelvis, hip_yaw, hy, Z, dataclasses.replace(leg, range=0.6))
        hip_roll = p.box(f"{side}_hip_roll_link", hp, (0.07, 0.07, 0.07), 0.6)
        p.hinge(f"{side}_hip_roll", hip_yaw, hip_roll, hp, X, dataclasses.replace(leg, range=0.4))
        thigh = p.rod(f"{side}_thigh", hp, K, 1.0, 0.035, com=0.4)
        p.hinge(f"{side}_hip_pitch", hip_roll, thigh, hp, Y, leg)
        shin = p.rod(f"{side}_shin", K, A, 0.6, 0.03, com=0.4)
        p.hinge(f"{side}_knee", thigh, shin, K, Y, leg)
        foot_c = _v(0.02, y, 0.02)
        foot = p.box(f"{side}_foot", foot_c, (0.17, 0.08, 0.04), 0.45)
        p.hinge(f"{side}_ankle", shin, foot, A, Y, dataclasses.replace(leg, range=0.8))
        p.foot(f"{side}_sole", foot, foot_c, (0.085, 0.04, 0.02), friction)
    n0, n1, n2 = _v(0.10, 0.0, 0.64), _v(0.14, 0.0, 0.76), _v(0.12, 0.0, 0.86)
    neck_lower = p.rod("neck_lower", n0, n1, 0.5, 0.03)
    p.hinge("neck_pitch", pelvis, neck_lower, n0, Y, neck)
    neck_upper = p.rod("neck_upper", n1, n2, 0.4, 0.03)
    p.hinge("head_pitch", neck_lower, neck_upper, n1, Y, neck)
    head_pan = p.box("head_pan", n2 + _v(0.0, 0.0, 0.02), (0.05, 0.05, 0.04), 0.3)
    p.hinge("head_yaw", neck_upper, head_pan, n2, Z, dataclasses.replace(neck, range=1.2))
    head = p.box("head", _v(0.17, 0.0, 0.92), (0.16, 0.14, 0.10), 1.2)
    p.hinge("head_roll", head_pan, head, n2 + _v(0.0, 0.0, 0.04), X, dataclasses.replace(neck, range=0.5))
    visor = p.box("visor", _v(0.255, 0.0, 0.93), (0.02, 0.12, 0.05), 0.1)
    p.fixed("visor_mount", head, visor)
    for side, s in (("l", 1.0), ("r", -1.0)):
        antenna = p.rod(f"{side}_antenna", _v(0.12, s * 0.05, 0.97), _v(0.10, s * 0.08, 1.05), 0.08, 0.02)
        p.fixed(f"{side}_antenna_mount", head, antenna)
    if ground:
        p.ground(friction)
    return p.finalize()


# ---------------------------------------------------------------------------------------
# Olaf: character biped with four-bar couplers in jaw, shoulders and eyes
# ---------------------------------------------------------------------------------------

def olaf(ground: bool = True, leg_gains: tuple[float, float] = (200.0, 5.0),
         neck_gains: tuple[float, float] = (40.0, 1.0), arm_gains: tuple[float, float] = (10.0, 0.3),
         face_gains: tuple[float, float] = (2.0, 0.05), armature: float = 0.01, friction: float = 1.0,
         gravity: float = 9.81) -> Model:
    """A biped character of the class of Disney's Olaf robot: a snowman whose short legs hide under the
    lower snowball, about 16 kg, 0.91 m to the top of the head.

    Counts: 36 bodies; 41 joints: a FREE joint world -> ``pelvis`` (the lower and middle snowballs),
    25 actuated and 15 passive REVOLUTE joints; 5 independent loops, each a planar four-bar whose
    crank is actuated and whose coupler ("rod") and output hinge are passive:

    - legs (12 actuated, serial): per leg ``hip_yaw`` z, ``hip_roll`` x, ``hip_pitch`` y, ``knee`` y,
      ``ankle_pitch`` y, ``ankle_roll`` x; BOX contact geoms under the feet (``ground=True``);
    - neck (3 actuated): ``neck_yaw`` z, ``neck_pitch`` y, ``head_roll`` x;
    - jaw (loop 1): ``jaw_drive`` crank on the head, rod, jaw hinged to the head (``jaw_pivot``);
    - shoulders (loops 2, 3): per arm ``shoulder_roll`` (x, actuated) carries a four-bar whose
      ``shoulder_drive`` crank swings the stick arm about y (``shoulder_pivot``);
    - eyes (loops 4, 5): per eye ``eye_yaw`` (z, actuated) carries a four-bar whose ``eye_drive``
      crank pitches the eyeball (``eye_pivot``, y); one actuated ``eyelid`` (y) for both eyes.

    Actuated ranges [rad]: hip yaw ±0.5, hip roll ±0.4, hip pitch, knee, ankle pitch ±1.0, ankle
    roll ±0.4, neck ±0.6, shoulder roll and drives, jaw, eye drives and eyelid ±0.6, eye yaw ±0.5.
    Gains ``(kp [N m/rad], kd [N m s/rad])`` for legs, neck, arms and face; effort limits 40, 8, 5 and
    2 N m; ``armature`` [kg m^2] on the leg and neck servos (half of it on the arm servos, a fifth on
    the face servos); ``friction`` of the foot and ground geoms; ``gravity`` [m/s^2].
    """
    p = _Parts(gravity)
    leg = _Servo(leg_gains[0], leg_gains[1], 40.0, 1.0, armature)
    neck = _Servo(neck_gains[0], neck_gains[1], 8.0, 0.6, armature)
    arm_servo = _Servo(arm_gains[0], arm_gains[1], 5.0, 0.6, 0.5 * armature)
    face = _Servo(face_gains[0], face_gains[1], 2.0, 0.6, 0.2 * armature)

    pelvis = p.blob("pelvis", _v(0.0, 0.0, 0.46), (0.17, 0.17, 0.22), 7.0)
    _free_base(p, pelvis)
    beta = 0.25
    for side, s in (("l", 1.0), ("r", -1.0)):
        y = s * 0.08
        hy, hp = _v(0.0, y, 0.33), _v(0.0, y, 0.29)
        K = hp + 0.11 * _v(np.sin(beta), 0.0, -np.cos(beta))
        A = K + 0.11 * _v(-np.sin(beta), 0.0, -np.cos(beta))
        hip_yaw = p.rod(f"{side}_hip_yaw_link", hy, hp, 0.4, 0.03)
        p.hinge(f"{side}_hip_yaw", pelvis, hip_yaw, hy, Z, dataclasses.replace(leg, range=0.5))
        hip_roll = p.box(f"{side}_hip_roll_link", hp, (0.06, 0.06, 0.06), 0.5)
        p.hinge(f"{side}_hip_roll", hip_yaw, hip_roll, hp, X, dataclasses.replace(leg, range=0.4))
        thigh = p.rod(f"{side}_thigh", hp, K, 0.8, 0.035)
        p.hinge(f"{side}_hip_pitch", hip_roll, thigh, hp, Y, leg)
        shin = p.rod(f"{side}_shin", K, A, 0.6, 0.03)
        p.hinge(f"{side}_knee", thigh, shin, K, Y, leg)
        ankle = p.box(f"{side}_ankle_link", A, (0.05, 0.05, 0.05), 0.2)
        p.hinge(f"{side}_ankle_pitch", shin, ankle, A, Y, leg)
        foot_c = _v(A[0] + 0.02, y, 0.02)
        foot = p.box(f"{side}_foot", foot_c, (0.18, 0.11, 0.04), 0.5)
        p.hinge(f"{side}_ankle_roll", ankle, foot, A, X, dataclasses.replace(leg, range=0.4))
        p.foot(f"{side}_sole", foot, foot_c, (0.09, 0.055, 0.02), friction)
    n0 = _v(0.0, 0.0, 0.70)
    neck_yaw = p.box("neck_yaw_link", n0 + _v(0.0, 0.0, 0.015), (0.06, 0.06, 0.03), 0.25)
    p.hinge("neck_yaw", pelvis, neck_yaw, n0, Z, neck)
    n1 = n0 + _v(0.0, 0.0, 0.03)
    neck_pitch = p.box("neck_pitch_link", n1 + _v(0.0, 0.0, 0.015), (0.06, 0.06, 0.03), 0.25)
    p.hinge("neck_pitch", neck_yaw, neck_pitch, n1, Y, neck)
    n2 = n1 + _v(0.0, 0.0, 0.03)
    head = p.blob("head", _v(0.03, 0.0, 0.83), (0.12, 0.09, 0.08), 1.4)
    p.hinge("head_roll", neck_pitch, head, n2, X, neck)
    # jaw (loop 1): planar four-bar beside the mouth
    Dj = _v(0.0, 0.0, 0.79)
    jaw = p.box("jaw", _v(0.09, 0.0, 0.77), (0.12, 0.12, 0.03), 0.15)
    dy = _v(0.0, 0.06, 0.0)
    Aj = Dj + _v(-0.03, 0.0, 0.035) + dy
    p.fourbar("jaw", head, jaw, Aj, Aj + _v(-0.02, 0.0, 0.0), Dj + _v(-0.02, 0.0, -0.012) + dy, Dj + dy, Y, face,
              crank_mass=0.04, rod_mass=0.02, radius=0.006, hub=0.015, pivot="jaw_pivot")
    # shoulders (loops 2, 3): roll carrier, four-bar driven stick arm
    for side, s in (("l", 1.0), ("r", -1.0)):
        S = _v(0.0, s * 0.125, 0.60)
        carrier = p.box(f"{side}_shoulder", S + _v(0.0, s * 0.02, 0.0), (0.04, 0.04, 0.04), 0.1)
        p.hinge(f"{side}_shoulder_roll", pelvis, carrier, S, X, arm_servo)
        Da = S + _v(0.0, s * 0.04, 0.0)
        arm = p.rod(f"{side}_arm", Da, Da + _v(0.02, s * 0.20, -0.12), 0.12, 0.012, com=0.45)
        Aa = Da + _v(0.0, 0.0, 0.03)
        p.fourbar(f"{side}_shoulder", carrier, arm, Aa, Aa + _v(-0.015, 0.0, 0.0), Da + _v(-0.018, 0.0, 0.004), Da,
                  Y, arm_servo, crank_mass=0.04, rod_mass=0.03, radius=0.008, hub=0.015,
                  pivot=f"{side}_shoulder_pivot")
    # eyes (loops 4, 5): yaw carrier, four-bar driven eyeball pitch; one eyelid for both eyes
    for side, s in (("l", 1.0), ("r", -1.0)):
        E = _v(0.12, s * 0.035, 0.86)
        carrier = p.box(f"{side}_eye_carrier", E + _v(-0.025, 0.0, 0.0), (0.03, 0.03, 0.03), 0.05)
        p.hinge(f"{side}_eye_yaw", head, carrier, E, Z, dataclasses.replace(face, range=0.5))
        eyeball = p.blob(f"{side}_eyeball", E, (0.02, 0.02, 0.02), 0.05)
        dy = _v(0.0, s * 0.012, 0.0)
        Ae = E + _v(-0.035, 0.0, 0.0) + dy
        p.fourbar(f"{side}_eye", carrier, eyeball, Ae, Ae + _v(0.0, 0.0, 0.012), E + _v(0.0, 0.0, 0.014) + dy,
                  E + dy, Y, face, crank_mass=0.02, rod_mass=0.01, radius=0.004, hub=0.01, pivot=f"{side}_eye_pivot")
    lid = p.box("eyelid", _v(0.125, 0.0, 0.885), (0.03, 0.11, 0.012), 0.04)
    p.hinge("eyelid", head, lid, _v(0.12, 0.0, 0.86), Y, face)
    if ground:
        p.ground(friction)
    return p.finalize()


# ---------------------------------------------------------------------------------------
# Animatronic: fixed-base figure with a linkage-driven face and hands
# ---------------------------------------------------------------------------------------

def _lever_drive(p: _Parts, name: str, ground: int, output: int, D, to_crank, lever, axis, servo: _Servo,
                 length: float, crank: float, rocker: float, offset=(0.0, 0.0, 0.0), crank_mass: float = 0.04,
                 rod_mass: float = 0.01, hub: float = 0.015, radius: float = 0.004, pivot: str | None = None) -> None:
    """A near-parallelogram drive four-bar: ``output`` hinged to ``ground`` at ``D`` (about ``axis``); the
    servo crank pivots ``length`` away along ``to_crank``; crank and output lever both point along
    ``lever`` (normal to ``to_crank``), so the rod is parallel to the ground line and the
    transmission angle is 90 deg at the builder pose. ``offset`` shifts the linkage along ``axis``."""
    D = np.asarray(D, float) + np.asarray(offset, float)
    A = D + length * _unit(to_crank)
    p.fourbar(name, ground, output, A, A + crank * _unit(lever), D + rocker * _unit(lever), D, axis, servo,
              crank_mass=crank_mass, rod_mass=rod_mass, radius=radius, hub=hub, pivot=pivot)


def _finger(p: _Parts, name: str, palm: int, M, u, n, lengths, servo: _Servo | None, mass: float = 0.02) -> int:
    """A three-phalanx finger whose joints are coupled by two crossed four-bars (MCP drives PIP drives
    DIP), all hinges along ``n``; ``u`` is the finger's straight direction, ``n x u`` the palmar side.
    Nominal curl 0.2 / 0.45 / 0.7 rad (proximal / middle / distal, absolute). The MCP hinge is driven
    by ``servo`` (or passive, for a finger driven through a rod by a palm crank). 5 bodies, 7
    joints, 2 loops. Returns the proximal phalanx."""
    u, n = _unit(u), _unit(n)
    v = np.cross(n, u)  # palmar (curl) direction

    def along(th: float) -> np.ndarray:
        return np.cos(th) * u + np.sin(th) * v

    def dorsal(th: float) -> np.ndarray:
        return np.sin(th) * u - np.cos(th) * v

    a1, a2, a3 = 0.2, 0.45, 0.7
    l1, l2, l3 = lengths
    M = np.asarray(M, float)
    P = M + l1 * along(a1)
    D = P + l2 * along(a2)
    tip = D + l3 * along(a3)
    prox = p.rod(f"{name}_proximal", M, P, mass, 0.008)
    mid = p.rod(f"{name}_middle", P, D, 0.75 * mass, 0.007)
    dist = p.rod(f"{name}_distal", D, tip, 0.5 * mass, 0.006)
    p.hinge(f"{name}_mcp", palm, prox, M, n, servo)
    p.hinge(f"{name}_pip", prox, mid, P, n)
    p.hinge(f"{name}_dip", mid, dist, D, n)
    G1, Q1 = M + 0.008 * dorsal(a1), P - 0.008 * dorsal(a2)
    _check_fourbar(M, P, Q1, G1, n, (-0.6, 0.6), f"{name}_pip_coupler")
    c1 = p.rod(f"{name}_pip_coupler", G1, Q1, 0.4 * mass, 0.004)
    p.hinge(f"{name}_pip_coupler_palm", palm, c1, G1, n)
    p.hinge(f"{name}_pip_coupler_middle", c1, mid, Q1, n)
    G2, Q2 = P + 0.006 * dorsal(a2 - 0.25), D - 0.006 * dorsal(a3)
    _check_fourbar(P, D, Q2, G2, n, (-0.7, 0.7), f"{name}_dip_coupler")
    c2 = p.rod(f"{name}_dip_coupler", G2, Q2, 0.3 * mass, 0.004)
    p.hinge(f"{name}_dip_coupler_proximal", prox, c2, G2, n)
    p.hinge(f"{name}_dip_coupler_distal", c2, dist, Q2, n)
    return prox


def _servo_housing(p: _Parts, name: str, parent: int, center, size, mass: float) -> None:
    """A servo housing rigidly mounted (FIXED) on ``parent``."""
    housing = p.box(f"{name}_servo", center, size, mass)
    p.fixed(f"{name}_servo_mount", parent, housing)


def animatronic(ground: bool = True, body_gains: tuple[float, float] = (300.0, 8.0),
                face_gains: tuple[float, float] = (5.0, 0.08), hand_gains: tuple[float, float] = (6.0, 0.06),
                armature: float = 0.02, gravity: float = 9.81) -> Model:
    """A fixed-base figure of the class of Disney's Audio-Animatronics figures: an upper body on a
    pedestal with a linkage-driven face and hands, about 45 kg with the 20 kg pedestal.

    Counts: 151 bodies; 196 joints: 27 actuated REVOLUTE joints and 169 passive joints (the FIXED
    ``pedestal_mount`` to the world, 33 FIXED mounts of servo housings and shells, 131 REVOLUTE,
    2 SPHERICAL and 2 UNIVERSAL); 45 independent loops:

    - body (8 actuated, serial): ``waist_yaw``, ``neck_yaw``, ``neck_pitch``, ``head_roll``, per arm
      ``shoulder_pitch`` and ``shoulder_roll``;
    - elbows and wrists (4 loops): per arm a servo crank near the shoulder (``elbow_drive``) and one on
      the forearm (``wrist_drive``) drive the elbow and wrist hinges through rods (planar four-bars);
    - jaw (1 loop), brows (2), eyelids (2 drive four-bars, 2 follower four-bars that close the lower
      lids with the upper ones), mouth corners (2 drives, 2 cheek followers): planar four-bars;
    - eyes (4 loops): one crank yaws both eye carriers through two rods (planar, hinges along z);
      one crank pitches both eyeballs through two rods with a ball joint at the crank and a cardan at
      the eyeball (spatial loops);
    - hands (26 loops): per hand the thumb and index MCP are actuated, a palm crank drives the
      middle, ring and little fingers through three rods; every finger couples PIP and DIP to MCP
      with two crossed four-bars (2 loops per finger, 1 more per rod-driven finger).

    Every actuator's servo housing is a body FIXED to the link that carries it (27), plus a skull
    cap, a face frame, chest and back shells and two palm covers. Without geoms touching the world
    the ``ground`` plane (``ground=True``) has no contact pairs. Actuated ranges [rad]: waist yaw
    ±1.0, neck and head ±0.6, shoulders ±1.0, elbow, wrist, face and finger drives ±0.6. Gains
    ``(kp [N m/rad], kd [N m s/rad])`` for body, face and hand servos; effort limits 60, 3 and 1 N m;
    ``armature`` [kg m^2] on the body servos (a twentieth of it on the small face and finger servos,
    see docs/robots.md "Modelling for the solver"); ``gravity`` [m/s^2].
    """
    p = _Parts(gravity)
    body = _Servo(body_gains[0], body_gains[1], 60.0, 1.0, armature)
    body6 = dataclasses.replace(body, range=0.6)
    face = _Servo(face_gains[0], face_gains[1], 3.0, 0.6, 0.05 * armature)
    hand = _Servo(hand_gains[0], hand_gains[1], 1.0, 0.6, 0.05 * armature)

    pedestal = p.box("pedestal", _v(0.0, 0.0, 0.5), (0.4, 0.4, 1.0), 20.0)
    p.fixed("pedestal_mount", -1, pedestal)
    torso = p.box("torso", _v(0.0, 0.0, 1.25), (0.22, 0.36, 0.46), 8.0)
    p.hinge("waist_yaw", pedestal, torso, _v(0.0, 0.0, 1.0), Z, body)
    _servo_housing(p, "waist", pedestal, _v(-0.08, 0.0, 0.95), (0.08, 0.08, 0.06), 0.6)
    for name, c, size, m in (("chest_shell", _v(0.12, 0.0, 1.28), (0.03, 0.34, 0.36), 1.0),
                             ("back_shell", _v(-0.13, 0.0, 1.25), (0.05, 0.3, 0.3), 1.5)):
        shell = p.box(name, c, size, m)
        p.fixed(f"{name}_mount", torso, shell)
    # neck and head
    n0, n1, n2 = _v(0.0, 0.0, 1.49), _v(0.0, 0.0, 1.54), _v(0.0, 0.0, 1.59)
    neck_yaw = p.box("neck_yaw_link", n0 + _v(0.0, 0.0, 0.025), (0.08, 0.08, 0.05), 0.4)
    p.hinge("neck_yaw", torso, neck_yaw, n0, Z, body6)
    _servo_housing(p, "neck_yaw", torso, n0 + _v(-0.06, 0.0, -0.03), (0.05, 0.05, 0.04), 0.3)
    neck_pitch = p.box("neck_pitch_link", n1 + _v(0.0, 0.0, 0.025), (0.08, 0.08, 0.05), 0.3)
    p.hinge("neck_pitch", neck_yaw, neck_pitch, n1, Y, body6)
    _servo_housing(p, "neck_pitch", neck_yaw, n1 + _v(0.0, 0.06, 0.0), (0.04, 0.04, 0.04), 0.2)
    head = p.box("head", _v(0.02, 0.0, 1.70), (0.20, 0.17, 0.22), 2.0)
    p.hinge("head_roll", neck_pitch, head, n2, X, body6)
    _servo_housing(p, "head_roll", neck_pitch, n2 + _v(-0.05, 0.0, -0.01), (0.04, 0.04, 0.04), 0.2)
    for name, c, size, m in (("skull_cap", _v(0.0, 0.0, 1.83), (0.18, 0.16, 0.04), 0.2),
                             ("face_frame", _v(0.11, 0.0, 1.70), (0.02, 0.14, 0.16), 0.15)):
        shell = p.box(name, c, size, m)
        p.fixed(f"{name}_mount", head, shell)
    # jaw
    Dj = _v(0.03, 0.0, 1.65)
    jaw = p.box("jaw", _v(0.09, 0.0, 1.625), (0.10, 0.12, 0.03), 0.15)
    _lever_drive(p, "jaw", head, jaw, Dj, -X, Z, Y, face, 0.05, 0.015, 0.018, offset=(0.0, 0.07, 0.0),
                 crank_mass=0.04, rod_mass=0.02, hub=0.012, pivot="jaw_pivot")
    _servo_housing(p, "jaw", head, Dj + _v(-0.05, 0.085, 0.0), (0.03, 0.02, 0.03), 0.04)
    # eyes: carriers yaw on the head (z), eyeballs pitch on the carriers (y)
    eyes = {}
    for side, s in (("l", 1.0), ("r", -1.0)):
        E = _v(0.10, s * 0.035, 1.74)
        carrier = p.box(f"{side}_eye_carrier", E + _v(-0.015, 0.0, 0.0), (0.02, 0.02, 0.03), 0.03)
        p.hinge(f"{side}_eye_yaw", head, carrier, E, Z)
        eyeball = p.blob(f"{side}_eyeball", E, (0.012, 0.012, 0.012), 0.02)
        p.hinge(f"{side}_eye_pitch", carrier, eyeball, E, Y)
        eyes[side] = (E, carrier, eyeball)
    E_l = eyes["l"][0]
    W = _v(E_l[0] - 0.005, 0.0, E_l[2] - 0.018)
    yaw_crank = p.crank("eye_yaw_crank", W, W + _v(-0.015, 0.0, 0.0), Z, 0.03, 0.01)
    p.hinge("eye_yaw_drive", head, yaw_crank, W, Z, face)
    _servo_housing(p, "eye_yaw", head, W + _v(0.0, 0.0, -0.02), (0.02, 0.02, 0.02), 0.02)
    Cp = _v(E_l[0] - 0.03, 0.0, E_l[2] + 0.03)
    pitch_crank = p.crank("eye_pitch_crank", Cp, Cp + _v(0.015, 0.0, 0.0), Y, 0.03, 0.01)
    p.hinge("eye_pitch_drive", head, pitch_crank, Cp, Y, face)
    _servo_housing(p, "eye_pitch", head, Cp + _v(-0.02, 0.0, 0.0), (0.02, 0.02, 0.02), 0.02)
    for side in ("l", "r"):
        E, carrier, eyeball = eyes[side]
        B, Lv = W + _v(-0.015, 0.0, 0.0), _v(E[0] - 0.02, E[1], W[2])
        _check_fourbar(W, B, Lv, E, Z, (-face.range, face.range), f"{side}_eye_yaw_rod")
        rod = p.rod(f"{side}_eye_yaw_rod", B, Lv, 0.01, 0.004)
        p.hinge(f"{side}_eye_yaw_rod_crank", yaw_crank, rod, B, Z)
        p.hinge(f"{side}_eye_yaw_rod_carrier", rod, carrier, Lv, Z)
        Bt, Up = _v(Cp[0] + 0.015, E[1], Cp[2]), E + _v(-0.015, 0.0, 0.0)
        _check_fourbar(Cp, Bt, Up, E, Y, (-face.range, face.range), f"{side}_eye_pitch_rod")
        rod = p.rod(f"{side}_eye_pitch_rod", Bt, Up, 0.01, 0.004)
        p.ball(f"{side}_eye_pitch_rod_ball", pitch_crank, rod, Bt)
        p.cardan(f"{side}_eye_pitch_rod_cardan", rod, eyeball, Up, Y, np.cross(Y, _unit(Up - Bt)))
    # eyelids: upper lids driven, lower lids follow through a crossed four-bar; brows
    for side, s in (("l", 1.0), ("r", -1.0)):
        E = eyes[side][0]
        upper = p.box(f"{side}_upper_lid", E + _v(0.008, 0.0, 0.012), (0.02, 0.03, 0.006), 0.01)
        _lever_drive(p, f"{side}_upper_lid", head, upper, E, -X, Z, Y, face, 0.04, 0.01, 0.012,
                     offset=(0.0, s * 0.022, 0.0), pivot=f"{side}_upper_lid_pivot")
        _servo_housing(p, f"{side}_upper_lid", head, E + _v(-0.04, s * 0.032, 0.0), (0.02, 0.015, 0.02), 0.02)
        lower = p.box(f"{side}_lower_lid", E + _v(0.008, 0.0, -0.012), (0.02, 0.03, 0.006), 0.01)
        dy = _v(0.0, s * 0.026, 0.0)
        U1 = E + _v(-0.01, 0.0, 0.0) + dy
        p.fourbar(f"{side}_lower_lid", head, lower, E + dy, U1, U1 + _v(0.0, 0.0, -0.015),
                  E + _v(-0.02, 0.0, -0.015) + dy, Y, None, crank_mass=0.0, rod_mass=0.01, radius=0.004,
                  crank=upper, pivot=f"{side}_lower_lid_pivot")
        Db = _v(0.09, s * 0.035, 1.78)
        brow = p.box(f"{side}_brow", Db + _v(0.012, 0.0, 0.0), (0.012, 0.035, 0.008), 0.01)
        _lever_drive(p, f"{side}_brow", head, brow, Db, -X, Z, Y, face, 0.04, 0.01, 0.012,
                     offset=(0.0, s * 0.025, 0.0), pivot=f"{side}_brow_pivot")
        _servo_housing(p, f"{side}_brow", head, Db + _v(-0.04, s * 0.035, 0.0), (0.02, 0.015, 0.02), 0.02)
        # mouth corner lever (driven) and cheek plate (follower)
        Dm = _v(0.07, s * 0.04, 1.66)
        corner = p.rod(f"{side}_mouth_corner", Dm, Dm + _v(0.04, s * 0.005, -0.01), 0.015, 0.005)
        _lever_drive(p, f"{side}_mouth", head, corner, Dm, -X, Z, Y, face, 0.04, 0.01, 0.012,
                     offset=(0.0, s * 0.012, 0.0), pivot=f"{side}_mouth_pivot")
        _servo_housing(p, f"{side}_mouth", head, Dm + _v(-0.04, s * 0.022, 0.0), (0.02, 0.015, 0.02), 0.02)
        Dc = Dm + _v(0.0, 0.0, 0.03)
        cheek = p.box(f"{side}_cheek", Dc + _v(0.015, 0.0, 0.0), (0.03, 0.02, 0.03), 0.02)
        dy = _v(0.0, s * 0.005, 0.0)
        p.fourbar(f"{side}_cheek", head, cheek, Dm + dy, Dm + _v(-0.01, 0.0, 0.0) + dy,
                  Dc + _v(-0.012, 0.0, 0.0) + dy, Dc + dy, Y, None, crank_mass=0.0, rod_mass=0.01,
                  radius=0.004, crank=corner, pivot=f"{side}_cheek_pivot")
    # arms and hands
    for side, s in (("l", 1.0), ("r", -1.0)):
        Sh = _v(0.0, s * 0.21, 1.42)
        shoulder = p.box(f"{side}_shoulder", Sh + _v(0.0, s * 0.035, 0.0), (0.07, 0.07, 0.07), 0.4)
        p.hinge(f"{side}_shoulder_pitch", torso, shoulder, Sh, Y, body)
        _servo_housing(p, f"{side}_shoulder_pitch", torso, Sh + _v(0.0, -s * 0.04, 0.0), (0.06, 0.04, 0.06), 0.3)
        Sr = Sh + _v(0.0, s * 0.06, 0.0)
        El = Sr + _v(0.0, 0.0, -0.28)
        upper_arm = p.rod(f"{side}_upper_arm", Sr, El, 1.0, 0.035, com=0.35)
        p.hinge(f"{side}_shoulder_roll", shoulder, upper_arm, Sr, X, body)
        _servo_housing(p, f"{side}_shoulder_roll", shoulder, Sh + _v(-0.05, s * 0.035, 0.0), (0.04, 0.05, 0.05),
                       0.25)
        Wr = El + _v(0.25, 0.0, 0.0)
        forearm = p.rod(f"{side}_forearm", El, Wr, 0.6, 0.03, com=0.4)
        A = Sr + _v(0.0, -s * 0.03, -0.06)
        p.fourbar(f"{side}_elbow", upper_arm, forearm, A, A + _v(-0.03, 0.0, 0.0),
                  El + _v(-0.035, -s * 0.03, 0.0), El + _v(0.0, -s * 0.03, 0.0), Y, body6, crank_mass=0.5,
                  rod_mass=0.15, radius=0.01, hub=0.05, pivot=f"{side}_elbow")
        _servo_housing(p, f"{side}_elbow", upper_arm, A + _v(0.0, -s * 0.03, 0.0), (0.04, 0.03, 0.05), 0.12)
        palm = p.box(f"{side}_palm", Wr + _v(0.05, 0.0, 0.0), (0.09, 0.08, 0.025), 0.15)
        A = El + _v(0.06, s * 0.025, 0.0)
        p.fourbar(f"{side}_wrist", forearm, palm, A, A + _v(0.0, 0.0, 0.025), Wr + _v(0.0, s * 0.025, 0.028),
                  Wr + _v(0.0, s * 0.025, 0.0), Y, body6, crank_mass=0.1, rod_mass=0.04, radius=0.006, hub=0.02,
                  pivot=f"{side}_wrist")
        _servo_housing(p, f"{side}_wrist", forearm, A + _v(0.0, s * 0.025, 0.0), (0.03, 0.025, 0.04), 0.08)
        cover = p.box(f"{side}_palm_cover", Wr + _v(0.05, 0.0, 0.016), (0.08, 0.07, 0.006), 0.03)
        p.fixed(f"{side}_palm_cover_mount", palm, cover)
        # fingers: thumb and index driven at the MCP, middle/ring/little through rods from a palm crank
        xm = Wr[0] + 0.095
        med = -s  # towards the body's midline
        _finger(p, f"{side}_thumb", palm, Wr + _v(0.03, med * 0.042, -0.005), _v(0.8, med * 0.6, 0.0),
                _v(-med * 0.6, 0.8, 0.0), (0.035, 0.026, 0.022), hand)
        _servo_housing(p, f"{side}_thumb", palm, Wr + _v(0.01, med * 0.025, -0.01), (0.02, 0.015, 0.012), 0.015)
        _finger(p, f"{side}_index", palm, _v(xm, Wr[1] + med * 0.028, Wr[2]), X, Y, (0.040, 0.025, 0.020), hand)
        _servo_housing(p, f"{side}_index", palm, Wr + _v(0.03, med * 0.01, -0.01), (0.02, 0.015, 0.012), 0.015)
        Wc = _v(xm - 0.03, Wr[1], Wr[2])
        drive = p.box(f"{side}_finger_crank", Wc + _v(0.0, 0.0, -0.004), (0.012, 0.075, 0.016), 0.05)
        p.hinge(f"{side}_finger_drive", palm, drive, Wc, Y, hand)
        _servo_housing(p, f"{side}_finger", palm, Wc + _v(-0.02, 0.0, -0.005), (0.02, 0.03, 0.012), 0.015)
        for finger, dy, lengths in (("middle", med * 0.009, (0.044, 0.028, 0.021)),
                                    ("ring", -med * 0.009, (0.041, 0.026, 0.020)),
                                    ("little", -med * 0.028, (0.032, 0.020, 0.017))):
            M = _v(xm, Wr[1] + dy, Wr[2])
            prox = _finger(p, f"{side}_{finger}", palm, M, X, Y, lengths, None)
            B = _v(Wc[0], M[1], Wc[2] - 0.012)
            R = M + _v(0.0, 0.0, -0.013)
            _check_fourbar(Wc, B, R, M, Y, (-hand.range, hand.range), f"{side}_{finger}_rod")
            rod = p.rod(f"{side}_{finger}_rod", B, R, 0.008, 0.004)
            p.hinge(f"{side}_{finger}_rod_crank", drive, rod, B, Y)
            p.hinge(f"{side}_{finger}_rod_proximal", rod, prox, R, Y)
    if ground:
        p.ground(1.0)
    return p.finalize()
