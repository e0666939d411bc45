import sys, time, pathlib, numpy as np
sys.path.insert(0, "benchmarks")
import throughput as tb
import warp as wp, kamino
from kamino.warp_backend import backend as wb
from kamino.warp_backend.pipeline import Stepper
wp.config.quiet = True
for scene in ["fourbar", "ladder8", "dr_legs", "bdx", "olaf"]:
    base = tb.load_scene(scene)[0]
    model = kamino.replicate(base, 4)
    for ws in (1.0, 0.99):
        st = Stepper(model, kamino.SolverConfig(dt=tb.DT, warmstart_scale=ws), np.float32, "cpu", padmm="thread")
        wb.load_state(st, kamino.init_state(model, dtype=np.float32), None)
        its = []; lam = []
        for k in range(400):
            st.run(1); its.append(st.work.iters.numpy().copy())
            if k % 100 == 99: lam.append(float(np.abs(st.work.kin_force.numpy()).max()))
        q = st.work.q.numpy().view(np.float32).reshape(-1, 7)[: int(base.num_bodies)]
        its = np.array(its)
        print(scene, ws, "iters mean first100 %.2f last300 %.2f max %d" % (its[:100].mean(), its[100:].mean(), its.max()),
              "max|kin_force| at 100..400:", ["%.3g" % x for x in lam], "closure %.2e" % tb.closure_distance(base, q), flush=True)
