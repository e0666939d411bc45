"""Session 33: PADMM iterations and closure of the benchmark scenes standing at rest, warm start at 1.0 and 0.99
(Warp CPU, 4 worlds, float32, ``SolverConfig(dt)`` defaults, 400 steps). Run from the repository root:
``python benchmarks/results/s33_cpu/warmstart_at_rest.py``; output: ``warmstart_at_rest.txt``."""

import sys
from pathlib import Path

import numpy as np
import warp as wp

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))  # benchmarks/, for throughput's scenes
import throughput as tb

import kamino
from kamino.warp_backend import backend as wb
from kamino.warp_backend.pipeline import Stepper

wp.config.quiet = True
for scene in ["fourbar", "ladder8", "dr_legs", "bdx", "olaf"]:
    base = tb.load_scene(scene)[0]
    model = kamino.replicate(base, 4)
    for ws in (1.0, 0.99):
        st = Stepper(model, kamino.SolverConfig(dt=tb.DT, warmstart_scale=ws), np.float32, "cpu", padmm="thread")
        wb.load_state(st, kamino.init_state(model, dtype=np.float32), None)
        its, lam = [], []
        for k in range(400):
            st.run(1)
            its.append(st.work.iters.numpy().copy())
            if k % 100 == 99:
                lam.append(float(np.abs(st.work.kin_force.numpy()).max()))
        q = st.work.q.numpy().view(np.float32).reshape(-1, 7)[: int(base.num_bodies)]
        its = np.array(its)
        print(f"{scene} {ws} iters mean first100 {its[:100].mean():.2f} last300 {its[100:].mean():.2f} max "
              f"{its.max()} max|kin_force| at 100..400: {[f'{x:.3g}' for x in lam]} closure "
              f"{tb.closure_distance(base, q):.2e}", flush=True)
