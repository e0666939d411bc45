"""Per-task PPO settings (``brax.training.agents.ppo.train`` keyword arguments) and environment arguments.

``kamino train TASK`` and notebook 05 read them through :func:`ppo_kwargs`. Each entry:
``env`` (keyword arguments of the task's class), ``network`` (hidden layer sizes of the policy and value MLPs) and
``ppo`` (``ppo.train`` keywords). ``fourbar_track`` is sized for a 2-core CPU (about a minute); ``dr_legs_joystick``
and ``bdx_joystick`` for a GPU (``bdx_joystick`` takes dr_legs' recipe with the robot's own stance width).
"""

from __future__ import annotations

import copy
import functools

PPO_CONFIGS: dict[str, dict] = {
    "fourbar_track": {
        "env": {},
        "network": {"policy_hidden_layer_sizes": (32, 32), "value_hidden_layer_sizes": (64, 64)},
        "ppo": {
            "num_timesteps": 102_400, "num_evals": 5, "episode_length": 100, "num_envs": 64, "num_eval_envs": 64,
            "unroll_length": 10, "batch_size": 64, "num_minibatches": 8, "num_updates_per_batch": 4,
            "learning_rate": 1e-3, "entropy_cost": 1e-3, "discounting": 0.95, "reward_scaling": 1.0,
            "normalize_observations": True, "deterministic_eval": True, "seed": 0,
        },
    },
    "dr_legs_joystick": {
        # the recipe that passes the walking test from scratch (docs/envs.md, "The `dr_legs_joystick` recipe, and
        # why"; 0.070 m/s mean tracking error and no falls in 256 episodes at 55 M steps): a 2.5 Hz gait clock
        # whose swing heights are rewarded (feet_phase), forward commands up to 0.6 m/s, a narrow tracking kernel,
        # and a stance of 0.13 m between the feet (feet_width; the model's own is 0.2 m), which cuts the lateral sway
        # by a quarter and the mean-velocity error by half against the same recipe without it (0.095 m/s at 43 M)
        "env": {"gait_frequency": 2.5, "command_lin_x": 0.6, "tracking_sigma": 0.1, "stance_width": 0.13,
                "reward_weights": {"tracking_lin_vel": 1.5, "tracking_ang_vel": 1.5, "feet_phase": 1.0,
                                   "lin_vel_z": -2.0, "ang_vel_xy": -0.05, "feet_width": 0.5}},
        "network": {"policy_hidden_layer_sizes": (128, 128, 128), "value_hidden_layer_sizes": (256, 256, 256)},
        "ppo": {
            "num_timesteps": 300_000_000, "num_evals": 20, "episode_length": 1000, "num_envs": 16384,
            "num_eval_envs": 128, "unroll_length": 20, "batch_size": 512, "num_minibatches": 32,
            "num_updates_per_batch": 4, "learning_rate": 3e-4, "entropy_cost": 5e-3, "discounting": 0.98,
            "reward_scaling": 1.0, "normalize_observations": True, "max_grad_norm": 1.0, "seed": 0,
            # a fixed rate (brax's default schedule), as Playground trains its joysticks. Brax's ADAPTIVE_KL adapts
            # after each of the 128 minibatch steps of an update and held every run trained with it at its 1e-5
            # floor; at 3e-4 the walking test's error fell from 0.282 to 0.144 m/s in 38 M steps (docs/envs.md,
            # "The `dr_legs_joystick` recipe, and why")
        },
    },
}
#: the loop-free biped: dr_legs' recipe and PPO settings; ``feet_width`` holds the stance of bdx's nominal pose
PPO_CONFIGS["bdx_joystick"] = {**PPO_CONFIGS["dr_legs_joystick"],
                               "env": {k: v for k, v in PPO_CONFIGS["dr_legs_joystick"]["env"].items()
                                       if k != "stance_width"}}
#: Olaf's show (kamino.envs.olaf_show): dr_legs' PPO settings and networks; the task's own rewards (standing, show)
PPO_CONFIGS["olaf_show"] = {**PPO_CONFIGS["dr_legs_joystick"], "env": {}}
#: dr_legs on rough terrain (kamino.envs.rough): dr_legs_joystick's recipe and environment keywords, so that its
#: policies (the shipped dr_legs_walk) run on it and can be fine-tuned there; the terrain's defaults
PPO_CONFIGS["dr_legs_rough"] = copy.deepcopy(PPO_CONFIGS["dr_legs_joystick"])


def task_config(task: str) -> dict:
    """A deep copy of ``PPO_CONFIGS[task]`` (raises naming the known tasks)."""
    if task not in PPO_CONFIGS:
        raise ValueError(f"task_config: unknown task {task!r} (the task argument); choose one of "
                         f"{sorted(PPO_CONFIGS)}")
    return copy.deepcopy(PPO_CONFIGS[task])


def ppo_kwargs(task: str, **overrides) -> dict:
    """``ppo.train`` keyword arguments of ``task``: its ``ppo`` entry, ``network_factory`` built from ``network``,
    then ``overrides`` (any ``ppo.train`` keyword)."""
    from brax.training.agents.ppo import networks as ppo_networks

    cfg = task_config(task)
    kwargs = dict(cfg["ppo"])
    kwargs["network_factory"] = functools.partial(ppo_networks.make_ppo_networks, **cfg["network"])
    kwargs.update(overrides)
    return kwargs


__all__ = ["PPO_CONFIGS", "ppo_kwargs", "task_config"]
