"""Brax's PPO on JAX releases without ``jax.device_put_replicated``.

Brax 0.14 (``brax.training.agents.ppo.train``, ``brax.training.pmap``) places its training state on the local
devices with ``jax.device_put_replicated``, which JAX 0.11 removed (it raises ``AttributeError``; the JAX guide
"Migrating to the new jax.pmap" names ``jax.device_put`` as the replacement). Where it is missing,
:func:`install` provides it as that replacement, so that ``brax.training.agents.ppo.train`` runs unchanged on
either release (the lent GPUs carry JAX 0.11). Where JAX still has it, nothing changes.
"""

from __future__ import annotations

import warnings
from collections.abc import Sequence

import jax
import jax.numpy as jnp
import numpy as np


def device_put_replicated(x, devices: Sequence[jax.Device]):
    """Every leaf of ``x`` stacked ``len(devices)`` times on a new leading axis, one copy on each device (what
    ``pmap`` expects of a replicated argument)."""
    devices = list(devices)
    if not devices:
        raise ValueError("device_put_replicated: devices is empty")
    mesh = jax.sharding.Mesh(np.asarray(devices), ("devices",))
    sharding = jax.sharding.NamedSharding(mesh, jax.sharding.PartitionSpec("devices"))
    return jax.tree.map(lambda a: jax.device_put(jnp.stack([jnp.asarray(a)] * len(devices)), sharding), x)


def install() -> None:
    """Provide ``jax.device_put_replicated`` where this JAX lacks it."""
    with warnings.catch_warnings():  # the probe alone must not warn; brax's own call still does where deprecated
        warnings.simplefilter("ignore", DeprecationWarning)
        present = hasattr(jax, "device_put_replicated")  # False where removed (getattr raises AttributeError)
    if not present:
        jax.device_put_replicated = device_put_replicated
