"""MJCF export (kamino.save_mjcf, kamino/io/mjcf_export.py): round trips through load_mjcf and runs in MuJoCo.

Every procedural model of ``kamino.models`` (and a "zoo" of every joint type, reversed tree joints, joint
coordinates that are not zero at ``body_q0``, a coupling, a FIXED loop closure and explicit contact pairs) is
exported, read back with ``load_mjcf`` and compared: bodies, masses, inertias, geoms, contact pairs, actuators,
mobility, then a short simulation (JAX reference, float64: tests/conftest.py). MuJoCo itself loads the files and
keeps their loops closed. Simulations are batched (``kamino.concat``) into four compiled models to keep the file
under a minute on two cores.
"""

from __future__ import annotations

import dataclasses
import functools
import re

import jax
import numpy as np
import pytest

import kamino
from kamino import Actuation, GeomType, JointType
from kamino.hostmath import axis_frame, matrix_to_quat, quat_mul, quat_to_matrix
from kamino.io import load_mjcf
from kamino.io.mjcf_export import save_mjcf

mujoco = pytest.importorskip("mujoco")

jax.config.update("jax_enable_x64", True)

PROCEDURAL = [n for n in kamino.models.__all__ if n != "describe"]
ROBOTS = ["bdx", "dr_legs", "olaf", "animatronic"]
#: models with geom restitution, which MJCF cannot carry: exported with lossy=True, compared without restitution
LOSSY = {"newtons_cradle", "sphere_drop"}


# ---------------------------------------------------------------------------------------------
# the zoo: what the procedural models do not exercise
# ---------------------------------------------------------------------------------------------

def _conj(q):
    return np.array([-q[0], -q[1], -q[2], q[3]])


def _rot(axis, angle):
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    return np.concatenate([np.sin(angle / 2) * axis, [np.cos(angle / 2)]])


def _joint(b: kamino.ModelBuilder, jtype, parent, child, anchor, axis=(1.0, 0.0, 0.0), axis2=None,
           motion=(0.0, 0.0, 0.0, 1.0), t=(0.0, 0.0, 0.0), **kw) -> int:
    """A joint whose coordinates at the builder poses are ``(t, motion)`` (translation and rotation of the
    follower's joint frame in the base's), not zero as with ``add_joint_at``: the frames of ``add_joint_at``, with
    the follower frame moved back by the motion."""
    poses = {i: (bb.pos, bb.quat / np.linalg.norm(bb.quat)) for i, bb in enumerate(b._bodies)}
    rp, qp = poses.get(parent, (np.zeros(3), np.array([0.0, 0.0, 0.0, 1.0])))
    rc, qc = poses[child]
    Rp = quat_to_matrix(qp)
    ax_p = Rp.T @ np.asarray(axis, float)
    ax2_p = None if axis2 is None else Rp.T @ np.asarray(axis2, float)
    if jtype == JointType.UNIVERSAL:
        A = axis_frame(ax_p, ax2_p if ax2_p is not None else np.array([0.0, 1.0, 0.0]))
    elif jtype in (JointType.REVOLUTE, JointType.PRISMATIC, JointType.CYLINDRICAL):
        A = axis_frame(ax_p)
    else:
        A = np.eye(3)
    qa = matrix_to_quat(A)
    p_B = np.asarray(anchor, float)
    p_F = p_B + Rp @ A @ np.asarray(t, float)
    child_q = quat_mul(quat_mul(quat_mul(_conj(qc), qp), quat_mul(qa, np.asarray(motion, float))), _conj(qa))
    return b.add_joint(jtype, parent, child, parent_frame=(Rp.T @ (p_B - rp), (0, 0, 0, 1)),
                       child_frame=(quat_to_matrix(qc).T @ (p_F - rc), child_q), axis=ax_p, axis2=ax2_p, **kw)


def zoo(shifted: bool = False) -> kamino.Model:
    """Every tree joint type, with non-zero coordinates at body_q0 (MJCF ``ref``), three of them pointing against
    the tree (C, D and E hang from B through joints whose *base* is the lower body), limits, armature, damping, a
    spring, the three actuator kinds (one with gear and ctrl range), a polynomial coupling between joints with
    non-zero coordinates, a FIXED tree joint between moving bodies, a full (non-diagonal) inertia, a loop closed by
    a FIXED joint (``<weld>`` with a relpose), and contact pairs that MuJoCo's own rules would add or drop.
    ``shifted``: the translational joints (cylindrical, cartesian, prismatic) are not at zero either; their anchors
    then come back coincident (see SIM_BATCHES: kamino's curvature correction tells the two apart)."""
    t = 1.0 if shifted else 0.0
    b = kamino.ModelBuilder(gravity=(0.0, 0.0, -9.81))

    def body(name, pos, mass, quat=(0.0, 0.0, 0.0, 1.0), inertia=None):
        return b.add_body(mass, np.diag([0.02, 0.03, 0.04]) * mass if inertia is None else inertia, pos=pos,
                          quat=np.asarray(quat) / np.linalg.norm(quat), name=name)

    A = body("A", (0.0, 0.0, 1.0), 1.0, _rot((1, 2, 3), 0.4))
    B = body("B", (0.3, 0.0, 1.0), 0.8, _rot((0, 0, 1), 0.3))
    C = body("C", (0.3, 0.3, 1.0), 0.6, inertia=np.array([[0.02, 0.003, 0.0], [0.003, 0.03, 0.001],
                                                           [0.0, 0.001, 0.025]]))
    D = body("D", (0.6, 0.3, 1.0), 0.5, _rot((1, 0, 0), -0.5))
    E = body("E", (0.6, 0.6, 1.0), 0.4)
    F = body("F", (0.0, 0.3, 0.8), 0.3)
    G = body("G", (0.0, 0.5, 0.8), 0.3, _rot((0, 1, 1), 0.7))
    H = body("H", (0.0, 0.6, 0.8), 0.2)
    K = body("K", (-0.1, 0.3, 0.9), 0.2)
    hinge = _joint(b, JointType.REVOLUTE, -1, A, (0.0, 0.0, 1.2), axis=(0, 1, 0), motion=_rot((1, 0, 0), 0.3),
                   limits=(-1.0, 1.0), damping=0.1, armature=0.01, name="hinge")
    _joint(b, JointType.CYLINDRICAL, A, B, (0.15, 0.0, 1.0), axis=(1, 0, 0), motion=_rot((1, 0, 0), -0.2),
           t=(0.05 * t, 0, 0), actuation=Actuation("velocity", kd=1.0, effort_limit=5.0), name="cyl")
    _joint(b, JointType.UNIVERSAL, C, B, (0.3, 0.15, 1.0), axis=(0, 1, 0), axis2=(1, 0, 0),
           motion=quat_mul(_rot((1, 0, 0), 0.2), _rot((0, 1, 0), -0.3)), limits=(-0.5, 0.5), name="univ")
    cart = _joint(b, JointType.CARTESIAN, D, C, (0.45, 0.3, 1.0), t=(0.02 * t, -0.03 * t, 0.01 * t),
                  actuation=Actuation("effort", effort_limit=3.0), name="cart")
    slide = _joint(b, JointType.PRISMATIC, E, D, (0.6, 0.45, 1.0), axis=(0, 1, 0), t=(0.04 * t, 0, 0), stiffness=5.0,
                   springref=0.02, name="slide")
    _joint(b, JointType.SPHERICAL, A, F, (0.0, 0.15, 0.9), motion=_rot((1, 1, 0), 0.4), damping=0.05, name="ball")
    b.add_joint_at(JointType.REVOLUTE, F, G, anchor=(0.0, 0.4, 0.8), axis=(1, 0, 0), name="servo",
                   actuation=Actuation("position", kp=30.0, kd=1.0, effort_limit=4.0))
    b.add_joint_at(JointType.FIXED, G, H, anchor=(0.0, 0.55, 0.8), name="glue")
    b.add_joint_at(JointType.SPHERICAL, G, K, anchor=(-0.05, 0.4, 0.85), name="knuckle", damping=0.01)
    b.add_joint_at(JointType.FIXED, A, K, anchor=(-0.1, 0.2, 0.95), name="weld_loop")
    b.add_coupling(slide, hinge, polycoef=(0.04 * t - 0.2 * 0.3 - 0.1 * 0.09, 0.2, 0.1), name="mimic")
    b.add_actuator(cart, dof=1, gear=2.0, ctrl_range=(-1.0, 1.0), name="cart_y")
    ground = b.add_geom(GeomType.PLANE, -1, friction=0.7, name="ground")
    robot = {"group": 2, "mask": 1}  # robot geoms touch the ground only (as the procedural robots' feet)
    gb = b.add_geom(GeomType.SPHERE, B, size=0.05, friction=0.3, margin=0.01, name="ball_B", **robot)
    gc = b.add_geom(GeomType.BOX, C, size=(0.05, 0.04, 0.03), pos=(0.01, 0, 0), quat=_rot((0, 0, 1), 0.3),
                    name="box_C", **robot)
    b.add_geom(GeomType.CAPSULE, D, size=(0.02, 0.05), name="capsule_D", **robot)
    ge1 = b.add_geom(GeomType.CYLINDER, E, size=(0.03, 0.04), name="cyl_E", **robot)
    b.add_geom(GeomType.ELLIPSOID, F, size=(0.03, 0.04, 0.05), name="ellipsoid_F", **robot)
    b.add_geom(GeomType.SPHERE, E, size=0.02, pos=(0, 0, 0.05), name="sphere_E", **robot)
    b.set_collision(gb, gc, True)  # B and C are joined (kamino) and parent and child (MuJoCo): an explicit <pair>
    b.set_collision(ge1, ground, False)  # E's other geom still touches the ground: <exclude> plus a <pair>
    b.add_geom(GeomType.BOX, H, size=(0.02, 0.02, 0.02), group=4, mask=4, name="box_H")  # pairs with nothing
    return b.finalize()


# ---------------------------------------------------------------------------------------------
# helpers
# ---------------------------------------------------------------------------------------------

def _model(name: str) -> kamino.Model:
    if name.startswith("zoo"):
        return zoo(shifted=name == "zoo_shifted")
    return getattr(kamino.models, name)()


@functools.cache
def _round_trip(name: str) -> tuple[kamino.Model, kamino.Model, str]:
    """``(m, load_mjcf(save_mjcf(m)), xml)``; for the LOSSY models ``m`` without its restitution."""
    m = _model(name)
    xml = save_mjcf(m, lossy=name in LOSSY)
    if name in LOSSY:
        m = dataclasses.replace(m, geom_restitution=np.zeros_like(m.geom_restitution))
    m2 = load_mjcf(xml, contact_capacity=int(m.world_contact_capacity[0]))
    return m, m2, xml


def _welded_to_world(m: kamino.Model) -> set[int]:
    """Bodies joined to the world by FIXED joints only (MJCF static bodies: load_mjcf puts their geoms on the
    world and drops the body)."""
    out: set[int] = set()
    grew = True
    while grew:
        grew = False
        for j in range(m.num_joints):
            p, c = int(m.joint_parent[j]), int(m.joint_child[j])
            if m.joint_type[j] != JointType.FIXED:
                continue
            for a, bb in ((p, c), (c, p)):
                if (a < 0 or a in out) and bb >= 0 and bb not in out:
                    out.add(bb)
                    grew = True
    return out


def _pose(m: kamino.Model, b: int) -> tuple[np.ndarray, np.ndarray]:
    if b < 0:
        return np.zeros(3), np.eye(3)
    return np.asarray(m.body_q0[b, :3]), quat_to_matrix(m.body_q0[b, 3:])


#: Per joint type: the constrained translation axes and rotation axes of the joint frame (formulation.md §2.4);
#: "univ" is the normal to a universal joint's two axes.
_CONSTRAINED = {JointType.FIXED: ((0, 1, 2), (0, 1, 2)), JointType.REVOLUTE: ((0, 1, 2), (1, 2)),
                JointType.PRISMATIC: ((1, 2), (0, 1, 2)), JointType.CYLINDRICAL: ((1, 2), (1, 2)),
                JointType.UNIVERSAL: ((0, 1, 2), ("univ",)), JointType.SPHERICAL: ((0, 1, 2), ()),
                JointType.CARTESIAN: ((), (0, 1, 2)), JointType.FREE: ((), ())}


def _mobility(m: kamino.Model) -> int:
    """6 nb - rank of the joint rows at body_q0 (the mechanism's DoFs; couplings aside, as both models have the
    same ones), from the joint rows of formulation.md §2.5 built here in NumPy."""
    rows = []
    for j in range(m.num_joints):
        P, C = int(m.joint_parent[j]), int(m.joint_child[j])
        (rP, RP), (rC, RC) = _pose(m, P), _pose(m, C)
        RB, RF = RP @ quat_to_matrix(m.joint_frame_B[j]), RC @ quat_to_matrix(m.joint_frame_F[j])
        p = rP + RP @ m.joint_anchor_B[j]
        trans, rot = _CONSTRAINED[JointType(int(m.joint_type[j]))]
        dirs = [(RB[:, k], True) for k in trans]
        dirs += [(np.cross(RB[:, 0], RF[:, 1]) if k == "univ" else RB[:, k], False) for k in rot]
        for a, is_trans in dirs:
            row = np.zeros(6 * m.num_bodies)
            row[6 * C:6 * C + 6] = np.concatenate([a, np.cross(p - rC, a)]) if is_trans else np.r_[0, 0, 0, a]
            if P >= 0:
                row[6 * P:6 * P + 6] -= np.concatenate([a, np.cross(p - rP, a)]) if is_trans else np.r_[0, 0, 0, a]
            rows.append(row)
    if not rows:
        return 6 * m.num_bodies
    s = np.linalg.svd(np.array(rows), compute_uv=False)
    return 6 * m.num_bodies - int(np.sum(s > 1e-9 * s[0]))


# ---------------------------------------------------------------------------------------------
# structure
# ---------------------------------------------------------------------------------------------

@pytest.mark.parametrize("name", [*PROCEDURAL, "zoo", "zoo_shifted"])
def test_round_trip_keeps_the_model(name):
    """Bodies (less those welded to the world), masses and world inertias to 1e-9, poses, mobility, geoms, the
    contact-pair set, actuators and couplings survive ``load_mjcf(save_mjcf(m))``."""
    m, m2, _ = _round_trip(name)
    static = _welded_to_world(m)
    assert sorted(m2.body_names) == sorted(m.body_names[b] for b in range(m.num_bodies) if b not in static)
    for b2, bname in enumerate(m2.body_names):
        b = m.body_index(bname)
        assert abs(m2.body_mass[b2] - m.body_mass[b]) <= 1e-9 * m.body_mass[b]
        (r, R), (r2, R2) = _pose(m, b), _pose(m2, b2)
        np.testing.assert_allclose(r2, r, atol=1e-12)
        I, I2 = R @ m.body_inertia[b] @ R.T, R2 @ m2.body_inertia[b2] @ R2.T  # world frame (principal axes may differ)
        np.testing.assert_allclose(I2, I, atol=1e-9 * np.abs(I).max())
    np.testing.assert_allclose(m2.gravity, m.gravity)
    assert _mobility(m2) == _mobility(m)
    # geoms: same names, shapes, friction, margin and world poses
    assert sorted(m2.geom_names) == sorted(m.geom_names)
    for g2, gname in enumerate(m2.geom_names):
        g = m.geom_names.index(gname)
        assert m2.geom_type[g2] == m.geom_type[g]
        n = {0: 0, 1: 1, 2: 2, 3: 3, 4: 2, 5: 3}[int(m.geom_type[g])]
        np.testing.assert_allclose(m2.geom_size[g2, :n], m.geom_size[g, :n], rtol=1e-15)
        assert (m2.geom_friction[g2], m2.geom_margin[g2]) == (m.geom_friction[g], m.geom_margin[g])
        (r, R), (r2, R2) = _pose(m, int(m.geom_body[g])), _pose(m2, int(m2.geom_body[g2]))
        np.testing.assert_allclose(r2 + R2 @ m2.geom_pos[g2], r + R @ m.geom_pos[g], atol=1e-12)
        np.testing.assert_allclose(R2 @ quat_to_matrix(m2.geom_quat[g2]), R @ quat_to_matrix(m.geom_quat[g]),
                                   atol=1e-12)

    def pairs(mm):
        return {frozenset((mm.geom_names[a], mm.geom_names[c])) for a, c in zip(mm.pair_geom_a, mm.pair_geom_b,
                                                                                   strict=True)}

    assert pairs(m2) == pairs(m)
    # actuators: same order, modes, gains, limits, gears and ctrl ranges
    assert m2.actuator_names == m.actuator_names
    for field in ("dof_act_mode", "dof_kp", "dof_kd", "dof_effort_limit"):
        np.testing.assert_allclose(getattr(m2, field)[m2.actuator_dof], getattr(m, field)[m.actuator_dof])
    np.testing.assert_allclose(m2.actuator_gear, m.actuator_gear)
    np.testing.assert_allclose(m2.actuator_ctrl_range, m.actuator_ctrl_range)
    assert m2.coupling_names == m.coupling_names


def test_zoo_exports_what_it_should():
    """The zoo's file: refs for non-zero coordinates, axes negated on reversed joints, a <weld> with relpose, the
    coupling's polynomial re-centred on the reference coordinates, and the contact plan."""
    _, m2, xml = _round_trip("zoo_shifted")
    assert re.search(r'<joint name="hinge" type="hinge" [^>]*ref="0.3', xml)
    assert re.search(r'<weld name="weld_loop" body1="K" body2="A" [^>]*relpose=', xml)
    # geoms in no kamino pair pair with nothing (cyl_E), MuJoCo's extra pairs are excluded by body (the robot geoms
    # touch the ground only), and B-C (parent and child in MuJoCo, forced on in kamino) is an explicit pair
    assert re.search(r'<geom name="cyl_E" [^>]*contype="2" conaffinity="0"', xml)
    assert '<exclude body1="B" body2="D" />' in xml
    assert re.findall(r'<pair geom1="(\w+)" geom2="(\w+)"', xml) == [("ball_B", "box_C")]
    # q_slide = 0.04 + 0.2 (q_hinge - 0.3) + 0.1 (q_hinge - 0.3)^2 ... in MuJoCo's coordinates relative to qpos0
    poly = next(re.finditer(r'<joint name="mimic" [^>]*polycoef="([^"]+)"', xml)).group(1).split()
    np.testing.assert_allclose([float(x) for x in poly], [0.0, 0.2 + 0.2 * 0.3, 0.1, 0.0, 0.0], atol=1e-15)
    # the round trip's joints with the reversed ones' parent and child swapped (kamino follower <- MJCF parent)
    for name, (parent, child) in {"univ": ("B", "C"), "slide": ("D", "E")}.items():
        j = next(k for k, n in enumerate(m2.joint_names) if n.startswith(name) or n == name)
        assert (m2.body_names[m2.joint_parent[j]], m2.body_names[m2.joint_child[j]]) == (parent, child)


# ---------------------------------------------------------------------------------------------
# simulation
# ---------------------------------------------------------------------------------------------

#: Batches compiled together (one ``kamino.concat`` of each model and its round trip per batch): models, steps,
#: bound on the body CoM positions [m], solver settings (float64, PADMM tolerance 1e-8 unless stated) and backend.
#: Every batch runs on the Warp backend (its CPU kernels are compiled once per CI worker; a new JAX program per batch
#: costs 10-40 s there), with the bounds measured on the reference.
#:
#: The round trip is the same physics written in other constraint rows: load_mjcf completes a hinge axis into a
#: joint frame its own way, places FIXED joints at the child's frame, puts both anchors of a joint at the MJCF
#: joint's position, and a revolute loop closure comes back as two SPHERICAL joints (one redundant row). Masses,
#: forces and the constraint manifold are the same; what is not:
#:
#: * PADMM stops at another iterate within its tolerance. One step of dr_legs differs by 4e-11 m, a floor as the
#:   tolerance goes from 1e-8 to 1e-11 (1e-4: 1.1e-7 m, 1e-6: 1.1e-9 m): solver tolerance, not a model difference.
#:   Over two steps of the falling, servo-stepped robots at tolerance 1e-6 the largest difference is 6e-9 m
#:   (dr_legs; 1.2e-7 m after 3 steps at 1e-8, from velocity differences of the light linkage parts up to
#:   2e-5 m/s): bound 1e-6 m. The animatronic stops at 300 iterations (2.6e-9 m).
#: * kamino's stabilisation acts on the rows' residual functions: post-stabilisation's Gauss-Newton projection
#:   differs by ~1e-9 m per step on the zoo (0 with ``post_stabilisation=0``); mechanisms measured <= 2e-10 m
#:   except chain_of_loops (redundant planar loops); bound 1e-8 m.
#: * The curvature correction depends on how far apart a PRISMATIC/CYLINDRICAL/CARTESIAN joint's anchors sit: the
#:   ``zoo_shifted`` model (translations not zero at body_q0, so its anchors are apart in kamino and coincident after
#:   the round trip) differs by 1.2e-4 m/s after one step, 1e-13 m/s with ``curvature_correction=False``; it is
#:   checked for structure and in MuJoCo, and simulated here only as ``zoo`` (translations at zero).
#:
#: The contact scenes have the same rows both ways (free bodies): they agree exactly.
SIM_BATCHES = {
    "mechanisms": (["pendulum", "double_pendulum", "fourbar", "slider_crank", "chain_of_loops", "zoo"], 5, 1e-8,
                   {"max_iterations": 1000, "stabilisation.projection_shift": 1.5e-8}, "warp"),
    "scenes": (["box_on_plane", "box_stack", "incline", "sphere_drop", "newtons_cradle"], 2, 1e-12,
               {"max_iterations": 1000}, "warp"),
    "robots": (["bdx", "dr_legs", "olaf"], 2, 1e-6, {"max_iterations": 1000, "tolerance": 1e-6}, "warp"),
    "animatronic": (["animatronic"], 2, 1e-6, {"max_iterations": 300}, "warp"),
}


@pytest.mark.parametrize("batch", list(SIM_BATCHES))
def test_round_trip_simulates_alike(batch):
    """From the same initial state under the same (random, constant) ctrl, each model and its round trip move their
    bodies alike (float64, tolerance 1e-8; bounds, settings and backend: SIM_BATCHES). The mechanisms project with a
    shift of sqrt(eps): the default follows PADMM's (1.1e-4), which leaves part of a position error along slow
    directions for later steps, so the MJCF text's rounding of the parameters shows (chain_of_loops: 1.7e-8 m)."""
    names, steps, bound, settings, backend = SIM_BATCHES[batch]
    rng = np.random.default_rng(0)
    models, ctrls, maps = [], [], []
    for name in names:
        m, m2, _ = _round_trip(name)
        lo, hi = np.maximum(m.actuator_ctrl_range[:, 0], -0.2), np.minimum(m.actuator_ctrl_range[:, 1], 0.2)
        ctrl = rng.uniform(lo, hi)
        models += [m, m2]
        ctrls += [ctrl, ctrl]
        maps.append(np.array([m.body_index(n) for n in m2.body_names], dtype=np.int64))
    big = kamino.concat(models)
    controls = kamino.Control.from_ctrl(big, np.tile(np.concatenate(ctrls), (steps, 1)))
    cfg = kamino.SolverConfig(tolerance=1e-8).replace(**settings)
    traj = kamino.rollout(big, kamino.init_state(big), controls, config=cfg, backend=backend)
    q = np.asarray(traj.body_q)
    for k, name in enumerate(names):
        s1, s2 = int(big.world_body_start[2 * k]), int(big.world_body_start[2 * k + 1])
        p1 = q[:, s1 + maps[k], :3]
        p2 = q[:, s2:s2 + len(maps[k]), :3]
        err = float(np.abs(p1 - p2).max())
        moved = float(np.abs(p1[-1] - np.asarray(big.body_q0)[s1 + maps[k], :3]).max())
        assert err <= bound, f"{name}: body positions differ by {err:.3g} m (bound {bound:g})"
        assert moved > 100 * bound or name in ("box_on_plane", "box_stack", "incline"), name  # resting scenes
    assert np.all(np.isfinite(q))


# ---------------------------------------------------------------------------------------------
# MuJoCo
# ---------------------------------------------------------------------------------------------

def _connect_residual(mj, d) -> float:
    out = 0.0
    for i in range(mj.neq):
        if mj.eq_type[i] == mujoco.mjtEq.mjEQ_CONNECT:
            b1, b2 = mj.eq_obj1id[i], mj.eq_obj2id[i]
            p1 = d.xpos[b1] + d.xmat[b1].reshape(3, 3) @ mj.eq_data[i, :3]
            p2 = d.xpos[b2] + d.xmat[b2].reshape(3, 3) @ mj.eq_data[i, 3:6]
            out = max(out, float(np.linalg.norm(p1 - p2)))
    return out


@pytest.mark.parametrize("name", ["fourbar", "slider_crank", "chain_of_loops", "zoo_shifted", *ROBOTS])
def test_mujoco_simulates_the_export(name, tmp_path):
    """Plain MuJoCo loads the file, its mobility (nv - rank of the equality rows) is kamino's (less the couplings),
    the loops are closed at qpos0 and stay closed to 1e-3 m over 100 steps (soft equality constraints, solref 4 ms;
    at most 1.3e-4 m measured over 500 steps), the state stays finite, and floating robots keep standing (base
    within 2 cm)."""
    m = _model(name)
    path = tmp_path / f"{name}.xml"
    save_mjcf(m, path)
    mj = mujoco.MjModel.from_xml_path(str(path))
    mj.opt.jacobian = mujoco.mjtJacobian.mjJAC_DENSE
    d = mujoco.MjData(mj)
    mujoco.mj_forward(mj, d)
    eq_rows = np.asarray(d.efc_type)[:d.nefc] == mujoco.mjtConstraint.mjCNSTR_EQUALITY
    J = np.asarray(d.efc_J).reshape(-1, mj.nv)[:d.nefc][eq_rows]
    rank = 0 if J.size == 0 else int(np.linalg.matrix_rank(J, tol=1e-9 * np.abs(J).max()))
    assert mj.nv - rank == _mobility(m) - m.num_couplings  # MuJoCo's couplings are equality rows too
    assert _connect_residual(mj, d) < 1e-12
    z0 = d.xpos[1, 2]
    worst = 0.0
    for _ in range(100):
        mujoco.mj_step(mj, d)
        worst = max(worst, _connect_residual(mj, d))
    assert np.all(np.isfinite(d.qpos)) and np.all(np.isfinite(d.qvel))
    assert worst < 1e-3, f"{name}: connect residual {worst:.3g} m"
    if name in ("bdx", "dr_legs", "olaf"):
        assert abs(d.xpos[1, 2] - z0) < 0.02


# ---------------------------------------------------------------------------------------------
# what raises, and the API
# ---------------------------------------------------------------------------------------------

def _prismatic_triangle() -> kamino.Model:
    b = kamino.ModelBuilder()
    a = b.add_body(1.0, np.eye(3) * 0.01, pos=(0, 0, 1), name="a")
    c = b.add_body(1.0, np.eye(3) * 0.01, pos=(1, 0, 1), name="c")
    b.add_joint_at(JointType.PRISMATIC, -1, a, anchor=(0, 0, 1), axis=(1, 0, 0), name="p1")
    b.add_joint_at(JointType.PRISMATIC, a, c, anchor=(1, 0, 1), axis=(1, 0, 0), name="p2")
    b.add_joint_at(JointType.PRISMATIC, -1, c, anchor=(1, 0, 1), axis=(1, 0, 0), name="p3")
    return b.finalize()


def _limited_loop() -> kamino.Model:
    b = kamino.ModelBuilder()
    a = b.add_body(1.0, np.eye(3) * 0.01, pos=(0, 0, 1), name="a")
    c = b.add_body(1.0, np.eye(3) * 0.01, pos=(1, 0, 1), name="c")
    for name, (p, q, x) in {"h1": (-1, a, 0.0), "h2": (a, c, 1.0), "h3": (-1, c, 1.0)}.items():
        b.add_joint_at(JointType.REVOLUTE, p, q, anchor=(x, 0, 1), axis=(0, 1, 0), limits=(-1, 1), name=name)
    return b.finalize()


def _moving_plane() -> kamino.Model:
    b = kamino.ModelBuilder()
    a = b.add_body(1.0, np.eye(3) * 0.01, pos=(0, 0, 1), name="a")
    b.add_geom(GeomType.PLANE, a, name="deck")
    return b.finalize()


def _offset_servo(angle: float = 0.5) -> kamino.Model:
    b = kamino.ModelBuilder()
    a = b.add_body(1.0, np.eye(3) * 0.01, pos=(0, 0, 1), name="a")
    _joint(b, JointType.REVOLUTE, -1, a, (0, 0, 1.5), axis=(0, 1, 0), motion=_rot((1, 0, 0), angle), name="servo",
           actuation=Actuation("position", kp=10.0, kd=1.0))
    return b.finalize()


def _ball_limits() -> kamino.Model:
    b = kamino.ModelBuilder()
    a = b.add_body(1.0, np.eye(3) * 0.01, pos=(0, 0, 1), name="a")
    b.add_joint_at(JointType.SPHERICAL, -1, a, anchor=(0, 0, 1.5), limits=(-0.5, 0.5), name="shoulder")
    return b.finalize()


@pytest.mark.parametrize(("build", "match"), [
    (lambda: kamino.replicate(kamino.models.pendulum(), 2), r"exports one world; this model has 2 worlds"),
    (kamino.models.newtons_cradle, r"restitution on geoms 'ball0', 'ball1', 'ball2'"),
    (lambda: kamino.models.box_on_plane(velocity=(1.0, 0.0, 0.0)), r"initial body velocities .* 'box'"),
    (_prismatic_triangle, r"PRISMATIC joint 'p3' closes a kinematic loop"),
    (_limited_loop, r"loop-closing REVOLUTE joint 'h3' has limits"),
    (_moving_plane, r"PLANE geom 'deck' on moving body 'a'"),
    (_offset_servo, r"position actuator on joint 'servo' whose coordinate at the reference pose is 0.5"),
    (_ball_limits, r"SPHERICAL joint 'shoulder': limits"),
])
def test_unrepresentable_features_raise(build, match):
    """What MJCF cannot express raises a ValueError naming the joint, geom, body or actuator and why."""
    with pytest.raises(ValueError, match=match):
        save_mjcf(build())


def test_save_mjcf_api(tmp_path):
    """``kamino.save_mjcf`` writes the file it returns; ``lossy=True`` lists what it dropped; an MJCF model read by
    load_mjcf comes back with the same names (composite joints ``a+b`` are written as their MuJoCo parts)."""
    path = tmp_path / "cradle.xml"
    text = kamino.save_mjcf(kamino.models.newtons_cradle(), path, lossy=True)
    assert path.read_text() == text
    assert "dropped (lossy=True): geom restitution" in text
    from tests.test_mjcf import COMPOSITES, HUMANOID

    for source in (HUMANOID, COMPOSITES):
        m = load_mjcf(source)
        m2 = load_mjcf(save_mjcf(m))
        assert (m2.body_names, m2.joint_names) == (m.body_names, m.joint_names)
        np.testing.assert_allclose(m2.dof_armature, m.dof_armature)
        np.testing.assert_allclose(m2.dof_damping, m.dof_damping)
        np.testing.assert_allclose(m2.dof_lower, m.dof_lower)
