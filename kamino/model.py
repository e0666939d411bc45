"""Model (immutable, host NumPy) and ModelBuilder with validation.

Storage is flat over all worlds, sized by the *sum* of per-world counts, with per-world
offsets and counts (docs/conventions.md, "Data layout"). Index fields (``joint_parent``,
``joint_child``) are global body indices; ``-1`` is the world.
"""

from __future__ import annotations

import dataclasses
import enum
from collections.abc import Sequence
from typing import Any

import numpy as np

from kamino.hostmath import IDENTITY_QUAT, axis_frame, matrix_to_quat, quat_mul, quat_to_matrix


class ModelError(ValueError):
    """A model description is invalid; the message names the body/joint and the problem."""


class JointType(enum.IntEnum):
    """Joint types of formulation.md §2.4. Every joint may close a loop; none is special."""

    FIXED = 0
    REVOLUTE = 1
    PRISMATIC = 2
    CYLINDRICAL = 3
    UNIVERSAL = 4
    SPHERICAL = 5
    CARTESIAN = 6
    FREE = 7


# Row kinds: how a constraint row's residual is read (formulation.md §2.3).
RES_TRANS, RES_LOG, RES_HINGE, RES_UNIV = 0, 1, 2, 3
# DoF-row kinds: which axis a DoF row uses (formulation.md §2.5).
DOF_TRANS, DOF_ROT, DOF_UNIV, DOF_FREE = 0, 1, 2, 3

#: Per type: constrained rows as (axis 0..5, residual kind), in row order (formulation.md §2.4).
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
#: Per type: DoF rows as (axis 0..5, DoF kind) (formulation.md §2.4-2.5).
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
#: Number of joint coordinates per type (formulation.md §2.4).
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

_QUAT_UNIT_TOL = 1e-6  # issue 2: "zero or non-unit quaternion (beyond 1e-6)"


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

    num_worlds: int
    gravity: np.ndarray  # [W, 3]
    # bodies
    body_mass: np.ndarray  # [B]
    body_inertia: np.ndarray  # [B, 3, 3]
    body_q0: np.ndarray  # [B, 7]
    body_u0: np.ndarray  # [B, 6]
    body_world: np.ndarray  # [B]
    body_names: tuple[str, ...]
    world_body_start: np.ndarray  # [W]
    world_body_count: np.ndarray  # [W]
    # joints
    joint_type: np.ndarray  # [J]
    joint_parent: np.ndarray  # [J] global body index or -1
    joint_child: np.ndarray  # [J] global body index
    joint_world: np.ndarray  # [J]
    joint_anchor_B: np.ndarray  # [J, 3]
    joint_anchor_F: np.ndarray  # [J, 3]
    joint_frame_B: np.ndarray  # [J, 4]
    joint_frame_F: np.ndarray  # [J, 4]
    joint_names: tuple[str, ...]
    world_joint_start: np.ndarray
    world_joint_count: np.ndarray
    # joint DoFs (global flat), coordinates, kinematic constraint rows
    joint_dof_start: np.ndarray
    joint_dof_count: np.ndarray
    joint_coord_start: np.ndarray
    joint_coord_count: np.ndarray
    joint_cts_start: np.ndarray
    joint_cts_count: np.ndarray
    dof_lower: np.ndarray  # [D]
    dof_upper: np.ndarray  # [D]
    world_dof_start: np.ndarray
    world_dof_count: np.ndarray
    world_coord_start: np.ndarray
    world_coord_count: np.ndarray
    world_cts_start: np.ndarray
    world_cts_count: np.ndarray

    # ---- sizes -------------------------------------------------------------------------
    @property
    def num_bodies(self) -> int:
        return int(self.body_mass.shape[0])

    @property
    def num_joints(self) -> int:
        return int(self.joint_type.shape[0])

    @property
    def num_dofs(self) -> int:
        return int(self.dof_lower.shape[0])

    @property
    def num_coords(self) -> int:
        return int(self.joint_coord_count.sum())

    @property
    def num_constraints(self) -> int:
        """Total bilateral (joint) constraint rows over all worlds."""
        return int(self.joint_cts_count.sum())

    def body_index(self, name: str, world: int = 0) -> int:
        """Global index of the body called ``name`` in ``world``."""
        s, c = int(self.world_body_start[world]), int(self.world_body_count[world])
        for i in range(s, s + c):
            if self.body_names[i] == name:
                return i
        raise KeyError(f"no body named {name!r} in world {world}")

    def joint_index(self, name: str, world: int = 0) -> int:
        """Global index of the joint called ``name`` in ``world``."""
        s, c = int(self.world_joint_start[world]), int(self.world_joint_count[world])
        for j in range(s, s + c):
            if self.joint_names[j] == name:
                return j
        raise KeyError(f"no joint named {name!r} in world {world}")

    def summary(self) -> str:
        """One line per world kind: bodies, joints, DoFs, constraint rows, independent loops."""
        lines = []
        for w in range(min(self.num_worlds, 8)):
            nb, nj = int(self.world_body_count[w]), int(self.world_joint_count[w])
            lines.append(
                f"world {w}: {nb} bodies, {nj} joints, {int(self.world_dof_count[w])} dofs, "
                f"{int(self.world_cts_count[w])} constraint rows, {count_loops(self, w)} loops"
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


def _check_quat(q: np.ndarray, what: str) -> None:
    n = float(np.linalg.norm(q))
    if n == 0.0:
        raise ModelError(f"{what}: zero quaternion (expected a unit quaternion (x, y, z, w))")
    if abs(n - 1.0) > _QUAT_UNIT_TOL:
        raise ModelError(f"{what}: quaternion norm is {n:.9g}, not 1 (tolerance {_QUAT_UNIT_TOL})")


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
        self._bodies: list[_Body] = []
        self._joints: list[_Joint] = []

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
        actuation: Any = None,
        name: str | None = None,
    ) -> int:
        """Add a joint between ``parent`` (a body index or -1 for the world) and ``child``.

        ``parent_frame``/``child_frame`` are ``(pos, quat)`` of the joint frame in the parent's and
        child's CoM frames (world frame for ``parent=-1``). ``axis`` is the motion axis in the joint
        frame (REVOLUTE, PRISMATIC, CYLINDRICAL; first axis of UNIVERSAL, whose second is ``axis2``,
        default the joint frame's y). SPHERICAL, CARTESIAN, FIXED and FREE use the joint frame axes.
        ``limits`` is ``(lower, upper)`` per DoF (scalars for 1-DoF joints); stored and validated
        here, enforced by the solver once joint limits land (issue 3).
        Any joint may close a kinematic loop.
        """
        idx = len(self._joints)
        name = name if name is not None else f"joint_{idx}"
        if actuation is not None:
            raise NotImplementedError(
                f"joint {name!r}: actuation is not supported yet (implicit PD arrives with the actuation "
                "issue); apply efforts through kamino.Control(dof_effort=...)"
            )
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
            lower = np.broadcast_to(np.asarray(lo, dtype=float), (ndof,)).copy()
            upper = np.broadcast_to(np.asarray(hi, dtype=float), (ndof,)).copy()
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
    ) -> int:
        """Add a joint whose frame sits at ``anchor`` with motion ``axis`` (and ``axis2``), both in
        world coordinates at the bodies' current (builder) poses. The joint frames are computed so
        that the joint's coordinates are zero at those poses (as for an MJCF reference pose)."""
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
            limits=limits, name=name,
        )

    # -- validation and assembly -----------------------------------------------------
    def _validate_body(self, i: int, b: _Body) -> None:
        what = f"body {b.name!r} (index {i})"
        for field_name, arr in (("inertia", b.inertia), ("pos", b.pos), ("quat", b.quat),
                                ("velocity", b.vel), ("angular_velocity", b.ang_vel)):
            _finite(np.asarray(arr), f"{what} {field_name}")
        if not np.isfinite(b.mass):  # b.mass is a float (add_body converts or raises ModelError)
            raise ModelError(f"{what}: mass is {b.mass}")
        if b.mass <= 0.0:
            raise ModelError(f"{what}: mass must be > 0, got {b.mass}")
        I = b.inertia
        if I.shape != (3, 3):
            raise ModelError(f"{what}: inertia must be 3x3 or 3 principal moments, got shape {I.shape}")
        scale = max(float(np.abs(I).max()), 1e-300)
        if np.abs(I - I.T).max() > 1e-9 * scale:
            raise ModelError(f"{what}: inertia is not symmetric")
        eig = np.linalg.eigvalsh(0.5 * (I + I.T))
        if eig[0] <= 0.0:
            raise ModelError(f"{what}: inertia is not positive definite (eigenvalues {eig.tolist()})")
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
        if jt.axis2 is not None:
            _finite(jt.axis2, f"{what} axis2")
        lo, hi = jt.limits
        if np.any(np.isnan(lo)) or np.any(np.isnan(hi)):
            raise ModelError(f"{what}: limits contain NaN")
        if not (-1 <= jt.parent < nb):
            raise ModelError(f"{what}: parent body {jt.parent} does not exist ({nb} bodies; -1 is the world)")
        if not (0 <= jt.child < nb):
            raise ModelError(f"{what}: child body {jt.child} does not exist ({nb} bodies)")
        if jt.parent == jt.child:
            raise ModelError(f"{what}: connects body {jt.child} to itself")
        _check_quat(jt.parent_frame[1], f"{what} parent_frame quaternion")
        _check_quat(jt.child_frame[1], f"{what} child_frame quaternion")
        uses_axis = jt.type in (JointType.REVOLUTE, JointType.PRISMATIC, JointType.CYLINDRICAL, JointType.UNIVERSAL)
        if uses_axis and np.linalg.norm(jt.axis) < 1e-12:
            raise ModelError(f"{what}: zero-length axis")
        if jt.axis2 is not None:
            if np.linalg.norm(jt.axis2) < 1e-12:
                raise ModelError(f"{what}: zero-length axis2")
            a1 = jt.axis / np.linalg.norm(jt.axis)
            a2 = jt.axis2 / np.linalg.norm(jt.axis2)
            if np.linalg.norm(np.cross(a1, a2)) < 1e-6:
                raise ModelError(f"{what}: axis2 is parallel to axis")
        bad = np.nonzero(lo > hi)[0]
        if bad.size:
            k = int(bad[0])
            raise ModelError(f"{what}: lower limit {lo[k]} > upper limit {hi[k]} (DoF {k})")

    def finalize(self) -> Model:
        """Validate and return the single-world :class:`Model`; raises :class:`ModelError`."""
        _finite(self.gravity, "gravity")
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
            world_dof_start=one.copy(),
            world_dof_count=np.array([dof_count.sum()], dtype=np.int64),
            world_coord_start=one.copy(),
            world_coord_count=np.array([coord_count.sum()], dtype=np.int64),
            world_cts_start=one.copy(),
            world_cts_count=np.array([cts_count.sum()], dtype=np.int64),
        )
        return _freeze(model)


# ---------------------------------------------------------------------------------------
# Multi-world models
# ---------------------------------------------------------------------------------------

# fields holding per-entity data, grouped by the entity that sizes them
_BODY_FIELDS = ("body_mass", "body_inertia", "body_q0", "body_u0")
_JOINT_FIELDS = ("joint_type", "joint_anchor_B", "joint_anchor_F", "joint_frame_B", "joint_frame_F",
                 "joint_dof_count", "joint_coord_count", "joint_cts_count")
_DOF_FIELDS = ("dof_lower", "dof_upper")
_WORLD_COUNT_FIELDS = ("world_body_count", "world_joint_count", "world_dof_count", "world_coord_count",
                       "world_cts_count")


def _freeze(model: Model) -> Model:
    for f in dataclasses.fields(model):
        v = getattr(model, f.name)
        if isinstance(v, np.ndarray):
            v.flags.writeable = False
    return model


def _prefix(counts: np.ndarray) -> np.ndarray:
    """Exclusive prefix sum (the start offsets of consecutive segments); empty for no segments."""
    counts = np.asarray(counts, dtype=np.int64)
    return (np.cumsum(counts) - counts).astype(np.int64)


def concat(models: Sequence[Model]) -> Model:
    """Stack models (each with one or more worlds) into one multi-world model, in order.

    Worlds may differ (heterogeneous): storage is the sum of per-world sizes, with per-world
    offsets/counts recomputed here.
    """
    models = list(models)
    if not models:
        raise ModelError("concat: no models given")
    cat = {}
    for name in _BODY_FIELDS + _JOINT_FIELDS + _DOF_FIELDS + _WORLD_COUNT_FIELDS + ("gravity",):
        cat[name] = np.concatenate([getattr(m, name) for m in models], axis=0)
    nbs = np.array([m.num_bodies for m in models])
    nws = np.array([m.num_worlds for m in models])
    body_off = np.repeat(_prefix(nbs), [m.num_joints for m in models])
    world_off_b = np.repeat(_prefix(nws), nbs)
    world_off_j = np.repeat(_prefix(nws), [m.num_joints for m in models])
    parent = np.concatenate([m.joint_parent for m in models])
    parent = np.where(parent >= 0, parent + body_off, -1)
    child = np.concatenate([m.joint_child for m in models]) + body_off
    return _assemble(
        cat, parent, child,
        np.concatenate([m.body_world for m in models]) + world_off_b,
        np.concatenate([m.joint_world for m in models]) + world_off_j,
        sum((m.body_names for m in models), ()),
        sum((m.joint_names for m in models), ()),
    )


def replicate(model: Model, n: int) -> Model:
    """``n`` copies of ``model`` as one multi-world model (homogeneous worlds)."""
    if int(n) < 1:
        raise ModelError(f"replicate: number of copies must be >= 1, got {n}")
    n = int(n)
    cat = {}
    for name in _BODY_FIELDS + _JOINT_FIELDS + _DOF_FIELDS + _WORLD_COUNT_FIELDS + ("gravity",):
        v = getattr(model, name)
        cat[name] = np.tile(v, (n,) + (1,) * (v.ndim - 1))
    nb, nj, nw = model.num_bodies, model.num_joints, model.num_worlds
    body_off = np.repeat(np.arange(n) * nb, nj)
    parent = np.tile(model.joint_parent, n)
    parent = np.where(parent >= 0, parent + body_off, -1)
    child = np.tile(model.joint_child, n) + body_off
    return _assemble(
        cat, parent, child,
        np.tile(model.body_world, n) + np.repeat(np.arange(n) * nw, nb),
        np.tile(model.joint_world, n) + np.repeat(np.arange(n) * nw, nj),
        model.body_names * n,
        model.joint_names * n,
    )


def _assemble(cat, parent, child, body_world, joint_world, body_names, joint_names) -> Model:
    model = Model(
        num_worlds=int(cat["world_body_count"].shape[0]),
        gravity=cat["gravity"],
        body_mass=cat["body_mass"],
        body_inertia=cat["body_inertia"],
        body_q0=cat["body_q0"],
        body_u0=cat["body_u0"],
        body_world=body_world.astype(np.int64),
        body_names=tuple(body_names),
        world_body_start=_prefix(cat["world_body_count"]),
        world_body_count=cat["world_body_count"],
        joint_type=cat["joint_type"],
        joint_parent=parent.astype(np.int64),
        joint_child=child.astype(np.int64),
        joint_world=joint_world.astype(np.int64),
        joint_anchor_B=cat["joint_anchor_B"],
        joint_anchor_F=cat["joint_anchor_F"],
        joint_frame_B=cat["joint_frame_B"],
        joint_frame_F=cat["joint_frame_F"],
        joint_names=tuple(joint_names),
        world_joint_start=_prefix(cat["world_joint_count"]),
        world_joint_count=cat["world_joint_count"],
        joint_dof_start=_prefix(cat["joint_dof_count"]),
        joint_dof_count=cat["joint_dof_count"],
        joint_coord_start=_prefix(cat["joint_coord_count"]),
        joint_coord_count=cat["joint_coord_count"],
        joint_cts_start=_prefix(cat["joint_cts_count"]),
        joint_cts_count=cat["joint_cts_count"],
        dof_lower=cat["dof_lower"],
        dof_upper=cat["dof_upper"],
        world_dof_start=_prefix(cat["world_dof_count"]),
        world_dof_count=cat["world_dof_count"],
        world_coord_start=_prefix(cat["world_coord_count"]),
        world_coord_count=cat["world_coord_count"],
        world_cts_start=_prefix(cat["world_cts_count"]),
        world_cts_count=cat["world_cts_count"],
    )
    return _freeze(model)

