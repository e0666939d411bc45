"""The physical parameters a step may take from its caller instead of the :class:`kamino.Model` (domain
randomization): one field list, :class:`PhysicalParameters`, under the Model's own array names. Two containers carry
it: :class:`kamino.warp_backend.parameters.WorldParameters` (the Warp step's, flat over worlds) and
:class:`kamino.envs.EnvSystem` (an environment's ``sys``, its one world's, with the action delay). This module
imports neither Warp nor brax.
"""

from __future__ import annotations

import dataclasses

import jax


@dataclasses.dataclass(frozen=True)
class PhysicalParameters:
    """Per-world physical parameters, under the :class:`kamino.Model` arrays' names (the Model's shapes: over bodies,
    geoms or DoFs; a container says whether over one world or all).

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
        gravity: [m/s^2], per world.
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


PARAMETER_NAMES: tuple[str, ...] = tuple(f.name for f in dataclasses.fields(PhysicalParameters))
"""The names of :class:`PhysicalParameters`' fields, in order."""

__all__ = ["PARAMETER_NAMES", "PhysicalParameters"]
