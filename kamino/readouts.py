"""The read-outs a task needs, computed by the JAX reference whichever backend steps: ``metrics`` (loop closure,
anchor gaps, energies), ``joint_positions`` (every joint's coordinates), ``joint_coordinates`` (one joint's, by
name), ``dof_state`` (every DoF's position and rate), ``body_frame`` (a body's velocity, gravity direction and height
in its own frame) and ``body_contact_forces`` (the net contact force on each body). Each reads a state, or a
rollout's trajectory whole.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from kamino.checks import check_model, check_state_model
from kamino.jax_ref import backend
from kamino.model import Model
from kamino.spatial import quat_to_matrix
from kamino.state import State


def metrics(model: Model, state: State) -> dict[str, jax.Array]:
    """Per-world diagnostics ``[num_worlds]``: ``constraint_violation`` (max |residual| of the joint
    rows and couplings: m for translational rows, rad for rotational ones), ``anchor_gap`` (max |residual| of the
    translational joint rows [m]: how far the joints' anchor points, loop closures included, sit apart),
    ``kinetic_energy``,
    ``potential_energy`` (``-m g . r``) and ``total_energy``.

    ``state`` may also be a trajectory from :func:`rollout` (a leading time axis on every field): then each
    entry is ``[num_steps, num_worlds]``, the diagnostics after every step."""
    check_model(model, "metrics")
    if not isinstance(state, State):
        raise TypeError(f"metrics: state must be a kamino.State (or a rollout's trajectory), got "
                        f"{type(state).__name__}")
    check_state_model(model, state, "metrics")
    if state.body_q.ndim == 3:  # a trajectory [num_steps, num_bodies, 7]
        return jax.vmap(lambda q, u: backend.metrics(model, state.replace(body_q=q, body_u=u)))(state.body_q,
                                                                                               state.body_u)
    return backend.metrics(model, state)


def joint_positions(model: Model, state: State) -> jax.Array:
    """Joint coordinates of all joints, flat ``[model.num_coords]`` in joint order
    (docs/formulation.md §2.4): REVOLUTE angle, PRISMATIC t_x, CYLINDRICAL (t_x, angle), UNIVERSAL
    (theta_1, theta_2), SPHERICAL quaternion (x, y, z, w), CARTESIAN t, FREE (t, quaternion).
    Angles are in [-pi, pi]."""
    packed = backend.joint_coordinates_padded(model, state.body_q)
    return packed.reshape(-1)[_coord_gather(model)]


def dof_state(model: Model, state: State) -> tuple[jax.Array, jax.Array]:
    """``(positions, rates)`` of every DoF, each flat ``[model.num_dofs]`` in DoF order (``model.joint_dof_start``):
    a hinge's angle [rad] and angular rate [rad/s], a slider's offset [m] and speed [m/s], what an actuated joint's
    observation reads. Positions come from the joint kinematics the step's PD actuators read; a rate is ``J_dofs u``
    (the actuation Jacobian of docs/formulation.md §2.5 applied to the body twists), the time derivative of the DoF
    position for hinges and slides. A trajectory from :func:`rollout` adds a leading ``num_steps`` axis."""
    return _per_step(state, "dof_state", lambda s: backend.dof_state(model, s.body_q, s.body_u))


def _world_index(model: Model, world: int, fn: str) -> int:
    if isinstance(world, bool) or not isinstance(world, (int, np.integer)) or not 0 <= world < model.num_worlds:
        raise ValueError(f"{fn}: world must be an integer in [0, {model.num_worlds}) (the model's worlds), got "
                         f"{world!r}")
    return int(world)


def _entity_index(model: Model, kind: str, names: tuple[str, ...], which: str | int, world: int, fn: str) -> int:
    """Global index of the ``kind`` (``"joint"``, ``"body"``) named ``which`` in ``world``, or ``which`` itself when
    it is a global index; a ``KeyError`` / ``ValueError`` names what is wrong and the world's names."""
    world = _world_index(model, world, fn)
    start = int(getattr(model, f"world_{kind}_start")[world])
    count = int(getattr(model, f"world_{kind}_count")[world])
    if isinstance(which, str):
        local = names[start:start + count]
        if which not in local:
            shown = ", ".join(repr(n) for n in local[:12]) + (", ..." if count > 12 else "")
            plural = {"body": "bodies"}.get(kind, f"{kind}s")
            raise KeyError(f"{fn}: no {kind} named {which!r} in world {world}; its {plural} are {shown}")
        return start + local.index(which)
    total = len(names)
    if isinstance(which, bool) or not isinstance(which, (int, np.integer)) or not 0 <= which < total:
        raise ValueError(f"{fn}: {kind} must be a {kind} name or a global {kind} index in [0, {total}), got "
                         f"{which!r}")
    return int(which)


def _per_step(state: State, fn: str, read):
    """``read(state)`` for one state, or over a trajectory's leading time axis (:func:`rollout`)."""
    if not isinstance(state, State):
        raise TypeError(f"{fn}: state must be a kamino.State (or a rollout's trajectory), got {type(state).__name__}")
    if state.body_q.ndim == 3:
        return jax.vmap(read)(state)
    return read(state)


def joint_coordinates(model: Model, state: State, joint: str | int, world: int = 0) -> jax.Array:
    """The coordinates of one joint: ``[model.joint_coord_count[j]]``, in the layout of :func:`joint_positions`
    (REVOLUTE: the angle in ``[-pi, pi]``; PRISMATIC: ``t_x``; FREE: position then quaternion ``(x, y, z, w)``; ...).

    ``joint`` is the joint's name in ``world`` (``model.joint_names``) or its global index (then ``world`` is not
    read). ``state`` may be a trajectory from :func:`rollout`: then the result is ``[num_steps, count]``. An unknown
    name raises a ``KeyError`` listing the world's joints::

        crank = kamino.joint_coordinates(model, state, "ground_crank")[0]  # the crank angle [rad]
    """
    j = _entity_index(model, "joint", model.joint_names, joint, world, "joint_coordinates")
    start, count = int(model.joint_coord_start[j]), int(model.joint_coord_count[j])
    return _per_step(state, "joint_coordinates", lambda s: joint_positions(model, s)[start:start + count])


def body_frame(model: Model, state: State, body: str | int, world: int = 0) -> dict[str, jax.Array]:
    """A body's motion seen in its own (CoM) frame, what a legged robot's base observes:

    - ``lin_vel`` ``[3]``: CoM linear velocity [m/s] in body axes;
    - ``ang_vel`` ``[3]``: angular velocity [rad/s] in body axes;
    - ``gravity`` ``[3]``: the world's ``-z`` in body axes, ``(0, 0, -1)`` when the body is upright;
    - ``height``: CoM height above ``z = 0`` [m];
    - ``up``: the world z component of the body's z axis (1 upright, 0 on its side, -1 upside down).

    ``body`` is the body's name in ``world`` (``model.body_names``) or its global index. A trajectory from
    :func:`rollout` adds a leading ``num_steps`` axis to every entry."""
    b = _entity_index(model, "body", model.body_names, body, world, "body_frame")
    return _per_step(state, "body_frame", lambda s: frame_vectors(s.body_q, s.body_u, b))


def frame_vectors(body_q: jax.Array, body_u: jax.Array, body: int) -> dict[str, jax.Array]:
    """:func:`body_frame`'s entries for the body at index ``body`` of ``body_q`` ``[n, 7]`` and ``body_u``
    ``[n, 6]`` (``State.body_q`` / ``body_u``, or one world's rows)."""
    R = quat_to_matrix(body_q[body, 3:])
    down = jnp.asarray([0.0, 0.0, -1.0], body_q.dtype)
    return {"gravity": R.T @ down, "lin_vel": R.T @ body_u[body, :3], "ang_vel": R.T @ body_u[body, 3:],
            "height": body_q[body, 2], "up": R[2, 2]}


def body_contact_forces(model: Model, state: State) -> jax.Array:
    """The net contact force on every body [N], world frame: ``[model.num_bodies, 3]``, the sum over the last
    step's contacts (``state.contacts``) of ``ContactState.force`` on geom b's body and its opposite on geom a's.
    Bodies without a contact get zeros; a world-attached geom (the ground) takes no row. A body resting on the
    ground carries about its weight, ``(0, 0, m g)``; a foot is on the ground while its z component is positive.
    A trajectory from :func:`rollout` gives ``[num_steps, num_bodies, 3]``."""
    cap = model.num_contacts
    if cap == 0 or model.num_pairs == 0:
        return _per_step(state, "body_contact_forces",
                         lambda s: jnp.zeros((model.num_bodies, 3), s.body_q.dtype))
    slot_world = np.repeat(np.arange(model.num_worlds), model.world_contact_capacity)
    first_pair = jnp.asarray(model.world_pair_start[slot_world], jnp.int32)  # [C]
    body_a = jnp.asarray(model.geom_body[model.pair_geom_a], jnp.int32)  # [P] global body or -1
    body_b = jnp.asarray(model.geom_body[model.pair_geom_b], jnp.int32)
    dump = model.num_bodies  # the segment that collects world-attached geoms and empty slots

    def read(s: State) -> jax.Array:
        pair = s.contacts.pair
        used = pair >= 0
        k = first_pair + jnp.maximum(pair, 0)
        a = jnp.where(used & (body_a[k] >= 0), body_a[k], dump)
        b = jnp.where(used & (body_b[k] >= 0), body_b[k], dump)
        f = jnp.where(used[:, None], s.contacts.force, 0.0)
        total = jax.ops.segment_sum(f, b, dump + 1) - jax.ops.segment_sum(f, a, dump + 1)
        return total[:dump]

    return _per_step(state, "body_contact_forces", read)


def _coord_gather(model: Model) -> np.ndarray:
    """Flat index into the padded ``[W * max_joints * 7]`` coordinates for each model coordinate."""
    nj = int(model.world_joint_count.max()) if model.num_joints else 0
    local_j = np.arange(model.num_joints) - model.world_joint_start[model.joint_world]
    slot = model.joint_world * nj + local_j
    counts = model.joint_coord_count
    return np.repeat(slot * 7, counts) + (np.arange(int(counts.sum())) - np.repeat(model.joint_coord_start, counts))


__all__ = ["body_contact_forces", "body_frame", "dof_state", "frame_vectors", "joint_coordinates", "joint_positions",
           "metrics"]
