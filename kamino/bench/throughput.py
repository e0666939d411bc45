"""Throughput against error on the GPU: kamino (Warp backend, each Jacobian/solver configuration, and the
JAX backend) and, when importable, the peers MuJoCo Warp and Newton SolverKamino on the same scenes.

    kamino bench [--scenes fourbar ladder8 ...] [--worlds 1 64 512 4096 16384]
                 [--configs dense-llt sparse-llt sparse-cr jax] [--no-peers] [--out FILE]
    kamino bench --suite accuracy [--scenes ...] [--worlds ...] [--out STEM.json]   # a preset, any option overridden
    kamino bench --plot RUN.json [RUN2.json ...] [--out STEM.json]   # PNG plots of saved runs (the bench extra)
    kamino bench --table RUN.json [RUN2.json ...]                    # the markdown tables of saved runs

(``python -m kamino.bench.throughput`` is the same command.)

Progress bars (tqdm, on stderr) over the runs and over each closure run's steps; ``--no-progress`` turns them off.
stdout carries the JSON records only, one a line.

Method (docs/architecture.md "Performance method", the same for kamino and the peers):
float32, dt = 0.0025 s; throughput = steps/s x worlds with a CUDA graph of ``--graph-steps`` steps replayed, also
given in simulated world-seconds per second (``sim_seconds_per_s``: throughput x dt, comparable across time steps).
Each scene runs under each of ``--loads`` (:mod:`kamino.bench.loads`): ``gentle``, every world alike with one drive on
its first actuator (a scene's motor ``2 N m sin(2 pi t)``; a robot standing in its reference pose under PD, its first
target ``0.2 sin(2 pi t)`` rad), and ``rl``, each world from its own random loop-closed configuration under its own
random controls at 50 Hz. Next to each of kamino's figures: the statistics of the timed batch itself
(:class:`kamino.bench.loads.BatchStats`: PADMM iterations per world and step, mean, p99 and max; the converged share;
the failed worlds; the loop closure, the largest anchor distance of any joint with translational rows over every world
and step) and the device memory per world. The peers run fourbar, ladder8, ladder32 from kamino/bench/scenes and the
robots from their ``kamino.save_mjcf`` export (:mod:`kamino.bench.peers`, :func:`run_peers`): MuJoCo Warp under
every load, with the same starts and draws, the statistics of its own timed batch, and once per setting of
``--mjw-sweep`` (the ``<connect>`` time constant, time step, iterations, tolerance: its accuracy knobs); SolverKamino
under the gentle load, its closure from a one-world run of ``--closure-steps``.

Speed against accuracy: ``--kamino-sweep F=V,V ...`` runs kamino once per combination of its solver settings
(:func:`kamino_sweep`, ``tolerance=1e-2,1e-3,1e-4``), ``--mjw-sweep`` MuJoCo Warp once per combination of its
accuracy knobs (:func:`mjw_sweep`) and ``--sk-sweep`` each SolverKamino variant once per combination of its
tolerance and iteration cap (:func:`sk_sweep`); a ``+`` between items starts another group of combinations (the
runs of each group after those of the one before it: ``timeconst=0.02,0.005 dt=0.0025,0.0005 + iterations=10`` is
four runs and a fifth at the file's time constant and the benchmark's time step). Each record names its setting
(kamino's ``solver``, a peer's ``variant``), so the records of a sweep stay apart (:func:`record_key`) and the table
gives each its column.
``--table`` prints that table and the Pareto readout (:func:`pareto`): per scene, load, world count and solver, the
most simulated world-seconds per second at a loop closure of at most 1e-3, 1e-4 and 1e-5 m, or the best closure
reached. ``--suite NAME`` sets the options of a preset (:data:`SUITES`; ``accuracy``: every scene at 4096 and 16384
worlds under both loads, with the three sweeps) as defaults that the command line overrides, writes the records to
``--out`` (default ``bench_NAME.json``) and, at the end, ``STEM.md`` (both tables) and the plots ``STEM_*.png``
(:func:`write_report`). A suite too long for one sitting runs in parts (``--scenes``, ``--worlds``; ``--no-peers``
for kamino alone, ``--configs`` with no value for the peers alone), whose JSONs ``--table`` and ``--plot`` merge;
``--gpus 0 1 ...`` splits a run into such parts and runs them side by side, one process per GPU, then merges them
(:func:`run_on_gpus`).

The timed window (one rule for kamino Warp, kamino JAX, MuJoCo Warp and SolverKamino, :mod:`kamino.bench.timed_window`):
each of ``--repeats`` trials resets the simulation to its initial state (state, time, controls, warm start: see
:func:`time_warp`, :func:`bench_jax` and :mod:`kamino.bench.peers` for what each solver's reset covers), runs
``--warmup`` blocks of ``--graph-steps`` steps untimed, synchronises and times ``--replays`` blocks; the figure is the
median trial. Every figure therefore covers steps ``[warmup * graph_steps, (warmup + replays) * graph_steps)`` of the
same driven motion from the same start, written into each record as ``window_steps`` and ``window_s`` (simulated
seconds). Why: a step costs in proportion to its PADMM iterations, which follow the motion; on the four-bar they run 21,
20, 20, 27, 22, 38, 56, 160, 54, 36, 164 per block of 10 steps from reset, so trials that continued the simulation would
time a different stretch of motion in every trial (:mod:`kamino.bench.timed_window`). With the defaults
(``--graph-steps 10 --warmup 2 --replays 100 --repeats 3``) the window is steps [20, 1020), 0.05 to 2.55 s: long
enough that a scene's hard stretches, and under the ``rl`` load its worlds' falls and contacts, are in it. Figures of
runs with other ``--graph-steps``, ``--warmup`` or ``--replays`` cover another window: compare records whose
``window_steps`` agree.
"""

import argparse
import importlib
import json
import math
import os
import pathlib
import platform
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Iterable

import numpy as np
from tqdm import tqdm

import kamino
from kamino.bench import MODULES, loads, scene_path, timed_window
from kamino.config import field_names, setting_value, solver_settings
from kamino.model import ActuationMode

SCENES = ("fourbar", "ladder8", "ladder32", "dr_legs")
#: the procedural robots (kamino.models), standing under PD with the joint-space drive on their first actuator
ROBOTS = ("dr_legs", "bdx", "olaf", "animatronic")
CONFIGS = {
    "default": {},  # kamino.SolverConfig(dt=DT) as it comes: sparse J, LLT (CR: pipeline.resolve_linear_solver)
    "dense-llt": {"warp.jacobian": "dense", "warp.linear_solver": "llt"},
    "sparse-llt": {"warp.jacobian": "sparse", "warp.linear_solver": "llt"},
    "sparse-cr": {"warp.jacobian": "sparse", "warp.linear_solver": "cr"},
    "sparse-llt-warp": {"warp.jacobian": "sparse", "warp.linear_solver": "llt"},
}
#: PADMM schedule of a configuration (``Stepper(padmm=...)``): one thread per world unless ``"warp"`` (32 threads
#: per world, solver_lanes.py)
PADMM = {"sparse-llt-warp": "warp"}
DT = 0.0025
#: solver settings of every kamino configuration here on top of ``kamino.SolverConfig(dt=DT)``: none, the library
#: defaults are the measured configuration (``--tolerance``, ``--rho`` and ``--solver FIELD=VALUE`` set them for one
#: run of :func:`main`)
SOLVER: dict = {}
AMPLITUDE, FREQUENCY = 2.0, 1.0
#: the progress bars' least refresh period [s] (tqdm ``mininterval``): a bar redrawn at most twice a second
PROGRESS_INTERVAL = 0.5


def progress(iterable=None, *, args=None, **kw) -> tqdm:
    """A tqdm bar on stderr, off with ``--no-progress`` (``args.no_progress``); extra keywords go to tqdm."""
    return tqdm(iterable, disable=bool(getattr(args, "no_progress", False)), mininterval=PROGRESS_INTERVAL,
                dynamic_ncols=True, file=sys.stderr, **kw)


def load_scene(name: str):
    """(model, drive) of a benchmark scene: an MJCF file of :func:`kamino.bench.scene_path`, or a robot of
    :data:`ROBOTS` (position targets ``0.2 sin(2 pi t)`` rad about its reference pose on the first actuator)."""
    if name in ROBOTS:
        model = getattr(kamino.models, name)()
        return model, {"offset_from_state": True, "amplitude": 0.2}
    return kamino.load_mjcf(scene_path(name)), {"offset_from_state": False, "amplitude": AMPLITUDE}


def closure_distance(model, body_q: np.ndarray) -> float:
    """Largest distance between the two anchors of any joint of :func:`kamino.bench.loads.anchored_joints` (host
    NumPy; :class:`kamino.bench.loads.BatchStats` folds the same distance on the device)."""
    q = np.asarray(body_q, np.float64)

    def rot(qs):
        x, y, z, w = qs[..., 0], qs[..., 1], qs[..., 2], qs[..., 3]
        return np.stack([np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], -1),
                         np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], -1),
                         np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], -1)], -2)

    sel = loads.anchored_joints(model)
    if not sel.size:
        return 0.0
    par, chi = model.joint_parent[sel], model.joint_child[sel]
    pF = q[chi, :3] + np.einsum("jab,jb->ja", rot(q[chi, 3:]), model.joint_anchor_F[sel])
    qB = np.where((par >= 0)[:, None], q[np.maximum(par, 0)], np.array([0, 0, 0, 0, 0, 0, 1.0]))
    pB = qB[:, :3] + np.einsum("jab,jb->ja", rot(qB[:, 3:]), model.joint_anchor_B[sel])
    return float(np.max(np.linalg.norm(pF - pB, axis=-1)))


def _drive_hook(st, model, drive, base_targets):
    """A pre-step hook writing ``offset + A sin(2 pi f t)`` to the first actuator of every world (device side)."""
    import warp as wp

    from kamino.warp_backend.types import types_of

    T = types_of(st.np_dtype)
    scalar = T.scalar
    dof = model.actuator_dof[model.world_actuator_start]
    mode = int(model.dof_act_mode[dof[0]])
    gear = float(model.actuator_gear[model.world_actuator_start[0]])
    offset = base_targets[dof] if drive["offset_from_state"] else np.zeros(len(dof))
    dof_w = wp.array(dof.astype(np.int32), dtype=wp.int32, device=st.device)
    off_w = wp.array(offset.astype(st.np_dtype), dtype=scalar, device=st.device)

    @wp.kernel(module="unique", enable_backward=False)
    def drive_kernel(time: wp.array(dtype=scalar), dofs: wp.array(dtype=wp.int32), off: wp.array(dtype=scalar),
                     effort: wp.array(dtype=scalar), target: wp.array(dtype=scalar), amp: scalar, omega: scalar,
                     effort_mode: int):
        w = wp.tid()
        v = off[w] + amp * wp.sin(omega * time[w])
        if effort_mode != 0:
            effort[dofs[w]] = v
        else:
            target[dofs[w]] = v

    def hook(s):
        wp.launch(drive_kernel, dim=len(dof), device=s.device,
                  inputs=[s.work.time, dof_w, off_w, s.work.effort, s.work.position_target,
                          drive["amplitude"] * (gear if mode == int(ActuationMode.EFFORT) else 1.0),
                          2.0 * math.pi * FREQUENCY, int(mode == int(ActuationMode.EFFORT))])
    return hook


def _initial(model, name):
    """Initial state, controls and the drive's offset per DoF. A robot stands in its reference pose, held by zero
    position targets (its DoFs are measured from that pose), as in tests/test_robots.py."""
    state = kamino.init_state(model, np.float32)
    if name in ROBOTS:
        return state, kamino.Control(position_target=np.zeros(model.num_dofs, np.float32)), np.zeros(model.num_dofs)
    return state, None, np.zeros(model.num_dofs)


def warp_stepper(name, config_name, num_worlds, load="gentle", seed=0, padmm=None):
    """``(stepper, state, control)``: the Warp stepper of a scene at ``num_worlds`` worlds under ``load``
    (:mod:`kamino.bench.loads`: the gentle drive's hook, or the ``rl`` load's random configurations and control
    sequences drawn from ``seed``), and the initial state and controls that :func:`time_warp` resets it to (loaded
    once here). ``padmm`` picks the PADMM schedule (``Stepper``'s; default: the configuration's, :data:`PADMM`)."""
    import warp as wp

    from kamino.warp_backend import backend as wb
    from kamino.warp_backend.pipeline import Stepper

    if load not in loads.LOADS:
        raise ValueError(f"warp_stepper: load must be one of {loads.LOADS}, got {load!r}")
    base, drive = load_scene(name)
    model = kamino.replicate(base, num_worlds) if num_worlds > 1 else base
    cfg = kamino.SolverConfig(dt=DT).replace(**SOLVER, **CONFIGS[config_name])
    state, control, base_targets = _initial(model, name)
    if load == "rl":
        state = state.replace(body_q=loads.random_configurations(base, model, loads.RL_FRACTION, seed))
    st = Stepper(model, cfg, np.float32, wp.get_device(), padmm=padmm or PADMM.get(config_name))
    wb.load_state(st, state, control)
    hook = _drive_hook(st, model, drive, base_targets) if load == "gentle" else loads.rl_drive_hook(st, base,
                                                                                                    seed=seed)
    st.pre_step.append(hook)
    return st, state, control


def time_warp(st, state, control, args, before_timing=None, after_trial=None) -> dict:
    """The timed window (:mod:`kamino.bench.timed_window`) of a Warp stepper: each trial resets the stepper, runs
    ``--warmup`` blocks of ``--graph-steps`` steps (one CUDA graph each, captured on the stepper's buffers during the
    first trial's warm-up; plain launches on the CPU) untimed, then times ``--replays`` blocks.

    The reset is :func:`kamino.warp_backend.backend.load_state` of the initial ``state`` and ``control`` into the
    buffers the graph was captured on: poses, twists, time (the drive hook reads it), the previous step's reactions
    and contacts (PADMM's warm start, ``Work.f0``/``v0`` are rebuilt from them every step), the penalty that adapts
    from step to step (``Work.rho_u``), the unconverged-step counters and frozen flags, and the controls. Everything
    else in the workspace is rewritten by every step before it is read, so a trial after a reset repeats the first
    bit for bit on the CPU (tests/test_timed_window.py); on a GPU the atomics' order may still differ."""
    import warp as wp

    from kamino.warp_backend import backend as wb

    return timed_window.time_window(
        lambda: wb.load_state(st, state, control), lambda: st.run(args.graph_steps),
        lambda: wp.synchronize_device(st.device), graph_steps=args.graph_steps, warmup=args.warmup,
        replays=args.replays, repeats=args.repeats, dt=DT, before_timing=before_timing, after_trial=after_trial)


def _window_fields(timing: dict) -> dict:
    """The record's share of a :func:`timed_window.time_window` result: step time, the trials and the window."""
    keys = ("step_time_s", "trials_s", "graph_steps", "warmup_blocks", "replays_per_trial", "repeats", "window_steps",
            "window_s")
    return {k: timing[k] for k in keys}


def bench_warp(name, config_name, num_worlds, args, load="gentle") -> dict:
    """Throughput of the Warp backend under ``load``: :func:`time_warp`'s window, with the statistics of its timed
    batch (:class:`kamino.bench.loads.BatchStats`, folded inside the timed graphs and zeroed at the start of every
    trial's timed blocks: the record holds the last trial's); the memory is what the stepper allocates."""
    import warp as wp

    dev = wp.get_device()
    wp.synchronize_device(dev)
    mem0 = wp.get_mempool_used_mem_current(dev) if dev.is_cuda else 0
    st, state, control = warp_stepper(name, config_name, num_worlds, load)
    wp.synchronize_device(dev)
    mem = (wp.get_mempool_used_mem_current(dev) - mem0) if dev.is_cuda else 0
    stats = loads.BatchStats(st)
    st.post_step.append(stats.hook)
    timing = time_warp(st, state, control, args, before_timing=lambda _: stats.reset())
    return {"kamino": "warp", "config": config_name, "scene": name, "load": load, "num_worlds": num_worlds,
            "throughput": num_worlds / timing["step_time_s"],
            "sim_seconds_per_s": num_worlds * DT / timing["step_time_s"], **_window_fields(timing),
            **stats.summary(), "memory_per_world_bytes": mem / num_worlds, "rows_max": st.wm.max_rows,
            "linear_solver": st.linear_solver, "padmm": st.padmm, "solver": dict(SOLVER)}


def bench_jax(name, num_worlds, args) -> dict:
    """The JAX backend over the same window as :func:`bench_warp` (:mod:`kamino.bench.timed_window`): blocks of
    ``--graph-steps`` jitted steps, the drive evaluated at each world's simulated time (so both backends see the same
    part of the motion); each trial starts again from the initial ``state`` (the JAX state is a value: that is the
    whole reset, warm start included), runs ``--warmup`` blocks untimed and times ``--replays`` blocks."""
    import jax
    import jax.numpy as jnp

    base, _ = load_scene(name)
    model = kamino.replicate(base, num_worlds) if num_worlds > 1 else base
    cfg = kamino.SolverConfig(dt=DT).replace(**SOLVER)
    state, _, _ = _initial(model, name)
    n = args.graph_steps
    dof = jnp.asarray(model.actuator_dof[model.world_actuator_start])

    def block(s):
        t = s.time[0] + DT * jnp.arange(n, dtype=s.time.dtype)
        effort = jnp.zeros((n, model.num_dofs), s.time.dtype)
        effort = effort.at[:, dof].set((AMPLITUDE * jnp.sin(2 * jnp.pi * FREQUENCY * t))[:, None])
        traj = kamino.rollout(model, s, kamino.Control(dof_effort=effort), config=cfg, backend="jax")
        return jax.tree_util.tree_map(lambda x: x[-1], traj)

    run = jax.jit(block)
    sim = {"s": state}

    def reset():
        sim["s"] = state

    def advance():
        sim["s"] = run(sim["s"])

    timing = timed_window.time_window(reset, advance, lambda: jax.block_until_ready(sim["s"]), graph_steps=n,
                                      warmup=args.warmup, replays=args.replays, repeats=args.repeats, dt=DT)
    return {"kamino": "jax", "config": "jax", "scene": name, "num_worlds": num_worlds, "solver": dict(SOLVER),
            "throughput": num_worlds / timing["step_time_s"], **_window_fields(timing),
            "iterations_last_step_max": int(np.max(np.asarray(sim["s"].info.iterations)))}


def environment() -> dict:
    import jax
    import warp as wp

    dev = wp.get_device()
    return {"gpu": dev.name if dev.is_cuda else platform.processor(), "warp": wp.__version__, "jax": jax.__version__,
            "python": platform.python_version(), "date": time.strftime("%Y-%m-%d"), "solver": dict(SOLVER), "dt": DT,
            "command": " ".join(sys.argv)}


def solver_overrides(items: list[str]) -> dict:
    """``--solver F=V ...`` as SolverConfig settings (:func:`kamino.config.solver_settings`); a bad item exits
    naming it."""
    try:
        return solver_settings(items)
    except ValueError as e:
        raise SystemExit(str(e)) from None


#: the ``--configs`` choices: the Warp configurations of :data:`CONFIGS` and the JAX backend
CONFIG_CHOICES = (*CONFIGS, "jax")
#: the first line of ``kamino bench --help``
SUMMARY = "Throughput against error of kamino and, when importable, MuJoCo Warp and Newton's SolverKamino."


def _parser(prog: str | None = None) -> argparse.ArgumentParser:
    others = ", ".join(m for m in MODULES if m != "throughput")
    p = argparse.ArgumentParser(
        prog=prog, description=SUMMARY,
        formatter_class=lambda prog: argparse.RawDescriptionHelpFormatter(prog, max_help_position=36, width=110),
        usage=f"{prog or '%(prog)s'} [options]   |   {prog or '%(prog)s'} --plot/--table JSON...",
        epilog=f"Other benchmarks (kamino bench NAME --help): {others}.\n"
               "The method and the suites: help(kamino.bench.throughput).")
    p.add_argument("--suite", choices=sorted(SUITES), default=None,
                   help="a preset of the options below, each overridable; writes JSON, table, plots")
    p.add_argument("--scenes", nargs="+", default=list(SCENES), choices=sorted({*SCENES, *ROBOTS}), metavar="SCENE",
                   help=f"of {' '.join(SCENES)} (default) and {' '.join(r for r in ROBOTS if r not in SCENES)}")
    p.add_argument("--worlds", nargs="+", type=int, default=[1, 64, 512, 4096, 16384], metavar="N",
                   help="world counts (default: 1 64 512 4096 16384)")
    p.add_argument("--configs", nargs="*", default=list(CONFIG_CHOICES), choices=CONFIG_CHOICES, metavar="CONFIG",
                   help=f"of {', '.join(CONFIG_CHOICES)} (all)")
    p.add_argument("--graph-steps", type=int, default=10, metavar="N", help="steps per block, one CUDA graph (10)")
    p.add_argument("--warmup", type=int, default=timed_window.WARMUP_BLOCKS, metavar="N",
                   help=f"untimed blocks after each trial's reset ({timed_window.WARMUP_BLOCKS})")
    p.add_argument("--replays", type=int, default=100, metavar="N", help="timed blocks per trial (100)")
    p.add_argument("--loads", nargs="+", default=list(loads.LOADS), choices=loads.LOADS, metavar="LOAD",
                   help=f"of {', '.join(loads.LOADS)} (all; kamino.bench.loads)")
    p.add_argument("--repeats", type=int, default=3, metavar="N", help="trials from a reset; the median counts (3)")
    p.add_argument("--closure-steps", type=int, default=1000, metavar="N", help="the peers' one-world closure run")
    p.add_argument("--tolerance", type=float, default=None, metavar="TOL",
                   help="PADMM tolerance (default: SolverConfig's)")
    p.add_argument("--rho", type=float, default=None, help="PADMM starting penalty (default: SolverConfig's)")
    p.add_argument("--solver", nargs="+", default=[], metavar="F=V",
                   help="SolverConfig settings F (dotted: warp.linear_solver=cr), V as JSON")
    p.add_argument("--kamino-sweep", nargs="+", default=[], metavar="F=V,V",
                   help="kamino per combination of its settings F (as --solver); + adds a group")
    p.add_argument("--no-peers", action="store_true", help="run kamino only")
    p.add_argument("--kamino-variants", nargs="*", default=["padmm_dense", "dvi"], metavar="VARIANT",
                   help="SolverKamino variants (default: padmm_dense dvi; none: MuJoCo Warp alone)")
    p.add_argument("--mjw-sweep", nargs="+", default=[], metavar="K=V,V",
                   help=f"MuJoCo Warp per combination of K in {' '.join(MJW_SWEEP)}")
    p.add_argument("--sk-sweep", nargs="+", default=[], metavar="K=V,V",
                   help=f"SolverKamino per combination of K in {' '.join(SK_SWEEP)}")
    p.add_argument("--out", type=pathlib.Path, default=None, metavar="JSON",
                   help="write the records here (default: stdout only)")
    p.add_argument("--plot", type=pathlib.Path, nargs="+", default=None, metavar="JSON",
                   help="PNG plots of saved runs, named after --out or the first JSON; exit")
    p.add_argument("--table", type=pathlib.Path, nargs="+", default=None, metavar="JSON",
                   help="print markdown tables of saved runs (all; speed at closure) and exit")
    p.add_argument("--no-progress", action="store_true", help="no progress bars (tqdm, on stderr)")
    p.add_argument("--gpus", nargs="+", default=None, metavar="ID",
                   help="run the parts side by side, one per GPU (CUDA ids), and merge them")
    p.add_argument("--part", action="store_true", help=argparse.SUPPRESS)  # one of --gpus' parts: no report
    return p


def _check_counts(p: argparse.ArgumentParser, args: argparse.Namespace) -> None:
    """A parser error naming the option for a world count, block count or step count out of range."""
    if min(args.worlds) < 1:
        p.error(f"--worlds: every world count must be >= 1, got {min(args.worlds)}")
    for name in ("graph_steps", "replays", "repeats"):
        if getattr(args, name) < 1:
            p.error(f"--{name.replace('_', '-')} must be >= 1, got {getattr(args, name)}")
    for name in ("warmup", "closure_steps"):
        if getattr(args, name) < 0:
            p.error(f"--{name.replace('_', '-')} must be >= 0, got {getattr(args, name)}")
    for option, parse in (("--mjw-sweep", mjw_sweep), ("--sk-sweep", sk_sweep), ("--kamino-sweep", kamino_sweep)):
        try:
            parse(getattr(args, option[2:].replace("-", "_")))
        except ValueError as e:
            p.error(f"{option} {e}")


def _read_records(p: argparse.ArgumentParser, option: str, files: list[pathlib.Path]) -> list[dict]:
    """The records of saved runs, a later record of the same thing replacing an earlier one; a parser error names
    a file that is missing or not a run's JSON."""
    records = []
    for f in files:
        try:
            records.extend(json.loads(f.read_text())["records"])
        except (OSError, ValueError, KeyError, TypeError) as e:
            p.error(f"{option} {f}: not a saved run's JSON with 'records' ({type(e).__name__}: {e})")
    return latest_records(records)


def main(argv: list[str] | None = None, prog: str | None = None) -> int:
    """``kamino bench ARGS`` (``prog`` names the command in the help and errors); 0 when done."""
    p = _parser(prog)
    args = p.parse_args(argv)
    if args.suite:  # the preset's values as defaults: what the command line gives still wins
        p.set_defaults(**SUITES[args.suite])
        args = p.parse_args(argv)
        if not (args.plot or args.table):
            args.out = args.out or pathlib.Path(f"bench_{args.suite}.json")
    _check_counts(p, args)
    if args.plot:
        try:
            import matplotlib  # noqa: F401
        except ImportError:
            p.error("--plot needs matplotlib, which is not installed: pip install 'kamino[bench]'")
        plot({"records": _read_records(p, "--plot", args.plot)}, (args.out or args.plot[0]).with_suffix(""))
        return 0
    if args.table:
        records = _read_records(p, "--table", args.table)
        print(table(records) + "\n\n" + pareto(records))
        return 0
    if args.gpus:
        return run_on_gpus(argv if argv is not None else sys.argv[1:], args)
    from kamino._warp import quiet_warp

    quiet_warp()  # Warp's banner and module-load lines off stdout (KAMINO_WARP_VERBOSE=1 keeps them)
    SOLVER.clear()  # this run's settings only, also where main runs twice in one process
    if args.tolerance is not None:
        SOLVER["tolerance"] = args.tolerance
    if args.rho is not None:
        SOLVER["penalty.rho"] = args.rho
    SOLVER.update(solver_overrides(args.solver))
    base, sweep = dict(SOLVER), kamino_sweep(args.kamino_sweep)
    results = {"environment": environment(), "records": []}

    def emit(rec):
        results["records"].append(rec)
        with tqdm.external_write_mode():  # the same line on stdout, the bars cleared around it on a terminal
            print(json.dumps(rec), flush=True)
        if args.out:
            args.out.write_text(json.dumps(results, indent=1))

    # one bar over kamino's (scene, config, worlds) runs; the peers' runs of a scene show in its description
    runs = sum(1 if c == "jax" else len(args.loads) for c in args.configs) * len(args.scenes) * len(args.worlds) \
        * len(sweep)
    bar = progress(args=args, total=runs, desc="throughput", unit="run")
    with bar:
        for scene in args.scenes:
            for config in args.configs:
                for load in ["gentle"] if config == "jax" else args.loads:
                    for nw in args.worlds:
                        for setting in sweep:  # each point of --kamino-sweep on top of --tolerance/--rho/--solver
                            SOLVER.clear()
                            SOLVER.update({**base, **setting})
                            named = " ".join(f"{k}={v}" for k, v in setting.items())
                            bar.set_description(f"{scene} {config} {load} {nw} worlds {named}".strip())
                            emit(_bench_or_error(scene, config, nw, args, load))
                            bar.update()
            SOLVER.clear()
            SOLVER.update(base)
            if not args.no_peers:
                bar.set_description(f"{scene} peers")
                run_peers(scene, args, emit)
    if args.suite and not args.part:
        write_report(results, args.out)
    return 0


def parts(argv: list[str], args: argparse.Namespace) -> list[tuple[list[str], tuple[str, int, str]]]:
    """The command line and ``(scene, worlds, "kamino" or "peers")`` of each part of a ``--gpus`` run: per scene and
    world count, kamino's runs (``--no-peers``) and the peers' (``--configs`` with no value), each the whole command
    with ``--scenes``, ``--worlds`` and ``--out`` narrowed to it; the largest world counts first, so the longest parts
    start first."""
    base, skip = [], 0
    for a in argv:  # drop the options that the parts set themselves
        if skip and not a.startswith("--"):
            continue
        skip = a in ("--gpus", "--scenes", "--worlds", "--out")
        if not skip:
            base.append(a)
    whos = (["kamino"] if args.configs else []) + ([] if args.no_peers else ["peers"])
    out = []
    for nw in sorted(args.worlds, reverse=True):
        for scene in args.scenes:
            for who in whos:
                narrow = ["--scenes", scene, "--worlds", str(nw), "--part", "--no-progress"]
                out.append(([*base, *narrow, "--no-peers" if who == "kamino" else "--configs"],
                            (scene, nw, who)))
    return out


def run_part(cmd: list[str], gpu: str, out: pathlib.Path, log: pathlib.Path) -> int:
    """One part of a ``--gpus`` run: ``kamino bench CMD --out OUT`` in a process of its own that sees only CUDA device
    ``gpu``, its stderr into ``log``; its exit status."""
    env = {**os.environ, "CUDA_VISIBLE_DEVICES": gpu}
    with open(log, "w") as err:
        return subprocess.run([sys.executable, "-m", "kamino.bench.throughput", *cmd, "--out", str(out)], env=env,
                              stdout=subprocess.DEVNULL, stderr=err, check=False).returncode


def run_on_gpus(argv: list[str], args: argparse.Namespace) -> int:
    """``--gpus ID ...``: the run's :func:`parts` side by side, each GPU taking the next part when its last one ends
    (one process per part: each part's figures come from a GPU it has alone), then their records merged into
    ``--out`` (default ``bench_gpus.json``), with the suite's report (:func:`write_report`) under ``--suite``. A part
    that fails leaves a record naming it and its log; the other parts go on. Each part's JSON and stderr stay beside
    ``--out`` in ``STEM_parts/``."""
    out = args.out or pathlib.Path("bench_gpus.json")
    folder = out.with_suffix("").with_name(out.with_suffix("").name + "_parts")
    folder.mkdir(parents=True, exist_ok=True)
    jobs = parts(argv, args)
    queue = list(enumerate(jobs))
    lock = threading.Lock()
    bar = progress(args=args, total=len(jobs), desc=f"parts on GPUs {' '.join(args.gpus)}", unit="part")
    failed = []

    def worker(gpu: str) -> None:
        while True:
            with lock:
                if not queue:
                    return
                _, (cmd, (scene, nw, who)) = queue.pop(0)
            name = f"{scene}_{nw}_{who}"
            rc = run_part(cmd, gpu, folder / f"{name}.json", folder / f"{name}.log")
            with lock:
                if rc != 0:  # keyed as the part's own records are (record_key), so that a re-run replaces it
                    failed.append({**({"kamino": "warp", "config": "all"} if who == "kamino" else {"peer": "all"}),
                                   "scene": scene, "num_worlds": nw, "gpu": gpu, "command": " ".join(cmd),
                                   "error": f"exit status {rc}: see {folder / (name + '.log')}"})
                bar.update()

    with bar:
        threads = [threading.Thread(target=worker, args=(g,)) for g in args.gpus]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
    records, environments = [], []
    for _, (scene, nw, who) in jobs:
        f = folder / f"{scene}_{nw}_{who}.json"
        if f.exists():
            saved = json.loads(f.read_text())
            records.extend(saved["records"])
            environments.append(saved["environment"])
    environment = {**(environments[0] if environments else {}), "command": " ".join(["kamino bench", *argv]),
                   "parts": [e.get("command") for e in environments]}
    results = {"environment": environment, "records": records + failed}
    out.write_text(json.dumps(results, indent=1))
    for rec in results["records"]:
        print(json.dumps(rec))
    if args.suite:
        write_report(results, out)
    return 0


def _bench_or_error(scene, config, num_worlds, args, load) -> dict:
    """The record of one kamino run (:func:`bench_jax` for ``jax``, else :func:`bench_warp` under ``load``), or
    a record of its error: the run goes on with the next."""
    try:
        if config == "jax":
            return bench_jax(scene, num_worlds, args)
        return bench_warp(scene, config, num_worlds, args, load)
    except Exception as e:  # keep going: report what failed
        if config == "jax":
            return {"kamino": "jax", "scene": scene, "num_worlds": num_worlds, "solver": dict(SOLVER),
                    "error": repr(e)[:300]}
        return {"kamino": "warp", "config": config, "scene": scene, "load": load, "num_worlds": num_worlds,
                "solver": dict(SOLVER), "error": repr(e)[:300]}


def write_report(results: dict, out: pathlib.Path) -> None:
    """A suite's table and plots beside its JSON ``out``: ``<stem>.md``, the markdown table of every record
    (:func:`table`) and the speed each solver reaches at each closure target (:func:`pareto`); the plots of
    :func:`plot` (``<stem>_throughput.png``, ``_error.png``, ``_accuracy.png``) when matplotlib is installed."""
    stem = out.with_suffix("")
    records = latest_records(results["records"])
    text = f"# {results['environment'].get('command', 'kamino bench')}\n\n{table(records)}\n\n{pareto(records)}\n"
    stem.with_suffix(".md").write_text(text)
    try:
        import matplotlib  # noqa: F401
    except ImportError:
        print("kamino bench: no plots (matplotlib is not installed: pip install 'kamino[bench]')", file=sys.stderr)
        return
    plot({"records": records}, stem)


#: the MJCF scenes the peers run from kamino/bench/scenes (the robots of :data:`ROBOTS` run from kamino's export)
PEER_SCENES = ("fourbar", "ladder8", "ladder32")


#: ``--mjw-sweep`` keys and the :func:`kamino.bench.peers.run_mujoco_warp` keywords they set
MJW_SWEEP = {"timeconst": ("timeconst", float), "dt": ("timestep", float), "iterations": ("iterations", int),
             "tolerance": ("tolerance", float)}
#: ``--sk-sweep`` keys and the :func:`kamino.bench.peers.run_solver_kamino` keywords they set (PADMM: the primal,
#: dual and complementarity tolerances and ``max_iterations``; DVI: its ``tolerance`` and
#: ``max_alternating_iterations``)
SK_SWEEP = {"tolerance": ("tolerance", float), "iterations": ("iterations", int)}

#: ``kamino bench --suite NAME``: presets of the command's options (argparse ``dest`` names), each overridable on the
#: command line. ``accuracy``: speed against accuracy on every scene at 4096 and 16384 worlds under both loads,
#: kamino's default configuration over a tolerance sweep; MuJoCo Warp over its ``<connect>`` time constant and time
#: step (MuJoCo holds the time constant at 2 dt at least, so 0.001 s acts at dt 0.5 ms and is 0.005 s at 2.5 ms), then
#: its solver loosened at the file's stiffness (10 iterations, tolerance 1e-4) and pushed at the stiffest setting (300
#: iterations, tolerance 1e-10); SolverKamino's PADMM and DVI over their tolerance (1e-4: Newton's four-bar example;
#: 1e-6: PADMM's default); one trial of 300 timed steps per point (``window_steps`` [20, 320)).
SUITES = {
    "accuracy": {
        "scenes": ["fourbar", "ladder8", "ladder32", "dr_legs", "bdx", "olaf", "animatronic"],
        "worlds": [4096, 16384], "loads": ["gentle", "rl"], "configs": ["default"],
        "kamino_sweep": ["tolerance=1e-2,1e-3,1e-4"],
        "mjw_sweep": ["timeconst=0.02,0.005,0.001", "dt=0.0025,0.0005", "+", "iterations=10", "tolerance=1e-4",
                      "+", "timeconst=0.001", "dt=0.0005", "iterations=300", "tolerance=1e-10"],
        "kamino_variants": ["padmm_dense", "dvi"], "sk_sweep": ["tolerance=1e-4,1e-6"],
        "replays": 30, "repeats": 1,
    },
}


#: the sweep item that starts another group of combinations (``--mjw-sweep timeconst=0.02,0.005 + iterations=10``)
SWEEP_GROUP = "+"


def _grid(items: list[str], keys: dict, parse) -> list[dict]:
    """Every combination of ``KEY=V[,V...]`` items (``parse(key, text)`` gives a value and raises ``ValueError``
    for a bad one), and where :data:`SWEEP_GROUP` items split them into groups, each group's combinations after the
    previous group's, a setting already listed left out (an empty group is the run without settings, ``{}``);
    no items: ``[{}]``."""
    settings: list[dict] = []
    groups: list[list[str]] = [[]]
    for item in items:
        if item == SWEEP_GROUP:
            groups.append([])
        else:
            groups[-1].append(item)
    for group in groups:
        grid: dict[str, list] = {}
        for item in group:
            key, sep, values = item.partition("=")
            if not sep or key not in keys or not values:
                raise ValueError(f"{item!r}: expected KEY=V[,V...] with KEY one of {', '.join(keys)}, or "
                                 f"{SWEEP_GROUP!r} between groups")
            try:
                grid[key] = [parse(key, v) for v in values.split(",")]
            except ValueError as e:
                raise ValueError(f"{item!r}: {e}") from None
        combos = [{}]
        for key, values in grid.items():
            combos = [{**c, key: v} for c in combos for v in values]
        settings += [c for c in combos if c not in settings]
    return settings


def _peer_sweep(items: list[str], keys: dict) -> list[dict]:
    """A peer's sweep (:data:`MJW_SWEEP` or :data:`SK_SWEEP`): positive numbers, each key renamed to its runner's
    keyword."""
    def parse(key, text):
        kind = keys[key][1]
        try:
            value = kind(text)
        except ValueError:
            raise ValueError(f"the values of {key} must be {kind.__name__}s") from None
        if value <= 0:
            raise ValueError(f"the values of {key} must be > 0")
        return value

    return [{keys[k][0]: v for k, v in s.items()} for s in _grid(items, keys, parse)]


def mjw_sweep(items: list[str]) -> list[dict]:
    """``["timeconst=0.02,0.004", "dt=0.001"]`` -> the :func:`kamino.bench.peers.run_mujoco_warp` settings of every
    combination (``[{"timeconst": 0.02, "timestep": 0.001}, {"timeconst": 0.004, "timestep": 0.001}]``); no items:
    one run with the file's settings (``[{}]``). Raises ``ValueError`` naming a bad item."""
    return _peer_sweep(items, MJW_SWEEP)


def sk_sweep(items: list[str]) -> list[dict]:
    """``["tolerance=1e-4,1e-6"]`` -> the :func:`kamino.bench.peers.run_solver_kamino` settings of every combination
    (``[{"tolerance": 1e-4}, {"tolerance": 1e-6}]``); no items: one run with the variant's settings (``[{}]``).
    Raises ``ValueError`` naming a bad item."""
    return _peer_sweep(items, SK_SWEEP)


def kamino_sweep(items: list[str]) -> list[dict]:
    """``["tolerance=1e-2,1e-3", "penalty.rho=0.05"]`` -> kamino's solver settings of every combination, by the
    dotted names of :func:`kamino.config.field_names` but ``dt`` (the benchmark's time step is :data:`DT`) with
    values read by :func:`kamino.config.setting_value`, each checked by ``kamino.SolverConfig(dt=DT).replace``; no
    items: ``[{}]``, the run's own settings. Raises ``ValueError`` naming a bad item."""
    fields = [f for f in field_names() if f != "dt"]

    def parse(key, text):
        value = setting_value(text)
        try:
            kamino.SolverConfig(dt=DT).replace(**{key: value})
        except (ValueError, TypeError) as e:
            raise ValueError(f"kamino.SolverConfig rejects {key}={value!r} ({e})") from None
        return value

    return _grid(items, dict.fromkeys(fields), parse)


def run_peers(scene, args, emit) -> None:
    """MuJoCo Warp and Newton SolverKamino on the same MJCF and drive as kamino, when importable
    (:mod:`kamino.bench.peers`).

    The MJCF scenes (:data:`PEER_SCENES`) run from kamino/bench/scenes with the torque drive of amplitude
    :data:`AMPLITUDE`. A robot of :data:`ROBOTS` is exported by ``kamino.save_mjcf`` (position actuators become
    ``<position kp kv>``, loop-closing joints ``<connect>`` with ``solref`` 0.004) into a temporary directory, and
    the peers drive the position target of its first actuator with ``0.2 sin(2 pi t)`` rad, as kamino does
    (:func:`load_scene`), the other actuators holding the reference pose. Each record names the scene (``scene``)
    and where its MJCF came from (``scene_source``).

    MuJoCo Warp runs every load of ``--loads`` (the ``rl`` load from kamino's starts and draws of the kamino model
    that the MJCF describes), once per setting of ``--mjw-sweep`` (:func:`mjw_sweep`); SolverKamino runs the
    ``gentle`` load only, each variant once per setting of ``--sk-sweep`` (:func:`sk_sweep`)."""
    if scene not in PEER_SCENES and scene not in ROBOTS:
        return
    try:
        peers = importlib.import_module("kamino.bench.peers")
    except ImportError as e:
        emit({"peer": "all", "scene": scene, "error": f"kamino.bench.peers not importable: {e}"})
        return
    run_loads = list(getattr(args, "loads", None) or ["gentle"])
    sweep = mjw_sweep(list(getattr(args, "mjw_sweep", None) or []))
    sk_settings = sk_sweep(list(getattr(args, "sk_sweep", None) or []))
    with tempfile.TemporaryDirectory(prefix="kamino_peers_") as tmp:
        try:
            model, drive = load_scene(scene)
            if scene in ROBOTS:
                path = str(pathlib.Path(tmp) / f"{scene}.xml")
                kamino.save_mjcf(model, path, model_name=scene)
                source = f"kamino.save_mjcf(kamino.models.{scene}())"
            else:
                path = str(scene_path(scene))
                source = f"kamino/bench/scenes/{scene}.xml"
        except Exception as e:  # the export raises ValueError for what MJCF cannot represent
            for name in ["run_mujoco_warp", *(["run_solver_kamino"] if args.kamino_variants else [])]:
                emit({"peer": name, "scene": scene, "error": f"MJCF for the peers: {e!r}"[:300]})
            return
        for load in run_loads:
            runs = [(peers.run_mujoco_warp, {"load": load, "kamino_model": model, **setting}) for setting in sweep]
            if load == "gentle":
                runs += [(peers.run_solver_kamino, {"variant": v, **setting}) for v in args.kamino_variants
                         for setting in sk_settings]
            for nw in args.worlds:
                for fn, kw in runs:
                    try:
                        rec = fn(path, nw, graph_steps=args.graph_steps, warmup=args.warmup, replays=args.replays,
                                 repeats=args.repeats,
                                 closure_steps=args.closure_steps if nw == args.worlds[0] else 0,
                                 amplitude=drive["amplitude"], **kw)
                        emit({**rec, "scene": scene, "scene_source": source})
                    except Exception as e:
                        emit({"peer": fn.__name__, "scene": scene, "load": load, "num_worlds": nw,
                              "error": repr(e)[:300]})


def _cell(rec: dict | None) -> str:
    """One record as ``world-steps/s (closure, converged, iterations mean/max, memory per world)``; what a record
    lacks is left out. kamino's closure, convergence and iterations are its timed batch's
    (:class:`kamino.bench.loads.BatchStats`), a peer's closure its one-world run's."""
    if rec is None:
        return ""
    if rec.get("throughput") is None:
        reason = str(rec.get("reason") or rec.get("error") or "no figure")
        return f"not run: {reason[:60]}" + ("..." if len(reason) > 60 else "")
    notes = []
    closure = rec.get("closure_batch_max_m", rec.get("closure_max_m"))
    if closure is not None:
        notes.append(f"{closure:.1e} m")
    converged = rec.get("converged_share", rec.get("converged_fraction"))
    if converged is not None:
        notes.append(f"{100 * converged:.1f} %")
    if rec.get("iterations_max") is not None and rec.get("iterations_mean") is not None:
        notes.append(f"it {rec['iterations_mean']:.1f}/{rec['iterations_max']}")
    if rec.get("failed_worlds"):
        notes.append(f"{rec['failed_worlds']} failed")
    if rec.get("memory_per_world_bytes") is not None:
        notes.append(f"{rec['memory_per_world_bytes'] / 1e3:.1f} kB")
    return f"{rec['throughput']:.2e}" + (f" ({', '.join(notes)})" if notes else "")


def record_key(r: dict) -> tuple:
    """What a record measures: scene, world count, load (an older record's: ``gentle``), and the solver (kamino's
    backend, configuration and solver settings, or the peer and its variant, which names its settings)."""
    who = ((r["peer"], r.get("variant")) if "peer" in r
           else (r.get("kamino"), r.get("config"), json.dumps(r.get("solver") or {}, sort_keys=True)))
    return (r.get("scene"), r.get("num_worlds"), r.get("load", "gentle"), *who)


def latest_records(records: Iterable[dict]) -> list[dict]:
    """``records`` with a later record of the same :func:`record_key` replacing an earlier one (kept where the later
    one stands: runs merged from several files give the newest measurement of each thing)."""
    latest: dict[tuple, dict] = {}
    for r in records:
        latest.pop(record_key(r), None)
        latest[record_key(r)] = r
    return list(latest.values())


def _column(r: dict) -> str | None:
    """The table column of a record: ``kamino`` (its ``default`` configuration; other configurations have none) with
    the solver settings it ran (``kamino tolerance=0.01``), ``MuJoCo Warp`` with the settings of a sweep, or
    ``SolverKamino <variant>``."""
    if "peer" in r:
        if r["peer"] != "mujoco_warp":
            return f"SolverKamino {r.get('variant')}"
        settings = str(r.get("variant") or "").split()[1:]  # the variant after its solver's name: the sweep's settings
        return " ".join(["MuJoCo Warp", *settings])
    if r.get("config") != "default":
        return None
    return " ".join(["kamino", *(f"{k}={v}" for k, v in sorted((r.get("solver") or {}).items()))])


def table(records: list[dict]) -> str:
    """A markdown table of throughput records (this module's JSON ``records``): one row per scene, load and world
    count, kamino's ``default`` configuration beside MuJoCo Warp and each SolverKamino variant, each cell
    ``world-steps/s (closure, converged, iterations, memory per world)`` (:func:`_cell`), and kamino's speed and
    memory over MuJoCo Warp's. A later record of the same scene, size, load and solver replaces an earlier one."""
    cells: dict[tuple[str, str, int], dict[str, dict]] = {}
    columns: list[str] = []
    for r in records:
        col = _column(r)
        if col is None:
            continue
        if col not in columns:
            columns.append(col)
        cells.setdefault((r["scene"], r.get("load", "gentle"), int(r["num_worlds"])), {})[col] = r
    columns.sort(key=lambda c: (not c.startswith("kamino"), not c.startswith("MuJoCo Warp"), c))
    lines = ["| scene | load | worlds | " + " | ".join(columns) + " | speed / MuJoCo Warp | memory / MuJoCo Warp |",
             "|---|---|---|" + "---|" * (len(columns) + 2)]
    for (scene, load, worlds), row in sorted(cells.items()):
        k, mjw = row.get("kamino"), row.get("MuJoCo Warp")
        speed = memory = ""
        if k and mjw and k.get("throughput") and mjw.get("throughput"):
            speed = f"{k['throughput'] / mjw['throughput']:.2f}x"
        if k and mjw and k.get("memory_per_world_bytes") and mjw.get("memory_per_world_bytes"):
            memory = f"{k['memory_per_world_bytes'] / mjw['memory_per_world_bytes']:.2f}x"
        lines.append(f"| {scene} | {load} | {worlds} | " + " | ".join(_cell(row.get(c)) for c in columns)
                     + f" | {speed} | {memory} |")
    return "\n".join(lines)


#: the loop closures [m] at which :func:`pareto` reads each solver's best speed
CLOSURE_TARGETS = (1e-3, 1e-4, 1e-5)


def _speed(x: float) -> str:
    """Simulated world-seconds per second as the tables print them: ``7,040``, ``37.5``, ``0.952``."""
    return f"{x:,.0f}" if x >= 100 else f"{x:.3g}"


def pareto(records: list[dict], targets: tuple[float, ...] = CLOSURE_TARGETS) -> str:
    """A markdown table of the speed each solver reaches at each accuracy: one row per scene, load, world count and
    solver (:func:`kamino.plots.solver_setting`: kamino's ``default`` configuration, MuJoCo Warp, each SolverKamino
    variant), one column per loop closure of ``targets`` [m]. A cell is the largest simulated world-seconds per
    second (``sim_seconds_per_s``, world-steps/s x dt) of the solver's settings whose closure is at most the target
    and that failed no world, with that setting and its closure (``7,020 s/s (timeconst=0.005, 2.5e-04 m)``); where
    none qualifies, ``best reached: X s/s at Y m (setting)``, the setting of the smallest closure (the faster of a
    tie), and its failed worlds if any. The points are :func:`kamino.plots.accuracy_points`' (a SolverKamino
    record takes the closure of its one-world run, made at the first world count); a later record of the same thing
    replaces an earlier one (:func:`latest_records`)."""
    from kamino.plots import accuracy_points

    lines = ["| scene | load | worlds | solver | " + " | ".join(f"closure <= {t:.0e} m" for t in targets) + " |",
             "|---|---|---|---|" + "---|" * len(targets)]
    order = {"kamino": 0, "MuJoCo Warp": 1}
    for (scene, load, worlds), solvers in sorted(accuracy_points(latest_records(records)).items()):
        for solver in sorted(solvers, key=lambda name: (order.get(name, 2), name)):
            pts = solvers[solver]
            cells = []
            for target in targets:
                ok = [p for p in pts if p[0] <= target and not p[3].get("failed_worlds")]
                if ok:
                    closure, speed, setting, _ = max(ok, key=lambda p: (p[1], -p[0]))
                    cells.append(f"{_speed(speed)} s/s ({', '.join(filter(None, [setting, f'{closure:.1e} m']))})")
                    continue
                closure, speed, setting, rec = min(pts, key=lambda p: (p[0], -p[1]))
                notes = ", ".join(filter(None, [setting, f"{rec['failed_worlds']} failed worlds"
                                                if rec.get("failed_worlds") else ""]))
                cells.append(f"best reached: {_speed(speed)} s/s at {closure:.1e} m" + (f" ({notes})" if notes else ""))
            lines.append(f"| {scene} | {load} | {worlds} | {solver} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def plot(results: dict, stem: pathlib.Path) -> None:
    """``<stem>_throughput.png``: throughput against worlds; ``<stem>_error.png``: throughput against max loop
    closure (one point per world count, each configuration and peer a series), both one panel per scene;
    ``<stem>_accuracy.png``: simulated seconds per second against closure, one point per solver setting, one panel per
    scene, load and world count (:mod:`kamino.plots`)."""
    from kamino import plots

    plots.save_figure(plots.throughput_against_worlds(results), f"{stem}_throughput.png")
    try:
        fig, accuracy = plots.speed_against_error(results), plots.speed_at_accuracy(results)
    except ValueError:  # no record has a closure: no error plots
        return
    plots.save_figure(fig, f"{stem}_error.png")
    plots.save_figure(accuracy, f"{stem}_accuracy.png")


if __name__ == "__main__":
    raise SystemExit(main())
