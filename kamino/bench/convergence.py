"""Convergence of kamino's PADMM at the library defaults, scene by scene, on the Warp backend in float32.

    kamino bench convergence [--scenes fourbar dr_legs ...] [--worlds 4096] [--steps 1000]
                             [--no-sweep] [--no-stress] [--out FILE.json]
    kamino bench convergence --plot FILE.json     # FILE_speed_error.png, FILE_iterations.png (the bench extra)
    kamino bench convergence --table FILE.json    # a markdown table on stdout

(``python -m kamino.bench.convergence`` is the same command.)

Progress bars (tqdm, on stderr) over the scenes' runs and over each run's steps; ``--no-progress`` turns them off.
stdout carries the JSON records only, one a line.

Configuration: ``kamino.SolverConfig(dt=0.0025)`` and nothing else (every solver setting at its library
default: the adaptive penalty, tolerance 1e-3, ...), float32, Warp's CUDA device (its CPU device when there
is none: smoke runs, no throughput). The sweep changes ``tolerance`` only; ``serial_chain_dt1e-3`` changes
``dt`` only. ``--solver FIELD=VALUE ...`` sets settings (nested ones by their paths: ``warp.linear_solver=cr``)
on top of the defaults, for experiments (a candidate default measured beside the current one); the JSON records
them under ``solver_overrides`` and the whole configuration, nested as it is, under ``solver_config``.

Worlds are not copies of one another: a driven scene gives world ``w`` of ``W`` the drive phase
``2 pi w / W`` (a device-side pre-step hook, :func:`drive_hook`); an undriven scene starts world ``w`` with
the twist perturbation ``1e-2 (cos phase, sin phase, 0)`` added to every body's linear and angular velocity
(:func:`perturb`). Statistics over worlds are therefore over different trajectories.

Measured per scene (:func:`measure`), over every (world, step) pair of the run:

- ``converged_fraction``: the fraction of pairs whose PADMM converged (a failed world's pairs count as not
  converged); the mean / p50 / p99 / max PADMM iterations per step and their histogram (accumulated on the
  device every step by a pre-step hook, :class:`StepStats`, so the run replays CUDA graphs);
- ``failed_worlds``: worlds flagged ``failed`` at the end (non-finite, or unconverged for more than
  ``max_unconverged_steps`` consecutive steps: docs/conventions.md, "World health");
- ``closure_max_m``: the largest joint anchor distance (``throughput.closure_distance``'s definition: every
  joint whose first three rows are translational) over all worlds, every ``--sample-every`` steps, and
  ``closure_worst_worlds``, the five worlds with the largest (index: closure), to replay one of them;
- ``bilateral_velocity``: the joint rows' velocity errors for ``--sample-worlds`` worlds every
  ``--sample-every`` steps, with the JAX reference's joint Jacobian (:class:`VelocityProbe`): ``solve``
  ``|J(q_t) u+ + v*|`` (the residual of the rows PADMM solved, bias ``v*`` included), ``pre`` ``|J(q_t) u+|``
  and ``post`` ``|J(q_{t+1}) u+|`` (the constraint velocity of the new state), max over translational [m/s]
  and rotational [rad/s] rows;
- ``throughput``: world-steps/s after the run, over ``throughput.time_warp``'s timed window (each trial resets to the
  state the run ended in, ``--warmup`` blocks of ``--graph-steps`` steps untimed, ``--replays`` blocks timed; median
  of ``--repeats`` trials); ``None`` on the CPU;
- ``diverged``: a failed or non-finite world, or a closure above 1e-2 m;
- ``steps`` and ``truncated``: the steps run; with ``--time-limit`` a run that would pass the limit stops at the
  next sample and reports what it ran (``truncated: true``) instead of losing the record at a device call's
  limit (the robots' replays are latency-bound);
- for the free spinning body, the drift of the kinetic energy and of ``|L|`` relative to each world's start.
"""

import argparse
import dataclasses
import functools
import gc
import json
import math
import os
import pathlib
import platform
import subprocess
import sys
import time
from collections.abc import Callable

import numpy as np
from tqdm import tqdm

os.environ.setdefault("XLA_PYTHON_CLIENT_PREALLOCATE", "false")  # JAX (host probes) must not take Warp's GPU memory

import kamino
from kamino.bench import scene_path, stress_models
from kamino.bench.throughput import progress, solver_overrides, time_warp
from kamino.bench.timed_window import WARMUP_BLOCKS
from kamino.model import JOINT_CONSTRAINT_ROWS, RES_TRANS, ActuationMode, JointType

DT = 0.0025
TOLERANCES = (1e-2, 1e-3, 1e-4, 1e-5, 1e-6)
#: effort drive of the MJCF scenes (:mod:`kamino.bench.throughput`): ``2 N m sin(2 pi t + phase)`` on the first actuator
EFFORT_AMPLITUDE = 2.0
#: joint-space drive of the robots: every position target ``0.1 rad sin(2 pi t + phase)`` around its reference
TARGET_AMPLITUDE = 0.1
FREQUENCY = 1.0
#: initial twist perturbation of the undriven scenes [m/s and rad/s]
PERTURBATION = 1e-2
#: a closure above this [m] counts as diverged
DIVERGED_CLOSURE = 1e-2


# --------------------------------------------------------------------------------------------------- scenes
@dataclasses.dataclass(frozen=True)
class Scene:
    """A benchmark scene: ``build()`` gives the single-world model; ``drive`` is ``"effort"`` (first actuator),
    ``"targets"`` (every position target) or ``None`` (undriven: per-world initial perturbation); ``dt`` the
    time step; ``invariants``: report energy and ``|L|`` drift (torque-free scenes); ``stress``: part of the
    float32 stress suite (not swept)."""

    name: str
    build: Callable[[], kamino.Model]
    drive: str | None
    dt: float = DT
    invariants: bool = False
    stress: bool = False


def _mjcf(name: str) -> Callable[[], kamino.Model]:
    return lambda: kamino.load_mjcf(scene_path(name))


MAIN = (
    Scene("fourbar", _mjcf("fourbar"), "effort"),
    Scene("ladder8", _mjcf("ladder8"), "effort"),
    Scene("ladder32", _mjcf("ladder32"), "effort"),
    Scene("dr_legs", kamino.models.dr_legs, "targets"),
    Scene("bdx", kamino.models.bdx, "targets"),
    Scene("olaf", kamino.models.olaf, "targets"),
    Scene("animatronic", kamino.models.animatronic, "targets"),
    Scene("cradle5", lambda: kamino.models.newtons_cradle(5), None),
    Scene("box_stack10", lambda: kamino.models.box_stack(10), None),
)
STRESS = (
    Scene("mass_ratio_1e4", stress_models.mass_ratio_pendulum, None, stress=True),
    Scene("serial_chain20", stress_models.serial_chain, None, stress=True),
    Scene("serial_chain20_dt1e-3", stress_models.serial_chain, None, dt=1e-3, stress=True),
    *(Scene(f"fourbar_tilt{t}", functools.partial(stress_models.tilted_fourbar, float(t)), "effort", stress=True)
      for t in (1, 10, 45)),
    Scene("spinning_body", stress_models.spinning_body, None, invariants=True, stress=True),
    Scene("biped_connect", stress_models.biped_connect, "targets", stress=True),
)
SCENES = {s.name: s for s in (*MAIN, *STRESS)}


# ---------------------------------------------------------------------------------------------- device hooks
@functools.cache
def _kernels(np_dtype):
    """The drive and statistics kernels for states of ``np_dtype``."""
    import warp as wp

    from kamino.warp_backend.types import types_of

    scalar = types_of(np_dtype).scalar

    @wp.kernel(module="unique", enable_backward=False)
    def drive(time: wp.array(dtype=scalar), world: wp.array(dtype=wp.int32), dof: wp.array(dtype=wp.int32),
              offset: wp.array(dtype=scalar), phase: wp.array(dtype=scalar), amp: scalar, omega: scalar,
              effort_mode: int, effort: wp.array(dtype=scalar), target: wp.array(dtype=scalar)):
        i = wp.tid()
        w = world[i]
        v = offset[i] + amp * wp.sin(omega * time[w] + phase[w])
        if effort_mode != 0:
            effort[dof[i]] = v
        else:
            target[dof[i]] = v

    @wp.kernel(module="unique", enable_backward=False)
    def accumulate(iters: wp.array(dtype=wp.int32), converged: wp.array(dtype=wp.int32),
                   failed: wp.array(dtype=wp.int32), primed: wp.array(dtype=wp.int32), hist: wp.array(dtype=wp.int32),
                   hist_last: int, it_sum: wp.array(dtype=wp.int32), it_max: wp.array(dtype=wp.int32),
                   conv_steps: wp.array(dtype=wp.int32), fail_steps: wp.array(dtype=wp.int32),
                   steps: wp.array(dtype=wp.int32)):
        w = wp.tid()
        if primed[w] != 0:
            it = iters[w]
            wp.atomic_add(hist, wp.min(it, hist_last), 1)
            it_sum[w] = it_sum[w] + it
            it_max[w] = wp.max(it_max[w], it)
            if failed[w] != 0:
                fail_steps[w] = fail_steps[w] + 1
            elif converged[w] != 0:
                conv_steps[w] = conv_steps[w] + 1
            steps[w] = steps[w] + 1
        primed[w] = 1

    return drive, accumulate


def drive_hook(st, model: kamino.Model, drive: str, phase: np.ndarray):
    """A pre-step hook (captured with the step) setting each world's drive at its simulated time:
    ``"effort"``: ``2 N m sin(2 pi t + phase_w)`` (times the gear) on the world's first actuator, as
    ``throughput._drive_hook`` but with a phase per world; ``"targets"``: every POSITION DoF's target
    ``0.1 rad sin(2 pi t + phase_w)`` around its reference 0 (the robots' nominal pose, docs/robots.md)."""
    import warp as wp

    from kamino.warp_backend.types import types_of

    scalar = types_of(st.np_dtype).scalar
    if drive == "effort":
        first = model.world_actuator_start
        dof = model.actuator_dof[first]
        mode = int(model.dof_act_mode[dof[0]])
        effort_mode = int(mode == int(ActuationMode.EFFORT))
        amp = EFFORT_AMPLITUDE * (float(model.actuator_gear[first[0]]) if effort_mode else 1.0)
        world = np.arange(model.num_worlds)
    elif drive == "targets":
        dof = np.nonzero(model.dof_act_mode == int(ActuationMode.POSITION))[0]
        world = np.searchsorted(model.world_dof_start, dof, side="right") - 1
        effort_mode, amp = 0, TARGET_AMPLITUDE
    else:
        raise ValueError(f"unknown drive {drive!r}")
    arr = functools.partial(wp.array, device=st.device)
    world_w, dof_w = arr(world.astype(np.int32), dtype=wp.int32), arr(dof.astype(np.int32), dtype=wp.int32)
    off_w = arr(np.zeros(len(dof), st.np_dtype), dtype=scalar)
    phase_w = arr(phase.astype(st.np_dtype), dtype=scalar)
    kernel = _kernels(st.np_dtype)[0]

    def hook(s):
        wp.launch(kernel, dim=len(dof), device=s.device,
                  inputs=[s.work.time, world_w, dof_w, off_w, phase_w, amp, 2.0 * math.pi * FREQUENCY, effort_mode,
                          s.work.effort, s.work.position_target])
    return hook


def perturb(st, model: kamino.Model, phase: np.ndarray) -> None:
    """Add ``PERTURBATION (cos phase_w, sin phase_w, 0)`` to the linear and the angular velocity of every body of
    world ``w`` (an undriven scene's worlds then differ; a constrained body's share is removed by the first
    step's solve)."""
    u = st.work.u.numpy().reshape(-1, 6).astype(np.float64)
    ph = phase[model.body_world]
    d = PERTURBATION * np.stack([np.cos(ph), np.sin(ph), np.zeros_like(ph)], -1)
    u[:, :3] += d
    u[:, 3:] += d
    st.work.u.assign(u.astype(st.np_dtype))


class StepStats:
    """Per-step PADMM statistics accumulated on the device: the hook, run at the start of every step (so
    inside the captured graph), adds the previous step's ``iters``/``converged``/``failed`` of every world to
    per-world counters and to an iteration histogram; :meth:`flush` adds the last step's."""

    def __init__(self, st, cfg: kamino.SolverConfig):
        import warp as wp

        W = st.wm.num_worlds
        self.bins = 2 * int(cfg.max_iterations) + 2  # curvature refinement may run max_iterations twice
        z = functools.partial(wp.zeros, dtype=wp.int32, device=st.device)
        self.primed, self.it_sum, self.it_max = z(W), z(W), z(W)
        self.conv_steps, self.fail_steps, self.steps = z(W), z(W), z(W)
        self.hist = z(self.bins)
        self.kernel = _kernels(st.np_dtype)[1]

    def hook(self, s) -> None:
        import warp as wp

        w = s.work
        wp.launch(self.kernel, dim=s.wm.num_worlds, device=s.device,
                  inputs=[w.iters, w.converged, w.failed, self.primed, self.hist, self.bins - 1, self.it_sum,
                          self.it_max, self.conv_steps, self.fail_steps, self.steps])

    def flush(self, st) -> None:
        self.hook(st)

    def result(self) -> dict:
        hist = self.hist.numpy().astype(np.int64)
        n = int(hist.sum())
        k = np.arange(len(hist))
        cdf = np.cumsum(hist)
        pct = lambda p: int(np.searchsorted(cdf, p * n)) if n else None  # noqa: E731
        conv, steps = self.conv_steps.numpy(), self.steps.numpy()
        per_world_mean = self.it_sum.numpy() / np.maximum(steps, 1)
        return {
            "world_steps": n,
            "converged_fraction": float(conv.sum() / n) if n else None,
            "failed_world_steps": int(self.fail_steps.numpy().sum()),
            "iterations": {"mean": float((k * hist).sum() / n) if n else None, "p50": pct(0.5), "p99": pct(0.99),
                           "max": int(k[hist > 0].max()) if n else None,
                           "worst_world_mean": float(per_world_mean.max()) if n else None},
            "iterations_histogram": [[int(i), int(c)] for i, c in zip(k, hist, strict=True) if c],
        }


# ---------------------------------------------------------------------------------------------- host probes
def _rotate(q: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Rotate ``v`` by unit quaternions ``q = (x, y, z, w)`` (broadcast over leading axes)."""
    u, w = q[..., :3], q[..., 3:]
    t = 2.0 * np.cross(u, v)
    return v + w * t + np.cross(u, t)


class ClosureProbe:
    """Per-world loop closure of a replicated model, vectorised over worlds: the largest distance between
    the two anchors of a joint whose first three rows are translational (``throughput.closure_distance``)."""

    def __init__(self, base: kamino.Model):
        rows = [JOINT_CONSTRAINT_ROWS[JointType(int(t))] for t in base.joint_type]
        sel = np.array([j for j, r in enumerate(rows) if len(r) >= 3 and r[0][0] == 0 and r[2][0] == 2], int)
        self.nb = base.num_bodies
        self.parent, self.child = base.joint_parent[sel], base.joint_child[sel]
        self.anchor_B, self.anchor_F = base.joint_anchor_B[sel], base.joint_anchor_F[sel]

    def __call__(self, body_q: np.ndarray) -> np.ndarray:
        q = np.asarray(body_q, np.float64).reshape(-1, self.nb, 7)
        if not len(self.child):
            return np.zeros(q.shape[0])
        qF = q[:, self.child]
        pF = qF[..., :3] + _rotate(qF[..., 3:], self.anchor_F)
        qB = np.where((self.parent >= 0)[None, :, None], q[:, np.maximum(self.parent, 0)],
                      np.array([0, 0, 0, 0, 0, 0, 1.0]))
        pB = qB[..., :3] + _rotate(qB[..., 3:], self.anchor_B)
        return np.max(np.linalg.norm(pF - pB, axis=-1), axis=-1)


class VelocityProbe:
    """The joint rows' velocities of one world with the JAX reference's kinematics
    (``kamino.jax_ref.jacobians.joint_frames`` / ``constraint_jacobian`` on the padded single-world layout of
    ``kamino.jax_ref.types.layout_of``), vmapped over a few sampled worlds, on JAX's CPU device in JAX's default
    float (float32: a rounding floor of ~1e-7 |u|). For a step ``q_t -> q_{t+1}`` with free velocity ``u_f``
    and solved velocity ``u+`` (Euler: the step's evaluation pose is ``q_t``):

    - ``solve``: ``|J(q_t) u+ + v*|``, the residual of the row equation ``J u+ + v* = 0`` that PADMM solved, with
      the stabilisation bias ``v*`` of ``kamino.jax_ref.rows.joint_bias`` (Baumgarte + curvature along ``u_f``):
      what ``tolerance`` controls;
    - ``pre``: ``|J(q_t) u+|``, without the bias (the bias is O(dt |u|^2) by design: the curvature correction
      asks for that velocity so that the *position* error stays small);
    - ``post``: ``|J(q_{t+1}) u+|``, the constraint velocity of the new state.
    """

    def __init__(self, base: kamino.Model):
        import jax

        from kamino.jax_ref.types import layout_of

        self.cpu = jax.devices("cpu")[0]
        with jax.default_device(self.cpu):
            lay = layout_of(base)
            self.pm = jax.tree_util.tree_map(lambda x: x[0], lay.padded)
            self.trans = np.asarray(self.pm.row_kind == RES_TRANS) & np.asarray(self.pm.row_mask)
            self.rot = ~np.asarray(self.pm.row_kind == RES_TRANS) & np.asarray(self.pm.row_mask)
        self.nb, self.rows, self.dtype = lay.max_bodies, lay.max_rows, lay.dtype
        self._fns: dict = {}

    def _fn(self, cfg: kamino.SolverConfig):
        import jax

        from kamino.jax_ref.jacobians import constraint_jacobian, constraint_residual, joint_frames
        from kamino.jax_ref.rows import joint_bias

        if cfg not in self._fns:
            pm, nb = self.pm, self.nb

            def rows(q_pre, q_post, u_plus, u_f):
                jf = joint_frames(pm, q_pre)
                J = constraint_jacobian(pm, jf, nb)
                e = constraint_residual(pm, jf)
                v_star = joint_bias(pm, q_pre, u_f, e, e, J, cfg.dt, cfg)
                pre = J @ u_plus.reshape(-1)
                post = constraint_jacobian(pm, joint_frames(pm, q_post), nb) @ u_plus.reshape(-1)
                return pre + v_star, pre, post

            self._fns[cfg] = jax.jit(jax.vmap(rows))
        return self._fns[cfg]

    def __call__(self, cfg: kamino.SolverConfig, q_pre, q_post, u_plus, u_f) -> dict[str, tuple]:
        """Per quantity (``solve``, ``pre``, ``post``): the max over translational rows [m/s] and over rotational
        rows [rad/s], per sampled world (inputs ``[n, nb, 7]`` / ``[n, nb, 6]``)."""
        import jax

        with jax.default_device(self.cpu):
            args = [np.asarray(a, self.dtype) for a in (q_pre, q_post, u_plus, u_f)]
            out = [np.abs(np.asarray(v, np.float64)) for v in self._fn(cfg)(*args)]
        mx = lambda v, m: np.max(np.where(m, v, 0.0), axis=-1)  # noqa: E731
        return {key: (mx(v, self.trans), mx(v, self.rot)) for key, v in zip(("solve", "pre", "post"), out, strict=True)}


def invariants(base: kamino.Model, q: np.ndarray, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Kinetic energy ``[W]`` and angular momentum about the origin ``[W, 3]`` of every world
    (``q [W, nb, 7]``, ``u [W, nb, 6]``): the invariants of a torque-free system."""
    q, u = np.asarray(q, np.float64), np.asarray(u, np.float64)
    v, w = u[..., :3], u[..., 3:]
    wb = _rotate(q[..., 3:] * np.array([-1, -1, -1, 1.0]), w)  # body-frame angular velocity
    Iwb = np.einsum("bij,...bj->...bi", base.body_inertia, wb)
    ke = 0.5 * (base.body_mass * np.sum(v * v, -1) + np.sum(wb * Iwb, -1)).sum(-1)
    L = (_rotate(q[..., 3:], Iwb) + base.body_mass[:, None] * np.cross(q[..., :3], v)).sum(-2)
    return ke, L


# --------------------------------------------------------------------------------------------------- measure
def _world_slice(arr, w: int, per: int, width: int) -> np.ndarray:
    """World ``w``'s ``per`` rows of a flat per-body device array, on the host."""
    return arr[w * per:(w + 1) * per].numpy().reshape(per, width)


def _throughput(st, control, args) -> tuple[float | None, float | None]:
    """(world-steps/s, s per step) after the run, by ``throughput.time_warp``'s timed window
    (:mod:`kamino.bench.timed_window`): every trial starts again from the state the run ended in, runs ``--warmup``
    blocks of ``--graph-steps`` steps untimed and times ``--replays`` blocks; the median of ``--repeats`` trials.
    ``None`` on the CPU."""
    from kamino.warp_backend import backend as wb

    if not st.device.is_cuda:
        return None, None
    timing = time_warp(st, wb.read_state(st), control, args)
    return st.wm.num_worlds / timing["step_time_s"], timing["step_time_s"]


def measure(scene: Scene, base: kamino.Model, cfg: kamino.SolverConfig, args, device,
            probe: VelocityProbe | None) -> dict:
    """Run ``scene`` for ``--steps`` steps on ``--worlds`` worlds with ``cfg``; return its record (module doc)."""
    model = kamino.replicate(base, args.worlds) if args.worlds > 1 else base
    try:
        return _measure(scene, base, model, cfg, args, device, probe)
    finally:
        gc.collect()  # the run's stepper (device buffers) goes before the next scene's is built


def _measure(scene: Scene, base: kamino.Model, model: kamino.Model, cfg: kamino.SolverConfig, args, device,
             probe: VelocityProbe | None) -> dict:
    import warp as wp

    from kamino.warp_backend import backend as wb
    from kamino.warp_backend.pipeline import Stepper

    W, steps, every = args.worlds, args.steps, max(1, args.sample_every)
    state = kamino.init_state(model, np.float32)
    control = (kamino.Control(position_target=np.zeros(model.num_dofs, np.float32))
               if scene.drive == "targets" else None)
    st = Stepper(model, cfg, np.float32, device, padmm=args.padmm)
    st.pre_step.clear()
    st.invalidate_graphs()
    wb.load_state(st, state, control)
    phase = 2.0 * math.pi * np.arange(W) / W
    if scene.drive:
        st.pre_step.append(drive_hook(st, model, scene.drive, phase))
    else:
        perturb(st, model, phase)
    stats = StepStats(st, cfg)
    st.pre_step.append(stats.hook)
    nb = base.num_bodies
    sampled = sorted({int(w) for w in np.linspace(0, W - 1, min(args.sample_worlds, W))})
    closure = ClosureProbe(base)
    closure_max = np.zeros(W)
    vel: dict[str, tuple[list, list]] = {"solve": ([], []), "pre": ([], []), "post": ([], [])}
    inv0 = invariants(base, st.work.q.numpy().reshape(W, nb, 7), st.work.u.numpy().reshape(W, nb, 6)) \
        if scene.invariants else None
    inv_dev = {"energy": 0.0, "L_norm": 0.0, "L_vector": 0.0}
    wp.synchronize_device(st.device)
    t0 = time.perf_counter()
    done = 0
    with progress(args=args, total=steps, desc=f"{scene.name} tol {cfg.tolerance:g}", unit="step",
                  leave=False) as bar:
        while done < steps:
            if args.time_limit is not None and time.perf_counter() - t0 > args.time_limit:
                break  # report the steps run so far (module doc, ``--time-limit``)
            n = min(every, steps - done)
            if n > 1:
                st.run(n - 1)
            if probe is not None:
                q_pre = np.stack([_world_slice(st.work.q, w, nb, 7) for w in sampled])
            st.run(1)
            done += n
            bar.update(n)
            q_all = st.work.q.numpy().reshape(W, nb, 7)
            closure_max = np.maximum(closure_max, np.nan_to_num(closure(q_all), nan=np.inf))
            if probe is not None:
                u_s = np.stack([_world_slice(st.work.u, w, nb, 6) for w in sampled])
                uf_s = np.stack([_world_slice(st.work.u_f, w, nb, 6) for w in sampled])
                for key, (t, r) in probe(cfg, q_pre, q_all[sampled], u_s, uf_s).items():
                    vel[key][0].append(t)
                    vel[key][1].append(r)
            if inv0 is not None:
                ke, L = invariants(base, q_all, st.work.u.numpy().reshape(W, nb, 6))
                n0 = np.linalg.norm(inv0[1], axis=-1)
                inv_dev["energy"] = max(inv_dev["energy"], float(np.max(np.abs(ke / inv0[0] - 1))))
                inv_dev["L_norm"] = max(inv_dev["L_norm"], float(np.max(np.abs(np.linalg.norm(L, axis=-1) / n0 - 1))))
                inv_dev["L_vector"] = max(inv_dev["L_vector"], float(np.max(np.linalg.norm(L - inv0[1], axis=-1) / n0)))
    stats.flush(st)
    wp.synchronize_device(st.device)
    wall = time.perf_counter() - t0
    failed = st.work.failed.numpy() != 0
    q_end, u_end = st.work.q.numpy().reshape(W, -1), st.work.u.numpy().reshape(W, -1)
    nonfinite = ~(np.isfinite(q_end).all(-1) & np.isfinite(u_end).all(-1))
    rho = st.work.rho_u.numpy()
    rec = {
        "scene": scene.name, "suite": "stress" if scene.stress else "main", "tolerance": cfg.tolerance, "dt": cfg.dt,
        "drive": scene.drive or "perturbed initial twist", "num_worlds": W, "steps": done,
        "truncated": done < steps,
        "bodies": int(base.num_bodies), "joints": int(base.num_joints), "rows_max": int(st.wm.max_rows),
        "linear_solver": st.linear_solver, "padmm": st.padmm,
        **stats.result(),
        "failed_worlds": int(failed.sum()), "nonfinite_worlds": int(nonfinite.sum()),
        "closure_max_m": float(closure_max.max()), "closure_p99_over_worlds_m": float(np.quantile(closure_max, 0.99)),
        "closure_worst_worlds": {int(w): float(closure_max[w]) for w in np.argsort(closure_max)[::-1][:5]},
        "closure_sample_every": every,
        "penalty_final": {"min": float(rho.min()), "median": float(np.median(rho)), "max": float(rho.max())},
        "residuals_final_max": {k: float(np.nanmax(getattr(st.work, k).numpy())) for k in ("r_p", "r_d", "r_c")},
        "run_wall_s": wall, "run_world_steps_per_s": W * done / wall if wall > 0 else None,
    }
    if probe is not None and vel["solve"][0]:  # (none sampled when a time limit stopped the run at once)
        rec["bilateral_velocity"] = {"sampled_worlds": sampled, "sample_every": every, **{
            key: {"trans_max_m_s": float(np.max(t)), "rot_max_rad_s": float(np.max(r)),
                  "trans_mean_m_s": float(np.mean(t)), "rot_mean_rad_s": float(np.mean(r))}
            for key, (t, r) in vel.items()}}
    if inv0 is not None:
        rec["invariants_max_relative_drift"] = inv_dev
    rec["diverged"] = bool(rec["failed_worlds"] or rec["nonfinite_worlds"]
                           or not rec["closure_max_m"] <= DIVERGED_CLOSURE)
    st.pre_step.remove(stats.hook)
    st.invalidate_graphs()
    rec["throughput_world_steps_per_s"], rec["step_time_s"] = _throughput(st, control, args)
    rec["config"] = dataclasses.asdict(cfg)
    return rec


# ------------------------------------------------------------------------------------------------------ main
def environment(argv: list[str], device, overrides: dict | None = None) -> dict:
    """GPU (or CPU) name, versions, the exact command, and the measured configuration (the defaults, with the
    ``--solver`` ``overrides`` of an experiment)."""
    import jax
    import warp as wp

    try:
        rev = subprocess.run(["git", "describe", "--always", "--dirty"], cwd=pathlib.Path(__file__).resolve().parent,
                             capture_output=True, text=True, timeout=10).stdout.strip() or None
    except (OSError, subprocess.SubprocessError):
        rev = None
    return {"device": str(device), "gpu": device.name if device.is_cuda else None,
            "cpu": platform.processor() or platform.machine(), "warp": wp.__version__, "jax": jax.__version__,
            "kamino": kamino.__version__, "python": platform.python_version(), "git": rev,
            "date": time.strftime("%Y-%m-%d %H:%M:%S"),
            "command": " ".join(["kamino bench convergence", *argv]),
            "dtype": "float32",
            "solver_config": dataclasses.asdict(kamino.SolverConfig(dt=DT).replace(**(overrides or {}))),
            "solver_overrides": overrides or {}}


def _parser(prog: str | None = None) -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog=prog, description=__doc__.split("\n\n")[0],
                                epilog="The method and what each record holds: help(kamino.bench.convergence).")
    p.add_argument("--scenes", nargs="+", default=None, choices=list(SCENES), metavar="SCENE",
                   help=f"default: every scene ({', '.join(SCENES)})")
    p.add_argument("--worlds", type=int, default=4096)
    p.add_argument("--steps", type=int, default=1000)
    p.add_argument("--no-sweep", action="store_true", help="skip the tolerance sweep")
    p.add_argument("--no-stress", action="store_true", help="skip the float32 stress scenes")
    p.add_argument("--tolerances", nargs="+", type=float, default=list(TOLERANCES))
    p.add_argument("--sample-every", type=int, default=10, help="closure / |J u| sample period [steps]")
    p.add_argument("--sample-worlds", type=int, default=4, help="worlds whose |J u| is computed")
    p.add_argument("--graph-steps", type=int, default=10)
    p.add_argument("--warmup", type=int, default=WARMUP_BLOCKS)
    p.add_argument("--replays", type=int, default=10)
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--solver", nargs="+", default=[], metavar="FIELD=VALUE",
                   help="experiments only: SolverConfig settings (dotted: penalty.rho=0.05) set on top of the defaults "
                        "(recorded in the JSON)")
    p.add_argument("--padmm", choices=("thread", "warp"), default=None,
                   help="PADMM schedule (Stepper(padmm=...)): one thread or 32 threads per world (default: the "
                        "Stepper's choice)")
    p.add_argument("--device", default=None, help="Warp device (default: CUDA if available, else cpu)")
    p.add_argument("--time-limit", type=float, default=None, metavar="SECONDS",
                   help="stop a scene's run after this wall time and report the steps done (``truncated``)")
    p.add_argument("--out", type=pathlib.Path, default=None)
    p.add_argument("--plot", type=pathlib.Path, default=None, help="write PNGs from an existing JSON and exit")
    p.add_argument("--table", type=pathlib.Path, default=None, help="print a markdown table of a JSON and exit")
    p.add_argument("--no-progress", action="store_true", help="no progress bars (tqdm, on stderr)")
    return p


def main(argv: list[str] | None = None, prog: str | None = None) -> int:
    """``kamino bench convergence ARGS`` (``prog`` names the command in the help and errors); 0 when done."""
    argv = list(sys.argv[1:] if argv is None else argv)
    p = _parser(prog)
    args = p.parse_args(argv)
    from kamino._warp import quiet_warp

    quiet_warp()  # Warp's banner and module-load lines off stdout (KAMINO_WARP_VERBOSE=1 keeps them)
    if args.plot:
        try:
            import matplotlib  # noqa: F401
        except ImportError:
            p.error("--plot needs matplotlib, which is not installed: pip install 'kamino[bench]'")
        plot(json.loads(args.plot.read_text()), args.plot.with_suffix(""))
        return 0
    if args.table:
        print(table(json.loads(args.table.read_text())))
        return 0
    import warp as wp

    device = wp.get_device(args.device)
    names = args.scenes or list(SCENES)
    scenes = [SCENES[n] for n in names if not (args.no_stress and SCENES[n].stress)]
    overrides = solver_overrides(args.solver)
    results = {"environment": environment(argv, device, overrides), "records": []}

    def emit(rec: dict) -> None:
        results["records"].append(rec)
        brief = {k: v for k, v in rec.items() if k not in ("iterations_histogram", "config")}
        with tqdm.external_write_mode():  # the same line on stdout, the bars cleared around it on a terminal
            print(json.dumps(brief), flush=True)
        if args.out:
            args.out.write_text(json.dumps(results, indent=1))

    bar = progress(scenes, args=args, desc="convergence", unit="scene")
    for scene in bar:
        bar.set_description(scene.name)
        try:
            base = scene.build()
            probe = VelocityProbe(base) if base.num_constraints else None
        except Exception as e:  # keep going: report what failed
            emit({"scene": scene.name, "error": repr(e)[:500]})
            continue
        default = kamino.SolverConfig(dt=scene.dt).replace(**overrides)
        runs = [(default, False)]
        if not (args.no_sweep or scene.stress):
            runs += [(dataclasses.replace(default, tolerance=t), True) for t in args.tolerances]
        first = None
        for cfg, sweep in runs:
            try:
                if sweep and first is not None and cfg == default:
                    rec = dict(first)  # the default tolerance: the run above
                else:
                    rec = measure(scene, base, cfg, args, device, probe)
                    first = first or rec
                emit({**rec, "sweep": sweep})
            except Exception as e:
                emit({"scene": scene.name, "tolerance": cfg.tolerance, "sweep": sweep, "error": repr(e)[:500]})
    return 0


# ------------------------------------------------------------------------------------------- table and plots
def _fmt(x, spec: str = ".2g") -> str:
    return "—" if x is None else format(x, spec)


def table(results: dict) -> str:
    """A markdown table of every record: the default runs, the sweep, then the stress suite."""
    env = results["environment"]
    head = (f"{env.get('gpu') or env.get('cpu')}, warp {env['warp']}, jax {env['jax']}, float32, "
            f"`{env['command']}`\n\n"
            "| scene | tolerance | dt | worlds x steps | converged | iterations mean / p99 / max | failed worlds "
            "| closure max [m] | \\|J u+ + v*\\| trans [m/s] / rot [rad/s] | \\|J u+\\| post: trans / rot "
            "| world-steps/s | diverged |\n"
            "|---|---|---|---|---|---|---|---|---|---|---|---|")
    recs = results["records"]
    order = [r for r in recs if not r.get("sweep") and r.get("suite") == "main"]
    order += [r for r in recs if r.get("sweep")] + [r for r in recs if r.get("suite") == "stress"]
    order += [r for r in recs if "error" in r]
    lines = [head]
    for r in order:
        if "error" in r:
            lines.append(f"| {r['scene']} | {_fmt(r.get('tolerance'))} | error: {r['error'][:80]} ||||||||||")
            continue
        it = r["iterations"]
        bv = r.get("bilateral_velocity", {})
        bv_s = " | ".join(f"{_fmt(bv[k]['trans_max_m_s'])} / {_fmt(bv[k]['rot_max_rad_s'])}" if k in bv else "—"
                          for k in ("solve", "post"))
        tp = r.get("throughput_world_steps_per_s")
        name = r["scene"] + (" (sweep)" if r.get("sweep") else "")
        if r.get("invariants_max_relative_drift"):
            d = r["invariants_max_relative_drift"]
            name += f" (dE {_fmt(d['energy'])}, d\\|L\\| {_fmt(d['L_norm'])})"
        steps = f"{r['steps']}{' (time limit)' if r.get('truncated') else ''}"
        lines.append(f"| {name} | {_fmt(r['tolerance'])} | {_fmt(r['dt'])} | {r['num_worlds']} x {steps} "
                     f"| {_fmt(r['converged_fraction'], '.4f')} "
                     f"| {_fmt(it['mean'], '.1f')} / {_fmt(it['p99'], 'd')} / {_fmt(it['max'], 'd')} "
                     f"| {r['failed_worlds']} | {_fmt(r['closure_max_m'])} | {bv_s} | {_fmt(tp, '.3g')} "
                     f"| {'yes' if r['diverged'] else 'no'} |")
    return "\n".join(lines)


def plot(results: dict, stem: pathlib.Path) -> list[str]:
    """``<stem>_speed_error.png``: per scene, throughput against max loop closure over the tolerance sweep,
    each point labelled with its tolerance (the run's own world-steps/s where there is no throughput: CPU);
    ``<stem>_iterations.png``: the PADMM iterations-per-step histogram of each scene's default run. Drawn by
    :mod:`kamino.plots`; returns the paths written."""
    from kamino import plots

    recs = [r for r in results["records"] if "error" not in r]
    written = []
    swept = {r["scene"] for r in recs if r.get("sweep")}
    if swept:  # each swept scene's curve, its default run a point of it too
        written.append(plots.save_figure(plots.speed_against_error([r for r in recs if r["scene"] in swept]),
                                         f"{stem}_speed_error.png"))
    default = [r for r in recs if not r.get("sweep") and r.get("iterations_histogram")]
    if default:
        written.append(plots.save_figure(plots.iterations_histogram(default), f"{stem}_iterations.png"))
    return written


if __name__ == "__main__":
    raise SystemExit(main())
