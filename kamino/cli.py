"""The ``kamino`` command: ``demo`` simulates the four-bar and reports closure, energy and speed; ``train`` trains a
registered environment with Brax's PPO; ``eval`` scores a trained policy; ``export`` writes one as an ONNX
model; ``bench`` measures throughput against error. Each subcommand's options: ``kamino SUBCOMMAND --help``."""

from __future__ import annotations

import argparse
import math
import sys
import time

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


def demo(seconds: float = 5.0, dt: float = 1.0 / 240.0, integrator: str = "midpoint",
         backend: str | None = None) -> dict[str, float]:
    """Simulate ``kamino.models.fourbar()`` on ``backend`` (kamino's default: Warp) and print loop-closure violation,
    energy drift and step rate.

    The first run on a machine compiles the rollout (Warp's kernels, or the JAX reference's XLA program: tens of
    seconds on a CPU); a line on stderr says so (``kamino._progress.announce_compile``), and Warp's kernel cache or
    JAX's compilation cache makes the next run start in seconds."""
    n = demo_steps(seconds, dt)
    import jax

    import kamino
    from kamino._progress import announce_compile

    model = kamino.models.fourbar()
    state = kamino.init_state(model)
    cfg = kamino.SolverConfig(dt=dt, integrator=integrator)
    sim = kamino.Simulator(model, cfg) if backend is None else kamino.Simulator(model, cfg, backend=backend)
    print(f"kamino demo: four-bar linkage, {seconds:g} s at dt = {dt:.5g} s ({integrator}, {sim.backend} backend)",
          flush=True)
    warp_note = "the first run on a machine takes longest; Warp keeps the kernels for later runs"
    with announce_compile("the four-bar's rollout", note=warp_note if sim.backend == "warp" else None):
        sim.rollout(state, num_steps=n).body_q.block_until_ready()
    t0 = time.perf_counter()
    traj = sim.rollout(state, num_steps=n)
    traj.body_q.block_until_ready()
    elapsed = time.perf_counter() - t0
    with announce_compile("the diagnostics"):
        met = jax.device_get(kamino.metrics(model, traj))
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
    print(f"  max loop-closure violation : {out['max_loop_closure_violation']:.3e} m")
    print(f"  energy drift               : {100 * out['energy_drift_of_peak_kinetic']:.4f} % of peak kinetic energy")
    print(f"  step rate                  : {out['steps_per_second']:.0f} steps/s (1 world)")
    print(f"  PADMM iterations per step  : {out['mean_padmm_iterations']:.1f}")
    return out


#: subcommands whose options belong to a library module: name -> (module, one-line help)
DELEGATED = {
    "train": ("kamino.envs.train", "train a registered environment with Brax's PPO (kamino train --help)"),
    "eval": ("kamino.envs.evaluate", "score a trained policy or a shipped one (kamino eval --help)"),
    "export": ("kamino.envs.onnx_export", "write a trained policy as an ONNX model (kamino export --help)"),
    "bench": ("kamino.bench.cli", "throughput against error on the benchmark scenes (kamino bench --help)"),
}


def delegate(command: str, args: list[str]) -> int:
    """Run ``kamino COMMAND ARGS`` through the ``main(argv)`` of the module that owns ``COMMAND``."""
    import importlib

    module = importlib.import_module(DELEGATED[command][0])
    return int(module.main(args) or 0)


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    if argv[:1] and argv[0] in DELEGATED:
        return delegate(argv[0], argv[1:])
    parser = argparse.ArgumentParser(prog="kamino", description=__doc__.replace("``", ""))
    sub = parser.add_subparsers(dest="command", required=True)
    d = sub.add_parser("demo", help="simulate the four-bar linkage and report closure, energy, speed")
    d.add_argument("--seconds", type=float, default=5.0, help="simulated time [s], > 0 (default 5)")
    d.add_argument("--dt", type=float, default=1.0 / 240.0, help="time step [s], > 0 (default 1/240)")
    d.add_argument("--integrator", choices=["euler", "midpoint"], default="midpoint")
    d.add_argument("--x64", action="store_true", help="simulate in float64")
    d.add_argument("--backend", choices=["warp", "jax"], default=None,
                   help="warp (the default: the production backend) or jax (the reference)")
    for name, (_, help_line) in DELEGATED.items():
        sub.add_parser(name, help=help_line, add_help=False)
    args = parser.parse_args(argv)
    if args.command == "demo":
        try:
            demo_steps(args.seconds, args.dt)
        except ValueError as e:
            d.error(str(e).removeprefix("kamino demo: "))
        if args.x64:
            import jax

            jax.config.update("jax_enable_x64", True)
        demo(args.seconds, args.dt, args.integrator, args.backend)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
