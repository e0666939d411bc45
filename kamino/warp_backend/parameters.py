"""Per-world physical parameters that a traced Warp step takes from its caller (domain randomization).

A :class:`WorldParameters` holds the model quantities a step may read from its caller instead of the host
:class:`kamino.Model`: masses, inertias, friction, PD gains, armature, damping, effort limits and gravity, flat over
worlds like the Model's own arrays (a ``jax.vmap`` over ``B`` environments of a one-world model gives the arrays of
``kamino.replicate(model, B)``: every environment is a world with its own parameters). The traced step
(:func:`kamino.warp_backend.jit.batchable_step`) writes them into its stepper's model arrays before the step's
kernels run (:func:`load_parameters`), so every kernel reads each world's own values without change. Such a
stepper owns its parameter arrays (:func:`private_parameters`); the other model arrays (geometry, layout) stay
shared with the engine's other steppers.

What the stepper derives from them it derives again there: the inverse mass and inverse body-frame inertia
(``inv_mass``, ``inv_inertia``). Everything else is computed from these arrays inside every step (world-frame
inertias, gyroscopic terms, the Delassus matrix and its preconditioner, the contact pairs' friction ``max(mu_a,
mu_b)``). The row layout is the nominal model's: a passive joint-dynamics row exists where the Model's armature,
damping or stiffness is positive, an actuator row where the DoF is a PD actuator, on both backends; a parameter set
to a positive value where the nominal one is zero has no row to act on.
"""

import dataclasses
import functools
from typing import NamedTuple

import jax
import numpy as np
import warp as wp

from kamino.parameters import PARAMETER_NAMES
from kamino.warp_backend.model_data import WarpModel, model_struct
from kamino.warp_backend.types import types_of

WorldParameters = NamedTuple("WorldParameters", [(name, jax.Array) for name in PARAMETER_NAMES])
WorldParameters.__doc__ = """Physical parameters of every world, flat over worlds as in :class:`kamino.Model`: a named
tuple of the fields of :class:`kamino.parameters.PhysicalParameters` (masses, inertias, friction, PD gains, armature,
damping, effort limits; ``gravity`` ``[num_worlds, 3]``)."""

#: (WorldParameters field, ModelArrays field, Warp kind) of every parameter, in the traced step's argument order
FIELDS = (
    ("body_mass", "mass", "scalar"), ("body_inertia", "inertia", "mat33"), ("geom_friction", "geom_friction", "scalar"),
    ("dof_kp", "kp", "scalar"), ("dof_kd", "kd", "scalar"), ("dof_armature", "armature", "scalar"),
    ("dof_damping", "damping", "scalar"), ("dof_effort_limit", "effort_limit", "scalar"),
    ("gravity", "gravity", "vec3"),
)
#: model arrays derived from the parameters (written by :func:`load_parameters` too)
DERIVED = ("inv_mass", "inv_inertia")


def shapes(num_bodies: int, num_geoms: int, num_dofs: int, num_worlds: int) -> dict[str, tuple[int, ...]]:
    """The shape of every :class:`WorldParameters` field for a model of these sizes."""
    return {"body_mass": (num_bodies,), "body_inertia": (num_bodies, 3, 3), "geom_friction": (num_geoms,),
            **{f: (num_dofs,) for f in ("dof_kp", "dof_kd", "dof_armature", "dof_damping", "dof_effort_limit")},
            "gravity": (num_worlds, 3)}


def nominal(model, dtype) -> WorldParameters:
    """The parameters of ``model`` itself (a :class:`kamino.Model`) in ``dtype``: what a traced step with
    ``parameters=None`` reads."""
    f = lambda a: jax.numpy.asarray(np.asarray(a, np.float64), dtype)  # noqa: E731
    return WorldParameters(
        body_mass=f(model.body_mass), body_inertia=f(model.body_inertia), geom_friction=f(model.geom_friction),
        dof_kp=f(model.dof_kp), dof_kd=f(model.dof_kd), dof_armature=f(model.dof_armature),
        dof_damping=f(model.dof_damping), dof_effort_limit=f(model.dof_effort_limit),
        gravity=f(np.reshape(model.gravity, (model.num_worlds, 3))))


def private_parameters(wm: WarpModel) -> WarpModel:
    """``wm`` with its own copies of the parameter arrays (:data:`FIELDS` and :data:`DERIVED`) and every other
    model array shared: a stepper that loads per-world parameters leaves the engine's other steppers nominal."""
    struct = model_struct(wm.np_dtype)
    arrays = struct()
    own = {f[1] for f in FIELDS} | set(DERIVED)
    for name in struct.vars:
        value = getattr(wm.arrays, name)
        setattr(arrays, name, wp.clone(value) if name in own else value)
    return dataclasses.replace(wm, arrays=arrays)


@functools.cache
def _load_kernel(np_dtype):
    T = types_of(np_dtype)
    farr = wp.array(dtype=T.scalar)

    @wp.kernel
    def load(mass_in: farr, inertia_in: wp.array(dtype=T.mat33), friction_in: farr, kp_in: farr, kd_in: farr,
             armature_in: farr, damping_in: farr, effort_in: farr, gravity_in: wp.array(dtype=T.vec3),
             mass: farr, inv_mass: farr, inertia: wp.array(dtype=T.mat33), inv_inertia: wp.array(dtype=T.mat33),
             friction: farr, kp: farr, kd: farr, armature: farr, damping: farr, effort: farr,
             gravity: wp.array(dtype=T.vec3)):
        """Entry ``i`` of every parameter array that has one (a body's mass and inertia with their inverses, a
        geom's friction, a DoF's gains, armature, damping and effort limit, a world's gravity)."""
        i = wp.tid()
        if i < mass_in.shape[0]:
            mass[i] = mass_in[i]
            inv_mass[i] = T.scalar(1.0) / mass_in[i]
            inertia[i] = inertia_in[i]
            inv_inertia[i] = wp.inverse(inertia_in[i])
        if i < friction_in.shape[0]:
            friction[i] = friction_in[i]
        if i < kp_in.shape[0]:
            kp[i] = kp_in[i]
            kd[i] = kd_in[i]
            armature[i] = armature_in[i]
            damping[i] = damping_in[i]
            effort[i] = effort_in[i]
        if i < gravity_in.shape[0]:
            gravity[i] = gravity_in[i]

    return load


def load_parameters(arrays, np_dtype, device, given: dict) -> None:
    """Write ``given`` (:class:`WorldParameters` field -> Warp array, the traced step's inputs; an empty field may
    be left out) into the model arrays ``arrays`` (a stepper's ``wm.arrays``, owned: :func:`private_parameters`),
    with the inverse masses and inertias. One launch (capturable), a thread per entry of the longest array."""
    ins = [given.get(field, getattr(arrays, name)) for field, name, _ in FIELDS]
    n = max(a.shape[0] for a in ins)
    if n:
        outs = [arrays.mass, arrays.inv_mass, arrays.inertia, arrays.inv_inertia, arrays.geom_friction, arrays.kp,
                arrays.kd, arrays.armature, arrays.damping, arrays.effort_limit, arrays.gravity]
        wp.launch(_load_kernel(np.dtype(np_dtype)), dim=n, inputs=ins, outputs=outs, device=device)


__all__ = ["DERIVED", "FIELDS", "WorldParameters", "load_parameters", "nominal", "private_parameters", "shapes"]
