"""Simulation throughput over 1..n devices of one host: worlds sharded over the devices (kamino/sharding.py).

    kamino bench multi_device [--scenes dr_legs ladder8] [--worlds-per-device 4096] [--devices 1 2]
                              [--backend warp] [--out FILE]

Weak scaling, the figure an RL user needs: ``--worlds-per-device`` worlds on each device, so ``k`` devices step
``k`` times the worlds. For each ``k``: the scene replicated ``k * N`` times, its state placed with
``kamino.sharding.shard_worlds`` on the first ``k`` devices, and blocks of ``--block`` steps run by
``kamino.sharding.sharded_program`` (a scan of the group model's ``Simulator.step`` under ``jax.shard_map``; on
one device too, so that every ``k`` runs the same program). Throughput = worlds x steps / s, median of
``--repeats`` trials of ``--replays`` blocks after two warm-up blocks; parallel efficiency = throughput(k) /
(k x throughput(1)).

The drive and the solver settings are :mod:`kamino.bench.throughput`'s (float32, ``SolverConfig(dt=0.0025)``, the robots
standing under PD with ``0.2 sin(2 pi t)`` rad on the first actuator, the scenes driven by ``2 N m sin(2 pi t)``),
written into the controls of each block. On one device, the eager rollout (the Warp backend's own CUDA graph, no JAX
boundary per step) is recorded beside it as ``"path": "eager"``: what sharding costs against it.

On a CPU, ``XLA_FLAGS=--xla_force_host_platform_device_count=2`` gives two host devices (for a smoke run, not for
figures). Records go to stdout as JSON lines and to ``--out``.
"""

from __future__ import annotations

import argparse
import json
import pathlib
import statistics
import time

import jax
import jax.numpy as jnp
import numpy as np

import kamino
from kamino.sharding import group_model, shard_worlds, sharded_program

DT = 0.0025


def _controls(model, name: str, t0: float, steps: int, throughput) -> kamino.Control:
    """The throughput benchmark's drive over ``steps`` steps from time ``t0``, as controls with a leading time axis."""
    t = t0 + DT * np.arange(1, steps + 1)
    dof = np.asarray(model.actuator_dof[model.world_actuator_start]) if model.num_actuators else np.zeros(0, int)
    values = np.zeros((steps, model.num_dofs), np.float32)
    if name in throughput.ROBOTS:
        values[:, dof] = (0.2 * np.sin(2 * np.pi * t))[:, None]
        return kamino.Control(position_target=values)
    values[:, dof] = (throughput.AMPLITUDE * np.sin(2 * np.pi * throughput.FREQUENCY * t))[:, None]
    return kamino.Control(dof_effort=values)


def _time(run, state, args) -> tuple[float, object]:
    """Median seconds per block over ``--repeats`` trials of ``--replays`` blocks, after two warm-up blocks."""
    state = run(run(state))
    jax.block_until_ready(state)
    trials = []
    for _ in range(args.repeats):
        t0 = time.perf_counter()
        for _ in range(args.replays):
            state = run(state)
        jax.block_until_ready(state)
        trials.append((time.perf_counter() - t0) / args.replays)
    return statistics.median(trials), state


def bench(name: str, k: int, args, throughput) -> list[dict]:
    base, _ = throughput.load_scene(name)
    devices = jax.devices()[:k]
    model = kamino.replicate(base, args.worlds_per_device * k)
    cfg = kamino.SolverConfig(dt=DT)
    state = kamino.init_state(model, jnp.float32)
    controls = _controls(model, name, 0.0, args.block, throughput)  # the same block each time: timing only
    last = lambda traj: jax.tree.map(lambda x: x[-1], traj)  # noqa: E731
    group = kamino.Simulator(group_model(model, k), cfg, backend=args.backend)
    mesh = jax.sharding.Mesh(np.asarray(devices), ("worlds",))
    sharded = shard_worlds(model, state, mesh)
    ctrl = jax.tree.map(lambda x: jax.device_put(x, jax.sharding.NamedSharding(
        mesh, jax.sharding.PartitionSpec(None, "worlds"))), controls)

    program = sharded_program("rollout", group.step, mesh, "worlds", args.block)

    def run(s):
        return last(program(s, ctrl))

    seconds, end = _time(run, sharded, args)
    worlds = model.num_worlds
    records = [{"scene": name, "backend": args.backend, "path": "shard_map", "devices": k,
                "worlds_per_device": args.worlds_per_device, "num_worlds": worlds, "block_steps": args.block,
                "throughput": worlds * args.block / seconds, "block_time_s": seconds,
                "converged_fraction": float(np.mean(np.asarray(end.info.converged))),
                "device_kind": devices[0].device_kind}]
    if k == 1 and args.backend == "warp":  # the eager path: the Warp backend's CUDA graph
        def eager(s):
            return last(kamino.rollout(model, s, controls, config=cfg, backend="warp"))

        seconds, _ = _time(eager, state, args)
        records.append({**records[0], "path": "eager", "throughput": worlds * args.block / seconds,
                        "block_time_s": seconds})
    return records


def main(argv: list[str] | None = None, prog: str | None = None) -> int:
    """``kamino bench multi_device ARGS`` (``prog`` names the command in the help and errors); 0 when done."""
    from kamino.bench import throughput

    p = argparse.ArgumentParser(prog=prog, description=__doc__.split("\n")[0])
    p.add_argument("--scenes", nargs="+", default=["dr_legs", "ladder8"],
                   choices=sorted({*throughput.SCENES, *throughput.ROBOTS}), metavar="SCENE",
                   help=f"of {', '.join(sorted({*throughput.SCENES, *throughput.ROBOTS}))} (default: dr_legs ladder8)")
    p.add_argument("--worlds-per-device", type=int, default=4096)
    p.add_argument("--devices", nargs="+", type=int, default=None, help="device counts (default 1..all)")
    p.add_argument("--backend", default="warp", choices=["warp", "jax"])
    p.add_argument("--block", type=int, default=10, help="steps per timed rollout")
    p.add_argument("--replays", type=int, default=5)
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--out", type=pathlib.Path, default=None)
    args = p.parse_args(argv)
    from kamino._warp import quiet_warp

    quiet_warp()
    counts = args.devices or list(range(1, len(jax.devices()) + 1))
    if max(counts) > len(jax.devices()):
        p.error(f"--devices {max(counts)}: only {len(jax.devices())} devices ({jax.devices()})")
    records = []
    for name in args.scenes:
        base_thr = None
        for k in counts:
            for rec in bench(name, k, args, throughput):
                if rec["path"] == "shard_map":
                    base_thr = rec["throughput"] / k if k == 1 else base_thr
                    if base_thr:
                        rec["parallel_efficiency"] = rec["throughput"] / (k * base_thr)
                records.append(rec)
                print(json.dumps(rec), flush=True)
    if args.out:
        args.out.write_text(json.dumps({"records": records}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
