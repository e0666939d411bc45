"""MJCF export: ``save_mjcf(model, path=None) -> str`` (docs/mjcf.md, "Export").

The inverse of :func:`kamino.io.mjcf.load_mjcf`: a single-world kamino model becomes an MJCF file that
MuJoCo (and MuJoCo Warp, Newton, MuJoCo's viewer) loads, and that ``load_mjcf`` reads back into a
model with the same physics. MuJoCo describes a mechanism as a kinematic *tree* plus equality
constraints, so:

* a spanning tree of the joint graph (the world is a node) is chosen by Kruskal's algorithm over the
  joints in a fixed order of preference: joints MJCF can only express as tree joints first (prismatic,
  cylindrical, universal, cartesian, FIXED to the world, and every joint with actuation, limits,
  armature, damping, a spring or a coupling), then plain revolute joints, then plain spherical and
  FIXED joints; ties go by joint index, so the last-listed joint of a loop closes it;
* every MJCF body frame is its kamino body's centre-of-mass frame at ``body_q0``, placed relative to its
  tree parent; the tree is oriented from the world by breadth-first search, so a tree joint may point
  from kamino's follower to its base (its axes are then negated so that MuJoCo's ``qpos`` is still
  kamino's coordinate);
* the loop-closing joints become equalities: SPHERICAL -> ``<connect>``, REVOLUTE -> two ``<connect>``
  on its axis, FIXED -> ``<weld>`` (with an explicit ``relpose``); couplings -> ``<equality><joint>``.

Everything that has no MJCF equivalent raises ``ValueError`` listing every problem found.
"""

from __future__ import annotations

import math
import os
import xml.etree.ElementTree as ET
from collections import deque
from typing import Any

import numpy as np

from kamino.hostmath import quat_mul, quat_to_matrix
from kamino.model import CONTACT_POINTS, ActuationMode, GeomType, JointType, Model

#: Distance [m] between the two ``<connect>`` points that close a revolute loop joint (along its axis).
REVOLUTE_CONNECT_SPACING = 0.1
#: ``solref`` time constant [s] of the exported equality constraints (MuJoCo's default is 0.02).
EQUALITY_TIMECONST = 0.004
#: A joint coordinate at the reference pose below this [m or rad] is written as 0 (no ``ref``).
_REF_TOL = 1e-12
#: A loop closed by ``<connect>`` must be closed at the reference pose to within this [m or rad]: MuJoCo
#: takes the second body's anchor from the reference pose.
_CLOSURE_TOL = 1e-6

_MJ_GEOM = {GeomType.PLANE: "plane", GeomType.SPHERE: "sphere", GeomType.CAPSULE: "capsule", GeomType.BOX: "box",
            GeomType.CYLINDER: "cylinder", GeomType.ELLIPSOID: "ellipsoid", GeomType.HFIELD: "hfield"}
_GEOM_SIZES = {GeomType.SPHERE: 1, GeomType.CAPSULE: 2, GeomType.BOX: 3, GeomType.CYLINDER: 2, GeomType.ELLIPSOID: 3,
               GeomType.HFIELD: 0}
#: contype/conaffinity of geoms in a kamino contact pair, and of the others (they then pair with nothing)
_COLLIDING, _NON_COLLIDING = (1, 1), (2, 0)


def _fmt(values: Any) -> str:
    """Numbers as MJCF text: shortest round-trip repr of each float64 (so the file is exact)."""
    arr = np.atleast_1d(np.asarray(values, dtype=float)).reshape(-1)
    out = []
    for v in arr:
        v = float(v)
        out.append(repr(0.0 if v == 0.0 else v))
    return " ".join(out)


def _wxyz(q_xyzw: np.ndarray) -> np.ndarray:
    q = np.asarray(q_xyzw, float)
    q = q / np.linalg.norm(q)
    if q[3] < 0:
        q = -q
    return np.array([q[3], q[0], q[1], q[2]])


def _conj(q: np.ndarray) -> np.ndarray:
    return np.array([-q[0], -q[1], -q[2], q[3]])


def _joint_world_frames(model: Model, j: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray,
                                                       np.ndarray]:
    """``(p_B, q_Bj, p_F, q_Fj)`` of joint ``j`` at ``body_q0`` (world anchors and joint-frame quaternions),
    plus the relative pose ``(t, Q)`` of formulation.md §2.2."""
    def pose(b: int) -> tuple[np.ndarray, np.ndarray]:
        if b < 0:
            return np.zeros(3), np.array([0.0, 0.0, 0.0, 1.0])
        q = model.body_q0[b]
        return np.asarray(q[:3], float), np.asarray(q[3:], float) / np.linalg.norm(q[3:])

    (rB, qB), (rF, qF) = pose(int(model.joint_parent[j])), pose(int(model.joint_child[j]))
    p_B = rB + quat_to_matrix(qB) @ model.joint_anchor_B[j]
    p_F = rF + quat_to_matrix(qF) @ model.joint_anchor_F[j]
    q_Bj = quat_mul(qB, model.joint_frame_B[j] / np.linalg.norm(model.joint_frame_B[j]))
    q_Fj = quat_mul(qF, model.joint_frame_F[j] / np.linalg.norm(model.joint_frame_F[j]))
    Q = quat_mul(_conj(q_Bj), q_Fj)
    if Q[3] < 0:
        Q = -Q
    t = quat_to_matrix(q_Bj).T @ (p_F - p_B)
    return p_B, q_Bj, p_F, q_Fj, t, Q


def joint_coordinates0(model: Model, j: int) -> np.ndarray:
    """Joint ``j``'s scalar coordinates at ``body_q0`` (host version of ``kamino.joint_positions`` for the types
    with scalar coordinates: REVOLUTE, PRISMATIC, CYLINDRICAL, UNIVERSAL, CARTESIAN; empty for the others)."""
    *_, t, Q = _joint_world_frames(model, j)
    jt = JointType(int(model.joint_type[j]))
    angle = 2.0 * math.atan2(Q[0], Q[3])
    if jt == JointType.REVOLUTE:
        return np.array([angle])
    if jt == JointType.PRISMATIC:
        return np.array([t[0]])
    if jt == JointType.CYLINDRICAL:
        return np.array([t[0], angle])
    if jt == JointType.UNIVERSAL:
        R = quat_to_matrix(Q)
        x_F, y_F = R[:, 0], R[:, 1]
        th1 = math.atan2(y_F[2], y_F[1])
        th2 = math.atan2(float(np.cross([1.0, 0.0, 0.0], x_F) @ y_F), x_F[0])
        return np.array([th1, th2])
    if jt == JointType.CARTESIAN:
        return t.copy()
    return np.zeros(0)


def _shift_poly(coef: np.ndarray, shift_b: float, shift_a: float) -> np.ndarray:
    """Coefficients of ``P(x) = poly(x + shift_b) - shift_a`` (``poly`` of degree <= 4, coefficients a_0..a_4)."""
    out = np.zeros(5)
    for k, c in enumerate(coef):
        for i in range(k + 1):
            out[i] += c * math.comb(k, i) * shift_b ** (k - i)
    out[0] -= shift_a
    return out


class _Exporter:
    """One kamino -> MJCF export (state shared by the steps of :func:`save_mjcf`)."""

    def __init__(self, model: Model, lossy: bool):
        self.m = model
        self.lossy = lossy
        self.problems: list[str] = []
        self.dropped: list[str] = []
        m = model
        self.nb, self.nj = m.num_bodies, m.num_joints
        self.jtype = [JointType(int(t)) for t in m.joint_type]
        self.coupled = set(int(j) for j in m.coupling_joint_a) | set(int(j) for j in m.coupling_joint_b if j >= 0)
        self.c0 = [joint_coordinates0(m, j) for j in range(self.nj)]
        # per body: MJCF parent (kamino body, -1 world), tree joint (-1: none), forward orientation
        self.mj_parent = [-1] * self.nb
        self.tree_joint = [-1] * self.nb
        self.forward = [True] * self.nb
        self.children: list[list[int]] = [[] for _ in range(self.nb + 1)]  # index nb: the world
        self.static = [False] * self.nb
        self.free_root: dict[int, int | None] = {}  # root body -> its FREE joint (None: a free joint is added)
        self.cut: list[int] = []
        self.dof_joint: dict[tuple[int, int], str] = {}  # (kamino joint, DoF) -> MJCF joint name
        self.joint_names: set[str] = set(m.joint_names)
        self.used_joint_names: set[str] = set()

    # -- helpers -----------------------------------------------------------------------------
    def jname(self, j: int) -> str:
        return self.m.joint_names[j]

    def bname(self, b: int) -> str:
        return self.m.body_names[b]

    def dofs(self, j: int) -> slice:
        s = int(self.m.joint_dof_start[j])
        return slice(s, s + int(self.m.joint_dof_count[j]))

    def features(self, j: int) -> list[str]:
        """What a joint carries that an equality constraint cannot (actuation, limits, passive terms, couplings)."""
        m, d = self.m, self.dofs(j)
        out = []
        if np.any(m.dof_act_mode[d] != int(ActuationMode.PASSIVE)):
            out.append("actuation")
        if np.any(np.isfinite(m.dof_lower[d])) or np.any(np.isfinite(m.dof_upper[d])):
            out.append("limits")
        for field in ("armature", "damping", "stiffness"):
            if np.any(getattr(m, f"dof_{field}")[d] != 0.0):
                out.append(field)
        if j in self.coupled:
            out.append("a coupling")
        return out

    def pose(self, b: int) -> tuple[np.ndarray, np.ndarray]:
        """``(position, quaternion xyzw)`` of body ``b``'s CoM frame at ``body_q0`` (the world for -1)."""
        if b < 0:
            return np.zeros(3), np.array([0.0, 0.0, 0.0, 1.0])
        q = np.asarray(self.m.body_q0[b], float)
        return q[:3].copy(), q[3:] / np.linalg.norm(q[3:])

    def local_point(self, b: int, p_world: np.ndarray) -> np.ndarray:
        r, q = self.pose(b)
        return quat_to_matrix(q).T @ (np.asarray(p_world, float) - r)

    def local_dir(self, b: int, v_world: np.ndarray) -> np.ndarray:
        return quat_to_matrix(self.pose(b)[1]).T @ np.asarray(v_world, float)

    def unique_joint_name(self, base: str, own: bool = True) -> str:
        """An unused MJCF joint name: a kamino joint keeps its own name (``own``); generated names (the parts of a
        composite joint, added free joints) avoid every kamino joint name."""
        name, k = base, 0
        while name in self.used_joint_names or ((not own or name != base) and name in self.joint_names):
            k += 1
            name = f"{base}_{k}"
        self.used_joint_names.add(name)
        return name

    def part_names(self, j: int, suffixes: tuple[str, ...]) -> list[str]:
        """Names of the MuJoCo joints of a composite kamino joint, one per DoF: the parts of a name
        ``a+b(+c)`` that load_mjcf gave the composite (so that a loaded model keeps its joint names), else
        ``<name>_<suffix>``."""
        name = self.jname(j)
        parts = name.split("+")
        if len(parts) == len(suffixes) and all(parts) and len(set(parts)) == len(parts) and \
                not any(p in self.used_joint_names or p in self.joint_names for p in parts):
            return [self.unique_joint_name(p, own=False) for p in parts]
        return [self.unique_joint_name(f"{name}_{s}", own=False) for s in suffixes]

    # -- checks -------------------------------------------------------------------------------
    def check_model(self) -> None:
        m = self.m
        if m.num_worlds != 1:
            raise ValueError(f"save_mjcf exports one world; this model has {m.num_worlds} worlds. Export the "
                             "single-world model that was replicated or concatenated (an MJCF file describes one "
                             "world)")
        if "world" in m.body_names:
            self.problems.append("body named 'world' (the name of MuJoCo's world body); rename it")
        restitution = np.nonzero(np.asarray(m.geom_restitution) > 0.0)[0]
        if restitution.size:
            names = ", ".join(repr(m.geom_names[g]) for g in restitution[:6])
            msg = (f"geom restitution on geoms {names}{' ...' if restitution.size > 6 else ''} (MuJoCo has no "
                   "restitution coefficient)")
            (self.dropped if self.lossy else self.problems).append(msg)
        moving = np.nonzero(np.any(np.asarray(m.body_u0) != 0.0, axis=1))[0]
        if moving.size:
            names = ", ".join(repr(m.body_names[b]) for b in moving[:6])
            msg = (f"initial body velocities (body_u0) of bodies {names}{' ...' if moving.size > 6 else ''} (MJCF "
                   "models start at rest; save_mjcf writes no keyframe)")
            (self.dropped if self.lossy else self.problems).append(msg)

    # -- spanning tree --------------------------------------------------------------------
    def keep_rank(self, j: int) -> int:
        """0: must be a tree joint; 1: plain revolute (cut as two connects); 2: plain spherical/FIXED (exact cut)."""
        jt = self.jtype[j]
        if jt in (JointType.PRISMATIC, JointType.CYLINDRICAL, JointType.UNIVERSAL, JointType.CARTESIAN):
            return 0
        if self.features(j) or (jt == JointType.FIXED and int(self.m.joint_parent[j]) < 0):
            return 0
        return 1 if jt == JointType.REVOLUTE else 2

    def spanning_tree(self) -> None:
        m, nb = self.m, self.nb
        world = nb
        parent = list(range(nb + 1))

        def find(a: int) -> int:
            while parent[a] != a:
                parent[a] = parent[parent[a]]
                a = parent[a]
            return a

        def node(b: int) -> int:
            return world if b < 0 else b

        edges = [j for j in range(self.nj) if self.jtype[j] != JointType.FREE]
        tree: list[int] = []
        for j in sorted(edges, key=lambda j: (self.keep_rank(j), j)):
            a, b = find(node(int(m.joint_parent[j]))), find(node(int(m.joint_child[j])))
            if a == b:
                self.cut.append(j)
            else:
                parent[a] = b
                tree.append(j)
        self.cut.sort()
        # roots of the components without the world: the child of a FREE joint (from the world first), else a
        # free joint is added on the component's first body
        frees = [j for j in range(self.nj) if self.jtype[j] == JointType.FREE]
        frees.sort(key=lambda j: (int(m.joint_parent[j]) >= 0, j))
        used_free: set[int] = set()
        roots: dict[int, int] = {}  # component -> root body
        for j in frees:
            c = int(m.joint_child[j])
            comp = find(c)
            if comp != find(world) and comp not in roots:
                roots[comp] = c
                self.free_root[c] = j
                used_free.add(j)
        for b in range(nb):
            comp = find(b)
            if comp != find(world) and comp not in roots:
                roots[comp] = b
                self.free_root[b] = None
        for j in frees:
            if j in used_free:
                feats = self.features(j)
                bad = [f for f in feats if f in ("actuation", "limits")]
                if bad:
                    self.problems.append(f"FREE joint {self.jname(j)!r}: {' and '.join(bad)} (a MuJoCo free joint has "
                                         "no limits, and joint actuators drive hinges and slides only)")
                elif int(m.joint_parent[j]) >= 0 and feats:
                    self.problems.append(f"FREE joint {self.jname(j)!r} between two bodies with {', '.join(feats)} "
                                         "(MJCF free joints are relative to the world)")
                continue
            if self.features(j):
                self.problems.append(f"FREE joint {self.jname(j)!r} with {', '.join(self.features(j))} inside a "
                                     "kinematic tree (a FREE joint only roots a floating body in MJCF)")
        # orient the tree from the world (and from the floating roots) by breadth-first search
        adj: dict[int, list[int]] = {i: [] for i in range(nb + 1)}
        for j in tree:
            p, c = node(int(m.joint_parent[j])), int(m.joint_child[j])
            adj[p].append(j)
            adj[c].append(j)
        seen = [False] * (nb + 1)
        order = [world, *sorted(self.free_root)]
        for start in order:
            if seen[start]:
                continue
            seen[start] = True
            if start != world:
                self.children[world].append(start)
            queue = deque([start])
            while queue:
                u = queue.popleft()
                for j in sorted(adj[u]):
                    p, c = node(int(m.joint_parent[j])), int(m.joint_child[j])
                    v, fwd = (c, True) if p == u else (p, False)
                    if seen[v]:
                        continue
                    seen[v] = True
                    self.mj_parent[v] = -1 if u == world else u
                    self.tree_joint[v] = j
                    self.forward[v] = fwd
                    self.children[u].append(v)
                    queue.append(v)
        for b in range(nb):  # static: FIXED all the way to the world
            path, x = [], b
            while x >= 0 and self.tree_joint[x] >= 0 and self.jtype[self.tree_joint[x]] == JointType.FIXED:
                path.append(x)
                x = self.mj_parent[x]
            if x < 0 and b not in self.free_root:
                for y in path:
                    self.static[y] = True
        for j in self.cut:
            feats = self.features(j)
            jt = self.jtype[j]
            if jt not in (JointType.SPHERICAL, JointType.REVOLUTE, JointType.FIXED):
                self.problems.append(f"{jt.name} joint {self.jname(j)!r} closes a kinematic loop whose other joints "
                                     "cannot close it either (MJCF closes loops with <connect> and <weld> only: "
                                     "spherical, revolute and FIXED joints)")
            elif feats:
                self.problems.append(f"loop-closing {jt.name} joint {self.jname(j)!r} has {', '.join(feats)} (an MJCF "
                                     "equality constraint carries none; no other joint of its loop can close it)")

    # -- XML: bodies and joints ---------------------------------------------------------------
    def mj_joint(self, body_el: ET.Element, name: str, kind: str, pos: np.ndarray | None, axis: np.ndarray | None,
                 j: int, dof: int | None, ref: float = 0.0) -> None:
        """One MJCF ``<joint>`` for DoF ``dof`` of kamino joint ``j`` (None: the whole joint: ball/free)."""
        m = self.m
        el = ET.SubElement(body_el, "joint", name=name, type=kind)
        if pos is not None:
            el.set("pos", _fmt(pos))
        if axis is not None:
            el.set("axis", _fmt(axis / np.linalg.norm(axis)))
        if kind in ("hinge", "slide"):
            assert dof is not None
            d = int(m.joint_dof_start[j]) + dof
            self.dof_joint[(j, dof)] = name
            if ref != 0.0:
                el.set("ref", _fmt(ref))
            lo, hi = float(m.dof_lower[d]), float(m.dof_upper[d])
            if np.isfinite(lo) or np.isfinite(hi):
                el.set("limited", "true")
                el.set("range", _fmt([lo, hi]))
            else:
                el.set("limited", "false")
            for field, attr in (("armature", "armature"), ("damping", "damping"), ("stiffness", "stiffness")):
                v = float(getattr(m, f"dof_{field}")[d])
                if v != 0.0:
                    el.set(attr, _fmt(v))
            if float(m.dof_stiffness[d]) != 0.0:
                el.set("springref", _fmt(m.dof_springref[d]))
        else:  # ball / free: one scalar per MuJoCo joint
            d = self.dofs(j)
            for field in ("armature", "damping"):
                vals = np.asarray(getattr(m, f"dof_{field}")[d], float)
                if vals.size and np.any(vals != 0.0):
                    if np.any(vals != vals[0]):
                        self.problems.append(f"{self.jtype[j].name} joint {self.jname(j)!r}: per-DoF {field} "
                                             f"{vals.tolist()} (a MuJoCo {kind} joint has one {field} for all DoFs)")
                    el.set(field, _fmt(vals[0]))

    def tree_joint_xml(self, body_el: ET.Element, b: int) -> None:
        """The MJCF joints of body ``b``'s tree joint (in ``b``'s frame, which is its CoM frame)."""
        m = self.m
        j = self.tree_joint[b]
        jt = self.jtype[j]
        fwd = self.forward[b]
        name = self.jname(j)
        p_B, q_Bj, p_F, q_Fj, _, _ = _joint_world_frames(m, j)
        R_B, R_F = quat_to_matrix(q_Bj), quat_to_matrix(q_Fj)
        ex_B, ey_B, ez_B, ey_F = R_B[:, 0], R_B[:, 1], R_B[:, 2], R_F[:, 1]
        s = 1.0 if fwd else -1.0
        anchor = self.local_point(b, p_F if fwd else p_B)
        c0 = self.c0[j]
        ref = [0.0 if abs(float(v)) <= _REF_TOL else float(v) for v in c0]
        d = self.dofs(j)
        if np.any(np.isfinite(m.dof_lower[d]) | np.isfinite(m.dof_upper[d])) and jt in (JointType.SPHERICAL,
                                                                                           JointType.FREE):
            self.problems.append(f"{jt.name} joint {name!r}: limits (MuJoCo ball joints have cone limits only, free "
                                 "joints none)")
        if np.any(m.dof_act_mode[d] != int(ActuationMode.PASSIVE)) and jt in (JointType.SPHERICAL, JointType.FREE):
            self.problems.append(f"{jt.name} joint {name!r}: actuation (MJCF joint actuators drive hinges and slides)")
        if jt == JointType.FIXED:
            return
        if jt == JointType.REVOLUTE:
            self.mj_joint(body_el, self.unique_joint_name(name), "hinge", anchor, self.local_dir(b, s * ex_B), j, 0,
                          ref[0])
        elif jt == JointType.PRISMATIC:
            self.mj_joint(body_el, self.unique_joint_name(name), "slide", anchor, self.local_dir(b, s * ex_B), j, 0,
                          ref[0])
        elif jt == JointType.CYLINDRICAL:
            axis = self.local_dir(b, s * ex_B)
            n1, n2 = self.part_names(j, ("slide", "hinge"))
            self.mj_joint(body_el, n1, "slide", anchor, axis, j, 0, ref[0])
            self.mj_joint(body_el, n2, "hinge", anchor, axis, j, 1, ref[1])
        elif jt == JointType.UNIVERSAL:
            if np.any(m.dof_armature[d] != 0.0):
                self.problems.append(f"UNIVERSAL joint {name!r}: armature (load_mjcf reads two hinges with armature "
                                     "as a chain through a light body, not as a universal joint)")
            n1, n2 = self.part_names(j, ("1", "2"))
            if fwd:  # R_rel = Rx(theta1) Ry(theta2): base x, then the follower's y
                self.mj_joint(body_el, n1, "hinge", anchor, self.local_dir(b, ex_B), j, 0, ref[0])
                self.mj_joint(body_el, n2, "hinge", anchor, self.local_dir(b, ey_F), j, 1, ref[1])
            else:  # R_rel^-1 = R(-y_F, theta2) R(-x_B, theta1)
                self.mj_joint(body_el, n2, "hinge", anchor, self.local_dir(b, -ey_F), j, 1, ref[1])
                self.mj_joint(body_el, n1, "hinge", anchor, self.local_dir(b, -ex_B), j, 0, ref[0])
        elif jt == JointType.CARTESIAN:
            axes = {0: ex_B, 1: ey_B, 2: ez_B}
            order = (0, 1, 2) if fwd else (0, 2, 1)  # reversed: (-x, -z, -y) stays right-handed
            parts = self.part_names(j, ("x", "y", "z"))
            for k in order:
                self.mj_joint(body_el, parts[k], "slide", anchor, self.local_dir(b, s * axes[k]), j, k, ref[k])
        elif jt == JointType.SPHERICAL:
            if np.any(m.dof_armature[d] != 0.0) and self.mj_parent[b] >= 0 and not self.static[self.mj_parent[b]]:
                self.problems.append(f"SPHERICAL joint {name!r}: armature with a moving parent (load_mjcf rejects "
                                     "armature on such a ball joint: kamino and MuJoCo apply it in different frames)")
            self.mj_joint(body_el, self.unique_joint_name(name), "ball", anchor, None, j, None)
        else:  # pragma: no cover - FREE joints are not tree edges
            raise AssertionError(jt)

    def inertial(self, body_el: ET.Element, b: int) -> None:
        m = self.m
        I = np.asarray(m.body_inertia[b], float)
        I = 0.5 * (I + I.T)
        el = ET.SubElement(body_el, "inertial", pos="0 0 0", mass=_fmt(m.body_mass[b]))
        if I[0, 1] == 0.0 and I[0, 2] == 0.0 and I[1, 2] == 0.0:
            el.set("diaginertia", _fmt(np.diag(I)))
        else:
            el.set("fullinertia", _fmt([I[0, 0], I[1, 1], I[2, 2], I[0, 1], I[0, 2], I[1, 2]]))

    def body_xml(self, parent_el: ET.Element, b: int) -> None:
        p = self.mj_parent[b]
        rp, qp = self.pose(p)
        rb, qb = self.pose(b)
        pos = quat_to_matrix(qp).T @ (rb - rp)
        quat = _wxyz(quat_mul(_conj(qp), qb))
        el = ET.SubElement(parent_el, "body", name=self.bname(b), pos=_fmt(pos), quat=_fmt(quat))
        self.inertial(el, b)
        if b in self.free_root:
            j = self.free_root[b]
            if j is None:
                ET.SubElement(el, "freejoint", name=self.unique_joint_name(f"{self.bname(b)}_free", own=False))
            else:
                self.mj_joint(el, self.unique_joint_name(self.jname(j)), "free", None, None, j, None)
        elif self.tree_joint[b] >= 0:
            self.tree_joint_xml(el, b)
        self.geoms_xml(el, b)
        for c in self.children[b]:
            self.body_xml(el, c)

    # -- XML: geoms and contacts ------------------------------------------------------------
    def geoms_xml(self, parent_el: ET.Element, b: int) -> None:
        m = self.m
        for g in np.nonzero(np.asarray(m.geom_body) == b)[0]:
            g = int(g)
            gt = GeomType(int(m.geom_type[g]))
            if gt == GeomType.PLANE and b >= 0 and not self.static[b]:
                self.problems.append(f"PLANE geom {m.geom_names[g]!r} on moving body {self.bname(b)!r} (MuJoCo allows "
                                     "planes on static bodies only)")
            size = [0.0, 0.0, 1.0] if gt == GeomType.PLANE else np.asarray(m.geom_size[g], float)[:_GEOM_SIZES[gt]]
            ct, ca = _COLLIDING if g in self.colliding else _NON_COLLIDING
            mu, margin = float(m.geom_friction[g]), float(m.geom_margin[g])
            el = ET.SubElement(parent_el, "geom", name=m.geom_names[g], type=_MJ_GEOM[gt], size=_fmt(size),
                               pos=_fmt(m.geom_pos[g]), quat=_fmt(_wxyz(m.geom_quat[g])),
                               friction=_fmt([mu, 0.005, 0.0001]), condim="3", contype=str(ct), conaffinity=str(ca))
            if gt == GeomType.HFIELD:  # its size is the asset's
                del el.attrib["size"]
                el.set("hfield", m.hfield_names[int(m.geom_dataid[g])])
            if margin != 0.0:
                el.set("margin", _fmt(margin))
                el.set("gap", _fmt(margin))

    def hfields_xml(self, root: ET.Element) -> None:
        """``<asset><hfield>`` of each heightfield: its normalised heights as ``elevation``, whose rows MJCF lists
        from ``+ry`` down (the reverse of ``Model.hfield_data``); MuJoCo normalises them again, which keeps them."""
        m = self.m
        if not m.num_hfields:
            return
        asset = ET.SubElement(root, "asset")
        for h in range(m.num_hfields):
            nrow, ncol, adr = int(m.hfield_nrow[h]), int(m.hfield_ncol[h]), int(m.hfield_adr[h])
            grid = np.asarray(m.hfield_data[adr:adr + nrow * ncol], float).reshape(nrow, ncol)
            ET.SubElement(asset, "hfield", name=m.hfield_names[h], nrow=str(nrow), ncol=str(ncol),
                          size=_fmt(m.hfield_size[h]), elevation=_fmt(grid[::-1]))

    def contact_plan(self) -> tuple[list[tuple[int, int]], list[tuple[int, int]]]:
        """``(excluded body pairs, explicit geom pairs)`` that make MuJoCo's pair set equal to kamino's.

        MuJoCo's automatic pairs (docs/mjcf.md, "Contact pairs"; ``_mjcf_contacts``) are reproduced on the
        exported tree: geoms of kamino pairs get contype = conaffinity = 1, the others pair with nothing. A body
        pair with an automatic pair kamino lacks is excluded; kamino pairs MuJoCo would not generate (or that
        an exclusion removed) are written as explicit ``<pair>`` elements."""
        m = self.m
        kpairs = {(min(int(a), int(b)), max(int(a), int(b))) for a, b in zip(m.pair_geom_a, m.pair_geom_b,
                                                                                strict=True)}
        self.colliding = {g for p in kpairs for g in p}
        WORLD = -1

        def weld(b: int) -> int:
            while b >= 0 and not self.static[b] and b not in self.free_root and \
                    self.jtype[self.tree_joint[b]] == JointType.FIXED:
                b = self.mj_parent[b]
            return WORLD if b < 0 or self.static[b] else b

        def weld_parent(b: int) -> int:
            w = weld(b)
            return WORLD if w == WORLD else weld(self.mj_parent[w])

        gbody = [int(x) for x in m.geom_body]
        auto = set()
        col = sorted(self.colliding)
        for i, g1 in enumerate(col):
            for g2 in col[i + 1:]:
                b1, b2 = gbody[g1], gbody[g2]
                w1, w2 = weld(b1), weld(b2)
                if w1 == w2:
                    continue
                if w1 != WORLD and w2 != WORLD and (w1 == weld_parent(b2) or w2 == weld_parent(b1)):
                    continue
                auto.add((g1, g2))
        extra, missing = auto - kpairs, kpairs - auto
        mjbody = [WORLD if b < 0 else b for b in gbody]
        excluded = sorted({(min(mjbody[a], mjbody[b]), max(mjbody[a], mjbody[b])) for a, b in extra})
        ex_set = set(excluded)
        explicit = set(missing)
        for a, b in kpairs:
            if (min(mjbody[a], mjbody[b]), max(mjbody[a], mjbody[b])) in ex_set:
                explicit.add((a, b))
        return excluded, sorted(explicit)

    # -- XML: equalities and actuators ------------------------------------------------------
    def equalities_xml(self, root: ET.Element) -> None:
        m = self.m
        eq = ET.Element("equality")
        names: set[str] = set()

        def eq_name(base: str) -> str:
            name, k = base, 0
            while name in names:
                k += 1
                name = f"{base}_{k}"
            names.add(name)
            return name

        for j in self.cut:
            jt = self.jtype[j]
            if jt not in (JointType.SPHERICAL, JointType.REVOLUTE, JointType.FIXED) or self.features(j):
                continue  # already reported
            P, C = int(m.joint_parent[j]), int(m.joint_child[j])
            if (P < 0 or self.static[P]) and self.static[C]:
                continue  # both sides welded to the world: nothing moves
            p_B, q_Bj, p_F, q_Fj, _, _ = _joint_world_frames(m, j)
            body = {"body1": self.bname(C)}
            if P >= 0:
                body["body2"] = self.bname(P)
            a_F = np.asarray(m.joint_anchor_F[j], float)  # C's frame is its CoM frame
            if jt == JointType.FIXED:
                X_B, X_F = m.joint_frame_B[j], m.joint_frame_F[j]
                rel = _wxyz(quat_mul(X_F / np.linalg.norm(X_F), _conj(X_B / np.linalg.norm(X_B))))
                ET.SubElement(eq, "weld", name=eq_name(self.jname(j)), **body,
                              anchor=_fmt(m.joint_anchor_B[j]), relpose=_fmt(np.concatenate([a_F, rel])),
                              torquescale="1")
                continue
            gap = float(np.linalg.norm(p_F - p_B))
            if jt == JointType.REVOLUTE:
                ex_B, ex_F = quat_to_matrix(q_Bj)[:, 0], quat_to_matrix(q_Fj)[:, 0]
                gap = max(gap, float(np.linalg.norm(np.cross(ex_B, ex_F))) * REVOLUTE_CONNECT_SPACING)
            if gap > _CLOSURE_TOL:
                self.problems.append(f"loop-closing {jt.name} joint {self.jname(j)!r} is open by {gap:.3g} m at the "
                                     "reference pose (body_q0); MJCF's <connect> closes a loop at the reference pose. "
                                     "Assemble the model first (kamino.forward_kinematics)")
                continue
            ET.SubElement(eq, "connect", name=eq_name(self.jname(j)), **body, anchor=_fmt(a_F))
            if jt == JointType.REVOLUTE:
                axis_F = quat_to_matrix(m.joint_frame_F[j] / np.linalg.norm(m.joint_frame_F[j]))[:, 0]
                ET.SubElement(eq, "connect", name=eq_name(f"{self.jname(j)}_axis"), **body,
                              anchor=_fmt(a_F + REVOLUTE_CONNECT_SPACING * axis_F))
        for k in range(m.num_couplings):
            ja, jb = int(m.coupling_joint_a[k]), int(m.coupling_joint_b[k])
            ca = float(self.c0[ja][0]) if abs(float(self.c0[ja][0])) > _REF_TOL else 0.0
            cb = 0.0 if jb < 0 else (float(self.c0[jb][0]) if abs(float(self.c0[jb][0])) > _REF_TOL else 0.0)
            coef = _shift_poly(np.asarray(m.coupling_coef[k], float), cb, ca)
            attrs = {"joint1": self.dof_joint.get((ja, 0), self.jname(ja))}
            if jb >= 0:
                attrs["joint2"] = self.dof_joint.get((jb, 0), self.jname(jb))
            ET.SubElement(eq, "joint", name=eq_name(m.coupling_names[k]), **attrs, polycoef=_fmt(coef))
        if len(eq):
            root.append(eq)

    def actuators_xml(self, root: ET.Element) -> None:
        m = self.m
        if m.num_actuators == 0:
            return
        act = ET.SubElement(root, "actuator")
        owner = np.repeat(np.arange(self.nj), m.joint_dof_count)
        for a in range(m.num_actuators):
            d = int(m.actuator_dof[a])
            j = int(owner[d])
            k = d - int(m.joint_dof_start[j])
            name = m.actuator_names[a]
            joint = self.dof_joint.get((j, k))
            if joint is None:
                continue  # a ball/free/loop joint: already reported
            mode = ActuationMode(int(m.dof_act_mode[d]))
            kp, kd, limit = float(m.dof_kp[d]), float(m.dof_kd[d]), float(m.dof_effort_limit[d])
            gear = float(m.actuator_gear[a])
            attrs = {"name": name, "joint": joint}
            if mode == ActuationMode.EFFORT:
                tag = "motor"
                attrs["gear"] = _fmt(gear)
                force = limit / abs(gear)
            elif mode == ActuationMode.POSITION:
                tag = "position"
                if kp <= 0.0:
                    self.problems.append(f"actuator {name!r}: position actuation with kp = 0 (a MuJoCo position "
                                         "actuator's gain is kp; load_mjcf needs kp > 0)")
                    continue
                if self.c0[j].size and abs(float(self.c0[j][k])) > _REF_TOL:
                    self.problems.append(f"actuator {name!r}: position actuator on joint {self.jname(j)!r} whose "
                                         f"coordinate at the reference pose is {float(self.c0[j][k]):.6g}, not 0 "
                                         "(load_mjcf needs ref = 0 under a position actuator)")
                    continue
                attrs["kp"], attrs["kv"] = _fmt(kp), _fmt(kd)
                force = limit
            else:
                tag = "velocity"
                attrs["kv"] = _fmt(kd)
                force = limit
            lo, hi = (float(v) for v in m.actuator_ctrl_range[a])
            if np.isfinite(lo) or np.isfinite(hi):
                attrs["ctrllimited"], attrs["ctrlrange"] = "true", _fmt([lo, hi])
            else:
                attrs["ctrllimited"] = "false"
            if np.isfinite(force):
                attrs["forcelimited"], attrs["forcerange"] = "true", _fmt([-force, force])
            else:
                attrs["forcelimited"] = "false"
            ET.SubElement(act, tag, **attrs)

    # -- all --------------------------------------------------------------------------------
    def run(self, model_name: str) -> str:
        self.check_model()
        self.spanning_tree()
        excluded, explicit = self.contact_plan()
        m = self.m
        root = ET.Element("mujoco", model=model_name)
        loops = [self.jname(j) for j in self.cut]
        root.append(ET.Comment(
            f" exported by kamino.save_mjcf: {self.nb} bodies, {self.nj} joints; loop-closing joints (as equalities): "
            f"{', '.join(loops) if loops else 'none'} "))
        if self.dropped:
            root.append(ET.Comment(" dropped (lossy=True): " + "; ".join(self.dropped) + " "))
        ET.SubElement(root, "compiler", angle="radian", autolimits="true", inertiafromgeom="false")
        option = ET.SubElement(root, "option", gravity=_fmt(m.gravity[0]), integrator="implicitfast")
        if m.suggested_dt is not None:  # the source's time step (model.suggested_dt) goes back where it came from
            option.set("timestep", _fmt(m.suggested_dt))
        capacity = int(m.world_contact_capacity[0]) if m.num_pairs else 0
        if capacity < _full_contact_capacity(m):  # a capacity chosen below the default: MuJoCo's contacts per world
            ET.SubElement(root, "size", nconmax=str(capacity))
        if self.cut or m.num_couplings:
            # kamino's loop closures are hard; MuJoCo's equalities are soft: a 4 ms time constant (twice MuJoCo's
            # default time step) keeps the exported loops closed to ~1e-4 m where the default 20 ms lets them sag
            # by mm (docs/mjcf.md, "Export"). load_mjcf ignores solref.
            default = ET.SubElement(root, "default")
            ET.SubElement(default, "equality", solref=f"{EQUALITY_TIMECONST!r} 1")
        self.hfields_xml(root)
        world = ET.SubElement(root, "worldbody")
        self.geoms_xml(world, -1)
        for b in self.children[self.nb]:
            self.body_xml(world, b)
        if excluded or explicit:
            contact = ET.SubElement(root, "contact")
            for a, b in explicit:
                mu = max(float(m.geom_friction[a]), float(m.geom_friction[b]))
                margin = max(float(m.geom_margin[a]), float(m.geom_margin[b]))
                ET.SubElement(contact, "pair", geom1=m.geom_names[a], geom2=m.geom_names[b], condim="3",
                              friction=_fmt([mu, mu, 0.005, 0.0001, 0.0001]), margin=_fmt(margin), gap=_fmt(margin))
            for b1, b2 in excluded:
                ET.SubElement(contact, "exclude", body1="world" if b1 < 0 else self.bname(b1),
                              body2="world" if b2 < 0 else self.bname(b2))
        self.equalities_xml(root)
        self.actuators_xml(root)
        if self.problems:
            lines = "\n".join(f"  - {p}" for p in self.problems)
            raise ValueError(f"save_mjcf: the model uses {len(self.problems)} feature(s) MJCF cannot represent:\n"
                             f"{lines}")
        ET.indent(root, space="  ")
        return ET.tostring(root, encoding="unicode") + "\n"


def _full_contact_capacity(m: Model) -> int:
    """What the candidate pairs of a single-world model can produce together: ``finalize``'s default capacity."""
    types = [(GeomType(int(m.geom_type[a])), GeomType(int(m.geom_type[b])))
             for a, b in zip(m.pair_geom_a, m.pair_geom_b, strict=True)]
    return sum(CONTACT_POINTS[(a, b) if a <= b else (b, a)] for a, b in types)


def loop_closing_joints(model: Model) -> list[int]:
    """The joints of ``model`` that close loops: those the export's spanning tree leaves out (its order of
    preference, docs/mjcf.md "Spanning tree"; ``kamino.models.fourbar()``: ``rocker_ground``). Indices into the joint
    arrays; every world's, for a batch."""
    exporter = _Exporter(model, lossy=True)
    exporter.spanning_tree()
    return sorted(int(j) for j in exporter.cut)


def save_mjcf(model: Model, path: str | os.PathLike | None = None, *, lossy: bool = False,
              model_name: str = "kamino") -> str:
    """Export a single-world kamino model as MJCF; returns the XML text and writes it to ``path`` if given.

    ``kamino.load_mjcf(save_mjcf(m))`` simulates like ``m`` (docs/mjcf.md, "Export: kamino.save_mjcf"), and the
    file loads in MuJoCo itself (``mujoco.MjModel.from_xml_path``), its viewer, MuJoCo Warp and Newton: the
    joint graph becomes a spanning tree (MJCF bodies at the kamino CoM frames of ``body_q0``) plus
    ``<connect>``/``<weld>`` equalities for the loop-closing joints, couplings become ``<equality><joint>``,
    actuators ``<position>``/``<velocity>``/``<motor>``, and the contact pairs are reproduced exactly with
    contype/conaffinity, ``<exclude>`` and ``<pair>``.

    Args:
        model: a single-world :class:`kamino.Model`.
        path: where to write the file (None: only return the text).
        lossy: drop what MJCF has no equivalent for but MuJoCo can simulate without (geom restitution, initial
            body velocities) instead of raising; what was dropped is listed in an XML comment.
        model_name: the ``<mujoco model=...>`` name.

    Raises:
        ValueError: for a multi-world model, or listing every feature MJCF cannot represent (which joint, geom or
            actuator, and why; docs/mjcf.md).
    """
    text = _Exporter(model, lossy).run(model_name)
    if path is not None:
        with open(os.fspath(path), "w", encoding="utf-8") as f:
            f.write(text)
    return text
