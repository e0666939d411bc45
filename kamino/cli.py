"""``kamino`` command line: ``kamino demo`` simulates the four-bar and reports closure, energy and speed;
``kamino bench`` runs the throughput-against-error benchmark (``benchmarks/throughput.py``)."""

from __future__ import annotations

import argparse
import math
import runpy
import sys
import textwrap
import time
from pathlib import Path

import numpy as np


def demo_steps(seconds: float, dt: float) -> int:
    """The number of steps of a ``seconds``-long demo at time step ``dt``; a ``ValueError`` names the option when
    there would be none."""
    if not (math.isfinite(dt) and dt > 0):
        raise ValueError(f"kamino demo: --dt must be a positive time step in seconds, got {dt:g}")
    if not math.isfinite(seconds) or seconds <= 0:
        raise ValueError(f"kamino demo: --seconds must be a positive duration, got {seconds:g}")
    n = round(seconds / dt)
    if n < 1:
        raise ValueError(f"kamino demo: --seconds {seconds:g} is shorter than one step of --dt {dt:g}")
    return n


def demo(seconds: float = 5.0, dt: float = 1.0 / 240.0, integrator: str = "midpoint") -> dict[str, float]:
    """Simulate ``kamino.models.fourbar()`` and print loop-closure violation, energy drift and step rate."""
    n = demo_steps(seconds, dt)
    import jax

    import kamino

    model = kamino.models.fourbar()
    state = kamino.init_state(model)
    cfg = kamino.SolverConfig(dt=dt, integrator=integrator)
    kamino.rollout(model, state, num_steps=n, config=cfg).body_q.block_until_ready()  # compile
    t0 = time.perf_counter()
    traj = kamino.rollout(model, state, num_steps=n, config=cfg)
    traj.body_q.block_until_ready()
    elapsed = time.perf_counter() - t0
    met = jax.vmap(lambda q, u: kamino.metrics(model, state.replace(body_q=q, body_u=u)))(traj.body_q, traj.body_u)
    e0 = float(kamino.metrics(model, state)["total_energy"][0])
    energy = np.asarray(met["total_energy"])[:, 0]
    peak_ke = float(np.max(met["kinetic_energy"]))
    out = {
        "steps": n,
        "max_loop_closure_violation": float(np.max(met["constraint_violation"])),
        "energy_drift_of_peak_kinetic": float(np.abs(energy - e0).max() / peak_ke),
        "steps_per_second": n / elapsed,
        "mean_padmm_iterations": float(np.mean(traj.info.iterations)),
    }
    print(f"kamino demo: four-bar linkage, {seconds:g} s at dt = {dt:.5g} s ({integrator}, {jax.default_backend()})")
    print(f"  max loop-closure violation : {out['max_loop_closure_violation']:.3e} m")
    print(f"  energy drift               : {100 * out['energy_drift_of_peak_kinetic']:.4f} % of peak kinetic energy")
    print(f"  step rate                  : {out['steps_per_second']:.0f} steps/s (1 world)")
    print(f"  PADMM iterations per step  : {out['mean_padmm_iterations']:.1f}")
    return out


def bench_script() -> Path:
    """``benchmarks/throughput.py`` of the source checkout this package runs from."""
    path = Path(__file__).resolve().parents[1] / "benchmarks" / "throughput.py"
    if not path.is_file():
        raise SystemExit(f"kamino bench: {path} not found; it runs from a source checkout of kamino "
                         "(pip install -e .), where benchmarks/ holds the scenes and the peers' runners")
    return path


#: printed after ``kamino bench --help``: where the method, the scenes and the settings are documented
BENCH_DOCS = ("Documentation (in the repository): docs/architecture.md (\"Performance method\"), "
              "docs/benchmark_scenes.md (the scenes and the peers' figures), docs/settings.md (the solver defaults "
              "and the speed-against-accuracy knob), benchmarks/README.md (the measurements).")


def check_bench_plot(args: list[str]) -> None:
    """``kamino bench --plot`` draws with matplotlib, the ``bench`` extra: without it, exit with a message that
    names the option and the extra before the benchmark script starts."""
    if not any(a == "--plot" or a.startswith("--plot=") for a in args):
        return
    try:
        import matplotlib  # noqa: F401
    except ImportError:
        raise SystemExit("kamino bench: --plot needs matplotlib, which is not installed; install the bench extra: "
                         "pip install 'kamino[bench]' (or pip install -e '.[bench]' in a source checkout)") from None


def bench(args: list[str]) -> int:
    """``kamino bench ARGS``: run ``benchmarks/throughput.py`` with ``ARGS`` (every option is the script's)."""
    check_bench_plot(args)
    script = bench_script()
    from kamino._warp import quiet_warp

    quiet_warp()  # the benchmark imports Warp itself; keep its banner and module-load lines off
    sys.argv = [f"kamino bench ({script})", *args]
    try:
        runpy.run_path(str(script), run_name="__main__")
    except SystemExit:
        if any(a in ("-h", "--help") for a in args):
            print("\n" + textwrap.fill(BENCH_DOCS, 100, break_on_hyphens=False))
        raise
    return 0


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    if argv[:1] == ["bench"]:
        # every option belongs to benchmarks/throughput.py (see `kamino bench --help`)
        return bench(argv[1:])
    parser = argparse.ArgumentParser(prog="kamino", description=__doc__)
    sub = parser.add_subparsers(dest="command", required=True)
    d = sub.add_parser("demo", help="simulate the four-bar linkage and report closure, energy, speed")
    d.add_argument("--seconds", type=float, default=5.0, help="simulated time [s], > 0 (default 5)")
    d.add_argument("--dt", type=float, default=1.0 / 240.0, help="time step [s], > 0 (default 1/240)")
    d.add_argument("--integrator", choices=["euler", "midpoint"], default="midpoint")
    d.add_argument("--x64", action="store_true", help="simulate in float64")
    sub.add_parser("bench", help="GPU throughput against error, with the peers (benchmarks/throughput.py; "
                                 "options: kamino bench --help; method: docs/architecture.md)")
    args = parser.parse_args(argv)
    if args.command == "demo":
        try:
            demo_steps(args.seconds, args.dt)
        except ValueError as e:
            d.error(str(e).removeprefix("kamino demo: "))
        if args.x64:
            import jax

            jax.config.update("jax_enable_x64", True)
        demo(args.seconds, args.dt, args.integrator)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
