"""``fourbar_track``: the actuated four-bar's crank tracks a target angle: a small loop task.

``kamino.models.fourbar(actuated=True)``: a Grashof crank-rocker (one loop) whose crank hinge ``ground_crank`` is
driven by an implicit PD actuator. Every ``resample_steps`` policy steps a new target crank angle is drawn; the
policy sees the crank's angle and rate, the target and its previous action, and sets the PD target. The coupler and
rocker load the crank with a gravity torque and an inertia that change along the cycle, and the 3 N m effort limit
makes a large move take about a second and overshoot, so tracking is a matter of mapping the target (observed as an
angle) to a PD target (an action in ``[-1, 1]``) and shaping the moves. A uniformly random policy scores about 0.12
per step, PPO reaches about 0.9 (of at most 1) within 60 000 environment steps. Small (4 bodies, 26 rows) so that
brax's PPO trains it on a CPU in about a minute (docs/envs.md, "fourbar_track"; notebooks/05_training.ipynb).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from kamino.config import SolverConfig
from kamino.envs.base import KaminoEnv
from kamino.models import fourbar
from kamino.state import State


def wrap_angle(x: jax.Array) -> jax.Array:
    """``x`` wrapped to ``[-pi, pi)``."""
    return jnp.mod(x + jnp.pi, 2.0 * jnp.pi) - jnp.pi


class FourbarTrack(KaminoEnv):
    """Crank-angle tracking on the actuated four-bar (observation, action, reward: docs/envs.md).

    Args:
        target_range: targets are drawn uniformly in ``[-target_range, target_range]`` [rad] of the crank joint
            coordinate (0: the builder pose, the crank 1.2 rad below the ground line).
        action_range: actions ``[-1, 1]`` map to PD targets in ``[-action_range, action_range]`` [rad].
        kp, kd, effort_limit: the crank's PD actuator (``kamino.models.fourbar``).
        tracking_sigma: width [rad] of the tracking kernel ``exp(-(err / sigma)^2)``.
        action_rate_weight: weight of the ``-|a - a_prev|^2`` term.
        sim_dt, decimation: 10 ms simulator steps, 5 per policy step (20 Hz).
        resample_steps: policy steps between target draws.
        reset_noise: the initial crank angle is drawn in ``reset_noise * action_range`` about 0.
        reset_bank: initial configurations solved at construction (``None``: FK in every reset; base class).
        **kwargs: :class:`kamino.envs.base.KaminoEnv` (``backend``, ``obs_noise``, ``solver_config``, ``dtype``).
    """

    reward_terms = ("tracking", "action_rate")
    task_keys = ("target",)

    def __init__(self, *, target_range: float = 2.5, action_range: float = 2.8, kp: float = 50.0, kd: float = 2.0,
                 effort_limit: float = 3.0, tracking_sigma: float = 0.4, action_rate_weight: float = 0.02,
                 sim_dt: float = 0.01, decimation: int = 5, resample_steps: int = 50, reset_noise: float = 1.0,
                 reset_bank: int | None = 256, solver_config: SolverConfig | None = None, **kwargs):
        for name, value in (("target_range", target_range), ("action_range", action_range),
                            ("tracking_sigma", tracking_sigma)):
            if not (isinstance(value, (int, float)) and np.isfinite(value) and value > 0):
                raise ValueError(f"FourbarTrack: {name} must be a positive number, got {value!r}")
        if action_range >= np.pi:
            raise ValueError(f"FourbarTrack: action_range must be below pi (a PD target beyond +-pi aliases, "
                             f"docs/conventions.md), got {action_range!r}")
        self._target_range = float(target_range)
        self._sigma = float(tracking_sigma)
        self._rate_weight = float(action_rate_weight)
        model = fourbar(actuated=True, kp=kp, kd=kd, effort_limit=effort_limit)
        super().__init__(model, sim_dt=sim_dt, decimation=decimation, action_lower=-action_range,
                         action_upper=action_range, reset_noise=reset_noise, resample_steps=resample_steps,
                         reset_bank=reset_bank, solver_config=solver_config, **kwargs)

    def _sample_task(self, rng: jax.Array) -> dict[str, jax.Array]:
        return {"target": jax.random.uniform(rng, (), self.dtype, -self._target_range, self._target_range)}

    def _obs_size(self) -> int:
        return 7

    def _observe(self, ps: State, info: dict) -> jax.Array:
        q, qd = self.actuated_state(ps)
        theta, target = q[0], info["target"]
        return jnp.stack([jnp.cos(theta), jnp.sin(theta), 0.1 * qd[0], jnp.cos(target), jnp.sin(target),
                          target / jnp.pi, info["last_action"][0]]).astype(self.dtype)

    def _obs_noise_scale(self) -> np.ndarray:
        return np.array([1.0, 1.0, 1.0, 0.0, 0.0, 0.0, 0.0])  # the target and the own action are exact

    def _reward(self, prev: State, ps: State, action: jax.Array, info: dict) -> tuple[jax.Array, dict]:
        q, _ = self.actuated_state(ps)
        err = wrap_angle(q[0] - info["target"])
        terms = {"tracking": jnp.exp(-(err / self._sigma) ** 2),
                 "action_rate": -self._rate_weight * jnp.sum((action - info["last_action"]) ** 2)}
        return terms["tracking"] + terms["action_rate"], terms


__all__ = ["FourbarTrack", "wrap_angle"]
