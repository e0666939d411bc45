"""Where a step's time goes: the Warp kernels of one step, timed one by one (CUDA events, Warp's timing API), for a
scene at its defaults, after a warm-up run, on both PADMM schedules from the same state.

    kamino bench profile_step --scene dr_legs --worlds 4096 --warmup 100 --steps 10 [--padmm thread warp] [--load rl]
        [--solver reduction=schur]

The worlds are :mod:`kamino.bench.convergence`'s (distinct drive phases; ``--load phases``) or the throughput
benchmark's under one of its loads (``--load gentle`` or ``rl``, :mod:`kamino.bench.loads`), run ``--warmup`` steps
with the CUDA graph of the first schedule; that state is copied, and each schedule then steps ``--steps`` times from
it without a graph (each kernel launched and timed alone; the PADMM loop is one launch that runs every world to
convergence). Reported per kernel: milliseconds per step, launches per step; per schedule: the PADMM iterations of the
worlds (mean, p99, max of the profiled steps), and the step time from a graph replay of the same steps (what the
throughput figures time). JSON with ``--out``; a table on stdout.
"""

import argparse
import json
import math
import pathlib
import sys
import time
from collections import defaultdict

import numpy as np

import kamino
from kamino.bench import loads
from kamino.bench.convergence import SCENES, drive_hook, perturb


def _stepper(model, scene, padmm, device, solver: dict):
    from kamino.warp_backend import backend as wb
    from kamino.warp_backend.pipeline import Stepper

    cfg = kamino.SolverConfig(dt=scene.dt).replace(**solver)
    st = Stepper(model, cfg, np.float32, device, padmm=padmm)
    st.pre_step.clear()
    st.invalidate_graphs()
    control = (kamino.Control(position_target=np.zeros(model.num_dofs, np.float32))
               if scene.drive == "targets" else None)
    wb.load_state(st, kamino.init_state(model, np.float32), control)
    phase = 2.0 * math.pi * np.arange(model.num_worlds) / model.num_worlds
    if scene.drive:
        st.pre_step.append(drive_hook(st, model, scene.drive, phase))
    else:
        perturb(st, model, phase)
    return st


def _copy_state(dst, src) -> None:
    """Every array of ``src.work`` into ``dst.work`` (same model, same shapes): the same state for both schedules."""
    import warp as wp

    for name in dir(src.work):
        a, b = getattr(src.work, name, None), getattr(dst.work, name, None)
        if isinstance(a, wp.array) and isinstance(b, wp.array) and a.shape == b.shape and a.dtype == b.dtype:
            wp.copy(b, a)


def profile(st, steps: int) -> dict:
    """Kernel times of ``steps`` un-graphed steps, then the graph replay of as many steps from the same state."""
    import warp as wp

    saved = {k: wp.clone(v) for k, v in vars(st.work).items() if isinstance(v, wp.array)}
    use_graph = st.use_graph
    st.use_graph = False
    iters = []
    wp.synchronize_device(st.device)
    wp.timing_begin(cuda_filter=wp.TIMING_KERNEL)
    for _ in range(steps):
        st.launch_step()
        iters.append(st.work.iters.numpy().copy())
    results = wp.timing_end()
    st.use_graph = use_graph
    per = defaultdict(lambda: [0.0, 0])
    for r in results:
        name = r.name.split("__locals__")[-1].rsplit("_", 1)[0] if "__locals__" in r.name else r.name
        per[name][0] += r.elapsed / steps
        per[name][1] += 1
    kernels = {k: {"ms_per_step": v[0], "launches_per_step": v[1] / steps} for k, v in per.items()}
    it = np.concatenate(iters)
    for k, v in saved.items():  # the same steps again, replayed as one CUDA graph
        wp.copy(getattr(st.work, k), v)
    graph_s = None
    if st.device.is_cuda:
        st.run(steps)  # capture
        for k, v in saved.items():
            wp.copy(getattr(st.work, k), v)
        wp.synchronize_device(st.device)
        t0 = time.perf_counter()
        st.run(steps)
        wp.synchronize_device(st.device)
        graph_s = (time.perf_counter() - t0) / steps
    return {"kernels": kernels, "kernel_ms_per_step": sum(v["ms_per_step"] for v in kernels.values()),
            "iterations": {"mean": float(it.mean()), "p99": float(np.percentile(it, 99)), "max": int(it.max())},
            "graph_step_time_s": graph_s,
            "graph_world_steps_per_s": (st.wm.num_worlds / graph_s) if graph_s else None}


def main(argv: list[str] | None = None, prog: str | None = None) -> int:
    """``kamino bench profile_step ARGS`` (``prog`` names the command in the help and errors); 0 when done."""
    p = argparse.ArgumentParser(prog=prog, description=__doc__.split("\n\n")[0],
                                epilog="What is measured: help(kamino.bench.profile_step).")
    p.add_argument("--scene", default="dr_legs", choices=sorted(SCENES))
    p.add_argument("--load", default="phases", choices=["phases", *loads.LOADS],
                   help="phases: kamino.bench.convergence's drives; gentle, rl: kamino.bench.loads (phases)")
    p.add_argument("--worlds", type=int, default=4096)
    p.add_argument("--warmup", type=int, default=100)
    p.add_argument("--steps", type=int, default=10)
    p.add_argument("--padmm", nargs="+", default=["thread", "warp"], choices=["thread", "warp"])
    p.add_argument("--solver", nargs="+", default=[], metavar="F=V",
                   help="SolverConfig settings by their dotted names (kamino bench's --solver): reduction=schur")
    p.add_argument("--out", type=pathlib.Path)
    args = p.parse_args(argv)
    import warp as wp

    from kamino.bench import throughput

    solver = throughput.solver_overrides(args.solver)

    device = wp.get_device()
    if args.load == "phases":
        scene = SCENES[args.scene]
        model = kamino.replicate(scene.build(), args.worlds)
        steppers = [_stepper(model, scene, padmm, device, solver) for padmm in args.padmm]
    else:
        if args.scene not in {*throughput.SCENES, *throughput.ROBOTS}:
            p.error(f"--load {args.load}: --scene must be a throughput scene, one of "
                    f"{sorted({*throughput.SCENES, *throughput.ROBOTS})}")
        throughput.SOLVER.clear()
        throughput.SOLVER.update(solver)
        steppers = [throughput.warp_stepper(args.scene, "default", args.worlds, args.load, padmm=padmm)[0]
                    for padmm in args.padmm]
    steppers[0].run(args.warmup)
    for st in steppers[1:]:
        _copy_state(st, steppers[0])
    rec = {"scene": args.scene, "load": args.load, "num_worlds": args.worlds, "warmup_steps": args.warmup,
           "device": str(device.name), "rows_max": steppers[0].wm.max_rows, "solver": solver, "schedules": {}}
    for padmm, st in zip(args.padmm, steppers, strict=True):
        rec["schedules"][padmm] = profile(st, args.steps)
    for padmm, r in rec["schedules"].items():
        print(f"\n{args.scene} x{args.worlds} after {args.warmup} steps, padmm={padmm}: kernels "
              f"{r['kernel_ms_per_step']:.3f} ms/step, graph {1e3 * (r['graph_step_time_s'] or 0):.3f} ms/step "
              f"({r['graph_world_steps_per_s'] or 0:.3g} world-steps/s), iterations {r['iterations']}")
        for k, v in sorted(r["kernels"].items(), key=lambda kv: -kv[1]["ms_per_step"])[:14]:
            print(f"  {k:32s} {v['ms_per_step']:9.3f} ms  x{v['launches_per_step']:.0f}")
    if args.out:
        args.out.write_text(json.dumps(rec, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
