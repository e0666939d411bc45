"""The JAX reference behind ``kamino.Simulator(..., backend="jax")``: flat State <-> padded worlds, jitted."""

from __future__ import annotations

import dataclasses
import functools
import threading

import jax
import jax.numpy as jnp
import numpy as np

from kamino.config import SolverConfig
from kamino.jax_ref.couplings import coupling_residual
from kamino.jax_ref.dynamics import body_dynamics, kinetic_energy, potential_energy
from kamino.jax_ref.jacobians import (
    constraint_residual,
    dof_jacobian,
    dof_positions,
    joint_coordinates,
    joint_frames,
)
from kamino.jax_ref.pipeline import step_batch
from kamino.jax_ref.precision import full_precision
from kamino.jax_ref.rows import WorldControl
from kamino.jax_ref.types import (
    Layout,
    PaddedModel,
    WorldCache,
    _pad_index,
    build_layout,
    layout_of,
    to_flat,
    to_padded,
)
from kamino.model import RES_TRANS, Model
from kamino.state import ContactState, Control, State, StepInfo

_IDENTITY_POSE = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0)


def padded_poses(pm: PaddedModel, t: dict, body_q: jax.Array) -> jax.Array:
    """Flat poses -> padded ``[W, nb, 7]``, identity poses on padding."""
    q = to_padded(body_q, t["bg"], pm.body_mask, 0.0)
    return jnp.where(pm.body_mask[..., None], q, jnp.asarray(_IDENTITY_POSE, body_q.dtype))


def _padded_state(pm: PaddedModel, t: dict, state: State, control: Control | None):
    """Flat State/Control -> padded poses, twists, warm-start cache and controls per world."""
    dtype = state.body_q.dtype
    q = padded_poses(pm, t, state.body_q)
    u = to_padded(state.body_u, t["bg"], pm.body_mask, 0.0)
    dof = lambda x: to_padded(x, t["dg"], pm.dof_mask, 0.0)  # noqa: E731
    con = lambda x, fill=0.0: to_padded(x, t["cg"], t["cm"], fill)  # noqa: E731
    c = state.contacts
    cache = WorldCache(
        kin=to_padded(state.constraint_force, t["rg"], pm.row_mask, 0.0),
        coupling=to_padded(state.coupling_force, t["ug"], pm.cpl_mask, 0.0),
        actuator=dof(state.actuator_force),
        passive=dof(state.passive_force),
        limit=dof(state.limit_force),
        contact_pair=con(c.pair, -1),
        contact_pos=con(c.pos),
        contact_normal=con(c.normal),
        contact_dist=con(c.dist),
        contact_force=con(c.force),
        contact_velocity=con(c.velocity),
        contact_point_b=con(c.point_b),
        penalty=state.info.penalty,
    )

    def ctl(field, fill_shape, gather, mask):
        value = None if control is None else getattr(control, field)
        if value is None:
            return jnp.zeros(fill_shape, dtype)
        return to_padded(jnp.asarray(value, dtype), gather, mask, 0.0)

    ctrl = WorldControl(
        effort=ctl("dof_effort", pm.dof_mask.shape, t["dg"], pm.dof_mask),
        wrench=ctl("body_wrench", u.shape, t["bg"], pm.body_mask),
        position_target=ctl("position_target", pm.dof_mask.shape, t["dg"], pm.dof_mask),
        velocity_target=ctl("velocity_target", pm.dof_mask.shape, t["dg"], pm.dof_mask),
    )
    return q, u, cache, ctrl


@functools.partial(jax.jit, static_argnames=("cfg",))
def step_padded(pm: PaddedModel, t: dict, state: State, control: Control | None, cfg: SolverConfig) -> State:
    """One step of the padded model ``pm`` with the layout tables ``t`` (``layout_of(model, dtype)``): what
    :func:`step` runs. Public for callers whose model parameters are traced, such as the environments' domain
    randomization (``kamino.envs``: ``pm`` then carries per-environment masses, gains, friction)."""
    q, u, cache, ctrl = _padded_state(pm, t, state, control)
    frozen = state.info.failed
    q, u, cache, out, nonfinite = step_batch(pm, q, u, cache, ctrl, cfg, frozen)
    res = out.solve
    # world health (docs/conventions.md): a frozen world reports no solve and keeps its count; a world that
    # stays unconverged past cfg.max_unconverged_steps fails and is frozen from the next step on
    converged = res.converged & ~frozen
    prev = state.info.unconverged_steps
    unconverged = jnp.where(frozen | nonfinite, prev, jnp.where(converged, 0, prev + 1)).astype(jnp.int32)
    failed = frozen | nonfinite | (unconverged > cfg.max_unconverged_steps)
    zero = jnp.zeros_like(res.primal_residual)
    info = StepInfo(
        iterations=jnp.where(frozen, 0, res.iterations).astype(jnp.int32),
        primal_residual=jnp.where(frozen, zero, res.primal_residual),
        dual_residual=jnp.where(frozen, zero, res.dual_residual),
        complementarity_residual=jnp.where(frozen, zero, res.complementarity_residual),
        converged=converged,
        failed=failed,
        num_contacts=out.num_contacts.astype(jnp.int32),
        contact_overflow=out.contact_overflow.astype(jnp.int32),
        penalty=cache.penalty,
        unconverged_steps=unconverged,
    )
    dof = lambda x: to_flat(x, t["ds"])  # noqa: E731
    con = lambda x: to_flat(x, t["cs"])  # noqa: E731
    return State(
        body_q=to_flat(q, t["bs"]),
        body_u=to_flat(u, t["bs"]),
        time=state.time + jnp.where(frozen | nonfinite, 0.0, cfg.dt).astype(state.time.dtype),
        constraint_force=to_flat(cache.kin, t["rs"]),
        actuator_force=dof(cache.actuator),
        passive_force=dof(cache.passive),
        limit_force=dof(cache.limit),
        coupling_force=to_flat(cache.coupling, t["us"]),
        contacts=ContactState(
            pair=con(cache.contact_pair),
            pos=con(cache.contact_pos),
            normal=con(cache.contact_normal),
            dist=con(cache.contact_dist),
            force=con(cache.contact_force),
            velocity=con(cache.contact_velocity),
            point_b=con(cache.contact_point_b),
        ),
        info=info,
    )


@functools.partial(jax.jit, static_argnames=("cfg", "num_steps"))
def _rollout_jit(pm, t, state, controls, cfg, num_steps):
    def body(s, c):
        s2 = step_padded(pm, t, s, c, cfg)
        return s2, s2

    if controls is None:
        _, traj = jax.lax.scan(lambda s, _: body(s, None), state, None, length=num_steps)
    else:
        _, traj = jax.lax.scan(body, state, controls)
    return traj


class Engine:
    """The JAX reference stepping one model with one configuration (what ``kamino.Simulator(..., backend="jax")``
    holds): the padded layout of each precision it has stepped, built on first use (:func:`build_layout`) and freed
    with the engine, and the jitted step and rollout. XLA's compiled programs are shared by every engine of the same
    padded shapes and configuration (the layout is an argument, not a constant)."""

    def __init__(self, model: Model, cfg: SolverConfig) -> None:
        self.model, self.cfg = model, cfg
        self._layouts: dict[np.dtype, Layout] = {}
        self._lock = threading.Lock()

    def layout(self, dtype) -> Layout:
        """The padded layout in ``dtype`` (built once)."""
        dtype = np.dtype(dtype)
        with self._lock:
            if dtype not in self._layouts:
                self._layouts[dtype] = build_layout(self.model, dtype)
            return self._layouts[dtype]

    def parameters(self, dtype) -> tuple[PaddedModel, dict]:
        """``(padded model, layout tables)`` in ``dtype``: every array :meth:`step` reads. A caller may replace the
        padded model's arrays with traced per-environment values (``kamino.envs``' domain randomization), and pass
        the pair through a loop's carry rather than close over it (``kamino.state.drop_empty`` says why)."""
        lay = self.layout(dtype)
        return lay.padded, lay.tables

    def step(self, state: State, control: Control | None, parameters: tuple[PaddedModel, dict] | None = None) -> State:
        pm, tables = self.parameters(state.body_q.dtype) if parameters is None else parameters
        return step_padded(pm, tables, state, control, self.cfg)

    def rollout(self, state: State, controls: Control | None, num_steps: int) -> State:
        lay = self.layout(state.body_q.dtype)
        return _rollout_jit(lay.padded, lay.tables, state, controls, self.cfg, int(num_steps))


#: the reactions of a :class:`State` that warm-start the next step's solve (§7.8), and nothing else; the contacts'
#: impulses and velocities and ``info.penalty`` do too (:func:`warm_started`)
WARM_START_FIELDS = ("constraint_force", "coupling_force", "actuator_force", "passive_force", "limit_force")


def warm_started(state: State, solution: State) -> State:
    """``state`` with the warm start (:data:`WARM_START_FIELDS`, the contacts and ``info.penalty``) taken from
    ``solution``, a step's output from ``state``: stepping the result again starts every solve at that step's
    solution (the contacts it detects at ``state``'s poses are ``solution``'s, matched by geom pair and point on
    geom b, §7.8)."""
    info = dataclasses.replace(state.info, penalty=solution.info.penalty)
    fields = {f: getattr(solution, f) for f in WARM_START_FIELDS}
    return dataclasses.replace(state, contacts=solution.contacts, info=info, **fields)


def with_world_parameters(model: Model, pm: PaddedModel, parameters) -> PaddedModel:
    """``pm`` (the padded ``model``) with the per-world parameters ``parameters`` written in: a
    ``kamino.warp_backend.parameters.WorldParameters`` (masses, inertias, friction, PD gains, armature, damping,
    effort limits, flat over worlds as in :class:`Model`, and gravity ``[num_worlds, 3]``), possibly traced. The
    padding keeps ``pm``'s values."""
    W = model.num_worlds
    lay = layout_of(model, pm.mass.dtype)
    gg, gmask, _ = _pad_index(model.world_geom_start, model.world_geom_count, pm.geom_friction.shape[1])
    dtype = pm.mass.dtype

    def put(current, flat, gather, mask):
        value = to_padded(jnp.asarray(flat, dtype), gather, mask, 0.0)
        m = np.asarray(mask).reshape(mask.shape + (1,) * (value.ndim - mask.ndim))
        return jnp.where(m, value, current)

    p = parameters
    body = lambda cur, x: put(cur, x, lay.body_gather, np.asarray(pm.body_mask))  # noqa: E731
    dof = lambda cur, x: put(cur, x, lay.dof_gather, np.asarray(pm.dof_mask))  # noqa: E731
    return dataclasses.replace(
        pm, mass=body(pm.mass, p.body_mass), inertia=body(pm.inertia, p.body_inertia),
        geom_friction=put(pm.geom_friction, p.geom_friction, gg, gmask),
        dof_kp=dof(pm.dof_kp, p.dof_kp), dof_kd=dof(pm.dof_kd, p.dof_kd),
        dof_armature=dof(pm.dof_armature, p.dof_armature), dof_damping=dof(pm.dof_damping, p.dof_damping),
        dof_effort_limit=dof(pm.dof_effort_limit, p.dof_effort_limit),
        gravity=jnp.asarray(p.gravity, dtype).reshape(W, 3))


def tangent_at(engine: Engine, solution: State, primals: tuple, tangents: tuple) -> State:
    """The tangent of the step at ``primals = (state, control, parameters)`` along ``tangents``, by this reference
    (:meth:`Engine.step`, its solves differentiated at their solutions: docs/formulation.md §7.10), with every solve
    warm-started from ``solution`` (:func:`warm_started`): another backend's output of the same step, which the
    reference's PADMM then starts from and, converging within ``engine.cfg.tolerance`` of it, differentiates there.
    ``parameters`` is ``None`` or a ``WorldParameters`` (:func:`with_world_parameters`). The warm start's own
    tangents are dropped (the solution does not depend on the warm start)."""
    state, control, parameters = primals

    def step(state, control, parameters):
        pm, tables = engine.parameters(state.body_q.dtype)
        if parameters is not None:
            pm = with_world_parameters(engine.model, pm, parameters)
        return step_padded(pm, tables, warm_started(state, solution), control, engine.cfg)

    return jax.jvp(step, (state, control, parameters), tangents)[1]


def padded_motion(pm: PaddedModel, t: dict, body_q: jax.Array, body_u: jax.Array) -> tuple[jax.Array, jax.Array]:
    """Flat poses and twists -> padded ``[W, nb, 7]`` / ``[W, nb, 6]`` (identity poses, zero twists on padding)."""
    return padded_poses(pm, t, body_q), to_padded(body_u, t["bg"], pm.body_mask, 0.0)


@jax.jit
@full_precision
def _metrics_jit(pm: PaddedModel, t: dict, body_q, body_u):
    q, u = padded_motion(pm, t, body_q, body_u)

    def one(pm_w, q_w, u_w):
        bd = body_dynamics(pm_w, q_w)
        jf = joint_frames(pm_w, q_w)
        rows = constraint_residual(pm_w, jf) if pm_w.row_mask.shape[0] else jnp.zeros(0, q_w.dtype)
        e = jnp.concatenate([rows, coupling_residual(pm_w, dof_positions(pm_w, jf))])
        gap = jnp.max(jnp.where(pm_w.row_kind == RES_TRANS, jnp.abs(rows), 0.0), initial=0.0)
        return (jnp.max(jnp.abs(e), initial=0.0), gap, kinetic_energy(bd, pm_w, u_w),
                potential_energy(pm_w, q_w))

    viol, gap, ke, pe = jax.vmap(one)(pm, q, u)
    return {"constraint_violation": viol, "anchor_gap": gap, "kinetic_energy": ke, "potential_energy": pe,
            "total_energy": ke + pe}


def metrics(model: Model, state: State) -> dict:
    lay = layout_of(model, state.body_q.dtype)
    return _metrics_jit(lay.padded, lay.tables, state.body_q, state.body_u)


@jax.jit
@full_precision
def _joint_coords_jit(pm: PaddedModel, gather_j: dict, body_q):
    q = padded_poses(pm, gather_j, body_q)
    return jax.vmap(lambda p, x: joint_coordinates(p, joint_frames(p, x)))(pm, q)


def joint_coordinates_padded(model: Model, body_q: jax.Array) -> jax.Array:
    """``[W, max_joints, 7]`` packed joint coordinates (see ``joints.joint_coordinates``)."""
    lay = layout_of(model, body_q.dtype)
    return _joint_coords_jit(lay.padded, lay.tables, body_q)


@jax.jit
@full_precision
def _dof_state_jit(pm: PaddedModel, t: dict, body_q, body_u):
    q, u = padded_motion(pm, t, body_q, body_u)

    def one(p, x, v):
        jf = joint_frames(p, x)
        return dof_positions(p, jf), dof_jacobian(p, jf, x.shape[0]) @ v.reshape(-1)

    pos, rate = jax.vmap(one)(pm, q, u)
    return to_flat(pos, t["ds"]), to_flat(rate, t["ds"])


def dof_state(model: Model, body_q: jax.Array, body_u: jax.Array) -> tuple[jax.Array, jax.Array]:
    """``(positions, rates)`` of every DoF, flat ``[num_dofs]``: ``dof_positions`` and ``J_dofs u``
    (docs/formulation.md §2.5) at the poses ``body_q`` and twists ``body_u``."""
    lay = layout_of(model, body_q.dtype)
    return _dof_state_jit(lay.padded, lay.tables, body_q, body_u)
