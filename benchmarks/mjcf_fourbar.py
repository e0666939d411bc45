"""MJCF four-bar closed by ``<equality><connect>``: loop closure of kamino vs MuJoCo.

Loads ``benchmarks/scenes/fourbar_connect.xml`` with ``kamino.io.load_mjcf`` and with MuJoCo, drives
the crank's position servo with the same control ``ctrl(t) = A (1 - cos 2 pi f t)`` (starts at rest)
for 10 s at the same time step (float64, both semi-implicit Euler), and prints

* the loop-closure violation: distance between the two connect anchor points (kamino: the loop
  joint's anchors on the coupler and rocker bodies; MuJoCo: ``xpos + xmat @ eq_data`` of both
  bodies after ``mj_kinematics``), max over the run and over the last second;
* the crank's tracking error against the target, and the kamino - MuJoCo joint-angle difference.

Usage: ``python benchmarks/mjcf_fourbar.py [--dt 1e-3] [--duration 10] [--json out.json]``.
"""

from __future__ import annotations

import argparse
import json
import platform
import time
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

import mujoco  # noqa: E402
import numpy as np  # noqa: E402

import kamino  # noqa: E402
from kamino.hostmath import quat_to_matrix  # noqa: E402
from kamino.io import import_mjcf  # noqa: E402

SCENE = Path(__file__).resolve().parent / "scenes" / "fourbar_connect.xml"


def kamino_closure(model: kamino.Model, body_q: np.ndarray, joint: int) -> np.ndarray:
    """Distance [m] between the base and follower anchors of ``joint`` for poses ``body_q [T, B, 7]``."""
    def anchor(body: int, local: np.ndarray) -> np.ndarray:
        R = np.stack([quat_to_matrix(q) for q in body_q[:, body, 3:]])
        return body_q[:, body, :3] + R @ local

    p_b = anchor(int(model.joint_parent[joint]), model.joint_anchor_B[joint])
    p_f = anchor(int(model.joint_child[joint]), model.joint_anchor_F[joint])
    return np.linalg.norm(p_f - p_b, axis=-1)


def run_kamino(imp, ctrl: np.ndarray, dt: float, integrator: str) -> dict:
    m = imp.model
    cfg = kamino.SolverConfig(dt=dt, integrator=integrator)
    controls = kamino.Control.from_ctrl(m, ctrl[:, None])
    state = imp.state()
    t0 = time.perf_counter()
    traj = kamino.rollout(m, state, controls, config=cfg)
    traj.body_q.block_until_ready()
    first = time.perf_counter() - t0
    t0 = time.perf_counter()
    traj = kamino.rollout(m, state, controls, config=cfg)
    traj.body_q.block_until_ready()
    wall = time.perf_counter() - t0
    body_q = np.asarray(traj.body_q)
    return {
        "closure": kamino_closure(m, body_q, m.joint_index("loop")),
        "qpos": imp.qpos(body_q),
        "iterations": np.asarray(traj.info.iterations)[:, 0],
        "converged": bool(np.asarray(traj.info.converged).all()),
        "wall_s": wall,
        "compile_and_run_s": first,
    }


def run_mujoco(mj, ctrl: np.ndarray, dt: float) -> dict:
    mj.opt.timestep = dt
    mj.opt.integrator = mujoco.mjtIntegrator.mjINT_EULER
    data = mujoco.MjData(mj)
    eq = 0
    b1, b2 = int(mj.eq_obj1id[eq]), int(mj.eq_obj2id[eq])
    a1, a2 = mj.eq_data[eq, 0:3].copy(), mj.eq_data[eq, 3:6].copy()
    closure = np.empty(len(ctrl))
    qpos = np.empty((len(ctrl), mj.nq))
    t0 = time.perf_counter()
    for i, c in enumerate(ctrl):
        data.ctrl[0] = c
        mujoco.mj_step(mj, data)
        mujoco.mj_kinematics(mj, data)  # poses of the state after the step
        p1 = data.xpos[b1] + data.xmat[b1].reshape(3, 3) @ a1
        p2 = data.xpos[b2] + data.xmat[b2].reshape(3, 3) @ a2
        closure[i] = np.linalg.norm(p1 - p2)
        qpos[i] = data.qpos
    return {"closure": closure, "qpos": qpos, "wall_s": time.perf_counter() - t0}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--dt", type=float, default=1e-3)
    parser.add_argument("--duration", type=float, default=10.0)
    parser.add_argument("--amplitude", type=float, default=0.4, help="A [rad]; the target swings over [0, 2A]")
    parser.add_argument("--frequency", type=float, default=1.0, help="f [Hz]")
    parser.add_argument("--integrator", default="euler", choices=("euler", "midpoint"), help="kamino's")
    parser.add_argument("--json", type=Path, default=None, help="write the numbers here")
    args = parser.parse_args()

    imp = import_mjcf(SCENE)
    steps = round(args.duration / args.dt)
    t = args.dt * np.arange(1, steps + 1)
    ctrl = args.amplitude * (1.0 - np.cos(2 * np.pi * args.frequency * t))  # target after each step
    k = run_kamino(imp, ctrl, args.dt, args.integrator)
    mj = run_mujoco(imp.mj_model, ctrl, args.dt)

    crank = imp.joint("crank_hinge").qposadr
    rocker = imp.joint("rocker_hinge").qposadr
    last = t > args.duration - 1.0
    out = {
        "scene": str(SCENE.relative_to(Path(__file__).resolve().parents[1])),
        "dt": args.dt, "duration": args.duration, "steps": steps, "integrator_kamino": args.integrator,
        "integrator_mujoco": "Euler", "precision": "float64",
        "kamino_closure_max_m": float(k["closure"].max()),
        "kamino_closure_last_s_max_m": float(k["closure"][last].max()),
        "mujoco_closure_max_m": float(mj["closure"].max()),
        "mujoco_closure_last_s_max_m": float(mj["closure"][last].max()),
        "kamino_crank_tracking_rms_rad": float(np.sqrt(np.mean((k["qpos"][:, crank] - ctrl) ** 2))),
        "mujoco_crank_tracking_rms_rad": float(np.sqrt(np.mean((mj["qpos"][:, crank] - ctrl) ** 2))),
        "crank_kamino_vs_mujoco_max_rad": float(np.abs(k["qpos"][:, crank] - mj["qpos"][:, crank]).max()),
        "rocker_kamino_vs_mujoco_max_rad": float(np.abs(k["qpos"][:, rocker] - mj["qpos"][:, rocker]).max()),
        "kamino_padmm_iterations_mean": float(k["iterations"].mean()),
        "kamino_padmm_iterations_max": int(k["iterations"].max()),
        "kamino_all_converged": k["converged"],
        "kamino_wall_s": k["wall_s"], "mujoco_wall_s": mj["wall_s"],
        "machine": f"{platform.machine()} {platform.processor() or ''}".strip(),
        "versions": {"jax": jax.__version__, "mujoco": mujoco.__version__, "kamino": kamino.__version__},
    }
    print(f"MJCF four-bar ({out['scene']}), {args.duration:g} s at dt = {args.dt:g}, float64, "
          f"ctrl = {args.amplitude:g} (1 - cos 2 pi {args.frequency:g} t)")
    print(f"  loop closure, max          kamino ({args.integrator}) {out['kamino_closure_max_m']:.2e} m   "
          f"MuJoCo (Euler) {out['mujoco_closure_max_m']:.2e} m")
    print(f"  loop closure, last second  kamino {out['kamino_closure_last_s_max_m']:.2e} m   "
          f"MuJoCo {out['mujoco_closure_last_s_max_m']:.2e} m")
    print(f"  crank tracking RMS         kamino {out['kamino_crank_tracking_rms_rad']:.2e} rad   "
          f"MuJoCo {out['mujoco_crank_tracking_rms_rad']:.2e} rad")
    print(f"  kamino - MuJoCo, max       crank {out['crank_kamino_vs_mujoco_max_rad']:.2e} rad   "
          f"rocker {out['rocker_kamino_vs_mujoco_max_rad']:.2e} rad")
    print(f"  kamino PADMM iterations    mean {out['kamino_padmm_iterations_mean']:.1f}, "
          f"max {out['kamino_padmm_iterations_max']}, all converged {out['kamino_all_converged']}")
    print(f"  wall time                  kamino {out['kamino_wall_s']:.2f} s (after compile)   "
          f"MuJoCo {out['mujoco_wall_s']:.2f} s")
    if args.json is not None:
        args.json.write_text(json.dumps(out, indent=2) + "\n")
        print(f"wrote {args.json}")


if __name__ == "__main__":
    main()
