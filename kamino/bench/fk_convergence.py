"""Forward-kinematics convergence on random actuated configurations.

For each robot, draws N actuated configurations uniformly within the actuators' joint limits
(the limit box; ±1 rad where a DoF is unlimited), solves forward kinematics for all of them in one
batched call (one world per configuration), and reports the fraction that converged (max |C| <=
1e-6), residual quantiles, iterations and wall time. Non-converged worlds must be finite. The command line runs
in float64 (``jax_enable_x64``), the precision the 1e-6 criterion is stated in.

    kamino bench fk_convergence --robots dr_legs animatronic --num 1000 [--json out.json]
"""

from __future__ import annotations

import argparse
import json
import time

import jax
import jax.numpy as jnp
import numpy as np

import kamino

#: the robots with loops and actuators that the command line samples
ROBOTS = ("dr_legs", "animatronic", "bdx", "olaf")


def random_actuated(model: kamino.Model, num: int, seed: int = 0, unlimited: float = 1.0) -> np.ndarray:
    """``[num, num_actuators]`` uniform within each actuated DoF's limits (``±unlimited`` if none)."""
    rng = np.random.default_rng(seed)
    lo = model.dof_lower[model.actuator_dof]
    hi = model.dof_upper[model.actuator_dof]
    lo = np.where(np.isfinite(lo), lo, -unlimited)
    hi = np.where(np.isfinite(hi), hi, unlimited)
    return rng.uniform(lo, hi, size=(num, len(lo)))


def run(name: str, num: int, seed: int = 0, chunk: int = 1000) -> dict:
    """Forward kinematics of ``num`` random actuated configurations of ``kamino.models.NAME()`` in batches of
    ``chunk`` worlds: the converged fraction, residual quantiles, iterations and the wall time of the solves."""
    robot = getattr(kamino.models, name)()  # the procedural robots: kamino/models/robots.py
    samples = random_actuated(robot, num, seed)
    converged, residual, iterations, finite = [], [], [], []
    t_total = 0.0
    for s in range(0, num, chunk):
        part = samples[s:s + chunk]
        model = kamino.replicate(robot, len(part))
        fk = kamino.forward_kinematics(model, actuated_positions=jnp.asarray(part.reshape(-1)))  # compile
        jax.block_until_ready(fk.body_q)
        t0 = time.perf_counter()
        fk = kamino.forward_kinematics(model, actuated_positions=jnp.asarray(part.reshape(-1)))
        jax.block_until_ready(fk.body_q)
        t_total += time.perf_counter() - t0
        converged.append(np.asarray(fk.converged))
        residual.append(np.asarray(fk.residual))
        iterations.append(np.asarray(fk.iterations))
        finite.append(np.all(np.isfinite(np.asarray(fk.body_q)).reshape(len(part), -1), axis=1))
    converged, residual = np.concatenate(converged), np.concatenate(residual)
    iterations, finite = np.concatenate(iterations), np.concatenate(finite)
    return {
        "robot": name, "num": int(num), "bodies": robot.num_bodies, "actuators": robot.num_actuators,
        "converged_fraction": float(converged.mean()), "all_finite": bool(finite.all()),
        "residual_median": float(np.median(residual)), "residual_p99": float(np.quantile(residual, 0.99)),
        "residual_max": float(residual.max()), "iterations_mean": float(iterations.mean()),
        "iterations_max": int(iterations.max()), "wall_s": t_total, "device": str(jax.devices()[0]),
    }


def main(argv: list[str] | None = None, prog: str | None = None) -> int:
    """``kamino bench fk_convergence ARGS`` (``prog`` names the command in the help and errors); 0 when done."""
    ap = argparse.ArgumentParser(prog=prog, description=__doc__.splitlines()[0])
    ap.add_argument("--robots", nargs="+", default=["dr_legs", "animatronic"], choices=ROBOTS, metavar="ROBOT",
                    help=f"of {', '.join(ROBOTS)} (default: dr_legs animatronic)")
    ap.add_argument("--num", type=int, default=1000, help="configurations per robot")
    ap.add_argument("--chunk", type=int, default=1000, help="configurations per batched call")
    ap.add_argument("--json", default=None, help="write the rows as JSON here")
    args = ap.parse_args(argv)
    if args.num < 1 or args.chunk < 1:
        ap.error(f"--num and --chunk must be >= 1, got {args.num} and {args.chunk}")
    jax.config.update("jax_enable_x64", True)
    rows = [run(r, args.num, chunk=args.chunk) for r in args.robots]
    for r in rows:
        print(f"{r['robot']:12s} N={r['num']} converged {100 * r['converged_fraction']:.1f}% finite={r['all_finite']} "
              f"residual median {r['residual_median']:.1e} p99 {r['residual_p99']:.1e} max {r['residual_max']:.1e} "
              f"iterations mean {r['iterations_mean']:.1f} max {r['iterations_max']} "
              f"time {r['wall_s']:.2f} s on {r['device']}")
    if args.json:
        with open(args.json, "w") as f:
            json.dump(rows, f, indent=2)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
