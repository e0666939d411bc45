"""LLT against CR on Warp's CPU device: ``python benchmarks/linear_solver_cpu.py SCENE [--worlds 4] [--steps 20]``.

One thread per world, float32, ``SolverConfig(dt, linear_solver=...)`` at the defaults, the worlds at rest from
``kamino.init_state`` (no drive). It reports the wall time per step after two warm-up steps, the PADMM iterations,
the converged fraction and the loop closure, for ``linear_solver="llt"`` and ``"cr"``: the data for a CPU rule of
``linear_solver="auto"`` (``pipeline.AUTO_CR_ROWS`` comes from H100 timings). SCENE is a benchmark scene
(``throughput.py``) or ``ROBOT_rt``, a robot of ``kamino.models`` after an MJCF round trip (``save_mjcf`` then
``load_mjcf``). ``--out`` writes the two records as JSON.
"""

from __future__ import annotations

import argparse
import json
import pathlib
import sys
import tempfile
import time

import numpy as np

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent))
import throughput as tb  # the benchmark scenes


def load(scene: str):
    import kamino

    if not scene.endswith("_rt"):
        return tb.load_scene(scene)[0]
    with tempfile.TemporaryDirectory() as d:
        path = pathlib.Path(d) / "model.xml"
        kamino.save_mjcf(getattr(kamino.models, scene[:-3])(), path)
        return kamino.load_mjcf(path)


def measure(base, linear_solver: str, worlds: int, steps: int) -> dict:
    import warp as wp

    import kamino
    from kamino.warp_backend import backend as wb
    from kamino.warp_backend.pipeline import Stepper

    wp.config.quiet = True
    model = kamino.replicate(base, worlds)
    st = Stepper(model, kamino.SolverConfig(dt=tb.DT, linear_solver=linear_solver), np.float32, "cpu", padmm="thread")
    wb.load_state(st, kamino.init_state(model, dtype=np.float32), None)
    st.run(2)  # compilation and warm-up
    its, conv = [], []
    t0 = time.perf_counter()
    for _ in range(steps):
        st.run(1)
        its.append(st.work.iters.numpy().copy())
        conv.append(st.work.converged.numpy().copy())
    wall = (time.perf_counter() - t0) / steps
    q = st.work.q.numpy().view(np.float32).reshape(-1, 7)[: int(base.num_bodies)]
    return {"linear_solver": linear_solver, "rows": int(st.wm.max_rows), "worlds": worlds, "steps": steps,
            "s_per_step": wall, "iterations_mean": float(np.mean(its)), "iterations_max": int(np.max(its)),
            "converged": float(np.mean(conv)), "closure_m": tb.closure_distance(base, q),
            "failed": int(st.work.failed.numpy().sum())}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("scene")
    p.add_argument("--worlds", type=int, default=4)
    p.add_argument("--steps", type=int, default=20)
    p.add_argument("--out", type=pathlib.Path, default=None)
    args = p.parse_args(argv)
    if args.worlds < 1 or args.steps < 1:
        p.error(f"--worlds and --steps must be >= 1, got {args.worlds} and {args.steps}")
    base = load(args.scene)
    records = [measure(base, ls, args.worlds, args.steps) for ls in ("llt", "cr")]
    for r in records:
        print(f"{args.scene} {r['linear_solver']}: {r['rows']} rows, {1e3 * r['s_per_step']:.1f} ms per step, "
              f"{r['iterations_mean']:.2f} PADMM iterations (max {r['iterations_max']}), "
              f"{100 * r['converged']:.0f} % converged, closure {r['closure_m']:.2e} m")
    if args.out:
        args.out.write_text(json.dumps({"scene": args.scene, "records": records}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
