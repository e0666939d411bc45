"""MJCF import: ``load_mjcf(path_or_xml) -> kamino.Model`` (docs/mjcf.md).

The file is parsed and compiled by MuJoCo itself (``mujoco.MjSpec`` -> ``mujoco.MjModel``), so
defaults classes, includes, compiler options (degrees, ``autolimits``, inertia from geoms...) are
exactly MuJoCo's. Every number is read from the compiled model and from ``mj_kinematics`` at
``qpos0``: world CoM frames (``xipos``/``ximat``), principal inertias, joint anchors and axes,
geom world poses, equality data and actuator parameters. The kinematic tree becomes kamino's
maximal coordinates:

* a body with joints becomes a kamino body (CoM frame = MuJoCo's inertial frame) joined to its
  parent by one kamino joint per *group* of its MuJoCo joints (a composite UNIVERSAL, CYLINDRICAL
  or CARTESIAN joint where that is exact, otherwise a chain through light intermediate bodies);
* a jointless body welded to the world is static (its geoms go on the world), a jointless massless
  body is merged into its parent, any other jointless body gets a FIXED joint;
* ``<equality>`` ``connect``/``weld`` become SPHERICAL/FIXED loop joints and ``joint`` a coupling.

Joint coordinates are zero at ``qpos0`` (``ModelBuilder.add_joint_at`` convention), except FREE
joints, whose coordinates are MuJoCo's qpos (position and orientation of the body frame).
:func:`import_mjcf` also returns the maps between MuJoCo's qpos/qvel and kamino's state.
"""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path
from typing import Any
from xml.etree import ElementTree

import numpy as np

from kamino.hostmath import axis_frame, matrix_to_quat
from kamino.io._mjcf_contacts import PairInfo, candidate_pairs
from kamino.io._mjcf_features import (
    MJ_MINVAL,
    ActuatorSpec,
    classify_actuators,
    global_problems,
    joint_problems,
    obj_name,
)
from kamino.kinematics import init_state
from kamino.model import (
    CONTACT_POINTS,
    Actuation,
    ActuationMode,
    GeomType,
    JointType,
    Keyframe,
    Model,
    ModelBuilder,
    ModelError,
    with_extras,
)
from kamino.readouts import joint_positions

#: Default mass (and inertia) of a light intermediate body relative to the body it leads to.
LIGHT_MASS_RATIO = 1e-2
_PARALLEL_TOL = 1e-9  # |cos| or |sin| below which two unit axes count as orthogonal / parallel
_POINT_TOL = 1e-9  # [m] two anchors closer than this coincide

_HINGE, _SLIDE, _BALL, _FREE = "hinge", "slide", "ball", "free"


@dataclasses.dataclass(frozen=True)
class MjcfJoint:
    """Where one MuJoCo joint lives in the kamino model.

    ``joint`` is the kamino joint, ``coord``/``dof`` the offsets of this MuJoCo joint's coordinates and
    DoFs inside it (non-zero for the second and third joints of a composite), ``qposadr``/``dofadr``
    its slots in MuJoCo's qpos/qvel, ``qpos0`` its reference (kamino coordinate 0 of a hinge/slide).
    """

    name: str
    type: str  # "hinge", "slide", "ball" or "free"
    joint: int
    coord: int
    dof: int
    qposadr: int
    dofadr: int
    qpos0: np.ndarray


@dataclasses.dataclass(frozen=True, eq=False)
class MjcfImport:
    """A converted MJCF model with the maps back to MuJoCo (see :func:`import_mjcf`).

    Attributes:
        model: the kamino model.
        mj_model: the compiled ``mujoco.MjModel`` it was read from.
        joints: one :class:`MjcfJoint` per MuJoCo joint, in MuJoCo order.
        body_map: per MuJoCo body, the kamino body carrying it (-1: the world, also for static bodies;
            a merged massless body maps to the body it was merged into).
        body_source: per kamino body, ``(MuJoCo body, joints)``: the MuJoCo body whose inertial frame it
            is and how many of that body's joints it moves with (-1: all; fewer for a light
            intermediate body of a chained joint group).
        actuators: the MuJoCo actuator index of each kamino actuator (kamino order = MuJoCo order).
    """

    model: Model
    mj_model: Any
    joints: tuple[MjcfJoint, ...]
    body_map: tuple[int, ...]
    body_source: tuple[tuple[int, int], ...]
    actuators: tuple[int, ...]

    def joint(self, name: str) -> MjcfJoint:
        """The :class:`MjcfJoint` of the MuJoCo joint called ``name``."""
        for j in self.joints:
            if j.name == name:
                return j
        raise KeyError(f"no MuJoCo joint named {name!r}")

    def qpos(self, body_q: Any) -> np.ndarray:
        """MuJoCo's qpos ``[..., nq]`` of kamino body poses ``body_q [..., num_bodies, 7]`` (leading axes,
        e.g. time, are kept): hinge/slide = kamino coordinate + qpos0 (angles not unwrapped), ball/free
        quaternions in MuJoCo's (w, x, y, z) order."""
        import jax

        body_q = np.asarray(body_q)
        lead = body_q.shape[:-2]
        flat = body_q.reshape((-1, *body_q.shape[-2:]))
        template = init_state(self.model, dtype=flat.dtype)
        coords = np.asarray(jax.vmap(lambda q: joint_positions(self.model, template.replace(body_q=q)))(flat))
        starts = self.model.joint_coord_start
        out = np.zeros((flat.shape[0], self.mj_model.nq))
        for jm in self.joints:
            c = int(starts[jm.joint]) + jm.coord
            a = jm.qposadr
            if jm.type in (_HINGE, _SLIDE):
                out[:, a] = coords[:, c] + jm.qpos0[0]
            elif jm.type == _BALL:
                out[:, a:a + 4] = coords[:, [c + 3, c, c + 1, c + 2]]
            else:
                out[:, a:a + 3] = coords[:, c:c + 3]
                out[:, a + 3:a + 7] = coords[:, [c + 6, c + 3, c + 4, c + 5]]
        return out.reshape((*lead, self.mj_model.nq))

    def body_state(self, qpos: Any = None, qvel: Any = None) -> tuple[np.ndarray, np.ndarray]:
        """kamino ``(body_q, body_u)`` of MuJoCo's ``qpos``/``qvel`` (defaults: ``qpos0`` and zero), by
        MuJoCo's own forward kinematics: CoM poses ``(xipos, ximat)`` and CoM twists (world frame).
        Light intermediate bodies get the pose and twist of their body with the later joints at
        ``qpos0`` and at rest."""
        import mujoco

        m = self.mj_model
        qpos = np.array(m.qpos0 if qpos is None else qpos, dtype=float).reshape(m.nq)
        qvel = np.zeros(m.nv) if qvel is None else np.array(qvel, dtype=float).reshape(m.nv)
        nb = self.model.num_bodies
        body_q, body_u = np.zeros((nb, 7)), np.zeros((nb, 6))
        data = mujoco.MjData(m)

        def forward(qp: np.ndarray, qv: np.ndarray) -> None:
            data.qpos[:], data.qvel[:] = qp, qv
            mujoco.mj_forward(m, data)

        def read(kb: int, b: int) -> None:
            R = data.ximat[b].reshape(3, 3)
            body_q[kb] = np.concatenate([data.xipos[b], matrix_to_quat(R)])
            vel = np.zeros(6)
            mujoco.mj_objectVelocity(m, data, mujoco.mjtObj.mjOBJ_BODY, b, vel, 0)
            body_u[kb] = np.concatenate([vel[3:], vel[:3]])

        levels = sorted({n for _, n in self.body_source})
        for level in levels:  # -1 (real bodies) first, then the light bodies' joint prefixes
            qp, qv = qpos.copy(), qvel.copy()
            if level >= 0:  # joints past the prefix of every chained body back at qpos0, at rest
                for b, n in {(b, n) for b, n in self.body_source if n == level}:
                    for jm in self.joints[int(m.body_jntadr[b]) + n:int(m.body_jntadr[b] + m.body_jntnum[b])]:
                        nq = {_FREE: 7, _BALL: 4}.get(jm.type, 1)
                        nv = {_FREE: 6, _BALL: 3}.get(jm.type, 1)
                        qp[jm.qposadr:jm.qposadr + nq] = m.qpos0[jm.qposadr:jm.qposadr + nq]
                        qv[jm.dofadr:jm.dofadr + nv] = 0.0
            forward(qp, qv)
            for kb, (b, n) in enumerate(self.body_source):
                if n == level:
                    read(kb, b)
        return body_q, body_u

    def state(self, qpos: Any = None, qvel: Any = None, dtype: Any = None):
        """A kamino :class:`~kamino.State` at MuJoCo's ``qpos``/``qvel`` (see :meth:`body_state`)."""
        import jax.numpy as jnp

        body_q, body_u = self.body_state(qpos, qvel)
        state = init_state(self.model, dtype=dtype)
        return state.replace(body_q=jnp.asarray(body_q, state.body_q.dtype),
                             body_u=jnp.asarray(body_u, state.body_u.dtype))


def _mujoco() -> Any:
    try:
        import mujoco
    except ImportError as exc:  # pragma: no cover - mujoco is a test dependency
        raise ImportError("kamino.load_mjcf needs the 'mujoco' package (pip install mujoco)") from exc
    return mujoco


def _compile(source: str | os.PathLike | bytes) -> tuple[Any, Any]:
    """``(MjSpec, MjModel)`` of a file path or an XML string; MuJoCo errors become ModelError."""
    mujoco = _mujoco()
    if isinstance(source, bytes):
        try:
            source = source.decode("utf-8")
        except UnicodeDecodeError as exc:
            raise ModelError(f"load_mjcf: the MJCF bytes are not UTF-8 text ({exc.reason} at byte {exc.start}: "
                             f"{source[max(exc.start - 20, 0):exc.start + 5]!r})") from None
    is_xml = isinstance(source, str) and source.lstrip().startswith("<")
    try:
        if is_xml:
            spec = mujoco.MjSpec.from_string(source)
        else:
            path = Path(source)
            if isinstance(source, str) and "<" in source and not _is_file(path):
                raise ModelError(f"load_mjcf: the source is neither a file nor XML: an XML string must start with "
                                 f"'<' (its first characters: {source[:40]!r})")
            if not path.is_file():
                raise FileNotFoundError(f"load_mjcf: no MJCF file at {str(path)!r} (an XML string must start with '<')")
            spec = mujoco.MjSpec.from_file(str(path))
        mj = spec.compile()
    except FileNotFoundError:
        raise
    except Exception as exc:  # mujoco raises ValueError (parse) or its own errors (compile)
        raise ModelError(f"MuJoCo could not load the MJCF model: {exc}") from exc
    _check_compiled(mj)
    return spec, mj


def _is_file(path: Path) -> bool:
    """Whether ``path`` names an existing file (``False`` for a string no file system accepts as a path)."""
    try:
        return path.is_file()
    except (OSError, ValueError):
        return False


def _check_compiled(mj: Any) -> None:
    """Raise a :class:`ModelError` for a compiled model kamino cannot simulate: names that are not UTF-8, no
    moving body, no joint."""
    names = bytes(np.asarray(mj.names, dtype=np.uint8)) if not isinstance(mj.names, bytes) else mj.names
    try:
        names.decode("utf-8")
    except UnicodeDecodeError as exc:
        start = names.rfind(b"\0", 0, exc.start) + 1
        end = names.find(b"\0", exc.start)
        raise ModelError(f"load_mjcf: the name {names[start:end if end >= 0 else None]!r} is not UTF-8 text "
                         f"({exc.reason}); MJCF names must be UTF-8") from None
    if mj.nbody <= 1:
        raise ModelError("load_mjcf: the MJCF model has no bodies (its <worldbody> holds no <body>); kamino "
                         "simulates moving bodies")
    if mj.njnt == 0:
        nb = mj.nbody - 1
        raise ModelError(f"load_mjcf: the MJCF model has no joints: its {nb} {'body is' if nb == 1 else 'bodies are'} "
                         "welded to the world; give a moving body a <joint> or a <freejoint>")


def _quat_wxyz_matrix(mujoco: Any, q: np.ndarray) -> np.ndarray:
    R = np.zeros(9)
    mujoco.mju_quat2Mat(R, np.asarray(q, dtype=float))
    return R.reshape(3, 3)


def _unit(v: np.ndarray) -> np.ndarray:
    return np.asarray(v, float) / np.linalg.norm(v)


class _Converter:
    """One MJCF -> kamino conversion (state shared by the steps; see :func:`import_mjcf`)."""

    def __init__(self, mujoco: Any, spec: Any, mj: Any, light_mass_ratio: float):
        self.mujoco, self.spec, self.mj = mujoco, spec, mj
        self.ratio = float(light_mass_ratio)
        if not (self.ratio > 0.0 and np.isfinite(self.ratio)):
            raise ModelError(f"light_mass_ratio must be a positive number, got {light_mass_ratio!r}")
        self.data = mujoco.MjData(mj)
        self.data.qpos[:] = mj.qpos0
        mujoco.mj_kinematics(mj, self.data)
        self.problems: list[str] = []
        dis = int(mj.opt.disableflags)
        D = mujoco.mjtDisableBit
        self.limits_on = not dis & int(D.mjDSBL_LIMIT)
        self.springs_on = not dis & int(D.mjDSBL_SPRING)
        self.dampers_on = not dis & int(D.mjDSBL_DAMPER)
        self.equality_on = not dis & int(D.mjDSBL_EQUALITY)
        gravity = np.zeros(3) if dis & int(D.mjDSBL_GRAVITY) else np.asarray(mj.opt.gravity, float)
        self.b = ModelBuilder(gravity=gravity)
        self.suggested_dt: float | None = None  # the file's <option timestep>, if it sets one
        self.poses: list[tuple[np.ndarray, np.ndarray]] = []  # kamino body CoM (r, R) at qpos0
        self.body_map = [-1] * mj.nbody
        self.body_source: list[tuple[int, int]] = []
        # MuJoCo's own names first, so that generated names (fixed/light/loop joints) give way to them
        self.mj_body_names = {self.name("body", b) for b in range(1, mj.nbody)}
        self.mj_joint_names = {self.name("joint", j) for j in range(mj.njnt)}
        self.body_names: set[str] = set()
        self.joint_names: set[str] = set()
        self.geom_info: dict[int, tuple[int, GeomType, float]] = {}  # kamino geom -> (body, type, friction)
        self.hfield_map: dict[int, int] = {}  # MuJoCo heightfield -> the builder's
        self.joint_map: dict[int, MjcfJoint] = {}
        self.actuated: dict[int, tuple[int, int]] = {}  # MuJoCo actuator -> (kamino joint, dof)
        self.jtype = {int(mujoco.mjtJoint.mjJNT_HINGE): _HINGE, int(mujoco.mjtJoint.mjJNT_SLIDE): _SLIDE,
                      int(mujoco.mjtJoint.mjJNT_BALL): _BALL, int(mujoco.mjtJoint.mjJNT_FREE): _FREE}

    # -- names and frames ------------------------------------------------------------------
    def name(self, objtype: str, idx: int) -> str:
        prefix = objtype.lower()
        return obj_name(self.mujoco, self.mj, getattr(self.mujoco.mjtObj, f"mjOBJ_{objtype.upper()}"), idx, prefix)

    def pose(self, kb: int) -> tuple[np.ndarray, np.ndarray]:
        return (np.zeros(3), np.eye(3)) if kb < 0 else self.poses[kb]

    def local(self, kb: int, p_w: np.ndarray, R_w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """A world frame ``(p_w, R_w)`` at qpos0 in kamino body ``kb``'s CoM frame, as (pos, quat xyzw)."""
        r, R = self.pose(kb)
        return R.T @ (np.asarray(p_w, float) - r), matrix_to_quat(R.T @ R_w)

    def body_frame(self, b: int) -> tuple[np.ndarray, np.ndarray]:
        return self.data.xpos[b].copy(), self.data.xmat[b].reshape(3, 3).copy()

    @staticmethod
    def unique(name: str, taken: set[str], reserved: set[str], own: bool) -> str:
        """Kamino names are unique per entity: a MuJoCo element keeps its own name (``own``); a generated
        name (fixed, light, composite and loop joints...) avoids every name in use or reserved for a
        MuJoCo element by appending ``_1``, ``_2``..."""
        out, k = name, 0
        while not own and (out in taken or out in reserved):
            k += 1
            out = f"{name}_{k}"
        taken.add(out)
        return out

    def add_joint(self, jtype: JointType, parent: int, child: int, base_w: tuple, follower_w: tuple, name: str,
                  own_name: bool = False, **kwargs: Any) -> int:
        """A kamino joint whose base/follower frames are the given world frames at qpos0; the joint
        frame's x (and y) axes are the frame's own (axis = e_x, axis2 = e_y)."""
        return self.b.add_joint(jtype, parent, child, parent_frame=self.local(parent, *base_w),
                                child_frame=self.local(child, *follower_w), axis=(1.0, 0.0, 0.0),
                                name=self.unique(name, self.joint_names, self.mj_joint_names, own_name),
                                **kwargs)

    def add_body(self, b: int, name: str, scale: float = 1.0, joints: int = -1, own_name: bool = True) -> int:
        """Kamino body at MuJoCo body ``b``'s inertial frame (mass and inertia times ``scale``), moving
        with the first ``joints`` of ``b``'s joints (-1: all)."""
        mj, d = self.mj, self.data
        self.body_source.append((b, joints))
        R = d.ximat[b].reshape(3, 3).copy()
        kb = self.b.add_body(mass=scale * float(mj.body_mass[b]), inertia=scale * np.asarray(mj.body_inertia[b], float),
                             pos=d.xipos[b].copy(), quat=matrix_to_quat(R),
                             name=self.unique(name, self.body_names, self.mj_body_names, own_name))
        self.poses.append((d.xipos[b].copy(), R))
        return kb

    # -- joints ------------------------------------------------------------------------------
    def composite(self, group: list[int], coupled: set[int], acts: dict[int, ActuatorSpec]) -> JointType | None:
        """The exact composite kamino joint of consecutive MuJoCo joints ``group``, or None."""
        mj, d = self.mj, self.data
        kinds = [self.jtype[int(mj.jnt_type[j])] for j in group]
        if any(j in coupled for j in group):
            return None
        modes = {acts[j].mode if j in acts else ActuationMode.PASSIVE for j in group}
        if len(modes) > 1:
            return None
        mode = modes.pop()
        axes = [_unit(d.xaxis[j]) for j in group]
        stiff = self.springs_on and any(float(mj.jnt_stiffness[j]) != 0.0 for j in group)
        if kinds == [_HINGE, _HINGE]:
            same_point = np.linalg.norm(d.xanchor[group[0]] - d.xanchor[group[1]]) < _POINT_TOL
            # armature: kamino's universal DoF rows read rates along moving intermediate axes, which
            # differs from MuJoCo's two hinges by a gyroscopic term; two REVOLUTE joints are exact there
            armature = any(float(mj.dof_armature[mj.jnt_dofadr[j]]) != 0.0 for j in group)
            if same_point and abs(axes[0] @ axes[1]) < _PARALLEL_TOL and not stiff and not armature and mode in (
                    ActuationMode.PASSIVE, ActuationMode.EFFORT):
                return JointType.UNIVERSAL
        elif kinds == [_SLIDE, _HINGE]:
            if np.linalg.norm(np.cross(axes[0], axes[1])) < _PARALLEL_TOL and axes[0] @ axes[1] > 0:
                return JointType.CYLINDRICAL
        elif kinds == [_SLIDE, _SLIDE, _SLIDE]:
            A = np.column_stack(axes)
            if np.abs(A.T @ A - np.eye(3)).max() < _PARALLEL_TOL and np.linalg.det(A) > 0 and not stiff and mode in (
                    ActuationMode.PASSIVE, ActuationMode.EFFORT):
                return JointType.CARTESIAN
        return None

    def group_joints(self, b: int, coupled: set[int], acts: dict[int, ActuatorSpec]) -> list[tuple[JointType, list]]:
        """Split body ``b``'s joints (MuJoCo order) into kamino joints, greedily from the parent side."""
        mj = self.mj
        jnts = list(range(int(mj.body_jntadr[b]), int(mj.body_jntadr[b] + mj.body_jntnum[b])))
        single = {_HINGE: JointType.REVOLUTE, _SLIDE: JointType.PRISMATIC, _BALL: JointType.SPHERICAL,
                  _FREE: JointType.FREE}
        out, i = [], 0
        while i < len(jnts):
            for size in (3, 2):
                g = jnts[i:i + size]
                jt = self.composite(g, coupled, acts) if len(g) == size else None
                if jt is not None:
                    out.append((jt, g))
                    i += size
                    break
            else:
                out.append((single[self.jtype[int(mj.jnt_type[jnts[i]])]], [jnts[i]]))
                i += 1
        return out

    def joint_terms(self, jtype: JointType, group: list[int], acts: dict[int, ActuatorSpec]) -> dict[str, Any]:
        """Limits, passive terms and actuation of a kamino joint made of MuJoCo joints ``group``."""
        mj = self.mj
        lo, hi, arm, damp, stiff, sref = [], [], [], [], [], []
        for j in group:
            kind = self.jtype[int(mj.jnt_type[j])]
            nd = {_FREE: 6, _BALL: 3}.get(kind, 1)
            dofs = slice(int(mj.jnt_dofadr[j]), int(mj.jnt_dofadr[j]) + nd)
            arm += list(np.asarray(mj.dof_armature[dofs], float))
            damp += list(np.asarray(mj.dof_damping[dofs], float) if self.dampers_on else np.zeros(nd))
            if kind in (_HINGE, _SLIDE):
                q0 = float(mj.qpos0[mj.jnt_qposadr[j]])
                limited = self.limits_on and bool(mj.jnt_limited[j])
                lo.append(float(mj.jnt_range[j, 0]) - q0 if limited else -np.inf)
                hi.append(float(mj.jnt_range[j, 1]) - q0 if limited else np.inf)
                stiff.append(float(mj.jnt_stiffness[j]) if self.springs_on else 0.0)
                sref.append(float(mj.qpos_spring[mj.jnt_qposadr[j]]) - q0)
            else:
                lo += [-np.inf] * nd
                hi += [np.inf] * nd
                stiff += [0.0] * nd
                sref += [0.0] * nd
        if jtype == JointType.FREE and (np.any(arm) or np.any(damp)):
            b = int(mj.jnt_bodyid[group[0]])
            if np.linalg.norm(mj.body_ipos[b]) > _POINT_TOL:
                self.problems.append(f"armature or damping on free joint {self.name('joint', group[0])!r} whose body "
                                     "CoM is off the body origin: refused because kamino applies them at the CoM, "
                                     "MuJoCo at the body origin (set armature=\"0\" damping=\"0\" on the free "
                                     "joint, which a default <joint> class may have given it)")
            if len(set(arm)) > 1 or len(set(damp)) > 1:
                self.problems.append(f"free joint {self.name('joint', group[0])!r}: per-DoF armature/damping")
        terms: dict[str, Any] = {"armature": arm, "damping": damp, "stiffness": stiff, "springref": sref}
        if np.isfinite(lo).any() or np.isfinite(hi).any():
            terms["limits"] = (lo, hi)
        specs = [acts.get(j) for j in group]
        if any(s is not None for s in specs):
            mode = next(s.mode for s in specs if s is not None)
            terms["actuation"] = Actuation(mode=mode, kp=[s.kp for s in specs], kd=[s.kd for s in specs],
                                           effort_limit=[s.effort_limit for s in specs])
        return terms

    def add_joint_group(self, jtype: JointType, group: list[int], parent: int, child: int, b: int,
                        acts: dict[int, ActuatorSpec]) -> int:
        mj, d = self.mj, self.data
        j0 = group[0]
        anchor = d.xanchor[j0].copy()
        axes = [_unit(d.xaxis[j]) for j in group]
        if jtype in (JointType.REVOLUTE, JointType.PRISMATIC):
            R = axis_frame(axes[0])
        elif jtype == JointType.CYLINDRICAL:  # (slide, hinge): the hinge's line
            anchor, R = d.xanchor[group[1]].copy(), axis_frame(axes[1])
        elif jtype == JointType.UNIVERSAL:
            R = np.column_stack([axes[0], axes[1], np.cross(axes[0], axes[1])])
        elif jtype == JointType.CARTESIAN:
            R = np.column_stack(axes)
        else:  # SPHERICAL, FREE: the body frame (MuJoCo's ball/free qpos are relative to it)
            R = self.body_frame(b)[1]
        name = "+".join(self.name("joint", j) for j in group)
        terms = self.joint_terms(jtype, group, acts)
        if jtype == JointType.SPHERICAL and parent >= 0 and np.any(terms["armature"]):
            arm = float(np.max(terms["armature"]))
            self.problems.append(
                f"armature on ball joint {name!r} ({arm:g}), whose parent body moves: refused because kamino cannot "
                "reproduce it (kamino's spherical armature acts on the relative angular velocity in world axes, "
                "MuJoCo's in the child's moving joint frame; they differ by a gyroscopic term armature * "
                "(w_parent x w_rel), 1e-2 rad apart after 0.5 s on a humanoid). A default <joint armature=...> "
                "reaches ball joints too: set armature=\"0\" on each ball joint, or give them a <default> class "
                "with armature=\"0\". Armature on hinge and slide joints, and on a ball joint to the world, is "
                "supported")
        if jtype == JointType.FREE:
            kj = self.add_joint(jtype, -1, child, (np.zeros(3), np.eye(3)), self.body_frame(b), name,
                                own_name=len(group) == 1, **terms)
        else:
            kj = self.add_joint(jtype, parent, child, (anchor, R), (anchor, R), name, own_name=len(group) == 1,
                                **terms)
        coord = dof = 0
        for j in group:
            kind = self.jtype[int(mj.jnt_type[j])]
            nq = int(mj.jnt_qposadr[j])
            width = {_FREE: 7, _BALL: 4}.get(kind, 1)
            self.joint_map[j] = MjcfJoint(name=self.name("joint", j), type=kind, joint=kj, coord=coord, dof=dof,
                                          qposadr=nq, dofadr=int(mj.jnt_dofadr[j]),
                                          qpos0=np.asarray(mj.qpos0[nq:nq + width], float).copy())
            if j in acts:
                self.actuated[acts[j].index] = (kj, dof)
            coord += width
            dof += {_FREE: 6, _BALL: 3}.get(kind, 1)
        return kj

    # -- bodies -------------------------------------------------------------------------------
    def bodies(self, acts: dict[int, ActuatorSpec], coupled: set[int]) -> None:
        mj = self.mj
        static = [True] + [False] * (mj.nbody - 1)
        for b in range(1, mj.nbody):
            p = int(mj.body_parentid[b])
            kp = self.body_map[p]
            name = self.name("body", b)
            if int(mj.body_jntnum[b]) == 0:
                if static[p] or int(mj.body_mocapid[b]) >= 0:
                    static[b] = True  # welded to the world (a mocap body is static at its initial pose)
                    continue
                if float(mj.body_mass[b]) < MJ_MINVAL:
                    self.body_map[b] = kp  # massless: merged into its parent
                    continue
                kb = self.add_body(b, name)
                self.body_map[b] = kb
                frame = self.body_frame(b)
                self.add_joint(JointType.FIXED, kp, kb, frame, frame, f"{name}_fixed")
                continue
            groups = self.group_joints(b, coupled, acts)
            prev = kp
            for gi, (jtype, group) in enumerate(groups):
                last = gi == len(groups) - 1
                if last:
                    kb = self.add_body(b, name)
                else:
                    kb = self.add_body(b, f"{name}_light{gi}", self.ratio, sum(len(g) for _, g in groups[:gi + 1]),
                                       own_name=False)
                self.add_joint_group(jtype, group, prev, kb, b, acts)
                prev = kb
            self.body_map[b] = prev

    # -- equalities ---------------------------------------------------------------------------
    def object_frame(self, objtype: int, idx: int, offset: np.ndarray | None = None,
                     quat_wxyz: np.ndarray | None = None) -> tuple[int, tuple[np.ndarray, np.ndarray]]:
        """``(MuJoCo body, world frame)`` of a body point/frame (body semantic) or of a site."""
        mujoco, d = self.mujoco, self.data
        if objtype == int(mujoco.mjtObj.mjOBJ_SITE):
            return int(self.mj.site_bodyid[idx]), (d.site_xpos[idx].copy(), d.site_xmat[idx].reshape(3, 3).copy())
        p, R = self.body_frame(idx)
        if offset is not None:
            p = p + R @ offset
        if quat_wxyz is not None:
            R = R @ _quat_wxyz_matrix(mujoco, quat_wxyz)
        return idx, (p, R)

    def equalities(self) -> None:
        mujoco, mj = self.mujoco, self.mj
        E = mujoco.mjtEq
        for i in range(mj.neq):
            name = self.name("equality", i)
            etype = int(mj.eq_type[i])
            kind = mujoco.mjtEq(etype).name.replace("mjEQ_", "").lower()
            if etype not in (int(E.mjEQ_CONNECT), int(E.mjEQ_WELD), int(E.mjEQ_JOINT)):
                self.problems.append(f"{kind} equality {name!r}")
                continue
            if not mj.eq_active0[i]:
                self.problems.append(f"inactive (active='false') {kind} equality {name!r}")
                continue
            data = np.asarray(mj.eq_data[i], float)
            o1, o2 = int(mj.eq_obj1id[i]), int(mj.eq_obj2id[i])
            if etype == int(E.mjEQ_JOINT):
                self.coupling(name, o1, o2, data[:5])
                continue
            otype = int(mj.eq_objtype[i])
            jtype = JointType.SPHERICAL
            if etype == int(E.mjEQ_CONNECT):
                b1, f1 = self.object_frame(otype, o1, data[0:3])
                b2, f2 = self.object_frame(otype, o2, data[3:6])
            else:
                b1, f1 = self.object_frame(otype, o1, data[3:6], data[6:10])
                b2, f2 = self.object_frame(otype, o2, data[0:3])
                torquescale = float(data[10])
                if torquescale == 1.0:
                    jtype = JointType.FIXED
                elif torquescale != 0.0:  # 0: MuJoCo's weld acts as a connect
                    self.problems.append(f"weld equality {name!r}: torquescale {torquescale:g} (only 1, or 0 = "
                                         "connect, are exact with hard constraints)")
                    continue
            k1, k2 = self.body_map[b1], self.body_map[b2]
            if k1 == k2:
                if np.linalg.norm(f1[0] - f2[0]) > _POINT_TOL:
                    self.problems.append(f"{kind} equality {name!r} between two parts of one rigid body that do not "
                                         "coincide at qpos0")
                continue
            if k1 < 0:  # the follower must be a body: the world (or static geometry) is the base
                k1, k2, f1, f2 = k2, k1, f2, f1
            self.add_joint(jtype, k2, k1, f2, f1, name)

    def coupling(self, name: str, j1: int, j2: int, polycoef: np.ndarray) -> None:
        """MuJoCo's ``q1 - q1_0 = poly(q2 - q2_0)``: kamino coordinates are zero at qpos0, so it maps as is."""
        ka = self.joint_map[j1].joint
        kb = None if j2 < 0 else self.joint_map[j2].joint
        self.b.add_coupling(ka, kb, polycoef, name=name)

    # -- geoms --------------------------------------------------------------------------------
    def geoms(self) -> None:
        mujoco, mj, d = self.mujoco, self.mj, self.data
        G = mujoco.mjtGeom
        kinds = {int(G.mjGEOM_PLANE): GeomType.PLANE, int(G.mjGEOM_SPHERE): GeomType.SPHERE,
                 int(G.mjGEOM_CAPSULE): GeomType.CAPSULE, int(G.mjGEOM_BOX): GeomType.BOX,
                 int(G.mjGEOM_CYLINDER): GeomType.CYLINDER, int(G.mjGEOM_ELLIPSOID): GeomType.ELLIPSOID,
                 int(G.mjGEOM_HFIELD): GeomType.HFIELD}
        pairs = candidate_pairs(mujoco, mj)
        in_pair = {g for p in pairs for g in (p.geom1, p.geom2)}
        kgeom: dict[int, int] = {}
        for g in range(mj.ngeom):
            colliding = bool(mj.geom_contype[g] or mj.geom_conaffinity[g]) or g in in_pair
            if not colliding:
                continue  # visual geom
            t = int(mj.geom_type[g])
            name = self.name("geom", g)
            if t not in kinds:
                if g in in_pair:
                    kind = mujoco.mjtGeom(t).name.replace("mjGEOM_", "").lower()
                    self.problems.append(f"colliding {kind} geom {name!r} (kamino collides primitives only)")
                continue
            condim = int(mj.geom_condim[g])
            if condim not in (1, 3) and g in in_pair:
                self.problems.append(f"geom {name!r}: condim {condim} (torsional/rolling friction; kamino has "
                                     "condim 1 and 3)")
            if hasattr(mj, "geom_surfacevel") and np.any(np.asarray(mj.geom_surfacevel[g]) != 0.0):
                self.problems.append(f"geom {name!r}: surface velocity")
            kb = self.body_map[int(mj.geom_bodyid[g])]
            hfield = None
            if kinds[t] == GeomType.HFIELD:
                if kb >= 0:
                    self.problems.append(f"heightfield geom {name!r} on the moving body {self.b_name(kb)!r} (kamino's "
                                         "heightfields are static: put the geom in the worldbody or a body without "
                                         "joints)")
                    continue
                hfield = self.hfield(int(mj.geom_dataid[g]))
            p, q = self.local(kb, d.geom_xpos[g], d.geom_xmat[g].reshape(3, 3))
            size = np.asarray(mj.geom_size[g], float)
            mu = 0.0 if condim == 1 else float(mj.geom_friction[g, 0])
            # group/mask select no pair: every MuJoCo pair is enabled explicitly (set_collision) in pair()
            kgeom[g] = self.b.add_geom(kinds[t], kb, size=size[:1] if kinds[t] == GeomType.SPHERE else size, pos=p,
                                       quat=q, friction=mu, margin=float(mj.geom_margin[g]), group=1, mask=0,
                                       name=name, hfield=hfield)
            self.geom_info[kgeom[g]] = (kb, kinds[t], mu)
        for pair in pairs:
            self.pair(pair, kgeom)

    def b_name(self, kb: int) -> str:
        """The name of kamino body ``kb`` being built."""
        return self.b._bodies[kb].name

    def hfield(self, h: int) -> int:
        """The builder's heightfield of MuJoCo's heightfield ``h`` (added on first use): MuJoCo's compiled
        ``hfield_data`` (normalised, in kamino's row order, whether it came from ``elevation`` or a PNG ``file``)."""
        if h not in self.hfield_map:
            mj = self.mj
            nrow, ncol, adr = int(mj.hfield_nrow[h]), int(mj.hfield_ncol[h]), int(mj.hfield_adr[h])
            data = np.asarray(mj.hfield_data[adr:adr + nrow * ncol], float)
            self.hfield_map[h] = self.b.add_hfield(nrow, ncol, np.asarray(mj.hfield_size[h], float), data,
                                                   name=self.name("hfield", h))
        return self.hfield_map[h]

    def pair(self, pair: PairInfo, kgeom: dict[int, int]) -> None:
        g1, g2 = pair.geom1, pair.geom2
        if g1 not in kgeom or g2 not in kgeom:
            return  # a non-primitive geom: already reported
        mj = self.mj
        t1, t2 = int(mj.geom_type[g1]), int(mj.geom_type[g2])
        plane = int(self.mujoco.mjtGeom.mjGEOM_PLANE)
        if t1 == plane and t2 == plane:
            return  # MuJoCo has no plane-plane collider either
        (kb1, type1, mu1), (kb2, type2, mu2) = self.geom_info[kgeom[g1]], self.geom_info[kgeom[g2]]
        if kb1 == kb2:
            return  # no relative motion (MuJoCo skips a contact that moves no DoF)
        label = f"contact pair ({self.name('geom', g1)!r}, {self.name('geom', g2)!r})"
        key = (min(type1, type2), max(type1, type2))
        if key not in CONTACT_POINTS:
            self.problems.append(f"{label}: {key[0].name.lower()}-{key[1].name.lower()} collision")
            return
        if pair.condim not in (1, 3):
            if pair.explicit >= 0:
                self.problems.append(f"{label}: condim {pair.condim}")
            return
        mu = 0.0 if pair.condim == 1 else pair.friction
        if not np.isclose(max(mu1, mu2), mu, rtol=1e-12, atol=0.0):
            self.problems.append(f"{label}: friction {mu:g} differs from the larger of the geoms' frictions "
                                 f"{max(mu1, mu2):g} (pair-specific friction, priority or condim mix)")
        if pair.margin - pair.gap > 0.0:
            self.problems.append(f"{label}: margin - gap = {pair.margin - pair.gap:g} > 0 (MuJoCo keeps such geoms "
                                 "apart; kamino contacts act at zero distance)")
        self.b.set_collision(kgeom[g1], kgeom[g2], True)

    # -- all ----------------------------------------------------------------------------------
    def run(self, contact_capacity: int | None) -> MjcfImport:
        mujoco, mj = self.mujoco, self.mj
        self.problems += global_problems(mujoco, mj, self.spec)
        self.problems += joint_problems(mujoco, mj)
        acts = classify_actuators(mujoco, mj, self.problems)
        coupled = set()
        if self.equality_on:
            for i in range(mj.neq):
                if int(mj.eq_type[i]) == int(mujoco.mjtEq.mjEQ_JOINT):
                    coupled.update(int(x) for x in (mj.eq_obj1id[i], mj.eq_obj2id[i]) if x >= 0)
        self.bodies(acts, coupled)
        if self.equality_on:
            self.equalities()
        self.geoms()
        if self.problems:
            lines = "\n".join(f"  - {p}" for p in self.problems)
            raise ModelError(f"the MJCF model uses {len(self.problems)} feature(s) kamino does not support:\n{lines}")
        order = sorted(self.actuated)
        for i in order:
            kj, dof = self.actuated[i]
            spec = acts[int(mj.actuator_trnid[i, 0])]
            self.b.add_actuator(kj, name=spec.name, gear=spec.gear, ctrl_range=spec.ctrl_range, dof=dof)
        if contact_capacity is None and int(mj.nconmax) >= 0:
            # <size nconmax="N">: MuJoCo's (and MuJoCo Warp's) contacts per world, kamino's contact capacity; no
            # more than the pairs can produce together (the default, which never overflows)
            contact_capacity = min(int(mj.nconmax), self.b.full_contact_capacity())
        model = self.b.finalize(contact_capacity=contact_capacity)
        imp = MjcfImport(model=model, mj_model=mj, joints=tuple(self.joint_map[j] for j in range(mj.njnt)),
                         body_map=tuple(self.body_map), body_source=tuple(self.body_source), actuators=tuple(order))
        with_extras(model, suggested_dt=self.suggested_dt, keyframes=self.keyframes(imp))
        return imp

    def keyframes(self, imp: MjcfImport) -> list[Keyframe]:
        """The file's ``<keyframe><key>`` elements as kamino keyframes (poses and twists at the key's qpos/qvel)."""
        mj, out = self.mj, []
        for k in range(mj.nkey):
            qpos, qvel = np.asarray(mj.key_qpos[k], float), np.asarray(mj.key_qvel[k], float)
            ctrl = np.asarray(mj.key_ctrl[k], float)[list(imp.actuators)] if mj.nu else np.zeros(0)
            name = self.name("key", k)
            for what, arr in (("qpos", qpos), ("qvel", qvel), ("ctrl", ctrl), ("time", mj.key_time[k])):
                if not np.all(np.isfinite(arr)):
                    raise ModelError(f"keyframe {name!r}: {what} contains NaN or inf")
            body_q, body_u = imp.body_state(qpos, qvel)
            out.append(Keyframe(name=name, time=float(mj.key_time[k]), body_q=body_q, body_u=body_u, ctrl=ctrl))
        return out


def _suggested_dt(source: str | os.PathLike | bytes) -> float | None:
    """The ``timestep`` of the file's ``<option>`` element, if it sets one (``None``: MuJoCo's default applies)."""
    try:
        if isinstance(source, bytes):
            source = source.decode("utf-8")
        text = source if isinstance(source, str) and source.lstrip().startswith("<") else Path(source).read_text()
        root = ElementTree.fromstring(text)
    except (OSError, ValueError, ElementTree.ParseError):
        return None
    for option in root.iter("option"):
        if "timestep" in option.attrib:
            try:
                dt = float(option.attrib["timestep"])
            except ValueError:
                return None
            return dt if np.isfinite(dt) and dt > 0 else None
    return None


def import_mjcf(source: str | os.PathLike | bytes, *, contact_capacity: int | None = None,
                light_mass_ratio: float = LIGHT_MASS_RATIO) -> MjcfImport:
    """Convert an MJCF model and keep the maps back to MuJoCo (:class:`MjcfImport`).

    Args:
        source: a path to an MJCF file, or the XML itself (a string starting with ``'<'``).
        contact_capacity: passed to :meth:`kamino.ModelBuilder.finalize`. Default: the file's
            ``<size nconmax="N"/>`` (MuJoCo's contacts per world) if it sets one, at most what the
            candidate pairs can produce; else what they can produce, which never overflows.
        light_mass_ratio: mass and inertia of the light intermediate bodies that chain MuJoCo joints
            of one body which form no exact composite joint, relative to that body's.

    Raises:
        ModelError: listing *every* unsupported feature found (docs/mjcf.md), or when MuJoCo itself
            rejects the file.
        FileNotFoundError: ``source`` is neither XML nor an existing file.
    """
    spec, mj = _compile(source)
    converter = _Converter(_mujoco(), spec, mj, light_mass_ratio)
    converter.suggested_dt = _suggested_dt(source)
    return converter.run(contact_capacity)


def load_mjcf(source: str | os.PathLike | bytes, *, contact_capacity: int | None = None,
              light_mass_ratio: float = LIGHT_MASS_RATIO) -> Model:
    """Load an MJCF model (file path or XML string) as a :class:`kamino.Model` (docs/mjcf.md).

    Names are kept (bodies, joints, geoms, actuators; unnamed ones get MuJoCo-style ``body3``,
    ``joint2``...); ``<connect>``/``<weld>`` become loop joints and ``<equality><joint>`` couplings
    named after the equality (or ``equality<i>``); actuators are in MuJoCo's order, so a MuJoCo ctrl
    vector drives the model through :meth:`kamino.Control.from_ctrl`. See :func:`import_mjcf` for the
    options and for the qpos/qvel maps.
    """
    return import_mjcf(source, contact_capacity=contact_capacity, light_mass_ratio=light_mass_ratio).model
