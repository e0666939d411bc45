"""The joint-dynamics, kinematic joint, coupling and limit rows of one world and their stabilisation bias
(docs/formulation.md §3.1-§3.2, §4.1, §5; the Warp backend's ``rows.py``).

Every function here works on one world's padded arrays; ``kamino.jax_ref.pipeline`` assembles their rows, in
order (docs/formulation.md §7.1): joint-dynamics rows (actuators, then armature/damping/springs) | joint kinematic
rows | coupling rows | limit rows | contact triples (``contacts``).
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp

from kamino.config import LIMIT_BAUMGARTE, LIMIT_MARGIN, MIDPOINT_DAMPING, SolverConfig, joint_deadband
from kamino.jax_ref import contacts as cts
from kamino.jax_ref.couplings import coupling_residual
from kamino.jax_ref.jacobians import constraint_residual, dof_positions, joint_frames
from kamino.jax_ref.types import DYN_ACTUATOR, PaddedModel
from kamino.model import ActuationMode
from kamino.spatial import integrate_pose


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class WorldControl:
    """One world's inputs (padded): DoF efforts, body wrenches, position and velocity targets."""

    effort: jax.Array  # [nd]
    wrench: jax.Array  # [nb, 6]
    position_target: jax.Array  # [nd]
    velocity_target: jax.Array  # [nd]


def joint_bias(pm: PaddedModel, q_eval: jax.Array, u_pred: jax.Array, e_eval: jax.Array, e_start: jax.Array,
               J: jax.Array, h, cfg: SolverConfig) -> jax.Array:
    """Stabilisation bias ``v*`` of the joint rows (docs/formulation.md §5; docs/conventions.md "Stabilisation").

    The step ends with the update ``q+ = q_eval ⊕ h u+`` (Euler: ``q_eval = q-``, ``h = dt``;
    midpoint: ``q_eval = q_m``, ``h = dt/2``). Expanding ``e(q+) = e_eval + h J u+ + c`` and asking
    for ``e(q+) = (1 - alpha) e(q-) + gamma h w-`` gives the row equation ``J u+ + v* = 0`` with

        v* = (e_eval - (1 - alpha) e_start - gamma h w- + c) / h,

    i.e. the Baumgarte term ``alpha e / dt`` of §5 for Euler (``gamma = 0``: no first half-step), and an
    end-of-step contraction for the midpoint rule. There ``h w- = e_eval - e_start - c`` estimates
    ``h J(q-) u-``, what the first half-step moved the residual along the start pose's constraint
    velocity (its curvature taken equal to the second half-step's ``c``); ``gamma =``
    :data:`MIDPOINT_DAMPING` lets that much of it stand instead of reversing it, so the end pose's
    constraint velocity is ``w+ = -(1 - gamma) w- - alpha e- / h`` and the alternating mode decays
    (docs/conventions.md). With ``curvature_correction``, ``c = e(q_eval ⊕ h u_pred) - e_eval -
    h J u_pred`` (a finite difference along the free velocity ``u_pred``) cancels the second-order
    drift of the exponential-map update, leaving ``O(h^2 |u+ - u_pred|)`` instead of ``O(h^2 |u|^2)``.
    Errors below the dead band get no bias (rounding noise on redundant loop rows).
    """
    delta = joint_deadband(e_eval.dtype)
    c = jnp.zeros_like(e_eval)
    if cfg.stabilisation.curvature_correction:
        e_pred = constraint_residual(pm, joint_frames(pm, integrate_pose(q_eval, u_pred, h)))
        nb = u_pred.shape[0]
        c = e_pred - e_eval - h * (J @ u_pred.reshape(nb * 6))
    target = (1.0 - cfg.stabilisation.baumgarte) * e_start
    if cfg.integrator == "midpoint":
        target = target + MIDPOINT_DAMPING * (e_eval - e_start - c)
    bias = cts.deadband(e_eval - target, delta) + cts.deadband(c, delta)
    return jnp.where(pm.row_mask, bias / h, 0.0)


def coupling_bias(pm: PaddedModel, q_eval: jax.Array, u_pred: jax.Array, e_eval: jax.Array, e_start: jax.Array,
                  J: jax.Array, h, cfg: SolverConfig) -> jax.Array:
    """Stabilisation bias of the coupling rows: :func:`joint_bias`'s rule on ``q_a - p(q_b)``."""
    if not e_eval.shape[0]:
        return e_eval
    delta = joint_deadband(e_eval.dtype)
    c = jnp.zeros_like(e_eval)
    if cfg.stabilisation.curvature_correction:
        e_pred = coupling_residual(pm, dof_positions(pm, joint_frames(pm, integrate_pose(q_eval, u_pred, h))))
        c = e_pred - e_eval - h * (J @ u_pred.reshape(-1))
    target = (1.0 - cfg.stabilisation.baumgarte) * e_start
    if cfg.integrator == "midpoint":
        target = target + MIDPOINT_DAMPING * (e_eval - e_start - c)
    bias = cts.deadband(e_eval - target, delta) + cts.deadband(c, delta)
    return jnp.where(pm.cpl_mask, bias / h, 0.0)


def explicit_effort(pm: PaddedModel, effort: jax.Array) -> jax.Array:
    """Efforts applied as body wrenches ``J_dofs^T tau`` (docs/formulation.md §3.1): as given on PASSIVE
    DoFs, clipped to the effort limit on EFFORT DoFs, none on POSITION/VELOCITY DoFs (there the
    effort is the actuator row's feed-forward)."""
    mode = pm.dof_act_mode
    lim = pm.dof_effort_limit
    tau = jnp.where(mode == ActuationMode.EFFORT, jnp.clip(effort, -lim, lim), effort)
    explicit = (mode == ActuationMode.PASSIVE) | (mode == ActuationMode.EFFORT)
    return jnp.where(pm.dof_mask & explicit, tau, 0.0)


def dynamics_rows(pm: PaddedModel, q_dof: jax.Array, qd_minus: jax.Array, ctrl: WorldControl, h,
                  cfg: SolverConfig):
    """Regularisation ``R``, bias ``v*`` and impulse bounds of the joint-dynamics rows (docs/formulation.md §3.2).

    Each row is the DoF row of ``J_dofs``; with ``m`` the row's implicit inertia the row equation
    ``J u+ + lambda/m + v* = 0`` reads ``m qd+ = p0 - lambda``, i.e. backward-Euler dynamics:

    - actuator row (POSITION/VELOCITY DoFs): ``m = dt (kd + h kp)``, ``p0 = dt (tau_ff + kp (q_ref -
      q) + kd qd_ref)`` (kp only in POSITION mode), so that ``lambda = dt [tau_ff + kp (q_ref - q -
      h qd+) + kd (qd_ref - qd+)]`` is the PD impulse at the end of the step; the effort limit bounds
      it: ``|lambda| <= dt tau_max`` (a box row, enforced by PADMM);
    - passive row (armature ``a``, damping ``b``, spring ``k`` at ``q_s``): ``m = a + dt b + dt h k``,
      ``p0 = a qd- + dt k (q_s - q)``.

    ``q`` is evaluated where the dynamics are built; ``h`` is the pose update after the solve.
    """
    dt = cfg.dt
    d = pm.dyn_dof
    is_act = pm.dyn_kind == DYN_ACTUATOR
    pos_mode = pm.dof_act_mode[d] == ActuationMode.POSITION
    kp, kd = jnp.where(pos_mode, pm.dof_kp[d], 0.0), pm.dof_kd[d]
    q, qd = q_dof[d], qd_minus[d]
    m_act = dt * (kd + h * kp)
    p_act = dt * (ctrl.effort[d] + kp * (ctrl.position_target[d] - q) + kd * ctrl.velocity_target[d])
    a, b, k = pm.dof_armature[d], pm.dof_damping[d], pm.dof_stiffness[d]
    m_pas = a + dt * b + dt * h * k
    p_pas = a * qd + dt * k * (pm.dof_springref[d] - q)
    # m > 0 on every real row (positive gains; armature, damping or a spring); the floor only keeps
    # padding finite — a larger floor would add false damping to a soft spring at small dt
    m = jnp.maximum(jnp.where(is_act, m_act, m_pas), 1e-30)
    p0 = jnp.where(is_act, p_act, p_pas)
    bound = jnp.where(is_act, dt * pm.dof_effort_limit[d], jnp.inf)
    mask = pm.dyn_mask
    return (jnp.where(mask, 1.0 / m, 0.0), jnp.where(mask, -p0 / m, 0.0),
            jnp.where(mask, -bound, -jnp.inf), jnp.where(mask, bound, jnp.inf))


def limit_rows(pm: PaddedModel, q_dof: jax.Array, qd_free: jax.Array, dt, cfg: SolverConfig):
    """Side, activity and bias of the limit rows (docs/formulation.md §4.1, with speculative activation).

    Each limited DoF watches its nearer limit: ``r = q - q_min`` (side ``+1``) or ``q_max - q``
    (side ``-1``), read where the dynamics are built. The unilateral rows look one whole step ``dt``
    ahead, to the pose at which the next step reads them, under both integrators: Euler's next
    evaluation pose is ``q+ = q- ⊕ dt u+``, the midpoint rule's is ``q_m' = q+ ⊕ h u+ = q_m ⊕ dt u+``
    (``h = dt/2``; the next step's ``u-`` is this step's ``u+``), so in both ``r' = r + dt side qd+``.
    The row ``side * J_dof`` is active when ``r < margin + dt max(0, -side qd_f)`` (the limit can be
    reached before the next reading), and its bias asks ``r' >= (1 - beta) min(r, 0)``: a gap may
    close, not more; a violation shrinks by ``beta`` per step. That is ``r / dt`` for a gap and
    ``beta r / dt`` for a violation (§5). Under the midpoint rule the end pose lies halfway,
    ``r+ = r + h side qd+ = (r + r') / 2``, inside the limit whenever both readings are, so an impact
    is stopped at the next midpoint instead of overshooting by up to ``h |qd|`` in the first
    half-step; asking ``r+ >= 0`` after such an overshoot would reverse the velocity (an elastic
    bounce). docs/conventions.md, "Joint limits".
    """
    d = pm.lim_dof
    r_lo, r_hi = q_dof[d] - pm.dof_lower[d], pm.dof_upper[d] - q_dof[d]
    side = jnp.where(r_lo <= r_hi, 1.0, -1.0)
    r = jnp.minimum(r_lo, r_hi)
    approach = jnp.maximum(-side * qd_free[d], 0.0)
    active = pm.lim_mask & (r < LIMIT_MARGIN + dt * approach)
    r_safe = jnp.where(active, r, 0.0)
    bias = (r_safe - (1.0 - LIMIT_BAUMGARTE) * jnp.minimum(r_safe, 0.0)) / dt
    return side, active, jnp.where(active, bias, 0.0)
