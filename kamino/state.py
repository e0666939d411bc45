"""State, Control and StepInfo: JAX pytrees shared by both backends (docs/conventions.md)."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from kamino.model import ActuationMode, Model


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class StepInfo:
    """Per-world report of the last step's constraint solve (all arrays ``[num_worlds]``).

    ``failed`` marks a world whose new state was non-finite: that world keeps its previous
    state (it never contaminates other worlds and never silently holds NaN).
    """

    iterations: jax.Array
    primal_residual: jax.Array
    dual_residual: jax.Array
    complementarity_residual: jax.Array
    converged: jax.Array
    failed: jax.Array
    num_contacts: jax.Array
    contact_overflow: jax.Array
    penalty: jax.Array
    unconverged_steps: jax.Array

    @staticmethod
    def empty(num_worlds: int, dtype=jnp.float32) -> StepInfo:
        z = jnp.zeros(num_worlds, dtype)
        zi = jnp.zeros(num_worlds, jnp.int32)
        return StepInfo(
            iterations=zi,
            primal_residual=z,
            dual_residual=z,
            complementarity_residual=z,
            converged=jnp.ones(num_worlds, bool),
            failed=jnp.zeros(num_worlds, bool),
            num_contacts=zi,
            contact_overflow=zi,
            penalty=z,
            unconverged_steps=zi,
        )


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class ContactState:
    """The last step's contacts, flat over worlds (``[total_contact_capacity, ...]``, world 0 first,
    each world's slots in detection order; empty slots have ``pair = -1`` and zeros).

    Attributes:
        pair: world-local index of the geom pair (``-1``: empty slot).
        pos: world point midway between the two surfaces.
        normal: unit normal from geom a to geom b.
        dist: signed gap [m] (negative: penetration).
        force: contact force on geom b's body [N], world frame (``C lambda / dt``).
        velocity: relative velocity of b with respect to a at the contact after the step, world frame.
        point_b: the contact point on geom b in its body's CoM frame (the warm-start key).
    """

    pair: jax.Array
    pos: jax.Array
    normal: jax.Array
    dist: jax.Array
    force: jax.Array
    velocity: jax.Array
    point_b: jax.Array

    @staticmethod
    def empty(capacity: int, dtype=jnp.float32) -> ContactState:
        v = jnp.zeros((capacity, 3), dtype)
        return ContactState(pair=jnp.full(capacity, -1, jnp.int32), pos=v, normal=v, dist=jnp.zeros(capacity, dtype),
                            force=v, velocity=v, point_b=v)


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class State:
    """Simulation state of all worlds (flat storage, world 0's entities first).

    Attributes:
        body_q: ``[total_bodies, 7]`` CoM poses ``(px, py, pz, qx, qy, qz, qw)`` in world.
        body_u: ``[total_bodies, 6]`` twists ``(v, w)``: CoM linear then angular velocity, world frame.
        time: ``[num_worlds]`` simulated time [s].
        constraint_force: ``[total_constraint_rows]`` last step's joint-row reactions ``lambda/dt``
            (the warm start of the next solve), in the row order of docs/conventions.md.
        actuator_force: ``[total_dofs]`` generalized force each DoF's actuator applied in the last step
            (implicit PD/D force, or the clipped commanded effort; for passive DoFs the applied effort).
        passive_force: ``[total_dofs]`` generalized force of armature, damping and springs.
        limit_force: ``[total_dofs]`` generalized force of the joint limits (positive pushes the DoF up).
        coupling_force: ``[total_couplings]`` reaction of each joint coupling (generalized force on
            joint a's DoF, ``lambda / dt``).
        contacts: the last step's :class:`ContactState`.
        info: the last solve's :class:`StepInfo`.
    """

    body_q: jax.Array
    body_u: jax.Array
    time: jax.Array
    constraint_force: jax.Array
    actuator_force: jax.Array
    passive_force: jax.Array
    limit_force: jax.Array
    coupling_force: jax.Array
    contacts: ContactState
    info: StepInfo

    def replace(self, **changes) -> State:
        return dataclasses.replace(self, **changes)


def drop_empty(tree):
    """``tree`` (a :class:`State`, or any pytree of arrays) with every zero-size array (the fields a model does not
    use: ``contacts`` without contact capacity, ``coupling_force`` without couplings, ...) replaced by ``None``, so
    that they are no pytree leaves.

    Why: XLA's GPU compiler (jax 0.11.2) crashes (segmentation fault) compiling a loop inside a per-device program
    (``pmap`` or ``shard_map`` over several GPUs, as brax's PPO builds) that carries a zero-size array, whether in
    the loop's state or among the arrays its body closes over. The environments therefore carry their
    ``pipeline_state``, and the model arrays of their substep loop, this way (docs/envs.md, "Multi-device").
    :func:`fill_empty` restores the arrays."""
    return jax.tree.map(lambda x: None if np.size(x) == 0 else x, tree)


def fill_empty(tree, like):
    """The :func:`drop_empty` ``tree`` made whole again: each ``None`` leaf becomes a zero-size array shaped and
    typed as ``like``'s (the full tree, e.g. ``kamino.init_state(model)``; only its shapes and dtypes are read), with
    ``tree``'s leading axes (a trajectory's time axis, a batch axis) in front. Inside a loop body the zeros are
    built there, not closed over."""

    def is_none(v) -> bool:
        return v is None

    pairs = zip(jax.tree.leaves(like), jax.tree.leaves(tree, is_leaf=is_none), strict=True)
    lead = next((np.shape(x)[:np.ndim(x) - np.ndim(t)] for t, x in pairs if x is not None), ())
    return jax.tree.map(lambda t, x: jnp.zeros((*lead, *np.shape(t)), t.dtype) if x is None else x, like, tree,
                        is_leaf=is_none)


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Control:
    """Inputs of one step. ``None`` fields mean zero.

    Attributes:
        dof_effort: ``[total_dofs]`` generalized joint efforts (N for translational DoFs, N m for
            rotational ones; a FREE joint's six are a world-aligned force and torque at the child CoM).
            On PASSIVE DoFs it is applied as is, on EFFORT DoFs clipped to the effort limit, both
            explicitly as body wrenches ``J_dofs^T tau`` (docs/formulation.md §3.1); on POSITION/VELOCITY
            DoFs it is the actuator's feed-forward, inside the effort limit.
        body_wrench: ``[total_bodies, 6]`` external wrenches ``(f, tau)`` in world, torque about the CoM.
        position_target: ``[total_dofs]`` targets of POSITION DoFs (DoF space, docs/formulation.md §4.1).
        velocity_target: ``[total_dofs]`` velocity targets of POSITION and VELOCITY DoFs.
    """

    dof_effort: jax.Array | None = None
    body_wrench: jax.Array | None = None
    position_target: jax.Array | None = None
    velocity_target: jax.Array | None = None

    @staticmethod
    def from_ctrl(model: Model, ctrl) -> Control:
        """A MuJoCo-style control vector -> :class:`Control`.

        ``ctrl`` has one entry per actuator (``[..., model.num_actuators]``, flat over worlds, in
        ``model.actuator_names`` order; leading axes, e.g. time, are kept). Each entry is clipped to the
        actuator's ``ctrl_range`` and lands on its DoF: EFFORT -> ``dof_effort = gear * ctrl``,
        POSITION -> ``position_target = ctrl``, VELOCITY -> ``velocity_target = ctrl``.
        """
        ctrl = jnp.asarray(ctrl)
        if ctrl.shape[-1:] != (model.num_actuators,):
            raise ValueError(f"ctrl has shape {ctrl.shape}, expected (..., {model.num_actuators}) "
                             f"(one entry per actuator: {list(model.actuator_names[:8])}...)")
        if not jnp.issubdtype(ctrl.dtype, jnp.floating):
            ctrl = ctrl.astype(jnp.zeros(0).dtype)
        c = jnp.clip(ctrl, model.actuator_ctrl_range[:, 0], model.actuator_ctrl_range[:, 1])
        mode = model.dof_act_mode[model.actuator_dof]
        zeros = jnp.zeros((*ctrl.shape[:-1], model.num_dofs), c.dtype)

        def scatter(selected, values):
            sel = np.nonzero(selected)[0]
            return zeros.at[..., model.actuator_dof[sel]].set(values[..., sel])

        return Control(
            dof_effort=scatter(mode == ActuationMode.EFFORT, c * model.actuator_gear),
            position_target=scatter(mode == ActuationMode.POSITION, c),
            velocity_target=scatter(mode == ActuationMode.VELOCITY, c),
        )
