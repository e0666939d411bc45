"""Small utilities shared by the tests."""

from __future__ import annotations

import dataclasses
import os

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import kamino


def trajectory_metrics(model: kamino.Model, state: kamino.State, traj: kamino.State) -> dict[str, np.ndarray]:
    """``kamino.metrics`` on every state of a rollout trajectory: arrays ``[T, num_worlds]``."""
    out = jax.vmap(lambda q, u: kamino.metrics(model, state.replace(body_q=q, body_u=u)))(traj.body_q, traj.body_u)
    return {k: np.asarray(v) for k, v in out.items()}


def trajectory_joint_positions(model: kamino.Model, state: kamino.State, traj: kamino.State) -> np.ndarray:
    """``kamino.joint_positions`` on every state of a trajectory: ``[T, num_coords]``."""
    return np.asarray(jax.vmap(lambda q: kamino.joint_positions(model, state.replace(body_q=q)))(traj.body_q))


def default_xla_env(env: dict | None = None) -> dict:
    """``env`` (``os.environ`` by default) for a subprocess at XLA's default optimisation level: without the level-0
    flag that tests/conftest.py gives the test processes, and marked so that a pytest subprocess keeps it off."""
    env = dict(os.environ if env is None else env)
    flags = [f for f in env.get("XLA_FLAGS", "").split() if not f.startswith("--xla_backend_optimization_level")]
    env["XLA_FLAGS"] = " ".join(flags)
    env["KAMINO_TEST_XLA_DEFAULT"] = "1"
    return env


#: first lines of a subprocess script that needs every core back (before it imports jax): conftest pins each xdist
#: worker to its share of the cores, and a run on two forced host devices needs a thread per device (their
#: collectives wait for each other). Source, not a ``preexec_fn``: forking a multithreaded process to run Python
#: in the child can deadlock.
ALL_CORES = """import os
if os.environ.get("KAMINO_TEST_ALL_CPUS") and hasattr(os, "sched_setaffinity"):
    os.sched_setaffinity(0, [int(c) for c in os.environ["KAMINO_TEST_ALL_CPUS"].split(",")])
"""


# ---------------------------------------------------------------------------------------------
# Backends: every physics test runs on the JAX reference and on the three Warp solver configurations
# ---------------------------------------------------------------------------------------------

@dataclasses.dataclass(frozen=True)
class Variant:
    """One backend / solver configuration a physics test runs on.

    ``config`` merges the variant's ``jacobian`` / ``linear_solver`` into a test's :class:`kamino.SolverConfig`
    (the JAX reference is dense + Cholesky only: its variant leaves the config as the test wrote it);
    ``step`` / ``rollout`` call the public API with ``backend=``.
    """

    id: str
    backend: str
    jacobian: str = "dense"
    linear_solver: str = "llt"
    #: CR budget per PADMM iteration (``SolverConfig.warp.cr_iterations``); ``None``: the config's (default 100)
    cr_iterations: int | None = None

    @property
    def is_warp(self) -> bool:
        return self.backend == "warp"

    @property
    def is_cr(self) -> bool:
        return self.is_warp and self.linear_solver == "cr"

    def config(self, cfg: kamino.SolverConfig | None = None, **changes) -> kamino.SolverConfig:
        cfg = (cfg or kamino.SolverConfig()).replace(**changes)
        if self.is_warp:
            cfg = cfg.replace(**{"warp.jacobian": self.jacobian, "warp.linear_solver": self.linear_solver})
        if self.is_cr and self.cr_iterations is not None:
            cfg = cfg.replace(**{"warp.cr_iterations": self.cr_iterations})
        return cfg

    def step(self, model: kamino.Model, state: kamino.State, control: kamino.Control | None = None, *,
             config: kamino.SolverConfig | None = None) -> kamino.State:
        return kamino.step(model, state, control, config=self.config(config), backend=self.backend)

    def rollout(self, model: kamino.Model, state: kamino.State, controls: kamino.Control | None = None, *,
                num_steps: int | None = None, config: kamino.SolverConfig | None = None) -> kamino.State:
        """``kamino.rollout`` on this variant's backend: the trajectory (leading time axis).

        Warp variants take the eager rollout: it writes its trajectory into buffers allocated once and compiles
        nothing for a new length (test_cross_backend.py::test_eager_warp_rollout_length_compiles_nothing),
        and runs a small model at ~1.3 ms per step where the rollout inside ``jax.jit`` takes ~2.3 ms (pendulum,
        500 steps, float64) plus a compile for every model, length and closure (measured: the Warp tests of
        test_contacts.py take 17 CPU-s eager against 34 jitted). The jitted rollout gives the same bits
        (test_cross_backend.py::test_jitted_warp_rollout_is_bitwise_the_eager_one).
        """
        return kamino.rollout(model, state, controls, num_steps=num_steps, config=self.config(config),
                              backend=self.backend)


JAX = Variant("jax", "jax")
WARP_DENSE_LLT = Variant("warp-dense-llt", "warp", "dense", "llt")
WARP_SPARSE_LLT = Variant("warp-sparse-llt", "warp", "sparse", "llt")
WARP_SPARSE_CR = Variant("warp-sparse-cr", "warp", "sparse", "cr")
WARP_VARIANTS = (WARP_DENSE_LLT, WARP_SPARSE_LLT, WARP_SPARSE_CR)
VARIANTS = (JAX, *WARP_VARIANTS)


def tier_marks(v: Variant) -> list:
    """The JAX reference's variant of a physics test is in the ``slow`` tier (``pytest -m slow``; README.md, under
    the test command).

    Its cost is XLA compiling the step on the CPU (10-20 s a test against 1-3 s for a Warp variant: 920 of 3728
    worker-seconds of a CI run). The default tier still checks
    the reference: the cross-backend tests compare every Warp variant with it step by step
    (tests/test_cross_backend.py), and the environments, gradients and sharding tests run it."""
    return [pytest.mark.slow] if not v.is_warp else []


def jax_on_gpu() -> bool:
    """Whether JAX runs on a GPU: the JAX reference's longest runs are in the gpu tier (``pytest -m gpu``), where
    they take seconds; on the 2-core CPU machine of CI they take tens of seconds each."""
    return any(d.platform == "gpu" for d in jax.devices())


#: the marks of a test (or a test's JAX variant) that runs in the gpu tier only: it needs JAX on the GPU
JAX_GPU_TIER = (pytest.mark.gpu, pytest.mark.skipif(not jax_on_gpu(), reason="needs JAX on the GPU (gpu tier)"))


def variant_param(v: Variant, *, id: str | None = None, marks: tuple = ()):
    """``pytest.param(v)`` with the variant's tier mark (:func:`tier_marks`): how a test that picks its own variants
    parametrizes over them."""
    return pytest.param(v, id=id or v.id, marks=[*marks, *tier_marks(v)])


#: ``@pytest.mark.parametrize("variant", BACKENDS)``: the four variants every physics test runs on (the JAX one in
#: the slow tier)
BACKENDS = [variant_param(v) for v in VARIANTS]
#: the three Warp solver configurations (cross-backend tests)
WARP_BACKENDS = [pytest.param(v, id=v.id) for v in WARP_VARIANTS]


def backends(*, xfail_cr: str | None = None) -> list:
    """:data:`BACKENDS`, with the ``warp-sparse-cr`` variant marked ``xfail(strict=True, reason=xfail_cr)``
    (a limitation of the Conjugate Residual path measured on that test, stated in ``xfail_cr``)."""
    out = []
    for v in VARIANTS:
        marks = [pytest.mark.xfail(strict=True, reason=xfail_cr)] if (xfail_cr and v.is_cr) else []
        out.append(variant_param(v, marks=tuple(marks)))
    return out


def spinning_chain(model: kamino.Model, state: kamino.State, rates: tuple[float, ...]) -> kamino.State:
    """``state`` with the first ``len(rates)`` bodies, a ``serial_chain`` from the world's pivot, turning about
    their hinges (world y) at ``rates`` [rad/s], the joints' velocity constraints met."""
    q, u = np.asarray(state.body_q), np.array(state.body_u)
    anchor, v_anchor = q[0, :3] - np.array([0.05, 0.0, 0.0]), np.zeros(3)  # the pivot, half a link before link 0
    for k, rate in enumerate(rates):
        w = np.array([0.0, rate, 0.0])
        u[k, :3], u[k, 3:] = v_anchor + np.cross(w, q[k, :3] - anchor), w
        v_anchor = v_anchor + np.cross(w, 2.0 * (q[k, :3] - anchor))
        anchor = 2.0 * q[k, :3] - anchor
    return state.replace(body_u=jnp.asarray(u, state.body_u.dtype))


#: a 4-link chain whose links turn at up to 200 rad/s relative to each other (0.8 rad per step at the default dt)
SPIN_RATES = (0.0, 100.0, -150.0, 200.0)


def stepper_delassus(st, n: int, rs: int = 1) -> np.ndarray:
    """World 0's Delassus matrix ``D = J M^-1 J^T + R`` (docs/formulation.md §7.1) on the first ``n`` rows of a Warp
    stepper (``kamino.warp_backend.pipeline.Stepper``; rows ``rs`` apart in its work arrays), in float64 from the
    stepper's row Jacobian blocks, regularisation and world-frame inverse inertias: the matrix its factor assembles."""
    w, m, nblk = st.work, st.wm.arrays, st.wm.blocks_per_row
    J = w.row_J.numpy().astype(np.float64).reshape(-1, nblk, 6)[: n * rs : rs]
    body = w.row_body.numpy().reshape(-1, nblk)[: n * rs : rs]
    reg = w.reg.numpy().astype(np.float64)[: n * rs : rs]
    nb = st.wm.max_bodies
    Minv = np.zeros((nb, 6, 6))
    Minv[:, :3, :3] = m.inv_mass.numpy()[:nb, None, None] * np.eye(3)
    Minv[:, 3:, 3:] = w.inv_inertia_w.numpy().reshape(-1, 3, 3)[:nb]
    Jd = np.zeros((n, nb, 6))
    for a in range(n):
        for k in range(nblk):
            if body[a, k] >= 0:
                Jd[a, body[a, k]] += J[a, k]
    return np.einsum("abi,bij,cbj->ac", Jd, Minv, Jd) + np.diag(reg)
