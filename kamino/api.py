"""Public entry points: ``step``, ``rollout``, ``init_state``, ``metrics``, and the read-outs a task needs:
``joint_positions`` (every joint's coordinates), ``joint_coordinates`` (one joint's, by name), ``body_frame`` (a
body's velocity, gravity direction and height in its own frame) and ``body_contact_forces`` (the net contact force
on each body).

``step`` and ``rollout`` run the :class:`~kamino.simulator.Simulator` a model keeps for each backend and
configuration: ``"jax"`` is the reference in ``kamino/jax_ref``, ``"warp"`` the production backend in
``kamino/warp_backend`` (docs/warp_backend.md).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from kamino.checks import check_model
from kamino.config import SolverConfig
from kamino.model import JointType, Model
from kamino.simulator import DEFAULT_BACKEND, Simulator, simulator_of
from kamino.spatial import quat_to_matrix
from kamino.state import ContactState, Control, State, StepInfo


def init_state(model: Model, dtype=None, *, joint_positions=None, actuated_positions=None, base_pose=None,
               **fk_options) -> State:
    """The model's initial state: zero twists (the builder's, if set), reactions and contacts.

    Without coordinates the bodies are at the builder's (reference) poses. With ``joint_positions``,
    ``actuated_positions`` and/or ``base_pose`` the poses come from :func:`kamino.forward_kinematics`
    (consistent with every joint and loop closure; ``fk_options`` are passed on), which raises a
    ``ValueError`` naming the worlds that do not converge. ``dtype`` defaults to JAX's default float
    (float32, or float64 with ``jax_enable_x64``).
    """
    dtype = jnp.zeros(0).dtype if dtype is None else jnp.dtype(dtype)
    body_q = jnp.asarray(model.body_q0, dtype)
    body_u = jnp.asarray(model.body_u0, dtype)
    if joint_positions is not None or actuated_positions is not None or base_pose is not None:
        from kamino.kinematics import forward_kinematics

        fk = forward_kinematics(model, joint_positions, actuated_positions, base_pose, dtype=dtype, **fk_options)
        bad = np.nonzero(~np.asarray(fk.converged))[0]
        if bad.size:
            raise ValueError(f"init_state: forward kinematics did not converge in worlds {bad[:8].tolist()} "
                             f"(residual {np.asarray(fk.residual)[bad[:8]].tolist()}); the coordinates may be "
                             "unreachable")
        body_q, body_u = fk.body_q, jnp.zeros_like(body_u)
    return State(
        body_q=body_q,
        body_u=body_u,
        time=jnp.zeros(model.num_worlds, dtype),
        constraint_force=jnp.zeros(model.num_constraints, dtype),
        actuator_force=jnp.zeros(model.num_dofs, dtype),
        passive_force=jnp.zeros(model.num_dofs, dtype),
        limit_force=jnp.zeros(model.num_dofs, dtype),
        coupling_force=jnp.zeros(model.num_couplings, dtype),
        contacts=ContactState.empty(model.num_contacts, dtype),
        info=StepInfo.empty(model.num_worlds, dtype),
    )


def load_mjcf(source, **options) -> Model:
    """Load an MJCF file (path) or XML string as a single-world :class:`Model` (``kamino/io/mjcf.py``;
    mapping, options and what is unsupported: docs/mjcf.md). Imports ``mujoco`` on first use."""
    from kamino.io.mjcf import load_mjcf as _load_mjcf

    return _load_mjcf(source, **options)


def save_mjcf(model: Model, path=None, **options) -> str:
    """Export a single-world :class:`Model` as MJCF (``kamino/io/mjcf_export.py``; mapping, the spanning-tree
    choice and what raises: docs/mjcf.md, "Export"). Returns the XML text and writes it to ``path`` if given;
    ``load_mjcf(save_mjcf(model))`` simulates like ``model``, and MuJoCo (its viewer, MuJoCo Warp, Newton) loads
    the file. ``options``: ``lossy`` (drop geom restitution and initial velocities instead of raising),
    ``model_name``. Raises ``ValueError`` naming every feature MJCF cannot represent."""
    from kamino.io.mjcf_export import save_mjcf as _save_mjcf

    return _save_mjcf(model, path, **options)


def step(model: Model, state: State, control: Control | None = None, *, config: SolverConfig | None = None,
         backend: str = DEFAULT_BACKEND) -> State:
    """Advance every world by ``config.dt``; returns a new :class:`State` (inputs are not mutated): one call of
    :meth:`Simulator.step` with the simulator that ``model`` keeps for ``(backend, config)``.

    ``control`` holds one step's inputs (arrays flat over all worlds, no time axis); ``config`` is a
    :class:`SolverConfig` (docs/settings.md: the defaults and the speed-against-accuracy knob). Arguments of the
    wrong kind or shape raise a ``TypeError`` / ``ValueError`` naming the argument before a backend runs. A state
    whose worlds are sharded over devices (``kamino.sharding.shard_worlds``) is stepped on each device in place.
    """
    return simulator_of(model, config, backend, "step").step(state, control)


def rollout(model: Model, state: State, controls: Control | None = None, *, num_steps: int | None = None,
            config: SolverConfig | None = None, backend: str = DEFAULT_BACKEND) -> State:
    """Run many steps: one call of :meth:`Simulator.rollout` with the simulator that ``model`` keeps for
    ``(backend, config)``. ``controls`` fields carry a leading time axis (or pass ``num_steps`` and no
    controls). Returns the trajectory: a :class:`State` whose arrays have a leading time axis
    (the state after each step); :func:`metrics` reads it whole (``[num_steps, num_worlds]``). A state sharded
    over devices (``kamino.sharding.shard_worlds``) gives a trajectory sharded the same way along its world axis."""
    return simulator_of(model, config, backend, "rollout").rollout(state, controls, num_steps=num_steps)


def metrics(model: Model, state: State) -> dict[str, jax.Array]:
    """Per-world diagnostics ``[num_worlds]``: ``constraint_violation`` (max |residual| of the joint
    rows and couplings: m for translational rows, rad for rotational ones), ``anchor_gap`` (max |residual| of the
    translational joint rows [m]: how far the joints' anchor points, loop closures included, sit apart),
    ``kinetic_energy``,
    ``potential_energy`` (``-m g . r``) and ``total_energy``.

    ``state`` may also be a trajectory from :func:`rollout` (a leading time axis on every field): then each
    entry is ``[num_steps, num_worlds]``, the diagnostics after every step."""
    from kamino.jax_ref import backend

    check_model(model, "metrics")
    if not isinstance(state, State):
        raise TypeError(f"metrics: state must be a kamino.State (or a rollout's trajectory), got "
                        f"{type(state).__name__}")
    if state.body_q.ndim == 3:  # a trajectory [num_steps, num_bodies, 7]
        return jax.vmap(lambda q, u: backend.metrics(model, state.replace(body_q=q, body_u=u)))(state.body_q,
                                                                                               state.body_u)
    return backend.metrics(model, state)


def joint_positions(model: Model, state: State) -> jax.Array:
    """Joint coordinates of all joints, flat ``[model.num_coords]`` in joint order
    (docs/formulation.md §2.4): REVOLUTE angle, PRISMATIC t_x, CYLINDRICAL (t_x, angle), UNIVERSAL
    (theta_1, theta_2), SPHERICAL quaternion (x, y, z, w), CARTESIAN t, FREE (t, quaternion).
    Angles are in [-pi, pi]."""
    from kamino.jax_ref import backend

    packed = backend.joint_coordinates_padded(model, state.body_q)
    return packed.reshape(-1)[_coord_gather(model)]


def dof_state(model: Model, state: State) -> tuple[jax.Array, jax.Array]:
    """``(positions, rates)`` of every DoF, each flat ``[model.num_dofs]`` in DoF order (``model.joint_dof_start``):
    a hinge's angle [rad] and angular rate [rad/s], a slider's offset [m] and speed [m/s], what an actuated joint's
    observation reads. Positions come from the joint kinematics the step's PD actuators read; a rate is ``J_dofs u``
    (the actuation Jacobian of docs/formulation.md §2.5 applied to the body twists), the time derivative of the DoF
    position for hinges and slides. A trajectory from :func:`rollout` adds a leading ``num_steps`` axis."""
    from kamino.jax_ref import backend

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


__all__ = ["Control", "JointType", "Simulator", "SolverConfig", "State", "body_contact_forces", "body_frame",
           "dof_state", "frame_vectors", "init_state", "joint_coordinates", "joint_positions", "load_mjcf", "metrics",
           "rollout", "save_mjcf", "step"]
