"""Mean PADMM iterations per step with and without warm start (issue 2), printed as a table.

    python benchmarks/warm_start.py            # float64, 10 s of each scene at dt = 1/240
    python benchmarks/warm_start.py --seconds 2 --float32
"""

from __future__ import annotations

import argparse

import jax
import numpy as np


def measure(seconds: float, float32: bool) -> list[dict]:
    import kamino

    scenes = {
        "pendulum": kamino.models.pendulum(),
        "double_pendulum": kamino.models.double_pendulum(),
        "fourbar": kamino.models.fourbar(),
        "slider_crank": kamino.models.slider_crank(),
        "chain_of_loops(8)": kamino.models.chain_of_loops(8),
    }
    dt = 1.0 / 240.0
    tol = 1e-4 if float32 else 1e-6
    rows = []
    for name, model in scenes.items():
        state = kamino.init_state(model, dtype=np.float32 if float32 else np.float64)
        row = {"scene": name, "rows": int(model.num_constraints)}
        for warm in (True, False):
            cfg = kamino.SolverConfig(dt=dt, warm_start=warm, tolerance=tol)
            traj = kamino.rollout(model, state, num_steps=round(seconds / dt), config=cfg)
            it = np.asarray(traj.info.iterations)
            key = "warm" if warm else "cold"
            row[f"{key}_mean"] = float(it.mean())
            row[f"{key}_max"] = int(it.max())
            row[f"{key}_converged"] = bool(np.all(traj.info.converged))
        rows.append(row)
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seconds", type=float, default=10.0)
    parser.add_argument("--float32", action="store_true")
    args = parser.parse_args()
    if not args.float32:
        jax.config.update("jax_enable_x64", True)
    rows = measure(args.seconds, args.float32)
    dtype = "float32, tol 1e-4" if args.float32 else "float64, tol 1e-6"
    print(f"PADMM iterations per step, {args.seconds:g} s at dt = 1/240, {dtype}, {jax.default_backend()}")
    print("| scene | rows | warm start: mean / max | cold start: mean / max | all converged |")
    print("|---|---|---|---|---|")
    for r in rows:
        conv = r["warm_converged"] and r["cold_converged"]
        print(f"| {r['scene']} | {r['rows']} | {r['warm_mean']:.1f} / {r['warm_max']} | "
              f"{r['cold_mean']:.1f} / {r['cold_max']} | {conv} |")


if __name__ == "__main__":
    main()
