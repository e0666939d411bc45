"""Tests run in float64 unless a test asks for float32 (issue 2: "float64 unless stated").

CI time (a 2-core machine, 20-minute budget) goes mostly to XLA compiling the step on the CPU, not to running
it. Two settings cut that without touching what is computed:

- ``--xla_cpu_use_fusion_emitters=false``: XLA's older CPU fusion code generator. Measured on this project's
  pendulum rollout, it compiles in 1.2 s instead of 2.7 s and the gradient in 8 s instead of 12 s. The
  run time of the 5 s animatronic hold stays the same (43 s). No fast-math: the floating-point semantics are
  unchanged. Set only where this XLA still has the flag (probed below).
- ``--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1``: one XLA compute thread per xdist worker
  (CI has two cores and runs two workers). Besides the contention it removes, XLA CPU's multi-threaded Eigen pool
  is reported to wedge on vmapped graphs (a hang at 0 % CPU, jax-ml/jax#25861 and PyAutoFit#1530), the symptom of a
  CI run that stalled at 75 % for 90 minutes.
- A persistent compilation cache under ``.pytest_cache/jax-<worker>``, one per xdist worker. Many tests
  compile the same step (same model, shapes and config) in fresh closures; from the second one on, the
  executable comes from disk. A clean clone starts with an empty cache. Not shared between the workers: since
  the shared cache came in (2026-11-23), a worker has hung at 0 % CPU inside a JAX rollout on three CI runs
  (test_post_stabilisation, test_batching), never in a single-process run; the cause is not proven.
"""

import os
import subprocess
import sys
from pathlib import Path

_FLAG = "--xla_cpu_use_fusion_emitters=false"
_THREADS = "--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1"


def _xla_accepts(flags: str) -> bool:
    """Whether this jaxlib's XLA starts with ``flags``: it aborts on a flag it does not know, and newer XLA
    releases have dropped this one (jax 0.11.2 on the GPU machine). One probe in a subprocess (~2 s), run by
    the first process; the xdist workers inherit the verdict through the environment."""
    env = {**os.environ, "XLA_FLAGS": flags, "JAX_PLATFORMS": "cpu"}
    probe = subprocess.run([sys.executable, "-c", "import jax; jax.numpy.zeros(1).block_until_ready()"], env=env,
                           capture_output=True, check=False)
    return probe.returncode == 0


_user = os.environ.get("XLA_FLAGS", "")
if "xla_cpu_use_fusion_emitters" not in _user and "KAMINO_TEST_XLA_PROBED" not in os.environ:
    os.environ["KAMINO_TEST_XLA_PROBED"] = "1"
    if _xla_accepts(f"{_user} {_FLAG}".strip()):
        _user = f"{_user} {_FLAG}".strip()
    if "multi_thread_eigen" not in _user and _xla_accepts(f"{_user} {_THREADS}".strip()):
        _user = f"{_user} {_THREADS}".strip()
    os.environ["XLA_FLAGS"] = _user

import jax  # noqa: E402  (XLA_FLAGS must be set before the backend starts)
import pytest  # noqa: E402

jax.config.update("jax_enable_x64", True)
# Synchronous CPU dispatch: a JAX computation runs to its end on the calling thread before the next Warp CPU launch.
# With asynchronous dispatch a worker that had run Warp steps deadlocked (0 % CPU) waiting for a JAX reference
# rollout (tests/test_post_stabilisation.py::test_warp_projects_as_the_reference, twice on 2026-11-23; the same
# test passes alone in about a minute); the hang docs/warp_backend.md lists as not understood looks the same.
jax.config.update("jax_cpu_enable_async_dispatch", False)
_WORKER = os.environ.get("PYTEST_XDIST_WORKER", "main")
jax.config.update("jax_compilation_cache_dir",
                  str(Path(__file__).resolve().parents[1] / ".pytest_cache" / f"jax-{_WORKER}"))
jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.3)
jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)


@pytest.fixture(autouse=True, scope="module")
def _release_compiled_steps():
    """After each test module, drop what the module compiled: JAX's in-memory executables and the Warp backend's
    per-model steppers and device models (``kamino.warp_backend.backend.release``). Without this a worker grew to
    6.8 GB over the suite, and workers died mid-run on CI. The on-disk compilation cache still serves later
    modules."""
    yield
    import gc

    from kamino.warp_backend.backend import release

    release()
    jax.clear_caches()
    gc.collect()
