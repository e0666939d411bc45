"""LLT against CR on Warp's CPU device (one thread per world), float32, SolverConfig(dt) defaults: wall time per
step, PADMM iterations, converged fraction, closure. python cpu_cross.py SCENE [WORLDS] [STEPS]"""
import sys, time, json
import numpy as np
sys.path.insert(0, "benchmarks")
import warp as wp
wp.config.quiet = True
import kamino
import throughput as tb
from kamino.warp_backend import backend as wb
from kamino.warp_backend.pipeline import Stepper

scene = sys.argv[1]
W = int(sys.argv[2]) if len(sys.argv) > 2 else 4
steps = int(sys.argv[3]) if len(sys.argv) > 3 else 20
if scene.endswith("_rt"):  # an MJCF round trip of a robot (save_mjcf -> load_mjcf)
    import tempfile, pathlib
    base = getattr(kamino.models, scene[:-3])()
    with tempfile.TemporaryDirectory() as d:
        path = pathlib.Path(d) / "m.xml"
        kamino.save_mjcf(base, path)
        base = kamino.load_mjcf(path)
else:
    base, _ = tb.load_scene(scene)
model = kamino.replicate(base, W)
out = {}
for ls in ("llt", "cr"):
    cfg = kamino.SolverConfig(dt=tb.DT, linear_solver=ls)
    st = Stepper(model, cfg, np.float32, "cpu", padmm="thread")
    wb.load_state(st, kamino.init_state(model, dtype=np.float32), None)
    st.run(2)  # compile, warm
    its, conv = [], []
    t0 = time.perf_counter()
    for _ in range(steps):
        st.run(1)
        its.append(st.work.iters.numpy().copy())
        conv.append(st.work.converged.numpy().copy())
    dt = (time.perf_counter() - t0) / steps
    q = st.work.q.numpy().view(np.float32).reshape(-1, 7)[: int(base.num_bodies)]
    out[ls] = {"rows": int(st.wm.max_rows), "s_per_step": dt, "iterations_mean": float(np.mean(its)),
               "iterations_max": int(np.max(its)), "converged": float(np.mean(conv)),
               "closure_m": tb.closure_distance(base, q), "failed": int(st.work.failed.numpy().sum())}
    print(scene, ls, out[ls], flush=True)
json.dump(out, open(f"benchmarks/results/s31_cpu/cross_{scene}.json", "w"), indent=1)
