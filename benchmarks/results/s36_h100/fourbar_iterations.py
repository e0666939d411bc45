"""Session 36: where the four-bar's PADMM iterations go (benchmarks/README.md, "Session 36"). One world of the
benchmark's four-bar (`throughput.warp_stepper`, the defaults, Warp CPU), 120 steps from rest; for steps 55-115 it
prints the iterations, the active limit rows and rows, the limit/contact penalty `rho_u`, the iteration of the step's
last penalty change (`k_rho`) and the largest twist component. Run from the repository root; output:
`fourbar_iterations.txt`."""
import sys

import numpy as np

sys.path.insert(0, "benchmarks")
import throughput as T

st, state, control = T.warp_stepper("fourbar", "default", 1)
w = st.work
for k in range(120):
    st.run(1)
    if 55 <= k <= 115:
        print(k, int(w.iters.numpy()[0]), "n_lim", int(w.n_lim.numpy()[0]), "n_rows", int(w.n_rows.numpy()[0]),
              "rho", round(float(w.rho_u.numpy()[0]), 3), "k_rho", int(w.k_rho.numpy()[0]),
              "u_max", round(float(np.abs(w.u.numpy()).max()), 2))
