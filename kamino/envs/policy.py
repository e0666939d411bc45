"""Trained policies as evaluation needs them: from a run's checkpoint, or shipped with kamino.

``kamino.envs.load_policy("dr_legs_walk")`` loads a shipped policy; :func:`load_checkpoint` loads a checkpoint of a
``kamino train`` run. Both return a :class:`Policy`: the task, the environment's keywords it was trained with, the
network config, and the parameters ``(normalizer, policy)`` that Brax's inference function takes.

A shipped policy is a folder under ``kamino/envs/policies/``: ``policy.json`` (task, environment keywords, network
config, origin) and ``params.npz`` (plain arrays, read with ``allow_pickle=False``). :func:`export_policy` writes
one from a checkpoint.
"""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

#: the folder of the shipped policies (package data)
POLICIES = Path(__file__).resolve().parent / "policies"
#: the normalizer's array fields as stored in ``params.npz`` (under ``normalizer/``)
_NORMALIZER_ARRAYS = ("mean", "std", "summed_variance", "std_eps")


@dataclasses.dataclass(frozen=True)
class Policy:
    """A trained PPO policy and what it was trained on.

    ``task``: the registered environment (``kamino.envs.TASKS``); ``env``: its keywords; ``config``: Brax's network
    config (``observation_size``, ``action_size``, ``normalize_observations``, ``network_factory_kwargs``);
    ``params``: ``(normalizer state, policy parameters)``; ``source``: where it was loaded from; ``step``: the
    environment steps it was trained for (``None`` when unknown)."""

    task: str
    env: dict
    config: dict
    params: tuple
    source: str
    step: int | None = None

    @property
    def observation_size(self) -> int:
        return int(self.config["observation_size"])

    @property
    def action_size(self) -> int:
        return int(self.config["action_size"])

    @property
    def make_policy(self) -> Callable:
        """Brax's inference factory for this network: ``make_policy(params, deterministic=True)(obs, key)`` is
        ``(action, extras)``."""
        from brax.training.agents.ppo import networks as ppo_networks

        return ppo_networks.make_inference_fn(make_networks(self.config))

    def act(self, obs: Any, deterministic: bool = True, key: Any = None) -> Any:
        """The action for observations ``obs`` (``[..., observation_size]``): the mode of the action distribution, or
        a sample with ``deterministic=False`` (``key``: a JAX PRNG key, default ``PRNGKey(0)``)."""
        import jax

        key = jax.random.PRNGKey(0) if key is None else key
        return self.make_policy(self.params, deterministic=deterministic)(obs, key)[0]


def make_networks(config: dict):
    """Brax's PPO networks of a network config (as ``ppo_network_config.json`` holds it), built without the task's
    current config, so that a policy keeps working when the task's defaults change."""
    from brax.training import networks
    from brax.training.acme import running_statistics
    from brax.training.agents.ppo import networks as ppo_networks

    kwargs = {k: v for k, v in dict(config.get("network_factory_kwargs", {})).items() if v is not None}
    if isinstance(kwargs.get("activation"), str):
        kwargs["activation"] = networks.ACTIVATION[kwargs["activation"]]
    for name, value in list(kwargs.items()):
        if name.endswith("_init_fn") and isinstance(value, str):
            kwargs[name] = networks.KERNEL_INITIALIZER[value]
    for name in ("policy_hidden_layer_sizes", "value_hidden_layer_sizes"):
        if name in kwargs:
            kwargs[name] = tuple(kwargs[name])
    normalize = running_statistics.normalize if config.get("normalize_observations") else (lambda x, y: x)
    return ppo_networks.make_ppo_networks(int(config["observation_size"]), int(config["action_size"]),
                                          preprocess_observations_fn=normalize, **kwargs)


def shipped_policies() -> list[str]:
    """The names of the policies that ship with kamino."""
    if not POLICIES.is_dir():
        return []
    return sorted(d.name for d in POLICIES.iterdir() if (d / "policy.json").is_file())


def load_policy(name: str) -> Policy:
    """The shipped policy ``name`` (one of :func:`shipped_policies`, e.g. ``"dr_legs_walk"``)."""
    names = shipped_policies()
    if name not in names:
        raise ValueError(f"load_policy: unknown policy {name!r}; the shipped policies are {names}")
    return read_policy(POLICIES / name)


def read_policy(folder: Path) -> Policy:
    """The policy stored in ``folder`` (``policy.json`` and ``params.npz``, as :func:`export_policy` writes them)."""
    from brax.training import types
    from brax.training.acme import running_statistics

    folder = Path(folder)
    meta = json.loads((folder / "policy.json").read_text())
    with np.load(folder / "params.npz", allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files}
    norm = {k: arrays.pop(f"normalizer/{k}") for k in _NORMALIZER_ARRAYS}
    count = types.UInt64(hi=arrays.pop("normalizer/count_hi"), lo=arrays.pop("normalizer/count_lo"))
    normalizer = running_statistics.RunningStatisticsState(
        count=count, mode=running_statistics.NormalizationMode(meta["normalizer_mode"]), **norm)
    policy: dict = {}
    for key, value in arrays.items():
        parts = key.split("/")
        if parts[0] != "policy":
            raise ValueError(f"read_policy: unexpected array {key!r} in {folder / 'params.npz'}")
        node = policy
        for part in parts[1:-1]:
            node = node.setdefault(part, {})
        node[parts[-1]] = value
    return Policy(task=meta["task"], env=meta["env"], config=meta["network"], params=(normalizer, policy),
                  source=str(folder), step=meta.get("step"))


def load_checkpoint(path: Path, task: str | None = None) -> Policy:
    """The policy of a ``kamino train`` checkpoint ``path`` (``RUN/checkpoints/<step>``; a run folder or its
    ``checkpoints`` folder gives its newest complete checkpoint). ``task`` defaults to the run's ``run.json``, else
    ``dr_legs_joystick``. Raises ``FileNotFoundError`` when there is no complete checkpoint."""
    from brax.training.agents.ppo import checkpoint as ppo_checkpoint

    from kamino.envs import runs

    ckpt = newest_checkpoint(Path(path).resolve())
    task = task or runs.run_task(ckpt) or "dr_legs_joystick"
    config = json.loads((ckpt / runs.NETWORK_CONFIG).read_text())
    params = ppo_checkpoint.load(ckpt)
    return Policy(task=task, env=runs.run_env(ckpt, task), config=config, params=(params[0], params[1]),
                  source=str(ckpt), step=int(ckpt.name) if ckpt.name.isdigit() else None)


def newest_checkpoint(path: Path) -> Path:
    """``path`` itself if it is a complete checkpoint, else the newest complete one of a run folder
    (``checkpoints/<step>/``) or of a ``checkpoints`` folder."""
    from kamino.envs import runs

    path = Path(path)
    if runs.is_checkpoint(path):
        return path
    for folder in (path / "checkpoints", path):
        _, newest = runs.latest_checkpoint(folder)
        if newest is not None:
            return newest
    raise FileNotFoundError(f"no complete brax PPO checkpoint in {path} (expected {runs.COMMIT_MARKER} and "
                            f"{runs.NETWORK_CONFIG}, or checkpoints/<step>/ as kamino train writes them)")


def export_policy(policy: Policy, folder: Path, **info: Any) -> Path:
    """Write ``policy`` to ``folder`` as a shipped policy (``policy.json`` with ``info`` merged in, and
    ``params.npz``: the normalizer and the policy network, not the value network)."""
    from brax.training import types

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    normalizer, policy_params = policy.params
    arrays = {f"normalizer/{k}": np.asarray(getattr(normalizer, k), np.float32) for k in _NORMALIZER_ARRAYS}
    count = normalizer.count
    if not hasattr(count, "hi"):  # a plain count: split into the 64-bit halves Brax's UInt64 holds
        total = int(np.asarray(count))
        count = types.UInt64(hi=total >> 32, lo=total & 0xFFFFFFFF)
    arrays["normalizer/count_hi"] = np.asarray(count.hi, np.uint32)
    arrays["normalizer/count_lo"] = np.asarray(count.lo, np.uint32)

    def flatten(node: dict, prefix: str) -> None:
        for key, value in node.items():
            if isinstance(value, dict):
                flatten(value, f"{prefix}/{key}")
            else:
                arrays[f"{prefix}/{key}"] = np.asarray(value)

    flatten(dict(policy_params), "policy")
    np.savez_compressed(folder / "params.npz", **arrays)
    meta = {"task": policy.task, "env": policy.env, "network": policy.config, "step": policy.step,
            "normalizer_mode": int(normalizer.mode), **info}
    (folder / "policy.json").write_text(json.dumps(meta, indent=1) + "\n")
    return folder


__all__ = ["POLICIES", "Policy", "export_policy", "load_checkpoint", "load_policy", "make_networks",
           "newest_checkpoint", "read_policy", "shipped_policies"]
