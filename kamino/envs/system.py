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
from kamino.parameters import PARAMETER_NAMES, PhysicalParameters


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class EnvSystem(PhysicalParameters):
    """Randomizable parameters of a one-world model: the fields of :class:`kamino.parameters.PhysicalParameters`
    (``body_mass``, ``body_inertia``, ``geom_friction``, ``dof_kp``, ``dof_kd``, ``dof_armature``, ``dof_damping``,
    ``dof_effort_limit``: arrays over that world's bodies, geoms or DoFs; ``gravity`` ``[3]``), and the action delay.

    Attributes:
        action_delay: ``[]`` [s]: within a policy step, substeps that start before this time still track the
            previous action's targets (0: no delay; at most one policy period).
    """

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
        values = {name: f(getattr(model, name)) for name in PARAMETER_NAMES}
        return EnvSystem(**values | {"gravity": values["gravity"].reshape(3)}, action_delay=jnp.zeros((), dtype))

    def apply(self, pm):
        """``pm`` (the one-world padded model of ``kamino.Simulator.parameters``, leading axis 1) with these
        parameters written in."""
        dt = pm.mass.dtype
        padded = {"body_mass": "mass", "body_inertia": "inertia"}  # the padded model's names where they differ
        return dataclasses.replace(pm, **{padded.get(name, name): jnp.asarray(getattr(self, name), dt)[None]
                                          for name in PARAMETER_NAMES})

    def world_parameters(self):
        """These parameters as the Warp step takes them (:class:`kamino.warp_backend.parameters.WorldParameters`
        of the one world: ``gravity`` ``[1, 3]``)."""
        from kamino.warp_backend.parameters import WorldParameters  # Warp is imported on first use

        values = {name: getattr(self, name) for name in PARAMETER_NAMES}
        return WorldParameters(**values | {"gravity": jnp.reshape(self.gravity, (1, 3))})
