"""Four-bar coupler-curve synthesis by gradients through the simulator, many candidate designs at once.

    python examples/design_fourbar.py --candidates 8 --steps 30              # a minute to compile, ~1 s a step (CPU)
    python examples/design_fourbar.py --candidates 4096 --steps 200 --device gpu --remat

A design is six numbers ``p = (ground, crank, coupler, rocker, u, w)`` [m]: the four link lengths of
``kamino.models.fourbar`` (ground pivots ``A`` fixed, ``D = A + ground e_x``) and the coupler point ``P = B + u e +
w n`` (``e`` the unit vector from the crank pin ``B`` to the coupler-rocker pin ``C``, ``n`` its normal in the xz
plane). Each candidate design is one world of ``kamino.replicate(fourbar, N)``; its lengths enter the JAX reference's
padded model (``Simulator.parameters``: joint anchors, link masses and inertias) and its initial poses (the loop
assembled at the crank's start angle) as traced values, so ``jax.grad`` reaches them through every step.

The crank's motor turns it through 1.1 revolutions at a constant rate (the tenth more, so that the servo's lag leaves
no gap in the path): the actuator is a velocity servo (``kp = 0``, ``kd`` = :data:`KD`) whose velocity target is the
rate plus :data:`POSITION_GAIN` times the wrapped angle error, a PD on the crank angle that does not jump where the
hinge angle passes pi (the actuator's own position error is not wrapped). The coupler point's simulated path ``P_i``
(one point per step) is compared with the target curve (a closed polyline through ``T_j``) by the symmetric chamfer
distance

    J(p) = 1/2 [ mean_i d(P_i, T)^2 + mean_j d(T_j, P)^2 ]          [m^2]

with ``d(x, T)`` the distance of ``x`` from the polyline ``T`` (:func:`squared_distances`): zero when the path and
the curve coincide as sets, whatever the timing along them; ``1000 sqrt(J)`` is an rms distance in mm. Added to it is
a penalty that keeps the crank able to turn a full revolution (Grashof's condition with a margin:
:func:`rotatability`, :func:`penalty`). The target is the coupler curve of Hoeken's straight-line linkage (ground 2,
crank 1, coupler and rocker 2.5, the point on the coupler extended to 5 from the crank pin; here times 0.1 m), a
D-shaped curve with a nearly straight side: a four-bar traces it exactly, so the best objective is known to be near
zero (Hoeken's own design, simulated, scores 0.06 mm: the simulator's path against the closed-form curve).

Adam (optax) descends the gradient of every candidate at once (the worlds are independent, so the gradient of the sum
over worlds is each world's own gradient); a step that would leave the feasible set is not taken for that candidate.
The script prints the objective of the best and the median candidate before and after, and the wall times. Measured
on the 2-core CPU machine (float32, 16 candidates, 150 steps at the default step size of 1 cm): best 54.7 -> 0.45 mm,
median 140.5 -> 10.0 mm, in 286 s (57 s of them tracing and compiling the first gradient); the best design, ground
0.1996, crank 0.1000, coupler 0.2424, rocker 0.2381, u 0.5001, w 0.0192 m, is next to Hoeken's. At 5 mm: best 2.1 mm,
median 15.6 mm. On an NVIDIA H200 (jax 0.11.2, float32, ``--candidates 4096 --steps 20 --remat``): best
12.8 -> 2.5 mm, median 191.7 -> 55.8 mm, in 96 s (the first evaluation, which compiles, 45 s; 2.4 s each after it,
1.85e5 world-steps/s forward and reverse).
The gradient goes through a fixed number of solver iterations per step (:func:`design_config`, the unrolled gradient,
cheap at ten iterations), and :class:`Problem` takes the configuration as its one ``config`` argument. The reverse pass
stores every iteration of every step (64 candidates: 2.0 GiB of temporaries; 4096 do not fit an H200's 141 GB);
``--remat`` (``Problem.remat``) recomputes each step from the state stored before it instead (``jax.checkpoint``):
64 candidates take 63 MiB, for about a fifth more time.
"""

from __future__ import annotations

import argparse
import dataclasses
import time

import jax
import jax.numpy as jnp
import numpy as np

import kamino
from kamino.spatial import rotate

#: the names of a design's six numbers [m]
PARAMETERS = ("ground", "crank", "coupler", "rocker", "u", "w")
#: Hoeken's linkage times 0.1 m: the design whose coupler curve is the target
HOEKEN = np.array([0.2, 0.1, 0.25, 0.25, 0.5, 0.0])
#: the crank's start angle [rad] from the ground line (every design starts there)
CRANK_ANGLE = -1.2
#: the ground pivot A's height [m]
HEIGHT = 1.0
#: the links' mass per length [kg/m] and capsule radius [m] (kamino.models.fourbar's defaults)
LINEAR_DENSITY, RADIUS = 2.0, 0.01
#: the crank motor: the actuator's velocity gain [N m s/rad] and the outer loop's position gain [1/s] (module
#: docstring)
KD, POSITION_GAIN = 5.0, 40.0
#: the smallest link [m], the Grashof margin [m] (see :func:`rotatability`)
MIN_LENGTH, MARGIN = 0.03, 0.02
#: the penalty's weight (dimensionless): a margin violated by 1 cm adds 1e-4 m^2 to J, as much as 1 cm rms of path error
PENALTY = 1.0
#: the ranges random candidates are drawn from [m]
LOWER = np.array([0.12, 0.05, 0.12, 0.12, 0.0, -0.15])
UPPER = np.array([0.32, 0.14, 0.40, 0.40, 0.6, 0.15])


def design_config(dt: float = 0.01, max_iterations: int = 10) -> kamino.SolverConfig:
    """The solver configuration gradients go through: a fixed number of iterations per step, without the curvature
    refinement (its second solve would double the iterations the reverse pass stores), as notebook 04 uses."""
    return kamino.SolverConfig(dt=dt, fixed_iterations=True, max_iterations=max_iterations).replace(
        **{"stabilisation.curvature_refinement": False})


def template(num: int) -> kamino.Model:
    """``num`` worlds of the actuated four-bar (its own lengths are replaced per world by the design's), the crank's
    actuator a velocity servo (``kp = 0``: the position loop is :class:`Problem`'s, on the wrapped angle)."""
    return kamino.replicate(kamino.models.fourbar(crank_angle=CRANK_ANGLE, height=HEIGHT, actuated=True, kp=0.0, kd=KD,
                                                  linear_density=LINEAR_DENSITY, radius=RADIUS), num)


def _circle_intersection(c0, r0, c1, r1):
    """The intersection with the larger z of the circles ``(c0, r0)`` and ``(c1, r1)`` in the xz plane (batched over
    leading axes; NumPy or JAX arrays); the assembly the four-bar's ``coupler_above=True`` chooses."""
    xp = jnp if isinstance(c0, jax.Array) or isinstance(r0, jax.Array) else np
    d_vec = c1 - c0
    d = xp.linalg.norm(d_vec, axis=-1)
    e = d_vec / d[..., None]
    a = (r0 * r0 - r1 * r1 + d * d) / (2 * d)
    h = xp.sqrt(xp.maximum(r0 * r0 - a * a, 1e-12))
    perp = xp.stack([-e[..., 2], xp.zeros_like(d), e[..., 0]], -1)
    p1 = c0 + a[..., None] * e + h[..., None] * perp
    p2 = c0 + a[..., None] * e - h[..., None] * perp
    return xp.where((p1[..., 2] >= p2[..., 2])[..., None], p1, p2)


def joint_points(p, crank_angle):
    """``A, B, C, D`` ``[..., 3]`` of designs ``p`` ``[..., 6]`` at ``crank_angle`` [rad] (broadcast)."""
    xp = jnp if isinstance(p, jax.Array) or isinstance(crank_angle, jax.Array) else np
    g, c, l, r = p[..., 0], p[..., 1], p[..., 2], p[..., 3]
    zero = xp.zeros_like(g * crank_angle)
    A = xp.stack([zero, zero, zero + HEIGHT], -1)
    D = A + xp.stack([g + zero, zero, zero], -1)
    B = A + (c + zero)[..., None] * xp.stack([xp.cos(crank_angle) + zero, zero, xp.sin(crank_angle) + zero], -1)
    C = _circle_intersection(B, l + zero, D, r + zero)
    return A, B, C, D


def coupler_point(p, B, C):
    """``P = B + u e + w n`` (module docstring) ``[..., 3]``."""
    xp = jnp if isinstance(p, jax.Array) else np
    e = (C - B) / xp.linalg.norm(C - B, axis=-1, keepdims=True)
    n = xp.stack([-e[..., 2], xp.zeros_like(e[..., 0]), e[..., 0]], -1)  # the link frame's z axis (e x y)
    return B + p[..., 4:5] * e + p[..., 5:6] * n


def target_curve(num_points: int = 128, design=HOEKEN) -> np.ndarray:
    """``[num_points, 3]`` the coupler curve of ``design`` (default Hoeken's linkage), by closed-form assembly at
    evenly spaced crank angles."""
    angles = CRANK_ANGLE + 2 * np.pi * np.arange(num_points) / num_points
    _, B, C, _ = joint_points(np.asarray(design, float), angles)
    return coupler_point(np.broadcast_to(np.asarray(design, float), (num_points, 6)), B, C)


def rotatability(p):
    """``[...]`` the margins [m] by which the crank of ``p`` can turn a full revolution (all must be >= 0): the dyad
    (coupler, rocker) spans every crank-pin-to-rocker-pivot distance ``|B - D|`` in ``[|g - c|, g + c]`` when
    ``g + c <= l + r`` and ``|g - c| >= |l - r|``; each with :data:`MARGIN` (the transmission angle stays away from
    0 and pi), and every link at least :data:`MIN_LENGTH`. Returns the smallest margin."""
    xp = jnp if isinstance(p, jax.Array) else np
    g, c, l, r = p[..., 0], p[..., 1], p[..., 2], p[..., 3]
    margins = xp.stack([l + r - g - c - MARGIN, xp.abs(g - c) - xp.abs(l - r) - MARGIN,
                        g - c - MARGIN,  # with the two above, the crank is the shortest link: a crank-rocker
                        xp.min(p[..., :4], axis=-1) - MIN_LENGTH], -1)
    return xp.min(margins, axis=-1)


def penalty(p):
    """``[...]`` :data:`PENALTY` times the squared violations of the margins of :func:`rotatability`."""
    g, c, l, r = p[..., 0], p[..., 1], p[..., 2], p[..., 3]
    margins = jnp.stack([l + r - g - c - MARGIN, jnp.abs(g - c) - jnp.abs(l - r) - MARGIN, g - c - MARGIN,
                         *(p[..., k] - MIN_LENGTH for k in range(4))], -1)
    return PENALTY * jnp.sum(jnp.minimum(margins, 0.0) ** 2, axis=-1)


def random_designs(num: int, seed: int = 0) -> np.ndarray:
    """``[num, 6]`` designs drawn uniformly from ``[LOWER, UPPER]`` whose crank turns with a margin (rejection)."""
    rng = np.random.default_rng(seed)
    out = np.zeros((0, 6))
    while len(out) < num:
        draw = rng.uniform(LOWER, UPPER, size=(4 * num, 6))
        out = np.concatenate([out, draw[rotatability(draw) >= MARGIN]])
    return out[:num]


def _capsule_inertia(mass, length):
    """``[..., 3, 3]`` a capsule's inertia about its CoM, axis along local x (``kamino.models.shapes.capsule_inertia``
    in JAX: the cylinder and the two hemispheres share the mass by volume)."""
    r, h = RADIUS, length
    v_cyl, v_sph = jnp.pi * r * r * h, 4.0 / 3.0 * jnp.pi * r**3
    m_cyl, m_sph = mass * v_cyl / (v_cyl + v_sph), mass * v_sph / (v_cyl + v_sph)
    axial = 0.5 * m_cyl * r * r + 0.4 * m_sph * r * r
    transverse = m_cyl * (r * r / 4 + h * h / 12) + m_sph * (83.0 / 320.0 * r * r + (h / 2 + 3 * r / 8) ** 2)
    return jnp.stack([axial, transverse, transverse], -1)[..., None] * jnp.eye(3)


def _link_pose(p0, p1):
    """``[..., 7]`` the pose of a link from ``p0`` to ``p1`` in the xz plane as ``kamino.models.shapes.add_link``
    places it: CoM at the midpoint, local x along the link, local y the world's y (a rotation by ``phi`` about y)."""
    d = p1 - p0
    phi = jnp.arctan2(-d[..., 2], d[..., 0])
    zero = jnp.zeros_like(phi)
    quat = jnp.stack([zero, jnp.sin(phi / 2), zero, jnp.cos(phi / 2)], -1)
    return jnp.concatenate([0.5 * (p0 + p1), quat], -1)


def design_parameters(parameters, p):
    """The padded model ``parameters`` (``Simulator.parameters``: ``(PaddedModel, tables)``) with each world's
    link lengths from ``p`` ``[W, 6]``: the joints' anchors in the bodies' frames, the links' masses and inertias and
    the health check's lever-arm sum. The joint frames' rotations stay the template's: every hinge's axis is the
    world's y, so a passive hinge's rows hold at any planar assembly, and the crank hinge's zero is its start angle,
    the same for every design."""
    pm, tables = parameters
    dtype = pm.anchor_B.dtype
    p = jnp.asarray(p, dtype)
    g, c, l, r = p[:, 0], p[:, 1], p[:, 2], p[:, 3]
    zero = jnp.zeros_like(g)

    def x(v):  # a point on a link's own x axis
        return jnp.stack([v, zero, zero], -1)

    # joints: fix (world -> ground), ground_crank (A), crank_coupler (B), coupler_rocker (C), rocker_ground (D); a
    # link from p0 to p1 has p0 at -L/2 and p1 at +L/2 on its x axis (ground A->D, crank A->B, coupler B->C,
    # rocker D->C)
    anchor_B = jnp.stack([x(g / 2) + jnp.asarray([0.0, 0.0, HEIGHT], dtype), x(-g / 2), x(c / 2), x(l / 2),
                          x(-r / 2)], 1)
    anchor_F = jnp.stack([x(zero), x(-c / 2), x(-l / 2), x(r / 2), x(g / 2)], 1)
    lengths = jnp.stack([g, c, l, r], 1)
    mass = LINEAR_DENSITY * lengths
    world_parent = jnp.asarray([True, False, False, False, False])
    reach = jnp.sum(jnp.linalg.norm(anchor_F, axis=-1)
                    + jnp.where(world_parent, 0.0, jnp.linalg.norm(anchor_B, axis=-1)), axis=1)
    pm = dataclasses.replace(pm, anchor_B=anchor_B, anchor_F=anchor_F, mass=mass,
                             inertia=_capsule_inertia(mass, lengths), reach=jax.lax.stop_gradient(reach))
    return pm, tables


def initial_poses(p):
    """``[W * 4, 7]`` the bodies' poses (ground, crank, coupler, rocker per world) of designs ``p`` ``[W, 6]``
    assembled at :data:`CRANK_ANGLE`."""
    A, B, C, D = joint_points(p, jnp.asarray(CRANK_ANGLE, p.dtype))
    poses = jnp.stack([_link_pose(A, D), _link_pose(A, B), _link_pose(B, C), _link_pose(D, C)], 1)
    return poses.reshape(-1, 7)


def crank_schedule(num_steps: int, turns: float = 1.1) -> np.ndarray:
    """``[num_steps]`` the crank's target angle [rad] after each step: ``turns`` revolutions at a constant rate
    (one revolution in ``num_steps / turns`` steps)."""
    return 2 * np.pi * turns * np.arange(1, num_steps + 1) / num_steps


def squared_distances(points, polyline, closed: bool):
    """``[n]`` the squared distance [m^2] of each of ``points`` ``[n, 3]`` from the polyline through ``polyline``
    ``[m, 3]`` (``closed``: with the segment from the last point back to the first): the smallest over its segments
    of ``|x - a - t (b - a)|^2``, ``t = clip((x - a).(b - a) / |b - a|^2, 0, 1)``."""
    a = polyline
    b = jnp.roll(polyline, -1, axis=0) if closed else polyline[1:]
    a = a if closed else a[:-1]
    ab = b - a
    rel = points[:, None, :] - a[None]
    t = jnp.clip(jnp.sum(rel * ab, -1) / jnp.maximum(jnp.sum(ab * ab, -1), 1e-30), 0.0, 1.0)
    return jnp.min(jnp.sum((rel - t[..., None] * ab) ** 2, -1), axis=1)


@dataclasses.dataclass
class Problem:
    """What the objective needs, built once for ``num`` candidates: the template model, its JAX simulator, the
    target curve, the crank's schedule."""

    num: int
    config: kamino.SolverConfig
    num_steps: int = 110
    target: np.ndarray = dataclasses.field(default_factory=target_curve)
    #: recompute each step in the reverse pass (``jax.checkpoint``) instead of storing its solver iterations
    remat: bool = False

    def __post_init__(self):
        self.model = template(self.num)
        self.sim = kamino.Simulator(self.model, self.config, backend="jax")
        self.schedule = crank_schedule(self.num_steps)
        self.rate = float(self.schedule[0] / self.config.dt)
        self.coupler = self.model.body_names.index("coupler")

    def paths(self, p, dtype=None) -> tuple[jax.Array, jax.Array]:
        """The coupler point's simulated path ``[W, num_steps, 3]`` of designs ``p`` ``[W, 6]`` (after each step) and
        whether each world failed the simulator's health checks during the run ``[W]`` (``state.info.failed``)."""
        dtype = dtype or jnp.asarray(p).dtype
        p = jnp.asarray(p, dtype)
        W, nb = self.num, self.model.num_bodies // self.num
        params = design_parameters(self.sim.parameters(dtype), p)
        state = kamino.init_state(self.model, dtype=dtype).replace(body_q=initial_poses(p))
        crank = nb * np.arange(W) + self.model.body_names.index("crank")
        drive = np.asarray(self.model.actuator_dof)  # the crank hinge's DoF in each world
        phi0 = -CRANK_ANGLE  # the crank's start rotation about +y (its x axis at CRANK_ANGLE from the ground line)
        offset = jnp.stack([p[:, 4] - p[:, 2] / 2, jnp.zeros(W, dtype), p[:, 5]], -1)  # P in the coupler's frame
        co = nb * np.arange(W) + self.coupler

        def one_step(carry, target):
            state, params = carry
            # the crank's angle (its rotation about +y from the start) and the position loop on the wrapped error:
            # the actuator's own position error (target - hinge angle) is not wrapped, and the hinge angle jumps by
            # 2 pi where it passes pi, so the actuator serves the velocity and the position loop is here
            q = state.body_q[crank]
            error = jnp.mod(target - (2 * jnp.arctan2(q[:, 4], q[:, 6]) - phi0) + jnp.pi, 2 * jnp.pi) - jnp.pi
            target_rate = jnp.zeros(self.model.num_dofs, dtype).at[drive].set(self.rate + POSITION_GAIN * error)
            control = kamino.Control(velocity_target=target_rate)  # [num_dofs]: step_with does not check shapes
            state = self.sim.step_with(params, state, control)
            q_co = state.body_q[co]
            point = q_co[:, :3] + rotate(q_co[:, 3:], offset)
            return (state, params), (point, state.info.failed)

        schedule = jnp.asarray(self.schedule, dtype)
        step = jax.checkpoint(one_step) if self.remat else one_step
        (_, _), (points, failed) = jax.lax.scan(step, (state, params), schedule)
        return jnp.swapaxes(points, 0, 1), jnp.any(failed, axis=0)

    def objective(self, p, dtype=None) -> tuple[jax.Array, dict]:
        """``[W]`` the chamfer distance ``J`` (module docstring) plus :func:`penalty`, and the parts."""
        path, failed = self.paths(p, dtype)
        target = jnp.asarray(self.target, path.dtype)
        to_curve = jax.vmap(lambda x: squared_distances(x, target, closed=True))(path)  # [W, steps]
        to_path = jax.vmap(lambda x: squared_distances(target, x, closed=False))(path)  # [W, M]
        chamfer = 0.5 * (jnp.mean(to_curve, axis=1) + jnp.mean(to_path, axis=1))
        return chamfer + penalty(jnp.asarray(p, path.dtype)), {"chamfer": chamfer, "failed": failed, "path": path}


def optimise(problem: Problem, p0, steps: int, learning_rate: float = 1e-2, dtype=None, log=None) -> dict:
    """Adam (optax) on every candidate at once, ``steps`` gradient steps from ``p0`` ``[W, 6]``, the step size
    decaying from ``learning_rate`` [m] to a tenth of it (a cosine). A candidate's step is not taken where its
    gradient or objective is not finite, its world failed the simulator's health check, or the new design would break
    :func:`rotatability` (its crank could no longer turn). Each candidate keeps the best design it visited (the
    objective is evaluated at the design before every step, and once after the last).

    Returns a dict: ``p0``, ``before`` (``[W]`` objectives at ``p0``), ``p`` and ``after`` (each candidate's best
    design and its objective), ``history`` (per evaluation: objectives, chamfer parts, which candidates stepped) and
    ``step_times`` [s] (per evaluation; the first one traces and compiles), and ``gradient`` (``[W, 6]`` the
    objective's gradient at ``p0``)."""
    import optax

    dtype = dtype or jnp.zeros(0).dtype
    opt = optax.adam(optax.cosine_decay_schedule(learning_rate, max(steps, 1), alpha=0.1))

    def total(p):
        value, parts = problem.objective(p, dtype)
        return jnp.sum(value), (value, parts["chamfer"], parts["failed"])

    grad_fn = jax.grad(total, has_aux=True)

    @jax.jit
    def update(p, opt_state, best_p, best):
        g, (value, chamfer, failed) = grad_fn(p)
        ok = jnp.all(jnp.isfinite(g), axis=1) & jnp.isfinite(value) & ~failed
        better = ok & (value < best)
        best_p, best = jnp.where(better[:, None], p, best_p), jnp.where(better, value, best)
        g = jnp.where(ok[:, None], g, 0.0)
        step, new_state = opt.update(g, opt_state, p)
        trial = optax.apply_updates(p, step)
        keep = ok & (rotatability(trial) >= 0.0)
        return jnp.where(keep[:, None], trial, p), new_state, best_p, best, value, chamfer, ok, g

    p = jnp.asarray(p0, dtype)
    opt_state = opt.init(p)
    best_p, best = p, jnp.full(p.shape[0], jnp.inf, dtype)
    history, times, gradient = [], [], None
    for k in range(steps + 1):  # the last evaluation scores the last design; its step is not taken
        t0 = time.perf_counter()
        p_new, opt_state, best_p, best, value, chamfer, ok, g = update(p, opt_state, best_p, best)
        gradient = np.asarray(g) if gradient is None else gradient
        history.append((np.asarray(value), np.asarray(chamfer), np.asarray(ok)))  # blocks: the step is done
        times.append(time.perf_counter() - t0)
        if log is not None:
            log(k, history[-1])
        p = p_new
    return {"p0": np.asarray(p0), "before": history[0][0], "p": np.asarray(best_p), "after": np.asarray(best),
            "gradient": gradient, "history": history, "step_times": times}


def rms_mm(objective) -> np.ndarray:
    """The objective as a root-mean-square distance [mm]: ``1000 sqrt(J)``."""
    return 1000.0 * np.sqrt(np.maximum(np.asarray(objective, float), 0.0))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--candidates", type=int, default=8, help="designs optimised at once (worlds)")
    parser.add_argument("--steps", type=int, default=30, help="Adam steps")
    parser.add_argument("--learning-rate", type=float, default=1e-2, help="Adam's step size [m]")
    parser.add_argument("--sim-steps", type=int, default=110, help="simulator steps per rollout (1.1 crank turns)")
    parser.add_argument("--dt", type=float, default=0.01, help="time step [s]")
    parser.add_argument("--max-iterations", type=int, default=10, help="solver iterations per step (fixed)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--remat", action="store_true", help="recompute each step in the reverse pass (less memory)")
    parser.add_argument("--device", choices=("cpu", "gpu"), default=None, help="default: JAX's default device")
    parser.add_argument("--x64", action="store_true", help="float64 (default: JAX's default float, float32)")
    args = parser.parse_args(argv)
    if args.x64:
        jax.config.update("jax_enable_x64", True)
    device = jax.devices(args.device)[0] if args.device else jax.devices()[0]
    with jax.default_device(device):
        start = time.perf_counter()
        problem = Problem(args.candidates, design_config(args.dt, args.max_iterations), num_steps=args.sim_steps,
                          remat=args.remat)
        p0 = random_designs(args.candidates, args.seed)

        def log(k, entry):
            if k in (0, 1, args.steps) or k % max(1, args.steps // 10) == 0:
                value, _, ok = entry
                print(f"evaluation {k:4d}: best {rms_mm(value.min()):7.2f} mm, median "
                      f"{rms_mm(np.median(value)):7.2f} mm ({int(ok.sum())}/{ok.size} candidates stepped)", flush=True)

        out = optimise(problem, p0, args.steps, args.learning_rate, log=log)
        total = time.perf_counter() - start
    before, after, times = out["before"], out["after"], out["step_times"]
    best = int(np.argmin(after))
    dtype = jnp.zeros(0).dtype
    print(f"\n{args.candidates} candidates, {args.steps} Adam steps, {args.sim_steps} simulator steps of "
          f"{args.dt} s each ({args.max_iterations} solver iterations), {dtype}, on {device.platform}: "
          f"{device.device_kind}")
    print("objective: rms distance of the coupler path from the target curve, sqrt(J) [mm]")
    print(f"  before: best {rms_mm(before.min()):.2f}, median {rms_mm(np.median(before)):.2f}")
    print(f"  after:  best {rms_mm(after.min()):.2f}, median {rms_mm(np.median(after)):.2f}")
    print("best design [m]: " + ", ".join(f"{n} {v:.4f}" for n, v in zip(PARAMETERS, out["p"][best], strict=True))
          + "   (Hoeken's: " + ", ".join(f"{v:.3f}" for v in HOEKEN) + ")")
    steady = np.asarray(times[1:]) if len(times) > 1 else np.asarray(times)
    print(f"wall time: {total:.1f} s in all; first evaluation (traces and compiles) {times[0]:.1f} s; later "
          f"evaluations {np.median(steady):.3f} s each (median), {steady.sum():.1f} s for {len(steady)}")
    world_steps = args.candidates * args.sim_steps / np.median(steady)
    print(f"gradient throughput: {world_steps:.3g} world-steps/s (forward and reverse)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
