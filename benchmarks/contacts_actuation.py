"""Issue 3 figures: contacts, friction, restitution, limits and actuation in the JAX reference.

Runs each scene of the issue's acceptance list with both integrators (dt = 1/240 s) and prints a
Markdown table row per measurement (the same quantities the tests assert).

    python benchmarks/contacts_actuation.py
"""

from __future__ import annotations

import argparse

import jax
import numpy as np

jax.config.update("jax_enable_x64", True)

import kamino  # noqa: E402
from kamino import Actuation, JointType  # noqa: E402

G, DT = 9.81, 1.0 / 240.0


def rollout(model, steps, integrator, dtype=np.float64, controls=None, **cfg):
    state = kamino.init_state(model, dtype)
    config = kamino.SolverConfig(dt=DT, integrator=integrator, **cfg)
    if controls is None:
        return state, kamino.rollout(model, state, num_steps=steps, config=config)
    return state, kamino.rollout(model, state, controls, config=config)


def iters(traj) -> str:
    it = np.asarray(traj.info.iterations)
    return f"{it.mean():.1f} / {it.max()}"


def angles(model, state, traj):
    return np.asarray(jax.vmap(lambda q: kamino.joint_positions(model, state.replace(body_q=q)))(traj.body_q))


def measure(integrator: str) -> list[tuple[str, str, str]]:
    rows = []
    m = kamino.models.box_on_plane()
    _, tr = rollout(m, 1200, integrator)
    q = np.asarray(tr.body_q)[:, 0]
    fz = np.asarray(tr.contacts.force)[-1, :, 2].sum()
    rows.append(("box resting on a plane, 5 s", f"penetration {max(0.1 - q[:, 2].min(), 0):.1e} m, drift "
                 f"{np.abs(q[:, :2]).max():.1e} m, normal force error {abs(fz - G) / G:.1e}", iters(tr)))
    th = np.deg2rad(20.0)
    down = np.array([np.cos(th), 0.0, -np.sin(th)])
    for mu in (0.5, 0.2):
        m = kamino.models.incline(20.0, mu)
        _, tr = rollout(m, 480, integrator)
        s = (np.asarray(tr.body_q)[:, 0, :3] - m.body_q0[0, :3]) @ down
        if mu == 0.5:
            rows.append(("incline 20°, μ = 0.5, 2 s", f"displacement {abs(s[-1]):.1e} m (sticks)", iters(tr)))
        else:
            t = DT * np.arange(1, 481)
            a = 2 * np.polyfit(t, s, 2)[0]
            exact = G * (np.sin(th) - mu * np.cos(th))
            rows.append(("incline 20°, μ = 0.2, 2 s", f"acceleration error {abs(a - exact) / exact:.1e} (relative)",
                         iters(tr)))
    m = kamino.models.box_on_plane(velocity=(2.0, 0.0, 0.0), mu=0.3)
    _, tr = rollout(m, 100, integrator, tolerance=1e-8)
    rows.append(("box sliding at 2 m/s, μ = 0.3 (tol 1e-8)",
                 f"max normal velocity {np.abs(np.asarray(tr.body_u)[:, 0, 2]).max():.1e} m/s", iters(tr)))
    m = kamino.models.sphere_drop(0.5)
    _, tr = rollout(m, 300, integrator)
    z = np.asarray(tr.body_q)[:, 0, 2] - 0.05
    k = int(np.argmin(z[:150]))
    rows.append(("sphere from 1 m, e = 0.5", f"rebound {z[k:k + 150].max():.4f} m (ideal 0.25)", iters(tr)))
    m = kamino.models.newtons_cradle(3, hanging=False)
    _, tr = rollout(m, 60, integrator)
    v = np.asarray(tr.body_u)[:, :, 0]
    rows.append(("free Newton's cradle of 3", f"momentum error {np.abs(0.1 * v.sum(1) - 0.05).max():.1e} kg m/s, "
                 f"final velocities {np.round(v[-1], 6).tolist()}", iters(tr)))
    m = kamino.models.newtons_cradle(3, hanging=True)
    _, tr = rollout(m, 240, integrator)
    zz = np.asarray(tr.body_q)[:, :, 2]
    rise = zz.max(0) - zz[0, 1]
    rows.append(("hanging Newton's cradle of 3", f"last ball rises to {rise[2] / (zz[0, 0] - zz[0, 1]):.4f} of the "
                 "release height", iters(tr)))
    m = kamino.models.box_stack(5)
    _, tr = rollout(m, 2400, integrator, dtype=np.float32, tolerance=1e-4)
    dev = np.abs(np.asarray(tr.body_q)[:, :, :3] - m.body_q0[None, :, :3]).max()
    rows.append(("stack of 5 boxes, 10 s, float32 (tol 1e-4)", f"max displacement {dev:.1e} m", iters(tr)))

    b = kamino.ModelBuilder()
    rod = b.add_body(mass=1.0, inertia=(0.001, 0.021, 0.021), pos=(0.25, 0, 1))
    b.add_joint_at(JointType.REVOLUTE, -1, rod, anchor=(0, 0, 1), axis=(0, 1, 0), limits=(-1.0, 0.2))
    m = b.finalize()
    st, tr = rollout(m, 1200, integrator)
    rows.append(("pendulum falling onto a limit, 5 s", f"max violation {angles(m, st, tr)[:, 0].max() - 0.2:.1e} rad",
                 iters(tr)))

    def turntable(act):
        b = kamino.ModelBuilder()
        body = b.add_body(mass=1.0, inertia=(0.1,) * 3, pos=(0, 0, 1))
        b.add_joint_at(JointType.REVOLUTE, -1, body, anchor=(0, 0, 1), axis=(0, 0, 1), actuation=act, armature=0.02)
        return b.finalize()

    m = turntable(Actuation("position", kp=10.0, kd=1.2))
    st, tr = rollout(m, 480, integrator, controls=kamino.Control(position_target=np.ones((480, 1))))
    t = DT * np.arange(1, 481)
    J, kp, kd = 0.12, 10.0, 1.2
    wn, ze = np.sqrt(kp / J), kd / (2 * np.sqrt(kp * J))
    wd = wn * np.sqrt(1 - ze**2)
    exact = 1 - np.exp(-ze * wn * t) * (np.cos(wd * t) + ze / np.sqrt(1 - ze**2) * np.sin(wd * t))
    rows.append(("PD step response (kp 10, kd 1.2, I + a = 0.12)",
                 f"max error {np.abs(angles(m, st, tr)[:, 0] - exact).max():.1e} of the step", iters(tr)))
    m = turntable(Actuation("position", kp=1e5, kd=0.0))
    st, tr = rollout(m, 2400, integrator, controls=kamino.Control(position_target=np.ones((2400, 1))))
    err = np.abs(angles(m, st, tr)[:, 0] - 1)
    rows.append(("PD kp = 1e5, kd = 0, 10 s", f"error first second {err[:240].max():.2f} rad, last second "
                 f"{err[-240:].max():.1e} rad", iters(tr)))
    b = kamino.ModelBuilder()
    body = b.add_body(mass=1.0, inertia=(0.1,) * 3, pos=(0, 0, 1))
    b.add_joint_at(JointType.REVOLUTE, -1, body, anchor=(0, 0, 1), axis=(0, 0, 1), limits=(-1.0, 0.5),
                   actuation=Actuation("position", kp=50.0, kd=1.0, effort_limit=0.3), armature=0.02)
    m = b.finalize()
    st, tr = rollout(m, 720, integrator, controls=kamino.Control(position_target=np.full((720, 1), 2.0)))
    rows.append(("effort limit 0.3 N m, unreachable target", f"max applied torque magnitude "
                 f"{np.abs(np.asarray(tr.actuator_force)).max():.6f} N m", iters(tr)))
    m = kamino.models.fourbar(actuated=True, kp=500.0, kd=10.0)
    T = 720
    t = DT * np.arange(1, T + 1)
    pos, vel = np.zeros((T, m.num_dofs)), np.zeros((T, m.num_dofs))
    pos[:, 0], vel[:, 0] = 0.4 * (1 - np.cos(2 * np.pi * t)), 0.4 * 2 * np.pi * np.sin(2 * np.pi * t)
    st, tr = rollout(m, T, integrator, controls=kamino.Control(position_target=pos, velocity_target=vel))
    th = angles(m, st, tr)[:, 0]
    viol = np.asarray(jax.vmap(lambda q: kamino.metrics(m, st.replace(body_q=q))["constraint_violation"])(tr.body_q))
    rows.append(("actuated four-bar, 1 Hz sinusoid (amplitude 0.4 rad), 3 s",
                 f"RMS tracking error {np.sqrt(np.mean((th - pos[:, 0])[T // 3:] ** 2)):.1e} rad, closure "
                 f"{viol.max():.1e} m", iters(tr)))
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--integrators", nargs="+", default=["euler", "midpoint"])
    args = parser.parse_args()
    print("| scene | integrator | result | PADMM iterations mean / max |")
    print("|---|---|---|---|")
    for integ in args.integrators:
        for scene, result, it in measure(integ):
            print(f"| {scene} | {integ} | {result} | {it} |", flush=True)


if __name__ == "__main__":
    main()
