"""The Jansen walker (``kamino.models.jansen_walker``): many redundant planar loops on a free chassis, driven.

- Four legs (12 loops, 1.5 s, float32, ``SolverConfig(dt=1/240)``): the Warp sparse LLT converges on every step and
  keeps the loops closed; the Conjugate Residual path at its default budget walks the same distance; the JAX
  reference (slow tier: XLA's compile) walks it too.
- Eight legs in two crank phases (24 loops, 2 s): the JAX reference and CR at 30 iterations walk it; the Warp LLT
  solves stall at 1.21 s (a strict xfail stating what is measured).
- Eight legs (24 loops): no step reports a healthy world whose loops are open past 1 mm (world health,
  ``kamino.warp_backend.integrate.LOOP_OPEN_BOUND``): a world either keeps its loops closed or is flagged failed on
  the step they open.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import warp as wp

import kamino
from kamino.warp_backend.integrate import LOOP_OPEN_BOUND
from tests.helpers import JAX, WARP_SPARSE_CR, WARP_SPARSE_LLT, Variant, variant_param

DT = 1.0 / 240.0


def _drive(model: kamino.Model, seconds: float) -> kamino.Control:
    """The crank's velocity target ramping to 0.5 rev/s in 1 s, then held."""
    n = round(seconds / DT)
    target = np.zeros((n, model.num_dofs), np.float32)
    target[:, int(model.actuator_dof[0])] = np.pi * np.minimum(DT * np.arange(1, n + 1), 1.0)
    return kamino.Control(velocity_target=jnp.asarray(target))


def _walk(variant: Variant, legs: int, seconds: float, phases: int | None = None) -> dict[str, np.ndarray]:
    model = kamino.models.jansen_walker(legs=legs, phases=phases)
    s0 = kamino.init_state(model, jnp.float32)
    tr = variant.rollout(model, s0, _drive(model, seconds), config=kamino.SolverConfig(dt=DT))
    q = np.asarray(tr.body_q)
    return {"converged": np.asarray(tr.info.converged)[:, 0], "failed": np.asarray(tr.info.failed)[:, 0],
            "closure": np.asarray(kamino.metrics(model, tr)["constraint_violation"])[:, 0],
            "walked": q[-1, 0, 0] - float(s0.body_q[0, 0])}


#: the four-legged walk, measured (CPU, float32, 1.5 s): the sparse LLT 100 % converged at 3.3 iterations, closure
#: 1.14e-5 m, 0.690 m; CR at 9 iterations 96.1 % at 18.4 iterations, closure 5.2e-5 m, 0.693 m
_LLT_WALK = {}


@pytest.mark.parametrize("variant", [variant_param(WARP_SPARSE_LLT), variant_param(WARP_SPARSE_CR),
                                     variant_param(JAX)])
def test_four_legged_walker_walks_with_its_loops_closed(variant):
    """Four legs, 1.5 s: no failed world; the chassis walks 0.6-0.8 m forward (+x: a positive crank velocity);
    the sparse LLT (and the JAX reference) converge on at least 99 % of the steps with every loop closed to 2e-5 m
    (post-stabilisation; float32 rounding of ~1 m coordinates is ~1e-7 m, the worst step measured 1.14e-5 m); CR
    at its default budget of 9 iterations per PADMM iteration on at least 90 % (measured 96.1 %) with loops closed
    to 1e-4 m, and within 5 % of the sparse LLT's distance."""
    r = _walk(variant, legs=4, seconds=1.5)
    assert not r["failed"].any()
    assert 0.6 < r["walked"] < 0.8, r["walked"]
    if variant.is_cr:
        assert r["converged"].mean() >= 0.90, r["converged"].mean()
        assert r["closure"].max() <= 1e-4
        ref = _LLT_WALK.get("walked") or _walk(WARP_SPARSE_LLT, legs=4, seconds=1.5)["walked"]
        assert abs(r["walked"] - ref) <= 0.05 * abs(ref)
    else:
        assert r["converged"].mean() >= 0.99, r["converged"].mean()
        assert r["closure"].max() <= 2e-5, r["closure"].max()
        if variant.id == WARP_SPARSE_LLT.id:
            _LLT_WALK["walked"] = r["walked"]


@pytest.mark.parametrize("variant", [
    variant_param(JAX),
    variant_param(Variant("warp-sparse-cr30", "warp", "sparse", "cr", cr_iterations=30)),
    pytest.param(WARP_SPARSE_LLT, id=WARP_SPARSE_LLT.id, marks=pytest.mark.xfail(strict=True, reason=(
        "from the state after step 290 (1.21 s) the JAX reference converges in 8 iterations and CR (30) in 16, while "
        "the Warp LLT solves (sparse and dense factor alike) keep the dual residual at 2e-3 from their second "
        "iteration on, run 200 iterations, drive the penalty to its minimum and fail the world at 1.23 s. The factor "
        "solves its assembled matrix as accurately as a dense float32 Cholesky; in float64 the same Warp step "
        "converges in 8 iterations with the reference's residuals and penalty, and with rho_free = 1e-3 in 9: "
        "float32 Delassus entries 1.1e-5 off their float64 values, a tenth of the proximal shift that alone keeps the "
        "redundant rows definite")))])
def test_eight_legged_walker_in_two_phases_walks(variant):
    """Eight legs in two crank phases (two mirrored pairs per phase), 2 s: no failed world, at least 99 % of the
    steps converged, anchors within 1e-4 m, at least 1 m walked (measured: the JAX reference 100 % at 10.6
    iterations, 1.87e-5 m, 1.711 m in 3 s; CR at 30 iterations 99.8 % at 9.5, 4.7e-5 m, 1.03 m in 2 s)."""
    r = _walk(variant, legs=8, seconds=2.0, phases=2)
    assert not r["failed"].any()
    assert r["converged"].mean() >= 0.99, r["converged"].mean()
    assert r["closure"].max() <= 1e-4, r["closure"].max()
    assert r["walked"] >= 1.0, r["walked"]


def test_eight_legged_walker_never_reports_open_loops_as_healthy():
    """Eight legs on the sparse LLT, 1.2 s: on every step either the world is healthy with its loops closed to
    ``LOOP_OPEN_BOUND`` (1 mm), or it is flagged failed, from that step on (frozen at its last state)."""
    r = _walk(WARP_SPARSE_LLT, legs=8, seconds=1.2)
    healthy = ~r["failed"]
    assert np.all(r["closure"][healthy] <= LOOP_OPEN_BOUND), r["closure"][healthy].max()
    first = np.flatnonzero(r["failed"])
    if len(first):
        assert r["failed"][first[0]:].all()
        assert r["closure"][first[0]:].max() <= LOOP_OPEN_BOUND  # frozen before its loops opened


@pytest.mark.gpu
@pytest.mark.skipif(not wp.is_cuda_available(), reason="needs a CUDA device for Warp")
@pytest.mark.parametrize(("legs", "linear_solver"), [(4, "auto"), (4, "llt"), (4, "cr"), (8, "auto"), (8, "llt")])
def test_walker_on_the_gpu(legs, linear_solver):
    """On the GPU (JAX and Warp there; ``auto`` takes the 32-lane sparse LLT), every ``linear_solver``: the
    four-legged walk of the CPU test (no failed world, 0.6-0.8 m, at least 90 % converged with the loops closed to
    1e-4 m), and the eight-legged walker never reports open loops as healthy (on the LLT paths: CR runs one
    thread per world, about 2 steps/s on this walker on an H200)."""
    if not any(d.platform == "gpu" for d in jax.devices()):
        pytest.skip("needs JAX on the GPU")
    variant = Variant(f"warp-{linear_solver}", "warp", "sparse", linear_solver)
    r = _walk(variant, legs=legs, seconds=1.5 if legs == 4 else 1.2)
    if legs == 4:
        assert not r["failed"].any()
        assert 0.6 < r["walked"] < 0.8, r["walked"]
        assert r["converged"].mean() >= 0.90, r["converged"].mean()
        assert r["closure"].max() <= 1e-4
    else:
        assert np.all(r["closure"][~r["failed"]] <= LOOP_OPEN_BOUND)
