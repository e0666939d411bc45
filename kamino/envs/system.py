"""The randomizable parameters of an environment: ``env.sys``, a pytree.

Brax's domain randomization (``brax.envs.wrappers.training.DomainRandomizationVmapWrapper``) calls
``randomization_fn(env.sys, rng)`` once, gets a batched copy and its ``in_axes`` back, and ``vmap``s ``reset`` /
``step`` over it with ``env.sys`` swapped for each environment's slice. :class:`EnvSystem` is that ``sys``: the
arrays of the one-world :class:`kamino.Model` that a randomization may change, under the Model's own names
(``body_mass``, ``geom_friction``, ``dof_kp``, ...), world-local (for a one-world model they are the Model's arrays
themselves). Every simulator step of an environment reads its own parameters, on both backends: on ``"jax"``
:meth:`EnvSystem.apply` writes them into the reference's padded model (``kamino.Simulator.parameters``); on
``"warp"`` :meth:`EnvSystem.world_parameters` passes them to the Warp step's JAX FFI call, which writes them into its
stepper's model arrays before the step's kernels run (:mod:`kamino.warp_backend.parameters`; under brax's ``vmap``
each environment is one world of the batched call, with its own values). Geometry (joint frames, geom sizes) is
not randomizable: resets are solved by forward kinematics on the nominal geometry.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from kamino.model import Model


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class EnvSystem:
    """Randomizable parameters of a one-world model (arrays over that world's bodies, geoms or DoFs).

    Attributes:
        body_mass: ``[num_bodies]`` [kg].
        body_inertia: ``[num_bodies, 3, 3]`` about the CoM, body frame [kg m^2] (scale it with the mass: a denser
            body, same shape).
        geom_friction: ``[num_geoms]`` Coulomb friction (a pair uses the larger of its two geoms',
            docs/conventions.md "Contacts").
        dof_kp: ``[num_dofs]`` PD stiffness of POSITION actuators [N m/rad or N/m].
        dof_kd: ``[num_dofs]`` PD damping [N m s/rad or N s/m].
        dof_armature: ``[num_dofs]`` reflected rotor inertia [kg m^2 or kg].
        dof_damping: ``[num_dofs]`` passive viscous damping.
        dof_effort_limit: ``[num_dofs]`` actuator effort bound (``inf``: none).
        gravity: ``[3]`` [m/s^2].
        action_delay: ``[]`` [s]: within a policy step, substeps that start before this time still track the
            previous action's targets (0: no delay; at most one policy period).
    """

    body_mass: jax.Array
    body_inertia: jax.Array
    geom_friction: jax.Array
    dof_kp: jax.Array
    dof_kd: jax.Array
    dof_armature: jax.Array
    dof_damping: jax.Array
    dof_effort_limit: jax.Array
    gravity: jax.Array
    action_delay: jax.Array

    def replace(self, **changes) -> EnvSystem:
        """A copy with ``changes`` (field name -> array); unknown names raise ``TypeError``."""
        return dataclasses.replace(self, **changes)

    def tree_replace(self, params: dict) -> EnvSystem:
        """Brax's ``System.tree_replace`` spelling: ``{"body_mass": ..., ...}`` -> a copy."""
        return self.replace(**params)

    @staticmethod
    def from_model(model: Model, dtype=jnp.float32) -> EnvSystem:
        """The nominal parameters of a one-world ``model`` (its own arrays), ``action_delay`` 0."""
        if model.num_worlds != 1:
            raise ValueError(f"EnvSystem.from_model: model has {model.num_worlds} worlds; an environment simulates "
                             "one world (brax vmaps environments)")
        f = lambda a: jnp.asarray(np.asarray(a, np.float64), dtype)  # noqa: E731
        return EnvSystem(
            body_mass=f(model.body_mass), body_inertia=f(model.body_inertia), geom_friction=f(model.geom_friction),
            dof_kp=f(model.dof_kp), dof_kd=f(model.dof_kd), dof_armature=f(model.dof_armature),
            dof_damping=f(model.dof_damping), dof_effort_limit=f(model.dof_effort_limit),
            gravity=f(model.gravity).reshape(3), action_delay=jnp.zeros((), dtype))

    def apply(self, pm):
        """``pm`` (the one-world padded model of ``kamino.Simulator.parameters``, leading axis 1) with these
        parameters written in."""
        dt = pm.mass.dtype
        c = lambda x: jnp.asarray(x, dt)[None]  # noqa: E731
        return dataclasses.replace(
            pm, mass=c(self.body_mass), inertia=c(self.body_inertia), geom_friction=c(self.geom_friction),
            dof_kp=c(self.dof_kp), dof_kd=c(self.dof_kd), dof_armature=c(self.dof_armature),
            dof_damping=c(self.dof_damping), dof_effort_limit=c(self.dof_effort_limit), gravity=c(self.gravity))

    def world_parameters(self):
        """These parameters as the Warp step takes them (:class:`kamino.warp_backend.parameters.WorldParameters`
        of the one world: ``gravity`` ``[1, 3]``)."""
        from kamino.warp_backend.parameters import WorldParameters  # Warp is imported on first use

        return WorldParameters(
            body_mass=self.body_mass, body_inertia=self.body_inertia, geom_friction=self.geom_friction,
            dof_kp=self.dof_kp, dof_kd=self.dof_kd, dof_armature=self.dof_armature, dof_damping=self.dof_damping,
            dof_effort_limit=self.dof_effort_limit, gravity=jnp.reshape(self.gravity, (1, 3)))


__all__ = ["EnvSystem"]
