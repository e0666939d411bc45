"""Model (immutable, host NumPy) and ModelBuilder with validation.

Storage is flat over all worlds, sized by the *sum* of per-world counts, with per-world
offsets and counts (docs/conventions.md, "Data layout"). Index fields (``joint_parent``,
``joint_child``) are global body indices; ``-1`` is the world.
"""

from __future__ import annotations

import dataclasses
import enum
import hashlib
import itertools
import numbers
import threading
from collections.abc import Callable, Hashable, Sequence
from typing import Any, TypeVar

import numpy as np

from kamino.hostmath import IDENTITY_QUAT, axis_frame, matrix_to_quat, quat_mul, quat_to_matrix


class ModelError(ValueError):
    """A model description is invalid; the message names the body/joint and the problem."""


class JointType(enum.IntEnum):
    """Joint types of docs/formulation.md §2.4. Every joint may close a loop; none is special."""

    FIXED = 0
    """No relative motion: 6 constraint rows, no DoF, no coordinate."""
    REVOLUTE = 1
    """A hinge: rotation about the joint frame's x axis (1 DoF; coordinate: the angle [rad])."""
    PRISMATIC = 2
    """A slider: translation along the joint frame's x axis (1 DoF; coordinate: ``t_x`` [m])."""
    CYLINDRICAL = 3
    """Translation along and rotation about the joint frame's x axis (2 DoFs; coordinates ``(t_x, angle)``)."""
    UNIVERSAL = 4
    """Rotations about the joint frame's x and y axes (2 DoFs; coordinates ``(theta_1, theta_2)`` [rad])."""
    SPHERICAL = 5
    """A ball joint: any rotation about the joint origin (3 DoFs; coordinates: a quaternion ``(x, y, z, w)``)."""
    CARTESIAN = 6
    """Translation along the joint frame's three axes, no rotation (3 DoFs; coordinates ``t`` [m])."""
    FREE = 7
    """No constraint: a floating body, e.g. a robot's base (6 DoFs; coordinates ``(t, quaternion)``, 7)."""


class GeomType(enum.IntEnum):
    """Collision geometry types (MuJoCo's size conventions, all in the geom's local frame).

    PLANE: infinite half-space below local z = 0 (normal +z); size ignored.
    SPHERE: radius ``size[0]``. CAPSULE: radius ``size[0]``, half-length ``size[1]`` of the
    segment along local z. BOX: half-extents ``size[0:3]``. CYLINDER: radius ``size[0]``,
    half-height ``size[1]`` along local z. ELLIPSOID: semi-axes ``size[0:3]`` along local x, y, z
    (collides with planes only: another enabled pair with an ellipsoid is a :class:`ModelError`).
    HFIELD: a heightfield (MuJoCo's ``<hfield>``): a grid of heights over ``[-rx, rx] x [-ry, ry]`` in the
    geom's frame, stored in ``Model.hfield_*`` (``Model.geom_dataid`` names the grid); static (world) only;
    ``size`` is ``(rx, ry, max(z_top, z_base))``, the half-extents of a box about the geom's origin that holds it.
    """

    PLANE = 0
    """Infinite half-space below local ``z = 0`` (normal ``+z``); ``size`` ignored."""
    SPHERE = 1
    """Sphere of radius ``size[0]``."""
    CAPSULE = 2
    """Capsule of radius ``size[0]`` around a segment of half-length ``size[1]`` along local z."""
    BOX = 3
    """Box of half-extents ``size[0:3]``."""
    CYLINDER = 4
    """Cylinder of radius ``size[0]`` and half-height ``size[1]`` along local z."""
    ELLIPSOID = 5
    """Ellipsoid of semi-axes ``size[0:3]`` along local x, y, z (collides with planes only)."""
    HFIELD = 6
    """Heightfield ``Model.hfield_*[geom_dataid]`` (world geoms only; collides with spheres, capsules, boxes and
    cylinders: kamino/jax_ref/collision.py)."""


class ActuationMode(enum.IntEnum):
    """How a joint DoF is driven (docs/formulation.md §3; docs/conventions.md "Actuation").

    PASSIVE: no actuator (``Control.dof_effort`` is still applied as an external joint effort).
    EFFORT: the commanded effort, clipped to the effort limit, applied explicitly.
    POSITION: implicit PD towards ``Control.position_target`` (and ``velocity_target``).
    VELOCITY: implicit D towards ``Control.velocity_target``.
    """

    PASSIVE = 0
    """No actuator (``Control.dof_effort`` is still applied as an external joint effort)."""
    EFFORT = 1
    """The commanded effort, clipped to the effort limit, applied explicitly."""
    POSITION = 2
    """Implicit PD towards ``Control.position_target`` (and ``velocity_target``)."""
    VELOCITY = 3
    """Implicit D towards ``Control.velocity_target``."""


@dataclasses.dataclass(frozen=True)
class Actuation:
    """Actuator of a joint's DoFs (scalars apply to every DoF of the joint).

    ``kp`` [N m/rad or N/m], ``kd`` [N m s/rad or N s/m]; ``effort_limit`` bounds the actuator's
    generalized force (PD + feed-forward, or the commanded effort) and is enforced by the solver.
    """

    mode: ActuationMode | str = ActuationMode.POSITION
    """How the DoFs are driven: an :class:`ActuationMode` or its name (case-insensitive, ``"position"``)."""
    kp: float = 0.0
    """PD stiffness [N m/rad or N/m] (POSITION only)."""
    kd: float = 0.0
    """PD damping [N m s/rad or N s/m] (POSITION and VELOCITY)."""
    effort_limit: float = float("inf")
    """Bound on the actuator's generalized force [N m or N], enforced by the solver (``inf``: unlimited)."""

    def __post_init__(self) -> None:
        self.resolved_mode()  # an unknown mode fails here, where the Actuation is written, not at add_joint

    def resolved_mode(self) -> ActuationMode:
        """``mode`` as an :class:`ActuationMode` (a name is case-insensitive: ``"position"``)."""
        names = [m.name.lower() for m in ActuationMode]
        if isinstance(self.mode, str):
            try:
                return ActuationMode[self.mode.upper()]
            except KeyError as exc:
                raise ModelError(f"Actuation(mode={self.mode!r}): unknown actuation mode {self.mode!r}; choose one "
                                 f"of {names} (or a kamino.ActuationMode)") from exc
        try:
            return ActuationMode(self.mode)
        except (ValueError, TypeError) as exc:
            raise ModelError(f"Actuation(mode={self.mode!r}): unknown actuation mode {self.mode!r}; choose one of "
                             f"{names} (or a kamino.ActuationMode)") from exc


#: Joint types whose DoFs have a scalar coordinate a PD actuator can track (docs/formulation.md §3.2).
PD_JOINT_TYPES = (JointType.REVOLUTE, JointType.PRISMATIC, JointType.CYLINDRICAL)


# Row kinds: how a constraint row's residual is read (docs/formulation.md §2.3).
RES_TRANS, RES_LOG, RES_HINGE, RES_UNIV = 0, 1, 2, 3
# DoF-row kinds: which axis a DoF row uses (docs/formulation.md §2.5).
DOF_TRANS, DOF_ROT, DOF_UNIV, DOF_FREE = 0, 1, 2, 3

#: Per type: constrained rows as (axis 0..5, residual kind), in row order (docs/formulation.md §2.4).
JOINT_CONSTRAINT_ROWS: dict[JointType, tuple[tuple[int, int], ...]] = {
    JointType.FIXED: ((0, RES_TRANS), (1, RES_TRANS), (2, RES_TRANS), (3, RES_LOG), (4, RES_LOG), (5, RES_LOG)),
    JointType.REVOLUTE: ((0, RES_TRANS), (1, RES_TRANS), (2, RES_TRANS), (4, RES_HINGE), (5, RES_HINGE)),
    JointType.PRISMATIC: ((1, RES_TRANS), (2, RES_TRANS), (3, RES_LOG), (4, RES_LOG), (5, RES_LOG)),
    JointType.CYLINDRICAL: ((1, RES_TRANS), (2, RES_TRANS), (4, RES_HINGE), (5, RES_HINGE)),
    JointType.UNIVERSAL: ((0, RES_TRANS), (1, RES_TRANS), (2, RES_TRANS), (5, RES_UNIV)),
    JointType.SPHERICAL: ((0, RES_TRANS), (1, RES_TRANS), (2, RES_TRANS)),
    JointType.CARTESIAN: ((3, RES_LOG), (4, RES_LOG), (5, RES_LOG)),
    JointType.FREE: (),
}
#: Per type: DoF rows as (axis 0..5, DoF kind) (docs/formulation.md §2.4-2.5).
JOINT_DOF_ROWS: dict[JointType, tuple[tuple[int, int], ...]] = {
    JointType.FIXED: (),
    JointType.REVOLUTE: ((3, DOF_ROT),),
    JointType.PRISMATIC: ((0, DOF_TRANS),),
    JointType.CYLINDRICAL: ((0, DOF_TRANS), (3, DOF_ROT)),
    JointType.UNIVERSAL: ((3, DOF_UNIV), (4, DOF_UNIV)),
    JointType.SPHERICAL: ((3, DOF_ROT), (4, DOF_ROT), (5, DOF_ROT)),
    JointType.CARTESIAN: ((0, DOF_TRANS), (1, DOF_TRANS), (2, DOF_TRANS)),
    JointType.FREE: tuple((k, DOF_FREE) for k in range(6)),
}
#: Number of joint coordinates per type (docs/formulation.md §2.4).
JOINT_NUM_COORDS: dict[JointType, int] = {
    JointType.FIXED: 0,
    JointType.REVOLUTE: 1,
    JointType.PRISMATIC: 1,
    JointType.CYLINDRICAL: 2,
    JointType.UNIVERSAL: 2,
    JointType.SPHERICAL: 4,
    JointType.CARTESIAN: 3,
    JointType.FREE: 7,
}

#: Contact points the narrow phase can return per geom pair (type_a <= type_b), the pair's share
#: of the default contact capacity (kamino/jax_ref/collision.py produces exactly these counts).
CONTACT_POINTS: dict[tuple[GeomType, GeomType], int] = {
    (GeomType.PLANE, GeomType.SPHERE): 1,
    (GeomType.PLANE, GeomType.CAPSULE): 2,
    (GeomType.PLANE, GeomType.BOX): 4,
    (GeomType.PLANE, GeomType.CYLINDER): 4,
    (GeomType.PLANE, GeomType.ELLIPSOID): 1,
    (GeomType.SPHERE, GeomType.SPHERE): 1,
    (GeomType.SPHERE, GeomType.CAPSULE): 1,
    (GeomType.SPHERE, GeomType.BOX): 1,
    (GeomType.SPHERE, GeomType.CYLINDER): 1,
    (GeomType.CAPSULE, GeomType.CAPSULE): 2,
    (GeomType.CAPSULE, GeomType.BOX): 2,
    (GeomType.CAPSULE, GeomType.CYLINDER): 2,
    (GeomType.BOX, GeomType.BOX): 8,
    (GeomType.BOX, GeomType.CYLINDER): 4,
    (GeomType.CYLINDER, GeomType.CYLINDER): 4,
    (GeomType.SPHERE, GeomType.HFIELD): 1,
    (GeomType.CAPSULE, GeomType.HFIELD): 2,
    (GeomType.BOX, GeomType.HFIELD): 4,
    (GeomType.CYLINDER, GeomType.HFIELD): 4,
}

#: How many leading ``size`` entries each geom type uses (all must be positive).
_GEOM_SIZE_COUNT = {GeomType.PLANE: 0, GeomType.SPHERE: 1, GeomType.CAPSULE: 2, GeomType.BOX: 3, GeomType.CYLINDER: 2,
                    GeomType.ELLIPSOID: 3, GeomType.HFIELD: 0}

_QUAT_UNIT_TOL = 1e-6  # a quaternion whose norm is further than this from 1 is a ModelError
#: The largest magnitude a finite model parameter may have (lengths, masses, inertias, gains, limits, ...): float32
#: reaches 3.4e38, and a product of two parameters (a mass times a squared length, a gain times a limit) must stay
#: below it for a float32 step to mean anything. Infinite limits stay allowed where a field documents them.
MAX_PARAMETER = 1e30
#: The smallest body mass [kg] and principal moment of inertia [kg m^2] a body may have (MuJoCo's ``mjMINVAL``): a
#: positive value below it is a unit mistake, and its inverse overflows float32 in the solver.
MIN_MASS = 1e-15
#: The shortest joint axis accepted before normalising: a shorter one has no reliable direction.
MIN_AXIS_LENGTH = 1e-10
T = TypeVar("T")


@dataclasses.dataclass(frozen=True, eq=False)
class Keyframe:
    """A named initial state of one world (an MJCF ``<keyframe><key>``): ``kamino.init_state(model,
    keyframe=name)`` starts every world there."""

    name: str
    """the key's name (MuJoCo's ``key<i>`` for an unnamed one)."""
    time: float
    """the key's simulated time [s]."""
    body_q: np.ndarray
    """``[bodies per world, 7]`` CoM poses (``State.body_q``'s layout)."""
    body_u: np.ndarray
    """``[bodies per world, 6]`` twists."""
    ctrl: np.ndarray
    """``[actuators per world]`` the key's control vector (``kamino.Control.from_ctrl(model, key.ctrl)``; tile it
    for several worlds)."""


#: the attribute of a Model that holds what an MJCF file suggests beside the mechanism (:func:`with_extras`)
_EXTRAS = "_extras"


@dataclasses.dataclass(frozen=True, eq=False)
class Model:
    """An immutable multi-world model. Build one with :class:`ModelBuilder`, ``replicate`` or ``concat``.

    All per-entity arrays are flat over worlds (world 0's entities first, in builder order);
    ``world_<entity>_start``/``world_<entity>_count`` give each world's segment.
    Bodies are described at their centre of mass: ``body_q0[i] = (px, py, pz, qx, qy, qz, qw)``
    is the CoM frame, ``body_inertia[i]`` the 3x3 inertia about the CoM in that frame.
    Joint frames: the joint frame sits at ``joint_anchor_B`` in the base CoM frame with
    orientation ``joint_frame_B`` (quaternion ``X_B``), and at ``joint_anchor_F`` /
    ``joint_frame_F`` on the follower; its local x axis is the joint's (first) motion axis.
    """

    def __getstate__(self) -> dict:
        """The model's fields for ``pickle`` / ``copy``: without what :func:`derived` keeps (compiled programs,
        device buffers), which the copy builds again when it needs it."""
        return {k: v for k, v in self.__dict__.items() if k != _DERIVED}

    num_worlds: int
    """Number of worlds ``W`` (independent copies or variants simulated side by side)."""
    gravity: np.ndarray
    """``[W, 3]`` gravitational acceleration per world [m/s^2], world frame."""

    # bodies
    body_mass: np.ndarray
    """``[B]`` body masses [kg] (``B``: bodies over all worlds)."""
    body_inertia: np.ndarray
    """``[B, 3, 3]`` inertia about the CoM in the body's CoM frame [kg m^2]."""
    body_q0: np.ndarray
    """``[B, 7]`` initial (reference) CoM poses ``(px, py, pz, qx, qy, qz, qw)``, world frame."""
    body_u0: np.ndarray
    """``[B, 6]`` initial twists ``(v, w)``: CoM linear then angular velocity, world frame."""
    body_world: np.ndarray
    """``[B]`` world of each body."""
    body_names: tuple[str, ...]
    """``[B]`` body names (unique within a world; :meth:`body_index` looks one up)."""
    world_body_start: np.ndarray
    """``[W]`` index of each world's first body."""
    world_body_count: np.ndarray
    """``[W]`` bodies per world."""

    # joints
    joint_type: np.ndarray
    """``[J]`` :class:`JointType` of each joint (``J``: joints over all worlds)."""
    joint_parent: np.ndarray
    """``[J]`` global index of the base body (``-1``: the world)."""
    joint_child: np.ndarray
    """``[J]`` global index of the follower body."""
    joint_world: np.ndarray
    """``[J]`` world of each joint."""
    joint_anchor_B: np.ndarray
    """``[J, 3]`` joint frame origin in the base body's CoM frame (world frame for a world-attached joint) [m]."""
    joint_anchor_F: np.ndarray
    """``[J, 3]`` joint frame origin in the follower body's CoM frame [m]."""
    joint_frame_B: np.ndarray
    """``[J, 4]`` joint frame orientation ``X_B`` in the base body's CoM frame (quaternion ``(x, y, z, w)``); its
    local x axis is the joint's first motion axis."""
    joint_frame_F: np.ndarray
    """``[J, 4]`` joint frame orientation in the follower body's CoM frame (quaternion ``(x, y, z, w)``)."""
    joint_names: tuple[str, ...]
    """``[J]`` joint names (unique within a world; :meth:`joint_index` looks one up)."""
    world_joint_start: np.ndarray
    """``[W]`` index of each world's first joint."""
    world_joint_count: np.ndarray
    """``[W]`` joints per world."""

    # joint DoFs (global flat), coordinates, kinematic constraint rows
    joint_dof_start: np.ndarray
    """``[J]`` index of each joint's first DoF in the flat DoF arrays (``dof_*``, ``Control.dof_effort``,
    ``State.actuator_force``)."""
    joint_dof_count: np.ndarray
    """``[J]`` DoFs per joint (REVOLUTE 1, ..., FREE 6)."""
    joint_coord_start: np.ndarray
    """``[J]`` index of each joint's first coordinate in :func:`kamino.joint_positions`'s flat vector
    (:func:`kamino.joint_coordinates` reads one joint's by name)."""
    joint_coord_count: np.ndarray
    """``[J]`` coordinates per joint (REVOLUTE 1, SPHERICAL 4 (a quaternion), FREE 7, ...)."""
    joint_cts_start: np.ndarray
    """``[J]`` index of each joint's first constraint row in ``State.constraint_force``."""
    joint_cts_count: np.ndarray
    """``[J]`` constraint rows per joint (6 minus its DoFs)."""
    dof_lower: np.ndarray
    """``[D]`` lower position limit of each DoF [m or rad] (``-inf``: none; ``D``: DoFs over all worlds)."""
    dof_upper: np.ndarray
    """``[D]`` upper position limit of each DoF [m or rad] (``inf``: none)."""
    dof_act_mode: np.ndarray
    """``[D]`` :class:`ActuationMode` of each DoF."""
    dof_kp: np.ndarray
    """``[D]`` PD stiffness [N/m or N m/rad] of POSITION DoFs."""
    dof_kd: np.ndarray
    """``[D]`` PD damping [N s/m or N m s/rad] of POSITION and VELOCITY DoFs."""
    dof_effort_limit: np.ndarray
    """``[D]`` bound on the actuator's generalized force [N or N m] (``inf``: unlimited)."""
    dof_armature: np.ndarray
    """``[D]`` armature: reflected rotor inertia added along the DoF [kg or kg m^2]."""
    dof_damping: np.ndarray
    """``[D]`` passive viscous damping [N s/m or N m s/rad]."""
    dof_stiffness: np.ndarray
    """``[D]`` passive spring stiffness [N/m or N m/rad]."""
    dof_springref: np.ndarray
    """``[D]`` rest position of the passive spring [m or rad]."""
    world_dof_start: np.ndarray
    """``[W]`` index of each world's first DoF."""
    world_dof_count: np.ndarray
    """``[W]`` DoFs per world."""
    world_coord_start: np.ndarray
    """``[W]`` index of each world's first joint coordinate."""
    world_coord_count: np.ndarray
    """``[W]`` joint coordinates per world."""
    world_cts_start: np.ndarray
    """``[W]`` index of each world's first constraint row."""
    world_cts_count: np.ndarray
    """``[W]`` constraint rows per world."""

    # collision geometry (pose in the body's CoM frame; world frame for body -1)
    geom_type: np.ndarray
    """``[G]`` :class:`GeomType` of each collision geom (``G``: geoms over all worlds)."""
    geom_body: np.ndarray
    """``[G]`` global index of the body a geom is attached to (``-1``: the world, e.g. the ground plane)."""
    geom_world: np.ndarray
    """``[G]`` world of each geom."""
    geom_pos: np.ndarray
    """``[G, 3]`` geom position in its body's CoM frame (world frame for ``geom_body == -1``) [m]."""
    geom_quat: np.ndarray
    """``[G, 4]`` geom orientation in the same frame (quaternion ``(x, y, z, w)``)."""
    geom_size: np.ndarray
    """``[G, 3]`` size parameters in MuJoCo's conventions (:class:`GeomType`) [m]."""
    geom_friction: np.ndarray
    """``[G]`` Coulomb friction coefficient (a contact takes the larger of its two geoms')."""
    geom_restitution: np.ndarray
    """``[G]`` coefficient of restitution (a contact takes the larger of its two geoms')."""
    geom_margin: np.ndarray
    """``[G]`` contact margin [m]: a contact is active once its gap is within the two geoms' margins plus
    ``SolverConfig.contact_margin`` (plus what the approach speed closes in the step)."""
    geom_names: tuple[str, ...]
    """``[G]`` geom names."""
    world_geom_start: np.ndarray
    """``[W]`` index of each world's first geom."""
    world_geom_count: np.ndarray
    """``[W]`` geoms per world."""
    geom_dataid: np.ndarray
    """``[G]`` global index of the heightfield (``hfield_*``) of an HFIELD geom; ``-1`` for the other types."""

    # heightfields (MuJoCo's <hfield>): grids of heights referred to by HFIELD geoms
    hfield_nrow: np.ndarray
    """``[H]`` rows of each heightfield grid (along local y; ``H``: heightfields over all worlds)."""
    hfield_ncol: np.ndarray
    """``[H]`` columns of each grid (along local x)."""
    hfield_size: np.ndarray
    """``[H, 4]`` MuJoCo's ``(rx, ry, z_top, z_base)`` [m]: the grid spans ``[-rx, rx] x [-ry, ry]`` of the geom's
    frame, heights are ``z_top`` times the normalised data, and the solid reaches ``z_base`` below ``z = 0``."""
    hfield_adr: np.ndarray
    """``[H]`` index of each grid's first height in ``hfield_data``."""
    hfield_world: np.ndarray
    """``[H]`` world of each heightfield."""
    hfield_names: tuple[str, ...]
    """``[H]`` heightfield names."""
    hfield_data: np.ndarray
    """``[HD]`` normalised heights in ``[0, 1]``, grid after grid, row-major: height ``k = r ncol + c`` sits at
    ``x = -rx + 2 rx c / (ncol - 1)``, ``y = -ry + 2 ry r / (nrow - 1)`` (MuJoCo's ``hfield_data``)."""
    world_hfield_start: np.ndarray
    """``[W]`` index of each world's first heightfield."""
    world_hfield_count: np.ndarray
    """``[W]`` heightfields per world."""
    world_hfield_data_start: np.ndarray
    """``[W]`` index of each world's first height in ``hfield_data``."""
    world_hfield_data_count: np.ndarray
    """``[W]`` heights per world."""

    # candidate contact pairs (filtered at build time; geom a has the smaller type)
    pair_geom_a: np.ndarray
    """``[P]`` global index of each candidate contact pair's first geom (the one with the smaller type; ``P``:
    pairs over all worlds, filtered at build time). ``ContactState.pair`` indexes a world's pairs from
    ``world_pair_start``."""
    pair_geom_b: np.ndarray
    """``[P]`` global index of each pair's second geom (``ContactState.force`` acts on its body)."""
    pair_world: np.ndarray
    """``[P]`` world of each pair."""
    world_pair_start: np.ndarray
    """``[W]`` index of each world's first pair."""
    world_pair_count: np.ndarray
    """``[W]`` candidate pairs per world."""
    world_contact_capacity: np.ndarray
    """``[W]`` contact slots per world (the most contacts a step keeps); ``State.contacts`` holds them world after
    world."""

    # joint couplings (mimic joints): q_a = sum_k coef[k] q_b^k (docs/conventions.md "Couplings")
    coupling_joint_a: np.ndarray
    """``[K]`` global index of each coupling's driven joint ``a``: ``q_a = sum_k coef[k] q_b^k``
    (docs/conventions.md, "Couplings"; ``K``: couplings over all worlds)."""
    coupling_joint_b: np.ndarray
    """``[K]`` global index of the driving joint ``b`` (``-1``: none, ``q_a = coef[0]``)."""
    coupling_coef: np.ndarray
    """``[K, 5]`` polynomial coefficients ``a_0 .. a_4``."""
    coupling_world: np.ndarray
    """``[K]`` world of each coupling."""
    coupling_names: tuple[str, ...]
    """``[K]`` coupling names."""
    world_coupling_start: np.ndarray
    """``[W]`` index of each world's first coupling."""
    world_coupling_count: np.ndarray
    """``[W]`` couplings per world."""

    # named actuators: one per actuated DoF (the DoF's Actuation sets mode and gains)
    actuator_dof: np.ndarray
    """``[A]`` global DoF index of each named actuator (one per actuated DoF; the DoF's :class:`Actuation` sets
    mode and gains; ``A``: actuators over all worlds)."""
    actuator_gear: np.ndarray
    """``[A]`` factor from a control value to an effort (EFFORT DoFs; :meth:`Control.from_ctrl`)."""
    actuator_ctrl_range: np.ndarray
    """``[A, 2]`` range a control value is clipped to (``(-inf, inf)``: none)."""
    actuator_world: np.ndarray
    """``[A]`` world of each actuator."""
    actuator_names: tuple[str, ...]
    """``[A]`` actuator names (the order of a MuJoCo-style control vector; :meth:`actuator_index`)."""
    world_actuator_start: np.ndarray
    """``[W]`` index of each world's first actuator."""
    world_actuator_count: np.ndarray
    """``[W]`` actuators per world."""

    # ---- sizes -------------------------------------------------------------------------
    @property
    def num_bodies(self) -> int:
        """Bodies over all worlds (``B``)."""
        return int(self.body_mass.shape[0])

    @property
    def num_joints(self) -> int:
        """Joints over all worlds (``J``)."""
        return int(self.joint_type.shape[0])

    @property
    def num_dofs(self) -> int:
        """Joint DoFs over all worlds (``D``): the length of ``Control.dof_effort``."""
        return int(self.dof_lower.shape[0])

    @property
    def num_coords(self) -> int:
        """Joint coordinates over all worlds: the length of :func:`kamino.joint_positions`."""
        return int(self.joint_coord_count.sum())

    @property
    def num_geoms(self) -> int:
        """Collision geoms over all worlds (``G``)."""
        return int(self.geom_type.shape[0])

    @property
    def num_hfields(self) -> int:
        """Heightfields over all worlds (``H``)."""
        return int(self.hfield_nrow.shape[0])

    @property
    def num_pairs(self) -> int:
        """Candidate contact pairs over all worlds (``P``)."""
        return int(self.pair_geom_a.shape[0])

    @property
    def num_contacts(self) -> int:
        """Total contact capacity over all worlds."""
        return int(self.world_contact_capacity.sum())

    @property
    def num_couplings(self) -> int:
        """Joint couplings over all worlds (``K``)."""
        return int(self.coupling_joint_a.shape[0])

    @property
    def num_actuators(self) -> int:
        """Named actuators over all worlds (``A``): the length of a MuJoCo-style control vector."""
        return int(self.actuator_dof.shape[0])

    @property
    def num_constraints(self) -> int:
        """Total bilateral (joint) constraint rows over all worlds."""
        return int(self.joint_cts_count.sum())

    def _lookup(self, entity: str, names: tuple[str, ...], name: str, world: int) -> int:
        start = int(getattr(self, f"world_{entity}_start")[world])
        count = int(getattr(self, f"world_{entity}_count")[world])
        for k in range(start, start + count):
            if names[k] == name:
                return k
        raise KeyError(f"no {entity} named {name!r} in world {world}")

    def body_index(self, name: str, world: int = 0) -> int:
        """Global index of the body called ``name`` in ``world``."""
        return self._lookup("body", self.body_names, name, world)

    def joint_index(self, name: str, world: int = 0) -> int:
        """Global index of the joint called ``name`` in ``world``."""
        return self._lookup("joint", self.joint_names, name, world)

    def actuator_index(self, name: str, world: int = 0) -> int:
        """Global index of the actuator called ``name`` in ``world``."""
        return self._lookup("actuator", self.actuator_names, name, world)

    @property
    def suggested_dt(self) -> float | None:
        """The time step [s] the model's source suggests: an MJCF file's ``<option timestep>`` (``None``: the file
        sets none, or the model was built procedurally). kamino does not apply it by itself: pass
        ``SolverConfig(dt=model.suggested_dt)``; a ``dt`` above 0.05 s warns and names it."""
        return self.__dict__.get(_EXTRAS, {}).get("suggested_dt")

    @property
    def keyframes(self) -> tuple[Keyframe, ...]:
        """The model's named initial states (an MJCF file's ``<keyframe>``; empty for a procedural model), for
        ``kamino.init_state(model, keyframe="home")`` or ``keyframe=0``. ``replicate`` and ``concat`` of models with
        the same keyframes keep them (each world starts at the key)."""
        return self.__dict__.get(_EXTRAS, {}).get("keyframes", ())

    def keyframe(self, which: str | int) -> Keyframe:
        """The :class:`Keyframe` called ``which``, or at index ``which``; a ``ValueError`` lists the known ones."""
        keys = self.keyframes
        if isinstance(which, str):
            for k in keys:
                if k.name == which:
                    return k
        elif isinstance(which, (int, np.integer)) and not isinstance(which, bool) and -len(keys) <= which < len(keys):
            return keys[which]
        known = [k.name for k in keys]
        raise ValueError(f"keyframe {which!r}: the model has no such keyframe (known: {known}; an MJCF file's "
                         "<keyframe><key name=...> become the model's keyframes)")

    def summary(self) -> str:
        """One line per world kind: bodies, joints, DoFs, constraint rows, independent loops."""
        lines = []
        for w in range(min(self.num_worlds, 8)):
            nb, nj = int(self.world_body_count[w]), int(self.world_joint_count[w])
            js, je = int(self.world_dof_start[w]), int(self.world_dof_start[w] + self.world_dof_count[w])
            actuated = int(np.count_nonzero(self.dof_act_mode[js:je] != ActuationMode.PASSIVE))
            lines.append(
                f"world {w}: {nb} bodies, {nj} joints, {int(self.world_dof_count[w])} dofs ({actuated} actuated), "
                f"{int(self.world_cts_count[w])} constraint rows, {count_loops(self, w)} loops, "
                f"{int(self.world_geom_count[w])} geoms, {int(self.world_pair_count[w])} contact pairs, "
                f"contact capacity {int(self.world_contact_capacity[w])}"
            )
        if self.num_worlds > 8:
            lines.append(f"... ({self.num_worlds} worlds)")
        return "\n".join(lines)


def count_loops(model: Model, world: int = 0) -> int:
    """Independent loops of a world's joint graph (world as a node): joints - bodies - 1 + components."""
    s, c = int(model.world_body_start[world]), int(model.world_body_count[world])
    js, jc = int(model.world_joint_start[world]), int(model.world_joint_count[world])
    parent = list(range(c + 1))  # union-find; node c is the world

    def find(a: int) -> int:
        while parent[a] != a:
            parent[a] = parent[parent[a]]
            a = parent[a]
        return a

    loops = 0
    for j in range(js, js + jc):
        p = int(model.joint_parent[j])
        a = c if p < 0 else p - s
        b = int(model.joint_child[j]) - s
        ra, rb = find(a), find(b)
        if ra == rb:
            loops += 1
        else:
            parent[ra] = rb
    return loops


# ---------------------------------------------------------------------------------------
# Builder
# ---------------------------------------------------------------------------------------


def _vec(value: Any, n: int, what: str) -> np.ndarray:
    try:
        arr = np.asarray(value, dtype=float).reshape(-1)
    except (TypeError, ValueError) as exc:
        raise ModelError(f"{what}: expected {n} numbers, got {value!r}") from exc
    if arr.shape != (n,):
        raise ModelError(f"{what}: expected {n} numbers, got shape {arr.shape}")
    return arr


def _finite(arr: np.ndarray, what: str) -> None:
    if not np.all(np.isfinite(arr)):
        raise ModelError(f"{what}: contains NaN or inf ({np.asarray(arr).tolist()})")


def _check_range(arr: Any, what: str) -> None:
    """Raise a :class:`ModelError` naming ``what`` if a finite entry of ``arr`` exceeds :data:`MAX_PARAMETER` in
    magnitude (infinite entries are left to the field's own rule)."""
    a = np.asarray(arr, dtype=float)
    big = np.isfinite(a) & (np.abs(a) > MAX_PARAMETER)
    if np.any(big):
        raise ModelError(f"{what}: {a[big].flat[0]:g} is beyond the float32 range kamino steps in "
                         f"(|value| <= {MAX_PARAMETER:g}; got {a.tolist()})")


def _check_quat(q: np.ndarray, what: str) -> None:
    n = float(np.linalg.norm(q))
    if n == 0.0:
        raise ModelError(f"{what}: zero quaternion (expected a unit quaternion (x, y, z, w))")
    if abs(n - 1.0) > _QUAT_UNIT_TOL:
        raise ModelError(f"{what}: quaternion norm is {n:.9g}, not 1 (tolerance {_QUAT_UNIT_TOL})")


def _per_dof(value: Any, ndof: int, what: str) -> np.ndarray:
    """A scalar or per-DoF sequence as ``[ndof]`` floats."""
    try:
        return np.broadcast_to(np.asarray(value, dtype=float), (ndof,)).copy()
    except (TypeError, ValueError) as exc:
        raise ModelError(f"{what}: expected a number or {ndof} numbers (one per DoF), got {value!r}") from exc


def _joint_dynamics(name: str, jtype: JointType, ndof: int, actuation: Actuation | None, armature: Any,
                    damping: Any, stiffness: Any, springref: Any) -> dict[str, np.ndarray]:
    """Per-DoF actuation and passive-dynamics arrays of one joint, validated (docs/formulation.md §3.2)."""
    what = f"joint {name!r}"
    out = {
        "armature": _per_dof(armature, ndof, f"{what} armature"),
        "damping": _per_dof(damping, ndof, f"{what} damping"),
        "stiffness": _per_dof(stiffness, ndof, f"{what} stiffness"),
        "springref": _per_dof(springref, ndof, f"{what} springref"),
    }
    if actuation is None:
        actuation = Actuation(mode=ActuationMode.PASSIVE)
    elif not isinstance(actuation, Actuation):
        raise ModelError(f"{what}: actuation must be a kamino.Actuation, got {actuation!r}")
    mode = actuation.resolved_mode()
    out["act_mode"] = np.full(ndof, int(mode), dtype=np.int64)
    out["kp"] = _per_dof(actuation.kp, ndof, f"{what} kp")
    out["kd"] = _per_dof(actuation.kd, ndof, f"{what} kd")
    out["effort_limit"] = _per_dof(actuation.effort_limit, ndof, f"{what} effort_limit")
    for key in ("armature", "damping", "stiffness", "springref", "kp", "kd"):
        _finite(out[key], f"{what} {key}")
    for key in ("armature", "damping", "stiffness", "kp", "kd"):
        if np.any(out[key] < 0):
            raise ModelError(f"{what}: {key} must be >= 0, got {out[key].tolist()}")
    if np.any(np.isnan(out["effort_limit"])) or np.any(out["effort_limit"] <= 0):
        raise ModelError(f"{what}: effort_limit must be > 0 (inf for none), got {out['effort_limit'].tolist()}")
    if mode != ActuationMode.PASSIVE and ndof == 0:
        raise ModelError(f"{what}: a {jtype.name} joint has no DoF to actuate")
    if mode in (ActuationMode.PASSIVE, ActuationMode.EFFORT) and (np.any(out["kp"]) or np.any(out["kd"])):
        raise ModelError(f"{what}: {mode.name.lower()} actuation takes no gains (kp, kd must be 0)")
    if mode == ActuationMode.VELOCITY and np.any(out["kp"]):
        raise ModelError(f"{what}: velocity actuation takes no kp (use mode='position')")
    if mode in (ActuationMode.POSITION, ActuationMode.VELOCITY):
        if jtype not in PD_JOINT_TYPES:
            allowed = ", ".join(t.name for t in PD_JOINT_TYPES)
            raise ModelError(f"{what}: {mode.name.lower()} actuation needs a scalar-coordinate joint ({allowed}), "
                             f"not {jtype.name}")
        gains = out["kp"] + out["kd"] if mode == ActuationMode.POSITION else out["kd"]
        if np.any(gains <= 0):
            raise ModelError(f"{what}: {mode.name.lower()} actuation needs positive gains, got kp={out['kp'].tolist()} "
                             f"kd={out['kd'].tolist()}")
    if np.any(out["stiffness"] > 0) and jtype not in PD_JOINT_TYPES:
        raise ModelError(f"{what}: a passive spring needs a scalar-coordinate joint, not {jtype.name}")
    return out


@dataclasses.dataclass
class _Body:
    name: str
    mass: float
    inertia: np.ndarray
    pos: np.ndarray
    quat: np.ndarray
    vel: np.ndarray
    ang_vel: np.ndarray


@dataclasses.dataclass
class _Joint:
    name: str
    type: JointType
    parent: int
    child: int
    parent_frame: tuple[np.ndarray, np.ndarray]
    child_frame: tuple[np.ndarray, np.ndarray]
    axis: np.ndarray
    axis2: np.ndarray | None
    limits: tuple[np.ndarray, np.ndarray]
    dynamics: dict[str, np.ndarray]  # per-DoF act_mode, kp, kd, effort_limit, armature, damping, ...


@dataclasses.dataclass
class _Geom:
    name: str
    type: GeomType
    body: int
    size: np.ndarray
    pos: np.ndarray
    quat: np.ndarray
    friction: float
    restitution: float
    margin: float
    group: int
    mask: int
    dataid: int = -1


@dataclasses.dataclass
class _HField:
    name: str
    nrow: int
    ncol: int
    size: np.ndarray
    data: np.ndarray  # normalised to [0, 1], row-major (row r at y = -ry + 2 ry r / (nrow - 1))


@dataclasses.dataclass
class _Coupling:
    name: str
    joint_a: int
    joint_b: int
    coef: np.ndarray


@dataclasses.dataclass
class _Actuator:
    name: str
    joint: int
    dof: int
    gear: float
    ctrl_range: tuple[float, float]


#: Joint types a coupling may tie (their single coordinate, zero at the joint's reference).
COUPLING_JOINT_TYPES = (JointType.REVOLUTE, JointType.PRISMATIC)


class ModelBuilder:
    """Builds a single-world :class:`Model` (combine worlds with ``replicate``/``concat``).

    >>> b = ModelBuilder(gravity=(0, 0, -9.81))
    >>> link = b.add_body(mass=1.0, inertia=np.eye(3) * 1e-2, pos=(0, 0, 1))
    >>> b.add_joint(JointType.REVOLUTE, parent=-1, child=link, parent_frame=((0, 0, 1.5), (0, 0, 0, 1)),
    ...             child_frame=((0, 0, 0.5), (0, 0, 0, 1)), axis=(0, 1, 0))
    0
    >>> model = b.finalize()
    """

    def __init__(self, gravity: Sequence[float] = (0.0, 0.0, -9.81)):
        self.gravity = np.asarray(gravity, dtype=float)
        """Gravitational acceleration of the world being built [m/s^2], world frame."""
        self._bodies: list[_Body] = []
        self._joints: list[_Joint] = []
        self._geoms: list[_Geom] = []
        self._hfields: list[_HField] = []
        self._pair_overrides: dict[tuple[int, int], bool] = {}
        self._couplings: list[_Coupling] = []
        self._actuators: list[_Actuator] = []

    # -- bodies ------------------------------------------------------------------------
    def add_body(
        self,
        mass: float,
        inertia: Any,
        pos: Sequence[float] = (0.0, 0.0, 0.0),
        quat: Sequence[float] = (0.0, 0.0, 0.0, 1.0),
        name: str | None = None,
        velocity: Sequence[float] = (0.0, 0.0, 0.0),
        angular_velocity: Sequence[float] = (0.0, 0.0, 0.0),
    ) -> int:
        """Add a rigid body; returns its index. ``pos``/``quat`` give the centre-of-mass frame in
        world coordinates, ``inertia`` is the 3x3 inertia about the CoM in that frame (a 3-vector
        is read as principal moments). ``velocity`` / ``angular_velocity`` set the initial twist
        (CoM linear velocity and angular velocity, both in world coordinates)."""
        idx = len(self._bodies)
        name = name if name is not None else f"body_{idx}"
        inertia_arr = np.asarray(inertia, dtype=float)
        if inertia_arr.shape == (3,):
            inertia_arr = np.diag(inertia_arr)
        try:
            mass = float(mass)
        except (TypeError, ValueError) as exc:
            raise ModelError(f"body {name!r}: mass must be a number, got {mass!r}") from exc
        self._bodies.append(
            _Body(
                name=name,
                mass=mass,
                inertia=inertia_arr,
                pos=_vec(pos, 3, f"body {name!r} pos"),
                quat=_vec(quat, 4, f"body {name!r} quat"),
                vel=_vec(velocity, 3, f"body {name!r} velocity"),
                ang_vel=_vec(angular_velocity, 3, f"body {name!r} angular_velocity"),
            )
        )
        return idx

    # -- joints ------------------------------------------------------------------------
    def add_joint(
        self,
        type: JointType,
        parent: int,
        child: int,
        parent_frame: tuple[Sequence[float], Sequence[float]] = ((0, 0, 0), (0, 0, 0, 1)),
        child_frame: tuple[Sequence[float], Sequence[float]] = ((0, 0, 0), (0, 0, 0, 1)),
        axis: Sequence[float] = (1.0, 0.0, 0.0),
        axis2: Sequence[float] | None = None,
        limits: Any = None,
        actuation: Actuation | None = None,
        name: str | None = None,
        armature: Any = 0.0,
        damping: Any = 0.0,
        stiffness: Any = 0.0,
        springref: Any = 0.0,
    ) -> int:
        """Add a joint between ``parent`` (a body index or -1 for the world) and ``child``.

        ``parent_frame``/``child_frame`` are ``(pos, quat)`` of the joint frame in the parent's and
        child's CoM frames (world frame for ``parent=-1``). ``axis`` is the motion axis in the joint
        frame (REVOLUTE, PRISMATIC, CYLINDRICAL; first axis of UNIVERSAL, whose second is ``axis2``,
        default the joint frame's y). SPHERICAL, CARTESIAN, FIXED and FREE use the joint frame axes.
        ``limits`` is ``(lower, upper)`` per DoF (scalars broadcast; ``±inf`` for no limit), enforced
        as unilateral rows (docs/formulation.md §4.1). ``actuation`` (an :class:`Actuation`) drives every
        DoF of the joint; ``armature`` (reflected inertia), ``damping`` (viscous), ``stiffness`` and
        ``springref`` (a passive spring) are per DoF (scalars broadcast), all treated implicitly
        (docs/formulation.md §3.2). Any joint may close a kinematic loop.
        """
        idx = len(self._joints)
        name = name if name is not None else f"joint_{idx}"
        try:
            jtype = JointType(type)
        except ValueError as exc:
            raise ModelError(f"joint {name!r}: unknown joint type {type!r}") from exc
        ndof = len(JOINT_DOF_ROWS[jtype])
        if limits is None:
            lower, upper = np.full(ndof, -np.inf), np.full(ndof, np.inf)
        else:
            try:
                lo, hi = limits
            except (TypeError, ValueError) as exc:
                raise ModelError(f"joint {name!r}: limits must be (lower, upper), got {limits!r}") from exc
            lower = _per_dof(lo, ndof, f"joint {name!r} lower limit")
            upper = _per_dof(hi, ndof, f"joint {name!r} upper limit")
        dynamics = _joint_dynamics(name, jtype, ndof, actuation, armature, damping, stiffness, springref)
        self._joints.append(
            _Joint(
                name=name,
                type=jtype,
                parent=int(parent),
                child=int(child),
                parent_frame=(
                    _vec(parent_frame[0], 3, f"joint {name!r} parent_frame position"),
                    _vec(parent_frame[1], 4, f"joint {name!r} parent_frame quaternion"),
                ),
                child_frame=(
                    _vec(child_frame[0], 3, f"joint {name!r} child_frame position"),
                    _vec(child_frame[1], 4, f"joint {name!r} child_frame quaternion"),
                ),
                axis=_vec(axis, 3, f"joint {name!r} axis"),
                axis2=None if axis2 is None else _vec(axis2, 3, f"joint {name!r} axis2"),
                limits=(lower, upper),
                dynamics=dynamics,
            )
        )
        return idx

    def add_joint_at(
        self,
        type: JointType,
        parent: int,
        child: int,
        anchor: Sequence[float],
        axis: Sequence[float] = (1.0, 0.0, 0.0),
        axis2: Sequence[float] | None = None,
        limits: Any = None,
        name: str | None = None,
        **dynamics: Any,
    ) -> int:
        """Add a joint whose frame sits at ``anchor`` with motion ``axis`` (and ``axis2``), both in
        world coordinates at the bodies' current (builder) poses. The joint frames are computed so
        that the joint's coordinates are zero at those poses (as for an MJCF reference pose).
        ``dynamics`` are :meth:`add_joint`'s ``actuation``, ``armature``, ``damping``, ``stiffness``,
        ``springref``."""
        name = name if name is not None else f"joint_{len(self._joints)}"
        if not (-1 <= parent < len(self._bodies)) or not (0 <= child < len(self._bodies)):
            raise ModelError(f"joint {name!r}: parent {parent} or child {child} is not a body")

        def pose(i: int) -> tuple[np.ndarray, np.ndarray]:
            if i < 0:
                return np.zeros(3), IDENTITY_QUAT.copy()
            b = self._bodies[i]
            return b.pos, b.quat / np.linalg.norm(b.quat)

        anchor_w = _vec(anchor, 3, f"joint {name!r} anchor")
        (rp, qp), (rc, qc) = pose(parent), pose(child)
        Rp, Rc = quat_to_matrix(qp), quat_to_matrix(qc)
        q_rel = quat_mul(np.array([-qc[0], -qc[1], -qc[2], qc[3]]), qp)  # child frame = parent frame in world
        return self.add_joint(
            type, parent, child,
            parent_frame=(Rp.T @ (anchor_w - rp), IDENTITY_QUAT.copy()),
            child_frame=(Rc.T @ (anchor_w - rc), q_rel / np.linalg.norm(q_rel)),
            axis=Rp.T @ _vec(axis, 3, f"joint {name!r} axis"),
            axis2=None if axis2 is None else Rp.T @ _vec(axis2, 3, f"joint {name!r} axis2"),
            limits=limits, name=name, **dynamics,
        )

    # -- couplings and actuators -------------------------------------------------------
    def add_coupling(self, joint_a: int, joint_b: int | None = None, polycoef: Sequence[float] = (0.0, 1.0),
                     name: str | None = None) -> int:
        """Tie joint ``joint_a``'s coordinate to ``joint_b``'s: ``q_a = sum_k polycoef[k] q_b^k`` (k = 0..4;
        MuJoCo's ``<equality><joint>``; without ``joint_b``, ``q_a = polycoef[0]``). Both joints are
        REVOLUTE or PRISMATIC; coordinates are zero at the joint's reference (the builder pose for
        :meth:`add_joint_at` joints). One bilateral constraint row (docs/conventions.md "Couplings")."""
        idx = len(self._couplings)
        name = name if name is not None else f"coupling_{idx}"
        coef = np.asarray(polycoef, dtype=float).reshape(-1)
        if coef.size == 0 or coef.size > 5:
            raise ModelError(f"coupling {name!r}: polycoef needs 1 to 5 coefficients, got {coef.size}")
        _finite(coef, f"coupling {name!r} polycoef")
        _check_range(coef, f"coupling {name!r} polycoef")
        jb = -1 if joint_b is None else int(joint_b)
        self._couplings.append(_Coupling(name=name, joint_a=int(joint_a), joint_b=jb,
                                         coef=np.concatenate([coef, np.zeros(5 - coef.size)])))
        return idx

    def add_actuator(self, joint: int, name: str | None = None, gear: float = 1.0,
                     ctrl_range: tuple[float, float] | None = None, dof: int = 0) -> int:
        """Name the actuator of DoF ``dof`` of an actuated ``joint`` (the joint's :class:`Actuation`
        sets the mode and gains). ``gear`` maps a control to an effort on EFFORT DoFs (must be 1 for
        POSITION/VELOCITY DoFs) and ``ctrl_range`` clips the control (:meth:`kamino.Control.from_ctrl`).
        Actuated DoFs not named here get an actuator named after their joint at ``finalize``."""
        idx = len(self._actuators)
        lo, hi = (-np.inf, np.inf) if ctrl_range is None else (float(ctrl_range[0]), float(ctrl_range[1]))
        self._actuators.append(_Actuator(name=name if name is not None else "", joint=int(joint), dof=int(dof),
                                         gear=float(gear), ctrl_range=(lo, hi)))
        return idx

    def _finalize_couplings(self) -> list[_Coupling]:
        nj = len(self._joints)
        for c in self._couplings:
            what = f"coupling {c.name!r}"
            for role, j in (("joint_a", c.joint_a), ("joint_b", c.joint_b)):
                if role == "joint_b" and j == -1:
                    continue
                if not (0 <= j < nj):
                    raise ModelError(f"{what}: {role} {j} is not a joint ({nj} joints)")
                jt = self._joints[j].type
                if jt not in COUPLING_JOINT_TYPES:
                    raise ModelError(f"{what}: {role} {self._joints[j].name!r} is a {jt.name} joint; couplings tie "
                                     "REVOLUTE or PRISMATIC joints")
            if c.joint_a == c.joint_b:
                raise ModelError(f"{what}: couples joint {self._joints[c.joint_a].name!r} to itself")
        names = [c.name for c in self._couplings]
        if len(set(names)) != len(names):
            raise ModelError(f"coupling name {next(n for n in names if names.count(n) > 1)!r} is used twice")
        return self._couplings

    def _finalize_actuators(self) -> list[_Actuator]:
        """Explicit actuators in call order, then one per remaining actuated DoF; validated."""
        nj = len(self._joints)
        taken: dict[tuple[int, int], str] = {}
        out = []
        for a in self._actuators:
            if not (0 <= a.joint < nj):
                raise ModelError(f"actuator {a.name!r}: joint {a.joint} does not exist ({nj} joints)")
            jt = self._joints[a.joint]
            name = a.name or (jt.name if len(jt.dynamics["act_mode"]) == 1 else f"{jt.name}_{a.dof}")
            what = f"actuator {name!r}"
            if not (0 <= a.dof < len(jt.dynamics["act_mode"])):
                raise ModelError(f"{what}: joint {jt.name!r} has no DoF {a.dof}")
            mode = ActuationMode(int(jt.dynamics["act_mode"][a.dof]))
            if mode == ActuationMode.PASSIVE:
                raise ModelError(f"{what}: joint {jt.name!r} is passive; give it an Actuation")
            if (a.joint, a.dof) in taken:
                raise ModelError(f"{what}: DoF {a.dof} of joint {jt.name!r} already has actuator "
                                 f"{taken[(a.joint, a.dof)]!r}")
            if not (np.isfinite(a.gear) and a.gear != 0.0):
                raise ModelError(f"{what}: gear must be finite and non-zero, got {a.gear}")
            _check_range(a.gear, f"{what} gear")
            _check_range(a.ctrl_range, f"{what} ctrl_range")
            if mode in (ActuationMode.POSITION, ActuationMode.VELOCITY) and a.gear != 1.0:
                raise ModelError(f"{what}: {mode.name.lower()} actuators take gear 1, got {a.gear}")
            lo, hi = a.ctrl_range
            if np.isnan(lo) or np.isnan(hi) or lo > hi:
                raise ModelError(f"{what}: ctrl_range must be (low, high) with low <= high, got {a.ctrl_range}")
            taken[(a.joint, a.dof)] = name
            out.append(dataclasses.replace(a, name=name))
        for j, jt in enumerate(self._joints):
            modes = jt.dynamics["act_mode"]
            for k in range(len(modes)):
                if modes[k] != ActuationMode.PASSIVE and (j, k) not in taken:
                    name = jt.name if len(modes) == 1 else f"{jt.name}_{k}"
                    out.append(_Actuator(name=name, joint=j, dof=k, gear=1.0, ctrl_range=(-np.inf, np.inf)))
        names = [a.name for a in out]
        if len(set(names)) != len(names):
            raise ModelError(f"actuator name {next(n for n in names if names.count(n) > 1)!r} is used twice")
        return out

    # -- collision geometry ------------------------------------------------------------
    def add_geom(
        self,
        type: GeomType,
        body: int,
        size: Any = (0.0, 0.0, 0.0),
        pos: Sequence[float] = (0.0, 0.0, 0.0),
        quat: Sequence[float] = (0.0, 0.0, 0.0, 1.0),
        friction: float = 1.0,
        restitution: float = 0.0,
        margin: float = 0.0,
        group: int = 1,
        mask: int = 0xFFFFFFFF,
        name: str | None = None,
        hfield: int | None = None,
    ) -> int:
        """Attach a collision geom to ``body`` (-1: the world); returns its index.

        ``size`` follows :class:`GeomType` (a sphere's radius may be a scalar). ``pos``/``quat`` place
        the geom in the body's CoM frame (world frame for -1). ``friction`` is the Coulomb coefficient,
        ``restitution`` the Newton coefficient in [0, 1]; a pair uses the larger of its two geoms'
        values (docs/conventions.md, "Contacts"). ``margin`` [m] widens contact activation. Two geoms
        may touch when ``group_a & mask_b`` and ``group_b & mask_a`` are both non-zero, they are on
        different bodies not both the world, and the bodies are not joined by a joint other than FREE
        (:meth:`set_collision` overrides all of this for one pair). A ``GeomType.HFIELD`` geom names its grid
        with ``hfield`` (an index from :meth:`add_hfield`), sits on the world (``body=-1``) and takes its size
        from the grid (``size`` is ignored).
        """
        idx = len(self._geoms)
        name = name if name is not None else f"geom_{idx}"
        try:
            gtype = GeomType(type)
        except ValueError as exc:
            raise ModelError(f"geom {name!r}: unknown geom type {type!r}") from exc
        sz = np.asarray(size, dtype=float).reshape(-1)
        if sz.size > 3:
            raise ModelError(f"geom {name!r}: size has {sz.size} numbers, at most 3")
        sz = np.concatenate([sz, np.zeros(3 - sz.size)])
        self._geoms.append(
            _Geom(name=name, type=gtype, body=int(body), size=sz, pos=_vec(pos, 3, f"geom {name!r} pos"),
                  quat=_vec(quat, 4, f"geom {name!r} quat"), friction=float(friction),
                  restitution=float(restitution), margin=float(margin), group=int(group), mask=int(mask),
                  dataid=-1 if hfield is None else int(hfield))
        )
        return idx

    def add_hfield(self, nrow: int, ncol: int, size: Sequence[float], elevation: Any, name: str | None = None) -> int:
        """Add a heightfield grid (MuJoCo's ``<hfield>``); returns its index for :meth:`add_geom`'s ``hfield``.

        ``elevation`` holds ``nrow x ncol`` heights, row-major, row ``r`` at ``y = -ry + 2 ry r / (nrow - 1)`` and
        column ``c`` at ``x = -rx + 2 rx c / (ncol - 1)`` of the geom's frame (MuJoCo's ``hfield_data`` order; an
        MJCF ``elevation`` attribute lists the rows the other way round, from ``+ry`` down). As MuJoCo does, the
        heights are normalised to ``[0, 1]`` (lowest 0, highest 1; all 0 when they are all equal) and scaled by
        ``z_top``: ``size = (rx, ry, z_top, z_base)``, all positive, the solid reaching ``z_base`` below ``z = 0``.
        """
        idx = len(self._hfields)
        name = name if name is not None else f"hfield_{idx}"
        what = f"hfield {name!r}"
        counts = {}
        for key, value in (("nrow", nrow), ("ncol", ncol)):
            if isinstance(value, bool) or not isinstance(value, numbers.Integral) or int(value) < 2:
                raise ModelError(f"{what}: {key} must be an integer >= 2 (a grid needs two rows and two columns), "
                                 f"got {value!r}")
            counts[key] = int(value)
        sz = _vec(size, 4, f"{what} size (rx, ry, z_top, z_base)")
        _finite(sz, f"{what} size")
        _check_range(sz, f"{what} size")
        if np.any(sz <= 0):
            raise ModelError(f"{what}: size (rx, ry, z_top, z_base) must be 4 positive numbers, got {sz.tolist()}")
        try:
            data = np.asarray(elevation, dtype=float).reshape(-1)
        except (TypeError, ValueError) as exc:
            raise ModelError(f"{what}: elevation must be numbers, got {elevation!r}") from exc
        n = counts["nrow"] * counts["ncol"]
        if data.size != n:
            raise ModelError(f"{what}: elevation has {data.size} values, expected nrow * ncol = {counts['nrow']} * "
                             f"{counts['ncol']} = {n}")
        _finite(data, f"{what} elevation")
        _check_range(data, f"{what} elevation")
        lo, hi = float(data.min()), float(data.max())
        data = (data - lo) / (hi - lo) if hi > lo else np.zeros(n)
        self._hfields.append(_HField(name=name, nrow=counts["nrow"], ncol=counts["ncol"], size=sz, data=data))
        return idx

    def set_collision(self, geom_a: int, geom_b: int, enabled: bool) -> None:
        """Force the contact pair ``(geom_a, geom_b)`` on or off, overriding group/mask filtering and
        the automatic exclusion of bodies joined by a joint."""
        key = (min(int(geom_a), int(geom_b)), max(int(geom_a), int(geom_b)))
        self._pair_overrides[key] = bool(enabled)

    def _validate_geom(self, i: int, g: _Geom, nb: int) -> None:
        what = f"geom {g.name!r} (index {i})"
        for field_name, arr in (("size", g.size), ("pos", g.pos), ("quat", g.quat)):
            _finite(arr, f"{what} {field_name}")
            _check_range(arr, f"{what} {field_name}")
        _check_range(g.friction, f"{what} friction")
        _check_range(g.margin, f"{what} margin")
        if not (-1 <= g.body < nb):
            raise ModelError(f"{what}: body {g.body} does not exist ({nb} bodies; -1 is the world)")
        if g.type == GeomType.HFIELD:
            if g.body != -1:
                raise ModelError(f"{what}: a heightfield is static: attach it to the world (body -1), not to body "
                                 f"{g.body}")
            if not (0 <= g.dataid < len(self._hfields)):
                raise ModelError(f"{what}: hfield {g.dataid} does not exist ({len(self._hfields)} heightfields; "
                                 "add one with add_hfield and pass its index as hfield=)")
        elif g.dataid != -1:
            raise ModelError(f"{what}: hfield={g.dataid} given for a {g.type.name} geom (only HFIELD geoms take one)")
        need = _GEOM_SIZE_COUNT[g.type]
        if np.any(g.size[:need] <= 0):
            raise ModelError(f"{what}: a {g.type.name} needs {need} positive size value(s), got {g.size.tolist()}")
        _check_quat(g.quat, f"{what} quat")
        if not (np.isfinite(g.friction) and g.friction >= 0):
            raise ModelError(f"{what}: friction must be >= 0, got {g.friction}")
        if not (0.0 <= g.restitution <= 1.0):
            raise ModelError(f"{what}: restitution must lie in [0, 1], got {g.restitution}")
        if not (np.isfinite(g.margin) and g.margin >= 0):
            raise ModelError(f"{what}: margin must be >= 0, got {g.margin}")

    def _contact_pairs(self) -> list[tuple[int, int]]:
        """Candidate pairs ``(a, b)`` with ``type_a <= type_b`` after filtering (only pairs
        that can touch generate work; docs/conventions.md, "Contacts"). A FREE joint constrains nothing
        (no rows in ``JOINT_CONSTRAINT_ROWS``, docs/formulation.md §2.4), so it does not exclude its bodies'
        pairs: a free body collides with the world's geoms. Every other joint type excludes them."""
        joined = {(min(j.parent, j.child), max(j.parent, j.child)) for j in self._joints
                  if j.type != JointType.FREE}
        for key in self._pair_overrides:
            for gi in key:
                if not (0 <= gi < len(self._geoms)):
                    raise ModelError(f"set_collision: geom {gi} does not exist ({len(self._geoms)} geoms)")
        pairs = []
        for a in range(len(self._geoms)):
            for b in range(a + 1, len(self._geoms)):
                ga, gb = self._geoms[a], self._geoms[b]
                override = self._pair_overrides.get((a, b))
                if ga.body == gb.body or (ga.body < 0 and gb.body < 0):
                    if override:
                        raise ModelError(f"set_collision: geoms {ga.name!r} and {gb.name!r} are on the same body "
                                         "(or both on the world) and cannot collide")
                    continue
                if (ga.type, gb.type) == (GeomType.PLANE, GeomType.PLANE):
                    if override:
                        raise ModelError(f"set_collision: plane-plane contact ({ga.name!r}, {gb.name!r}) is not "
                                         "supported")
                    continue
                if override is None:
                    ok = (ga.group & gb.mask) != 0 and (gb.group & ga.mask) != 0
                    ok = ok and (min(ga.body, gb.body), max(ga.body, gb.body)) not in joined
                else:
                    ok = override
                if ok:
                    key = (ga.type, gb.type) if ga.type <= gb.type else (gb.type, ga.type)
                    if key not in CONTACT_POINTS:
                        raise ModelError(f"geoms {ga.name!r} and {gb.name!r}: contact between a {key[0].name} and a "
                                         f"{key[1].name} is not supported; disable the pair with set_collision or "
                                         "group/mask")
                    pairs.append((a, b) if ga.type <= gb.type else (b, a))
        return pairs

    # -- validation and assembly -----------------------------------------------------
    def _validate_body(self, i: int, b: _Body) -> None:
        what = f"body {b.name!r} (index {i})"
        for field_name, arr in (("inertia", b.inertia), ("pos", b.pos), ("quat", b.quat),
                                ("velocity", b.vel), ("angular_velocity", b.ang_vel)):
            _finite(np.asarray(arr), f"{what} {field_name}")
            _check_range(arr, f"{what} {field_name}")
        if not np.isfinite(b.mass):  # b.mass is a float (add_body converts or raises ModelError)
            raise ModelError(f"{what}: mass is {b.mass}")
        if b.mass <= 0.0:
            raise ModelError(f"{what}: mass must be > 0, got {b.mass}")
        if b.mass < MIN_MASS:
            raise ModelError(f"{what}: mass {b.mass:g} is below {MIN_MASS:g} kg (MuJoCo's minimum; check the units)")
        _check_range(b.mass, f"{what} mass")
        I = b.inertia
        if I.shape != (3, 3):
            raise ModelError(f"{what}: inertia must be 3x3 or 3 principal moments, got shape {I.shape}")
        scale = max(float(np.abs(I).max()), 1e-300)
        if np.abs(I - I.T).max() > 1e-9 * scale:
            raise ModelError(f"{what}: inertia is not symmetric")
        eig = np.linalg.eigvalsh(0.5 * (I + I.T))
        if eig[0] <= 0.0:
            raise ModelError(f"{what}: inertia is not positive definite (eigenvalues {eig.tolist()})")
        if eig[0] < MIN_MASS:
            raise ModelError(f"{what}: smallest principal moment of inertia {eig[0]:g} is below {MIN_MASS:g} kg m^2 "
                             f"(MuJoCo's minimum; principal moments {eig.tolist()})")
        # physical inertia: each principal moment <= sum of the other two (relative tolerance 1e-9)
        if eig[2] > (eig[0] + eig[1]) * (1.0 + 1e-9):
            raise ModelError(
                f"{what}: inertia violates the triangle inequality (principal moments {eig.tolist()})"
            )
        _check_quat(b.quat, f"{what} quat")

    def _validate_joint(self, j: int, jt: _Joint, nb: int) -> None:
        what = f"joint {jt.name!r} (index {j})"
        for field_name, arr in (
            ("parent_frame position", jt.parent_frame[0]), ("parent_frame quaternion", jt.parent_frame[1]),
            ("child_frame position", jt.child_frame[0]), ("child_frame quaternion", jt.child_frame[1]),
            ("axis", jt.axis),
        ):
            _finite(arr, f"{what} {field_name}")
            _check_range(arr, f"{what} {field_name}")
        if jt.axis2 is not None:
            _finite(jt.axis2, f"{what} axis2")
            _check_range(jt.axis2, f"{what} axis2")
        lo, hi = jt.limits
        if np.any(np.isnan(lo)) or np.any(np.isnan(hi)):
            raise ModelError(f"{what}: limits contain NaN")
        _check_range(lo, f"{what} lower limit")
        _check_range(hi, f"{what} upper limit")
        for key in ("armature", "damping", "stiffness", "springref", "kp", "kd", "effort_limit"):
            _check_range(jt.dynamics[key], f"{what} {key}")
        if not (-1 <= jt.parent < nb):
            raise ModelError(f"{what}: parent body {jt.parent} does not exist ({nb} bodies; -1 is the world)")
        if not (0 <= jt.child < nb):
            raise ModelError(f"{what}: child body {jt.child} does not exist ({nb} bodies)")
        if jt.parent == jt.child:
            raise ModelError(f"{what}: connects body {jt.child} to itself")
        _check_quat(jt.parent_frame[1], f"{what} parent_frame quaternion")
        _check_quat(jt.child_frame[1], f"{what} child_frame quaternion")
        uses_axis = jt.type in (JointType.REVOLUTE, JointType.PRISMATIC, JointType.CYLINDRICAL, JointType.UNIVERSAL)
        if uses_axis and np.linalg.norm(jt.axis) < MIN_AXIS_LENGTH:
            raise ModelError(f"{what}: zero-length axis {jt.axis.tolist()} (length below {MIN_AXIS_LENGTH:g})")
        if jt.axis2 is not None:
            if np.linalg.norm(jt.axis2) < MIN_AXIS_LENGTH:
                raise ModelError(f"{what}: zero-length axis2 {jt.axis2.tolist()} (length below {MIN_AXIS_LENGTH:g})")
            a1 = jt.axis / np.linalg.norm(jt.axis)
            a2 = jt.axis2 / np.linalg.norm(jt.axis2)
            if np.linalg.norm(np.cross(a1, a2)) < 1e-6:
                raise ModelError(f"{what}: axis2 is parallel to axis")
        bad = np.nonzero(lo > hi)[0]
        if bad.size:
            k = int(bad[0])
            raise ModelError(f"{what}: lower limit {lo[k]} > upper limit {hi[k]} (DoF {k})")

    def full_contact_capacity(self, pairs: list[tuple[int, int]] | None = None) -> int:
        """The contacts the candidate pairs can produce together (``CONTACT_POINTS`` per pair): the default
        capacity of :meth:`finalize`, which never overflows."""
        pairs = self._contact_pairs() if pairs is None else pairs
        return sum(CONTACT_POINTS[(self._geoms[a].type, self._geoms[b].type)] for a, b in pairs)

    def finalize(self, contact_capacity: int | None = None) -> Model:
        """Validate and return the single-world :class:`Model`; raises :class:`ModelError`.

        ``contact_capacity`` bounds the contacts of the world (3 constraint rows each). The default
        is what the candidate pairs can produce together (``CONTACT_POINTS`` per pair), which never
        overflows; a smaller capacity keeps the first contacts in pair order and counts the rest in
        ``state.info.contact_overflow``.
        """
        _finite(self.gravity, "gravity")
        _check_range(self.gravity, "gravity")
        if self.gravity.shape != (3,):
            raise ModelError(f"gravity: expected 3 numbers, got shape {self.gravity.shape}")
        nb = len(self._bodies)
        if nb == 0:
            raise ModelError("model has no bodies")
        for i, b in enumerate(self._bodies):
            self._validate_body(i, b)
        for j, jt in enumerate(self._joints):
            self._validate_joint(j, jt, nb)
        names = [b.name for b in self._bodies]
        if len(set(names)) != len(names):
            dup = next(n for n in names if names.count(n) > 1)
            raise ModelError(f"body name {dup!r} is used twice")
        jnames = [j.name for j in self._joints]
        if len(set(jnames)) != len(jnames):
            dup = next(n for n in jnames if jnames.count(n) > 1)
            raise ModelError(f"joint name {dup!r} is used twice")
        for i, g in enumerate(self._geoms):
            self._validate_geom(i, g, nb)
        gnames = [g.name for g in self._geoms]
        if len(set(gnames)) != len(gnames):
            dup = next(n for n in gnames if gnames.count(n) > 1)
            raise ModelError(f"geom name {dup!r} is used twice")
        pairs = self._contact_pairs()
        full_capacity = self.full_contact_capacity(pairs)
        if contact_capacity is None:
            contact_capacity = full_capacity
        elif int(contact_capacity) < 0:
            raise ModelError(f"contact_capacity must be >= 0, got {contact_capacity}")
        contact_capacity = int(contact_capacity) if pairs else 0

        body_q0 = np.array([np.concatenate([b.pos, b.quat / np.linalg.norm(b.quat)]) for b in self._bodies])
        body_u0 = np.array([np.concatenate([b.vel, b.ang_vel]) for b in self._bodies])
        nj = len(self._joints)
        anchor_B, anchor_F = np.zeros((nj, 3)), np.zeros((nj, 3))
        frame_B, frame_F = np.tile(IDENTITY_QUAT, (nj, 1)), np.tile(IDENTITY_QUAT, (nj, 1))
        dof_count = np.zeros(nj, dtype=np.int64)
        coord_count = np.zeros(nj, dtype=np.int64)
        cts_count = np.zeros(nj, dtype=np.int64)
        lowers, uppers = [], []
        for j, jt in enumerate(self._joints):
            anchor_B[j], anchor_F[j] = jt.parent_frame[0], jt.child_frame[0]
            if jt.type in (JointType.REVOLUTE, JointType.PRISMATIC, JointType.CYLINDRICAL):
                A = axis_frame(jt.axis)
            elif jt.type == JointType.UNIVERSAL:
                A = axis_frame(jt.axis, jt.axis2 if jt.axis2 is not None else np.array([0.0, 1.0, 0.0]))
            else:
                A = np.eye(3)
            qa = matrix_to_quat(A)
            frame_B[j] = quat_mul(jt.parent_frame[1] / np.linalg.norm(jt.parent_frame[1]), qa)
            frame_F[j] = quat_mul(jt.child_frame[1] / np.linalg.norm(jt.child_frame[1]), qa)
            dof_count[j] = len(JOINT_DOF_ROWS[jt.type])
            coord_count[j] = JOINT_NUM_COORDS[jt.type]
            cts_count[j] = len(JOINT_CONSTRAINT_ROWS[jt.type])
            lowers.append(jt.limits[0])
            uppers.append(jt.limits[1])

        def dyn(key: str, dtype=float) -> np.ndarray:
            parts = [jt.dynamics[key] for jt in self._joints]
            return np.concatenate(parts).astype(dtype) if parts else np.zeros(0, dtype)

        hfields = self._hfields
        for g in self._geoms:
            if g.type == GeomType.HFIELD:
                hs = hfields[g.dataid].size
                g.size = np.array([hs[0], hs[1], max(hs[2], hs[3])])
        hnames = [h.name for h in hfields]
        if len(set(hnames)) != len(hnames):
            raise ModelError(f"hfield name {next(n for n in hnames if hnames.count(n) > 1)!r} is used twice")
        h_count = np.array([h.nrow * h.ncol for h in hfields], dtype=np.int64)
        nh = len(hfields)
        geoms = self._geoms
        ng = len(geoms)
        couplings = self._finalize_couplings()
        nk = len(couplings)
        actuators = self._finalize_actuators()
        na = len(actuators)
        act_dof = np.array([_prefix(dof_count)[a.joint] + a.dof for a in actuators], dtype=np.int64)

        one = np.array([0], dtype=np.int64)
        model = Model(
            num_worlds=1,
            gravity=self.gravity[None, :].copy(),
            body_mass=np.array([b.mass for b in self._bodies]),
            body_inertia=np.array([0.5 * (b.inertia + b.inertia.T) for b in self._bodies]),
            body_q0=body_q0,
            body_u0=body_u0,
            body_world=np.zeros(nb, dtype=np.int64),
            body_names=tuple(names),
            world_body_start=one.copy(),
            world_body_count=np.array([nb], dtype=np.int64),
            joint_type=np.array([int(j.type) for j in self._joints], dtype=np.int64),
            joint_parent=np.array([j.parent for j in self._joints], dtype=np.int64),
            joint_child=np.array([j.child for j in self._joints], dtype=np.int64),
            joint_world=np.zeros(nj, dtype=np.int64),
            joint_anchor_B=anchor_B,
            joint_anchor_F=anchor_F,
            joint_frame_B=frame_B,
            joint_frame_F=frame_F,
            joint_names=tuple(jnames),
            world_joint_start=one.copy(),
            world_joint_count=np.array([nj], dtype=np.int64),
            joint_dof_start=_prefix(dof_count),
            joint_dof_count=dof_count,
            joint_coord_start=_prefix(coord_count),
            joint_coord_count=coord_count,
            joint_cts_start=_prefix(cts_count),
            joint_cts_count=cts_count,
            dof_lower=np.concatenate(lowers) if lowers else np.zeros(0),
            dof_upper=np.concatenate(uppers) if uppers else np.zeros(0),
            dof_act_mode=dyn("act_mode", np.int64),
            dof_kp=dyn("kp"),
            dof_kd=dyn("kd"),
            dof_effort_limit=dyn("effort_limit"),
            dof_armature=dyn("armature"),
            dof_damping=dyn("damping"),
            dof_stiffness=dyn("stiffness"),
            dof_springref=dyn("springref"),
            world_dof_start=one.copy(),
            world_dof_count=np.array([dof_count.sum()], dtype=np.int64),
            world_coord_start=one.copy(),
            world_coord_count=np.array([coord_count.sum()], dtype=np.int64),
            world_cts_start=one.copy(),
            world_cts_count=np.array([cts_count.sum()], dtype=np.int64),
            geom_type=np.array([int(g.type) for g in geoms], dtype=np.int64),
            geom_body=np.array([g.body for g in geoms], dtype=np.int64),
            geom_world=np.zeros(ng, dtype=np.int64),
            geom_pos=np.array([g.pos for g in geoms]).reshape(ng, 3),
            geom_quat=np.array([g.quat / np.linalg.norm(g.quat) for g in geoms]).reshape(ng, 4),
            geom_size=np.array([g.size for g in geoms]).reshape(ng, 3),
            geom_friction=np.array([g.friction for g in geoms]),
            geom_restitution=np.array([g.restitution for g in geoms]),
            geom_margin=np.array([g.margin for g in geoms]),
            geom_names=tuple(gnames),
            world_geom_start=one.copy(),
            world_geom_count=np.array([ng], dtype=np.int64),
            geom_dataid=np.array([g.dataid for g in geoms], dtype=np.int64),
            hfield_nrow=np.array([h.nrow for h in hfields], dtype=np.int64),
            hfield_ncol=np.array([h.ncol for h in hfields], dtype=np.int64),
            hfield_size=np.array([h.size for h in hfields]).reshape(nh, 4),
            hfield_adr=_prefix(h_count),
            hfield_world=np.zeros(nh, dtype=np.int64),
            hfield_names=tuple(hnames),
            hfield_data=np.concatenate([h.data for h in hfields]) if hfields else np.zeros(0),
            world_hfield_start=one.copy(),
            world_hfield_count=np.array([nh], dtype=np.int64),
            world_hfield_data_start=one.copy(),
            world_hfield_data_count=np.array([h_count.sum()], dtype=np.int64),
            pair_geom_a=np.array([a for a, _ in pairs], dtype=np.int64),
            pair_geom_b=np.array([b for _, b in pairs], dtype=np.int64),
            pair_world=np.zeros(len(pairs), dtype=np.int64),
            world_pair_start=one.copy(),
            world_pair_count=np.array([len(pairs)], dtype=np.int64),
            world_contact_capacity=np.array([contact_capacity], dtype=np.int64),
            coupling_joint_a=np.array([c.joint_a for c in couplings], dtype=np.int64),
            coupling_joint_b=np.array([c.joint_b for c in couplings], dtype=np.int64),
            coupling_coef=np.array([c.coef for c in couplings]).reshape(nk, 5),
            coupling_world=np.zeros(nk, dtype=np.int64),
            coupling_names=tuple(c.name for c in couplings),
            world_coupling_start=one.copy(),
            world_coupling_count=np.array([nk], dtype=np.int64),
            actuator_dof=act_dof.reshape(na),
            actuator_gear=np.array([a.gear for a in actuators]).reshape(na),
            actuator_ctrl_range=np.array([a.ctrl_range for a in actuators]).reshape(na, 2),
            actuator_world=np.zeros(na, dtype=np.int64),
            actuator_names=tuple(a.name for a in actuators),
            world_actuator_start=one.copy(),
            world_actuator_count=np.array([na], dtype=np.int64),
        )
        return freeze_arrays(model)


# ---------------------------------------------------------------------------------------
# Multi-world models
# ---------------------------------------------------------------------------------------

def is_frozen(model: Model) -> bool:
    """Whether every array of ``model`` is read-only, as :class:`ModelBuilder`, ``concat`` and ``replicate`` leave
    them. ``Model`` is a frozen dataclass compared by identity, so a value derived from a frozen model and kept on
    the model object (:func:`derived`) cannot go stale."""
    return all(not v.flags.writeable for f in dataclasses.fields(model)
               if isinstance(v := getattr(model, f.name), np.ndarray))


_DERIVED = "_derived"  # the attribute of a Model that holds what :func:`derived` keeps
_DERIVED_LOCK = threading.Lock()


def derived(model: Model, key: Hashable, build: Callable[[], T]) -> T:
    """``build()``, a value computed from ``model`` alone (host tables, a compiled program, the simulators of the
    one-call entry points ``kamino.step`` / ``rollout``), kept on the model object under ``key`` when the model is
    frozen (:func:`is_frozen`): it lives and goes with the model. A model whose arrays can still change gets a new
    value on every call. Two threads asking for the same key at once get the same value (the first one stored)."""
    if not is_frozen(model):
        return build()
    store = model.__dict__.get(_DERIVED)
    if store is None:
        with _DERIVED_LOCK:
            store = model.__dict__.setdefault(_DERIVED, {})
    if key not in store:
        value = build()
        with _DERIVED_LOCK:
            store.setdefault(key, value)
    return store[key]


def freeze_arrays(obj):
    """``obj`` (a dataclass: a :class:`Model`, or tables derived from one and cached) with every numpy array field
    made read-only, so that a value shared by its callers cannot be changed under them."""
    for f in dataclasses.fields(obj):
        v = getattr(obj, f.name)
        if isinstance(v, np.ndarray):
            v.flags.writeable = False
    return obj


def _prefix(counts: np.ndarray) -> np.ndarray:
    """Exclusive prefix sum (the start offsets of consecutive segments); empty for no segments."""
    counts = np.asarray(counts, dtype=np.int64)
    return (np.cumsum(counts) - counts).astype(np.int64)


def concat(models: Sequence[Model]) -> Model:
    """Stack models (each with one or more worlds) into one multi-world model, in order.

    Worlds may differ (heterogeneous): storage is the sum of per-world sizes; per-world offsets,
    and every index field (bodies of joints and geoms, geoms of pairs, worlds), are shifted here.
    """
    if isinstance(models, Model):
        raise TypeError("concat: models must be a sequence of kamino.Model, got one Model "
                        "(write kamino.concat([a, b]), or kamino.replicate(model, n) for copies)")
    try:
        models = list(models)
    except TypeError:
        raise TypeError(f"concat: models must be a sequence of kamino.Model, got {type(models).__name__}") from None
    if not models:
        raise ModelError("concat: no models given")
    for k, m in enumerate(models):
        if not isinstance(m, Model):
            raise TypeError(f"concat: models[{k}] is a {type(m).__name__}, expected a kamino.Model "
                            "(kamino.models.fourbar(), ModelBuilder.finalize(), kamino.load_mjcf(...))")
    out: dict[str, Any] = {"num_worlds": sum(m.num_worlds for m in models)}
    shifts = {"body": _prefix([m.num_bodies for m in models]), "geom": _prefix([m.num_geoms for m in models]),
              "world": _prefix([m.num_worlds for m in models]), "joint": _prefix([m.num_joints for m in models]),
              "dof": _prefix([m.num_dofs for m in models]), "hfield": _prefix([m.num_hfields for m in models]),
              "hfield_data": _prefix([m.hfield_data.shape[0] for m in models])}
    for f in dataclasses.fields(Model):
        name = f.name
        if name == "num_worlds" or (name.startswith("world_") and name.endswith("_start")):
            continue
        first = getattr(models[0], name)
        if isinstance(first, tuple):
            out[name] = tuple(itertools.chain.from_iterable(getattr(m, name) for m in models))
            continue
        out[name] = _concat_shifted(name, [getattr(m, name) for m in models], shifts)
    return _shared_extras(models, _with_starts(out))


def _concat_shifted(name: str, parts: list[np.ndarray], shifts: dict[str, np.ndarray]) -> np.ndarray:
    """The parts (field ``name`` of each model) concatenated, each part's entity indices moved by its model's offset
    ``shifts[entity][k]`` if ``name`` is an index field (:data:`_INDEX_FIELDS`), as :func:`_shift_index` moves them:
    one numpy operation over all parts, whatever their number."""
    cat = np.concatenate(parts, axis=0)
    entity = _INDEX_FIELDS.get(name)
    if entity is None:
        return cat
    off = np.repeat(shifts[entity], [len(p) for p in parts]).reshape(-1, *([1] * (cat.ndim - 1)))
    return np.where(cat >= 0, cat + off, cat) if entity in _KEEP_NEGATIVE else cat + off


def _shift_index(name: str, v: np.ndarray, offsets: dict[str, int]) -> np.ndarray:
    """``v`` (field ``name``) with its entity indices moved by ``offsets[entity]`` if it is an index field
    (:data:`_INDEX_FIELDS`); -1 (the world, or no joint) stays -1 for body and joint indices."""
    shift = _INDEX_FIELDS.get(name)
    if shift is None:
        return v
    off = offsets[shift]
    return np.where(v >= 0, v + off, v) if shift in _KEEP_NEGATIVE else v + off


def _with_starts(out: dict[str, Any]) -> Model:
    """The frozen :class:`Model` of the fields ``out`` with every ``*_start`` offset recomputed from its counts."""
    for f in dataclasses.fields(Model):
        if f.name.startswith("world_") and f.name.endswith("_start"):
            out[f.name] = _prefix(out[f.name[: -len("_start")] + "_count"])
    for entity in ("joint_dof", "joint_coord", "joint_cts"):
        out[entity + "_start"] = _prefix(out[entity + "_count"])
    return freeze_arrays(Model(**out))


#: Index fields shifted by ``concat``: which entity's offset they get (-1 stays -1 for bodies).
_INDEX_FIELDS = {"joint_parent": "body", "joint_child": "body", "geom_body": "body", "body_world": "world",
                 "joint_world": "world", "geom_world": "world", "pair_world": "world", "pair_geom_a": "geom",
                 "pair_geom_b": "geom", "coupling_joint_a": "joint", "coupling_joint_b": "joint",
                 "coupling_world": "world", "actuator_dof": "dof", "actuator_world": "world",
                 "geom_dataid": "hfield", "hfield_adr": "hfield_data", "hfield_world": "world"}
#: Entities whose index fields keep -1 (the world, no joint, no heightfield) through the shifts.
_KEEP_NEGATIVE = ("body", "joint", "hfield")


#: The entity axis of each field prefix (the leading axis of the field's array); ``world`` fields are per world.
_PREFIX_ENTITY = (("body_", "body"), ("joint_", "joint"), ("dof_", "dof"), ("geom_", "geom"), ("pair_", "pair"),
                  ("coupling_", "coupling"), ("actuator_", "actuator"), ("hfield_data", "hfield_data"),
                  ("hfield_", "hfield"), ("world_", "world"), ("gravity", "world"))


#: The per-world entities (``world_<entity>_start/count``) besides the worlds themselves.
_ENTITIES = ("body", "joint", "dof", "geom", "pair", "coupling", "actuator", "hfield", "hfield_data")


def take_worlds(model: Model, start: int, stop: int) -> Model:
    """Worlds ``start .. stop - 1`` of ``model`` as a model of their own (the inverse of :func:`concat`: entities
    are stored world after world, so each kind is one contiguous range, and index fields are shifted back).
    ``concat([take_worlds(m, 0, k), take_worlds(m, k, m.num_worlds)])`` equals ``m``."""
    if not isinstance(model, Model):
        raise TypeError(f"take_worlds: model must be a kamino.Model, got {type(model).__name__}")
    start, stop = int(start), int(stop)
    if not 0 <= start < stop <= model.num_worlds:
        raise ModelError(f"take_worlds(start={start}, stop={stop}): need 0 <= start < stop <= num_worlds "
                         f"({model.num_worlds})")
    ranges = {"world": (start, stop)}
    for entity in _ENTITIES:
        first, count = getattr(model, f"world_{entity}_start"), getattr(model, f"world_{entity}_count")
        ranges[entity] = (int(first[start]), int(first[stop - 1] + count[stop - 1]))
    out: dict[str, Any] = {"num_worlds": stop - start}
    for f in dataclasses.fields(Model):
        name = f.name
        if name == "num_worlds" or (name.startswith("world_") and name.endswith("_start")):
            continue
        if name in ("joint_dof_start", "joint_coord_start", "joint_cts_start"):
            continue
        entity = next(e for prefix, e in _PREFIX_ENTITY if name.startswith(prefix))
        lo, hi = ranges[entity]
        v = getattr(model, name)[lo:hi]
        if isinstance(v, np.ndarray):
            out[name] = _shift_index(name, v, {e: -r[0] for e, r in ranges.items()}).copy()
        else:
            out[name] = tuple(v)
    return _shared_extras([model], _with_starts(out))


def same_model(a: Model, b: Model) -> bool:
    """Whether two models are equal field by field (arrays by value)."""
    for f in dataclasses.fields(Model):
        x, y = getattr(a, f.name), getattr(b, f.name)
        if isinstance(x, np.ndarray):
            if x.shape != y.shape or not np.array_equal(x, y):
                return False
        elif x != y:
            return False
    return True


#: The fields :func:`fingerprint` reads: the mechanism of each world (names, joint types and frames, geoms, pairs,
#: couplings, actuated DoFs), not its physical parameters (masses, inertias, gains, limits, friction, gravity,
#: initial pose).
_FINGERPRINT_FIELDS = ("body_names", "joint_names", "joint_type", "joint_parent", "joint_child", "joint_anchor_B",
                       "joint_anchor_F", "joint_frame_B", "joint_frame_F", "joint_dof_count", "geom_type", "geom_body",
                       "geom_pos", "geom_quat", "geom_size", "pair_geom_a", "pair_geom_b", "world_contact_capacity",
                       "coupling_joint_a", "coupling_joint_b", "coupling_coef", "actuator_dof", "geom_dataid",
                       "hfield_nrow", "hfield_ncol", "hfield_size", "hfield_adr", "hfield_data")


def _world_digest(model: Model, w: int) -> bytes:
    """A hash of world ``w``'s mechanism (:data:`_FINGERPRINT_FIELDS`, its indices made world-local)."""
    starts = {e: int(getattr(model, f"world_{e}_start")[w]) for e in _ENTITIES}
    starts["world"] = w
    h = hashlib.blake2b(digest_size=8)
    for name in _FINGERPRINT_FIELDS:
        entity = next(e for prefix, e in _PREFIX_ENTITY if name.startswith(prefix))
        lo = starts[entity]
        hi = lo + (1 if entity == "world" else int(getattr(model, f"world_{entity}_count")[w]))
        value = getattr(model, name)[lo:hi]
        if isinstance(value, np.ndarray):
            value = _shift_index(name, value, {e: -s for e, s in starts.items()})
            h.update(f"{name}{value.shape}".encode())
            h.update(np.ascontiguousarray(value, dtype=np.float64).tobytes())
        else:
            h.update(f"{name}={value!r}".encode())
    return h.digest()


def _worlds_alike(model: Model) -> bool:
    """Whether every world's mechanism (:data:`_FINGERPRINT_FIELDS`, indices world-local) equals world 0's."""
    W = model.num_worlds
    entities = _ENTITIES
    if any(np.any(getattr(model, f"world_{e}_count") != getattr(model, f"world_{e}_count")[0]) for e in entities):
        return False
    for name in _FINGERPRINT_FIELDS:
        entity = next(e for prefix, e in _PREFIX_ENTITY if name.startswith(prefix))
        per = 1 if entity == "world" else int(getattr(model, f"world_{entity}_count")[0])
        value = getattr(model, name)
        if isinstance(value, tuple):
            if value != value[:per] * W:
                return False
            continue
        shift = _INDEX_FIELDS.get(name)
        if shift is not None:
            start = np.repeat(getattr(model, f"world_{shift}_start"), per)
            value = np.where(value >= 0, value - start, value) if shift in _KEEP_NEGATIVE else value - start
        value = value.reshape(W, per, *value.shape[1:])
        if not np.array_equal(value, np.broadcast_to(value[:1], value.shape)):
            return False
    return True


def fingerprint(model: Model) -> str:
    """A short hash of ``model``'s mechanism: what :func:`kamino.init_state` stores in ``State.model_fingerprint``
    and ``kamino.step`` compares, so that a state of another mechanism with the same array shapes is an error. Two
    models that differ only in physical parameters (masses, inertias, gains, limits, friction, damping, gravity,
    initial pose: :data:`_FINGERPRINT_FIELDS` lists what counts) share it; equal models built twice share it. It
    hashes the shortest sequence of worlds whose repetition is the model's: ``replicate(m, n)`` and a group model of
    ``kamino.sharding`` (one block of identical groups of worlds) share ``m``'s (their states differ in shape, which
    the shape checks name)."""

    def build() -> str:
        if _worlds_alike(model):  # replicate(m, n): one world's hash (what the search below finds), at numpy speed
            return hashlib.blake2b(_world_digest(model, 0), digest_size=8).hexdigest()
        digests = [_world_digest(model, w) for w in range(model.num_worlds)]
        n = len(digests)
        period = next(p for p in range(1, n + 1) if n % p == 0 and digests == digests[:p] * (n // p))
        return hashlib.blake2b(b"".join(digests[:period]), digest_size=8).hexdigest()

    return derived(model, "fingerprint", build)


def with_extras(model: Model, suggested_dt: float | None = None, keyframes: Sequence[Keyframe] = ()) -> Model:
    """``model`` (changed in place and returned) with its source's suggested time step and keyframes
    (:attr:`Model.suggested_dt`, :attr:`Model.keyframes`); each keyframe must fit one world."""
    nb, na = int(model.world_body_count[0]), int(model.world_actuator_count[0])
    names = [k.name for k in keyframes]
    for k in keyframes:
        if k.body_q.shape != (nb, 7) or k.body_u.shape != (nb, 6) or k.ctrl.shape != (na,):
            raise ModelError(f"keyframe {k.name!r}: shapes {k.body_q.shape}, {k.body_u.shape}, {k.ctrl.shape} do not "
                             f"fit the model's world ({nb} bodies, {na} actuators)")
        if names.count(k.name) > 1:
            raise ModelError(f"keyframe name {k.name!r} is used twice")
        for arr in (k.body_q, k.body_u, k.ctrl):
            arr.setflags(write=False)
    if suggested_dt is not None and not (np.isfinite(suggested_dt) and suggested_dt > 0):
        raise ModelError(f"suggested_dt must be a positive time step, got {suggested_dt!r}")
    object.__setattr__(model, _EXTRAS, {"suggested_dt": None if suggested_dt is None else float(suggested_dt),
                                        "keyframes": tuple(keyframes)})
    return model


def _shared_extras(models: Sequence[Model], out: Model) -> Model:
    """``out`` with the extras of ``models`` if they all hold the same ones (``replicate``), else without."""
    first = models[0].__dict__.get(_EXTRAS)
    if first is not None and all(m.__dict__.get(_EXTRAS) is first for m in models):
        object.__setattr__(out, _EXTRAS, first)
    return out


def replicate(model: Model, n: int) -> Model:
    """``n`` copies of ``model`` as one multi-world model (homogeneous worlds)."""
    if not isinstance(model, Model):
        raise TypeError(f"replicate: model must be a kamino.Model, got {type(model).__name__}")
    if isinstance(n, bool) or not isinstance(n, numbers.Integral):
        raise TypeError(f"replicate(n={n!r}): n, the number of copies, must be an integer, got a "
                        f"{type(n).__name__}")
    if int(n) < 1:
        raise ModelError(f"replicate(n={n!r}): number of copies must be >= 1")
    return concat([model] * int(n))
