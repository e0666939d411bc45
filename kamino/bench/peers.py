"""Peer simulators for kamino's throughput benchmark: MuJoCo Warp and Newton's ``SolverKamino``.

Each ``run_*`` function loads one benchmark scene (an MJCF file, such as the shipped ``kamino/bench/scenes/``), builds
``num_worlds`` copies of it on one Warp device, and measures what docs/benchmark_scenes.md reports for
the peers, with the same method, so our numbers and theirs compare:

* **throughput**: steps/s x worlds at dt = 0.0025 s over the same simulated window as kamino's figures
  (:mod:`kamino.bench.timed_window`, the one rule of :mod:`kamino.bench.throughput`). On CUDA, ``graph_steps`` steps are
  captured in one CUDA graph (``wp.ScopedCapture``); on the CPU device a block is a plain Python loop of
  ``graph_steps`` steps (smoke tests only; ``use_graph=True`` tries Warp's CPU graphs). Each of ``repeats``
  trials resets the peer to its initial state, runs ``warmup`` blocks untimed and times ``replays`` blocks
  (``wp.synchronize_device`` before reading the clock); the median trial is reported. So the figure covers
  steps ``[warmup * graph_steps, (warmup + replays) * graph_steps)`` of the driven motion, the record's
  ``window_steps`` (``window_s`` in simulated seconds), as kamino's do. (Until this rule, a trial here was
  sized to last 0.5 s from a replay count calibrated on one replay, and the simulation went on from trial to
  trial: a window of its own, while a step's cost follows the motion: on the four-bar kamino's PADMM
  iterations per block of 10 steps run 21, 20, 20, 27, 22, 38, 56, 160, 54, 36, 164 from reset.)
  The resets: **MuJoCo Warp** copies back every array of its ``Data`` (found by walking it, nested containers
  included), saved right after ``put_data``: ``time``, ``qpos``, ``qvel``, ``act``, ``ctrl``, the solver's warm
  start ``qacc_warmstart``, the applied forces, mocap and ``eq_active`` (MuJoCo's integration state) and every
  derived quantity as well, so nothing of a trial reaches the next (a second copy of ``Data`` on the device,
  made after the memory figure is read). **SolverKamino**: its public ``reset(state)`` clears the solver's own
  buffers (PADMM and the limit/contact warm-start caches, as far as the installed Newton's ``reset`` clears
  them; a Newton without it, or whose ``reset`` raises, keeps them, noted in ``notes``), then both states,
  the control and the drive's step counter are copied back from the arrays saved before the first step
  (``_newton_reset``). The graph is captured once, before the first trial, and the resets write into the
  arrays it was captured on.
* **drive**: before every step, the first actuator's control is set to ``A sin(2 pi 1.0 t)`` in every world
  by a small Warp kernel that reads a device time counter (MuJoCo Warp: ``Data.time``; Newton: a step
  counter bumped after every step), so that the timed loop is pure graph replay. ``A`` is the ``amplitude``
  keyword, ``DRIVE_AMPLITUDE`` = 2.0 by default. A ``<motor>`` (fourbar's ``drive_j1``, the ladders' only
  motor) is a torque ``A sin`` [N m]: MuJoCo Warp's ``ctrl[:, 0]``, Newton's ``Control.joint_f`` of its DoF
  (set to explicit effort). A ``<position kp kv>`` actuator (kamino's robots exported by
  ``kamino.save_mjcf``, driven with ``A = 0.2``) gets the position target ``A sin`` [rad] about its
  reference pose (the exporter gives actuated joints no ``ref``, so target 0 is the pose of the file):
  MuJoCo Warp's ``ctrl[:, 0]``, Newton's ``Control.joint_target_q`` of the joint's coordinate, with the PD
  gains that ``add_mjcf`` puts into ``joint_target_ke``/``kd`` (mode ``POSITION``) and the actuator's
  ``forcerange`` copied into ``joint_effort_limit`` (``add_mjcf`` keeps it only for ``SolverMuJoCo``). The
  other actuators keep their targets (0: the reference pose). A scene whose Newton import lacks those PD
  gains fails with a ``reason`` rather than being driven by torques.
* **loads** (MuJoCo Warp; :mod:`kamino.bench.loads`): ``gentle`` is the drive above; ``rl`` starts every world at
  rest in kamino's random loop-closed configuration of the same world (``random_configurations`` of the kamino
  model the MJCF describes, turned into MuJoCo's ``qpos`` by :func:`mujoco_qpos` and checked on the host by
  :func:`mujoco_pose_errors`) and sets every actuator, matched to kamino's by name, to kamino's draw for the
  world's control period of ``Data.time`` through the same ``@wp.func`` (:func:`kamino.bench.loads.rl_uniform`),
  so MuJoCo Warp's world ``w`` does what kamino's world ``w`` does. SolverKamino runs the ``gentle`` load.
* **time step**: both peers step with ``DT``; MuJoCo Warp's ``opt.timestep`` is set to it (a file without
  ``<option timestep>``, e.g. an exported robot, would otherwise run at MuJoCo's 0.002 s; noted). MuJoCo Warp's
  ``timestep``, ``iterations``, ``tolerance`` and the ``<connect>`` ``solref`` time constant ``timeconst`` can be
  set per run (:func:`run_mujoco_warp`, the accuracy sweep); the record's ``settings`` name what it ran with.
* **batch statistics** (MuJoCo Warp): after every step of the timed graphs a kernel folds, per world, the solver
  iterations (``Data.solver_niter``), whether the solver stopped before ``opt.iterations``, non-finite
  ``qpos``/``qvel`` and the largest ``<connect>`` anchor distance, into kamino's record keys
  (``closure_batch_max_m``, ``iterations_mean``/``_p99``/``_max``, ``converged_share``, ``failed_worlds``,
  ``batch_world_steps``; :class:`_MjwBatchStats`).
* **closure**: besides the batch's (MuJoCo Warp), ONE world, freshly built, stepped ``closure_steps`` times with
  the same drive (``gentle`` only); after every
  step a Warp kernel folds the largest distance between the two anchors of each loop-closing joint into
  a device scalar (``wp.atomic_max``). MuJoCo Warp: ``<connect>`` equalities, anchor ``eq_data[0:3]`` on
  body1 and ``eq_data[3:6]`` on body2 (MuJoCo's compiled connect semantics), through ``xpos``/``xmat``
  (these are the poses at the start of each step, so a final ``kinematics`` call adds the last pose).
  Newton: joints outside every articulation (``joint_articulation == -1``), parent anchor
  ``body_q[parent] * X_p`` vs child anchor ``body_q[child] * X_c``. ``joint_error_max_m`` is the same
  largest distance over every joint whose anchors coincide (kamino's own closure measure, which counts tree
  joints as well): Newton's SolverKamino keeps tree joints as constraints too, so it measures them (a robot
  without loops, ``bdx``, has only this figure); MuJoCo's tree joints are exact (generalized coordinates), so
  there it equals ``closure_max_m`` (0 without ``<connect>``).
* **memory per world**: device memory in use after building the N-world model and data (Newton: model,
  two states, control and the solver) minus before, divided by N. On CUDA the primary figure is Warp's
  memory-pool usage (``wp.get_mempool_used_mem_current``; ``cudaMemGetInfo`` used-memory delta if the
  pool is off). A second figure, ``memory_per_world_arrays_bytes``, sums the distinct owning
  ``wp.array`` allocations reachable from those objects (also the only figure on CPU).

Results are plain JSON-serialisable dicts with the keys ``peer, variant, scene`` (file stem), ``scene_path,
drive`` (what is driven, in words), ``drive_amplitude, num_worlds, throughput`` (steps/s x worlds),
``step_time_s, closure_max_m, joint_error_max_m, closure_steps, memory_per_world_bytes, memory_per_world_arrays_bytes,
memory_method, device, timing`` (``graph_replay`` or ``python_loop``), ``graph_steps, warmup_blocks,
replays_per_trial, repeats, trials_s, window_steps, window_s, dt, versions, notes, reason`` (plus ``source``,
``settings`` and ``sim_seconds_per_s`` for SolverKamino; ``load``, ``settings``, ``sim_seconds_per_s`` and the batch
statistics for MuJoCo Warp, and under ``rl`` ``seed``, ``start_pose_error_m`` and ``start_closure_m``). A peer that
is not importable, or that cannot load or run the scene, gives a dict whose measurements are ``None`` and whose
``reason`` says why (``traceback`` holds the details). The closure run does not depend on ``num_worlds``: when
sweeping world counts, pass ``closure_steps=0`` after the first.

Scenes in Newton: ``add_mjcf`` turns each ``<connect>`` into a BALL loop joint (3 rows, as MuJoCo's
connect), which SolverKamino simulates (an exported revolute loop closure, two ``<connect>`` on its axis,
becomes two BALL joints between the same bodies: 6 rows, one redundant, as in kamino's own round trip);
``source="newton_basics"`` instead builds the four-bar with ``newton.tests.utils.basics.build_boxes_fourbar``
(REVOLUTE loop joint), where the README's SolverKamino four-bar figures come from.

CLI smoke test: ``kamino bench peers fourbar 1 4 [--device cpu]`` (a shipped scene by name, or an MJCF file).
"""

from __future__ import annotations

import argparse
import functools
import gc
import importlib.metadata
import json
import math
import sys
import traceback
import warnings
import xml.etree.ElementTree as ET
from collections.abc import Callable
from pathlib import Path
from types import SimpleNamespace
from typing import Any

try:  # the peers run on Warp; without it every runner returns a result whose ``reason`` says so
    import warp as wp
except ImportError:  # pragma: no cover
    wp = None

from kamino.bench import scene_path, timed_window

DT = 0.0025
"""Time step [s] of every scene (their ``<option timestep>``); the peers are stepped with it."""
DRIVE_AMPLITUDE = 2.0
"""Drive torque amplitude [N m] on the first actuator."""
DRIVE_FREQUENCY = 1.0
"""Drive frequency [Hz]."""
KAMINO_VARIANTS = ("padmm_dense", "padmm_sparse_cr", "dvi", "dvi_sparse", "lox")
"""SolverKamino configurations: the first three are the README's; ``dvi_sparse`` and ``lox`` are extras."""
SCENE_SOURCES = ("mjcf", "newton_basics")
"""How the Newton scene is built: Newton's MJCF importer, or (four-bar only) ``build_boxes_fourbar``."""
KAMINO_SETTINGS = ("newton_example", "defaults")
"""PADMM settings: those of Newton's ``example_kamino_basic_fourbar`` (default here), or the Config defaults."""

_DISTRIBUTIONS = {"mujoco_warp": "mujoco-warp", "mujoco": "mujoco", "newton": "newton", "warp": "warp-lang"}


def peer_versions() -> dict[str, str | None]:
    """Installed versions of the peers and of what they run on (``None`` where a package is missing).

    Read from the package metadata, so nothing is imported.
    """
    versions: dict[str, str | None] = {}
    for key, dist in _DISTRIBUTIONS.items():
        try:
            versions[key] = importlib.metadata.version(dist)
        except importlib.metadata.PackageNotFoundError:
            versions[key] = None
    return versions


# --------------------------------------------------------------------------------------------------
# Shared helpers
# --------------------------------------------------------------------------------------------------


def _new_result(peer: str, variant: str, scene: str, num_worlds: int) -> dict[str, Any]:
    """Result dict with every measurement ``None``; filled in by the runners."""
    return {
        "peer": peer,
        "variant": variant,
        "scene": Path(scene).stem,
        "scene_path": str(scene),
        "drive": None,
        "drive_amplitude": None,
        "num_worlds": int(num_worlds),
        "throughput": None,
        "step_time_s": None,
        "closure_max_m": None,
        "joint_error_max_m": None,
        "memory_per_world_bytes": None,
        "memory_per_world_arrays_bytes": None,
        "memory_method": None,
        "device": None,
        "timing": None,
        "graph_steps": None,
        "warmup_blocks": None,
        "replays_per_trial": None,
        "repeats": None,
        "trials_s": None,
        "window_steps": None,
        "window_s": None,
        "closure_steps": None,
        "iterations_mean": None,
        "iterations_max": None,
        "converged_fraction": None,
        "dt": DT,
        "versions": peer_versions(),
        "notes": "",
        "reason": None,
    }


def _fail(result: dict[str, Any], stage: str, exc: BaseException) -> dict[str, Any]:
    """Record why a run stopped; the measurements gathered so far are kept."""
    result["reason"] = f"{stage}: {type(exc).__name__}: {exc}"
    result["traceback"] = traceback.format_exc(limit=6)
    return result


def _add_note(result: dict[str, Any], note: str) -> None:
    result["notes"] = f"{result['notes']}; {note}" if result["notes"] else note


@functools.cache
def _kernels() -> SimpleNamespace:
    """The small Warp kernels of the benchmark (drives, time counter, closure, MuJoCo Warp's batch statistics),
    defined once on demand. MuJoCo Warp's ``rl`` drive draws through the same ``@wp.func`` as kamino's
    (:func:`kamino.bench.loads.rl_uniform`)."""
    from kamino.bench.loads import rl_period, rl_uniform

    @wp.kernel
    def mjw_drive(
        time_: wp.array(dtype=wp.float32),
        actuator: int,
        amplitude: float,
        omega: float,
        ctrl: wp.array2d(dtype=wp.float32),
    ):
        world = wp.tid()
        ctrl[world, actuator] = amplitude * wp.sin(omega * time_[world])

    @wp.kernel
    def counter_drive(
        counter: wp.array(dtype=wp.int32),
        index: wp.array(dtype=wp.int32),
        offset: wp.array(dtype=wp.float32),
        amplitude: float,
        omega: float,
        dt: float,
        values: wp.array(dtype=wp.float32),
    ):
        world = wp.tid()
        t = float(counter[0]) * dt
        values[index[world]] = offset[world] + amplitude * wp.sin(omega * t)

    @wp.kernel
    def tick(counter: wp.array(dtype=wp.int32)):
        counter[0] = counter[0] + 1

    @wp.kernel
    def mjw_closure(
        xpos: wp.array2d(dtype=wp.vec3),
        xmat: wp.array2d(dtype=wp.mat33),
        body1: wp.array(dtype=wp.int32),
        body2: wp.array(dtype=wp.int32),
        anchor1: wp.array(dtype=wp.vec3),
        anchor2: wp.array(dtype=wp.vec3),
        out: wp.array(dtype=wp.float32),
    ):
        world, i = wp.tid()
        b1 = body1[i]
        b2 = body2[i]
        p1 = xpos[world, b1] + xmat[world, b1] @ anchor1[i]
        p2 = xpos[world, b2] + xmat[world, b2] @ anchor2[i]
        wp.atomic_max(out, world % out.shape[0], wp.length(p1 - p2))

    @wp.kernel
    def mjw_rl_drive(
        time_: wp.array(dtype=wp.float32),
        actuator: wp.array(dtype=wp.int32),
        offset: wp.array(dtype=wp.float32),
        scale: wp.array(dtype=wp.float32),
        rate: float,
        half_dt: float,
        seed: int,
        ctrl: wp.array2d(dtype=wp.float32),
    ):
        world, a = wp.tid()
        period = rl_period(time_[world], half_dt, rate)
        u = rl_uniform(seed, period, world, a, ctrl.shape[0], offset.shape[0])
        ctrl[world, actuator[a]] = offset[a] + scale[a] * u

    @wp.kernel
    def mjw_fold(
        niter: wp.array(dtype=wp.int32),
        cap: int,
        qpos: wp.array2d(dtype=wp.float32),
        qvel: wp.array2d(dtype=wp.float32),
        it_sum: wp.array(dtype=wp.int64),
        it_max: wp.array(dtype=wp.int32),
        conv: wp.array(dtype=wp.int32),
        fail: wp.array(dtype=wp.int32),
        steps: wp.array(dtype=wp.int32),
        histogram: wp.array(dtype=wp.int32),
    ):
        world = wp.tid()
        k = niter[world]
        it_sum[world] = it_sum[world] + wp.int64(k)
        it_max[world] = wp.max(it_max[world], k)
        wp.atomic_add(histogram, wp.min(k, histogram.shape[0] - 1), 1)
        bad = wp.int32(0)
        for i in range(qpos.shape[1]):
            if not wp.isfinite(qpos[world, i]):
                bad = 1
        for i in range(qvel.shape[1]):
            if not wp.isfinite(qvel[world, i]):
                bad = 1
        if bad != 0:
            fail[world] = fail[world] + 1
        elif k < cap:
            conv[world] = conv[world] + 1
        steps[world] = steps[world] + 1

    @wp.kernel
    def newton_closure(
        body_q: wp.array(dtype=wp.transform),
        joints: wp.array(dtype=wp.int32),
        joint_parent: wp.array(dtype=wp.int32),
        joint_child: wp.array(dtype=wp.int32),
        joint_X_p: wp.array(dtype=wp.transform),
        joint_X_c: wp.array(dtype=wp.transform),
        out: wp.array(dtype=wp.float32),
    ):
        j = joints[wp.tid()]
        p = wp.transform_get_translation(joint_X_p[j])
        if joint_parent[j] >= 0:
            p = wp.transform_point(body_q[joint_parent[j]], p)
        c = wp.transform_get_translation(joint_X_c[j])
        if joint_child[j] >= 0:
            c = wp.transform_point(body_q[joint_child[j]], c)
        wp.atomic_max(out, 0, wp.length(p - c))

    return SimpleNamespace(
        mjw_drive=mjw_drive,
        counter_drive=counter_drive,
        tick=tick,
        mjw_closure=mjw_closure,
        mjw_rl_drive=mjw_rl_drive,
        mjw_fold=mjw_fold,
        newton_closure=newton_closure,
    )


def _resolve_device(device: str | None) -> Any:
    """The Warp device to run on: ``device`` if given, else Warp's preferred one (``cuda:0`` if present)."""
    wp.init()
    return wp.get_device(device) if device is not None else wp.get_preferred_device()


def _device_name(dev: Any) -> str:
    return f"{dev.alias} ({dev.name})"


def _memory_in_use(dev: Any) -> tuple[int | None, str]:
    """Device memory in use now [bytes] and how it was read; ``None`` on the CPU.

    Collects garbage first, so that arrays of earlier runs held only by reference cycles are freed.
    """
    gc.collect()
    wp.synchronize_device(dev)
    if not dev.is_cuda:
        return None, "cpu: no device memory counter (see memory_per_world_arrays_bytes)"
    if wp.is_mempool_enabled(dev):
        return int(wp.get_mempool_used_mem_current(dev)), "cuda mempool used bytes (wp.get_mempool_used_mem_current)"
    return int(dev.total_memory - dev.free_memory), "cudaMemGetInfo used bytes (memory pool off)"


def _reachable_arrays(*roots: Any, max_objects: int = 2_000_000) -> list[Any]:
    """The distinct ``wp.array`` objects reachable from ``roots`` (views included), in the order found.

    Walks the attributes, dataclass fields and slots of ``roots`` themselves and of the objects from the ``newton``
    and ``mujoco_warp`` packages they reach, and builtin containers.
    """
    seen: set[int] = set()
    arrays: list[Any] = []
    stack = list(reversed(roots))
    root_ids = {id(r) for r in roots}
    visited = 0
    while stack and visited < max_objects:
        obj = stack.pop()
        if id(obj) in seen:
            continue
        seen.add(id(obj))
        visited += 1
        if isinstance(obj, wp.array):
            arrays.append(obj)
            continue
        if isinstance(obj, dict):
            stack.extend(obj.values())
            continue
        if isinstance(obj, list | tuple | set | frozenset):
            stack.extend(obj)
            continue
        module = type(obj).__module__ or ""
        if id(obj) not in root_ids and not (module.startswith("newton") or module.startswith("mujoco_warp")):
            continue
        if isinstance(obj, type):
            continue
        fields = getattr(obj, "__dict__", None)
        if fields is not None:
            stack.extend(fields.values())
        for slot in getattr(type(obj), "__slots__", ()):
            if hasattr(obj, slot):
                stack.append(getattr(obj, slot))
    return arrays


def _owned_array_bytes(*roots: Any, max_objects: int = 2_000_000) -> int:
    """Bytes of the distinct owning ``wp.array`` allocations reachable from ``roots`` (:func:`_reachable_arrays`).

    Views (arrays without a deleter) are not counted, and each allocation is counted once by pointer.
    """
    allocations: dict[int, int] = {}
    for arr in _reachable_arrays(*roots, max_objects=max_objects):
        if arr.ptr and getattr(arr, "deleter", None) is not None:
            allocations[int(arr.ptr)] = max(allocations.get(int(arr.ptr), 0), int(arr.capacity))
    return sum(allocations.values())


def _snapshot(*roots: Any) -> list[tuple[Any, Any]]:
    """``(array, copy)`` for every non-empty ``wp.array`` reachable from ``roots`` (:func:`_reachable_arrays`): what
    :func:`_restore` writes back in place, so that a captured graph keeps its addresses."""
    return [(arr, wp.clone(arr)) for arr in _reachable_arrays(*roots) if arr.ptr and arr.size]


def _restore(snapshot: list[tuple[Any, Any]]) -> None:
    """Copy a :func:`_snapshot` back into its arrays (enqueued on the device; the caller synchronises)."""
    for arr, saved in snapshot:
        wp.copy(arr, saved)


def _time_steps(
    step: Callable[[], None],
    reset: Callable[[], None],
    dev: Any,
    *,
    graph_steps: int,
    replays: int,
    repeats: int,
    use_graph: bool,
    warmup: int = timed_window.WARMUP_BLOCKS,
    after_trial: Callable[[int], None] | None = None,
    before_timing: Callable[[int], None] | None = None,
    dt: float = DT,
) -> dict[str, Any]:
    """Time the benchmark's window of blocks of ``graph_steps`` calls of ``step`` (:mod:`kamino.bench.timed_window`).

    With ``use_graph`` one block is captured as a Warp graph (before the first trial: capturing runs nothing) and
    replayed; otherwise a block is a Python loop of ``graph_steps`` steps. Each of ``repeats`` trials calls ``reset``
    (the peer's initial state back into the arrays the graph was captured on), runs ``warmup`` blocks untimed and
    times ``replays`` blocks; the median trial is reported, with the window it covers. The device is synchronised
    before every clock read; ``before_timing(i)`` (untimed, after the warm-up) may zero statistics that the timed
    blocks fold, ``after_trial(i)`` (untimed) may read the state trial ``i`` ends in. ``dt`` [s] converts the window
    to simulated seconds.
    """
    if use_graph:
        with wp.ScopedCapture(device=dev) as capture:
            for _ in range(graph_steps):
                step()
        graph = capture.graph

        def block() -> None:
            wp.capture_launch(graph)

    else:

        def block() -> None:
            for _ in range(graph_steps):
                step()

    timing = timed_window.time_window(
        reset,
        block,
        lambda: wp.synchronize_device(dev),
        graph_steps=graph_steps,
        warmup=warmup,
        replays=replays,
        repeats=repeats,
        dt=dt,
        before_timing=before_timing,
        after_trial=after_trial,
    )
    return {"timing": "graph_replay" if use_graph else "python_loop", **timing}


def _run_closure_steps(step: Callable[[], None], dev: Any, n: int, graph_steps: int, use_graph: bool) -> None:
    """Run ``n`` steps, through graph replays of ``graph_steps`` steps where ``use_graph``."""
    done = 0
    if use_graph and n >= graph_steps:
        with wp.ScopedCapture(device=dev) as capture:
            for _ in range(graph_steps):
                step()
        while done + graph_steps <= n:
            wp.capture_launch(capture.graph)
            done += graph_steps
    while done < n:
        step()
        done += 1
    wp.synchronize_device(dev)


def _joint_actuators(scene: str) -> list[tuple[str, str, dict[str, str]]]:
    """``(kind, joint, attributes)`` of the scene's joint actuators in file order (``kind``: the element's tag,
    ``motor``, ``position``, ...; defaults classes are not resolved: the benchmark scenes and kamino's exports
    write every attribute on the element)."""
    root = ET.parse(scene).getroot()
    return [(act.tag, act.get("joint"), dict(act.attrib)) for acts in root.iter("actuator") for act in acts
            if act.get("joint")]


def _first_actuator(scene: str) -> tuple[str | None, str | None]:
    """``(joint, kind)`` of the scene's first joint actuator (``<actuator><motor joint=...>``: ``("j", "motor")``);
    ``(None, None)`` without one."""
    acts = _joint_actuators(scene)
    return (acts[0][1], acts[0][0]) if acts else (None, None)


def _drive_text(kind: str | None, joint: str | None, amplitude: float) -> str | None:
    """The drive in words, for the result's ``drive`` field."""
    if joint is None:
        return None
    wave = f"{amplitude:g} sin(2 pi {DRIVE_FREQUENCY:g} t)"
    if kind == "position":
        return f"position target {wave} rad on <position> actuator of joint {joint!r} (about its reference pose)"
    if kind == "motor":
        return f"torque {wave} N m on <motor> of joint {joint!r}"
    return f"ctrl[0] = {wave} on <{kind}> actuator of joint {joint!r}"


# --------------------------------------------------------------------------------------------------
# kamino poses as MuJoCo qpos (the rl load's starts)
# --------------------------------------------------------------------------------------------------


def _quat_rotate(q: Any, v: Any) -> Any:
    """``q v q*`` of ``(x, y, z, w)`` quaternions and vectors, broadcast over leading axes (host NumPy)."""
    import numpy as np

    u, w = q[..., :3], q[..., 3:]
    t = 2.0 * np.cross(u, v)
    return v + w * t + np.cross(u, t)


def _pose_mul(a: Any, b: Any) -> Any:
    """The pose ``a b`` of ``[..., 7]`` poses ``(position, quaternion x y z w)`` (host NumPy): ``b`` expressed in
    ``a``'s frame, carried to ``a``'s parent."""
    import numpy as np

    from kamino.hostmath import quat_mul

    qa, qb = np.moveaxis(a[..., 3:], -1, 0), np.moveaxis(b[..., 3:], -1, 0)
    return np.concatenate([a[..., :3] + _quat_rotate(a[..., 3:], b[..., :3]),
                           np.moveaxis(quat_mul(qa, qb), 0, -1)], axis=-1)


def _pose_inv(a: Any) -> Any:
    """The inverse of ``[..., 7]`` poses (host NumPy)."""
    import numpy as np

    qi = a[..., 3:] * np.array([-1.0, -1.0, -1.0, 1.0])
    return np.concatenate([-_quat_rotate(qi, a[..., :3]), qi], axis=-1)


def mujoco_qpos(scene: str, source: Any, body_q: Any) -> Any:
    """MuJoCo's ``qpos [num_worlds, nq]`` of the MJCF file ``scene`` for ``num_worlds`` configurations of the kamino
    model ``source`` (one world; ``body_q [num_worlds * source.num_bodies, 7]`` CoM poses, as
    :func:`kamino.bench.loads.random_configurations` gives them).

    ``source`` is the model that ``scene`` describes: ``kamino.load_mjcf(scene)`` itself, or the model that
    ``kamino.save_mjcf`` wrote to ``scene`` (a robot). Bodies are matched by name: :func:`kamino.io.import_mjcf` of
    ``scene`` gives kamino bodies on MuJoCo's inertial frames, each rigidly attached to the ``source`` body of the
    same name (a body that ``save_mjcf`` wrote has its frame on the source's CoM frame; MuJoCo puts the inertial frame
    on the principal axes), so its pose is the source pose times the fixed offset between the two reference poses
    ``body_q0``. :meth:`kamino.io.MjcfImport.qpos` then reads the joint coordinates of those poses: a hinge or slide
    its coordinate plus the joint's ``qpos0`` (MuJoCo's ``ref``), a ball or free joint its quaternion in MuJoCo's
    ``(w, x, y, z)`` order, a free joint the position of the body frame (not the CoM).

    Raises:
        ValueError: a body of the imported scene has no body of that name in ``source`` (for example a light body
            that ``load_mjcf`` adds to chain joints), or ``body_q`` is not a whole number of worlds.
    """
    import numpy as np

    from kamino.io import import_mjcf

    imp = import_mjcf(scene)
    names = {n: i for i, n in enumerate(source.body_names)}
    missing = [n for n in imp.model.body_names if n not in names]
    if missing:
        raise ValueError(f"mujoco_qpos: bodies {missing[:6]} of {Path(scene).name} have no body of that name in the "
                         "kamino model whose configurations are converted (pass the model the MJCF describes)")
    body_q = np.asarray(body_q, np.float64)
    if body_q.ndim != 2 or body_q.shape[1] != 7 or body_q.shape[0] % source.num_bodies:
        raise ValueError(f"mujoco_qpos: body_q must be [num_worlds * {source.num_bodies}, 7], got {body_q.shape}")
    body_q = body_q.reshape(-1, source.num_bodies, 7)
    sel = np.array([names[n] for n in imp.model.body_names], np.int64)
    ref_src = np.asarray(source.body_q0, np.float64)[sel]
    ref_imp = np.asarray(imp.model.body_q0, np.float64)
    offset = _pose_mul(_pose_inv(ref_src), ref_imp)  # the imported CoM frame in the source CoM frame
    return imp.qpos(_pose_mul(body_q[:, sel], offset[None]).astype(np.float32))  # kamino float32 poses


def mujoco_pose_errors(mjm: Any, qpos: Any, source: Any, body_q: Any) -> tuple[float, float]:
    """``(pose error, closure [m])`` of MuJoCo's ``qpos [num_worlds, nq]`` against kamino's ``body_q``
    (:func:`mujoco_qpos`), by ``mujoco.mj_kinematics`` of every world (host C MuJoCo): the pose error is the largest
    of the distances [m] between the CoM of each MuJoCo body (``xipos``) and that of the ``source`` body of the same
    name, and of the differences of their rotation matrices' entries (MuJoCo's inertial axes carried by the fixed
    rotation between the two frames at ``qpos0`` / ``body_q0``); the closure is the largest distance between the two
    anchors of any ``<connect>``. The check that the conversion puts MuJoCo in kamino's configurations."""
    import mujoco
    import numpy as np

    qpos = np.asarray(qpos, np.float64).reshape(-1, mjm.nq)
    body_q = np.asarray(body_q, np.float64).reshape(qpos.shape[0], source.num_bodies, 7)
    names = {n: i for i, n in enumerate(source.body_names)}
    pairs = [(b, names[n]) for b in range(1, mjm.nbody)
             if (n := mujoco.mj_id2name(mjm, mujoco.mjtObj.mjOBJ_BODY, b)) in names]
    mj_b = np.array([p[0] for p in pairs], np.int64)
    src_b = np.array([p[1] for p in pairs], np.int64)

    def rotations(q):  # [n, 3, 3] rotation matrices of (x, y, z, w) quaternions
        return np.swapaxes(_quat_rotate(q[:, None, :], np.eye(3)[None]), -1, -2)

    d = mujoco.MjData(mjm)
    mujoco.mj_kinematics(mjm, d)
    ref = rotations(np.asarray(source.body_q0, float)[src_b, 3:])
    offset = np.swapaxes(d.ximat[mj_b].reshape(-1, 3, 3), -1, -2) @ ref  # kamino's axes in MuJoCo's inertial frame
    connects = [i for i in range(mjm.neq) if mjm.eq_type[i] == mujoco.mjtEq.mjEQ_CONNECT
                and mjm.eq_objtype[i] == mujoco.mjtObj.mjOBJ_BODY]
    pose_err = closure = 0.0
    for w in range(qpos.shape[0]):
        d.qpos[:] = qpos[w]
        mujoco.mj_kinematics(mjm, d)
        kam = body_q[w, src_b]
        rot = np.abs(d.ximat[mj_b].reshape(-1, 3, 3) @ offset - rotations(kam[:, 3:])).max()
        pose_err = max(pose_err, float(np.abs(d.xipos[mj_b] - kam[:, :3]).max()), float(rot))
        for i in connects:
            b1, b2 = int(mjm.eq_obj1id[i]), int(mjm.eq_obj2id[i])
            p1 = d.xpos[b1] + d.xmat[b1].reshape(3, 3) @ mjm.eq_data[i, 0:3]
            p2 = d.xpos[b2] + d.xmat[b2].reshape(3, 3) @ mjm.eq_data[i, 3:6]
            closure = max(closure, float(np.linalg.norm(p1 - p2)))
    return pose_err, closure


# --------------------------------------------------------------------------------------------------
# MuJoCo Warp
# --------------------------------------------------------------------------------------------------


#: the settings that :func:`run_mujoco_warp` can override (its keywords, the accuracy sweep of ``kamino bench``)
MJW_SETTINGS = ("timeconst", "timestep", "iterations", "tolerance")


def _mjw_settings(mjm: Any, *, timeconst: float | None = None, timestep: float | None = None,
                  iterations: int | None = None, tolerance: float | None = None) -> dict[str, Any]:
    """Apply the accuracy settings to the host model ``mjm`` (before ``put_model``) and return those it runs with.

    ``timestep`` [s] is ``opt.timestep`` (default ``DT``); ``iterations`` and ``tolerance`` are the constraint solver's
    ``opt.iterations`` and ``opt.tolerance`` (default: the file's); ``timeconst`` [s] is the ``solref`` time constant
    ``eq_solref[:, 0]`` of every ``<connect>`` equality (default: the file's, e.g. 0.004 s in kamino's exports and
    MuJoCo's 0.02 s where a file sets none). MuJoCo keeps a time constant of at least ``2 timestep`` unless the
    ``refsafe`` flag is disabled (its constraint stays stable only then), so the returned ``timeconst_effective`` is
    ``max(timeconst, 2 timestep)``."""
    import mujoco
    import numpy as np

    mjm.opt.timestep = DT if timestep is None else float(timestep)
    if iterations is not None:
        if int(iterations) < 1:
            raise ValueError(f"iterations must be >= 1, got {iterations}")
        mjm.opt.iterations = int(iterations)
    if tolerance is not None:
        mjm.opt.tolerance = float(tolerance)
    connect = np.asarray(mjm.eq_type) == int(mujoco.mjtEq.mjEQ_CONNECT)
    if timeconst is not None:
        if not timeconst > 0:
            raise ValueError(f"timeconst must be > 0 s, got {timeconst}")
        mjm.eq_solref[connect, 0] = float(timeconst)
    dt = float(mjm.opt.timestep)
    tcs = sorted({float(v) for v in mjm.eq_solref[connect, 0]})
    refsafe = not (int(mjm.opt.disableflags) & int(mujoco.mjtDisableBit.mjDSBL_REFSAFE))

    def one(values: list[float]) -> Any:  # one value, or the distinct values, or None without <connect>
        return values[0] if len(values) == 1 else (values or None)

    return {"timestep": dt, "iterations": int(mjm.opt.iterations), "tolerance": float(mjm.opt.tolerance),
            "timeconst": one(tcs), "timeconst_effective": one([max(t, 2 * dt) if refsafe else t for t in tcs])}


def _mjw_build(scene: str, num_worlds: int, dev: Any, qpos: Any = None,
               **settings: Any) -> tuple[Any, Any, Any, float, dict[str, Any]]:
    """Host model, device ``Model``, ``num_worlds``-world ``Data`` of an MJCF scene (scene's own options, but
    ``opt.timestep = DT`` and the accuracy ``settings`` of :func:`_mjw_settings`), the file's own time step and the
    settings the model runs with.

    ``mj_forward`` runs on the host data first, so that MuJoCo Warp's default ``njmax`` covers the
    constraint rows present at the start (the ladders' 3 rows per ``<connect>``, a robot's contacts). With ``qpos``
    (``[num_worlds, nq]``: every world's own start, at rest) the host data is the world with the most constraint rows
    of up to 256 of them, and each world's ``qpos`` is then written into ``Data``.
    """
    import mujoco
    import mujoco_warp as mjw
    import numpy as np

    mjm = mujoco.MjModel.from_xml_path(str(scene))
    file_dt = float(mjm.opt.timestep)
    used = _mjw_settings(mjm, **settings)
    mjd = mujoco.MjData(mjm)
    mujoco.mj_forward(mjm, mjd)
    if qpos is not None:
        qpos = np.asarray(qpos, np.float64)
        if qpos.shape != (num_worlds, mjm.nq):
            raise ValueError(f"qpos must be [num_worlds, nq] = [{num_worlds}, {mjm.nq}], got {list(qpos.shape)}")
        probe = mujoco.MjData(mjm)
        for w in np.linspace(0, num_worlds - 1, min(num_worlds, 256)).astype(int):
            probe.qpos[:] = qpos[w]
            mujoco.mj_forward(mjm, probe)
            if probe.nefc > mjd.nefc:
                mjd.qpos[:] = qpos[w]
                mujoco.mj_forward(mjm, mjd)
    with wp.ScopedDevice(dev):
        m = mjw.put_model(mjm)
        # the file's <size nconmax> (contacts per world), as kamino's load_mjcf reads it; else MuJoCo Warp's default
        sizes = {"nconmax": int(mjm.nconmax)} if int(mjm.nconmax) >= 0 else {}
        d = mjw.put_data(mjm, mjd, nworld=num_worlds, **sizes)
        if qpos is not None:
            d.qpos.assign(qpos.astype(np.float32))
    return mjm, m, d, file_dt, used


def _mjw_rl_drive(mjm: Any, source: Any, dev: Any, seed: int, dt: float) -> SimpleNamespace:
    """The ``rl`` load's drive of MuJoCo Warp (:mod:`kamino.bench.loads`): per kamino actuator (kamino's order, the
    order of its draws) the MuJoCo actuator of the same name (as ``load_mjcf`` names it) and the map
    ``ctrl = offset + scale u`` of the draw ``u``: a ``<position>`` actuator's target is kamino's PD target (both
    measured from the reference pose: MuJoCo's ``ref`` is 0 under a position actuator in load_mjcf's and save_mjcf's
    files), a ``<motor>``'s ctrl kamino's DoF effort over its gear (MuJoCo applies ``gear ctrl``). MuJoCo actuators
    without a kamino namesake keep ctrl 0."""
    import mujoco
    import numpy as np

    from kamino.bench import loads
    from kamino.io._mjcf_features import obj_name

    offset, scale, effort = loads.rl_control_map(source)
    # kamino's names of MuJoCo's actuators: an unnamed one is ``actuator<index>`` to load_mjcf
    names = [obj_name(mujoco, mjm, mujoco.mjtObj.mjOBJ_ACTUATOR, i, "actuator") for i in range(mjm.nu)]
    index, problems = [], []
    for a, name in enumerate(source.actuator_names):
        if name not in names:
            problems.append(f"{name!r}: no MuJoCo actuator of that name")
            index.append(-1)
            continue
        i = names.index(name)
        index.append(i)
        motor = int(mjm.actuator_biastype[i]) == int(mujoco.mjtBias.mjBIAS_NONE)
        if motor != bool(effort[a]):
            problems.append(f"{name!r}: kamino {'effort' if effort[a] else 'PD'} actuator, MuJoCo "
                            f"{'motor' if motor else 'biased (position/velocity)'} actuator")
    if problems:
        raise ValueError(f"rl load: kamino's actuators do not map onto the MJCF's: {'; '.join(problems[:6])}")
    scale = np.where(effort, scale / np.asarray(source.actuator_gear, float), scale)
    return SimpleNamespace(
        actuator=wp.array(np.array(index, np.int32), dtype=wp.int32, device=dev),
        offset=wp.array(offset.astype(np.float32), dtype=wp.float32, device=dev),
        scale=wp.array(scale.astype(np.float32), dtype=wp.float32, device=dev),
        rate=float(loads.RL_RATE), half_dt=0.5 * float(dt), seed=int(seed))


class _MjwBatchStats:
    """MuJoCo Warp's statistics of the timed batch, as kamino's :class:`kamino.bench.loads.BatchStats`: after every
    step (captured in the graph with it) a kernel folds per world the solver iterations ``Data.solver_niter`` (sum,
    max, histogram), whether the solver stopped before ``opt.iterations`` (its tolerance met: the ``converged``
    count), whether ``qpos``/``qvel`` hold a non-finite number (failed), and a second kernel the largest distance
    between the two anchors of any ``<connect>`` per world. The anchors are read from ``xpos``/``xmat``, which a step
    computes from the poses it starts from: the fold covers the poses at the start of the timed steps (kamino's: at
    their ends, one step later)."""

    def __init__(self, num_worlds: int, cap: int, connects: tuple | None, dev: Any):
        self.num_worlds, self.cap, self.dev = num_worlds, int(cap), dev
        from kamino.bench import loads

        kinds = {"sum": wp.int64, "max": wp.int32, "converged": wp.int32, "failed": wp.int32, "steps": wp.int32}
        self.per_world = {k: wp.zeros(num_worlds, dtype=t, device=dev) for k, t in kinds.items()}
        self.histogram = wp.zeros(loads.HISTOGRAM_BINS, dtype=wp.int32, device=dev)
        self.connects = connects[:4] if connects is not None else None
        self.closure = wp.zeros(num_worlds, dtype=wp.float32, device=dev)

    def fold(self, d: Any) -> None:
        k, pw = _kernels(), self.per_world
        wp.launch(k.mjw_fold, dim=self.num_worlds, device=self.dev, inputs=[d.solver_niter, self.cap, d.qpos, d.qvel],
                  outputs=[pw["sum"], pw["max"], pw["converged"], pw["failed"], pw["steps"], self.histogram])
        if self.connects is not None:
            wp.launch(k.mjw_closure, dim=(self.num_worlds, self.connects[0].shape[0]), device=self.dev,
                      inputs=[d.xpos, d.xmat, *self.connects, self.closure])

    def reset(self) -> None:
        for a in (*self.per_world.values(), self.histogram, self.closure):
            a.zero_()

    def summary(self) -> dict[str, Any]:
        from kamino.bench import loads

        return loads.fold_summary(self.per_world, self.histogram, self.closure if self.connects is not None else None)


def _mjw_stepper(
    m: Any,
    d: Any,
    num_worlds: int,
    *,
    drive: bool = True,
    closure: tuple | None = None,
    amplitude: float = DRIVE_AMPLITUDE,
    rl: SimpleNamespace | None = None,
    stats: _MjwBatchStats | None = None,
) -> Callable[[], None]:
    """One benchmark step: the drive (``ctrl[:, 0] = amplitude sin(omega d.time)``, or with ``rl`` every actuator's
    draw of the ``rl`` load, :func:`_mjw_rl_drive`), ``mjw.step``, the optional closure and the batch statistics.

    ``ctrl`` is the actuator's own input: a torque for a ``<motor>``, a position target for a ``<position>``.
    """
    import mujoco_warp as mjw

    k = _kernels()
    omega = 2.0 * math.pi * DRIVE_FREQUENCY

    def step() -> None:
        if rl is not None:
            wp.launch(k.mjw_rl_drive, dim=(num_worlds, rl.offset.shape[0]),
                      inputs=[d.time, rl.actuator, rl.offset, rl.scale, rl.rate, rl.half_dt, rl.seed], outputs=[d.ctrl])
        elif drive:
            wp.launch(k.mjw_drive, dim=num_worlds, inputs=[d.time, 0, amplitude, omega], outputs=[d.ctrl])
        mjw.step(m, d)
        if closure is not None:
            wp.launch(k.mjw_closure, dim=(num_worlds, closure[0].shape[0]), inputs=[d.xpos, d.xmat, *closure])
        if stats is not None:
            stats.fold(d)

    return step


def _mjw_connects(mjm: Any, dev: Any) -> tuple | None:
    """Device arrays (body1, body2, anchor1, anchor2, out) of the model's ``<connect>`` equalities."""
    import mujoco
    import numpy as np

    b1, b2, a1, a2 = [], [], [], []
    for i in range(mjm.neq):
        if mjm.eq_type[i] != mujoco.mjtEq.mjEQ_CONNECT:
            continue
        o1, o2 = int(mjm.eq_obj1id[i]), int(mjm.eq_obj2id[i])
        if mjm.eq_objtype[i] == mujoco.mjtObj.mjOBJ_SITE:
            b1.append(int(mjm.site_bodyid[o1]))
            b2.append(int(mjm.site_bodyid[o2]))
            a1.append(mjm.site_pos[o1])
            a2.append(mjm.site_pos[o2])
        else:
            b1.append(o1)
            b2.append(o2)
            a1.append(mjm.eq_data[i, 0:3])
            a2.append(mjm.eq_data[i, 3:6])
    if not b1:
        return None
    return (
        wp.array(np.array(b1, np.int32), dtype=wp.int32, device=dev),
        wp.array(np.array(b2, np.int32), dtype=wp.int32, device=dev),
        wp.array(np.array(a1, np.float32), dtype=wp.vec3, device=dev),
        wp.array(np.array(a2, np.float32), dtype=wp.vec3, device=dev),
        wp.zeros(1, dtype=wp.float32, device=dev),
    )


def _mjw_overflow_note(d: Any) -> str | None:
    """A note if any world hit MuJoCo Warp's constraint (``njmax``) or contact (``naconmax``) capacity."""
    nefc = int(d.nefc.numpy().max())
    nacon = int(d.nacon.numpy()[0])
    notes = []
    if nefc > d.njmax:
        notes.append(f"nefc exceeded njmax={d.njmax}")
    if nacon > d.naconmax:
        notes.append(f"nacon exceeded naconmax={d.naconmax}")
    return ", ".join(notes) or None


#: largest pose error [m] of MuJoCo's ``rl`` starts against kamino's (:func:`mujoco_pose_errors`) that a run accepts:
#: a wrong joint map moves bodies by centimetres, float32 rounding and the FK tolerance by micrometres
START_POSE_TOL = 1e-4
#: worlds whose ``rl`` start :func:`run_mujoco_warp` checks on the host (evenly spaced, the first and last included)
START_CHECK_WORLDS = 256


def run_mujoco_warp(
    scene: str,
    num_worlds: int,
    *,
    device: str | None = None,
    graph_steps: int = 10,
    warmup: int = timed_window.WARMUP_BLOCKS,
    replays: int = 100,
    repeats: int = 3,
    closure_steps: int = 1000,
    use_graph: bool | None = None,
    amplitude: float = DRIVE_AMPLITUDE,
    load: str = "gentle",
    seed: int = 0,
    kamino_model: Any = None,
    timeconst: float | None = None,
    timestep: float | None = None,
    iterations: int | None = None,
    tolerance: float | None = None,
) -> dict[str, Any]:
    """Throughput, loop closure, solver statistics and memory of MuJoCo Warp on an MJCF scene under a load of
    :mod:`kamino.bench.loads`.

    The scene is loaded with ``mujoco.MjModel.from_xml_path`` and run with its own options (for these
    scenes: Newton solver, Euler, soft ``<connect>``; kamino's exported robots: Newton solver,
    ``implicitfast``, ``<connect>`` with ``solref`` 0.004) but the time step ``DT`` and the accuracy settings below,
    ``mujoco_warp.put_model`` / ``put_data(nworld=num_worlds)``, ``mujoco_warp.step``. See the module
    docstring for the method.

    Loads: ``gentle`` drives the first actuator with ``amplitude sin(2 pi t)`` from the file's pose (module
    docstring). ``rl`` starts every world at rest in kamino's random loop-closed configuration of that world
    (:func:`kamino.bench.loads.random_configurations` of ``kamino_model`` with ``seed``, converted by
    :func:`mujoco_qpos` and checked on the host by :func:`mujoco_pose_errors` for up to ``START_CHECK_WORLDS`` worlds:
    the record's ``start_pose_error_m`` and ``start_closure_m``) and drives every actuator with kamino's draws
    (:func:`_mjw_rl_drive`: the same ``@wp.func``, seed, control periods of ``Data.time`` and actuators by name), so
    world ``w`` of MuJoCo Warp does what world ``w`` of kamino's ``rl`` run does.

    The statistics of the timed batch (:class:`_MjwBatchStats`, folded after every step inside the timed graphs and
    zeroed before every trial's timed blocks: the record holds the last trial's) carry kamino's keys
    ``closure_batch_max_m``, ``iterations_mean``/``_p99``/``_max``, ``converged_share``, ``failed_worlds``,
    ``batch_steps`` and ``batch_world_steps``; ``sim_seconds_per_s`` is the simulated time per second of all worlds.

    Args:
        scene: MJCF path.
        num_worlds: number of worlds stepped together for the throughput.
        device: Warp device (``"cuda:0"``, ``"cpu"``); ``None`` picks Warp's preferred device.
        graph_steps: steps captured per graph (CUDA) or per timed block (CPU).
        warmup: untimed blocks after each trial's reset.
        replays: timed blocks per trial.
        repeats: timed trials, each from the initial ``Data`` (module docstring); the median is reported.
        closure_steps: steps of the one-world closure run of the ``gentle`` load (``closure_max_m``); 0 skips it.
            The ``rl`` load has none: its closure is the batch's.
        use_graph: capture graphs; ``None`` means on CUDA only.
        amplitude: drive amplitude ``A`` of ``ctrl[:, 0] = A sin(2 pi t)``: N m for a ``<motor>``, rad for a
            ``<position>`` actuator (the robots: 0.2). Not used by ``rl``.
        load: ``"gentle"`` or ``"rl"`` (:data:`kamino.bench.loads.LOADS`).
        seed: the ``rl`` load's seed (starts and draws), as kamino's.
        kamino_model: the one-world kamino model that ``scene`` describes, whose ``rl`` configurations and actuator
            ranges are used (a robot: the model ``kamino.save_mjcf`` wrote); default ``kamino.load_mjcf(scene)``.
        timeconst: the ``<connect>`` equalities' ``solref`` time constant [s] (``eq_solref[:, 0]``); MuJoCo keeps it
            at least ``2 timestep`` (``settings["timeconst_effective"]``). Default: the file's.
        timestep: ``opt.timestep`` [s]; default ``DT``. The window's ``window_s`` and ``sim_seconds_per_s`` use it.
        iterations: the solver's ``opt.iterations``; default: the file's.
        tolerance: the solver's ``opt.tolerance``; default: the file's.

    Returns:
        The result dict (module docstring) with ``load``, ``settings`` (what the run used, see :func:`_mjw_settings`)
        and the batch statistics; ``reason`` is set when something could not run. A run with any setting given
        names them in its ``variant`` too, so that records of a sweep stay apart.
    """
    given = {k: v for k, v in zip(MJW_SETTINGS, (timeconst, timestep, iterations, tolerance), strict=True)
             if v is not None}
    variant = " ".join(["newton_solver_soft_connect", *(f"{k}={v:g}" for k, v in given.items())])
    result = _new_result("mujoco_warp", variant, scene, num_worlds)
    result["drive_amplitude"] = float(amplitude) if load == "gentle" else None
    result["load"] = load
    try:
        import mujoco
        import mujoco_warp as mjw
    except Exception as exc:  # a missing or broken peer is a result, not an error
        return _fail(result, "import", exc)
    try:
        import numpy as np

        from kamino.bench import loads

        if load not in loads.LOADS:
            raise ValueError(f"load must be one of {loads.LOADS}, got {load!r}")
        dev = _resolve_device(device)
        result["device"] = _device_name(dev)
        graph = dev.is_cuda if use_graph is None else use_graph
        qpos = source = None
        if load == "rl":
            import kamino

            source = kamino.load_mjcf(scene) if kamino_model is None else kamino_model
            body_q = loads.random_configurations(
                source, kamino.replicate(source, num_worlds) if num_worlds > 1 else source, loads.RL_FRACTION, seed)
            qpos = mujoco_qpos(scene, source, body_q)
            result["seed"] = int(seed)
        with wp.ScopedDevice(dev):
            before, method = _memory_in_use(dev)
            mjm, m, d, file_dt, used = _mjw_build(scene, num_worlds, dev, qpos, **given)
            after, _ = _memory_in_use(dev)
            result["settings"] = used
            result["dt"] = dt = used["timestep"]
            result["memory_method"] = method
            if before is not None and after is not None:
                result["memory_per_world_bytes"] = (after - before) / num_worlds
            result["memory_per_world_arrays_bytes"] = _owned_array_bytes(m, d) / num_worlds
            rl = None
            if load == "rl":
                check = np.unique(np.linspace(0, num_worlds - 1, min(num_worlds, START_CHECK_WORLDS)).astype(int))
                err, closure = mujoco_pose_errors(mjm, qpos[check], source,
                                                  np.asarray(body_q).reshape(num_worlds, -1, 7)[check])
                result["start_pose_error_m"], result["start_closure_m"] = err, closure
                result["start_checked_worlds"] = int(check.size)
                if err > START_POSE_TOL:
                    raise ValueError(f"rl starts: MuJoCo's poses from the converted qpos differ from kamino's by "
                                     f"{err:g} m (> {START_POSE_TOL:g}): mujoco_qpos does not fit this scene")
                rl = _mjw_rl_drive(mjm, source, dev, seed, dt)
                result["drive"] = (f"rl load: {mjm.nu} actuators, random draws at {loads.RL_RATE:g} Hz from seed {seed}"
                                   " (kamino.bench.loads.rl_uniform), random loop-closed starts at rest")
            elif mjm.nu < 1:
                _add_note(result, "scene has no actuator: no drive")
            else:
                joint, kind = _first_actuator(scene)
                result["drive"] = _drive_text(kind, joint, amplitude)
            if file_dt != dt:
                _add_note(result, f"timestep {file_dt:g} s of the file replaced by {dt:g} s")
            if given.get("timeconst") is not None and used["timeconst_effective"] != used["timeconst"]:
                _add_note(result, f"connect timeconst {used['timeconst']:g} s below 2 timestep: MuJoCo uses "
                                  f"{used['timeconst_effective']:g} s (refsafe)")
            opt = mjm.opt
            _add_note(
                result,
                f"solver={mujoco.mjtSolver(opt.solver).name} integrator={mujoco.mjtIntegrator(opt.integrator).name} "
                f"cone={mujoco.mjtCone(opt.cone).name} iterations={opt.iterations} tolerance={opt.tolerance:g} "
                f"njmax={d.njmax} naconmax={d.naconmax}",
            )
    except Exception as exc:
        return _fail(result, "load", exc)

    try:
        with wp.ScopedDevice(dev):
            initial = _snapshot(d)  # the Data put_data made (with the rl starts): every trial starts from it
            stats = _MjwBatchStats(num_worlds, int(mjm.opt.iterations), _mjw_connects(mjm, dev), dev)
            step = _mjw_stepper(m, d, num_worlds, drive=mjm.nu > 0, amplitude=amplitude, rl=rl, stats=stats)
            step()  # compile and load the kernels outside any capture
            wp.synchronize_device(dev)
            timing = _time_steps(
                step,
                functools.partial(_restore, initial),
                dev,
                graph_steps=graph_steps,
                warmup=warmup,
                replays=replays,
                repeats=repeats,
                use_graph=graph,
                before_timing=lambda _, stats=stats: stats.reset(),
                dt=dt,
            )
            result.update(timing)
            result["throughput"] = num_worlds / timing["step_time_s"]
            result["sim_seconds_per_s"] = num_worlds * dt / timing["step_time_s"]
            result.update(stats.summary())
            overflow = _mjw_overflow_note(d)
            if overflow:
                _add_note(result, f"capacity hit during throughput run: {overflow}")
        del step, m, d, initial, stats  # free the N-world data before the closure run
        gc.collect()
    except Exception as exc:
        return _fail(result, "throughput", exc)

    if closure_steps > 0 and load == "gentle":
        try:
            with wp.ScopedDevice(dev):
                mjm1, m1, d1, _, _ = _mjw_build(scene, 1, dev, **given)
                connects = _mjw_connects(mjm1, dev)
                if connects is None:
                    _add_note(result, "no <connect> equality: no loop closure (tree joints are exact in MuJoCo)")
                    result["joint_error_max_m"] = 0.0
                else:
                    step = _mjw_stepper(m1, d1, 1, drive=mjm1.nu > 0, closure=connects, amplitude=amplitude)
                    _run_closure_steps(step, dev, closure_steps, graph_steps, graph)
                    mjw.kinematics(m1, d1)  # poses after the last step
                    wp.launch(
                        _kernels().mjw_closure, dim=(1, connects[0].shape[0]), inputs=[d1.xpos, d1.xmat, *connects]
                    )
                    result["closure_max_m"] = float(connects[4].numpy()[0])
                    result["joint_error_max_m"] = result["closure_max_m"]  # tree joints: exact
                    result["closure_steps"] = closure_steps
        except Exception as exc:
            return _fail(result, "closure", exc)
    return result


# --------------------------------------------------------------------------------------------------
# Newton SolverKamino
# --------------------------------------------------------------------------------------------------


def _kamino_config(variant: str, contact_free: bool, settings: str = "newton_example", *,
                   tolerance: float | None = None, iterations: int | None = None) -> Any:
    """``SolverKamino.Config`` of a benchmark variant (defaults otherwise).

    ``settings="newton_example"`` gives the PADMM variants the solver settings of Newton's
    ``example_kamino_basic_fourbar``: primal, dual and complementarity tolerances 1e-4 (default 1e-6),
    initial penalty ``rho_0 = 0.1`` (default 1.0) and ``geom_pair_net_force`` contact warm start; the rest
    (200 iterations max, acceleration, warm start from containers, preconditioning) are the defaults
    anyway. The README's SolverKamino figures are consistent with these: on the four-bar PADMM takes 8.4
    iterations per step on average with them and 94 (a quarter of the steps at the 200 cap) with the
    defaults (CPU, 400 steps, one world). DVI and LOX keep their defaults (the example sets none).
    ``settings="defaults"`` keeps every default. On top of either, ``tolerance`` sets PADMM's primal, dual and
    complementarity tolerances (DVI: its ``tolerance``) and ``iterations`` PADMM's ``max_iterations`` (DVI: its
    ``max_alternating_iterations``); a backend without these settings raises ``ValueError`` (the sweep of
    ``kamino bench --sk-sweep``).

    Kamino's own collision detector is on (default config: unified pipeline), as in Newton's four-bar
    example. For a scene without any collidable pair (``contact_free``: the ladders) its per-world contact
    capacity is set to 0, so that Kamino allocates no contact container: left to itself it sizes one from
    a geometry heuristic that ignores MJCF ``contype=0`` (at least 1000 contacts per world for DVI, or with
    the detector off), and its dense Delassus matrices with it (ladder8, one world: 80-117 MB instead of
    0.4 MB per world).

    * ``padmm_dense``: PADMM, dense Jacobian and dynamics, dense blocked LLT (``LLTB``), Newton's default.
    * ``padmm_sparse_cr``: PADMM, sparse Jacobian and dynamics, conjugate residual (``CR``) linear solver.
    * ``dvi``: DVI backend with its defaults (sparse Jacobian, RCM-reordered blocked LLT, PGS).
    * ``dvi_sparse``: DVI with sparse dynamics (CR) -- extra.
    * ``lox``: the experimental LOX backend -- extra.
    """
    from newton.solvers import SolverKamino

    common = {"use_collision_detector": True}
    if variant == "padmm_dense":
        cfg = SolverKamino.Config(dynamics_solver="padmm", sparse_jacobian=False, sparse_dynamics=False, **common)
    elif variant == "padmm_sparse_cr":
        cfg = SolverKamino.Config(dynamics_solver="padmm", sparse_jacobian=True, sparse_dynamics=True, **common)
        cfg.dynamics.linear_solver_type = "CR"
    elif variant == "dvi":
        cfg = SolverKamino.Config(dynamics_solver="dvi", **common)
    elif variant == "dvi_sparse":
        cfg = SolverKamino.Config(dynamics_solver="dvi", sparse_jacobian=True, sparse_dynamics=True, **common)
    elif variant == "lox":
        cfg = SolverKamino.Config(dynamics_solver="lox", **common)
    else:
        raise ValueError(f"unknown SolverKamino variant {variant!r}; one of {KAMINO_VARIANTS}")
    if settings == "newton_example":
        if cfg.dynamics_solver == "padmm":
            cfg.padmm.primal_tolerance = 1e-4
            cfg.padmm.dual_tolerance = 1e-4
            cfg.padmm.compl_tolerance = 1e-4
            cfg.padmm.rho_0 = 0.1
            cfg.padmm.contact_warmstart_method = "geom_pair_net_force"
    elif settings != "defaults":
        raise ValueError(f"unknown SolverKamino settings {settings!r}; one of {KAMINO_SETTINGS}")
    _set_solver_settings(cfg, tolerance=tolerance, iterations=iterations)
    if contact_free:
        cfg.collision_detector.max_contacts_per_world = 0
    cfg.validate()
    return cfg


#: the ``SolverKamino.Config`` sub-config and fields that ``tolerance`` and ``iterations`` set, per dynamics solver
SOLVER_KAMINO_SWEEP = {
    "padmm": ("padmm", {"tolerance": ("primal_tolerance", "dual_tolerance", "compl_tolerance"),
                        "iterations": ("max_iterations",)}),
    "dvi": ("dvi", {"tolerance": ("tolerance",), "iterations": ("max_alternating_iterations",)}),
}


def _set_solver_settings(cfg: Any, **values: float | int | None) -> None:
    """Set the :data:`SOLVER_KAMINO_SWEEP` fields of ``cfg``'s dynamics solver from ``values`` (``None``: keep);
    ``ValueError`` for a solver or a field that the installed Newton lacks, so that a swept run fails with a reason
    rather than run with a setting silently ignored."""
    given = {k: v for k, v in values.items() if v is not None}
    if not given:
        return
    if cfg.dynamics_solver not in SOLVER_KAMINO_SWEEP:
        raise ValueError(f"SolverKamino's {cfg.dynamics_solver!r} solver has no {', '.join(given)} setting here; "
                         f"these are set for {', '.join(SOLVER_KAMINO_SWEEP)}")
    name, fields = SOLVER_KAMINO_SWEEP[cfg.dynamics_solver]
    sub = getattr(cfg, name, None)
    for key, value in given.items():
        for field in fields[key]:
            if sub is None or not hasattr(sub, field):
                raise ValueError(f"SolverKamino.Config.{name}.{field} not found in the installed Newton")
            setattr(sub, field, value)


def _newton_world_builder(scene: str, source: str) -> tuple[Any, str]:
    """One world of the scene in a Newton ``ModelBuilder`` (Z up, SolverKamino attributes registered).

    ``mjcf``: ``ModelBuilder.add_mjcf`` (``<connect>`` becomes a BALL loop joint, Newton's default
    ``convert_mjc_equality_constraints=True``). ``newton_basics``: the four-bar of
    ``newton.tests.utils.basics.build_boxes_fourbar`` (REVOLUTE loop joint; actuator on joint 1 only), which
    the README's SolverKamino four-bar figures come from. Returns the builder and a note.
    """
    import newton

    builder = newton.ModelBuilder(up_axis=newton.Axis.Z)
    newton.solvers.SolverKamino.register_custom_attributes(builder)
    # MuJoCo's geom margin and gap default to 0; Newton's importer would otherwise take the builder's
    # rigid_gap (0.1 m) for geoms without a gap attribute, i.e. speculative contacts 10 cm away, which
    # keep PADMM from converging (200 iterations every step on the four-bar). Newton's Kamino examples
    # set the same zeros.
    builder.default_shape_cfg.margin = 0.0
    builder.default_shape_cfg.gap = 0.0
    if source == "mjcf":
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            builder.add_mjcf(str(scene))
        parallel = sum("Parallel joints" in str(w.message) for w in caught)
        for w in caught:  # pass on what is not the expected parallel-joint warning
            if "Parallel joints" not in str(w.message):
                warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)
        note = "scene from MJCF via newton add_mjcf (<connect> -> BALL loop joint; margin = gap = 0)"
        if parallel:
            note += (
                f"; {parallel} BALL loop joint(s) parallel to another joint between the same bodies (a revolute "
                "loop exported as two <connect>; Newton warns that parallel joints have undefined semantics)"
            )
        return builder, note
    if source == "newton_basics":
        if Path(scene).stem != "fourbar":
            raise ValueError("source='newton_basics' exists for fourbar only")
        from newton.tests.utils import basics

        basics.build_boxes_fourbar(builder=builder, actuator_ids=[1])
        return builder, "scene built by newton.tests.utils.basics.build_boxes_fourbar (REVOLUTE loop joint)"
    raise ValueError(f"unknown source {source!r}; one of {SCENE_SOURCES}")


def _find_joint(builder: Any, name: str) -> int:
    """Index of the builder joint labelled ``name`` (MJCF labels carry a path prefix)."""
    for j, label in enumerate(builder.joint_label):
        if label == name or label.endswith("/" + name):
            return j
    raise KeyError(f"no joint named {name!r} in the Newton scene")


def _newton_position_pd(world: Any, scene: str) -> tuple[int, int, list[str]]:
    """Check the PD that ``add_mjcf`` made of the scene's ``<position kp kv>`` actuators and copy their
    ``forcerange`` into ``joint_effort_limit`` (``add_mjcf`` keeps it only in SolverMuJoCo's custom attributes).

    Returns ``(actuators, limits copied, problems)``: ``problems`` names every ``<position>`` actuator whose
    joint DoF did not get mode ``POSITION`` with its ``kp`` (SolverKamino would not drive it as MuJoCo does).
    """
    import newton

    count, limited, problems = 0, 0, []
    for kind, joint, attrib in _joint_actuators(scene):
        if kind != "position":
            continue
        count += 1
        try:
            j = _find_joint(world, joint)
        except KeyError:
            problems.append(f"{joint}: no Newton joint of that name (merged into another joint?)")
            continue
        lin, ang = world.joint_dof_dim[j]
        if lin + ang != 1:
            problems.append(f"{joint}: Newton joint has {lin + ang} DoFs")
            continue
        dof = world.joint_qd_start[j]
        kp = float(attrib.get("kp", 1.0))
        if world.joint_target_mode[dof] != int(newton.JointTargetMode.POSITION) or world.joint_target_ke[dof] != kp:
            mode, ke = world.joint_target_mode[dof], world.joint_target_ke[dof]
            problems.append(f"{joint}: mode {mode} ke {ke} (expected POSITION, {kp})")
            continue
        if "forcerange" in attrib and attrib.get("forcelimited", "auto") != "false":
            world.joint_effort_limit[dof] = max(abs(float(v)) for v in attrib["forcerange"].split())
            limited += 1
    return count, limited, problems


def _newton_build(scene: str, num_worlds: int, dev: Any, source: str) -> SimpleNamespace:
    """Model (``num_worlds`` replicated worlds), the drive's target array and index per world, the loop joints.

    The drive writes ``offset + A sin(2 pi t)`` into ``getattr(control, drive_field)[drive_index]``: a
    ``<motor>``'s DoF in ``joint_f`` (the DoF set to explicit effort), or a ``<position>`` actuator's joint
    coordinate in ``joint_target_q`` (offset: the model's target there, the reference pose). Raises when a
    ``<position>`` actuator did not become a Newton PD (see ``_newton_position_pd``).
    """
    import newton
    import numpy as np

    world, note = _newton_world_builder(scene, source)
    drive_joint, drive_kind = _first_actuator(scene)
    if source == "mjcf":
        count, limited, problems = _newton_position_pd(world, scene)
        if problems:
            raise RuntimeError(
                f"Newton's add_mjcf did not make {len(problems)} of {count} <position> actuators a joint PD "
                f"(joint_target_ke/kd, mode POSITION): {'; '.join(problems[:4])}"
            )
        if count:
            note += (
                f"; {count} <position> actuators -> Newton joint PD (joint_target_ke = kp, joint_target_kd = kv, "
                f"mode POSITION), forcerange -> joint_effort_limit on {limited}"
            )
    drive_local, drive_field = None, None
    if drive_joint is not None:
        j = _find_joint(world, drive_joint)
        dof = world.joint_qd_start[j]
        if drive_kind == "motor":
            world.joint_target_mode[dof] = int(newton.JointTargetMode.EFFORT)  # an explicit-effort actuator
            drive_field = "joint_f"
        elif drive_kind == "position":
            drive_field = "joint_target_q"  # a 1-DoF joint (checked above): its one coordinate
        else:
            raise ValueError(f"first actuator <{drive_kind}> of joint {drive_joint!r}: no drive for this kind")
        drive_local = j
    joints_per_world = world.joint_count
    builder = newton.ModelBuilder(up_axis=newton.Axis.Z)
    newton.solvers.SolverKamino.register_custom_attributes(builder)
    builder.replicate(world, num_worlds)
    model = builder.finalize(device=dev, skip_validation_joints=True)

    joint_world = model.joint_world.numpy()
    in_worlds = np.flatnonzero(joint_world >= 0)
    if in_worlds.size != num_worlds * joints_per_world:
        raise RuntimeError("unexpected joint layout after replicate")
    per_world = in_worlds.reshape(num_worlds, joints_per_world)
    if not np.array_equal(joint_world[per_world[:, 0]], np.arange(num_worlds)):
        raise RuntimeError("unexpected joint order after replicate")
    drive_index = drive_offset = None
    if drive_local is not None:
        joints = per_world[:, drive_local]
        if drive_field == "joint_f":
            drive_index = model.joint_qd_start.numpy()[joints]
            drive_offset = np.zeros(num_worlds)
        else:
            drive_index = model.joint_q_start.numpy()[joints]
            drive_offset = model.joint_target_q.numpy()[drive_index]
        drive_index = drive_index.astype(np.int32)
        drive_offset = drive_offset.astype(np.float32)
    loops = np.flatnonzero(model.joint_articulation.numpy() < 0).astype(np.int32)
    return SimpleNamespace(
        model=model,
        drive_field=drive_field,
        drive_index=drive_index,
        drive_offset=drive_offset,
        drive_kind=drive_kind,
        drive_joint=drive_joint,
        loops=loops,
        note=note,
    )


def _newton_anchored_joints(model: Any) -> Any:
    """Joints whose two anchors coincide (REVOLUTE, BALL, FIXED, and D6 without linear axes), tree and loop.

    SolverKamino keeps every joint as constraint rows (maximal coordinates), so its tree joints drift too; the
    largest anchor distance over these is kamino's own closure measure (``closure_distance`` in
    :mod:`kamino.bench.throughput`: every joint whose first three rows are translational).
    """
    import newton
    import numpy as np

    jt = model.joint_type.numpy()
    lin = model.joint_dof_dim.numpy()[:, 0]
    T = newton.JointType
    keep = np.isin(jt, [int(T.REVOLUTE), int(T.BALL), int(T.FIXED)]) | ((jt == int(T.D6)) & (lin == 0))
    return np.flatnonzero(keep).astype(np.int32)


def _newton_sim(built: SimpleNamespace, variant: str, settings: str = "newton_example",
                **sweep: float | int | None) -> SimpleNamespace:
    """Solver, two states, control and the device-side drive arrays for a built Newton model (``sweep``:
    ``tolerance`` and ``iterations`` of :func:`_kamino_config`)."""
    from newton.solvers import SolverKamino

    model = built.model
    contact_free = int(model.shape_contact_pair_count) == 0
    config = _kamino_config(variant, contact_free, settings, **sweep)
    solver = SolverKamino(model, config=config)
    states = [model.state(), model.state()]
    control = model.control()
    counter = wp.zeros(1, dtype=wp.int32, device=model.device)
    index = offset = None
    if built.drive_index is not None:
        index = wp.array(built.drive_index, dtype=wp.int32, device=model.device)
        offset = wp.array(built.drive_offset, dtype=wp.float32, device=model.device)
    return SimpleNamespace(
        solver=solver, config=config, states=states, control=control, counter=counter, index=index, offset=offset
    )


def _padmm_status(solver: Any) -> Any:
    """SolverKamino's per-world PADMM status array (private attributes of Newton 1.8), or ``None``.

    Read only to report the peer's PADMM iterations next to kamino's; ``None`` for DVI or another layout.
    """
    padmm = getattr(getattr(solver, "_solver_kamino", None), "_solver_fd", None)
    data = getattr(padmm, "data", None) if padmm is not None and hasattr(padmm, "_step") else None
    return getattr(data, "status", None)


def _padmm_stats_kernel(status_dtype: Any) -> Any:
    """Kernel adding world 0's PADMM iterations and convergence flag of one step to ``out = [sum, conv, max]``."""

    def padmm_stats(status, out):
        s = status[0]
        out[0] = out[0] + s.iterations
        out[1] = out[1] + wp.where(s.converged > 0, 1, 0)
        out[2] = wp.max(out[2], s.iterations)

    # the struct type is only known here: set the annotations as objects (this module's are strings)
    padmm_stats.__annotations__ = {"status": wp.array(dtype=status_dtype), "out": wp.array(dtype=wp.int32)}
    return wp.kernel(padmm_stats)


def _newton_stepper(
    built: SimpleNamespace,
    sim: SimpleNamespace,
    closures: tuple = (),
    stats: wp.array | None = None,
    amplitude: float = DRIVE_AMPLITUDE,
) -> Callable[[], None]:
    """One benchmark step: drive kernel into ``control.joint_f`` (``<motor>``) or ``control.joint_target_q``
    (``<position>``), ``SolverKamino.step``, swap, tick.

    ``closures`` holds ``(joints, out)`` pairs: after every step the largest anchor distance of ``joints`` is
    folded into ``out[0]``.

    With ``stats`` (an int32 array of 3), world 0's PADMM iterations are accumulated after every step on the
    device (see ``_padmm_stats_kernel``). The states are swapped in Python after every step, so a captured
    graph must hold an even number of steps to be replayable (see ``_even``).
    """
    status = _padmm_status(sim.solver) if stats is not None else None
    stats_kernel = None if status is None else _padmm_stats_kernel(status.dtype)
    k = _kernels()
    model = built.model
    omega = 2.0 * math.pi * DRIVE_FREQUENCY
    n_drive = 0 if sim.index is None else sim.index.shape[0]
    target = None if not n_drive else getattr(sim.control, built.drive_field)

    def step() -> None:
        if n_drive:
            wp.launch(
                k.counter_drive,
                dim=n_drive,
                inputs=[sim.counter, sim.index, sim.offset, amplitude, omega, DT],
                outputs=[target],
            )
        sim.solver.step(sim.states[0], sim.states[1], sim.control, None, DT)
        sim.states.reverse()
        wp.launch(k.tick, dim=1, inputs=[sim.counter])
        for joints, out in closures:
            wp.launch(
                k.newton_closure,
                dim=joints.shape[0],
                inputs=[
                    sim.states[0].body_q,
                    joints,
                    model.joint_parent,
                    model.joint_child,
                    model.joint_X_p,
                    model.joint_X_c,
                    out,
                ],
            )
        if stats_kernel is not None:
            wp.launch(stats_kernel, dim=1, inputs=[status, stats])

    return step


def _newton_reset(sim: SimpleNamespace, result: dict[str, Any]) -> Callable[[], None]:
    """The reset of a Newton run between timed trials, its initial state saved now (before any step).

    Each call asks SolverKamino to clear its internal buffers (its public ``reset(state)``: the PADMM warm start, the
    limit and contact warm-start caches and its internal time, as far as the installed Newton's ``reset`` clears
    them), then copies the saved initial arrays back into both states (poses, twists, the custom
    ``joint_q_prev``/``joint_lambdas`` attributes), the control and the drive's step counter. The copies come last,
    so that what ``reset`` writes into the state is replaced by the exact initial values. A Newton without
    ``SolverKamino.reset``, or one whose ``reset`` raises, keeps its internal caches from trial to trial; the
    result's ``notes`` say so.
    """
    initial = _snapshot(sim.states[0], sim.states[1], sim.control, sim.counter)
    solver_reset = getattr(sim.solver, "reset", None)
    if solver_reset is None:
        _add_note(result, "SolverKamino has no reset(): its internal warm starts carry over between timed trials")

    def reset() -> None:
        nonlocal solver_reset
        if solver_reset is not None:
            try:
                solver_reset(sim.states[0])
            except Exception as exc:  # keep timing; say what was not reset
                solver_reset = None
                _add_note(
                    result,
                    f"SolverKamino.reset failed ({type(exc).__name__}: {exc}); its internal warm starts carry over "
                    "between timed trials",
                )
        _restore(initial)

    return reset


def _even(n: int) -> int:
    """``n`` rounded up to an even count (captured Newton graphs must end on the state they start from)."""
    return n + (n % 2)


def run_solver_kamino(
    scene: str,
    num_worlds: int,
    *,
    device: str | None = None,
    variant: str = "padmm_dense",
    graph_steps: int = 10,
    warmup: int = timed_window.WARMUP_BLOCKS,
    replays: int = 100,
    repeats: int = 3,
    closure_steps: int = 1000,
    use_graph: bool | None = None,
    source: str = "mjcf",
    settings: str = "newton_example",
    amplitude: float = DRIVE_AMPLITUDE,
    tolerance: float | None = None,
    iterations: int | None = None,
) -> dict[str, Any]:
    """Throughput, loop closure and memory of Newton's ``SolverKamino`` on a benchmark scene.

    The scene is built once with Newton's builder (``source``: the same MJCF through ``add_mjcf``, or
    Newton's own procedural four-bar) and replicated to ``num_worlds`` worlds with
    ``ModelBuilder.replicate``. The drive goes into ``Control.joint_f`` of the first actuator's joint if it
    is a ``<motor>`` (set to explicit-effort actuation), into ``Control.joint_target_q`` of its coordinate if
    it is a ``<position>`` actuator (Newton's joint PD, see ``_newton_build``). Kamino's own collision
    detector is on (see ``_kamino_config``). See the module docstring for the method.

    Args:
        scene: MJCF path.
        num_worlds: number of worlds stepped together for the throughput.
        device: Warp device; ``None`` picks Warp's preferred device.
        variant: one of ``KAMINO_VARIANTS`` (``padmm_dense``, ``padmm_sparse_cr``, ``dvi``; extras
            ``dvi_sparse``, ``lox``).
        graph_steps: steps per captured graph / timed block; rounded up to even (state ping-pong).
        warmup: untimed blocks after each trial's reset.
        replays: timed blocks per trial.
        repeats: timed trials, each from the initial state (see ``_newton_reset``); the median is reported.
        closure_steps: steps of the one-world closure run; 0 skips it.
        use_graph: capture graphs; ``None`` means on CUDA only.
        source: ``"mjcf"`` or ``"newton_basics"`` (fourbar only), see ``SCENE_SOURCES``.
        settings: ``"newton_example"`` (PADMM tolerances 1e-4 etc., see ``_kamino_config``) or ``"defaults"``.
        amplitude: drive amplitude ``A``: a ``<motor>``'s torque ``A sin(2 pi t)`` [N m], a ``<position>``
            actuator's target ``offset + A sin(2 pi t)`` [rad] (the robots: 0.2).
        tolerance: the solver's tolerance on top of ``settings`` (PADMM: primal, dual and complementarity; DVI:
            its one), ``_kamino_config``; default: ``settings``'.
        iterations: PADMM's ``max_iterations`` (DVI: ``max_alternating_iterations``); default: ``settings``'.
            A ``tolerance`` or ``iterations`` given is named in the record's ``variant`` too
            (``padmm_dense tolerance=1e-06``), so that the records of a sweep stay apart.

    Returns:
        The result dict (module docstring); ``reason`` is set when something could not run.
    """
    sweep = {"tolerance": tolerance, "iterations": iterations}
    label = " ".join([variant, *(f"{k}={v:g}" for k, v in sweep.items() if v is not None)])
    result = _new_result("newton_solver_kamino", label, scene, num_worlds)
    result["source"] = source
    result["settings"] = settings
    result["drive_amplitude"] = float(amplitude)
    try:
        import newton  # noqa: F401
    except Exception as exc:
        return _fail(result, "import", exc)
    if variant not in KAMINO_VARIANTS:
        return _fail(result, "config", ValueError(f"unknown variant {variant!r}; one of {KAMINO_VARIANTS}"))
    graph_steps = _even(graph_steps)
    try:
        dev = _resolve_device(device)
        result["device"] = _device_name(dev)
        graph = dev.is_cuda if use_graph is None else use_graph
        with wp.ScopedDevice(dev):
            before, method = _memory_in_use(dev)
            built = _newton_build(scene, num_worlds, dev, source)
            sim = _newton_sim(built, variant, settings, **sweep)
            after, _ = _memory_in_use(dev)
            result["memory_method"] = method
            if before is not None and after is not None:
                result["memory_per_world_bytes"] = (after - before) / num_worlds
            result["memory_per_world_arrays_bytes"] = (
                _owned_array_bytes(built.model, sim.solver, sim.states, sim.control) / num_worlds
            )
            _add_note(result, built.note)
            if int(built.model.shape_contact_pair_count) == 0:
                _add_note(result, "Kamino collision detector on, no contact pairs: contact capacity 0")
            else:
                _add_note(result, "Kamino collision detector on (default config)")
            cfg = sim.config
            if cfg.dynamics_solver == "padmm":
                _add_note(
                    result,
                    f"PADMM tol={cfg.padmm.primal_tolerance:g}/{cfg.padmm.dual_tolerance:g}/"
                    f"{cfg.padmm.compl_tolerance:g} rho_0={cfg.padmm.rho_0:g} max_iter={cfg.padmm.max_iterations} "
                    f"linear_solver={cfg.dynamics.linear_solver_type}",
                )
            else:
                _add_note(result, f"{cfg.dynamics_solver} linear_solver={cfg.dynamics.linear_solver_type}")
            if built.drive_index is None:
                _add_note(result, "scene has no joint actuator: no drive")
            else:
                result["drive"] = _drive_text(built.drive_kind, built.drive_joint, amplitude)
                if built.drive_field == "joint_target_q":
                    result["drive"] += " -> Newton Control.joint_target_q"
            if built.loops.size == 0:
                _add_note(result, "no loop joint in the Newton model: no loop closure (joint_error_max_m: all joints)")
    except Exception as exc:
        return _fail(result, "load", exc)

    try:
        with wp.ScopedDevice(dev):
            reset = _newton_reset(sim, result)  # saves the initial state before any step
            step = _newton_stepper(built, sim, amplitude=amplitude)
            step()  # compile and load the kernels outside any capture
            step()
            wp.synchronize_device(dev)
            timing = _time_steps(
                step,
                reset,
                dev,
                graph_steps=graph_steps,
                warmup=warmup,
                replays=replays,
                repeats=repeats,
                use_graph=graph,
            )
            result.update(timing)
            result["throughput"] = num_worlds / timing["step_time_s"]
            result["sim_seconds_per_s"] = num_worlds * DT / timing["step_time_s"]
        del step, reset, built, sim  # free the N-world model before the closure run
        gc.collect()
    except Exception as exc:
        return _fail(result, "throughput", exc)

    if closure_steps > 0:
        try:
            with wp.ScopedDevice(dev):
                built1 = _newton_build(scene, 1, dev, source)
                anchored = _newton_anchored_joints(built1.model)
                if anchored.size:
                    sim1 = _newton_sim(built1, variant, settings, **sweep)
                    closures = tuple(
                        (wp.array(joints, dtype=wp.int32, device=dev), wp.zeros(1, dtype=wp.float32, device=dev))
                        for joints in (anchored, built1.loops)
                        if joints.size
                    )
                    stats = wp.zeros(3, dtype=wp.int32, device=dev)
                    step = _newton_stepper(built1, sim1, closures=closures, stats=stats, amplitude=amplitude)
                    _run_closure_steps(step, dev, closure_steps, graph_steps, graph)
                    result["joint_error_max_m"] = float(closures[0][1].numpy()[0])
                    if built1.loops.size:
                        result["closure_max_m"] = float(closures[1][1].numpy()[0])
                    result["closure_steps"] = closure_steps
                    if _padmm_status(sim1.solver) is not None:
                        total, conv, most = (int(v) for v in stats.numpy())
                        result["iterations_mean"] = total / closure_steps
                        result["iterations_max"] = most
                        result["converged_fraction"] = conv / closure_steps
        except Exception as exc:
            return _fail(result, "closure", exc)
    return result


# --------------------------------------------------------------------------------------------------
# CLI
# --------------------------------------------------------------------------------------------------


def _format(r: dict[str, Any]) -> str:
    def num(x: float | None, fmt: str) -> str:
        return "-" if x is None else format(x, fmt)

    closure_m = r.get("closure_batch_max_m", r["closure_max_m"])  # the timed batch's where measured
    closure = None if closure_m is None else 1e3 * closure_m
    joint_error = None if r["joint_error_max_m"] is None else 1e3 * r["joint_error_max_m"]
    mem = r["memory_per_world_bytes"]
    if mem is None:
        mem = r["memory_per_world_arrays_bytes"]
    variant = f"{r['variant']}/{r['settings']}" if r["peer"] == "newton_solver_kamino" else r["variant"]
    if r.get("load"):
        variant += f" [{r['load']}]"
    line = (
        f"{r['peer']:<21} {variant:<30} {r['scene']:<9} worlds={r['num_worlds']:<6} "
        f"throughput={num(r['throughput'], '.3g')} step={num(r['step_time_s'], '.3g')}s "
        f"closure={num(closure, '.3f')}mm joints={num(joint_error, '.3f')}mm "
        f"mem/world={num(None if mem is None else mem / 1024, '.1f')}KiB "
        f"[{r['timing']}] {r['device']}"
    )
    if r["reason"]:
        line += f"  FAILED {r['reason']}"
    return line


def main(argv: list[str] | None = None, prog: str | None = None) -> int:
    """Run both peers on one scene for the given world counts and print one line per result."""
    parser = argparse.ArgumentParser(prog=prog, description=__doc__.splitlines()[0])
    parser.add_argument("scene", help="a shipped scene's name (e.g. fourbar) or an MJCF file")
    parser.add_argument("worlds", nargs="+", type=int, help="world counts")
    parser.add_argument("--device", default=None, help="Warp device (default: Warp's preferred)")
    parser.add_argument("--peers", default="mujoco_warp,solver_kamino", help="comma list")
    parser.add_argument("--variants", default="padmm_dense,padmm_sparse_cr,dvi", help="SolverKamino variants")
    parser.add_argument("--source", default="mjcf", choices=SCENE_SOURCES, help="Newton scene source")
    parser.add_argument("--kamino-settings", default="newton_example", choices=KAMINO_SETTINGS)
    parser.add_argument("--graph-steps", type=int, default=10, help="steps per block (one graph)")
    parser.add_argument("--warmup", type=int, default=timed_window.WARMUP_BLOCKS, help="untimed blocks per trial")
    parser.add_argument("--replays", type=int, default=100, help="timed blocks per trial (100)")
    parser.add_argument("--repeats", type=int, default=3, help="trials, each from a reset; the median is reported")
    parser.add_argument("--closure-steps", type=int, default=1000, help="closure run once per peer/variant")
    parser.add_argument(
        "--amplitude", type=float, default=DRIVE_AMPLITUDE, help="drive amplitude: N m (<motor>), rad (<position>)"
    )
    parser.add_argument("--graph", action=argparse.BooleanOptionalAction, default=None, help="force graphs on/off")
    parser.add_argument("--load", default="gentle", choices=("gentle", "rl"),
                        help="MuJoCo Warp's load (kamino.bench.loads; rl from kamino.load_mjcf of the scene)")
    parser.add_argument("--json", default=None, help="write all results to this JSON file")
    parser.add_argument("--verbose", action="store_true", help="keep Warp's module-load messages")
    args = parser.parse_args(argv)
    if not Path(args.scene).is_file():
        try:
            args.scene = str(scene_path(args.scene))
        except ValueError as e:
            parser.error(f"scene: {args.scene} is not a file, and {e}")
    if wp is None:
        parser.error("the peers need warp-lang, which is not importable")
    if not args.verbose:
        wp.config.quiet = True
        wp.config.log_level = wp.LOG_WARNING
    peers = [p.strip() for p in args.peers.split(",") if p.strip()]
    common = {
        "device": args.device,
        "graph_steps": args.graph_steps,
        "warmup": args.warmup,
        "replays": args.replays,
        "repeats": args.repeats,
        "use_graph": args.graph,
        "amplitude": args.amplitude,
    }
    print("versions:", json.dumps(peer_versions()), flush=True)
    results = []
    jobs: list[tuple[str, Callable[..., dict[str, Any]], dict[str, Any]]] = []
    if "mujoco_warp" in peers:
        jobs.append(("mujoco_warp", run_mujoco_warp, {"load": args.load}))
    if "solver_kamino" in peers:
        for v in [v.strip() for v in args.variants.split(",") if v.strip()]:
            jobs.append(
                (
                    f"solver_kamino/{v}",
                    run_solver_kamino,
                    {"variant": v, "source": args.source, "settings": args.kamino_settings},
                )
            )
    for _, fn, extra in jobs:
        closure = None
        for i, n in enumerate(args.worlds):
            steps = args.closure_steps if i == 0 else 0  # the closure run is one world: do it once
            r = fn(args.scene, n, closure_steps=steps, **common, **extra)
            if i == 0:
                closure = (r["closure_max_m"], r["joint_error_max_m"], r["closure_steps"])
            else:
                r["closure_max_m"], r["joint_error_max_m"], r["closure_steps"] = closure
            results.append(r)
            print(_format(r), flush=True)
    if args.json:
        Path(args.json).write_text(json.dumps(results, indent=1))
    return 0 if all(r["reason"] is None for r in results) else 1


if __name__ == "__main__":
    sys.exit(main())
