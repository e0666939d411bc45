"""GPU-only checks of the Warp backend: CUDA-graph capture with ``wp.capture_while``, zero-copy JAX interop.

Run on the lent GPU with ``python -m pytest -m gpu``; skipped where Warp sees no CUDA device.
"""

import subprocess
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import warp as wp

import kamino
from kamino.bench import scene_path
from kamino.warp_backend import backend as wb
from kamino.warp_backend.workspace import saturated_rows
from tests.helpers import jax_on_gpu

pytestmark = [pytest.mark.gpu,
              pytest.mark.skipif(not wp.is_cuda_available(), reason="needs a CUDA device for Warp")]


@pytest.mark.skipif(not jax_on_gpu(), reason="needs JAX on the GPU")
def test_from_jax_shares_the_device_pointer():
    state = kamino.init_state(kamino.models.fourbar(), jnp.float32)
    arr = wp.from_jax(state.body_q, dtype=wp.transformf)
    assert arr.ptr == state.body_q.unsafe_buffer_pointer()  # the same device memory: no copy
    assert arr.device.is_cuda


def test_a_captured_step_replays_the_uncaptured_one():
    model = kamino.replicate(kamino.load_mjcf(scene_path("fourbar")), 64)
    state = kamino.init_state(model, jnp.float32)
    cfg = kamino.SolverConfig(dt=0.0025)
    ctrl = kamino.Control.from_ctrl(model, np.full(model.num_actuators, 1.5, np.float32))
    graphed = wb.Stepper(model, cfg, np.float32, "cuda:0")
    plain = wb.Stepper(model, cfg, np.float32, "cuda:0")
    plain.use_graph = False
    for st in (graphed, plain):
        wb.load_state(st, state, ctrl)
        st.run(5)
    assert 5 in graphed._graphs  # the 5 steps were captured once (PADMM inside via capture_while)
    wp.synchronize_device("cuda:0")
    # same kernels, same order; the chunked capture_while loop stops each world at the same iteration
    np.testing.assert_allclose(graphed.work.q.numpy(), plain.work.q.numpy(), atol=1e-6)
    np.testing.assert_array_equal(graphed.work.iters.numpy(), plain.work.iters.numpy())
    graphed.run(5)  # a replay continues from the new state
    assert float(graphed.work.time.numpy()[0]) == pytest.approx(10 * 0.0025, rel=1e-5)


@pytest.mark.skipif(not jax_on_gpu(), reason="needs JAX on the GPU")
def test_gpu_backends_agree_and_results_stay_on_the_gpu():
    model = kamino.models.fourbar()
    state = kamino.init_state(model, jnp.float32)
    cfg = kamino.SolverConfig(dt=1 / 240)
    a = kamino.rollout(model, state, num_steps=50, config=cfg, backend="warp")
    b = kamino.rollout(model, state, num_steps=50, config=cfg, backend="jax")
    assert all(d.platform == "gpu" for d in a.body_q.devices())
    # float32 on both sides; 50 steps of a chaotic-free four-bar: rounding-level differences (measured 2e-6)
    assert float(jnp.max(jnp.abs(a.body_q - b.body_q))) < 1e-4


@pytest.mark.skipif(not jax_on_gpu(), reason="needs JAX on the GPU")
def test_jitted_warp_step_on_the_gpu_matches_the_eager_one():
    model = kamino.replicate(kamino.models.fourbar(), 32)
    state = kamino.init_state(model, jnp.float32)
    cfg = kamino.SolverConfig(dt=1 / 240)
    step = jax.jit(lambda s: kamino.step(model, s, config=cfg, backend="warp"))
    a = step(step(state))
    b = kamino.step(model, kamino.step(model, state, config=cfg, backend="warp"), config=cfg, backend="warp")
    # the eager path replays a captured graph (chunked PADMM loop), the jitted one launches the same kernels
    # without capture: the same arithmetic
    np.testing.assert_allclose(np.asarray(a.body_q), np.asarray(b.body_q), atol=1e-6)


@pytest.mark.skipif(not jax_on_gpu(), reason="needs JAX on the GPU")
def test_the_traced_step_replays_its_graph_with_the_launches_results():
    """Inside ``jax.jit`` the FFI call replays the step's CUDA graph (its PADMM loop a ``capture_while`` of chunks,
    the factor of the worlds whose effort-limited rows saturated redone after each chunk); the launches without a
    graph (one per possible switch) must give the same iterations and states. dr_legs with targets 0.6 rad off:
    300 N m/rad asks for 180 N m of its 80 N m limits, so rows saturate and switch."""
    model = kamino.replicate(kamino.models.dr_legs(), 16)
    state = kamino.init_state(model, jnp.float32)
    cfg = kamino.SolverConfig(dt=0.004)
    act = np.asarray(model.dof_act_mode) == int(kamino.ActuationMode.POSITION)
    target = np.where(act, np.random.default_rng(0).choice([-0.6, 0.6], model.num_dofs), 0.0).astype(np.float32)
    ctrl = kamino.Control(position_target=jnp.asarray(target))
    step = jax.jit(lambda s: kamino.step(model, s, ctrl, config=cfg, backend="warp"))
    a = state
    iters = []
    for _ in range(5):
        a = step(a)
        iters.append(np.asarray(a.info.iterations))
    traced = kamino.simulator.simulator_of(model, cfg, "warp", "step").engine.stepper(np.float32, "cuda:0",
                                                                                       for_jit=True)
    assert traced.captured(1) is not None  # the FFI call's stepper replayed the captured step
    plain = wb.Stepper(model, cfg, np.float32, "cuda:0")
    plain.use_graph = False
    wb.load_state(plain, state, ctrl)
    plain_iters = []
    for _ in range(5):
        plain.run(1)
        plain_iters.append(plain.work.iters.numpy().copy())
    assert saturated_rows(plain.work.row_info.numpy()).any()  # effort-limited rows saturated: the switch path ran
    np.testing.assert_array_equal(np.stack(iters), np.stack(plain_iters))
    # the same kernels in the same order on the same data: rounding-level differences at most
    np.testing.assert_allclose(np.asarray(a.body_q), plain.work.q.numpy(), atol=1e-5)


def test_precompile_covers_every_module_a_captured_step_launches(monkeypatch):
    # on CUDA the modules compile in parallel (wp.force_load's thread pool), and the step is a captured graph
    from tests.test_warp_pipeline import assert_precompile_covers_a_step

    assert_precompile_covers_a_step("cuda:0", monkeypatch)


@pytest.mark.skipif(not jax_on_gpu(), reason="needs JAX on the GPU")
def test_a_step_compiled_in_the_background_captures_its_graph_on_the_gpu():
    # test_warp_pipeline's background-compile test in a fresh process, so that Warp's CUDA context is not yet
    # acquired when the worker thread starts (compile_in_background's docstring: a worker that acquires it itself
    # leaves the traced step's graph capture unregistered, and wp.capture_while fails mid-capture)
    node = "tests/test_warp_pipeline.py::test_a_step_compiled_in_the_background_is_the_one_a_vmap_steps_with"
    run = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", node],
                         capture_output=True, text=True, check=False, cwd=Path(__file__).parent.parent)
    assert run.returncode == 0, run.stdout[-3000:] + run.stderr[-3000:]
