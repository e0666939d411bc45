"""Tests run in float64 unless a test asks for float32 (the reference physics is checked in float64).

CI time (a 2-core machine) goes mostly to XLA compiling the step on the CPU, not to running
it. These settings cut that without touching what is computed:

- ``--xla_cpu_use_fusion_emitters=false``: XLA's older CPU fusion code generator. Measured on this project's
  pendulum rollout, it compiles in 1.2 s instead of 2.7 s and the gradient in 8 s instead of 12 s. The
  run time of the 5 s animatronic hold stays the same (43 s). No fast-math: the floating-point semantics are
  unchanged. Set only where this XLA still has the flag (probed below).
- ``--xla_cpu_multi_thread_eigen=false``: Eigen's own matrix kernels stay on the calling thread (CI has two
  cores and runs two workers).
- ``--xla_backend_optimization_level=0``: LLVM's optimisation passes off in XLA's CPU backend (no fast-math either:
  the floating-point semantics are IEEE's). Compiles take less time and long runs more (the 5 s animatronic hold
  runs twice as long); over the suite it cuts the CPU time by about 17 %. Results change in their last bits, so the
  tests that compare at rounding level with a program compiled at XLA's default level carry the ``default_xla``
  mark and run in a subprocess at the default level (:func:`pytest_pyfunc_call`), with those whose run time
  dominates: the shipped policy's actions against the recorded ones (test_rl_eval.py, to 2e-7), the bitwise check of
  test_redundant_limits.py, and the JAX reference's animatronic hold. The subprocesses that compare two programs
  of their own (test_sharding.py's sharded and unsharded runs) get the default level too
  (``helpers.default_xla_env``). Notebook 05's training runs at level 0: its bar holds there (test_notebooks.py), and
  the notebook takes about 20 s less than in a subprocess at the default level.
- One persistent compilation cache under ``.pytest_cache/jax``, shared by the xdist workers and the subprocesses
  they start. Many tests compile the same step (same model, shapes and config) in fresh closures, often on the
  other worker; from the second one on, the executable comes from disk. A size bound turns on JAX's file lock
  around every read and write of the cache (``jax._src.lru_cache``, the ``filelock`` package), so two processes
  never see each other's half-written entry. A clean clone starts with an empty cache.

CPU deadlock (why pyproject.toml excludes jaxlib 0.10.x and 0.11.0). Workers hung at 0 % CPU inside JAX rollouts
on CI runs (test_post_stabilisation, test_batching), and one died. gdb on a hung worker
(jaxlib 0.10.2, ``tests/test_post_stabilisation.py::test_warp_projects_as_the_reference`` alone in
one process) showed both threads of XLA's intra-op pool inside ``lapack_dpotrf_ffi`` -> ``jax::ParallelBatchMap``
-> ``BlockingCounter::Wait``: two batched Cholesky factorisations ran concurrently, each on a pool thread, each
waiting for batch chunks it had queued on the same, now full, pool. jaxlib 0.10 added that parallel batch path and
0.11.1 compiled it out; 0.9.2 has none (no ``ParallelBatchMap`` symbol in its ``_lapack.so``). On a 2-core machine
the pool has two threads, so two concurrent batched LAPACK calls (the PADMM factorisation and the projection's,
or two worlds' groups) suffice.
"""

import ctypes
import os
import subprocess
import sys
from pathlib import Path

_FLAG = "--xla_cpu_use_fusion_emitters=false"
_THREADS = "--xla_cpu_multi_thread_eigen=false"


def _xla_accepts(flags: str) -> bool:
    """Whether this jaxlib's XLA starts with ``flags``: it aborts on a flag it does not know, and newer XLA
    releases have dropped this one (jax 0.11.2 on the GPU machine). One probe in a subprocess (~2 s), run by
    the first process; the xdist workers inherit the verdict through the environment."""
    env = {**os.environ, "XLA_FLAGS": flags, "JAX_PLATFORMS": "cpu"}
    probe = subprocess.run([sys.executable, "-c", "import jax; jax.numpy.zeros(1).block_until_ready()"], env=env,
                           capture_output=True, check=False)
    return probe.returncode == 0


def _one_core_per_worker() -> None:
    """Pin each xdist worker to its own share of the cores, before jax starts. JAX sizes its CPU thread pool from
    the process's affinity (jax-ml/jax#1539), so two workers on a 2-core machine each ran a pool as wide as the
    machine. XLA:CPU then slowed down far more than 2x when both computed at once: notebook 02's landing rollout
    (14-17 s alone) took 54 s and 387 s beside the animatronic's JAX hold test. The notebook kernels and
    other subprocesses inherit the affinity. The runs on two forced host devices get every core back
    (``helpers.ALL_CORES``): their collectives wait for a thread per device."""
    worker, count = os.environ.get("PYTEST_XDIST_WORKER"), int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "0"))
    if not worker or count < 2 or not hasattr(os, "sched_setaffinity"):
        return
    cpus = sorted(os.sched_getaffinity(0))
    if len(cpus) < count:
        return
    os.environ.setdefault("KAMINO_TEST_ALL_CPUS", ",".join(map(str, cpus)))
    per = len(cpus) // count
    index = int(worker.removeprefix("gw")) % count
    os.sched_setaffinity(0, cpus[index * per:(index + 1) * per])


_one_core_per_worker()
#: XLA's optimisation level of the test processes (module docstring); ``KAMINO_TEST_XLA_DEFAULT=1`` keeps the default
_OPT0 = "--xla_backend_optimization_level=0"
_user = os.environ.get("XLA_FLAGS", "")
if "xla_cpu_use_fusion_emitters" not in _user and "KAMINO_TEST_XLA_PROBED" not in os.environ:
    os.environ["KAMINO_TEST_XLA_PROBED"] = "1"
    _both = f"{_user} {_FLAG} {_THREADS}".strip()
    if "multi_thread_eigen" not in _user and _xla_accepts(_both):  # one probe where XLA knows both flags
        _user = _both
    else:
        if _xla_accepts(f"{_user} {_FLAG}".strip()):
            _user = f"{_user} {_FLAG}".strip()
        if "multi_thread_eigen" not in _user and _xla_accepts(f"{_user} {_THREADS}".strip()):
            _user = f"{_user} {_THREADS}".strip()
    os.environ["XLA_FLAGS"] = _user
if (os.environ.get("KAMINO_TEST_XLA_DEFAULT") != "1" and "xla_backend_optimization_level" not in _user
        and "KAMINO_TEST_XLA_OPT0" not in os.environ):
    os.environ["KAMINO_TEST_XLA_OPT0"] = "1" if _xla_accepts(f"{_user} {_OPT0}".strip()) else "0"
    if os.environ["KAMINO_TEST_XLA_OPT0"] == "1":
        _user = f"{_user} {_OPT0}".strip()
    os.environ["XLA_FLAGS"] = _user

import jax  # noqa: E402  (XLA_FLAGS must be set before the backend starts)
import pytest  # noqa: E402

jax.config.update("jax_enable_x64", True)
# Synchronous CPU dispatch: a JAX computation runs to its end on the calling thread before the next Warp CPU launch.
jax.config.update("jax_cpu_enable_async_dispatch", False)
_JAX_CACHE = Path(__file__).resolve().parents[1] / ".pytest_cache" / "jax"
#: the cache's bound [bytes]: far above what the suite writes; any bound makes JAX lock the cache
_JAX_CACHE_BYTES = 16 * 2**30
jax.config.update("jax_compilation_cache_dir", str(_JAX_CACHE))
jax.config.update("jax_compilation_cache_max_size", _JAX_CACHE_BYTES)
# the same directory and lock for what the tests start in subprocesses (README snippets, notebook kernels, the
# two-device run): kamino's own default (kamino/_jax_cache.py) would write to the user's cache directory
os.environ["KAMINO_JAX_CACHE"] = str(_JAX_CACHE)
os.environ["JAX_COMPILATION_CACHE_MAX_SIZE"] = str(_JAX_CACHE_BYTES)
#: compiles shorter than this [s] are not written to the cache
_JAX_CACHE_MIN_COMPILE_SECS = 0.3
jax.config.update("jax_persistent_cache_min_compile_time_secs", _JAX_CACHE_MIN_COMPILE_SECS)
# the subprocesses too: kamino's own threshold (1 s) left a resumed training (test_rl_resume.py) compiling again
# what the killed run before it had compiled, about 4 s of each warm process
os.environ["JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS"] = str(_JAX_CACHE_MIN_COMPILE_SECS)
jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)


def _return_freed_memory() -> None:
    """Hand the heap's free pages back to the system (glibc's ``malloc_trim``): without it the memory of the
    dropped executables stays resident, and a worker's resident size only ever grows. Nothing happens where the C
    library has no ``malloc_trim``."""
    try:
        ctypes.CDLL(None).malloc_trim(0)
    except (OSError, AttributeError):
        pass


@pytest.fixture(autouse=True, scope="module")
def _release_compiled_steps():
    """After each test module, drop what the module compiled: JAX's in-memory executables, and the simulators
    (Warp steppers, device models) of the module's models, which go with the models (``gc.collect``), and return
    the freed memory to the system. Without this a worker grew to 6.8 GB over the suite, and workers died mid-run on
    CI. The on-disk compilation cache still serves later modules. (Keeping the executables while a worker holds
    under 2 GB saved nothing measurable: the modules hardly share a compiled step.)"""
    yield
    import gc

    jax.clear_caches()
    gc.collect()
    _return_freed_memory()


def _hypothesis_examples_independent_of_imports() -> None:
    """Derandomised Hypothesis draws the same examples in every run only if what it draws from is fixed. Since
    6.131 it also draws literals mined from the project's modules loaded at the time (``_get_local_constants``:
    every module in ``sys.modules`` outside site-packages and the tests). Which of kamino's modules a worker has
    loaded depends on the tests xdist gave it before, so a property test drew other examples in the full suite
    than alone: a CI run failed ``test_cross_backend`` on examples no local run of that file could
    produce. Emptying that pool (the global constants stay: zeros, denormals, extremes of each range) makes the
    examples a function of the test's source only. A Hypothesis without this hook is left as it is."""
    from hypothesis.internal.conjecture import providers

    if callable(getattr(providers, "_get_local_constants", None)) and hasattr(providers, "Constants"):
        empty = providers.Constants()
        providers._get_local_constants = lambda: empty


_hypothesis_examples_independent_of_imports()


#: test modules in descending order of their time on one worker (seconds in a full run on the 2-core machine:
#: envs 244, notebooks 220, robots 177, contacts 123, rl_resume 120, actuation_limits 100, mjcf 95, grad and
#: inverse_kinematics about 90 each, physics 84, cross_backend 84, world_health 83, forward_kinematics 71, first_hour
#: 64, redundant_limits 63; then the modules with one test of 20-61 s: sharding, jansen_walker, refinement,
#: post_stabilisation, batching, rl_eval, fk_robots, design, simulator, solver_settings): collected first, in this
#: order, the rest after them in alphabetical order
_LONG_FIRST = ("test_envs.py", "test_notebooks.py", "test_robots.py", "test_contacts.py", "test_rl_resume.py",
               "test_actuation_limits.py", "test_mjcf.py", "test_grad.py", "test_inverse_kinematics.py",
               "test_physics.py", "test_cross_backend.py", "test_world_health.py", "test_forward_kinematics.py",
               "test_first_hour.py", "test_redundant_limits.py", "test_sharding.py", "test_jansen_walker.py",
               "test_refinement.py", "test_post_stabilisation.py", "test_batching.py", "test_rl_eval.py",
               "test_fk_robots.py", "test_design.py", "test_simulator.py", "test_solver_settings.py")


#: node ids of the tests outside the quick tier that carry no ``slow`` mark in their files (tests/slow_tests.txt)
_SLOW_IDS = frozenset(line.strip() for line in (Path(__file__).parent / "slow_tests.txt").read_text().splitlines()
                      if line.strip() and not line.startswith("#"))


def _mark_listed_slow(config, items) -> None:
    """Mark the tests of ``_SLOW_IDS`` ``slow``. When whole files are collected, a listed test that its file no
    longer has (renamed or removed) is an error, so the list cannot go stale silently."""
    collected = {item.nodeid for item in items}
    if not any("::" in arg for arg in config.args):
        files = {nodeid.split("::")[0] for nodeid in collected}
        stale = sorted(i for i in _SLOW_IDS if i.split("::")[0] in files and i not in collected)
        if stale:
            raise pytest.UsageError(f"tests/slow_tests.txt lists tests that do not exist: {stale}")
    for item in items:
        if item.nodeid in _SLOW_IDS:
            item.add_marker(pytest.mark.slow)


def pytest_collection_modifyitems(config, items) -> None:
    """Mark the listed slow tests (``_mark_listed_slow``), then order the test modules longest first
    (``_LONG_FIRST``). xdist hands tests out in collection order; started first, the long ones overlap with the many
    short tests, and the last tests to finish are short. The order within a module is kept (a stable sort), and each
    worker sorts the same way. (Handing out whole modules instead, xdist's ``loadfile``, made the suite 40 s slower
    on the 2-core machine: 1125 s against 1085 s.)"""
    _mark_listed_slow(config, items)
    rank = {name: i for i, name in enumerate(_LONG_FIRST)}
    items.sort(key=lambda item: rank.get(item.path.name, len(_LONG_FIRST)))


def pytest_configure(config: pytest.Config) -> None:
    config.addinivalue_line("markers", "default_xla: runs in a subprocess at XLA's default optimisation level "
                                       "(tests/conftest.py)")


@pytest.hookimpl(tryfirst=True)
def pytest_pyfunc_call(pyfuncitem: pytest.Function):
    """A ``default_xla`` test, in a process whose XLA runs at optimisation level 0: run it in a pytest subprocess at
    XLA's default level instead, and fail with its output if it fails there."""
    if pyfuncitem.get_closest_marker("default_xla") is None or _OPT0 not in os.environ.get("XLA_FLAGS", ""):
        return None
    from tests.helpers import default_xla_env

    root = Path(__file__).resolve().parents[1]
    proc = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-p", "no:xdist",
                           "--durations=0", pyfuncitem.nodeid], cwd=root, env=default_xla_env(), capture_output=True,
                          text=True, check=False)
    if proc.returncode != 0:
        pytest.fail(f"{pyfuncitem.nodeid} at XLA's default optimisation level:\n{proc.stdout[-6000:]}"
                    f"{proc.stderr[-3000:]}", pytrace=False)
    return True
