"""The Jansen walker (``kamino.models.jansen_walker``): many redundant planar loops on a free chassis, driven.

- Four legs (12 loops, 1.5 s, float32, ``SolverConfig(dt=1/240)``): the Warp sparse LLT converges on every step and
  keeps the loops closed; the Conjugate Residual path at 100 iterations walks the same distance; the JAX
  reference (slow tier: XLA's compile) walks it too.
- Eight legs in four crank phases (the default walker, 24 loops, 1.5 s): the JAX reference, the Warp sparse LLT and
  CR at 100 iterations, one rollout each shared by the asserts (a module fixture): convergence, loop closure,
  no failed world, and the walked distance against the reference's.
- The backends on identical problems (in the eight-legged LLT and CR tests): the reference's states as one world
  each (``kamino.replicate``), stepped once by Warp's sparse LLT and CR against the reference's own step from them:
  the same convergence and, within 20 %, the same mean PADMM iterations (the issue's bars).
- Eight legs in two crank phases with thin links (2 s): the JAX reference, CR (at its default 100 iterations) and the
  Warp LLT walk it; Delassus entries taken from one side only (``J_a M^-1 J_b^T``) stall the LLT there
  (docs/warp_backend.md, "Redundant planar loops in float32").
- Eight legs (24 loops): no step reports a healthy world whose loops are open past 1 mm (world health,
  ``kamino.warp_backend.integrate.LOOP_OPEN_BOUND``): a world either keeps its loops closed or is flagged failed on
  the step they open.
- The GPU tier: the eight-legged walker for 6 s on every ``linear_solver`` against the JAX reference there, and
  the backends on 1440 identical problems of that walk, the dense LLT included.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import warp as wp

import kamino
from kamino.model import fingerprint
from kamino.state import bind
from kamino.warp_backend.integrate import LOOP_OPEN_BOUND
from tests.helpers import JAX, JAX_GPU_TIER, WARP_SPARSE_CR, WARP_SPARSE_LLT, Variant, variant_param

DT = 1.0 / 240.0


def _drive(model: kamino.Model, seconds: float) -> kamino.Control:
    """The crank's velocity target ramping to 0.5 rev/s in 1 s, then held."""
    n = round(seconds / DT)
    target = np.zeros((n, model.num_dofs), np.float32)
    target[:, int(model.actuator_dof[0])] = np.pi * np.minimum(DT * np.arange(1, n + 1), 1.0)
    return kamino.Control(velocity_target=jnp.asarray(target))


def _walk(variant: Variant, legs: int, seconds: float, phases: int | None = None,
          **model_args) -> dict:
    """A ``seconds`` walk on ``variant``: per-step arrays (``converged``, ``failed``, ``iterations``, ``closure``,
    ``gap``, the chassis' ``x``), the distance ``walked``, and the ``model``, its ``drive`` and the trajectory
    ``traj`` the walk took."""
    model = kamino.models.jansen_walker(legs=legs, phases=phases, **model_args)
    s0 = kamino.init_state(model, jnp.float32)
    drive = _drive(model, seconds)
    tr = variant.rollout(model, s0, drive, config=kamino.SolverConfig(dt=DT))
    q = np.asarray(tr.body_q)
    met = kamino.metrics(model, tr)
    return {"converged": np.asarray(tr.info.converged)[:, 0], "failed": np.asarray(tr.info.failed)[:, 0],
            "iterations": np.asarray(tr.info.iterations)[:, 0],
            "closure": np.asarray(met["constraint_violation"])[:, 0], "gap": np.asarray(met["anchor_gap"])[:, 0],
            "x": q[:, 0, 0] - float(s0.body_q[0, 0]), "walked": q[-1, 0, 0] - float(s0.body_q[0, 0]),
            "model": model, "drive": drive, "traj": tr}


def _states_as_worlds(walk: dict, steps: np.ndarray) -> tuple[kamino.Model, kamino.State, kamino.Control]:
    """The problems the walk's steps ``steps + 1`` posed, as one world each: ``len(steps)`` copies of the walker
    (``kamino.replicate``), the trajectory's states after ``steps`` as their batched state (every leaf: poses,
    twists, the warm start's forces, the contacts, the adaptive penalty), and the drive of the step that follows
    each. One step of this batch solves, in world ``i``, exactly what step ``steps[i] + 1`` of the walk solved."""
    steps = np.asarray(steps)
    n = len(steps)
    model = kamino.replicate(walk["model"], n)
    pick = jax.tree.map(lambda a: jnp.asarray(np.asarray(a)[steps].reshape((n * a.shape[1], *a.shape[2:]))),
                        walk["traj"])
    state = bind(pick, fingerprint(model))
    control = kamino.Control(velocity_target=jnp.asarray(np.asarray(walk["drive"].velocity_target)[steps + 1]
                                                         .reshape(-1)))
    return model, state, control


def _solve_once(variant: Variant, problems: tuple[kamino.Model, kamino.State, kamino.Control]) -> dict:
    """One step of every world of ``problems`` on ``variant``: its per-world ``converged``, ``failed`` and
    ``iterations``."""
    model, state, control = problems
    out = variant.step(model, state, control, config=kamino.SolverConfig(dt=DT))
    return {"converged": np.asarray(out.info.converged), "failed": np.asarray(out.info.failed),
            "iterations": np.asarray(out.info.iterations)}


def _assert_same_convergence(r: dict, ref: dict) -> None:
    """The issue's bars for two backends on the same problems: each converges on at least 99 % of them, the
    converged shares differ by less than 1 %, and the mean PADMM iterations by less than 20 %."""
    share, share_ref = r["converged"].mean(), ref["converged"].mean()
    mean, mean_ref = r["iterations"].mean(), ref["iterations"].mean()
    assert not r["failed"].any() and not ref["failed"].any()
    assert share >= 0.99 and share_ref >= 0.99, (share, share_ref)
    assert abs(share - share_ref) < 0.01, (share, share_ref)
    assert abs(mean - mean_ref) < 0.2 * mean_ref, (mean, mean_ref)


#: every state of a walk: 360 problems of the 1.5-s walk, 1440 of the 6-s walk. The issue's bar of 99 % converged is
#: on the walk's steps; a sample of them (every 2nd or 4th) can hold more of the walk's few unconverged steps than
#: its share (two of 180 where the walk converges on over 99 %)
_EVERY = 1


def _assert_converges_as_the_reference_on_its_states(variant: Variant, ref: dict) -> None:
    """``variant`` against the reference on identical problems: every state of the reference's walk ``ref`` as
    one world each, stepped once on ``variant``, under the issue's bars (:func:`_assert_same_convergence`). The
    reference's own step from each state is its walk's next step, so both backends solve the same problems (the
    reference's one step from the same states, in a batch, takes its walk's count on 99.7 % of them: the 6-s walk's
    states, measured on the CPU). A walk per backend would not compare them: foot contact makes the walk chaotic,
    and two walks pose different problems within seconds."""
    steps = np.arange(0, len(ref["iterations"]) - 1, _EVERY)
    r = _solve_once(variant, _states_as_worlds(ref, steps))
    _assert_same_convergence(r, {key: ref[key][steps + 1] for key in ("converged", "failed", "iterations")})


#: the four-legged walk, measured (CPU, float32, 1.5 s): the sparse LLT 100 % converged at 3.3 iterations, closure
#: 5.9e-6 m, 0.690 m; CR at 100 iterations 100 % at 3.3 iterations, closure 5.6e-6 m, 0.690 m
_LLT_WALK = {}

@pytest.mark.parametrize("variant", [variant_param(WARP_SPARSE_LLT), variant_param(WARP_SPARSE_CR),
                                     variant_param(JAX)])
def test_four_legged_walker_walks_with_its_loops_closed(variant):
    """Four legs, 1.5 s: no failed world; the chassis walks 0.6-0.8 m forward (+x: a positive crank velocity);
    the sparse LLT (and the JAX reference) converge on at least 99 % of the steps with every loop closed to 2e-5 m
    (post-stabilisation; float32 rounding of ~1 m coordinates is ~1e-7 m, the worst step measured 5.9e-6 m); CR
    at 100 iterations per PADMM iteration on at least 90 % (measured 100 %) with loops closed
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


@pytest.fixture(scope="module")
def eight_legs():
    """``walk(variant, seconds=1.5)``: the default eight-legged walker (four phases) driven for ``seconds`` on
    ``variant``, computed once per variant and duration in the module."""
    done: dict[tuple[str, float], dict[str, np.ndarray]] = {}

    def walk(variant: Variant, seconds: float = 1.5) -> dict[str, np.ndarray]:
        key = (variant.id, seconds)
        if key not in done:
            done[key] = _walk(variant, legs=8, seconds=seconds)
        return done[key]

    return walk


def test_eight_legged_walker_reference_walks_with_its_loops_closed(eight_legs):
    """The JAX reference, eight legs in four phases, 1.5 s: no failed world, at least 99 % of the steps converged,
    every loop closed to 1e-5 m (measured: 100 % at 7.4 iterations, 8.5e-6 m), and 0.5-0.65 m walked towards +x
    (measured 0.573 m)."""
    r = eight_legs(JAX)
    assert not r["failed"].any()
    assert r["converged"].mean() >= 0.99, r["converged"].mean()
    assert r["closure"].max() <= 1e-5, r["closure"].max()
    assert 0.5 < r["walked"] < 0.65, r["walked"]


def test_eight_legged_walker_llt_solves_what_the_reference_solves(eight_legs):
    """The Warp sparse LLT, eight legs in four phases, 1.5 s, against the JAX reference: no failed world, at least
    99 % of the steps converged, every loop closed to 1e-5 m, and the walked distance within 5 % of the reference's
    (measured: 100 % at 6.8 iterations, 7.7e-6 m, 0.571 m against 0.573 m). The trajectories part over seconds of
    contact (3.67 m against 3.41 m after 6 s), so the horizon is short. On the reference's own states (360 problems,
    one step each) the LLT converges as the reference does (the issue's bars,
    :func:`_assert_converges_as_the_reference_on_its_states`; measured: both 100 % at 6.71 iterations, the same
    count on 98 % of the problems)."""
    r = eight_legs(WARP_SPARSE_LLT)
    ref = eight_legs(JAX)
    assert not r["failed"].any()
    assert r["converged"].mean() >= 0.99, r["converged"].mean()
    assert r["closure"].max() <= 1e-5, r["closure"].max()
    assert abs(r["walked"] - ref["walked"]) <= 0.05 * abs(ref["walked"]), (r["walked"], ref["walked"])
    _assert_converges_as_the_reference_on_its_states(WARP_SPARSE_LLT, ref)


def test_eight_legged_walker_cr_at_100_iterations(eight_legs):
    """Conjugate Residual at 100 iterations per PADMM iteration, eight legs in four phases,
    1.5 s: no failed world, the walked distance within 5 % of the reference's, at least 99 % of the steps converged
    with every joint row closed to 2e-5 (m or rad; measured: 100 % at 7.9 iterations, every row within 7.7e-6,
    anchors within 1.4e-6 m, 0.573 m against 0.573 m). At 30 iterations 100 % converged at 14.9 iterations (hinge rows
    within 1.2e-5 rad), at 9 iterations 92.5 % (1.4e-5): an inexact inner solve adds its residual to PADMM's dual
    residual (``solver.padmm_iterate``), so PADMM iterates until the solves are accurate, or reports the step
    unconverged. On the reference's own states (360 problems, one step each) CR converges as the reference does (the
    issue's bars, :func:`_assert_converges_as_the_reference_on_its_states`; measured: 100 % at 7.48 iterations
    against 6.71; at 30 CR iterations 17.7, which fails the 20 % bar)."""
    r = eight_legs(WARP_SPARSE_CR)
    ref = eight_legs(JAX)
    assert not r["failed"].any()
    assert r["converged"].mean() >= 0.99, r["converged"].mean()
    assert r["closure"].max() <= 2e-5, r["closure"].max()
    assert abs(r["walked"] - ref["walked"]) <= 0.05 * abs(ref["walked"]), (r["walked"], ref["walked"])
    _assert_converges_as_the_reference_on_its_states(WARP_SPARSE_CR, ref)


@pytest.mark.parametrize("variant", [
    # the reference in the gpu tier (19 s of CI): the Warp variants are what this case guards, and the reference walks
    # the eight-legged walker in CI above
    variant_param(JAX, marks=JAX_GPU_TIER),
    variant_param(WARP_SPARSE_CR),
    variant_param(WARP_SPARSE_LLT)])
def test_eight_legged_walker_in_two_phases_walks(variant):
    """Eight legs in two crank phases (two mirrored pairs per phase) with thin links (``radius=0.01``: their spin
    about their own axis makes the lightest rows, the hard case for float32), 2 s: no failed world, at least 99 % of
    the steps converged, anchors within 1e-4 m, at least 1 m walked. With Delassus entries taken from one side
    (``J_a M^-1 J_b^T``), the Warp LLT stalls here at 1.21 s and fails the world (docs/warp_backend.md, "Redundant
    planar loops in float32"). Measured: the JAX reference 100 % at 9.2 iterations, 1.87e-5 m, 1.019 m; the sparse
    LLT 100 % at 9.8, 1.72e-5 m, 1.019 m. CR (100 iterations): at 30, behind the warm-start filter
    (docs/conventions.md, "Warm start"), 98.96 % of its steps converged."""
    r = _walk(variant, legs=8, seconds=2.0, phases=2, radius=0.01)
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
@pytest.mark.parametrize(("legs", "linear_solver"),
                         [(4, "auto"), (4, "llt"), (4, "cr"), (8, "auto"), (8, "llt"), (8, "cr")])
def test_walker_on_the_gpu(legs, linear_solver):
    """On the GPU (JAX and Warp there; ``auto`` takes the 32-lane sparse LLT), every ``linear_solver``: the
    four-legged walk of the CPU test (no failed world, 0.6-0.8 m, at least 90 % converged with the loops closed to
    1e-4 m), and the eight-legged walker never reports open loops as healthy."""
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


def _solver_variant(linear_solver: str) -> Variant:
    """The Warp variant of a ``linear_solver`` setting: ``dense`` the dense LLT, ``cr`` Conjugate Residual (at its
    default 100 iterations), else the sparse Jacobian with that solver."""
    if linear_solver == "dense":
        return Variant("warp-dense-llt", "warp", "dense", "llt")
    if linear_solver == "cr":
        return WARP_SPARSE_CR
    return Variant(f"warp-{linear_solver}", "warp", "sparse", linear_solver)


#: the steps of the first 1.5 s, over which the backends' walks agree to 2 %
_EARLY = round(1.5 / DT)


@pytest.mark.gpu
@pytest.mark.skipif(not wp.is_cuda_available(), reason="needs a CUDA device for Warp")
@pytest.mark.parametrize("linear_solver", ["auto", "llt", "cr"])  # the dense LLT: 6 s take over 15 min there
def test_eight_legged_walker_for_6_s_on_the_gpu(linear_solver, eight_legs):
    """On the GPU, the default eight-legged walker (four phases) for 6 s on the sparse ``linear_solver`` choices
    (``auto`` and ``llt``: the 32-lane sparse LLT) against the JAX reference there: no failed world; the LLT
    converges on at least 99 % of the steps with every loop closed to 1e-5 m, as the reference does; CR at 100
    iterations on at least 99 % with the anchors closed to 1e-5 m and every row to 3e-5 (its hinge rows,
    in rad). The walked distance is within 5 % of the
    reference's after 1.5 s and within 15 % after 6 s: foot contact makes the walk chaotic, and a start 1 or 2 mrad
    of crank angle apart moves the 6-s distance by up to 11 % on either backend. Measured on an H200: the reference
    99.93 %, 7.9e-6 m, 3.10 m; the 32-lane LLT 99.86 %, 8.5e-6 m, 3.27 m (1.60e-5 m, one step after a foot lands,
    without post-stabilisation's pass for a gap left open, ``REPROJECTION_GAP``); CR at 30 iterations 99.65 %,
    anchors 2.8e-6 m, hinge rows 1.35e-5 rad, 3.59 m. On the CPU: the reference 100 %, 8.5e-6 m, 0.573 m and 3.41 m
    (3.04 and 3.36 m from the perturbed starts); the sparse LLT 99.65 % at 8.9 iterations, 9.5e-6 m, 0.571 m and
    3.67 m; CR at 100 iterations 99.93 % at 8.1, every row within 7.7e-6 (anchors 1.9e-6 m), 0.573 m and
    3.63 m (at 30 iterations: 99.79 % at 17.9, hinge rows 1.4e-5 rad, anchors 2.5e-6 m, 0.579 m and 3.64 m)."""
    if not any(d.platform == "gpu" for d in jax.devices()):
        pytest.skip("needs JAX on the GPU")
    variant = _solver_variant(linear_solver)
    r = eight_legs(variant, seconds=6.0)
    ref = eight_legs(JAX, seconds=6.0)
    assert not ref["failed"].any() and not r["failed"].any()
    assert ref["converged"].mean() >= 0.99, ref["converged"].mean()
    if linear_solver == "cr":
        assert r["converged"].mean() >= 0.99, r["converged"].mean()
        assert r["gap"].max() <= 1e-5, r["gap"].max()
        assert r["closure"].max() <= 3e-5, r["closure"].max()
    else:
        assert r["converged"].mean() >= 0.99, r["converged"].mean()
        assert r["closure"].max() <= 1e-5, r["closure"].max()
    early, early_ref = r["x"][_EARLY - 1], ref["x"][_EARLY - 1]
    assert abs(early - early_ref) <= 0.05 * abs(early_ref), (early, early_ref)
    assert abs(r["walked"] - ref["walked"]) <= 0.15 * abs(ref["walked"]), (r["walked"], ref["walked"])


@pytest.fixture(scope="module")
def same_states_on_the_gpu(eight_legs):
    """Every state of the reference's 6-s walk on the GPU as one world each (1440 problems), and the reference's
    own step of them there (JAX on the GPU)."""
    if not any(d.platform == "gpu" for d in jax.devices()):
        pytest.skip("needs JAX on the GPU")
    walk = eight_legs(JAX, seconds=6.0)
    problems = _states_as_worlds(walk, np.arange(0, len(walk["iterations"]) - 1, _EVERY))
    return problems, _solve_once(JAX, problems)


@pytest.mark.gpu
@pytest.mark.skipif(not wp.is_cuda_available(), reason="needs a CUDA device for Warp")
@pytest.mark.parametrize("linear_solver", ["auto", "llt", "dense", "cr"])
def test_eight_legged_walker_converges_as_the_reference_on_its_states_on_the_gpu(linear_solver,
                                                                                  same_states_on_the_gpu):
    """On the GPU (JAX and Warp there), the backends on identical problems: every state of the reference's 6-s
    walk (eight legs, four phases, float32, its contacts included), 1440 worlds stepped once by the reference and
    once by Warp on each ``linear_solver`` (``auto`` and ``llt``: the 32-lane sparse LLT; ``dense``: the dense LLT,
    one thread per world; ``cr`` at 100 iterations). The issue's bars: both converge on at least 99 % of the
    problems, the shares differ by under 1 %, and the mean PADMM iterations by under 20 %. Measured on the CPU, on
    the reference's 6-s walk there: every solver 100 % converged; the reference 7.70 iterations (its walk's own count
    on 99.7 % of the problems), the sparse LLT 7.69 (the reference's count on 97 %), CR 8.35 (at 30 iterations:
    16.4); on every 16th state, the reference 6.80 and the dense LLT 6.81 (0.6 s a world there)."""
    problems, ref = same_states_on_the_gpu
    variant = _solver_variant(linear_solver)
    _assert_same_convergence(_solve_once(variant, problems), ref)
