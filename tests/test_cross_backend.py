"""Cross-backend properties: the Warp backend (each of its three solver configurations) reproduces the JAX
reference on random mechanisms and random contact scenes in float32, and a heterogeneous multi-world model
gives each world its standalone result.

The Warp side is stepped eagerly (``kamino.step`` in a loop: the default, non-jitted path), the JAX side
with ``kamino.rollout``. Hypothesis runs derandomised (a fixed sequence of examples: CI is reproducible).
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import HealthCheck, Phase, assume, event, example, given, settings
from hypothesis import strategies as st

import kamino
from kamino import GeomType, JointType
from kamino.hostmath import quat_to_matrix
from kamino.models.shapes import box_inertia
from tests.helpers import (
    JAX,
    VARIANTS,
    WARP_BACKENDS,
    WARP_DENSE_LLT,
    WARP_SPARSE_CR,
    WARP_SPARSE_LLT,
    WARP_VARIANTS,
)

DT = 1.0 / 240.0
STEPS = 100
#: pose agreement after 1 and after 100 steps (issue): metres for positions, radians for orientations
POS_TOL = 1e-4
ROT_TOL = 1e-4
#: after 100 steps, orientations: the residuals let a light row's velocity error reach RESIDUAL_LOOSENING_MAX times
#: the tolerance (1e-5 below) on each backend, and the chaotic mechanisms amplify the difference. Measured worst
#: with the cap at 10: 1.25e-4 rad locally and 3.0e-4 rad on a CI run (light bodies of random mechanisms whose
#: positions agree to 1.4e-5 and 3.3e-5 m), the XLA CPU summation order alone moves it; the cap at 30 and
#: rho_free 1e-4 pass locally
ROT_TOL_LAST = 5e-4
#: the same for the CR configuration on the chaotic random mechanisms. CR's inexact inner solve takes PADMM along
#: another path (21 iterations against 3 on ``CR_STOP_POINT_MECHANISM``), so it stops at another point inside the
#: tolerance ball, and the mechanism amplifies that difference. Measured on that mechanism after 100 steps: 8.1e-4 rad
#: for CR, 2.2e-5 for both LLT configurations; the reference against itself at 10x the tolerance (1e-6): 7e-5; CR
#: against the reference both at 1e-6: 3e-5 (the gap shrinks with the tolerance: a stop point, not another
#: trajectory). Worst seen: 8.1e-4 there, 7.3e-4 on a CI run; the bound leaves 2.5x
ROT_TOL_LAST_CR = 2e-3

#: derandomised (the examples are a function of the test's source: CI runs the same ones every time), no example
#: database (nothing carried over from a local run), no shrinking (each example costs a JAX compile of ~10-20 s;
#: a failure prints its full example, which is reproducible as an ``@example``)
PROPERTY_SETTINGS = settings(max_examples=3, deadline=None, derandomize=True, database=None, print_blob=True,
                             phases=[Phase.explicit, Phase.generate],
                             suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])


#: the Warp configurations compared with the reference; CR with a budget of 30 iterations per PADMM iteration (the
#: default is 100), the least that these comparisons hold at: at 9 its inexact float32 inner solve leaves the first
#: steps of a random seven-hinge mechanism at the iteration cap where the reference converges in 17-18 (measured at
#: tolerance 1e-5; the default 1e-3 is met)
CR30 = dataclasses.replace(WARP_SPARSE_CR, id="warp-sparse-cr30", cr_iterations=30)
COMPARED = (WARP_DENSE_LLT, WARP_SPARSE_LLT, CR30)

# ---------------------------------------------------------------------------------------------
# comparison
# ---------------------------------------------------------------------------------------------

def _quat_angle(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Angle of ``a^-1 b`` for unit quaternions ``(x, y, z, w)`` (sign-insensitive, accurate near zero)."""
    a, b = np.asarray(a, float), np.asarray(b, float)
    av, aw, bv, bw = a[..., :3], a[..., 3:], b[..., :3], b[..., 3:]
    rel_w = np.sum(a * b, axis=-1)  # w of conj(a) * b
    rel_v = aw * bv - bw * av - np.cross(av, bv)
    return 2.0 * np.arctan2(np.linalg.norm(rel_v, axis=-1), np.abs(rel_w))


@dataclasses.dataclass
class Run:
    """What the comparison needs from ``STEPS`` steps: poses after step 1 and step ``STEPS``, and the
    per-step PADMM report ``[STEPS, num_worlds]``."""

    q1: np.ndarray
    qn: np.ndarray
    converged: np.ndarray
    residuals: np.ndarray  # [STEPS, num_worlds, 3]: primal, dual, complementarity
    iterations: np.ndarray


def _info(info: kamino.StepInfo):
    res = np.stack([np.asarray(info.primal_residual, np.float64), np.asarray(info.dual_residual, np.float64),
                    np.asarray(info.complementarity_residual, np.float64)], axis=-1)
    return np.asarray(info.converged), res, np.asarray(info.iterations)


def _run(variant, model: kamino.Model, state: kamino.State, cfg: kamino.SolverConfig, steps: int = STEPS) -> Run:
    if not variant.is_warp:
        traj = variant.rollout(model, state, num_steps=steps, config=cfg)
        conv, res, it = _info(traj.info)
        return Run(np.asarray(traj.body_q[0]), np.asarray(traj.body_q[-1]), conv, res, it)
    infos, q1 = [], None
    for k in range(steps):
        state = variant.step(model, state, config=cfg)  # eager Warp step
        if k == 0:
            q1 = np.asarray(state.body_q)
        infos.append(_info(state.info))
    conv, res, it = (np.stack(x) for x in zip(*infos, strict=True))
    return Run(q1, np.asarray(state.body_q), conv, res, it)


def _settled_worlds(ref: Run, cfg: kamino.SolverConfig) -> np.ndarray:
    """Worlds whose reference PADMM converged on every step within half its iteration cap.

    The property is about those: a world whose solve stalls (an over-constrained set of random loops, whose
    float32 rounding leaves the right-hand side slightly outside the range of J: docs/conventions.md,
    "Stabilisation"; or a residual that creeps to the tolerance near the cap) ends each step on an iterate that
    the order of floating-point operations decides, and its converged flag is decided by rounding too. A step that
    stopped on a numerically null direction (``kamino.jax_ref.solver.solve``, "Null directions": its dual residual
    stays above the tolerance) is such a step too.
    """
    plain = np.all(ref.residuals <= cfg.tolerance, axis=-1)  # not stopped on a null direction (below)
    return (np.all(ref.converged & plain, axis=0)
            & np.all(ref.iterations <= cfg.max_iterations // 2, axis=0))


def _assert_agree(model: kamino.Model, ref: Run, out: Run, cfg: kamino.SolverConfig, settled: np.ndarray,
                  label: str, chaotic: bool) -> None:
    """Poses and converged flags of the ``settled`` worlds; reported residuals everywhere. ``chaotic``: the
    scenes amplify where a solve stops inside the tolerance ball (``ROT_TOL_LAST_CR``)."""
    world = np.asarray(model.body_world)
    body = settled[world]
    last = ROT_TOL_LAST_CR if label == CR30.id and chaotic else ROT_TOL_LAST
    for name, a, b, rot_tol in (("step 1", ref.q1, out.q1, ROT_TOL),
                                (f"step {len(ref.converged)}", ref.qn, out.qn, last)):
        dp = np.where(body, np.abs(a[:, :3].astype(float) - b[:, :3].astype(float)).max(axis=1), 0.0)
        dr = np.where(body, _quat_angle(a[:, 3:], b[:, 3:]), 0.0)
        k = int(np.argmax(np.maximum(dp / POS_TOL, dr / rot_tol)))
        assert dp[k] < POS_TOL and dr[k] < rot_tol, (
            f"{label}, {name}: world {world[k]} body {k}: |dp| {dp[k]:.2e} m, |dR| {dr[k]:.2e} rad")
    for run, who in ((ref, "jax"), (out, label)):  # every world: a reported convergence is a real one
        # (the dual residual of a step that stopped on a null direction stays above the tolerance: settled worlds)
        worst = run.residuals[run.converged][:, [0, 2]].max(initial=0.0)
        assert worst <= cfg.tolerance, f"{who}: a step reported converged with a residual {worst:.2e} > tolerance"
        worst = run.residuals[:, settled][run.converged[:, settled]].max(initial=0.0)
        assert worst <= cfg.tolerance, f"{who}: a settled step reported converged with a residual {worst:.2e}"
    steps, worlds = np.nonzero((ref.converged != out.converged) & settled[None, :])
    where = list(zip(steps[:5].tolist(), worlds[:5].tolist(), strict=True))
    assert steps.size == 0, (f"{label}: converged flags differ at (step, world) {where}; "
                             f"iterations jax {ref.iterations[steps[:5], worlds[:5]].tolist()}, "
                             f"warp {out.iterations[steps[:5], worlds[:5]].tolist()}")


def _compare_backends(model: kamino.Model, state: kamino.State, cfg: kamino.SolverConfig, *, chaotic: bool) -> None:
    ref = _run(JAX, model, state, cfg)
    settled = _settled_worlds(ref, cfg)
    event(f"settled worlds: {int(settled.sum())} of {model.num_worlds}")
    assume(settled.any())
    for v in COMPARED:
        _assert_agree(model, ref, _run(v, model, state, cfg), cfg, settled, v.id, chaotic)


def _batch(builds) -> tuple[kamino.Model, kamino.State]:
    """One multi-world model of the ``(model, twists)`` pairs, its float32 state with those twists.

    The worlds of a model are independent (test_batching.py, and the heterogeneous test below): a batch of
    random examples stepped as one model is a batch of independent examples at the price of one JAX compile
    (~10-20 s each on the CPU, the cost that bounds how many examples CI can afford).
    """
    model = kamino.concat([m for m, _ in builds])
    state = kamino.init_state(model, jnp.float32)
    twists = np.concatenate([t for _, t in builds])
    return model, state.replace(body_u=jnp.asarray(twists, jnp.float32))


#: The library defaults (adaptive penalty) at a tighter tolerance than the default 1e-3, so that agreement tests the
#: physics rather than where two stopping points fall: 1e-5 (CR's float32 inner residual keeps some worlds from
#: reaching 3e-6, measured). An unconverged step's iterate depends on the iteration path, which float32 rounding
#: changes (restart decisions flip), hence the comparison of poses on settled worlds where the example asks for it.
#: The starting penalty 0.01 (default 0.1): from 0.1, one random contact world's first three steps reach the
#: iteration cap on CR (its float32 inner residual) before the adaptive penalty has moved (measured).
#: test_light_slider_with_a_hinged_load_stays_bounded is what a fixed rho = 1 did to such a mechanism.
F32_CFG = kamino.SolverConfig(dt=DT, tolerance=1e-5, penalty=kamino.Penalty(rho=0.01))


# ---------------------------------------------------------------------------------------------
# random mechanisms
# ---------------------------------------------------------------------------------------------

TREE_JOINTS = [JointType.REVOLUTE, JointType.PRISMATIC, JointType.CYLINDRICAL, JointType.UNIVERSAL,
               JointType.SPHERICAL, JointType.CARTESIAN, JointType.FIXED, JointType.FREE]
LOOP_JOINTS = [t for t in TREE_JOINTS if t != JointType.FREE]  # a FREE joint constrains nothing


def _unit(v) -> np.ndarray:
    v = np.asarray(v, float)
    n = np.linalg.norm(v)
    return v / n if n > 1e-3 else np.array([1.0, 0.0, 0.0])


def _perpendicular(a: np.ndarray, hint) -> np.ndarray:
    h = np.asarray(hint, float)
    p = h - np.dot(h, a) * a
    if np.linalg.norm(p) < 1e-3:
        p = np.cross(a, [0.0, 0.0, 1.0] if abs(a[2]) < 0.9 else [1.0, 0.0, 0.0])
    return _unit(p)


coord = st.floats(-1.0, 1.0, allow_nan=False, allow_infinity=False)
vec3 = st.tuples(coord, coord, coord)
quat4 = st.tuples(coord, coord, coord, coord)


@st.composite
def bodies(draw, index: int):
    """A body hanging off an earlier body (or the world) with a joint of a random type."""
    return {
        "parent": draw(st.integers(-1, index - 1)),
        "joint": draw(st.sampled_from(TREE_JOINTS)),
        "mass": 10.0 ** draw(st.floats(-0.5, 0.5)),  # relative to the mechanism's mass scale
        "size": draw(st.tuples(*[st.floats(0.05, 0.3)] * 3)),  # box edges [m]: inertia of that box
        "offset": draw(vec3),  # direction from the parent to the child
        "length": draw(st.floats(0.1, 0.4)),  # distance from parent to child [m]
        "quat": draw(quat4),
        "axis": draw(vec3),
        "axis2": draw(vec3),
        "v": draw(vec3),
        "w": draw(vec3),
    }


@st.composite
def mechanisms(draw):
    n = draw(st.integers(1, 12))
    # masses over three decades: a mechanism's scale is 0.01-10 kg, its bodies within a factor 3 of it
    spec = {"scale": 10.0 ** draw(st.floats(-2.0, 1.0)), "bodies": [draw(bodies(i)) for i in range(n)], "loops": []}
    for _ in range(draw(st.integers(0, 3 if n >= 2 else 0))):
        a, b = draw(st.lists(st.integers(0, n - 1), min_size=2, max_size=2, unique=True))
        spec["loops"].append({"a": a, "b": b, "joint": draw(st.sampled_from(LOOP_JOINTS)),
                              "t": draw(st.floats(0.2, 0.8)), "axis": draw(vec3), "axis2": draw(vec3)})
    return spec


def _add_joint(b: kamino.ModelBuilder, jtype, parent: int, child: int, anchor, axis, axis2, name: str) -> None:
    a1 = _unit(axis)
    kw = {"axis": a1}
    if jtype == JointType.UNIVERSAL:
        kw["axis2"] = _perpendicular(a1, axis2)
    b.add_joint_at(jtype, parent, child, anchor=anchor, name=name, **kw)


def build_mechanism(spec) -> tuple[kamino.Model, np.ndarray]:
    """The mechanism of ``spec`` and its initial twists ``[n, 6]``.

    Twists are small and random (|v| < 0.17 m/s, |w| < 0.35 rad/s per component range below): they are not
    consistent with the joints, so the first step's PADMM removes the inconsistent part as an impulse, the same
    problem for both backends. A tree hangs from world points at 1 m height; a loop joint's anchor is a point
    on the segment between its two bodies' centres of mass at the builder pose, where ``add_joint_at`` makes
    it satisfied.
    """
    b = kamino.ModelBuilder(gravity=(0.0, 0.0, -9.81))
    pos, twists = [], []
    for i, s in enumerate(spec["bodies"]):
        base = np.array([0.5 * i, 0.0, 1.0]) if s["parent"] < 0 else pos[s["parent"]]
        p = base + s["length"] * _unit(s["offset"])
        q = np.asarray(s["quat"], float) + np.array([0.0, 0.0, 0.0, 1.2])  # away from zero; normalised below
        q /= np.linalg.norm(q)
        # inertia of a box of edges ``size`` about its CoM, in the body (CoM) frame
        mass = spec["scale"] * s["mass"]
        b.add_body(mass=mass, inertia=box_inertia(mass, s["size"]), pos=p, quat=q, name=f"b{i}")
        pos.append(p)
        anchor = 0.5 * (base + p)
        if s["joint"] == JointType.FREE and s["parent"] >= 0:
            anchor = p
        _add_joint(b, s["joint"], s["parent"], i, anchor, s["axis"], s["axis2"], f"j{i}")
        twists.append(np.concatenate([0.1 * np.asarray(s["v"]), 0.2 * np.asarray(s["w"])]))
    for k, lp in enumerate(spec["loops"]):
        anchor = (1.0 - lp["t"]) * pos[lp["a"]] + lp["t"] * pos[lp["b"]]
        _add_joint(b, lp["joint"], lp["a"], lp["b"], anchor, lp["axis"], lp["axis2"], f"loop{k}")
    return b.finalize(), np.asarray(twists)


def _body(parent, joint, mass, size, length, offset=(1.0, 0.0, 0.0), axis=(1.0, 0.0, 0.0)):
    zero = (0.0, 0.0, 0.0)
    return {"parent": parent, "joint": joint, "mass": mass, "size": size, "offset": offset, "length": length,
            "quat": (0.0, 0.0, 0.0, 0.0), "axis": axis, "axis2": zero, "v": zero, "w": zero}


#: Found with the first configuration of this test (rho 1, tolerance 1e-4): two hinges whose axes (x) pass through
#: both centres of mass, a 1 kg link carrying a 10 kg one, at rest. Gravity exerts no torque about the axes (a
#: neutral equilibrium), so tolerance-sized differences of the two backends' impulses integrate freely (1.5e-4 m,
#: 4e-4 rad after 100 steps), and PADMM at rho 1 crawls (JAX 200 iterations on step 5, Warp 155: converged flags
#: differed). Kept as a regression case of ``F32_CFG``.
NEUTRAL_DOUBLE_HINGE = {"scale": 10.0 ** 0.5, "loops": [], "bodies": [
    _body(-1, JointType.REVOLUTE, 10.0 ** -0.5, (0.0625, 0.25, 0.125), 0.25),
    _body(0, JointType.REVOLUTE, 10.0 ** 0.5, (0.25, 0.25, 0.25), 0.25)]}


#: Drawn by a CI run (rounded to three digits, which keeps the effect): nine bodies hanging from
#: three world joints, two prismatic loops and a universal loop. Every configuration converges on every step, the
#: reference and the LLT ones in 3 iterations, CR in up to 21, and after 100 steps CR's body 3 is 8.1e-4 rad from the
#: reference where the LLT configurations are within 2.2e-5: the case behind ``ROT_TOL_LAST_CR``.
_BODY_KEYS = ("parent", "joint", "mass", "size", "offset", "length", "quat", "axis", "axis2", "v", "w")
_LOOP_KEYS = ("a", "b", "joint", "t", "axis", "axis2")
CR_STOP_POINT_MECHANISM = {"scale": 0.912, "bodies": [dict(zip(_BODY_KEYS, b, strict=True)) for b in (
    (-1, JointType.SPHERICAL, 1.72, (0.298, 0.232, 0.0805), (0.0, -0.0741, 0.989), 0.32,
     (0.88, 0.555, -0.165, 0.378), (-0.172, 0.273, 0.0), (0.0254, 0.601, 0.125),
     (-6.1e-05, -0.308, 0.65), (0.0, 0.545, 0.985)),
    (-1, JointType.PRISMATIC, 1.44, (0.145, 0.246, 0.3), (0.0, 0.0, 0.655), 0.216,
     (-0.287, -0.144, -0.422, -0.947), (0.0, 0.0, 0.981), (-0.971, 0.0849, 0.0),
     (-0.524, -0.799, 1.0), (0.0, 0.341, 0.554)),
    (1, JointType.REVOLUTE, 0.959, (0.17, 0.104, 0.209), (-0.247, -0.201, 0.0), 0.352,
     (0.997, 0.718, 0.0, 0.264), (0.0, 0.0338, 0.0), (0.046, 0.0, 0.532),
     (-0.673, 0.77, 0.21), (0.009, 0.554, -0.595)),
    (0, JointType.UNIVERSAL, 0.871, (0.23, 0.12, 0.0552), (-0.226, -0.13, 0.709), 0.285,
     (0.0, 0.475, -0.0959, 0.63), (-0.982, -0.611, -0.183), (0.955, 0.0521, -0.922),
     (0.681, -0.592, 0.361), (0.0, 0.0, -0.514)),
    (1, JointType.FIXED, 2.11, (0.12, 0.131, 0.17), (0.662, 0.664, 0.78), 0.153,
     (1.0, 0.283, -0.388, 0.0), (0.666, -0.693, 0.135), (0.0, 0.512, -0.104), (0.0, 0.0, 0.5), (0.496, 0.0, 0.264)),
    (-1, JointType.FIXED, 0.513, (0.14, 0.256, 0.149), (0.0, 0.0, 0.55), 0.127,
     (-0.944, 0.377, 0.307, 0.0), (0.0, 0.104, 0.0), (0.0026, -0.628, 1.0),
     (-0.436, -0.792, 0.31), (0.674, -0.116, 0.0)),
    (5, JointType.REVOLUTE, 1.0, (0.28, 0.138, 0.1), (-0.586, -0.566, 0.344), 0.4,
     (-0.648, 0.006, 0.698, 0.313), (-0.625, 0.0, 0.0147), (-0.742, 0.0, -0.281),
     (0.176, 0.0, -0.138), (-0.73, -0.955, -0.0634)),
    (5, JointType.FIXED, 1.8, (0.247, 0.168, 0.1), (0.022, -1.0, 0.237), 0.333,
     (0.741, -0.0577, -0.23, 0.0), (-0.181, -0.159, 0.986), (0.655, 0.806, -0.0746),
     (0.0, 0.0, 0.0506), (0.0, 0.88, -0.158)),
    (6, JointType.FREE, 1.0, (0.147, 0.07, 0.0643), (1.0, -0.08, -0.362), 0.19,
     (-0.494, 0.834, -0.181, -0.607), (0.0, 0.77, 0.0), (0.631, 0.06, 0.0),
     (0.0, -0.0475, -0.945), (0.0, 0.0, 0.309)),
)], "loops": [dict(zip(_LOOP_KEYS, lp, strict=True)) for lp in (
    (7, 4, JointType.PRISMATIC, 0.333, (0.0, -0.316, 0.0), (0.0, 0.026, -0.317)),
    (7, 8, JointType.PRISMATIC, 0.207, (0.0, 0.757, 0.012), (0.0, 0.0845, 1e-05)),
    (0, 2, JointType.UNIVERSAL, 0.639, (-0.338, 0.306, 0.788), (0.0, 0.322, -0.371)),
)]}


@PROPERTY_SETTINGS
@given(specs=st.lists(mechanisms(), min_size=3, max_size=6))
@example(specs=[NEUTRAL_DOUBLE_HINGE, CR_STOP_POINT_MECHANISM])  # the two regression cases: one batch, one compile
def test_random_mechanisms_agree_across_backends(specs):
    """Float32, ``F32_CFG`` (defaults, rho 0.01), 1 and 100 steps; each example is a batch of up to six random
    mechanisms, one world each.

    Why 100 steps stay comparable at 1e-4: the two backends evaluate the same formulas in a different order
    (float32 rounding ~1e-7 relative) and both stop PADMM at the same tolerance, so one step differs by rounding
    plus a tolerance-sized part of the impulses. Chaos amplifies these by ~exp(lambda t), lambda ~ sqrt(g / L)
    <= 10 1/s for links of 0.1-0.4 m, over t = 100/240 s: ~e^4, far inside 1e-4 from ~1e-7 (measured: <= 3e-5).
    The distributions keep the mechanisms in that regime:
    - twists are small (0.1 m/s, 0.2 rad/s scales): no link whips around (a fast spin raises lambda), and the
      first step's impulse that removes their joint-inconsistent part stays small;
    - the masses span three decades across mechanisms (a scale of 0.01-10 kg each) but within a mechanism stay
      within a factor 10 of each other: a 25 g slider carrying a 1 kg load already keeps PADMM from converging
      at the default rho (test_light_slider_with_a_hinged_load_stays_bounded), and an unconverged solve is where
      rounding decides the result;
    - ``F32_CFG`` (rho 0.01): most worlds converge in a few to a few tens of iterations.
    CR is the exception to 5e-4 rad at step 100: it stops elsewhere inside the same tolerance ball, a difference
    of the tolerance's size that the mechanism amplifies (``ROT_TOL_LAST_CR``, ``CR_STOP_POINT_MECHANISM``).
    What remains outside the regime is a world whose reference PADMM does not settle (``_settled_worlds``: a
    random set of redundant loops at the float32 residual floor, measured 0-1 of 5-6 worlds per batch): its
    poses and flags are not compared (measured there, before the CR fixes of solver.py: LLT within 8e-5 rad,
    CR 9e-4 rad after 100 steps), the example is discarded if no world settles, and the reported residuals are
    checked everywhere.
    """
    _compare_backends(*_batch([build_mechanism(s) for s in specs]), F32_CFG, chaotic=True)


# ---------------------------------------------------------------------------------------------
# random shapes dropped on a plane
# ---------------------------------------------------------------------------------------------

SHAPES = [GeomType.BOX, GeomType.SPHERE, GeomType.CAPSULE]


@st.composite
def drops(draw):
    n = draw(st.integers(1, 6))
    return [{"type": draw(st.sampled_from(SHAPES)), "mass": 10.0 ** draw(st.floats(-2.0, 1.0)),
             "size": draw(st.tuples(*[st.floats(0.03, 0.15)] * 3)), "quat": draw(quat4),
             "height": draw(st.floats(0.0, 0.05)), "v": draw(vec3), "w": draw(vec3),
             "mu": draw(st.floats(0.2, 1.0))} for _ in range(n)]


def _shape_inertia(gtype, mass: float, size) -> np.ndarray:
    r, h = size[0], size[1]
    if gtype == GeomType.SPHERE:
        return 0.4 * mass * r * r * np.eye(3)
    if gtype == GeomType.BOX:
        return box_inertia(mass, tuple(2.0 * np.asarray(size)))
    # capsule along local z: radius r, half-length h (a solid cylinder of length 2h plus two hemispheres)
    v_cyl, v_sph = np.pi * r * r * 2 * h, 4.0 / 3.0 * np.pi * r**3
    m_cyl, m_sph = mass * v_cyl / (v_cyl + v_sph), mass * v_sph / (v_cyl + v_sph)
    axial = 0.5 * m_cyl * r * r + 0.4 * m_sph * r * r
    transverse = m_cyl * (r * r / 4 + (2 * h) ** 2 / 12) + m_sph * (83.0 / 320.0 * r * r + (h + 3 * r / 8) ** 2)
    return np.diag([transverse, transverse, axial])


def _lowest_point(gtype, size, R: np.ndarray) -> float:
    """Depth of the geom's lowest point below its centre at orientation ``R``."""
    if gtype == GeomType.SPHERE:
        return size[0]
    if gtype == GeomType.CAPSULE:
        return size[0] + size[1] * abs(R[2, 2])
    return float(np.abs(R[2, :]) @ np.asarray(size))


def build_drop(spec) -> tuple[kamino.Model, np.ndarray]:
    """Shapes on a 0.5 m grid (they only meet the plane), their lowest point 0-5 cm above it, small twists."""
    b = kamino.ModelBuilder(gravity=(0.0, 0.0, -9.81))
    b.add_geom(GeomType.PLANE, -1, friction=0.5, name="ground")
    twists = []
    for i, s in enumerate(spec):
        gtype = s["type"]
        size = np.asarray(s["size"])
        q = np.asarray(s["quat"], float) + np.array([0.0, 0.0, 0.0, 1.2])
        q /= np.linalg.norm(q)
        R = quat_to_matrix(q)
        z = _lowest_point(gtype, size, R) + s["height"]
        body = b.add_body(mass=s["mass"], inertia=_shape_inertia(gtype, s["mass"], size),
                          pos=(0.5 * (i % 3), 0.5 * (i // 3), z), quat=q, name=f"s{i}")
        b.add_geom(gtype, body, size=size, friction=s["mu"], name=f"g{i}")
        twists.append(np.concatenate([0.1 * np.asarray(s["v"]), 0.5 * np.asarray(s["w"])]))
    return b.finalize(), np.asarray(twists)


@PROPERTY_SETTINGS
@given(specs=st.lists(drops(), min_size=2, max_size=4))
def test_random_shapes_dropped_on_a_plane_agree_across_backends(specs):
    """Float32, ``SolverConfig()`` defaults, 1 and 100 steps (0.42 s: a fall of up to 5 cm, the impact, and
    the shapes settling, sliding or rolling on the plane); each example is a batch of up to four scenes.

    Why 1e-4 holds: no chaos amplifies the differences here (one contact set per shape, friction dissipates
    them), and contact activation is a threshold on the gap that rounding moves by ~1e-8 m, far from the 5 cm
    scale of the drops; what remains is float32 rounding and PADMM's stop at the same tolerance (measured:
    <= 3e-5 m and rad). Poses and converged flags are compared where the reference settles (``_settled_worlds``);
    a world whose contact solve ends steps at the 200-iteration cap ends them on an iterate that rounding decides.
    That was not amplified in the first examples (frictional impacts of tumbling boxes, 3-10 % of the steps at the
    cap), but it was on a CI run. There, a 45 g capsule beside a 14 g sphere, in a world at the
    cap, rolled 1.1e-3 rad away from the reference on the dense LLT after 100 steps. Rolling is neutral: a
    velocity difference integrates, and the angle is the distance over a radius of 3-15 cm. Run again at
    tolerance 1e-6 (fewer steps at the cap), the gap was 5e-5 rad. The reported residuals are checked in every
    world.
    """
    _compare_backends(*_batch([build_drop(s) for s in specs]), kamino.SolverConfig(dt=DT, tolerance=1e-5),
                      chaotic=False)


# ---------------------------------------------------------------------------------------------
# heterogeneous worlds on the Warp backend
# ---------------------------------------------------------------------------------------------

@pytest.mark.parametrize("variant", WARP_BACKENDS)
def test_heterogeneous_worlds_match_standalone_on_warp(variant):
    """Each world of a concatenated model steps exactly as the same model alone.

    The bound is exact equality: a world's rows, Delassus, factorisation and PADMM iterations run in its own
    threads on its own segments, in the same order of floating-point operations whatever the other worlds
    are (padding blocks of a larger world are skipped, not added as zeros), and each world stops its PADMM
    on its own residuals. Anything else (a shared reduction, a padded row entering a sum) would show as a
    rounding-level difference: this test would catch it.
    """
    parts = [kamino.models.pendulum(), kamino.models.fourbar(), kamino.models.chain_of_loops(8),
             kamino.models.box_stack(3)]
    mixed = kamino.concat(parts)
    cfg = variant.config(kamino.SolverConfig(dt=DT, tolerance=1e-4))  # float32: the paper's tolerance
    steps = 50

    def run(model):
        state = kamino.init_state(model, jnp.float32)
        for _ in range(steps):
            state = kamino.step(model, state, config=cfg, backend="warp")
        return state

    out = run(mixed)
    for w, part in enumerate(parts):
        alone = run(part)
        s, c = int(mixed.world_body_start[w]), int(mixed.world_body_count[w])
        np.testing.assert_array_equal(np.asarray(out.body_q[s:s + c]), np.asarray(alone.body_q), err_msg=f"world {w}")
        np.testing.assert_array_equal(np.asarray(out.body_u[s:s + c]), np.asarray(alone.body_u), err_msg=f"world {w}")
        assert int(out.info.iterations[w]) == int(alone.info.iterations[0])
        assert bool(out.info.converged[w]) == bool(alone.info.converged[0])
        assert int(out.info.num_contacts[w]) == int(alone.info.num_contacts[0])


# ---------------------------------------------------------------------------------------------
# per-world parameters on the Warp backend (domain randomization)
# ---------------------------------------------------------------------------------------------

#: the hinge's PD target [rad] and the box's initial sliding speed [m/s] in the scene below
HINGE_TARGET = 0.5
SLIDE_SPEED = 1.5


def _hinge_and_sliding_box() -> kamino.Model:
    """One world: a 0.5 m link on a PD-driven hinge about y (armature, passive damping, an effort limit), hanging
    from (0, 1, 1), and a 0.2 m cube sliding along x on the ground plane (friction 0.5 on both geoms) at
    ``SLIDE_SPEED``."""
    b = kamino.ModelBuilder(gravity=(0.0, 0.0, -9.81))
    link = b.add_body(1.0, box_inertia(1.0, (0.04, 0.04, 0.5)), pos=(0.0, 1.0, 0.75), name="link")
    b.add_joint(JointType.REVOLUTE, -1, link, parent_frame=((0.0, 1.0, 1.0), (0, 0, 0, 1)),
                child_frame=((0.0, 0.0, 0.25), (0, 0, 0, 1)), axis=(0.0, 1.0, 0.0),
                actuation=kamino.Actuation("position", kp=20.0, kd=1.0, effort_limit=5.0), armature=0.01,
                damping=0.1, name="hinge")
    box = b.add_body(1.0, box_inertia(1.0, (0.2, 0.2, 0.2)), pos=(0.0, 0.0, 0.1), velocity=(SLIDE_SPEED, 0.0, 0.0),
                     name="box")
    b.add_geom(GeomType.BOX, box, size=(0.1, 0.1, 0.1), friction=0.5, name="box")
    b.add_geom(GeomType.PLANE, -1, friction=0.5, name="ground")
    return b.finalize()


#: four worlds' parameters: (mass factor, box friction, ground friction, kp, kd, armature, damping, effort limit, g)
_WORLDS = ((1.0, 0.5, 0.5, 20.0, 1.0, 0.01, 0.1, 5.0, 9.81),
           (2.0, 1.0, 0.3, 40.0, 0.5, 0.02, 0.05, 2.0, 9.81),
           (0.5, 0.2, 0.5, 20.0, 2.0, 0.005, 0.2, 4.0, 5.0),
           (1.5, 0.8, 0.4, 10.0, 1.0, 0.01, 0.1, 3.0, 15.0))


def _world_parameters(model: kamino.Model):
    """``_WORLDS`` as a batch of ``kamino.warp_backend.parameters.WorldParameters`` (leading axis: the world) and
    as host Models carrying each world's parameters."""
    from kamino.warp_backend.parameters import WorldParameters

    batch, hosts = [], []
    for mf, mu_box, mu_ground, kp, kd, arm, damp, effort, g in _WORLDS:
        dof = lambda v: np.full(model.num_dofs, v)  # noqa: E731
        p = dict(body_mass=model.body_mass * mf, body_inertia=model.body_inertia * mf,
                 geom_friction=np.array([mu_box, mu_ground]), dof_kp=dof(kp), dof_kd=dof(kd), dof_armature=dof(arm),
                 dof_damping=dof(damp), dof_effort_limit=dof(effort), gravity=np.array([[0.0, 0.0, -g]]))
        batch.append(WorldParameters(**{k: jnp.asarray(v, jnp.float32) for k, v in p.items()}))
        hosts.append(dataclasses.replace(model, **p))
    return jax.tree.map(lambda *x: jnp.stack(x), *batch), hosts


def test_per_world_parameters_on_warp():
    """A ``jax.vmap`` of the Warp step over four parameter sets (one FFI call, each environment a world with its
    own masses, inertias, friction, gains, armature, damping, effort limit and gravity: what an environment's
    domain randomization passes) steps a world as the eager Warp step of a host Model carrying that world's
    parameters, and the parameters have their physical effect:

    - worlds 1 and 2 (every parameter off nominal) follow their host Model's trajectory, to 1e-5 over 30 steps
      (float32: the batched call inverts masses and inertias on the device in float32, the host Model in float64;
      3.3e-6 m measured, the scene is not chaotic);
    - the effort-limited PD reports its own world's limit on the first step (the target is beyond every limit);
    - the box slides ``v^2 / (2 mu g)`` with ``mu`` the larger of its pair's (docs/conventions.md "Contacts") and the
      world's gravity, whatever its mass (Coulomb friction), to 0.1 % (the implicit step stops the cube within one
      step of 1/240 s; 0.015 % measured);
    - a nominal call after the randomized one still steps the nominal model (the parameters live in the stepper
      that reads them, not in the model arrays other steppers share).
    """
    model = _hinge_and_sliding_box()
    cfg = kamino.SolverConfig(tolerance=1e-5)
    sim = kamino.Simulator(model, cfg, backend="warp")
    params, hosts = _world_parameters(model)
    B = len(_WORLDS)
    control = kamino.Control(position_target=jnp.full(model.num_dofs, HINGE_TARGET, jnp.float32))
    start = kamino.state.bind(kamino.init_state(model, jnp.float32), None)
    batch = jax.tree.map(lambda x: jnp.broadcast_to(x, (B, *x.shape)), start)
    step = jax.jit(jax.vmap(lambda p, s: sim.engine.step(s, control, p)))
    nominal = jax.jit(jax.vmap(lambda s: sim.engine.step(s, control)))

    states = step(params, batch)
    limits = np.array([w[7] for w in _WORLDS])
    np.testing.assert_allclose(np.abs(np.asarray(states.actuator_force)[:, 0]), limits, rtol=1e-5)
    for _ in range(29):
        states = step(params, states)
    for w in (1, 2):  # every parameter off nominal in both (each world's limit and slide are checked too)
        host = hosts[w]
        alone = kamino.init_state(host, jnp.float32)
        for _ in range(30):
            alone = kamino.step(host, alone, control, config=cfg, backend="warp")
        np.testing.assert_allclose(np.asarray(states.body_q[w]), np.asarray(alone.body_q), atol=1e-5,
                                   err_msg=f"world {w}")
    for _ in range(150):  # 0.75 s in all: every box has stopped (the longest slide takes 1.5 / (0.5 * 5) = 0.6 s)
        states = step(params, states)
    moved = np.asarray(states.body_q)[:, 1, 0]
    mu = np.array([max(w[1], w[2]) for w in _WORLDS])
    g = np.array([w[8] for w in _WORLDS])
    np.testing.assert_allclose(moved, SLIDE_SPEED ** 2 / (2.0 * mu * g), rtol=1e-3)
    assert np.abs(np.asarray(states.body_u)[:, 1, :3]).max() < 1e-3  # at rest

    ref = kamino.init_state(model, jnp.float32)
    for _ in range(30):
        ref = kamino.step(model, ref, control, config=cfg, backend="warp")
    again = batch
    for _ in range(30):
        again = nominal(again)
    np.testing.assert_allclose(np.asarray(again.body_q[0]), np.asarray(ref.body_q), atol=1e-6)


# ---------------------------------------------------------------------------------------------
# regressions found on the way
# ---------------------------------------------------------------------------------------------

def _slider_with_a_hinged_load() -> kamino.Model:
    """A 25 g slider on an inclined prismatic rail carrying a 1 kg box on a vertical hinge 0.18 m away, the
    box moving at 4 cm/s: the first version of ``mechanisms()`` (masses drawn independently over 0.01-10 kg)
    produced it, shrunk to two bodies with rounded numbers."""
    b = kamino.ModelBuilder()
    slider = b.add_body(0.025, box_inertia(0.025, (0.1, 0.1, 0.1)), pos=(0.22, -0.17, 1.18))
    load = b.add_body(1.0, box_inertia(1.0, (0.11, 0.24, 0.26)), pos=(0.22, -0.54, 1.18), velocity=(0.0, 0.003, 0.04))
    b.add_joint_at(JointType.PRISMATIC, -1, slider, anchor=(0.11, -0.085, 1.09), axis=(0.63, 0.0, -0.77))
    b.add_joint_at(JointType.REVOLUTE, slider, load, anchor=(0.22, -0.355, 1.18), axis=(0.0, 0.0, 1.0))
    return b.finalize()


@pytest.mark.parametrize("variant", [pytest.param(v, id=v.id) for v in VARIANTS])
def test_light_slider_with_a_hinged_load_stays_bounded(variant):
    """The 40:1 mass ratio across the hinge at the defaults (float64, 100 steps): formerly (rho=1, baumgarte=1)
    PADMM did not converge and the mechanism blew up within 0.4 s; with ``rho_free = 1e-3`` every step converged
    but the joints opened by 2.7e-5 m (the proximal shift left velocity errors of 6.3e-4 m per step before
    post-stabilisation). At ``rho_free = 1e-4`` (the default) they stay within 1.8e-6 m
    (docs/conventions.md, 'Penalty'): the bound 1e-5 m is kamino's loop-closure target."""
    model = _slider_with_a_hinged_load()
    state = kamino.init_state(model)  # float64
    traj = variant.rollout(model, state, num_steps=100, config=kamino.SolverConfig())
    q = np.asarray(traj.body_q)
    # 0.42 s of sliding down the rail under gravity moves the bodies by less than 1 m
    assert np.all(np.isfinite(q)) and np.abs(q[:, :, :3] - model.body_q0[None, :, :3]).max() < 1.0
    assert bool(np.all(np.asarray(traj.info.converged)))
    viol = jax.vmap(lambda qq: kamino.metrics(model, state.replace(body_q=qq))["constraint_violation"])(traj.body_q)
    assert float(np.max(viol)) < 1e-5


def test_jitted_warp_rollout_is_bitwise_the_eager_one():
    """The Warp rollout inside ``jax.jit`` (a user's jitted loop; brax's training jits the step the same way): the
    same kernels as the eager rollout that the physics tests run (tests/helpers.py), through Warp's FFI. Bitwise
    equal on loops, contacts, limits and controls, on each Warp configuration."""
    model = kamino.concat([kamino.models.fourbar(actuated=True, kp=500.0, kd=10.0), kamino.models.box_stack(2)])
    state = kamino.init_state(model, jnp.float32)
    steps = 30
    targets = np.zeros((steps, model.num_dofs), np.float32)
    targets[:, 0] = 0.3 * np.sin(np.linspace(0.0, np.pi, steps))
    controls = kamino.Control(position_target=targets)
    for v in WARP_VARIANTS:
        cfg = v.config(kamino.SolverConfig(tolerance=1e-4))
        eager = kamino.rollout(model, state, controls, config=cfg, backend="warp")
        jitted = jax.jit(lambda s, c, cfg=cfg: kamino.rollout(model, s, c, config=cfg, backend="warp"))(state, controls)
        for name, a, b in zip(("body_q", "body_u", "constraint_force", "contacts.force", "info.iterations"),
                              (eager.body_q, eager.body_u, eager.constraint_force, eager.contacts.force,
                               eager.info.iterations),
                              (jitted.body_q, jitted.body_u, jitted.constraint_force, jitted.contacts.force,
                               jitted.info.iterations), strict=True):
            np.testing.assert_array_equal(np.asarray(a), np.asarray(b), err_msg=f"{v.id}: {name}")
        assert int(np.asarray(eager.info.num_contacts)[-1, 1]) > 0


# Regression: the eager Warp rollout used to return jnp.stack of one State per step, an XLA concatenate with
# num_steps operands compiled for every new length and leaf shape in time superlinear in num_steps (0.25 s per
# leaf for 100 steps, 3.4 s for 1000, 106 s for 10000; ~25 leaves). It now writes preallocated buffers
# (warp_backend/backend.py, _Trajectory).
def test_eager_warp_rollout_length_compiles_nothing():
    model = kamino.models.pendulum()
    state = kamino.init_state(model)
    cfg = WARP_SPARSE_LLT.config()
    kamino.rollout(model, state, num_steps=3, config=cfg, backend="warp")  # the stepper, kernels, eager ops
    compiles = []

    def listener(event, duration, **_):
        if event == "/jax/core/compile/backend_compile_duration":
            compiles.append(duration)

    jax.monitoring.register_event_duration_secs_listener(listener)
    try:
        kamino.rollout(model, state, num_steps=7, config=cfg, backend="warp")  # a length not seen before
    finally:
        jax.monitoring.unregister_event_duration_listener(listener)
    # nothing in a rollout depends on its length but the stacking of the trajectory
    assert not compiles, f"{len(compiles)} XLA compilations ({sum(compiles):.2f} s) for a new rollout length"
