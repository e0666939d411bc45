"""One time step of one world, and its vmapped/jitted batch over worlds (formulation.md §5-§6).

Pipeline (architecture.md, backend contract): kinematics -> dynamics -> PADMM -> integrate.
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp

from kamino.config import SolverConfig
from kamino.jax_ref import padmm
from kamino.jax_ref.dynamics import apply_inv_mass, body_dynamics, delassus, nonlinear_force
from kamino.jax_ref.joints import constraint_jacobian, constraint_residual, dof_jacobian, joint_frames
from kamino.jax_ref.layout import PaddedModel
from kamino.jax_ref.spatial import integrate_pose


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class WorldStep:
    """Result of one world's step (padded arrays)."""

    body_q: jax.Array
    body_u: jax.Array
    impulse: jax.Array
    solve: padmm.PADMMResult


def _deadband(x: jax.Array, delta) -> jax.Array:
    """``sign(x) max(0, |x| - delta)`` (the dead band of formulation.md §4.2, applied to joint errors)."""
    return jnp.sign(x) * jnp.maximum(jnp.abs(x) - delta, 0.0)


def joint_deadband(cfg: SolverConfig, dtype) -> float:
    """Configured joint dead band, or the dtype default (docs/conventions.md, "Stabilisation")."""
    if cfg.joint_deadband is not None:
        return cfg.joint_deadband
    return 1e-6 if jnp.dtype(dtype) == jnp.float32 else 1e-11


def joint_bias(pm: PaddedModel, q_eval: jax.Array, u_pred: jax.Array, e_eval: jax.Array, e_start: jax.Array,
               J: jax.Array, h, cfg: SolverConfig) -> jax.Array:
    """Stabilisation bias ``v*`` of the joint rows (formulation.md §5; docs/conventions.md "Stabilisation").

    The step ends with the update ``q+ = q_eval ⊕ h u+`` (Euler: ``q_eval = q-``, ``h = dt``;
    midpoint: ``q_eval = q_m``, ``h = dt/2``). Expanding ``e(q+) = e_eval + h J u+ + c`` and asking
    for ``e(q+) = (1 - alpha) e(q-)`` gives the row equation ``J u+ + v* = 0`` with

        v* = (e_eval - (1 - alpha) e_start + c) / h,

    i.e. the Baumgarte term ``alpha e / dt`` of §5 for Euler, and the same end-of-step contraction
    for the midpoint rule. With ``curvature_correction``, ``c = e(q_eval ⊕ h u_pred) - e_eval -
    h J u_pred`` (a finite difference along the free velocity ``u_pred``) cancels the second-order
    drift of the exponential-map update, leaving ``O(h^2 |u+ - u_pred|)`` instead of ``O(h^2 |u|^2)``.
    Errors below the dead band get no bias (rounding noise on redundant loop rows).
    """
    delta = joint_deadband(cfg, e_eval.dtype)
    bias = _deadband(e_eval - (1.0 - cfg.baumgarte) * e_start, delta)
    if cfg.curvature_correction:
        e_pred = constraint_residual(pm, joint_frames(pm, integrate_pose(q_eval, u_pred, h)))
        nb = u_pred.shape[0]
        c = e_pred - e_eval - h * (J @ u_pred.reshape(nb * 6))
        bias = bias + _deadband(c, delta)
    return jnp.where(pm.row_mask, bias / h, 0.0)


def _constrained_velocity(pm: PaddedModel, q_start: jax.Array, q_eval: jax.Array, body_u: jax.Array,
                          force_prev: jax.Array, wrench: jax.Array, effort: jax.Array, h, cfg: SolverConfig):
    """Build the dynamics at ``q_eval``, solve PADMM and return ``u+`` (formulation.md §6.2 steps 1-3).

    ``q_start`` is the pose at the start of the step (for the stabilisation target), ``h`` the
    duration of the pose update that follows the solve, ``force_prev`` the previous step's
    reactions (the warm start, §7.8).
    """
    dt = cfg.dt
    nb = body_u.shape[0]
    jf = joint_frames(pm, q_eval)
    bd = body_dynamics(pm, q_eval)
    J_dofs = dof_jacobian(pm, jf, nb)
    actuation = (J_dofs.T @ jnp.where(pm.dof_mask, effort, 0.0)).reshape(nb, 6)  # w^a = J_dofs^T tau (§3.1)
    h_force = nonlinear_force(pm, bd, body_u, pm.gravity, wrench + actuation)
    u_f = body_u + dt * apply_inv_mass(bd, h_force)  # §1.4 free velocity
    if pm.row_mask.shape[0] == 0:
        empty = jnp.zeros(0, body_u.dtype)
        z = jnp.asarray(0.0, body_u.dtype)
        return u_f, padmm.PADMMResult(empty, jnp.int32(0), z, z, z, jnp.asarray(True))
    e_eval = constraint_residual(pm, jf)
    e_start = e_eval if q_start is q_eval else constraint_residual(pm, joint_frames(pm, q_start))
    J = constraint_jacobian(pm, jf, nb)
    v_star = joint_bias(pm, q_eval, u_f, e_eval, e_start, J, h, cfg)
    v_f = J @ u_f.reshape(nb * 6) + v_star  # §5
    D = delassus(J, bd)  # R = 0: no dynamic rows yet (actuation issue)
    row_type = jnp.full(e_eval.shape, padmm.ROW_BILATERAL, jnp.int32)
    impulse0 = (cfg.warmstart_scale * dt) * force_prev if cfg.warm_start else jnp.zeros_like(force_prev)
    res = padmm.solve(D, v_f, row_type, pm.row_mask, impulse0, cfg)
    u_plus = u_f + apply_inv_mass(bd, (J.T @ res.impulse).reshape(nb, 6))  # u+ = u_f + M^-1 J^T lambda
    return u_plus, res


def step_world(pm: PaddedModel, body_q: jax.Array, body_u: jax.Array, force0: jax.Array, effort: jax.Array,
               wrench: jax.Array, cfg: SolverConfig) -> WorldStep:
    """Advance one world by ``cfg.dt`` (formulation.md §6.2 Euler, §6.3 Moreau-Jean midpoint)."""
    dt = cfg.dt
    if cfg.integrator == "euler":
        u_plus, res = _constrained_velocity(pm, body_q, body_q, body_u, force0, wrench, effort, dt, cfg)
        u_plus = _angular_damping(u_plus, cfg)
        q_plus = integrate_pose(body_q, u_plus, dt)
    else:
        q_mid = integrate_pose(body_q, body_u, 0.5 * dt)
        u_plus, res = _constrained_velocity(pm, body_q, q_mid, body_u, force0, wrench, effort, 0.5 * dt, cfg)
        u_plus = _angular_damping(u_plus, cfg)
        q_plus = integrate_pose(q_mid, u_plus, 0.5 * dt)
    mask = pm.body_mask[:, None]
    q_plus = jnp.where(mask, q_plus, body_q)
    u_plus = jnp.where(mask, u_plus, body_u)
    return WorldStep(body_q=q_plus, body_u=u_plus, impulse=res.impulse, solve=res)


def _angular_damping(u: jax.Array, cfg: SolverConfig) -> jax.Array:
    if cfg.angular_damping == 0.0:
        return u
    return u.at[:, 3:].multiply(1.0 - cfg.angular_damping * cfg.dt)


@functools.partial(jax.jit, static_argnames=("cfg",))
def step_batch(pm: PaddedModel, body_q, body_u, force0, effort, wrench, cfg: SolverConfig):
    """``step_world`` vmapped over worlds (all arrays padded, leading axis = world).

    A world whose new state is non-finite keeps its previous state and is flagged ``failed``.
    """
    out = jax.vmap(step_world, in_axes=(0, 0, 0, 0, 0, 0, None))(pm, body_q, body_u, force0, effort, wrench, cfg)
    finite = jnp.all(jnp.isfinite(out.body_q), axis=(1, 2)) & jnp.all(jnp.isfinite(out.body_u), axis=(1, 2))
    finite = finite & jnp.all(jnp.isfinite(out.impulse), axis=-1)
    keep = finite[:, None, None]
    q = jnp.where(keep, out.body_q, body_q)
    u = jnp.where(keep, out.body_u, body_u)
    force = jnp.where(finite[:, None], out.impulse / cfg.dt, force0)
    return q, u, force, out.solve, ~finite
