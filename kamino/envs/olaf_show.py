"""``olaf_show``: Olaf stands and performs: its jaw, arms and eyes, each moved through a four-bar loop, and its head
follow show targets, a whole-body motion through the robot's loop mechanisms.

``kamino.models.olaf()`` has five planar four-bars: the jaw, two stick arms and two eyeballs, each with an actuated
crank (``*_drive``) and a passive output hinge (``*_pivot``). The show targets are output angles: the policy sets
the cranks' PD targets, so it has to learn each loop's crank-to-output map, and it keeps the snowman standing while
the arms swing and the head turns (the legs, 12 actuators, are the policy's too). The targets are drawn uniformly
in each output's reachable range (:func:`show_ranges`, solved by forward kinematics at construction) and redrawn
every ``resample_steps`` policy steps. The rest is the joystick task with a zero velocity command: stand in place.

The show test (:func:`show_test`, :func:`summarize_show`; docs/envs.md, "olaf_show"): episodes of 10 s with targets
redrawn every 2 s; per episode the mean absolute output error over the second half of every target window (the
first second is the move), and the share of episodes that fall.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from kamino.envs.base import actuator_target_range
from kamino.envs.joystick import Joystick, standing_fraction
from kamino.kinematics import forward_kinematics, init_state
from kamino.model import Model, replicate
from kamino.models import olaf
from kamino.readouts import dof_state
from kamino.state import State

#: the loop outputs and the head joints that the show targets move, and the actuator that drives each
SHOW_JOINTS: tuple[tuple[str, str], ...] = (
    ("jaw_pivot", "jaw_drive"), ("l_shoulder_pivot", "l_shoulder_drive"), ("r_shoulder_pivot", "r_shoulder_drive"),
    ("l_eye_pivot", "l_eye_drive"), ("r_eye_pivot", "r_eye_drive"), ("neck_yaw", "neck_yaw"),
    ("neck_pitch", "neck_pitch"))


def joint_dofs(model: Model, names) -> np.ndarray:
    """The DoF index of each named one-DoF joint of ``model`` (raises naming an unknown joint)."""
    joints = list(model.joint_names)
    missing = [n for n in names if n not in joints]
    if missing:
        raise ValueError(f"joint_dofs: {missing} are not joints of the model (its joints: {joints})")
    return np.array([int(model.joint_dof_start[joints.index(n)]) for n in names], np.int32)


def show_ranges(model: Model, fraction: float = 0.9) -> tuple[np.ndarray, np.ndarray]:
    """``(low, high)`` [rad] of each :data:`SHOW_JOINTS` output over its driver's range: the driving actuators at
    ``-fraction``, 0 and ``+fraction`` of their half-ranges (the others at their centres), solved by one batched
    forward kinematics; an output's range is the span of its three angles (the crank-to-output map of these
    four-bars is monotonic within the crank limits). Raises if forward kinematics does not converge."""
    names = list(model.actuator_names)
    act = [names.index(a) for _, a in SHOW_JOINTS]
    lower, upper = actuator_target_range(model)
    centre, half = 0.5 * (lower + upper), 0.5 * (upper - lower)
    q = np.tile(centre, (3, 1))
    for row, s in enumerate((-fraction, 0.0, fraction)):
        q[row, act] = centre[act] + s * half[act]
    many = replicate(model, 3)
    fk = forward_kinematics(many, actuated_positions=q.reshape(-1))
    if not bool(np.all(np.asarray(fk.converged))):
        raise ValueError("show_ranges: forward kinematics did not converge at the drivers' range ends")
    state = dataclasses.replace(init_state(many), body_q=fk.body_q)
    dofs = joint_dofs(model, [j for j, _ in SHOW_JOINTS])
    angles = np.asarray(dof_state(many, state)[0]).reshape(3, model.num_dofs)[:, dofs]
    return angles.min(0), angles.max(0)


class OlafShow(Joystick):
    """Olaf standing in place while its jaw, arms, eyes and head follow show targets (the module doc).

    Args:
        show_weight: weight of the ``show`` reward, the mean over the joints of ``exp(-(q_j - target_j)^2 /
            show_sigma)`` (a kernel per joint, so that each output that reaches its target counts on its own).
        show_sigma: variance [rad^2] of that kernel (0.01: an error of 0.1 rad scores 1/e).
        show_fraction: the targets span the outputs' angles with their drivers within this fraction of their
            half-ranges (:func:`show_ranges`).
        resample_steps: policy steps between target draws (100: 2 s).
        min_height: the pelvis height [m] below which Olaf has fallen (default: 0.6 of its standing height).
        command_lin_x, command_lin_y, command_yaw: the velocity command's half-ranges; 0: stand in place.
        **kwargs: :class:`kamino.envs.joystick.Joystick` (the standing rewards, noise, backend).
    """

    reward_terms = (*Joystick.reward_terms, "show")
    task_keys = ("command", "show")
    evaluation = "show"
    #: the show test's bars (:func:`kamino.envs.evaluate.evaluate`): mean absolute output error [rad], fall fraction
    show_bars = (0.05, 0.05)

    def __init__(self, *, show_weight: float = 2.0, show_sigma: float = 0.01, show_fraction: float = 0.9,
                 resample_steps: int = 100, min_height: float | None = None, command_lin_x: float = 0.0,
                 command_lin_y: float = 0.0, command_yaw: float = 0.0, **kwargs):
        name = type(self).__name__
        for arg, value in (("show_weight", show_weight), ("show_sigma", show_sigma)):
            if not (isinstance(value, (int, float)) and np.isfinite(value) and value > 0):
                raise ValueError(f"{name}: {arg} must be a positive number, got {value!r}")
        if not (isinstance(show_fraction, (int, float)) and 0 < show_fraction <= 1):
            raise ValueError(f"{name}: show_fraction must be in (0, 1], got {show_fraction!r}")
        model = olaf()
        min_height = standing_fraction(model, 0.6) if min_height is None else min_height
        self._show_weight, self._show_sigma = float(show_weight), float(show_sigma)
        self._show_dofs = joint_dofs(model, [j for j, _ in SHOW_JOINTS])
        self._show_lo, self._show_hi = show_ranges(model, float(show_fraction))
        super().__init__(model, min_height=min_height, command_lin_x=command_lin_x, command_lin_y=command_lin_y,
                         command_yaw=command_yaw, resample_steps=resample_steps, **kwargs)

    @property
    def show_range(self) -> tuple[np.ndarray, np.ndarray]:
        """``(low, high)`` [rad] of the show targets, :data:`SHOW_JOINTS` order."""
        return self._show_lo.copy(), self._show_hi.copy()

    def show_angles(self, ps: State) -> jax.Array:
        """The :data:`SHOW_JOINTS` angles [rad] of ``ps``."""
        return dof_state(self._model, ps)[0][self._show_dofs]

    def _sample_task(self, rng: jax.Array) -> dict[str, jax.Array]:
        k_cmd, k_show = jax.random.split(rng)
        lo, hi = (jnp.asarray(x, self.dtype) for x in (self._show_lo, self._show_hi))
        return {**super()._sample_task(k_cmd), "show": jax.random.uniform(k_show, lo.shape, self.dtype, lo, hi)}

    def _obs_size(self) -> int:
        return super()._obs_size() + len(SHOW_JOINTS)

    def _observe(self, ps: State, info: dict) -> jax.Array:
        # the joystick's observation, then the targets; Joystick._obs_noise_scale puts no noise past its own entries
        return jnp.concatenate([super()._observe(ps, info), info["show"]]).astype(self.dtype)

    def _reward(self, prev: State, ps: State, action: jax.Array, info: dict) -> tuple[jax.Array, dict]:
        _, terms = super()._reward(prev, ps, action, info)
        err = self.show_angles(ps) - info["show"]
        terms["show"] = self._show_weight * jnp.mean(jnp.exp(-(err**2) / self._show_sigma))
        total = sum(terms.values())
        return (jnp.maximum(total, 0.0) if self._only_positive else total), terms


def show_test(env: OlafShow, make_policy, *, episodes: int, seconds: float, seed: int = 0,
              deterministic: bool = True):
    """The show test's rollout, compiled once for any parameters of ``make_policy``: returns ``run(params)``, which
    plays ``episodes`` episodes of ``seconds`` (targets redrawn every ``env``'s ``resample_steps``) and returns numpy
    arrays ``(error [E, T, J], counted [E, T], fell [E])``: the absolute output errors after each policy step against
    the targets in force, ``counted`` for the steps in the second half of a target window with the robot up, and
    the episodes that fell."""
    steps = round(seconds / env.dt)
    window = env._resample_steps or steps
    settled = (np.arange(steps) % window) >= window // 2
    key_reset, key_policy = jax.random.split(jax.random.PRNGKey(seed))

    def rollout(params, state, key):
        policy = make_policy(params, deterministic=deterministic)

        def body(carry, inputs):
            s, alive = carry
            k, late = inputs
            target = s.info["show"]
            action, _ = policy(s.obs, k)
            s = env.step(s, action)
            err = jnp.abs(env.show_angles(env.full_state(s.pipeline_state)) - target)
            alive = alive & (s.done == 0)
            return (s, alive), (err, alive & late)

        (_, alive_end), (err, counted) = jax.lax.scan(body, (state, jnp.bool_(True)),
                                                      (jax.random.split(key, steps), jnp.asarray(settled)))
        return err, counted, ~alive_end

    with jax.enable_x64(False):
        states = jax.jit(jax.vmap(env.reset))(jax.random.split(key_reset, episodes))
    play = jax.jit(jax.vmap(rollout, in_axes=(None, 0, 0)))
    keys = jax.random.split(key_policy, episodes)

    def run(params):
        with jax.enable_x64(False):
            return tuple(np.asarray(x) for x in play(params, states, keys))

    return run


def summarize_show(error: np.ndarray, counted: np.ndarray, fell: np.ndarray) -> dict:
    """The show test's figures of a :func:`show_test` rollout: the mean absolute output error [rad] per episode
    (over its counted steps and the joints), its mean and 90th percentile over the episodes, the mean error per
    joint (:data:`SHOW_JOINTS` order), and the fall fraction."""
    n = np.maximum(counted.sum(1), 1)
    per_episode = np.where(counted[..., None], error, 0.0).sum(1) / n[:, None]  # [E, J]
    return {"episodes": int(error.shape[0]), "policy_steps": int(error.shape[1]),
            "show_error_mean": float(per_episode.mean()),
            "show_error_p90": float(np.quantile(per_episode.mean(1), 0.9)),
            "show_error_per_joint": {j: float(e) for (j, _), e in zip(SHOW_JOINTS, per_episode.mean(0),
                                                                      strict=True)},
            "fall_fraction": float(fell.mean())}


__all__ = ["SHOW_JOINTS", "OlafShow", "joint_dofs", "show_ranges", "show_test", "summarize_show"]
