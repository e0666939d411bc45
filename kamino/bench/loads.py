"""The loads of the throughput benchmark (:mod:`kamino.bench.throughput`) and the statistics taken from its timed batch.

Two loads drive every world of a scene:

* ``gentle``: every world starts in the same pose (a robot in its reference pose under PD) and follows one drive on
  its first actuator, ``0.2 sin(2 pi t)`` rad about the reference (a robot's PD target) or ``2 N m sin(2 pi t)``
  (a scene's motor). All worlds do the same thing, so no world is slower than the others.
* ``rl``: what a reinforcement-learning batch looks like. Each world starts at rest in its own loop-closed
  configuration: :func:`random_configurations` draws every actuated coordinate uniformly within ``RL_FRACTION`` of its
  range about the range's centre (:func:`actuator_ranges`), solves the poses with :func:`kamino.forward_kinematics`
  (every joint and loop closure) and sets a floating robot down on the ground, as the environments' resets do
  (:meth:`kamino.envs.base.KaminoEnv.reset_state`). Each world then follows its own random control sequence,
  resampled at ``RL_RATE`` (a policy's 50 Hz): every actuator's PD target is drawn uniformly within ``RL_FRACTION``
  of its range about the centre, a motor's torque uniformly within ``[-2, 2] N m`` (:func:`rl_drive_hook`). The
  floating robots stand, step, stumble and touch the ground; worlds differ, and a step waits for its slowest world.

:class:`BatchStats` folds, after every step of the timed window and inside the same CUDA graph, the PADMM iterations
(per world and step: mean, p99, max), the converged share, the failed worlds and the loop closure (the largest
anchor distance of any joint with translational rows, over every world and step) of the timed batch itself.
"""

import math

import jax
import jax.numpy as jnp
import numpy as np
import warp as wp

import kamino
from kamino.envs.geometry import place_on_ground, support_points
from kamino.kinematics import base_bodies
from kamino.model import JOINT_CONSTRAINT_ROWS, ActuationMode, JointType, Model, fingerprint

LOADS = ("gentle", "rl")
#: the rate [Hz] at which the ``rl`` load draws new controls (a policy's control rate)
RL_RATE = 50.0
#: the share of each actuator's half-range that the ``rl`` load's draws cover about its centre
RL_FRACTION = 0.5
#: the range [rad or m] taken for an actuated DoF without finite limits (the ladders' motor hinge): +-pi/4
UNBOUNDED_HALF_RANGE = math.pi / 4
#: a motor's torque bound [N m] under the ``rl`` load, the gentle drive's amplitude
MOTOR_AMPLITUDE = 2.0
#: bins of the iteration histogram; a step with more iterations counts in the last bin
HISTOGRAM_BINS = 1024


def actuator_ranges(model: Model) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(lo, hi, effort)`` per actuator of a one-world ``model`` (actuator order): the actuated DoF's limits
    intersected with the actuator's control range (a DoF without finite limits: ``+-UNBOUNDED_HALF_RANGE``), and
    whether the actuator is a motor (effort) rather than a PD (position) actuator."""
    dof = model.actuator_dof
    lo = np.maximum(model.dof_lower[dof], model.actuator_ctrl_range[:, 0])
    hi = np.minimum(model.dof_upper[dof], model.actuator_ctrl_range[:, 1])
    lo = np.where(np.isfinite(lo), lo, -UNBOUNDED_HALF_RANGE)
    hi = np.where(np.isfinite(hi), hi, UNBOUNDED_HALF_RANGE)
    if np.any(lo >= hi):
        bad = [model.actuator_names[i] for i in np.nonzero(lo >= hi)[0]]
        raise ValueError(f"actuator_ranges: actuators {bad} have an empty range")
    effort = model.dof_act_mode[dof] == int(ActuationMode.EFFORT)
    return lo, hi, effort


def random_configurations(base: Model, model: Model, fraction: float, seed: int, dtype=np.float32) -> np.ndarray:
    """``[num_bodies, 7]`` poses of ``model`` (``base`` replicated) with every world in its own loop-closed
    configuration: actuated coordinates uniform within ``fraction`` of :func:`actuator_ranges` about the centre,
    solved by :func:`kamino.forward_kinematics`; a floating robot set down on the ground at its reference base pose
    (:func:`kamino.envs.geometry.place_on_ground`). A world whose solve does not converge keeps the reference pose.
    The result is kept per mechanism (:func:`kamino.model.fingerprint` of ``base``), world count, fraction, seed and
    dtype, so that kamino and the peers start from the same poses without solving them again."""
    num_worlds = model.num_worlds
    key = (fingerprint(base), num_worlds, float(fraction), int(seed), np.dtype(dtype).str)
    if key in _STARTS:
        return _STARTS[key].copy()
    lo, hi = actuator_ranges(base)[:2]
    centre, half = 0.5 * (lo + hi), 0.5 * (hi - lo) * fraction
    u = np.random.default_rng(seed).uniform(-1.0, 1.0, (num_worlds, base.num_actuators))
    fk = kamino.forward_kinematics(model, actuated_positions=(centre + half * u).reshape(-1), dtype=dtype)
    body_q = np.asarray(fk.body_q).reshape(num_worlds, base.num_bodies, 7)
    body_q = np.where(np.asarray(fk.converged)[:, None, None], body_q, np.asarray(base.body_q0, dtype)[None])
    if base_bodies(base)[0] >= 0:
        pts, bodies, radii = support_points(base)
        body_q = np.asarray(jax.vmap(lambda q: place_on_ground(q, jnp.asarray(pts, q.dtype), bodies,
                                                               jnp.asarray(radii, q.dtype), 0.0))(jnp.asarray(body_q)))
    _STARTS[key] = body_q.reshape(-1, 7).astype(dtype)
    return _STARTS[key].copy()


#: :func:`random_configurations`' results of this process, by mechanism, world count, fraction, seed and dtype
_STARTS: dict[tuple, np.ndarray] = {}


@wp.func
def rl_period(time: float, half_dt: float, rate: float) -> int:
    """The control period ``floor((t + dt / 2) rate)`` of a step that starts at time ``t`` (the period holding the
    step's midpoint, which rounding of ``t`` does not move)."""
    return int(wp.floor((time + half_dt) * rate))


@wp.func
def rl_uniform(seed: int, period: int, world: int, actuator: int, num_worlds: int, num_actuators: int) -> float:
    """The ``rl`` load's draw ``u``, uniform in ``[-1, 1)``, of one actuator (kamino's actuator order) of one world in
    one control period: Warp's counter-based generator seeded by ``seed`` at counter
    ``(period num_worlds + world) num_actuators + actuator``. kamino's hook (:func:`rl_drive_hook`) and MuJoCo Warp's
    (:mod:`kamino.bench.peers`) both draw through it, so the two see bit-identical draws."""
    rng = wp.rand_init(seed, (period * num_worlds + world) * num_actuators + actuator)
    return 2.0 * wp.randf(rng) - 1.0


def rl_control_map(base: Model, fraction: float = RL_FRACTION) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(offset, scale, effort)`` per actuator of ``base`` (actuator order): the ``rl`` load sets actuator ``a`` to
    ``offset[a] + scale[a] u`` with ``u`` of :func:`rl_uniform`: a PD target ``centre + fraction half u`` on the DoF,
    or a motor's DoF effort ``MOTOR_AMPLITUDE gear u`` (``effort[a]``)."""
    lo, hi, effort = actuator_ranges(base)
    centre, half = 0.5 * (lo + hi), 0.5 * (hi - lo) * fraction
    scale = np.where(effort, MOTOR_AMPLITUDE * base.actuator_gear, half)
    offset = np.where(effort, 0.0, centre)
    return offset, scale, effort


def rl_drive_hook(st, base: Model, fraction: float = RL_FRACTION, rate: float = RL_RATE, seed: int = 0):
    """A pre-step hook (``Stepper.pre_step``) that sets every actuator of every world to its draw for the current
    control period (:func:`rl_period` of the world's time ``t``): ``offset + scale u`` of :func:`rl_control_map`, a
    PD target ``centre + fraction half u`` or a motor torque ``MOTOR_AMPLITUDE gear u``, ``u`` of :func:`rl_uniform`
    seeded by ``(seed, period, world, actuator)``. The draws depend on nothing else, so a reset replays them."""
    from kamino.warp_backend.types import types_of

    scalar = types_of(st.np_dtype).scalar
    num_worlds, na = st.wm.num_worlds, base.num_actuators
    offset, scale, effort = rl_control_map(base, fraction)
    dofs = (base.actuator_dof[None, :] + base.num_dofs * np.arange(num_worlds)[:, None]).reshape(-1)
    dev = st.device
    dof_w = wp.array(dofs.astype(np.int32), dtype=wp.int32, device=dev)
    off_w = wp.array(offset.astype(st.np_dtype), dtype=scalar, device=dev)
    scale_w = wp.array(scale.astype(st.np_dtype), dtype=scalar, device=dev)
    eff_w = wp.array(effort.astype(np.int32), dtype=wp.int32, device=dev)

    @wp.kernel(module="unique", enable_backward=False)
    def rl_drive(time: wp.array(dtype=scalar), dofs: wp.array(dtype=wp.int32), offset: wp.array(dtype=scalar),
                 scale: wp.array(dtype=scalar), is_effort: wp.array(dtype=wp.int32), rate: float, half_dt: float,
                 seed: int, num_worlds: int, effort_out: wp.array(dtype=scalar), target_out: wp.array(dtype=scalar)):
        w, a = wp.tid()
        na = offset.shape[0]
        period = rl_period(float(time[w]), half_dt, rate)
        v = offset[a] + scale[a] * scalar(rl_uniform(seed, period, w, a, num_worlds, na))
        d = dofs[w * na + a]
        if is_effort[a] != 0:
            effort_out[d] = v
        else:
            target_out[d] = v

    def hook(s):
        wp.launch(rl_drive, dim=(num_worlds, na), device=dev,
                  inputs=[s.work.time, dof_w, off_w, scale_w, eff_w, float(rate), 0.5 * float(st.cfg.dt), int(seed),
                          num_worlds],
                  outputs=[s.work.effort, s.work.position_target])

    return hook


def anchored_joints(model: Model) -> np.ndarray:
    """Indices of the joints whose first three rows are translational (revolute, spherical, universal, fixed: every
    loop-closing joint of the benchmark scenes): their two anchors coincide, and their distance is the closure."""
    sel = []
    for j in range(model.num_joints):
        rows = JOINT_CONSTRAINT_ROWS[JointType(int(model.joint_type[j]))]
        if len(rows) >= 3 and rows[0][0] == 0 and rows[2][0] == 2:
            sel.append(j)
    return np.asarray(sel, np.int64)


class BatchStats:
    """Per-step statistics of a Warp stepper's batch, folded on the device by a post-step hook
    (``Stepper.post_step``; captured with the step). :meth:`reset` zeroes them (at the start of the timed window),
    :meth:`summary` reads them."""

    def __init__(self, st):
        from kamino.warp_backend.types import types_of

        T = types_of(st.np_dtype)
        model, dev = st.wm.model, st.device
        self.num_worlds, self.device = st.wm.num_worlds, dev
        joints = anchored_joints(model)
        self.num_joints = len(joints)
        zeros = {"sum": wp.int64, "max": wp.int32, "converged": wp.int32, "failed": wp.int32, "steps": wp.int32}
        self.per_world = {k: wp.zeros(self.num_worlds, dtype=t, device=dev) for k, t in zeros.items()}
        self.histogram = wp.zeros(HISTOGRAM_BINS, dtype=wp.int32, device=dev)
        self.closure = wp.zeros(self.num_worlds, dtype=T.scalar, device=dev)
        par = model.joint_parent[joints].astype(np.int32)
        self._joint_arrays = [
            wp.array(par, dtype=wp.int32, device=dev),
            wp.array(model.joint_child[joints].astype(np.int32), dtype=wp.int32, device=dev),
            wp.array(model.joint_anchor_B[joints].astype(st.np_dtype), dtype=T.vec3, device=dev),
            wp.array(model.joint_anchor_F[joints].astype(st.np_dtype), dtype=T.vec3, device=dev),
            wp.array(model.joint_world[joints].astype(np.int32), dtype=wp.int32, device=dev),
        ]
        self._kernels = _stats_kernels(st.np_dtype)

    def hook(self, s) -> None:
        """Fold the step just taken (a ``Stepper.post_step`` callable)."""
        w, pw = s.work, self.per_world
        step_stats, closure = self._kernels
        wp.launch(step_stats, dim=self.num_worlds, device=self.device,
                  inputs=[w.iters, w.converged, w.failed],
                  outputs=[pw["sum"], pw["max"], pw["converged"], pw["failed"], pw["steps"], self.histogram])
        if self.num_joints:
            wp.launch(closure, dim=self.num_joints, device=self.device, inputs=[w.q, *self._joint_arrays],
                      outputs=[self.closure])

    def reset(self) -> None:
        for a in (*self.per_world.values(), self.histogram, self.closure):
            a.zero_()

    def summary(self) -> dict:
        """Iterations per world and step (mean, p99, max), the converged share of world-steps, the worlds that failed
        on any step, and the largest closure [m] over every world and step, of the steps folded since :meth:`reset`
        (:func:`fold_summary`)."""
        return fold_summary(self.per_world, self.histogram, self.closure if self.num_joints else None)


def fold_summary(per_world: dict, histogram, closure=None) -> dict:
    """The record's statistics of per-world folds on the device (:class:`BatchStats`, and MuJoCo Warp's in
    :mod:`kamino.bench.peers`): ``per_world`` arrays ``sum`` and ``max`` (iterations), ``converged``, ``failed`` and
    ``steps`` (world-steps counted), the iteration ``histogram`` of :data:`HISTOGRAM_BINS` bins, and the largest
    closure per world (``None``: no anchored joint, closure 0). The p99 is the least bin holding 99 % of the
    world-steps."""
    pw = {k: v.numpy() for k, v in per_world.items()}
    hist = histogram.numpy().astype(np.int64)
    total = int(pw["steps"].sum())
    if total == 0:
        raise ValueError("fold_summary: no step was folded since the reset")
    cdf = np.cumsum(hist)
    return {"batch_steps": int(pw["steps"].max()), "batch_world_steps": total,
            "iterations_mean": float(pw["sum"].sum() / total),
            "iterations_p99": int(np.searchsorted(cdf, 0.99 * total)),
            "iterations_max": int(pw["max"].max()),
            "converged_share": float(pw["converged"].sum() / total),
            "failed_worlds": int(np.count_nonzero(pw["failed"])),
            "closure_batch_max_m": float(closure.numpy().max()) if closure is not None else 0.0}


def _stats_kernels(np_dtype):
    """The two kernels of :class:`BatchStats`: per world (iterations, convergence, failure) and per anchored joint
    (anchor distance ``|X_B(q_parent) a_B - X_F(q_child) a_F|``, a parent ``-1`` being the world frame)."""
    from kamino.warp_backend.types import types_of

    T = types_of(np_dtype)
    scalar, vec3, transform = T.scalar, T.vec3, T.transform

    @wp.kernel(module="unique", enable_backward=False)
    def step_stats(iters: wp.array(dtype=wp.int32), converged: wp.array(dtype=wp.int32),
                   failed: wp.array(dtype=wp.int32), it_sum: wp.array(dtype=wp.int64),
                   it_max: wp.array(dtype=wp.int32), conv: wp.array(dtype=wp.int32), fail: wp.array(dtype=wp.int32),
                   steps: wp.array(dtype=wp.int32), histogram: wp.array(dtype=wp.int32)):
        w = wp.tid()
        k = iters[w]
        it_sum[w] = it_sum[w] + wp.int64(k)
        it_max[w] = wp.max(it_max[w], k)
        wp.atomic_add(histogram, wp.min(k, histogram.shape[0] - 1), 1)
        if converged[w] != 0 and failed[w] == 0:
            conv[w] = conv[w] + 1
        if failed[w] != 0:
            fail[w] = fail[w] + 1
        steps[w] = steps[w] + 1

    @wp.kernel(module="unique", enable_backward=False)
    def closure(q: wp.array(dtype=transform), parent: wp.array(dtype=wp.int32), child: wp.array(dtype=wp.int32),
                anchor_b: wp.array(dtype=vec3), anchor_f: wp.array(dtype=vec3), world: wp.array(dtype=wp.int32),
                out: wp.array(dtype=scalar)):
        j = wp.tid()
        p_f = wp.transform_point(q[child[j]], anchor_f[j])
        p_b = anchor_b[j]
        if parent[j] >= 0:
            p_b = wp.transform_point(q[parent[j]], anchor_b[j])
        wp.atomic_max(out, world[j], wp.length(p_f - p_b))

    return step_stats, closure


__all__ = ["LOADS", "RL_FRACTION", "RL_RATE", "BatchStats", "actuator_ranges", "anchored_joints",
           "fold_summary", "random_configurations", "rl_control_map", "rl_drive_hook", "rl_period", "rl_uniform"]
