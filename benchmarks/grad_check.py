"""Gradients of a rollout's final state by the implicit function theorem, against central finite differences.

For each scene, in float64 at the default ``SolverConfig`` (early exit; only ``dt`` and the ``tolerance`` set, see
below), on the JAX reference (``--backend jax``, the default) or through the Warp backend (``--backend warp``: the
Warp step's value, the reference's tangent at the Warp solution, docs/formulation.md §7.10): a pre-roll of
``PRE_ROLL`` s from the scene's initial state (contacts settled, loops loaded, the mechanisms moving), then a
rollout of ``--seconds`` (default 1 s), and the scalar

    L = sum(W_q * q_T) + sum(W_u * u_T)      (fixed random weights over every body's final pose and twist)

differentiated by ``jax.grad`` with respect to a few scalar inputs: the initial velocities, a control held over the
rollout, and model parameters (a link mass, the friction coefficient, a joint damping) replaced in the padded model
that ``Simulator.step_with`` takes (on the Warp backend the same values as its ``WorldParameters``).

Step selection. Each gradient is compared with central differences ``D(h_i)`` at ``--decades`` steps ``h_i = h
10^i`` (default four: ``h`` to ``1000 h``; ``h`` = ``--fd-step`` times the input's scale). A difference's error is
the noise of the forward solves (an early exit moves a solution by up to about ``tolerance``, so the quotient by
about ``tolerance / h``: it grows ten times per decade down) plus the truncation error (``h^2``: a hundred times
per decade up) and the non-smooth events (a contact appearing, a dead band crossed) that a larger interval
``[-h, h]`` takes in. So at an interior step ``h_i`` the spread to the smaller neighbour, ``|D(h_{i-1}) - D(h_i)|``,
is at least about ten times ``D(h_i)``'s noise where the noise dominates, and the spread to the larger one,
``|D(h_{i+1}) - D(h_i)|``, about 99 times its truncation error where that dominates: the larger of the two spreads
(relative to ``|D(h_i)|``) bounds ``D(h_i)``'s error either way. The reference value is the interior step's
difference whose bound is smallest; the bound is printed with it (``fd bound``), and a relative error below it says
only that the gradient is within what the differences resolve. (Taking the step whose difference agrees best with
its ten times larger neighbour, the former rule, picks a step inside the noise when the noise falls slowly: on
dr_legs that gave 1.7e-4 and 4.2e-4 where the larger steps agree with the gradient to 3e-5.)

Tolerance: the finite difference divides the change of an early-exit solve by ``h``, so the solve's own error must
be far below ``h`` times the derivative: ``tolerance = 1e-10`` (``--tolerance``). The gradient itself does not
need it.

Cost (``--cost SCENE``): for a rollout of ``--cost-steps`` steps of the scene (after the pre-roll) on the current
device, the time of the jitted ``jax.grad`` of ``L`` against the jitted forward rollout alone (compiles excluded,
median of ``--repeats``), and the compiled gradient's temporary memory (XLA's memory analysis; on the Warp backend
the steppers' own Warp buffers are not in it) at each ``--cost-iterations`` ``max_iterations``, for each
``--backends``, at the default ``tolerance``.

    python benchmarks/grad_check.py                       # the four scenes, 1 s each
    python benchmarks/grad_check.py --scenes incline --seconds 0.2
    python benchmarks/grad_check.py --backend warp        # the same through the Warp backend
    python benchmarks/grad_check.py --memory fourbar      # implicit against fixed-iteration gradient: memory, time
    python benchmarks/grad_check.py --cost dr_legs --cost-steps 100   # gradient against forward: time, memory
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


def world_parameters(model: kamino.Model, pm):
    """The padded model ``pm``'s physical parameters as the Warp backend's ``WorldParameters`` (flat over worlds)."""
    from kamino.jax_ref.types import _pad_index, layout_of
    from kamino.warp_backend.parameters import WorldParameters

    lay = layout_of(model, pm.mass.dtype)
    gs = _pad_index(model.world_geom_start, model.world_geom_count, pm.geom_friction.shape[1])[2]
    flat = lambda x, scatter: x.reshape((-1, *x.shape[2:]))[scatter]  # noqa: E731
    body, dof = lambda x: flat(x, lay.body_scatter), lambda x: flat(x, lay.dof_scatter)
    return WorldParameters(
        body_mass=body(pm.mass), body_inertia=body(pm.inertia), geom_friction=flat(pm.geom_friction, gs),
        dof_kp=dof(pm.dof_kp), dof_kd=dof(pm.dof_kd), dof_armature=dof(pm.dof_armature),
        dof_damping=dof(pm.dof_damping), dof_effort_limit=dof(pm.dof_effort_limit), gravity=pm.gravity)


def make_loss(scene: Scene, cfg: kamino.SolverConfig, seconds: float, backend: str = "jax"):
    """``(loss(theta), state after the pre-roll, number of steps)``: ``theta`` holds one ``a`` per input."""
    sim = kamino.Simulator(scene.model, cfg, backend=backend)
    s0 = kamino.init_state(scene.model, dtype=jnp.float64)
    if scene.velocity0 is not None:
        s0 = s0.replace(body_u=jnp.asarray(scene.velocity0, jnp.float64))
    pm, tables = kamino.Simulator(scene.model, cfg, backend="jax").parameters(jnp.float64)
    control = jax.tree.map(lambda x: jnp.asarray(x, jnp.float64), scene.control)
    n_pre, n = round(PRE_ROLL / scene.dt), round(seconds / scene.dt)

    def run(state, ctrl, p, steps):
        given = (p, tables) if backend == "jax" else world_parameters(scene.model, p)

        def body(s, _):
            return sim.step_with(given, s, ctrl), None

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


def select(fds: list[float]) -> tuple[int, float]:
    """``(i, bound)``: the interior step whose central difference ``fds[i]`` has the smallest error bound, the
    larger of its relative spreads to its two neighbours (the module docstring, "Step selection")."""
    tiny = np.finfo(np.float64).tiny
    bounds = [max(abs(fds[i] - fds[i - 1]), abs(fds[i] - fds[i + 1])) / max(abs(fds[i]), tiny)
              for i in range(1, len(fds) - 1)]
    best = int(np.argmin(bounds))
    return best + 1, bounds[best]


def check(name: str, scene: Scene, cfg: kamino.SolverConfig, seconds: float, fd_step: float, decades: int = 4,
          backend: str = "jax") -> list[tuple]:
    loss, _, n = make_loss(scene, cfg, seconds, backend)
    theta0 = jnp.zeros(len(scene.inputs))
    fwd = jax.jit(lambda t: loss(t)[0])
    t0 = time.perf_counter()
    (value, sT), grad = jax.jit(jax.value_and_grad(loss, has_aux=True))(theta0)
    grad = np.asarray(grad)
    t_grad = time.perf_counter() - t0
    info = sT.info
    print(f"\n{name} ({backend}): {n} steps of dt {scene.dt:g} s after a {PRE_ROLL} s pre-roll; "
          f"L = {float(value):.6f}; "
          f"contacts at the end {int(np.sum(np.asarray(info.num_contacts)))}, iterations of the last step "
          f"{int(np.max(np.asarray(info.iterations)))}, converged {bool(np.all(np.asarray(info.converged)))}; "
          f"gradient (incl. compile) {t_grad:.1f} s", flush=True)
    rows = []
    for k, (label, (_, scale)) in enumerate(scene.inputs.items()):
        steps = [fd_step * scale * 10.0 ** i for i in range(decades)]
        fds = []
        for h in steps:
            e = np.zeros(len(theta0))
            e[k] = h
            fds.append((float(fwd(theta0 + e)) - float(fwd(theta0 - e))) / (2 * h))
        best, bound = select(fds)
        fd = fds[best]
        rel = abs(grad[k] - fd) / abs(fd) if fd != 0.0 else float("nan")
        rows.append((name, label, grad[k], fd, rel, steps[best], bound))
        all_fd = "  ".join(f"{f:+.8e}" for f in fds)
        print(f"  {label:30s} grad {grad[k]:+.8e}  fd(h .. {10 ** (decades - 1)}h) {all_fd}  h* {steps[best]:.0e}  "
              f"rel {rel:.1e}  fd bound {bound:.1e}", flush=True)
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


def cost(name: str, scene: Scene, steps: int, backends: list[str], iterations: list[int], repeats: int) -> None:
    """Time and memory of the gradient of ``L`` after ``steps`` steps against the forward rollout alone (the module
    docstring, "Cost")."""
    dev = jax.devices()[0]
    for backend in backends:
        for its in iterations:
            cfg = kamino.SolverConfig(dt=scene.dt, max_iterations=its)
            loss, _, n = make_loss(scene, cfg, steps * scene.dt, backend)
            theta0 = jnp.zeros(len(scene.inputs))
            row = {}
            for kind, fn in (("forward", lambda t, f=loss: f(t)[0]), ("gradient", jax.grad(lambda t, f=loss: f(t)[0]))):
                t0 = time.perf_counter()
                compiled = jax.jit(fn).lower(theta0).compile()
                t_compile = time.perf_counter() - t0
                jax.block_until_ready(compiled(theta0))
                times = []
                for _ in range(repeats):
                    t0 = time.perf_counter()
                    jax.block_until_ready(compiled(theta0))
                    times.append(time.perf_counter() - t0)
                mem = compiled.memory_analysis()
                row[kind] = (float(np.median(times)), t_compile, mem.temp_size_in_bytes / 2**20)
            (tf, cf, mf), (tg, cg, mg) = row["forward"], row["gradient"]
            print(f"{name} {backend} on {dev.platform} ({dev.device_kind}), {n} steps, max_iterations {its}: forward "
                  f"{tf * 1e3:.1f} ms (temp {mf:.1f} MiB), gradient {tg * 1e3:.1f} ms (temp {mg:.1f} MiB): "
                  f"{tg / tf:.2f}x the forward (median of {repeats}; compiles {cf:.0f} s, {cg:.0f} s)", flush=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scenes", nargs="*", default=["fourbar", "incline", "stewart", "dr_legs"])
    ap.add_argument("--backend", choices=("jax", "warp"), default="jax")
    ap.add_argument("--seconds", type=float, default=1.0)
    ap.add_argument("--tolerance", type=float, default=1e-10)
    ap.add_argument("--fd-step", type=float, default=1e-5)
    ap.add_argument("--decades", type=int, default=4, help="central differences at h, 10h, ... (at least 3)")
    ap.add_argument("--memory", metavar="SCENE", help="measure the implicit against the fixed-iteration gradient")
    ap.add_argument("--memory-seconds", type=float, default=0.25)
    ap.add_argument("--max-iterations", type=int, default=200)
    ap.add_argument("--cost", metavar="SCENE", help="time and memory of the gradient against the forward rollout")
    ap.add_argument("--cost-steps", type=int, default=100)
    ap.add_argument("--cost-iterations", type=int, nargs="*", default=[100, 400])
    ap.add_argument("--backends", nargs="*", default=["jax", "warp"])
    ap.add_argument("--repeats", type=int, default=5)
    args = ap.parse_args()
    all_scenes = scenes()
    if args.memory:
        memory(args.memory, all_scenes[args.memory], args.memory_seconds, args.max_iterations)
        return
    if args.cost:
        cost(args.cost, all_scenes[args.cost], args.cost_steps, args.backends, args.cost_iterations, args.repeats)
        return
    if args.decades < 3:
        ap.error("--decades: at least 3 (an interior step has two neighbours)")
    rows = []
    for name in args.scenes:
        scene = all_scenes[name]
        cfg = kamino.SolverConfig(dt=scene.dt, tolerance=args.tolerance)
        rows += check(name, scene, cfg, args.seconds, args.fd_step, args.decades, args.backend)
    print(f"\n{'scene':8s} {'input':30s} {'gradient':>15s} {'central diff.':>15s} {'h*':>6s} {'rel. error':>10s} "
          f"{'fd bound':>9s}")
    for name, label, g, fd, rel, h, bound in rows:
        err = f"{rel:10.1e}" if fd != 0.0 else f"{'fd = 0':>10s}"
        print(f"{name:8s} {label:30s} {g:+15.8e} {fd:+15.8e} {h:6.0e} {err} {bound:9.1e}")
    for name in args.scenes:
        rels = [r[4] for r in rows if r[0] == name and r[3] != 0.0]
        if rels:
            print(f"{name}: worst relative error {max(rels):.1e}")
    rels = [r[4] for r in rows if r[3] != 0.0]
    worst = max(rels)
    print(f"worst relative error {worst:.1e} ({'within' if worst <= 1e-4 else 'ABOVE'} 1e-4, {args.backend}); inputs "
          f"with a zero central difference (no effect): their gradients {[float(r[2]) for r in rows if r[3] == 0.0]}")


if __name__ == "__main__":
    main()
