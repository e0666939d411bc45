"""Velocity-command following for a legged robot on a ground plane: the joystick task.

The command ``(v_x, v_y, yaw rate)`` in the base body's frame is drawn at reset and every ``resample_steps``;
rewards follow the usual joystick recipe (velocity tracking through exponential kernels, upright, action rate,
torque, alive, legged_gym's base-steadiness and feet-air-time terms, and a gait clock's ``feet_phase``; the last
four are off by default), and an episode ends when the base body falls below ``min_height`` or tilts past
``max_tilt``, or the world's health flag is set. :class:`Joystick` holds the task for any one-world model with a
floating base and PD actuators; ``dr_legs_joystick`` (:class:`DrLegsJoystick`, kinematic loops) and ``bdx_joystick``
(:class:`BdxJoystick`, a tree) are its two robots. Observation, reward and termination tables: docs/envs.md,
"Joystick tasks".
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from kamino.config import SolverConfig
from kamino.envs.base import KaminoEnv
from kamino.envs.geometry import body_frame_vectors
from kamino.model import Model
from kamino.models import bdx, dr_legs
from kamino.spatial import quat_mul, quat_to_matrix
from kamino.state import State

#: reward weights (docs/envs.md); the reward is their weighted sum per policy step, clipped at 0
#: (``only_positive_rewards``). legged_gym's ``lin_vel_z`` (its weight -2.0), ``ang_vel_xy`` (-0.05) and
#: ``feet_air_time`` (1.0) are off by default: the committed policy was trained without them, and switching them on
#: for 28 M steps from it made the walking test worse; ``reward_weights`` sets them
#: ``feet_phase`` (0 by default) rewards feet that follow the gait clock's swing heights; it needs ``gait_frequency``.
#: ``feet_width`` (0 by default) rewards a lateral distance ``stance_width`` between two feet (a narrower stance sways
#: less: docs/envs.md, "The lateral sway")
REWARD_WEIGHTS = {"tracking_lin_vel": 1.0, "tracking_ang_vel": 0.5, "upright": 0.2, "action_rate": -0.01,
                  "torque": -2e-4, "alive": 0.2, "lin_vel_z": 0.0, "ang_vel_xy": 0.0, "feet_air_time": 0.0,
                  "feet_phase": 0.0, "feet_width": 0.0}


def feet_air_time(air: jax.Array, was_down: jax.Array, down: jax.Array, dt: float,
                  target: float) -> tuple[jax.Array, jax.Array]:
    """legged_gym's feet-air-time term over one policy step of length ``dt`` [s], per foot: a foot that lands (on the
    ground now or at the previous step, after time in the air) earns its time in the air minus ``target`` [s]; a foot
    on the ground has its clock reset. Counting contact over two steps filters a foot that grazes the ground for
    one. Returns ``(reward summed over the feet, air times after the step)``. The filter drops a swing's first step
    and the landing step counts, so a foot off the ground for ``n`` policy steps earns ``n dt - target``."""
    touching = down | was_down
    landing = touching & (air > 0)
    air = air + dt
    return jnp.sum(jnp.where(landing, air - target, 0.0)), jnp.where(touching, 0.0, air)


#: The warm start's factor on the previous substep's reactions in the walking tasks (``SolverConfig.warmstart_scale``;
#: the kamino default is 1). A robot's redundant loops (dr_legs' planar four-bars) admit internal loads that move no
#: body (the left null space of the joint Jacobian): the solver never corrects them, float32 rounding adds to them
#: each solve, and a warm start at 1 carries them over the whole episode. They grew to 1e5-1e6 N within 600 policy
#: steps, where PADMM stops converging and the robot is thrown. At 0.99 they decay
#: by 1 % per substep; measured over 600 policy steps of 32 walking dr_legs (Warp CPU): the median carried reaction
#: stays at 1.1-1.6e3 N (at 1.0: 2.3e3 rising to 6.9e4 N), with the same mean PADMM iterations (about 10).
WARMSTART_SCALE = 0.99


def swing_heights(phase: jax.Array, num_feet: int, height: float) -> jax.Array:
    """Target lift [m] of each foot at gait ``phase`` (cycles, any real; the clock of the periodic-gait rewards of
    Siekmann et al. 2021 and MuJoCo Playground's bipeds): foot ``i`` swings while ``sin(2 pi (phase - i / num_feet))``
    is positive, along that half sine scaled to ``height``, and stands (target 0) in the other half of its cycle.
    For two feet the swings alternate: foot 0 in ``[0, 0.5)``, foot 1 in ``[0.5, 1)``. Returns ``[num_feet]``."""
    offsets = jnp.arange(num_feet, dtype=jnp.result_type(phase)) / num_feet
    return height * jnp.maximum(jnp.sin(2.0 * jnp.pi * (phase - offsets)), 0.0)


class Joystick(KaminoEnv):
    """Velocity-command following on ``model`` (a floating base, PD actuators, feet on a ground plane).

    Args:
        model: a one-world model; its first floating body is the base whose velocity follows the command.
        command_lin_x, command_lin_y, command_yaw: half-ranges of the uniform command draw [m/s], [m/s], [rad/s].
        tracking_sigma: variance [(m/s)^2, (rad/s)^2] of the tracking kernels ``exp(-err^2 / sigma)``.
        feet: names of the foot bodies (default: every body whose name contains ``foot``) for ``feet_air_time``
            (none needed while its weight is 0).
        air_time_target: the swing time [s] at which a landing foot's ``feet_air_time`` turns positive.
        contact_height: a foot is on the ground while its CoM is within this height [m] of where it stands at the
            nominal reset (a box foot tilted on an edge or heel rises a few mm).
        min_height: the base CoM height [m] (above the ground below it) below which the robot has fallen.
        max_tilt: the base tilt [rad] past which it has fallen.
        reward_weights: overrides of :data:`REWARD_WEIGHTS`.
        only_positive_rewards: clip the reward of a policy step at 0 from below (the metrics keep every term). With
            the torque and action-rate penalties a vigorous step is worth less than nothing, so without the clip an
            episode that ends early beats one that lives, and PPO learned to fall: measured on dr_legs_joystick,
            the training return rose to 238 and then collapsed to episodes of 5-6 steps (docs/envs.md, "Training
            on the GPU"). legged_gym, whose RSL-RL the paper trains with, clips for the same reason.
        sim_dt, decimation: 4 ms, 5 per policy step (50 Hz).
        resample_steps: policy steps between command draws (250: 5 s).
        reset_noise: initial actuated angles drawn in ``reset_noise`` of each half-range about 0; the heading is
            uniform in ``[-pi, pi)``.
        reset_bank: leg configurations solved at construction (``None``: FK in every reset; base class); the
            heading is drawn in every reset (a rigid turn).
        obs_noise: scale on the per-entry noise of :meth:`_obs_noise_scale` (1: the documented levels).
        gait_frequency: a gait clock [Hz] (default ``None``: none). Its phase starts at 0 in every episode, advances
            by ``gait_frequency * dt`` per policy step and is observed as ``(sin, cos)(2 pi phase)`` (two more
            entries); ``feet_phase`` rewards feet that follow :func:`swing_heights` while a command asks for motion,
            and feet on the ground otherwise.
        swing_height: the clock's peak foot lift [m] (foot CoM above where it stands at the nominal reset).
        swing_sigma: variance [m^2] of the ``feet_phase`` kernel ``exp(-sum_feet (lift - target)^2 / swing_sigma)``.
        stance_width: the lateral distance [m] between two feet that ``feet_width`` rewards (default: theirs at the
            nominal reset). A narrower stance lowers the sway from foot to foot (docs/envs.md, "The lateral sway").
        stance_sigma: variance [m^2] of the ``feet_width`` kernel ``exp(-(width - stance_width)^2 / stance_sigma)``.
        solver_config: default ``SolverConfig(warmstart_scale=WARMSTART_SCALE)`` (a decaying warm start: see
            :data:`WARMSTART_SCALE`).
        **kwargs: :class:`kamino.envs.base.KaminoEnv` (``backend``, ``dtype``).
    """

    reward_terms = tuple(REWARD_WEIGHTS)
    task_keys = ("command",)
    evaluation = "walking"
    #: the walking test's bars (:func:`kamino.envs.evaluate.evaluate`): mean tracking error [m/s], fall fraction
    walking_bars = (0.1, 0.05)

    @classmethod
    def default_solver_config(cls) -> SolverConfig:
        """``SolverConfig(warmstart_scale=WARMSTART_SCALE)``: a decaying warm start (:data:`WARMSTART_SCALE`)."""
        return SolverConfig(warmstart_scale=WARMSTART_SCALE)

    def __init__(self, model: Model, *, min_height: float, command_lin_x: float = 0.5, command_lin_y: float = 0.3,
                 command_yaw: float = 0.8, tracking_sigma: float = 0.25, max_tilt: float = 1.0,
                 feet: tuple[str, ...] | None = None, air_time_target: float = 0.3, contact_height: float = 0.01,
                 reward_weights: dict | None = None, only_positive_rewards: bool = True, sim_dt: float = 0.004,
                 decimation: int = 5,
                 resample_steps: int = 250, reset_noise: float = 0.1, obs_noise: float = 1.0,
                 reset_bank: int | None = 128, gait_frequency: float | None = None, swing_height: float = 0.05,
                 swing_sigma: float = 0.0025, stance_width: float | None = None, stance_sigma: float = 0.0025,
                 solver_config: SolverConfig | None = None, **kwargs):
        name = type(self).__name__
        for arg, value in (("tracking_sigma", tracking_sigma), ("min_height", min_height), ("max_tilt", max_tilt),
                           ("air_time_target", air_time_target), ("contact_height", contact_height),
                           ("swing_height", swing_height), ("swing_sigma", swing_sigma),
                           ("stance_sigma", stance_sigma),
                           *((("stance_width", stance_width),) if stance_width is not None else ()),
                           *((("gait_frequency", gait_frequency),) if gait_frequency is not None else ())):
            if not (isinstance(value, (int, float)) and np.isfinite(value) and value > 0):
                raise ValueError(f"{name}: {arg} must be a positive number, got {value!r}")
        for arg, value in (("command_lin_x", command_lin_x), ("command_lin_y", command_lin_y),
                           ("command_yaw", command_yaw)):
            if not (isinstance(value, (int, float)) and np.isfinite(value) and value >= 0):
                raise ValueError(f"{name}: {arg} must be a number >= 0, got {value!r}")
        unknown = sorted(set(reward_weights or {}) - set(REWARD_WEIGHTS))
        if unknown:
            raise ValueError(f"{name}: reward_weights has unknown terms {unknown}; the terms are "
                             f"{list(REWARD_WEIGHTS)}")
        self._weights = {**REWARD_WEIGHTS, **(reward_weights or {})}
        if gait_frequency is None and self._weights["feet_phase"] != 0:
            raise ValueError(f"{name}: the feet_phase reward follows the gait clock; give gait_frequency (Hz) or set "
                             "reward_weights={'feet_phase': 0}")
        self._gait_frequency = None if gait_frequency is None else float(gait_frequency)
        self._swing_height, self._swing_sigma = float(swing_height), float(swing_sigma)
        self._only_positive = bool(only_positive_rewards)
        self._command_range = np.array([command_lin_x, command_lin_y, command_yaw], float)
        self._sigma = float(tracking_sigma)
        self._min_height = float(min_height)
        self._min_up = float(np.cos(max_tilt))
        names = list(model.body_names or [])
        if feet is None:
            feet = tuple(n for n in names if "foot" in n.lower())
            if not feet and (self._weights["feet_air_time"] != 0 or self._gait_frequency is not None):
                raise ValueError(f"{name}: no body name contains 'foot'; name the feet (feet=...) or set "
                                 "reward_weights={'feet_air_time': 0} and no gait_frequency")
        missing = [f for f in feet if f not in names]
        if missing:
            raise ValueError(f"{name}: feet {missing} are not bodies of the model (its bodies: {names})")
        self._feet = np.array([names.index(f) for f in feet], np.int32)
        if self._weights["feet_width"] != 0 and len(self._feet) != 2:
            raise ValueError(f"{name}: the feet_width reward needs exactly two feet, got {list(feet)}")
        self._stance_sigma = float(stance_sigma)
        self._air_target = float(air_time_target)
        super().__init__(model, sim_dt=sim_dt, decimation=decimation, reset_noise=reset_noise, obs_noise=obs_noise,
                         resample_steps=resample_steps, reset_bank=reset_bank,
                         solver_config=solver_config, **kwargs)
        placed = np.asarray(self._place(jnp.asarray(model.body_q0, self.dtype)))
        self._foot_stand_z = placed[self._feet, 2]
        self._foot_down_z = self._foot_stand_z + float(contact_height)
        self._stance_width = (float(np.linalg.norm(placed[self._feet[0], :2] - placed[self._feet[1], :2]))
                              if stance_width is None and len(self._feet) == 2 else
                              None if stance_width is None else float(stance_width))

    # ---------------------------------------------------------------- reset and commands

    def _move_rigidly(self, body_q: jax.Array, rng: jax.Array) -> jax.Array:
        """A uniform heading: every body turned about the vertical through the base body's CoM."""
        yaw = jax.random.uniform(rng, (), body_q.dtype, -jnp.pi, jnp.pi)
        c, s = jnp.cos(yaw), jnp.sin(yaw)
        pivot = body_q[self._base, :3]
        rel = body_q[:, :3] - pivot
        pos = pivot + jnp.stack([c * rel[:, 0] - s * rel[:, 1], s * rel[:, 0] + c * rel[:, 1], rel[:, 2]], -1)
        zq = jnp.stack([jnp.zeros_like(yaw), jnp.zeros_like(yaw), jnp.sin(0.5 * yaw), jnp.cos(0.5 * yaw)])
        return jnp.concatenate([pos, quat_mul(jnp.broadcast_to(zq, body_q[:, 3:].shape), body_q[:, 3:])], -1)

    def _sample_task(self, rng: jax.Array) -> dict[str, jax.Array]:
        r = jnp.asarray(self._command_range, self.dtype)
        return {"command": jax.random.uniform(rng, (3,), self.dtype, -1.0, 1.0) * r}

    def with_command(self, state, command: jax.Array):
        """``state`` (one environment, right after :meth:`reset`) with its command ``[3]`` replaced: in ``info``, in
        the memory an auto-reset restores, and in the observation (entries 9-11, which carry no noise). For
        evaluations at chosen commands (:func:`kamino.envs.evaluate.walking_test`); build the environment with
        ``resample_steps=None`` to keep the command for the whole episode."""
        command = jnp.asarray(command, self.dtype)
        if command.shape != (3,):
            raise ValueError(f"{type(self).__name__}.with_command: command has shape {command.shape}, expected (3,) "
                             "(v_x, v_y [m/s], yaw rate [rad/s] in the base frame)")
        info = dict(state.info, command=command, reset_memory=dict(state.info["reset_memory"], command=command))
        return state.replace(info=info, obs=state.obs.at[9:12].set(command))

    # ---------------------------------------------------------------- observation

    def _obs_size(self) -> int:
        return 12 + 3 * self.action_size + (2 if self._gait_frequency is not None else 0)

    def _observe(self, ps: State, info: dict) -> jax.Array:
        base = body_frame_vectors(ps.body_q, ps.body_u, self._base)
        q, qd = self.actuated_state(ps)
        centre = jnp.asarray(0.5 * (self.action_lower + self.action_upper), self.dtype)
        clock = []
        if self._gait_frequency is not None:
            angle = 2.0 * jnp.pi * info["phase"]
            clock = [jnp.stack([jnp.sin(angle), jnp.cos(angle)])]
        return jnp.concatenate([0.25 * base["ang_vel"], base["gravity"], base["lin_vel"], info["command"],
                                q - centre, 0.05 * qd, info["last_action"], *clock]).astype(self.dtype)

    def _obs_noise_scale(self) -> np.ndarray:
        """Noise standard deviation per entry at ``obs_noise = 1``, in observation units: angular velocity 0.05
        (0.2 rad/s), gravity 0.05, linear velocity 0.1 m/s, joint angles 0.01 rad, joint rates 0.075 (1.5 rad/s);
        none on the command, the previous action and the gait clock."""
        n = self.action_size
        return np.concatenate([np.full(3, 0.05), np.full(3, 0.05), np.full(3, 0.1), np.zeros(3), np.full(n, 0.01),
                               np.full(n, 0.075), np.zeros(n + self._obs_size() - 12 - 3 * n)])

    # ---------------------------------------------------------------- reward and termination

    def _above_ground(self, z: jax.Array, xy: jax.Array) -> jax.Array:
        """Heights ``z`` [m] of points at world ``xy`` ``[..., 2]`` measured from the ground below them: ``z`` itself
        on the flat ground plane at z = 0 (returned as is, so no float of the flat task changes); a terrain task
        subtracts the terrain's height (:class:`kamino.envs.rough.DrLegsRough`)."""
        return z

    def _fallen(self, ps: State) -> jax.Array:
        base = body_frame_vectors(ps.body_q, ps.body_u, self._base)
        height = self._above_ground(base["height"], ps.body_q[self._base, :2])
        return (height < self._min_height) | (base["up"] < self._min_up)

    def _episode_memory(self) -> dict[str, jax.Array]:
        n = len(self._feet)
        clock = {} if self._gait_frequency is None else {"phase": jnp.zeros((), self.dtype)}
        return {"feet_air_time": jnp.zeros(n, self.dtype), "feet_down": jnp.ones(n, bool), **clock}

    def _phase_after(self, info: dict) -> jax.Array:
        """The gait phase [cycles, in [0, 1)] one policy step after ``info``'s."""
        return jnp.mod(info["phase"] + self._gait_frequency * self.dt, 1.0)

    def _feet_phase(self, ps: State, info: dict) -> jax.Array:
        """``exp(-sum_feet (lift - target)^2 / swing_sigma)`` at the end of the step: the targets are
        :func:`swing_heights` of the clock while the command asks for motion (``|v_xy| > 0.1 m/s`` or ``|yaw rate|
        > 0.1 rad/s``), else 0 (both feet down)."""
        cmd = info["command"]
        moving = (jnp.linalg.norm(cmd[:2]) > 0.1) | (jnp.abs(cmd[2]) > 0.1)
        target = jnp.where(moving, swing_heights(self._phase_after(info), len(self._feet), self._swing_height), 0.0)
        feet = ps.body_q[self._feet]
        lift = self._above_ground(feet[:, 2], feet[:, :2]) - jnp.asarray(self._foot_stand_z, ps.body_q.dtype)
        return jnp.exp(-jnp.sum((lift - target) ** 2) / self._swing_sigma)

    def _feet_width(self, ps: State) -> jax.Array:
        """``exp(-(width - stance_width)^2 / stance_sigma)``: ``width`` is the distance between the two feet's CoMs
        along the base's lateral axis, levelled (its heading's left, in the ground plane), so a turned or tilted base
        measures the same stance."""
        R = quat_to_matrix(ps.body_q[self._base, 3:])
        left = jnp.stack([R[0, 1], R[1, 1]])
        left = left / jnp.maximum(jnp.linalg.norm(left), 1e-6)
        gap = ps.body_q[self._feet[0], :2] - ps.body_q[self._feet[1], :2]
        width = jnp.abs(jnp.dot(gap, left))
        return jnp.exp(-((width - self._stance_width) ** 2) / self._stance_sigma)

    def _feet_down(self, ps: State) -> jax.Array:
        feet = ps.body_q[self._feet]
        return self._above_ground(feet[:, 2], feet[:, :2]) < jnp.asarray(self._foot_down_z, ps.body_q.dtype)

    def _air_time(self, ps: State, info: dict) -> tuple[jax.Array, jax.Array]:
        return feet_air_time(info["feet_air_time"], info["feet_down"], self._feet_down(ps), self.dt,
                             self._air_target)

    def _update_memory(self, ps: State, info: dict) -> dict[str, jax.Array]:
        clock = {} if self._gait_frequency is None else {"phase": self._phase_after(info).astype(self.dtype)}
        return {"feet_air_time": self._air_time(ps, info)[1].astype(self.dtype), "feet_down": self._feet_down(ps),
                **clock}

    def _reward(self, prev: State, ps: State, action: jax.Array, info: dict) -> tuple[jax.Array, dict]:
        base = body_frame_vectors(ps.body_q, ps.body_u, self._base)
        cmd = info["command"]
        torque = ps.actuator_force[self._act_dof]
        moving = jnp.linalg.norm(cmd[:2]) > 0.1
        raw = {
            "tracking_lin_vel": jnp.exp(-jnp.sum((cmd[:2] - base["lin_vel"][:2]) ** 2) / self._sigma),
            "tracking_ang_vel": jnp.exp(-((cmd[2] - base["ang_vel"][2]) ** 2) / self._sigma),
            "upright": base["up"],
            "action_rate": jnp.sum((action - info["last_action"]) ** 2),
            "torque": jnp.sum(torque**2),
            "alive": 1.0 - self._fallen(ps).astype(self.dtype),
            "lin_vel_z": base["lin_vel"][2] ** 2,
            "ang_vel_xy": jnp.sum(base["ang_vel"][:2] ** 2),
            "feet_air_time": jnp.where(moving, self._air_time(ps, info)[0], 0.0),
            "feet_phase": self._feet_phase(ps, info) if self._gait_frequency is not None else jnp.zeros((), self.dtype),
            "feet_width": (self._feet_width(ps) if self._weights["feet_width"] != 0
                           else jnp.zeros((), self.dtype)),
        }
        terms = {k: self._weights[k] * v for k, v in raw.items()}
        total = sum(terms.values())
        return (jnp.maximum(total, 0.0) if self._only_positive else total), terms

    def _terminated(self, ps: State, info: dict) -> jax.Array:
        return self._fallen(ps)


def standing_fraction(model: Model, fraction: float) -> float:
    """``fraction`` of the height [m] of ``model``'s base body in its reference pose: a fall threshold."""
    from kamino.kinematics import base_bodies

    return fraction * float(model.body_q0[int(base_bodies(model)[0]), 2])


def _check_gains(name: str, kp, kd) -> None:
    if not (isinstance(kp, (int, float)) and np.isfinite(kp) and kp > 0):
        raise ValueError(f"{name}: kp must be a positive number, got {kp!r}")
    if not (isinstance(kd, (int, float)) and np.isfinite(kd) and kd >= 0):
        raise ValueError(f"{name}: kd must be a number >= 0, got {kd!r}")


class DrLegsJoystick(Joystick):
    """``dr_legs_joystick``: ``kamino.models.dr_legs()`` (31 bodies, 12 PD actuators, 6 kinematic loops: knee and
    ankle four-bars, a spatial ankle-roll loop per leg; box feet), fallen below a pelvis height of 0.45 m (0.77 m
    standing). The gains default to the model's own: ``kp`` 300 N m/rad and ``kd`` 8 N m s/rad at the hips and
    knees, 150 and 4 at the ankles. Numbers ``kp``, ``kd`` put those gains on every actuator instead: the
    paper's 15 / 0.6, for a robot a third of this one's size, cannot hold this one up (docs/envs.md).
    Other arguments: :class:`Joystick`."""

    def __init__(self, *, kp: float | None = None, kd: float | None = None, min_height: float = 0.45, **kwargs):
        if (kp is None) != (kd is None):
            raise ValueError(f"{type(self).__name__}: give kp and kd together (or neither, for the model's own "
                             f"gains), got kp={kp!r}, kd={kd!r}")
        if kp is None:
            model = self._robot()
        else:
            _check_gains(type(self).__name__, kp, kd)
            model = self._robot(hip_gains=(kp, kd), knee_gains=(kp, kd), ankle_gains=(kp, kd))
        super().__init__(model, min_height=min_height, **kwargs)

    def _robot(self, **gains) -> Model:
        """The model: ``kamino.models.dr_legs(**gains)`` on its ground plane (a terrain task puts its own ground)."""
        return dr_legs(**gains)


class BdxJoystick(Joystick):
    """``bdx_joystick``: ``kamino.models.bdx()`` (21 bodies, a tree: 10 leg and 4 neck PD actuators; box feet),
    the leg gains ``kp`` 400 N m/rad and ``kd`` 8 N m s/rad of the model, the neck's as built; fallen below a pelvis
    height of ``min_height`` (default 0.6 of the standing height). The neck is actuated by the policy too (14
    actions). Other arguments: :class:`Joystick`."""

    def __init__(self, *, kp: float = 400.0, kd: float = 8.0, min_height: float | None = None, **kwargs):
        _check_gains(type(self).__name__, kp, kd)
        model = bdx(leg_gains=(kp, kd))
        min_height = standing_fraction(model, 0.6) if min_height is None else min_height
        super().__init__(model, min_height=min_height, **kwargs)


__all__ = ["REWARD_WEIGHTS", "BdxJoystick", "DrLegsJoystick", "Joystick", "feet_air_time", "standing_fraction",
           "swing_heights"]
