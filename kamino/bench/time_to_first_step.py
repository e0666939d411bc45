"""Time to first step: the wall time from ``import kamino`` to the first completed ``kamino.step``, the first
``kamino.rollout`` of ``--steps`` steps, and the first ``jax.jit``-wrapped rollout, each in a fresh Python process (so
nothing compiled in memory helps), with JAX's persistent compilation cache cold (an empty directory) and then warm (the
same directory, a second process).

    kamino bench time_to_first_step [--models fourbar dr_legs humanoid10] [--entries step rollout jit_rollout]
                                    [--backend warp] [--worlds 1] [--steps 100] [--cpus 0] [--out results.json]

Each (model, entry) gets its own empty temporary cache directory, passed to the child through ``KAMINO_JAX_CACHE``
(kamino/_jax_cache.py); ``--phases`` adds ``off`` (``KAMINO_JAX_CACHE=0``: no persistent cache at all). A child times,
from just before ``import kamino``: the import, building the model (``humanoid10`` is the shipped scene
kamino/bench/scenes/humanoid10.xml through ``kamino.load_mjcf``), ``init_state``, and the first call until its result is
ready (``block_until_ready``); then a second, identical call (the run time alone, compiled). JAX's own monitoring events
split the first call into XLA's compilation (or the load from the persistent cache) and the rest: Python (tracing,
lowering to MLIR, kamino's checks and padded layout) and the run. ``--backend`` picks the backend of the timed calls
(``warp``, kamino's default, or ``jax``, the reference); the Warp backend's kernels come from Warp's own kernel cache,
which this benchmark does not empty. The defaults are a user's: float32, no XLA flags (``--xla-flags`` passes some, e.g.
``--xla_cpu_use_fusion_emitters=false`` as tests/conftest.py does), every CPU (``--cpus 0`` pins the children to one: on
a shared machine XLA's threads otherwise stall each other, docs/first_step.md). Results: docs/first_step.md.
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import platform
import subprocess
import sys
import tempfile
import time

# Only the standard library at the top: a child runs this file by path and times ``import kamino`` itself.
HERE = pathlib.Path(__file__).resolve().parent
SCENES = HERE / "scenes"
MODELS = ("fourbar", "dr_legs", "humanoid10")
ENTRIES = ("step", "rollout", "jit_rollout")


def _child(model_name: str, entry: str, worlds: int, steps: int, cpus: list[int] | None = None,
           backend: str = "warp") -> dict:
    """Runs in the fresh process: the timings of one entry point, as a dict (printed as JSON by ``main``)."""
    if cpus:  # before jax starts: XLA sizes its CPU thread pool from the affinity mask
        os.sched_setaffinity(0, set(cpus))
    t0 = time.perf_counter()
    import jax

    durations: dict[str, float] = {}
    counts: dict[str, int] = {}
    try:  # JAX's monitoring: where the first call's time goes; absent or renamed events just leave zeros
        from jax import monitoring

        def on_duration(event, secs, **_):
            durations[event] = durations.get(event, 0.0) + float(secs)

        def on_event(event, **_):
            counts[event] = counts.get(event, 0) + 1

        monitoring.register_event_duration_secs_listener(on_duration)
        monitoring.register_event_listener(on_event)
    except Exception as exc:  # report, keep timing
        print(f"no JAX monitoring events ({type(exc).__name__}: {exc})", file=sys.stderr)

    import kamino

    t_import = time.perf_counter()
    if model_name == "humanoid10":
        model = kamino.load_mjcf(SCENES / "humanoid10.xml")
    else:
        model = getattr(kamino.models, model_name)()
    if worlds > 1:
        model = kamino.replicate(model, worlds)
    t_model = time.perf_counter()
    state = kamino.init_state(model)
    jax.block_until_ready(state)
    t_state = time.perf_counter()
    durations.clear()
    counts.clear()

    if entry == "step":
        def call(s):
            return kamino.step(model, s, backend=backend)
    elif entry == "rollout":
        def call(s):
            return kamino.rollout(model, s, num_steps=steps, backend=backend)
    elif entry == "jit_rollout":
        call = jax.jit(lambda s: kamino.rollout(model, s, num_steps=steps, backend=backend))
    else:
        raise ValueError(f"unknown entry {entry!r}; choose from {ENTRIES}")

    out = jax.block_until_ready(call(state))
    t_first = time.perf_counter()
    first_events = dict(durations)
    first_counts = dict(counts)
    out = jax.block_until_ready(call(state))
    t_second = time.perf_counter()

    from kamino import _jax_cache

    def ev(*names):
        return round(sum(v for k, v in first_events.items() if any(k.endswith(n) for n in names)), 3)

    cache_dir = jax.config.jax_compilation_cache_dir
    entries = sorted(pathlib.Path(cache_dir).glob("*-cache")) if cache_dir else []
    return {
        "model": model_name, "entry": entry, "worlds": worlds, "steps": steps if entry != "step" else 1,
        "bodies_per_world": int(model.num_bodies // model.num_worlds),
        "rows_per_world_max": int(model.num_constraints // model.num_worlds),
        "import_s": round(t_import - t0, 3),
        "model_s": round(t_model - t_import, 3),
        "init_state_s": round(t_state - t_model, 3),
        "first_call_s": round(t_first - t_state, 3),
        "to_first_result_s": round(t_first - t0, 3),
        "second_call_s": round(t_second - t_first, 3),
        "python_s": round(max(0.0, (t_first - t_state) - ev("/jax/core/compile/backend_compile_duration")
                              - (t_second - t_first)), 3),
        # JAX's trace events nest (a jit inside a jit reports its own trace inside its caller's): a sum over them
        # counts time twice; python_s below is the first call less the XLA compile (or cache load) and the run
        "trace_events_s": ev("/jax/core/compile/jaxpr_trace_duration"),
        "lower_s": ev("/jax/core/compile/jaxpr_to_mlir_module_duration"),
        # XLA's compile, or the load from the persistent cache on a hit (JAX times both as one event)
        "xla_compile_s": ev("/jax/core/compile/backend_compile_duration"),
        "cache_load_s": ev("/jax/compilation_cache/cache_retrieval_time_sec"),
        "cache_hits": sum(v for k, v in first_counts.items() if k.endswith("/jax/compilation_cache/cache_hits")),
        "cache_misses": sum(v for k, v in first_counts.items() if k.endswith("/jax/compilation_cache/cache_misses")),
        "cache_dir": cache_dir,
        "cache_choice": _jax_cache.choice.source if _jax_cache.choice else None,
        "cache_entries": len(entries),
        "cache_bytes": sum(p.stat().st_size for p in entries),
        "finite": bool(jax.numpy.all(jax.numpy.isfinite(out.body_q))),
        "cpus": sorted(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else None,
        "jax": jax.__version__,
        "backend": jax.default_backend(),
        "kamino_backend": backend,
    }


def _run_child(model: str, entry: str, worlds: int, steps: int, cache: str, xla_flags: str, timeout: float,
               cpus: list[int] | None, backend: str) -> dict:
    env = dict(os.environ)
    env["KAMINO_JAX_CACHE"] = cache
    env.pop("JAX_COMPILATION_CACHE_DIR", None)  # kamino's variable decides (kamino/_jax_cache.py)
    if xla_flags:
        env["XLA_FLAGS"] = f"{env.get('XLA_FLAGS', '')} {xla_flags}".strip()
    cmd = [sys.executable, str(pathlib.Path(__file__).resolve()), "--child", model, entry, "--worlds", str(worlds),
           "--steps", str(steps), "--backend", backend] + (["--cpus", *map(str, cpus)] if cpus else [])
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=timeout, check=False)
    wall = time.perf_counter() - t0
    lines = [line for line in proc.stdout.splitlines() if line.startswith("RESULT ")]
    if proc.returncode != 0 or not lines:
        raise RuntimeError(f"{model}/{entry} child failed (rc {proc.returncode}):\n{proc.stderr[-3000:]}")
    result = json.loads(lines[-1][len("RESULT "):])
    result["process_wall_s"] = round(wall, 3)  # interpreter start to exit, for reference
    return result


def _machine() -> dict:
    cpu = platform.processor()
    try:
        for line in pathlib.Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    load = os.getloadavg() if hasattr(os, "getloadavg") else None
    return {"cpu": cpu, "cpu_count": os.cpu_count(), "platform": platform.platform(),
            "python": platform.python_version(), "loadavg_at_start": load}


def _table(rows: list[dict]) -> str:
    head = ("model", "worlds", "entry", "phase", "to first result [s]", "import", "model + init_state",
            "first call", "of which XLA compile / cache load", "Python (trace, lower)", "second call", "cache entries")
    lines = [" | ".join(head), " | ".join("---" for _ in head)]
    for r in rows:
        lines.append(" | ".join(str(x) for x in (
            r["model"], r["worlds"], r["entry"], r["phase"], f"{r['to_first_result_s']:.1f}", f"{r['import_s']:.1f}",
            f"{r['model_s'] + r['init_state_s']:.1f}", f"{r['first_call_s']:.1f}", f"{r['xla_compile_s']:.1f}",
            f"{r['python_s']:.1f}", f"{r['second_call_s']:.2f}", r["cache_entries"])))
    return "\n".join(f"| {line} |" for line in lines)


def main(argv: list[str] | None = None, prog: str | None = None) -> int:
    """``kamino bench time_to_first_step ARGS`` (``prog`` names the command in the help and errors); 0 when done."""
    ap = argparse.ArgumentParser(prog=prog, description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--child", nargs=2, metavar=("MODEL", "ENTRY"), help=argparse.SUPPRESS)
    ap.add_argument("--models", nargs="+", default=list(MODELS), choices=MODELS)
    ap.add_argument("--entries", nargs="+", default=list(ENTRIES), choices=ENTRIES)
    ap.add_argument("--phases", nargs="+", default=["cold", "warm"], choices=("cold", "warm", "off"),
                    help="cold: empty cache directory; warm: the same directory again; off: KAMINO_JAX_CACHE=0")
    ap.add_argument("--worlds", type=int, default=1, help="kamino.replicate(model, WORLDS)")
    ap.add_argument("--backend", choices=("warp", "jax"), default="warp",
                    help="the backend= of the timed calls (default warp, kamino's default)")
    ap.add_argument("--steps", type=int, default=100, help="steps of the rollouts")
    ap.add_argument("--xla-flags", default="", help="added to XLA_FLAGS in the children")
    ap.add_argument("--timeout", type=float, default=1800.0, help="seconds per child process")
    ap.add_argument("--cpus", type=int, nargs="+", help="pin the children to these CPUs (os.sched_setaffinity, before "
                    "jax starts): --cpus 0 runs XLA on one thread (docs/first_step.md, shared machines)")
    ap.add_argument("--out", type=pathlib.Path, help="write the results as JSON here")
    args = ap.parse_args(argv)

    if args.child:
        print("RESULT " + json.dumps(_child(args.child[0], args.child[1], args.worlds, args.steps, args.cpus,
                                            args.backend)), flush=True)
        return 0

    machine = _machine()
    print(f"# {machine['cpu']}, {machine['cpu_count']} CPUs, load {machine['loadavg_at_start']}", flush=True)
    rows = []
    for model in args.models:
        for entry in args.entries:
            with tempfile.TemporaryDirectory(prefix="kamino-ttfs-") as tmp:
                for phase in args.phases:
                    cache = "0" if phase == "off" else tmp
                    r = _run_child(model, entry, args.worlds, args.steps, cache, args.xla_flags, args.timeout,
                                   args.cpus, args.backend)
                    r["phase"] = phase
                    rows.append(r)
                    print(f"{model:>10} x{args.worlds} {entry:>11} {phase:>4}: {r['to_first_result_s']:7.1f} s to the "
                          f"first result (XLA {r['xla_compile_s']:.1f} s, Python {r['python_s']:.1f} s, cache "
                          f"load {r['cache_load_s']:.2f} s; 2nd call {r['second_call_s']:.2f} s)", flush=True)
    print()
    print(_table(rows))
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        doc = {"command": " ".join([os.path.basename(sys.executable), *sys.argv]), "machine": machine,
               "date": time.strftime("%Y-%m-%d %H:%M:%S %Z"), "xla_flags": args.xla_flags, "cpus": args.cpus,
               "results": rows}
        args.out.write_text(json.dumps(doc, indent=1) + "\n")
        print(f"\nwrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
