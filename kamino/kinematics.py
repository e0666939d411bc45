"""Loop-closing forward kinematics for resets: ``forward_kinematics``, ``set_joint_positions`` and ``init_state``
(a model's initial state, at given coordinates), and loop-aware ``inverse_kinematics`` to task-space targets
(docs/formulation.md §9).

Given joint coordinates — all of them, or only the actuated ones — find body poses that satisfy
every joint, loop-closure and coupling constraint, for all worlds at once. The solver
(``kamino/jax_ref/fk.py``) is a damped Gauss-Newton with line search on the body poses; a world that
does not converge is flagged in ``FKResult.converged`` and keeps its best (finite) iterate.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from kamino.checks import check_state_dtype
from kamino.jax_ref.backend import padded_poses
from kamino.jax_ref.fk import FKSettings, FKTables, IKSettings, IKTargets, ik_batch, solve_batch
from kamino.jax_ref.types import _pad_index, layout_of, to_flat, to_padded
from kamino.model import (
    JOINT_CONSTRAINT_ROWS,
    RES_LOG,
    RES_TRANS,
    ActuationMode,
    JointType,
    Model,
    derived,
    fingerprint,
)
from kamino.spatial import quat_conj, quat_exp, quat_mul, rotate
from kamino.state import ContactState, State, StepInfo, bind


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class FKResult:
    """Result of :func:`forward_kinematics`."""

    body_q: jax.Array
    """``[total_bodies, 7]`` CoM poses (flat, like ``State.body_q``)."""
    converged: jax.Array
    """``[num_worlds]`` bool: ``residual <= tolerance`` and every target within its joint limits
    (:attr:`within_limits`): a target beyond a limit is unreachable, whatever the residual."""
    residual: jax.Array
    """``[num_worlds]`` max |constraint residual| (m or rad) at the returned poses."""
    iterations: jax.Array
    """``[num_worlds]`` Gauss-Newton iterations used."""
    within_limits: jax.Array
    """``[num_worlds]`` bool: every given target coordinate of a limited DoF (an actuated position, or a scalar
    joint coordinate of ``joint_positions``) lies within ``[model.dof_lower, model.dof_upper]`` (to
    ``tolerance``). ``False``: the target is unreachable and :attr:`converged` is ``False``."""


_FIXED_ROWS = ((0, RES_TRANS), (1, RES_TRANS), (2, RES_TRANS), (3, RES_LOG), (4, RES_LOG), (5, RES_LOG))


def actuated_joints(model: Model) -> np.ndarray:
    """``[num_joints]`` bool: joints whose DoFs have an actuator (kamino.Actuation other than passive)."""
    active = model.dof_act_mode != int(ActuationMode.PASSIVE)
    owner = np.repeat(np.arange(model.num_joints), model.joint_dof_count)
    out = np.zeros(model.num_joints, bool)
    out[owner[active]] = True
    return out


def base_bodies(model: Model) -> np.ndarray:
    """``[num_worlds]`` global index of each world's floating base — the child of its first FREE joint
    from the world — or ``-1`` (fixed-base world)."""
    out = np.full(model.num_worlds, -1, np.int64)
    free = np.nonzero((model.joint_type == int(JointType.FREE)) & (model.joint_parent < 0))[0]
    for j in free[::-1]:
        out[model.joint_world[j]] = model.joint_child[j]
    return out


def _tables(model: Model, mode: str, use_base: bool) -> tuple[FKTables, np.ndarray, np.ndarray]:
    """Host-built FK row tables (kept on the model: :func:`kamino.model.derived`), the joint gather table and its
    mask. Built under ``jax.ensure_compile_time_eval()`` (as ``layout_of``): a first call from inside ``jax.jit``
    would otherwise keep tracers of that trace for every later call (``UnexpectedTracerError``)."""
    def build():
        with jax.ensure_compile_time_eval():
            return _build_tables(model, mode, use_base)

    return derived(model, ("fk_tables", mode, use_base), build)


def _build_tables(model: Model, mode: str, use_base: bool) -> tuple[FKTables, np.ndarray, np.ndarray]:
    W = model.num_worlds
    nj = int(model.world_joint_count.max()) if model.num_joints else 0
    jg, jmask, _ = _pad_index(model.world_joint_start, model.world_joint_count, nj)
    targeted = {"all": lambda: np.ones(model.num_joints, bool), "actuated": lambda: actuated_joints(model),
                "none": lambda: np.zeros(model.num_joints, bool)}[mode]()
    rows: list[list[tuple[int, int, int]]] = [[] for _ in range(W)]
    for j in range(model.num_joints):
        w = int(model.joint_world[j])
        local = j - int(model.world_joint_start[w])
        spec = _FIXED_ROWS if targeted[j] else JOINT_CONSTRAINT_ROWS[JointType(int(model.joint_type[j]))]
        rows[w].extend((local, axis, kind) for axis, kind in spec)
    nr = max((len(r) for r in rows), default=0)
    table = np.zeros((3, W, nr), np.int64)
    mask = np.zeros((W, nr), bool)
    for w, r in enumerate(rows):
        if r:
            table[:, w, :len(r)] = np.asarray(r).T
            mask[w, :len(r)] = True
    base = base_bodies(model)
    base_local = np.where(base >= 0, base - model.world_body_start, -1) if use_base else np.full(W, -1)
    tab = FKTables(
        row_joint=jnp.asarray(table[0], jnp.int32), row_axis=jnp.asarray(table[1], jnp.int32),
        row_kind=jnp.asarray(table[2], jnp.int32), row_mask=jnp.asarray(mask),
        targeted=jnp.asarray(np.where(jmask, targeted[jg] if model.num_joints else False, False)),
        base_body=jnp.asarray(base_local, jnp.int32),
    )
    return tab, jg, jmask


def _coords_from_dofs(model: Model, dof_pos: jax.Array) -> jax.Array:
    """Packed coordinates ``[num_joints, 7]`` from DoF positions (rotation vectors -> quaternions)."""
    counts = model.joint_dof_count
    joint = np.repeat(np.arange(model.num_joints), counts)
    slot = np.arange(int(counts.sum())) - np.repeat(model.joint_dof_start, counts)
    out = jnp.zeros((model.num_joints, 7), dof_pos.dtype).at[joint, slot].set(dof_pos)
    for jt, k in ((JointType.SPHERICAL, 0), (JointType.FREE, 3)):  # DoFs k..k+2 are a rotation vector
        sel = np.nonzero(model.joint_type == int(jt))[0]
        if sel.size:
            out = out.at[sel, k:k + 4].set(quat_exp(out[sel, k:k + 3]))
    return out


def _coords_from_flat(model: Model, coords: jax.Array) -> jax.Array:
    """Packed coordinates ``[num_joints, 7]`` from the flat ``[num_coords]`` vector (``kamino.joint_positions``)."""
    counts = model.joint_coord_count
    joint = np.repeat(np.arange(model.num_joints), counts)
    slot = np.arange(int(counts.sum())) - np.repeat(model.joint_coord_start, counts)
    out = jnp.zeros((model.num_joints, 7), coords.dtype).at[joint, slot].set(coords)
    # quaternion coordinates (SPHERICAL, FREE) are normalised
    for jt, k in ((JointType.SPHERICAL, 0), (JointType.FREE, 3)):
        sel = np.nonzero(model.joint_type == int(jt))[0]
        if sel.size:
            q = out[sel, k:k + 4]
            out = out.at[sel, k:k + 4].set(q / jnp.linalg.norm(q, axis=-1, keepdims=True))
    return out


def _concrete(x) -> np.ndarray | None:
    try:
        return np.asarray(x)
    except (TypeError, jax.errors.TracerArrayConversionError, jax.errors.ConcretizationTypeError):
        return None


def forward_kinematics(model: Model, joint_positions=None, actuated_positions=None, base_pose=None, *,
                       initial_body_q=None, tolerance: float = 1e-6, max_iterations: int = 30,
                       dtype=None) -> FKResult:
    """Body poses consistent with every joint, loop closure and coupling, for all worlds at once.

    Give either ``joint_positions`` — all joint coordinates, flat ``[num_coords]`` in the layout of
    :func:`kamino.joint_positions` — or ``actuated_positions`` — one DoF position per actuator,
    ``[num_actuators]`` in ``model.actuator_names`` order (angle [rad] or translation [m]; a
    rotation-vector component for SPHERICAL/FREE DoFs); unactuated joints are then solved for.
    With neither, the actuated joints are held at their reference (zero) coordinates.
    ``base_pose`` (``[7]`` or ``[num_worlds, 7]``, CoM pose of each world's floating base: the child
    of its FREE joint from the world) places floating robots; without it the base stays where the
    initial guess has it. ``initial_body_q`` (default: the model's reference pose ``body_q0``, moved
    rigidly to ``base_pose``) is where the Gauss-Newton iteration starts.

    Solves ``max |C| <= tolerance`` by damped Gauss-Newton with an Armijo line search, at most
    ``max_iterations`` plus one per sub-target of 10 deg / 5 cm (docs/formulation.md §9). A target coordinate
    beyond its DoF's limits is unreachable: ``within_limits`` and ``converged`` are ``False`` for its world, even
    though the poses may satisfy every joint. Works under
    ``jax.jit`` for the coordinate arguments. ``dtype`` defaults to JAX's default float.

    Called outside a trace, the whole solve runs as one program compiled once per model and argument pattern
    (measured on one core of the 2-core CPU, fresh models, no compilation cache: a four-bar's first call 16.1 s
    op by op, 12.7 s compiled whole).
    """
    args = (joint_positions, actuated_positions, base_pose, initial_body_q)
    if any(isinstance(x, jax.core.Tracer) for x in jax.tree.leaves(args)):
        return _forward_kinematics(model, *args, tolerance=tolerance, max_iterations=max_iterations, dtype=dtype)
    for name, value in zip(("joint_positions", "actuated_positions", "base_pose"), args, strict=False):
        if value is not None and not np.all(np.isfinite(np.asarray(value, float))):
            raise ValueError(f"forward_kinematics: {name} contains NaN or inf")
    dtype = jnp.zeros(0).dtype if dtype is None else jnp.dtype(dtype)
    key = ("fk_program", tuple(x is None for x in args), float(tolerance), int(max_iterations), str(dtype))
    program = derived(model, key, lambda: jax.jit(lambda *a: _forward_kinematics(
        model, *a, tolerance=tolerance, max_iterations=max_iterations, dtype=dtype)))
    return program(*(None if x is None else jnp.asarray(x) for x in args))


def _forward_kinematics(model: Model, joint_positions, actuated_positions, base_pose, initial_body_q, *,
                        tolerance: float, max_iterations: int, dtype) -> FKResult:
    """:func:`forward_kinematics` as traced operations (its docstring)."""
    if joint_positions is not None and actuated_positions is not None:
        raise ValueError("forward_kinematics: give joint_positions or actuated_positions, not both")
    if joint_positions is not None and base_pose is not None:
        raise ValueError("forward_kinematics: with joint_positions the base pose is the FREE joint's coordinates; "
                         "do not also give base_pose")
    dtype = jnp.zeros(0).dtype if dtype is None else jnp.dtype(dtype)
    mode = "all" if joint_positions is not None else "actuated"
    base = base_bodies(model)
    if base_pose is not None and np.any(base < 0):
        worlds = np.nonzero(base < 0)[0][:8].tolist()
        raise ValueError(f"forward_kinematics: base_pose given but worlds {worlds} have no floating base "
                         "(a FREE joint from the world)")
    tab, jg, jmask = _tables(model, mode, base_pose is not None)
    lay = layout_of(model, dtype)
    pm, t = lay.padded, lay.tables

    if mode == "all":
        jp = jnp.asarray(joint_positions, dtype)
        if jp.shape != (model.num_coords,):
            raise ValueError(f"joint_positions has shape {jp.shape}, expected ({model.num_coords},) "
                             "(the layout of kamino.joint_positions)")
        coords = _coords_from_flat(model, jp)
    else:
        ap = jnp.zeros(model.num_actuators, dtype) if actuated_positions is None else jnp.asarray(actuated_positions,
                                                                                                    dtype)
        if ap.shape != (model.num_actuators,):
            raise ValueError(f"actuated_positions has shape {ap.shape}, expected ({model.num_actuators},) "
                             f"(one per actuator: {list(model.actuator_names[:6])}...)")
        coords = _coords_from_dofs(model, jnp.zeros(model.num_dofs, dtype).at[model.actuator_dof].set(ap))
    for name, value in (("joint_positions", joint_positions), ("actuated_positions", actuated_positions),
                        ("base_pose", base_pose)):
        arr = None if value is None else _concrete(value)
        if arr is not None and not np.all(np.isfinite(arr)):
            raise ValueError(f"forward_kinematics: {name} contains NaN or inf")
    coords_p = to_padded(coords, jg, jmask, 0.0)

    q0 = jnp.asarray(model.body_q0 if initial_body_q is None else initial_body_q, dtype)
    if q0.shape != (model.num_bodies, 7):
        raise ValueError(f"initial_body_q has shape {q0.shape}, expected ({model.num_bodies}, 7)")
    if base_pose is None:
        base_target = jnp.tile(jnp.asarray([0, 0, 0, 0, 0, 0, 1.0], dtype), (model.num_worlds, 1))
    else:
        base_target = jnp.broadcast_to(jnp.asarray(base_pose, dtype), (model.num_worlds, 7))
        base_target = base_target.at[:, 3:].set(base_target[:, 3:] / jnp.linalg.norm(base_target[:, 3:], axis=-1,
                                                                                       keepdims=True))
        if initial_body_q is None:
            q0 = _move_rigidly(model, q0, base, base_target)

    q_pad = padded_poses(pm, t, q0)
    settings = FKSettings(tolerance=float(tolerance), max_iterations=int(max_iterations))
    q, converged, residual, iterations = solve_batch(pm, tab, q_pad, coords_p, base_target, settings)
    inside = _targets_within_limits(model, jp if mode == "all" else ap, mode, float(tolerance))
    return FKResult(body_q=to_flat(q, t["bs"]), converged=converged & inside, residual=residual,
                    iterations=iterations.astype(jnp.int32), within_limits=inside)


def _target_dofs(model: Model, mode: str) -> tuple[np.ndarray, np.ndarray]:
    """``(index into the target vector, DoF)`` of each target entry that is a limited DoF's position: every
    actuator (``mode="actuated"``), or each coordinate of a joint whose coordinates are its DoF positions
    (REVOLUTE, PRISMATIC, CYLINDRICAL, UNIVERSAL, CARTESIAN; ``mode="all"``)."""
    if mode == "actuated":
        entry, dof = np.arange(model.num_actuators), np.asarray(model.actuator_dof, np.int64)
    else:
        scalar = (model.joint_coord_count == model.joint_dof_count) & (model.joint_type != int(JointType.FIXED))
        joints = np.nonzero(scalar)[0]
        counts = model.joint_dof_count[joints]
        offset = np.arange(int(counts.sum())) - np.repeat(_starts(counts), counts)
        entry = np.repeat(model.joint_coord_start[joints], counts) + offset
        dof = np.repeat(model.joint_dof_start[joints], counts) + offset
    limited = np.isfinite(model.dof_lower[dof]) | np.isfinite(model.dof_upper[dof])
    return entry[limited], dof[limited]


def _starts(counts: np.ndarray) -> np.ndarray:
    return np.cumsum(counts) - counts


def _targets_within_limits(model: Model, targets: jax.Array, mode: str, tolerance: float) -> jax.Array:
    """``[num_worlds]`` bool: each world's limited targets lie within their DoF limits
    (:attr:`FKResult.within_limits`)."""
    entry, dof = _target_dofs(model, mode)
    inside = jnp.ones(model.num_worlds, bool)
    if entry.size == 0:
        return inside
    x = targets[entry]
    ok = (x >= model.dof_lower[dof] - tolerance) & (x <= model.dof_upper[dof] + tolerance)
    dof_world = np.repeat(np.arange(model.num_worlds), model.world_dof_count)
    return inside.at[dof_world[dof]].min(ok)


def _move_rigidly(model: Model, q0: jax.Array, base: np.ndarray, target: jax.Array) -> jax.Array:
    """Move every body of each world by the rigid transform taking its base body to ``target``."""

    world = model.body_world
    b = base[world]
    qb = q0[b]
    rel = quat_mul(target[world, 3:], quat_conj(qb[:, 3:]))
    pos = target[world, :3] + rotate(rel, q0[:, :3] - qb[:, :3])
    rot = quat_mul(rel, q0[:, 3:])
    return jnp.concatenate([pos, rot / jnp.linalg.norm(rot, axis=-1, keepdims=True)], axis=-1)


def init_state(model: Model, dtype=None, *, keyframe: str | int | None = None, joint_positions=None,
               actuated_positions=None, base_pose=None, **fk_options) -> State:
    """The model's initial state: zero twists (the builder's, if set), reactions and contacts. It carries the model's
    fingerprint (``State.model_fingerprint``), so stepping it with another mechanism raises.

    Without coordinates the bodies are at the builder's (reference) poses. With ``joint_positions``,
    ``actuated_positions`` and/or ``base_pose`` the poses come from :func:`kamino.forward_kinematics`
    (consistent with every joint and loop closure; ``fk_options`` are passed on), which raises a
    ``ValueError`` naming the worlds that do not converge. ``keyframe`` (a name or an index of
    ``model.keyframes``, e.g. an MJCF file's ``<key name="home">``) starts every world at that key's poses,
    twists and time; an unknown key raises a ``ValueError`` listing the known ones. ``dtype`` defaults to JAX's
    default float (float32, or float64 with ``jax_enable_x64``); a state is float32 or float64 (another dtype
    raises a ``ValueError``).
    """
    dtype = jnp.zeros(0).dtype if dtype is None else check_state_dtype(dtype, "init_state")
    body_q = jnp.asarray(model.body_q0, dtype)
    body_u = jnp.asarray(model.body_u0, dtype)
    time = jnp.zeros(model.num_worlds, dtype)
    if keyframe is not None:
        if joint_positions is not None or actuated_positions is not None or base_pose is not None:
            raise ValueError("init_state: give keyframe or coordinates (joint_positions, actuated_positions, "
                             "base_pose), not both")
        key = model.keyframe(keyframe)
        if key.body_q.shape[0] * model.num_worlds != model.num_bodies:
            raise ValueError(f"init_state: keyframe {key.name!r} holds {key.body_q.shape[0]} bodies, but the model's "
                             f"{model.num_worlds} worlds are not copies of that many")
        body_q = jnp.asarray(np.tile(key.body_q, (model.num_worlds, 1)), dtype)
        body_u = jnp.asarray(np.tile(key.body_u, (model.num_worlds, 1)), dtype)
        time = jnp.full(model.num_worlds, key.time, dtype)
    if joint_positions is not None or actuated_positions is not None or base_pose is not None:
        fk = forward_kinematics(model, joint_positions, actuated_positions, base_pose, dtype=dtype, **fk_options)
        beyond = np.nonzero(~np.asarray(fk.within_limits))[0]
        if beyond.size:
            raise ValueError(f"init_state: the target coordinates of worlds {beyond[:8].tolist()} lie beyond the "
                             "joint limits (model.dof_lower, model.dof_upper): unreachable")
        bad = np.nonzero(~np.asarray(fk.converged))[0]
        if bad.size:
            raise ValueError(f"init_state: forward kinematics did not converge in worlds {bad[:8].tolist()} "
                             f"(residual {np.asarray(fk.residual)[bad[:8]].tolist()}); the coordinates may be "
                             "unreachable")
        body_q, body_u = fk.body_q, jnp.zeros_like(body_u)
    return bind(State(
        body_q=body_q,
        body_u=body_u,
        time=time,
        constraint_force=jnp.zeros(model.num_constraints, dtype),
        actuator_force=jnp.zeros(model.num_dofs, dtype),
        passive_force=jnp.zeros(model.num_dofs, dtype),
        limit_force=jnp.zeros(model.num_dofs, dtype),
        coupling_force=jnp.zeros(model.num_couplings, dtype),
        contacts=ContactState.empty(model.num_contacts, dtype),
        info=StepInfo.empty(model.num_worlds, dtype),
    ), fingerprint(model))


def set_joint_positions(model: Model, state: State, joint_positions=None, actuated_positions=None,
                        base_pose=None, **options) -> State:
    """``state`` reset to the poses that :func:`forward_kinematics` finds from the given coordinates,
    starting from ``state.body_q``; twists, reactions and contacts are zeroed, time is kept. Worlds
    that do not converge keep the best iterate; call :func:`forward_kinematics` for the flags."""

    fk = forward_kinematics(model, joint_positions, actuated_positions, base_pose,
                            initial_body_q=state.body_q, dtype=state.body_q.dtype, **options)
    fresh = init_state(model, dtype=state.body_q.dtype)
    return fresh.replace(body_q=fk.body_q, time=state.time)


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class IKResult:
    """Result of :func:`inverse_kinematics`."""

    body_q: jax.Array
    """``[total_bodies, 7]`` CoM poses (flat, like ``State.body_q``)."""
    converged: jax.Array
    """``[num_worlds]`` bool: closure, joint limits and every target hold to ``tolerance``."""
    target_error: jax.Array
    """``[num_worlds]`` the largest target error: ``|p - p*|`` [m] of a position target or the rotation angle
    ``|Log(q q*^-1)|`` [rad] of an orientation target (rows of weight zero are not targets)."""
    position_error: jax.Array
    """``[num_worlds]`` max ``|p - p*|`` [m] over the position targets."""
    orientation_error: jax.Array
    """``[num_worlds]`` max rotation angle [rad] over the orientation targets."""
    closure_error: jax.Array
    """``[num_worlds]`` max |residual| (m or rad) of every joint, loop-closure and coupling row (and of the pinned
    base pose), as :attr:`FKResult.residual`."""
    within_limits: jax.Array
    """``[num_worlds]`` bool: every DoF lies within ``[model.dof_lower, model.dof_upper]`` to ``tolerance``."""
    iterations: jax.Array
    """``[num_worlds]`` Gauss-Newton iterations used."""


def _per_world(x, shape: tuple[int, ...], num_worlds: int, name: str, dtype) -> jax.Array:
    """``x`` (``shape`` or ``[num_worlds, *shape]``) broadcast to ``[num_worlds, *shape]``."""
    x = jnp.asarray(x, dtype)
    if x.shape == shape:
        return jnp.broadcast_to(x, (num_worlds, *shape))
    if x.shape != (num_worlds, *shape):
        raise ValueError(f"inverse_kinematics: {name} has shape {x.shape}, expected {shape} or "
                         f"({num_worlds}, {', '.join(map(str, shape))})")
    return x


def _body_locals(model: Model, bodies) -> np.ndarray:
    """``[num_worlds, k]`` world-local index of each named (or world-local integer) body in every world."""
    out = np.zeros((model.num_worlds, len(bodies)), np.int64)
    for w in range(model.num_worlds):
        start, count = int(model.world_body_start[w]), int(model.world_body_count[w])
        for i, b in enumerate(bodies):
            local = model.body_index(b, w) - start if isinstance(b, str) else int(b)
            if not 0 <= local < count:
                raise ValueError(f"inverse_kinematics: body {b!r} is not in world {w} ({count} bodies)")
            out[w, i] = local
    return out


def inverse_kinematics(model: Model, bodies, positions=None, orientations=None, *, offsets=None,
                       position_weights=None, orientation_weights=None, base_pose=None, reference_body_q=None,
                       regularization: float = 0.0, initial_body_q=None, tolerance: float = 1e-6,
                       max_iterations: int = 100, dtype=None) -> IKResult:
    """Body poses that put points and orientations of bodies at task-space targets while every joint, loop closure,
    coupling and joint limit holds, for all worlds at once (docs/formulation.md §9 "Inverse kinematics").

    ``bodies``: ``k`` body names (or world-local body indices), the same in every world. ``positions``
    (``[k, 3]`` or ``[num_worlds, k, 3]``, world frame) are targets for the points ``offsets`` (``[k, 3]`` or
    ``[num_worlds, k, 3]``, in each body's CoM frame, the frame of ``State.body_q``; default the CoM, e.g. a foot's
    contact point); ``orientations`` (``[k, 4]`` or ``[num_worlds, k, 4]``, ``x, y, z, w``) are targets for the
    bodies' orientations (``body_q[:, 3:]``). Either may be ``None`` (no such targets). ``position_weights`` /
    ``orientation_weights`` (``[k]`` or ``[num_worlds, k]``, default 1) weigh the target rows; a zero weight drops a
    row, so a subset of bodies may have positions only, orientations only, or both.

    A floating base (the child of each world's FREE joint from the world) is free unless ``base_pose`` (``[7]`` or
    ``[num_worlds, 7]``) pins it. ``regularization`` weighs ``1/2 |q - q_ref|^2`` (per body, position and rotation
    vector) toward ``reference_body_q`` (default: the initial guess); a positive weight biases a reachable target by
    about ``regularization |q - q_ref|`` relative to the target rows' scale. Without it (the default) directions the
    targets leave free (a free base, positions only) stay near the iterate through the step's damping.
    ``initial_body_q`` (default the model's reference poses ``body_q0``, moved rigidly to ``base_pose``) starts the
    iteration.

    Solves ``min 1/2 |W (x(q) - x*)|^2 + lambda/2 |q - q_ref|^2`` subject to the joint, loop and coupling rows
    ``C(q) = 0`` of :func:`forward_kinematics` and ``lower <= q_dof <= upper``, by Gauss-Newton SQP with an active set
    of joint limits and an Armijo line search (:func:`kamino.jax_ref.fk.ik_world`); at most ``max_iterations``.
    A target that cannot be reached leaves ``converged`` ``False`` with the closest configuration the iteration finds
    (closure and limits still held) and its :attr:`IKResult.target_error`. Works under ``jax.jit`` and ``jax.vmap``
    for the array arguments; ``dtype`` defaults to JAX's default float.
    """
    bodies = tuple(bodies)
    args = (positions, orientations, offsets, position_weights, orientation_weights, base_pose, reference_body_q,
            initial_body_q)
    kw = dict(bodies=bodies, regularization=float(regularization), tolerance=float(tolerance),
              max_iterations=int(max_iterations))
    if any(isinstance(x, jax.core.Tracer) for x in jax.tree.leaves(args)):
        return _inverse_kinematics(model, *args, dtype=dtype, **kw)
    for name, value in zip(("positions", "orientations", "offsets", "base_pose"), args[:3] + args[5:6], strict=True):
        if value is not None and not np.all(np.isfinite(np.asarray(value, float))):
            raise ValueError(f"inverse_kinematics: {name} contains NaN or inf")
    dtype = jnp.zeros(0).dtype if dtype is None else jnp.dtype(dtype)
    key = ("ik_program", tuple(x is None for x in args), tuple(kw.items()), str(dtype))
    program = derived(model, key, lambda: jax.jit(lambda *a: _inverse_kinematics(model, *a, dtype=dtype, **kw)))
    return program(*(None if x is None else jnp.asarray(x) for x in args))


def _inverse_kinematics(model: Model, positions, orientations, offsets, position_weights, orientation_weights,
                        base_pose, reference_body_q, initial_body_q, *, bodies, regularization, tolerance,
                        max_iterations, dtype) -> IKResult:
    """:func:`inverse_kinematics` as traced operations (its docstring)."""
    dtype = jnp.zeros(0).dtype if dtype is None else jnp.dtype(dtype)
    W, k = model.num_worlds, len(bodies)
    if positions is None and orientations is None:
        raise ValueError("inverse_kinematics: give positions and/or orientations")
    base = base_bodies(model)
    if base_pose is not None and np.any(base < 0):
        worlds = np.nonzero(base < 0)[0][:8].tolist()
        raise ValueError(f"inverse_kinematics: base_pose given but worlds {worlds} have no floating base "
                         "(a FREE joint from the world)")
    local = _body_locals(model, bodies)
    ones = jnp.ones((W, k), dtype)
    pw = ones if position_weights is None else _per_world(position_weights, (k,), W, "position_weights", dtype)
    ow = ones if orientation_weights is None else _per_world(orientation_weights, (k,), W, "orientation_weights",
                                                              dtype)
    if positions is None:
        pos, pw = jnp.zeros((W, k, 3), dtype), jnp.zeros_like(pw)
    else:
        pos = _per_world(positions, (k, 3), W, "positions", dtype)
    if orientations is None:
        rot, ow = jnp.tile(jnp.asarray([0, 0, 0, 1.0], dtype), (W, k, 1)), jnp.zeros_like(ow)
    else:
        rot = _per_world(orientations, (k, 4), W, "orientations", dtype)
        rot = rot / jnp.linalg.norm(rot, axis=-1, keepdims=True)
    off = jnp.zeros((W, k, 3), dtype) if offsets is None else _per_world(offsets, (k, 3), W, "offsets", dtype)
    targets = IKTargets(body=jnp.asarray(local, jnp.int32), offset=off, position=pos, orientation=rot,
                        position_weight=pw, orientation_weight=ow)

    tab, _, _ = _tables(model, "none", base_pose is not None)
    lay = layout_of(model, dtype)
    pm, t = lay.padded, lay.tables
    q0 = jnp.asarray(model.body_q0 if initial_body_q is None else initial_body_q, dtype)
    if q0.shape != (model.num_bodies, 7):
        raise ValueError(f"initial_body_q has shape {q0.shape}, expected ({model.num_bodies}, 7)")
    if base_pose is None:
        base_target = jnp.tile(jnp.asarray([0, 0, 0, 0, 0, 0, 1.0], dtype), (W, 1))
    else:
        base_target = jnp.broadcast_to(jnp.asarray(base_pose, dtype), (W, 7))
        base_target = base_target.at[:, 3:].set(base_target[:, 3:] / jnp.linalg.norm(base_target[:, 3:], axis=-1,
                                                                                       keepdims=True))
        if initial_body_q is None:
            q0 = _move_rigidly(model, q0, base, base_target)
    q_ref = q0 if reference_body_q is None else jnp.asarray(reference_body_q, dtype)
    if q_ref.shape != (model.num_bodies, 7):
        raise ValueError(f"reference_body_q has shape {q_ref.shape}, expected ({model.num_bodies}, 7)")
    settings = IKSettings(tolerance=tolerance, max_iterations=max_iterations, regularization=regularization)
    q, closure, ep, er, inside, it = ik_batch(pm, tab, padded_poses(pm, t, q0), padded_poses(pm, t, q_ref), targets,
                                              base_target, settings)
    err = jnp.maximum(ep, er)
    ok = (closure <= tolerance) & (err <= tolerance) & inside
    return IKResult(body_q=to_flat(q, t["bs"]), converged=ok, target_error=err, position_error=ep,
                    orientation_error=er, closure_error=closure, within_limits=inside,
                    iterations=it.astype(jnp.int32))
