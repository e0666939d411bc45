"""Gradients of a rollout's final state by the implicit function theorem, against central finite differences.

For each scene, in float64 on the JAX reference at the default ``SolverConfig`` (early exit; only ``dt`` and the
``tolerance`` set, see below): a pre-roll of ``PRE_ROLL`` s from the scene's initial state (contacts settled, loops
loaded, the mechanisms moving), then a rollout of ``--seconds`` (default 1 s), and the scalar

    L = sum(W_q * q_T) + sum(W_u * u_T)      (fixed random weights over every body's final pose and twist)

differentiated by ``jax.grad`` with respect to a few scalar inputs: the initial velocities, a control held over the
rollout, and model parameters (a link mass, the friction coefficient, a joint damping) replaced in the padded model
that ``Simulator.step_with`` takes. Each gradient is compared with central differences at three steps, ``h``,
``10 h`` and ``100 h`` (``h`` = ``--fd-step`` times the input's scale). The one in the smooth regime is the step
``h*`` whose difference agrees best with that of the ten times larger step (the spread printed): below it the noise
of the forward solves (an early exit moves a solution by up to about ``tolerance``, so the quotient by about
``tolerance / h``) dominates, above it the truncation error (``h^2``) and the non-smooth events (a contact
appearing, a dead band crossed) a larger interval ``[-h, h]`` takes in.

Tolerance: the finite difference divides the change of an early-exit solve by ``h``, so the solve's own error must
be far below ``h`` times the derivative: ``tolerance = 1e-10`` (``--tolerance``). The gradient itself does not
need it.

    python benchmarks/grad_check.py                       # the four scenes, 1 s each
    python benchmarks/grad_check.py --scenes incline --seconds 0.2
    python benchmarks/grad_check.py --memory fourbar      # implicit against fixed-iteration gradient: memory, time
"""

from __future__ import annotations

import argparse
import dataclasses
import time

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import kamino  # noqa: E402

PRE_ROLL = 0.1  # [s]


@dataclasses.dataclass
class Scene:
    """A model, its time step and its pre-rolled initial state, and the scalar inputs of the check: each maps
    ``(a, state, control, padded model)`` to the perturbed triple, ``a = 0`` the nominal one."""

    model: kamino.Model
    dt: float
    control: kamino.Control | None
    inputs: dict
    velocity0: object = None  # initial state's body_u before the pre-roll (None: the model's)


def _scale(pm, field, index, a):
    x = getattr(pm, field)
    return dataclasses.replace(pm, **{field: x.at[index].multiply(1.0 + a)})


def _add(pm, field, index, a):
    x = getattr(pm, field)
    return dataclasses.replace(pm, **{field: x.at[index].add(a)})


def _ctrl(control, field, index, a):
    return dataclasses.replace(control, **{field: getattr(control, field).at[index].add(a)})


def _friction(pm, a):
    return dataclasses.replace(pm, geom_friction=pm.geom_friction * (1.0 + a))  # contact mu = max of the two geoms


def _rigid_push(state, a):
    """Every body's twist plus a translation at ``a`` m/s along world x (consistent with every joint)."""
    return state.replace(body_u=state.body_u.at[:, 0].add(a))


def _speed(state, a):
    return state.replace(body_u=state.body_u * (1.0 + a))


def scenes() -> dict[str, Scene]:
    """The four scenes of the check (``Scene.inputs``: name -> (perturbation, scale of ``h``))."""
    out = {}
    m = kamino.models.fourbar(damping=0.05)
    zero = jnp.zeros(m.num_dofs)
    coupler = m.body_names.index("coupler")
    out["fourbar"] = Scene(m, 0.01, kamino.Control(dof_effort=zero), {
        "initial speed (x(1+a))": (lambda a, s, c, p: (_speed(s, a), c, p), 1.0),
        "crank effort [N m]": (lambda a, s, c, p: (s, _ctrl(c, "dof_effort", 0, a), p), 1.0),
        "coupler mass (x(1+a))": (lambda a, s, c, p: (s, c, _scale(p, "mass", (0, coupler), a)), 1.0),
        "crank damping [N m s]": (lambda a, s, c, p: (s, c, _add(p, "dof_damping", (0, 0), a)), 0.05),
    })
    m = kamino.models.incline(angle_deg=30.0, mu=0.5)
    downhill = np.array([np.cos(np.pi / 6), 0.0, -np.sin(np.pi / 6)])
    u0 = jnp.zeros((1, 6)).at[0, :3].set(0.3 * downhill)
    push = jnp.zeros((1, 6)).at[0, :3].set(1.0 * downhill)  # 1 N downhill: the motion then depends on the mass
    out["incline"] = Scene(m, 0.01, kamino.Control(body_wrench=push), {
        "initial downhill speed [m/s]": (
            lambda a, s, c, p: (s.replace(body_u=s.body_u.at[0, :3].add(a * downhill)), c, p), 1.0),
        "downhill force [N]": (lambda a, s, c, p: (s, dataclasses.replace(
            c, body_wrench=c.body_wrench.at[0, :3].add(a * downhill)), p), 1.0),
        "box mass (x(1+a))": (lambda a, s, c, p: (s, c, _scale(p, "mass", (0, 0), a)), 1.0),
        "friction (x(1+a))": (lambda a, s, c, p: (s, c, _friction(p, a)), 1.0),
    }, velocity0=u0)
    m = kamino.models.stewart_platform()
    zero = jnp.zeros(m.num_dofs)
    slide0 = int(m.actuator_dof[0])
    damped = int(np.flatnonzero(np.asarray(m.dof_damping) > 0)[0])
    platform = m.body_names.index("platform")
    # the legs driven to a tilt and a lift of the platform: it moves and swings on the loaded loops
    targets = jnp.asarray([0.03, -0.02, 0.01, 0.03, -0.01, 0.02])
    out["stewart"] = Scene(m, 0.01, kamino.Control(position_target=zero.at[np.asarray(m.actuator_dof)].set(targets)), {
        "initial speed (x(1+a))": (lambda a, s, c, p: (_speed(s, a), c, p), 1.0),
        "leg0 target [m]": (lambda a, s, c, p: (s, _ctrl(c, "position_target", slide0, a), p), 0.01),
        "platform mass (x(1+a))": (lambda a, s, c, p: (s, c, _scale(p, "mass", (0, platform), a)), 1.0),
        "leg0 base damping [N m s]": (lambda a, s, c, p: (s, c, _add(p, "dof_damping", (0, damped), a)), 0.1),
    })
    m = kamino.models.dr_legs()
    zero = jnp.zeros(m.num_dofs)
    knee = int(m.actuator_dof[m.actuator_names.index("l_knee_drive")])
    pelvis = m.body_names.index("pelvis")
    out["dr_legs"] = Scene(m, 1.0 / 240.0, kamino.Control(position_target=zero), {
        "push along x [m/s]": (lambda a, s, c, p: (_rigid_push(s, a), c, p), 0.1),
        "l_knee_drive target [rad]": (lambda a, s, c, p: (s, _ctrl(c, "position_target", knee, a), p), 0.1),
        "pelvis mass (x(1+a))": (lambda a, s, c, p: (s, c, _scale(p, "mass", (0, pelvis), a)), 1.0),
        "friction (x(1+a))": (lambda a, s, c, p: (s, c, _friction(p, a)), 1.0),
        # the actuator's damping gain: dr_legs has no passive joint damping (its armature sits in the actuator rows)
        "l_knee_drive kd [N m s]": (lambda a, s, c, p: (s, c, _add(p, "dof_kd", (0, knee), a)), 1.0),
    })
    return out


def make_loss(scene: Scene, cfg: kamino.SolverConfig, seconds: float):
    """``(loss(theta), state after the pre-roll, number of steps)``: ``theta`` holds one ``a`` per input."""
    sim = kamino.Simulator(scene.model, cfg, backend="jax")
    s0 = kamino.init_state(scene.model, dtype=jnp.float64)
    if scene.velocity0 is not None:
        s0 = s0.replace(body_u=jnp.asarray(scene.velocity0, jnp.float64))
    pm, tables = sim.parameters(jnp.float64)
    control = jax.tree.map(lambda x: jnp.asarray(x, jnp.float64), scene.control)
    n_pre, n = round(PRE_ROLL / scene.dt), round(seconds / scene.dt)

    def run(state, ctrl, p, steps):
        def body(s, _):
            return sim.step_with((p, tables), s, ctrl), None

        return jax.lax.scan(body, state, None, length=steps)[0]

    start = jax.jit(run, static_argnums=3)(s0, control, pm, n_pre)
    rng = np.random.default_rng(0)
    wq = jnp.asarray(rng.standard_normal(start.body_q.shape))
    wu = jnp.asarray(0.1 * rng.standard_normal(start.body_u.shape))
    perturb = list(scene.inputs.values())

    def loss(theta):
        s, c, p = start, control, pm
        for k, (fn, _) in enumerate(perturb):
            s, c, p = fn(theta[k], s, c, p)
        sT = run(s, c, p, n)
        return jnp.sum(wq * sT.body_q) + jnp.sum(wu * sT.body_u), sT

    return loss, start, n


def check(name: str, scene: Scene, cfg: kamino.SolverConfig, seconds: float, fd_step: float) -> list[tuple]:
    loss, _, n = make_loss(scene, cfg, seconds)
    theta0 = jnp.zeros(len(scene.inputs))
    fwd = jax.jit(lambda t: loss(t)[0])
    t0 = time.perf_counter()
    (value, sT), grad = jax.jit(jax.value_and_grad(loss, has_aux=True))(theta0)
    grad = np.asarray(grad)
    t_grad = time.perf_counter() - t0
    info = sT.info
    print(f"\n{name}: {n} steps of dt {scene.dt:g} s after a {PRE_ROLL} s pre-roll; L = {float(value):.6f}; "
          f"contacts at the end {int(np.sum(np.asarray(info.num_contacts)))}, iterations of the last step "
          f"{int(np.max(np.asarray(info.iterations)))}, converged {bool(np.all(np.asarray(info.converged)))}; "
          f"gradient (incl. compile) {t_grad:.1f} s", flush=True)
    rows = []
    tiny = np.finfo(np.float64).tiny
    for k, (label, (_, scale)) in enumerate(scene.inputs.items()):
        steps = [fd_step * scale * 10.0 ** i for i in range(3)]
        fds = []
        for h in steps:
            e = np.zeros(len(theta0))
            e[k] = h
            fds.append((float(fwd(theta0 + e)) - float(fwd(theta0 - e))) / (2 * h))
        # the smooth regime: the step whose difference its ten times larger neighbour's agrees with best (below it
        # the solves' noise grows as 1 / h, above it the truncation error as h^2)
        spread = [abs(fds[i] - fds[i + 1]) / max(abs(fds[i]), tiny) for i in range(len(fds) - 1)]
        best = int(np.argmin(spread))
        fd = fds[best]
        rel = abs(grad[k] - fd) / abs(fd) if fd != 0.0 else float("nan")
        rows.append((name, label, grad[k], fd, rel, steps[best], spread[best]))
        all_fd = "  ".join(f"{f:+.8e}" for f in fds)
        print(f"  {label:30s} grad {grad[k]:+.8e}  fd(h, 10h, 100h) {all_fd}  h* {steps[best]:.0e}  "
              f"rel {rel:.1e}  fd spread {spread[best]:.1e}", flush=True)
    return rows


def memory(name: str, scene: Scene, seconds: float, max_iterations: int) -> None:
    """Compiled temporary memory and time of one gradient of a ``seconds`` rollout: implicit (the default
    ``SolverConfig``) against fixed iterations (``fixed_iterations=True``, ``max_iterations``)."""
    configs = {"implicit (default, early exit)": kamino.SolverConfig(dt=scene.dt),
               f"fixed_iterations, max_iterations={max_iterations}":
                   kamino.SolverConfig(dt=scene.dt, fixed_iterations=True, max_iterations=max_iterations)}
    for label, cfg in configs.items():
        loss, _, n = make_loss(scene, cfg, seconds)
        theta0 = jnp.zeros(len(scene.inputs))
        g = jax.jit(jax.grad(lambda t, f=loss: f(t)[0]))
        t0 = time.perf_counter()
        compiled = g.lower(theta0).compile()
        t_compile = time.perf_counter() - t0
        mem = compiled.memory_analysis()
        jax.block_until_ready(compiled(theta0))
        t0 = time.perf_counter()
        times = []
        for _ in range(3):
            t0 = time.perf_counter()
            jax.block_until_ready(compiled(theta0))
            times.append(time.perf_counter() - t0)
        print(f"{name} {label}: {n} steps; temp {mem.temp_size_in_bytes / 2**20:.1f} MiB, "
              f"output {mem.output_size_in_bytes / 2**10:.1f} KiB, generated code "
              f"{mem.generated_code_size_in_bytes / 2**20:.2f} MiB; compile {t_compile:.1f} s; "
              f"gradient {min(times):.3f} s (best of 3)", flush=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scenes", nargs="*", default=["fourbar", "incline", "stewart", "dr_legs"])
    ap.add_argument("--seconds", type=float, default=1.0)
    ap.add_argument("--tolerance", type=float, default=1e-10)
    ap.add_argument("--fd-step", type=float, default=1e-5)
    ap.add_argument("--memory", metavar="SCENE", help="measure the implicit against the fixed-iteration gradient")
    ap.add_argument("--memory-seconds", type=float, default=0.25)
    ap.add_argument("--max-iterations", type=int, default=200)
    args = ap.parse_args()
    all_scenes = scenes()
    if args.memory:
        memory(args.memory, all_scenes[args.memory], args.memory_seconds, args.max_iterations)
        return
    rows = []
    for name in args.scenes:
        scene = all_scenes[name]
        cfg = kamino.SolverConfig(dt=scene.dt, tolerance=args.tolerance)
        rows += check(name, scene, cfg, args.seconds, args.fd_step)
    print(f"\n{'scene':8s} {'input':30s} {'gradient':>15s} {'central diff.':>15s} {'h*':>6s} {'rel. error':>10s} "
          f"{'fd spread':>9s}")
    for name, label, g, fd, rel, h, spread in rows:
        err = f"{rel:10.1e}" if fd != 0.0 else f"{'fd = 0':>10s}"
        print(f"{name:8s} {label:30s} {g:+15.8e} {fd:+15.8e} {h:6.0e} {err} {spread:9.1e}")
    rels = [r[4] for r in rows if r[3] != 0.0]
    worst = max(rels)
    print(f"worst relative error {worst:.1e} ({'within' if worst <= 1e-4 else 'ABOVE'} 1e-4); inputs with a zero "
          f"central difference (no effect): their gradients {[float(r[2]) for r in rows if r[3] == 0.0]}")

if __name__ == "__main__":
    main()
