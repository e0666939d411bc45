"""Domain randomization in Brax's form: ``randomization_fn(sys, rng) -> (sys_batched, in_axes)``.

``brax.training.agents.ppo.train(randomization_fn=...)`` calls it with the environment's ``sys``
(:class:`kamino.envs.system.EnvSystem`) and one key per environment of a device (``rng [num_envs, 2]``); Brax's
``DomainRandomizationVmapWrapper`` then ``vmap``s ``reset``/``step`` over the returned batch. :func:`randomize`
builds such a function from ranges; any function of that signature works (e.g. one that only changes
``sys.geom_friction``).
"""

from __future__ import annotations

from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np

from kamino.envs.system import EnvSystem

Range = tuple[float, float]


def _check_range(name: str, value, positive: bool) -> Range | None:
    if value is None:
        return None
    try:
        lo, hi = (float(v) for v in value)
    except (TypeError, ValueError):
        raise ValueError(f"randomize: {name} must be a (low, high) pair of numbers or None, got {value!r}") from None
    if not (np.isfinite(lo) and np.isfinite(hi) and lo <= hi and (lo > 0 if positive else lo >= 0)):
        need = "0 < low <= high" if positive else "0 <= low <= high"
        raise ValueError(f"randomize: {name} must satisfy {need} (finite), got {value!r}")
    return lo, hi


def randomize(*, mass_scale: Range | None = (0.8, 1.2), friction_scale: Range | None = (0.5, 1.5),
              kp_scale: Range | None = (0.9, 1.1), kd_scale: Range | None = (0.9, 1.1),
              armature_scale: Range | None = None, damping_scale: Range | None = None,
              effort_limit_scale: Range | None = None, gravity_scale: Range | None = None,
              action_delay: Range | None = None) -> Callable[[EnvSystem, jax.Array], tuple[EnvSystem, EnvSystem]]:
    """A Brax ``randomization_fn`` drawing, per environment and uniformly in the given ``(low, high)`` ranges:

    - ``mass_scale``: a factor per body on its mass *and* inertia (same shape, denser or lighter);
    - ``friction_scale``: a factor per geom on its friction;
    - ``kp_scale``, ``kd_scale``, ``armature_scale``, ``damping_scale``, ``effort_limit_scale``: one factor per DoF
      on the PD gains, armature, passive damping and actuator effort limit (an unlimited DoF, ``inf``, stays
      unlimited);
    - ``gravity_scale``: one factor on the gravity vector;
    - ``action_delay``: the actuator delay [s] (``EnvSystem.action_delay``, within one policy period).

    ``None`` leaves a parameter nominal. Returns ``fn(sys, rng)`` with ``rng`` a batch of keys ``[B, 2]``; it
    returns the batched :class:`EnvSystem` (every leaf with a leading axis ``B``) and ``in_axes`` (0 on every leaf).
    """
    ranges = {name: _check_range(name, value, positive=name != "action_delay") for name, value in (
        ("mass_scale", mass_scale), ("friction_scale", friction_scale), ("kp_scale", kp_scale),
        ("kd_scale", kd_scale), ("armature_scale", armature_scale), ("damping_scale", damping_scale),
        ("effort_limit_scale", effort_limit_scale), ("gravity_scale", gravity_scale), ("action_delay", action_delay))}

    def one(sys: EnvSystem, key: jax.Array) -> EnvSystem:
        # the first seven ranges' keys as before effort_limit_scale and gravity_scale existed (the same draws for the
        # same seed), the two later ones folded in
        first = [n for n in ranges if n not in ("effort_limit_scale", "gravity_scale")]
        keys = dict(zip(first, jax.random.split(key, len(first)), strict=True))
        keys.update(effort_limit_scale=jax.random.fold_in(key, 1), gravity_scale=jax.random.fold_in(key, 2))

        def draw(name, shape, dtype):
            lo, hi = ranges[name]
            return jax.random.uniform(keys[name], shape, dtype, lo, hi)

        changes = {}
        if ranges["mass_scale"]:
            f = draw("mass_scale", sys.body_mass.shape, sys.body_mass.dtype)
            changes.update(body_mass=sys.body_mass * f, body_inertia=sys.body_inertia * f[:, None, None])
        for name, field in (("friction_scale", "geom_friction"), ("kp_scale", "dof_kp"), ("kd_scale", "dof_kd"),
                            ("armature_scale", "dof_armature"), ("damping_scale", "dof_damping"),
                            ("effort_limit_scale", "dof_effort_limit")):
            if ranges[name]:
                x = getattr(sys, field)
                changes[field] = x * draw(name, x.shape, x.dtype)
        if ranges["gravity_scale"]:
            changes["gravity"] = sys.gravity * draw("gravity_scale", (), sys.gravity.dtype)
        if ranges["action_delay"]:
            changes["action_delay"] = draw("action_delay", (), sys.action_delay.dtype)
        return sys.replace(**changes)

    def randomization_fn(sys: EnvSystem, rng: jax.Array) -> tuple[EnvSystem, EnvSystem]:
        if not isinstance(sys, EnvSystem):
            raise TypeError(f"randomization_fn: sys must be a kamino.envs.EnvSystem (a kamino environment's "
                            f"env.sys), got {type(sys).__name__}")
        rng = jnp.asarray(rng)
        if rng.ndim != 2:
            raise ValueError(f"randomization_fn: rng must be a batch of keys [num_envs, 2], got shape {rng.shape}")
        batched = jax.vmap(lambda k: one(sys, k))(rng)
        return batched, jax.tree.map(lambda _: 0, batched)

    return randomization_fn


__all__ = ["randomize"]
