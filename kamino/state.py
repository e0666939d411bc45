"""State, Control and StepInfo: JAX pytrees shared by both backends (docs/conventions.md)."""

from __future__ import annotations

import copy
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
    """PADMM iterations the step's solve took (int32; 0 for a failed world)."""
    primal_residual: jax.Array
    """The solve's final primal residual, as a velocity [m/s or rad/s] of the world's heaviest constrained direction
    (``SolverConfig.tolerance``; docs/conventions.md, "PADMM defaults")."""
    dual_residual: jax.Array
    """The solve's final dual residual, in the units of :attr:`primal_residual`."""
    complementarity_residual: jax.Array
    """The solve's final complementarity residual ``|lambda v|`` of the limit and contact rows."""
    converged: jax.Array
    """Whether the solve met ``SolverConfig.tolerance`` within ``max_iterations`` (bool)."""
    failed: jax.Array
    """Whether the world is failed and frozen (bool): its new state was non-finite, or it went unconverged for more
    than ``SolverConfig.max_unconverged_steps`` steps (docs/conventions.md, "World health")."""
    num_contacts: jax.Array
    """Active contacts the step found (int32; at most the world's contact capacity)."""
    contact_overflow: jax.Array
    """Contacts dropped because the world's contact capacity was full (int32; 0 unless
    ``ModelBuilder.finalize(contact_capacity=...)`` lowered it)."""
    penalty: jax.Array
    """The adaptive PADMM penalty of the limit and contact rows at the end of the step, the next step's start
    (``SolverConfig.penalty``)."""
    unconverged_steps: jax.Array
    """Consecutive steps whose solve did not converge (int32; a converged step resets it)."""

    @staticmethod
    def empty(num_worlds: int, dtype=jnp.float32) -> StepInfo:
        """The report of a state no step has made: zero iterations and residuals, converged, not failed."""
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
    """

    pair: jax.Array
    """world-local index of the geom pair (``-1``: empty slot)."""
    pos: jax.Array
    """world point midway between the two surfaces."""
    normal: jax.Array
    """unit normal from geom a to geom b."""
    dist: jax.Array
    """signed gap [m] (negative: penetration)."""
    force: jax.Array
    """contact force on geom b's body [N], world frame (``C lambda / dt``)."""
    velocity: jax.Array
    """relative velocity of b with respect to a at the contact after the step, world frame."""
    point_b: jax.Array
    """the contact point on geom b in its body's CoM frame (the warm-start key)."""

    @staticmethod
    def empty(capacity: int, dtype=jnp.float32) -> ContactState:
        """``capacity`` empty contact slots (``pair = -1``, zeros elsewhere)."""
        v = jnp.zeros((capacity, 3), dtype)
        return ContactState(pair=jnp.full(capacity, -1, jnp.int32), pos=v, normal=v, dist=jnp.zeros(capacity, dtype),
                            force=v, velocity=v, point_b=v)


@dataclasses.dataclass(frozen=True)
class State:
    """Simulation state of all worlds (flat storage, world 0's entities first).

    A state made by :func:`kamino.init_state` also carries its model's :attr:`model_fingerprint`, which every step
    keeps."""

    body_q: jax.Array
    """``[total_bodies, 7]`` CoM poses ``(px, py, pz, qx, qy, qz, qw)`` in world."""
    body_u: jax.Array
    """``[total_bodies, 6]`` twists ``(v, w)``: CoM linear then angular velocity, world frame."""
    time: jax.Array
    """``[num_worlds]`` simulated time [s]."""
    constraint_force: jax.Array
    """``[total_constraint_rows]`` last step's joint-row reactions ``lambda/dt`` (the warm start of the next solve),
    in the row order of docs/conventions.md."""
    actuator_force: jax.Array
    """``[total_dofs]`` generalized force each DoF's actuator applied in the last step (implicit PD/D force, or the
    clipped commanded effort; for passive DoFs the applied effort)."""
    passive_force: jax.Array
    """``[total_dofs]`` generalized force of armature, damping and springs."""
    limit_force: jax.Array
    """``[total_dofs]`` generalized force of the joint limits (positive pushes the DoF up)."""
    coupling_force: jax.Array
    """``[total_couplings]`` reaction of each joint coupling (generalized force on joint a's DoF, ``lambda / dt``)."""
    contacts: ContactState
    """the last step's :class:`ContactState`."""
    info: StepInfo
    """the last solve's :class:`StepInfo`."""

    def replace(self, **changes) -> State:
        """A copy with the fields named in ``changes`` replaced (``state.replace(body_q=q)``); it keeps the
        :attr:`model_fingerprint`."""
        return bind(dataclasses.replace(self, **changes), self.model_fingerprint)

    @property
    def model_fingerprint(self) -> str | None:
        """The :func:`kamino.model.fingerprint` of the model the state belongs to, set by :func:`kamino.init_state`
        and kept by every step and by :meth:`replace` (``None``: not known, not checked). ``kamino.step`` /
        ``rollout``, ``Simulator.step`` and :func:`kamino.metrics` raise a ``ValueError`` for a state of another
        mechanism, even one with the same array shapes. It is static pytree data (no array, no leaf): free under
        ``jax.jit`` and ``vmap``; a trajectory or a batch of states carries it unchanged, and pickling keeps it.
        :func:`bind` sets it."""
        return self.__dict__.get(_FINGERPRINT)


#: the instance attribute of a :class:`State` that holds its model's fingerprint (not a dataclass field: code that
#: builds a state field by field, such as a backend, gets an unbound state)
_FINGERPRINT = "_model_fingerprint"
_STATE_FIELDS = tuple(f.name for f in dataclasses.fields(State))


def bind(state: State, model_fingerprint: str | None) -> State:
    """``state`` carrying ``model_fingerprint`` (``None``: unbound, as the backends' engines see a state)."""
    if state.model_fingerprint == model_fingerprint:
        return state
    out = copy.copy(state)
    if model_fingerprint is None:
        del out.__dict__[_FINGERPRINT]
    else:
        object.__setattr__(out, _FINGERPRINT, model_fingerprint)
    return out


def _flatten_with_keys(state: State):
    return tuple((jax.tree_util.GetAttrKey(n), getattr(state, n)) for n in _STATE_FIELDS), state.model_fingerprint


def _flatten(state: State):
    return tuple(getattr(state, n) for n in _STATE_FIELDS), state.model_fingerprint


def _unflatten(model_fingerprint: str | None, children) -> State:
    out = object.__new__(State)
    for name, value in zip(_STATE_FIELDS, children, strict=True):
        object.__setattr__(out, name, value)
    if model_fingerprint is not None:
        object.__setattr__(out, _FINGERPRINT, model_fingerprint)
    return out


jax.tree_util.register_pytree_with_keys(State, _flatten_with_keys, _unflatten, _flatten)


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

    if isinstance(like, State) and isinstance(tree, State):
        like = bind(like, tree.model_fingerprint)

    pairs = zip(jax.tree.leaves(like), jax.tree.leaves(tree, is_leaf=is_none), strict=True)
    lead = next((np.shape(x)[:np.ndim(x) - np.ndim(t)] for t, x in pairs if x is not None), ())
    return jax.tree.map(lambda t, x: jnp.zeros((*lead, *np.shape(t)), t.dtype) if x is None else x, like, tree,
                        is_leaf=is_none)


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Control:
    """Inputs of one step. ``None`` fields mean zero."""

    dof_effort: jax.Array | None = None
    """``[total_dofs]`` generalized joint efforts (N for translational DoFs, N m for rotational ones; a FREE joint's
    six are a world-aligned force and torque at the child CoM). On PASSIVE DoFs it is applied as is, on EFFORT DoFs
    clipped to the effort limit, both explicitly as body wrenches ``J_dofs^T tau`` (docs/formulation.md §3.1); on
    POSITION/VELOCITY DoFs it is the actuator's feed-forward, inside the effort limit."""
    body_wrench: jax.Array | None = None
    """``[total_bodies, 6]`` external wrenches ``(f, tau)`` in world, torque about the CoM."""
    position_target: jax.Array | None = None
    """``[total_dofs]`` targets of POSITION DoFs (DoF space, docs/formulation.md §4.1)."""
    velocity_target: jax.Array | None = None
    """``[total_dofs]`` velocity targets of POSITION and VELOCITY DoFs."""

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
