"""Inverse-kinematics convergence on dr_legs: random reachable foot targets, and unreachable ones.

Draws ``N`` actuated configurations of ``kamino.models.dr_legs`` uniformly within the actuators' joint limits
(:func:`kamino.bench.fk_convergence.random_actuated`, seeded), solves forward kinematics for them with the pelvis
held at its reference pose, and takes both feet's sole points (:func:`kamino.envs.geometry.sole_offsets`) and
orientations there as targets: 12 target rows for the 12 actuated DoFs, so a reachable target has an isolated
solution (positions alone would leave each leg three DoFs free, and "solved" would not say that IK recovered a
configuration). ``M`` more targets are made unreachable: the left foot's sole point ``--drop`` (0.5 m) below a
reachable one, out of the leg's reach. One jitted ``kamino.inverse_kinematics`` call solves the ``N`` reachable
targets (one world per target, the pelvis pinned by ``base_pose``, from the model's reference pose), a second the
``M`` unreachable ones; each is compiled ahead and timed apart from its compilation. Reports the converged share of
the reachable targets, the max / p99 closure and target errors over the converged ones, the unconverged ones'
errors, and each unreachable target's flag and distance (the sole point's distance from its target at the returned
poses). The closure is ``IKResult.closure_error`` (max
|residual| of every joint, loop-closure and pinned-base row, m or rad); the target error is the larger of the
position error [m] and the rotation angle [rad].

    kamino bench ik_convergence                            # N = 1000, M = 20, float64, JAX's default device
    kamino bench ik_convergence --dtype float32 --json out.json
    JAX_PLATFORMS=cuda kamino bench ik_convergence         # the GPU
"""

from __future__ import annotations

import argparse
import json
import time

import jax
import jax.numpy as jnp
import numpy as np

import kamino
from kamino.bench.fk_convergence import random_actuated
from kamino.envs.geometry import sole_offsets
from kamino.kinematics import base_bodies
from kamino.spatial import rotate

FEET = ("l_foot", "r_foot")


def foot_targets(num: int, seed: int = 0, unreachable: int = 0, drop: float = 0.5):
    """dr_legs replicated ``num + unreachable`` times and its targets: ``(model, positions [W, 2, 3], orientations
    [W, 2, 4], offsets [2, 3], base pose [7], reachable [W] bool)``. The sole points and orientations of both feet
    at random actuated positions (forward kinematics in float64, the pelvis at its reference pose); in the last
    ``unreachable`` worlds the left foot's target is ``drop`` [m] lower. Needs ``jax_enable_x64``; raises if forward
    kinematics does not converge (the targets would not be reachable)."""
    robot = kamino.models.dr_legs()
    total = num + unreachable
    model = kamino.replicate(robot, total)
    samples = random_actuated(robot, total, seed=seed)
    base = np.asarray(robot.body_q0[base_bodies(robot)[0]], float)  # the pelvis: the child of the free joint
    fk = kamino.forward_kinematics(model, actuated_positions=jnp.asarray(samples.reshape(-1)), base_pose=base,
                                   dtype=jnp.float64)
    if not np.all(np.asarray(fk.converged)):
        raise RuntimeError(f"forward kinematics did not converge in worlds "
                           f"{np.nonzero(~np.asarray(fk.converged))[0][:8].tolist()}")
    body_q = np.asarray(fk.body_q).reshape(total, robot.num_bodies, 7)
    feet = body_q[:, [robot.body_index(f) for f in FEET]]
    offsets = sole_offsets(robot, FEET)
    positions = feet[..., :3] + np.asarray(rotate(jnp.asarray(feet[..., 3:]),
                                                  jnp.asarray(np.broadcast_to(offsets, feet[..., :3].shape))))
    positions[num:, 0, 2] -= drop
    reachable = np.arange(total) < num
    return model, positions, feet[..., 3:], offsets, base, reachable


def _solve(model, pos, rot, offsets, base, dtype, tolerance, max_iterations):
    """One batched ``inverse_kinematics`` call, compiled ahead (``jax.jit(...).lower(...).compile()``) and then run:
    ``(IKResult, compile seconds, solve seconds)``."""
    def solve(p, r):
        return kamino.inverse_kinematics(model, FEET, p, r, offsets=offsets, base_pose=base, tolerance=tolerance,
                                         max_iterations=max_iterations, dtype=dtype)

    args = (jnp.asarray(pos, dtype), jnp.asarray(rot, dtype))
    t0 = time.perf_counter()
    compiled = jax.jit(solve).lower(*args).compile()
    t_compile = time.perf_counter() - t0
    t0 = time.perf_counter()
    ik = jax.block_until_ready(compiled(*args))
    return ik, t_compile, time.perf_counter() - t0


def run(num: int = 1000, unreachable: int = 20, seed: int = 0, dtype=jnp.float64, drop: float = 0.5,
        tolerance: float = 1e-6, max_iterations: int = 100) -> dict:
    """The check (module docstring) in ``dtype``: the ``num`` reachable targets in one batched call, the
    ``unreachable`` ones in a second (a batch runs until its slowest world stops, and an unreachable target's world
    iterates until its step stalls). Returns a dict of figures (JSON-ready)."""
    _, pos, rot, offsets, base, reachable = foot_targets(num, seed, unreachable, drop)
    dtype = jnp.dtype(dtype)
    robot = kamino.models.dr_legs()
    ik, t_compile, t_solve = _solve(kamino.replicate(robot, num), pos[reachable], rot[reachable], offsets, base,
                                    dtype, tolerance, max_iterations)
    ok = np.asarray(ik.converged)
    closure, target = np.asarray(ik.closure_error, float), np.asarray(ik.target_error, float)
    iterations = np.asarray(ik.iterations)
    missed = np.nonzero(~ok)[0]

    def stat(x, f):
        return float(f(x)) if x.size else None

    out = {
        "robot": "dr_legs", "num": int(num), "unreachable": int(unreachable), "seed": int(seed),
        "dtype": str(dtype), "tolerance": float(tolerance), "max_iterations": int(max_iterations),
        "drop": float(drop), "device": str(jax.devices()[0]), "jax": jax.__version__,
        "converged_fraction": float(ok.mean()),
        "closure_max": stat(closure[ok], np.max), "closure_p99": stat(closure[ok], lambda x: np.quantile(x, 0.99)),
        "target_max": stat(target[ok], np.max), "target_p99": stat(target[ok], lambda x: np.quantile(x, 0.99)),
        "iterations_mean": float(iterations.mean()), "iterations_max": int(iterations.max()),
        "unconverged": [{"world": int(w), "closure": float(closure[w]), "target": float(target[w]),
                         "position": float(np.asarray(ik.position_error)[w]),
                         "orientation": float(np.asarray(ik.orientation_error)[w]),
                         "within_limits": bool(np.asarray(ik.within_limits)[w]), "iterations": int(iterations[w])}
                        for w in missed],
        "compile_s": t_compile, "solve_s": t_solve,
    }
    if unreachable:
        far = ~reachable
        ik, t_compile, t_solve = _solve(kamino.replicate(robot, unreachable), pos[far], rot[far], offsets, base,
                                        dtype, tolerance, max_iterations)
        distance = np.asarray(ik.position_error, float)
        out.update({
            "unreachable_reported": int((~np.asarray(ik.converged)).sum()),
            "unreachable_distance_min": float(distance.min()), "unreachable_distance_max": float(distance.max()),
            "unreachable_closure_max": float(np.asarray(ik.closure_error).max()),
            "unreachable_iterations_max": int(np.asarray(ik.iterations).max()),
            "unreachable_compile_s": t_compile, "unreachable_solve_s": t_solve,
        })
    return out


def summary(r: dict) -> str:
    """Text lines of one :func:`run` result."""
    def e(x):
        return "-" if x is None else f"{x:.1e}"

    lines = [f"dr_legs IK, {r['dtype']}, {r['num']} reachable + {r['unreachable']} unreachable targets (seed "
             f"{r['seed']}) on {r['device']}",
             f"  reachable: converged {100 * r['converged_fraction']:.1f} %; over the converged: closure max "
             f"{e(r['closure_max'])} p99 {e(r['closure_p99'])}, target error max {e(r['target_max'])} p99 "
             f"{e(r['target_p99'])}; iterations mean {r['iterations_mean']:.1f} max {r['iterations_max']}"]
    for u in r["unconverged"]:
        lines.append(f"  unconverged world {u['world']}: closure {u['closure']:.1e}, target error {u['target']:.1e}, "
                     f"within limits {u['within_limits']}, {u['iterations']} iterations")
    if r["unreachable"]:
        lines.append(f"  unreachable (left foot {r['drop']} m lower): {r['unreachable_reported']}/{r['unreachable']} "
                     f"reported unconverged, distance {r['unreachable_distance_min']:.3f}-"
                     f"{r['unreachable_distance_max']:.3f} m, closure max {e(r['unreachable_closure_max'])}, "
                     f"iterations max {r['unreachable_iterations_max']}")
    lines.append(f"  time ({r['num']} worlds, one call): compile {r['compile_s']:.1f} s, solve {r['solve_s']:.2f} s")
    return "\n".join(lines)


def main(argv: list[str] | None = None, prog: str | None = None) -> int:
    """``kamino bench ik_convergence ARGS`` (``prog`` names the command in the help and errors); 0 when the
    acceptance holds (>= 99 % of the reachable targets converged, every unreachable one reported), 1 otherwise."""
    ap = argparse.ArgumentParser(prog=prog, description=__doc__.splitlines()[0])
    ap.add_argument("--num", type=int, default=1000, help="reachable targets (worlds)")
    ap.add_argument("--unreachable", type=int, default=20, help="unreachable targets, in a second call")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--dtype", nargs="+", default=["float64"], choices=["float32", "float64"],
                    help="one run per dtype (default float64)")
    ap.add_argument("--drop", type=float, default=0.5, help="an unreachable target's depth below a reachable one [m]")
    ap.add_argument("--max-iterations", type=int, default=100)
    ap.add_argument("--json", default=None, help="write the results as JSON here")
    args = ap.parse_args(argv)
    if args.num < 1 or args.unreachable < 0:
        ap.error(f"--num must be >= 1 and --unreachable >= 0, got {args.num} and {args.unreachable}")
    jax.config.update("jax_enable_x64", True)  # float64 available; each run names its dtype
    rows = []
    for name in args.dtype:
        rows.append(run(args.num, args.unreachable, args.seed, jnp.dtype(name), args.drop,
                        max_iterations=args.max_iterations))
        print(summary(rows[-1]), flush=True)
    if args.json:
        with open(args.json, "w") as f:
            json.dump(rows, f, indent=2)
    passed = all(r["converged_fraction"] >= 0.99 and r.get("unreachable_reported", 0) == r["unreachable"] for r in rows)
    return 0 if passed else 1


if __name__ == "__main__":
    raise SystemExit(main())
