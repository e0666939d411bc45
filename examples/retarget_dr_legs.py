"""Retargeting: a stepping gait's foot trajectory for ``kamino.models.dr_legs`` becomes actuator commands.

    python examples/retarget_dr_legs.py                  # 50 frames (one 1 s gait cycle), a table
    python examples/retarget_dr_legs.py --plot gait.png  # and a plot of the targets against the replay

1. **Targets.** A gait cycle in the pelvis frame (the pelvis pinned, as on a treadmill): each foot's sole point
   swings forward in an arc (``stride`` long, ``height`` high) for half the cycle and slides back along the ground
   for the other half (the stance), the two feet half a cycle apart; the soles stay flat (their reference
   orientation).
2. **Inverse kinematics, every frame at once.** The frames are the worlds of ``kamino.replicate(robot, frames)``: one
   call of ``kamino.inverse_kinematics`` (one compiled program) solves all of them with every loop of both legs
   closed (docs/formulation.md §9, "Inverse kinematics"): two feet's positions and orientations are 12 target rows
   for the 12 actuated DoFs.
3. **Actuator commands.** The actuated DoFs' positions at the solved poses (``kamino.dof_state`` read at
   ``model.actuator_dof``: what the PD position actuators' targets, ``Control.position_target``, are measured in, and
   what ``kamino.envs``' policies command).
4. **Replay.** The commands drive the simulator (``kamino.rollout``, the JAX backend), interpolated linearly between
   frames, with their rate as the velocity target: the robot hangs from its pelvis (the pelvis welded to the world,
   the feet in the air) and its PD servos track the commands. The table reports each frame's IK convergence and the
   replay's sole-point error against the targets and its loop closure.

The robot with a fixed pelvis is ``dr_legs`` exported with ``kamino.save_mjcf`` and loaded back without its free
joint (``fixed_pelvis``): the same bodies, joints, loops and actuators, the pelvis part of the world.
"""

from __future__ import annotations

import argparse
import time

import jax
import jax.numpy as jnp
import numpy as np

import kamino
from kamino.envs.geometry import sole_offsets
from kamino.spatial import rotate

FEET = ("l_foot", "r_foot")


def fixed_pelvis() -> kamino.Model:
    """``dr_legs`` (no ground) with its pelvis welded to the world at its reference pose: the MJCF export without the
    free joint, loaded back."""
    robot = kamino.models.dr_legs(ground=False)
    xml = kamino.save_mjcf(robot)
    free = '<joint name="floating_base" type="free" />'
    if free not in xml:
        raise RuntimeError("dr_legs' MJCF export has no free joint named floating_base")
    return kamino.load_mjcf(xml.replace(free, ""))


def sole_points(robot: kamino.Model, body_q, offsets) -> jax.Array:
    """``[..., 2, 3]`` the sole points of both feet from poses ``body_q`` ``[..., num_bodies, 7]`` of one world."""
    q = body_q[..., [robot.body_index(f) for f in FEET], :]
    return q[..., :3] + rotate(q[..., 3:], jnp.broadcast_to(jnp.asarray(offsets, q.dtype), q[..., :3].shape))


def gait(robot: kamino.Model, frames: int, stride: float = 0.12, height: float = 0.05):
    """The targets of one gait cycle of ``frames`` frames: sole positions ``[frames, 2, 3]`` and orientations
    ``[frames, 2, 4]`` (the reference's), and the sole offsets ``[2, 3]`` (``kamino.envs.geometry.sole_offsets``: the
    centre of each foot's lowest support points). Phase ``s = k / frames``; the left foot swings for ``s < 1/2``
    (``x`` from ``-stride/2`` to ``+stride/2`` about its reference, ``z`` up by ``height (1 - cos 4 pi s) / 2``) and
    slides back along the ground for ``s >= 1/2``, both eased by ``(1 - cos pi a) / 2`` (``a`` the progress through
    the phase: the foot stops at either end, so the commands have no jump in rate for the servos to overshoot); the
    right foot half a cycle later."""
    offsets = sole_offsets(robot, FEET)
    q0 = np.asarray(robot.body_q0, float)
    feet = [robot.body_index(f) for f in FEET]
    rest = np.asarray(sole_points(robot, jnp.asarray(q0), offsets))  # [2, 3]
    s = np.arange(frames) / frames
    pos = np.repeat(rest[None], frames, axis=0)
    for foot, shift in ((0, 0.0), (1, 0.5)):
        u = (s + shift) % 1.0
        swing = u < 0.5
        a = np.where(swing, u / 0.5, (u - 0.5) / 0.5)  # progress through the swing or the stance, 0..1
        ease = 0.5 - 0.5 * np.cos(np.pi * a)  # 0 -> 1 with zero rate at both ends
        dx = np.where(swing, stride * (ease - 0.5), stride * (0.5 - ease))
        dz = np.where(swing, height * 0.5 * (1.0 - np.cos(2 * np.pi * a)), 0.0)
        pos[:, foot, 0] += dx
        pos[:, foot, 2] += dz
    rot = np.repeat(q0[feet, 3:][None], frames, axis=0)
    return pos, rot, offsets


def actuator_commands(model: kamino.Model, body_q) -> jax.Array:
    """``[num_worlds, num_actuators // num_worlds]`` the actuated DoFs' positions at poses ``body_q`` (flat over
    worlds): the PD position targets that hold those poses."""
    state = kamino.init_state(model, dtype=body_q.dtype).replace(body_q=body_q)
    q, _ = kamino.dof_state(model, state)
    return q[np.asarray(model.actuator_dof)].reshape(model.num_worlds, -1)


def replay_controls(robot: kamino.Model, commands: np.ndarray, frame_dt: float, dt: float, cycles: int):
    """``Control`` with a time axis: ``commands`` ``[frames, num_actuators]`` (one gait cycle, periodic) interpolated
    linearly to every simulator step of ``dt`` for ``cycles`` cycles, as position targets, with their rate as the
    velocity target; and the times [s] at the end of each step."""
    frames = commands.shape[0]
    period = frames * frame_dt
    steps = round(cycles * period / dt)
    t = dt * np.arange(1, steps + 1)
    knots = frame_dt * np.arange(frames + 1)
    closed = np.concatenate([commands, commands[:1]])
    target = np.stack([np.interp(t % period, knots, closed[:, a]) for a in range(closed.shape[1])], -1)
    rate = np.stack([np.interp(t % period, knots[:-1] + frame_dt / 2, np.diff(closed[:, a]) / frame_dt,
                               period=period) for a in range(closed.shape[1])], -1)
    dof = np.asarray(robot.actuator_dof)
    pos = np.zeros((steps, robot.num_dofs))
    vel = np.zeros((steps, robot.num_dofs))
    pos[:, dof], vel[:, dof] = target, rate
    return kamino.Control(position_target=jnp.asarray(pos), velocity_target=jnp.asarray(vel)), t


def retarget(frames: int = 50, frame_dt: float = 0.02, stride: float = 0.12, height: float = 0.05,
             dt: float = 0.004, cycles: int = 1, robot: kamino.Model | None = None, config=None) -> dict:
    """The whole pipeline (module docstring) for one gait cycle of ``frames`` frames ``frame_dt`` apart, replayed
    for ``cycles`` cycles with simulator steps of ``dt`` (``config``: a ``kamino.SolverConfig``, default
    ``SolverConfig(dt=dt)``). Returns a dict of NumPy arrays: ``targets`` ``[frames, 2, 3]``, ``converged``,
    ``ik_error`` [m] and ``ik_closure`` (per frame), ``commands`` ``[frames, 12]``, ``replayed`` ``[cycles * frames,
    2, 3]`` (the sole points at the frame times), ``replay_error`` [m] (per frame time: the larger of the two feet's
    distance from the target), ``replay_closure`` (per frame time: the loops' largest constraint residual, m or
    rad), and the wall times [s] of the IK and the replay."""
    robot = fixed_pelvis() if robot is None else robot
    dtype = jnp.zeros(0).dtype
    pos, rot, offsets = gait(robot, frames, stride, height)
    model = kamino.replicate(robot, frames)
    t0 = time.perf_counter()
    ik = kamino.inverse_kinematics(model, FEET, pos, rot, offsets=offsets, dtype=dtype)
    commands = actuator_commands(model, ik.body_q)
    commands.block_until_ready()
    t_ik = time.perf_counter() - t0

    t0 = time.perf_counter()
    controls, _ = replay_controls(robot, np.asarray(commands), frame_dt, dt, cycles)
    start = np.asarray(ik.body_q).reshape(frames, robot.num_bodies, 7)[0]
    state = kamino.init_state(robot, dtype=dtype).replace(body_q=jnp.asarray(start, dtype))
    config = kamino.SolverConfig(dt=dt) if config is None else config
    traj = kamino.rollout(robot, state, jax.tree.map(lambda x: x.astype(dtype), controls), config=config,
                          backend="jax")
    per_frame = round(frame_dt / dt)
    at_frames = slice(per_frame - 1, None, per_frame)  # the states at t = frame_dt, 2 frame_dt, ...
    replayed = np.asarray(sole_points(robot, traj.body_q[at_frames], offsets))
    closure = np.asarray(kamino.metrics(robot, traj)["constraint_violation"])[at_frames, 0]
    t_replay = time.perf_counter() - t0
    # the state after step k * per_frame is at frame k + 1 of the cycle
    expected = np.roll(pos, -1, axis=0)[np.arange(len(replayed)) % frames]
    return {"targets": pos, "converged": np.asarray(ik.converged), "ik_error": np.asarray(ik.target_error),
            "ik_closure": np.asarray(ik.closure_error), "commands": np.asarray(commands), "replayed": replayed,
            "expected": expected, "replay_error": np.linalg.norm(replayed - expected, axis=-1).max(-1),
            "replay_closure": closure, "ik_seconds": t_ik, "replay_seconds": t_replay}


def table(out: dict, rows: int = 10) -> str:
    """A short text table of :func:`retarget`'s result: every ``len / rows``-th frame, then the totals."""
    n = len(out["converged"])
    lines = [f"{'frame':>5} {'IK':>4} {'IK error':>9} {'closure':>9} | {'replay error':>12} {'closure':>9}",
             f"{'':>5} {'':>4} {'[m]':>9} {'[m]':>9} | {'[mm]':>12} {'[m]':>9}"]
    for k in range(0, n, max(1, n // rows)):
        lines.append(f"{k:5d} {'ok' if out['converged'][k] else 'NO':>4} {out['ik_error'][k]:9.1e} "
                     f"{out['ik_closure'][k]:9.1e} | {1e3 * out['replay_error'][k - 1]:12.2f} "
                     f"{out['replay_closure'][k - 1]:9.1e}")
    err = out["replay_error"]
    lines.append(f"IK: {int(out['converged'].sum())}/{n} frames converged, largest target error "
                 f"{out['ik_error'].max():.1e} m, closure {out['ik_closure'].max():.1e} ({out['ik_seconds']:.1f} s)")
    lines.append(f"replay: sole-point error {1e3 * err.mean():.2f} mm mean, {1e3 * err.max():.2f} mm max; loop "
                 f"closure {out['replay_closure'].max():.1e} ({out['replay_seconds']:.1f} s)")
    return "\n".join(lines)


def plot(out: dict, path: str) -> None:
    """Side view (x against z, pelvis frame) of both feet's targets and replayed sole points, and the replay error."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (side, err) = plt.subplots(1, 2, figsize=(11, 4))
    for foot, name in enumerate(FEET):
        t, r = out["targets"][:, foot], out["replayed"][:, foot]
        side.plot(np.append(t[:, 0], t[0, 0]), np.append(t[:, 2], t[0, 2]), "-", label=f"{name} target")
        side.plot(r[:, 0], r[:, 2], ".", label=f"{name} replayed")
    side.set(xlabel="x [m]", ylabel="z [m]", title="sole points, pelvis frame")
    side.legend(fontsize=8)
    err.plot(1e3 * out["replay_error"])
    err.set(xlabel="frame", ylabel="error [mm]", title="replay: sole-point error (worse foot)")
    fig.tight_layout()
    fig.savefig(path, dpi=100)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--frames", type=int, default=50, help="frames of one gait cycle (IK worlds)")
    parser.add_argument("--frame-dt", type=float, default=0.02, help="time between frames [s]")
    parser.add_argument("--stride", type=float, default=0.12, help="stride length [m]")
    parser.add_argument("--height", type=float, default=0.05, help="swing height [m]")
    parser.add_argument("--dt", type=float, default=0.004, help="simulator time step [s]")
    parser.add_argument("--cycles", type=int, default=1, help="gait cycles replayed")
    parser.add_argument("--plot", metavar="PNG", help="save a plot (matplotlib)")
    parser.add_argument("--x64", action="store_true", help="float64 (default: JAX's default float, float32)")
    args = parser.parse_args(argv)
    if args.x64:
        jax.config.update("jax_enable_x64", True)
    out = retarget(args.frames, args.frame_dt, args.stride, args.height, args.dt, args.cycles)
    print(table(out))
    if args.plot:
        plot(out, args.plot)
        print(f"wrote {args.plot}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
