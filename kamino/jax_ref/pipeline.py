"""One time step of one world, and its vmapped/jitted batch over worlds (docs/formulation.md §3-§6).

Pipeline (docs/architecture.md, backend contract): kinematics -> collision -> dynamics -> PADMM ->
integrate. Rows of a world, in order (docs/formulation.md §7.1): joint-dynamics rows (actuators, then
armature/damping/springs) | joint kinematic rows | coupling rows | limit rows (their bias and bounds:
``rows``) | contact triples ``(t1, t2, n)`` (``contacts``).
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp

from kamino.config import CONTACT_MATCH_DISTANCE, SolverConfig
from kamino.jax_ref import contacts as cts
from kamino.jax_ref import post_stabilisation as post
from kamino.jax_ref import solver
from kamino.jax_ref.couplings import coupling_jacobian, coupling_residual
from kamino.jax_ref.dynamics import apply_inv_mass, body_dynamics, delassus, free_velocity, nonlinear_force
from kamino.jax_ref.integrate import commit, constrained_velocity, integrate, loop_opened, reactions, too_fast
from kamino.jax_ref.jacobians import (
    constraint_jacobian,
    constraint_residual,
    dof_jacobian,
    dof_positions,
    joint_frames,
)
from kamino.jax_ref.precision import full_precision
from kamino.jax_ref.rows import WorldControl, coupling_bias, dynamics_rows, explicit_effort, joint_bias, limit_rows
from kamino.jax_ref.types import DYN_ACTUATOR, PaddedModel, WorldCache
from kamino.spatial import integrate_pose


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class WorldStep:
    """Result of one world's step (padded arrays)."""

    body_q: jax.Array
    body_u: jax.Array
    cache: WorldCache
    solve: solver.PADMMResult
    num_contacts: jax.Array
    contact_overflow: jax.Array
    unsound: jax.Array  # the step passed a health bound (docs/conventions.md, "World health")


def _constrained_velocity(pm: PaddedModel, q_start: jax.Array, q_eval: jax.Array, body_u: jax.Array,
                          cache: WorldCache, ctrl: WorldControl, h, cfg: SolverConfig):
    """Build the dynamics at ``q_eval``, solve PADMM and return ``u+`` (docs/formulation.md §6.2 steps 1-3).

    ``q_start`` is the pose at the start of the step (stabilisation target), ``h`` the duration of
    the pose update that follows the solve, ``cache`` the previous step's reactions and contacts.
    """
    dt = cfg.dt
    nb = body_u.shape[0]
    dtype = body_u.dtype
    jf = joint_frames(pm, q_eval)
    bd = body_dynamics(pm, q_eval)
    J_dofs = dof_jacobian(pm, jf, nb)
    actuation = (J_dofs.T @ explicit_effort(pm, ctrl.effort)).reshape(nb, 6)  # w^a = J_dofs^T tau (§3.1)
    h_force = nonlinear_force(pm, bd, body_u, pm.gravity, ctrl.wrench + actuation)
    u_f = free_velocity(pm, bd, q_eval, body_u, h_force, dt)  # §1.4 free velocity, implicit gyroscopic term
    u_vec, uf_vec = body_u.reshape(nb * 6), u_f.reshape(nb * 6)
    q_dof = dof_positions(pm, jf)
    qd_minus, qd_free = J_dofs @ u_vec, J_dofs @ uf_vec

    # joint-dynamics rows
    d = pm.dyn_dof
    J_dyn = jnp.where(pm.dyn_mask[:, None], J_dofs[d], 0.0)
    R_dyn, vs_dyn, lo_dyn, hi_dyn = dynamics_rows(pm, q_dof, qd_minus, ctrl, h, cfg)
    # kinematic joint rows
    jf_start = jf if q_start is q_eval else joint_frames(pm, q_start)
    e_eval = constraint_residual(pm, jf)
    e_start = e_eval if q_start is q_eval else constraint_residual(pm, jf_start)
    J_kin = constraint_jacobian(pm, jf, nb)
    # coupling rows (mimic joints)
    J_cpl = coupling_jacobian(pm, q_dof, J_dofs)
    e_cpl = coupling_residual(pm, q_dof)
    e_cpl_start = e_cpl if q_start is q_eval else coupling_residual(pm, dof_positions(pm, jf_start))
    # limit rows
    # Unilateral rows look one step dt ahead, to the pose the next step reads them at, under both
    # integrators (the midpoint rule's next q_m is q_m ⊕ dt u+): an impact stops there instead of
    # overshooting in the first half-step (docs/conventions.md, "Joint limits").
    side, lim_active, vs_lim = limit_rows(pm, q_dof, qd_free, dt, cfg)
    J_lim = jnp.where(lim_active[:, None], side[:, None] * J_dofs[pm.lim_dof], 0.0)
    # contact rows
    ct = cts.detect(pm, q_eval, body_u, u_f, dt, cfg)
    J_con = cts.contact_jacobian(ct, q_eval, nb)
    vn_minus = (J_con @ u_vec).reshape(-1, 3)[:, 2]
    vs_con = cts.contact_bias(ct, ct.dist, vn_minus, dt, cfg)  # the same horizon as the limits above

    J = jnp.concatenate([J_dyn, J_kin, J_cpl, J_lim, J_con], axis=0)
    n_dyn, n_kin, n_lim = J_dyn.shape[0], J_kin.shape[0] + J_cpl.shape[0], J_lim.shape[0]
    n_box = n_dyn + n_kin + n_lim
    if J.shape[0] == 0:
        z = jnp.asarray(0.0, dtype)
        empty = jnp.zeros(0, dtype)
        return (u_f, solver.PADMMResult(empty, empty, jnp.int32(0), z, z, z, jnp.asarray(True), z, jnp.zeros(0, bool)),
                ct, side, None)
    # warm start (§7.8): previous reactions, contacts matched by geom pair and point on geom b
    frames = cts.contact_frames(ct.normal)
    point_b = cts.local_point_b(ct, q_eval)
    j, found = cts.match_previous(ct, point_b, cache.contact_pair, cache.contact_point_b, CONTACT_MATCH_DISTANCE)
    found = found & ct.mask
    f_prev = jnp.einsum("cji,cj->ci", frames, cache.contact_force[j])  # C_new^T f_world
    v_prev = jnp.einsum("cji,cj->ci", frames, cache.contact_velocity[j])
    f_prev = jnp.where(found[:, None], solver.cone_project(f_prev, ct.mu), 0.0)
    v_prev = jnp.where(found[:, None], v_prev, 0.0)
    v_prev = v_prev + solver.de_saxce(v_prev.reshape(-1), ct.mu, 0).reshape(-1, 3)
    act_prev = jnp.where(pm.dyn_kind == DYN_ACTUATOR, cache.actuator[d], cache.passive[d])
    force0 = jnp.concatenate([act_prev, cache.kin, cache.coupling, jnp.maximum(side * cache.limit[pm.lim_dof], 0.0),
                              f_prev.reshape(-1)])
    impulse0 = (cfg.warmstart_scale * dt) * force0 if cfg.warm_start else jnp.zeros_like(force0)
    velocity0 = jnp.concatenate([jnp.zeros(n_box, dtype), v_prev.reshape(-1)])
    if not cfg.warm_start:
        velocity0 = jnp.zeros_like(velocity0)
    # bilateral rows' stabilisation (§5); the curvature term is predicted along u_f, not along
    # u_f + M^-1 J^T lambda_prev (that feeds the midpoint rule's alternating mode: docs/conventions.md)
    vs_kin = joint_bias(pm, q_eval, u_f, e_eval, e_start, J_kin, h, cfg) if e_eval.shape[0] else e_eval
    vs_cpl = coupling_bias(pm, q_eval, u_f, e_cpl, e_cpl_start, J_cpl, h, cfg)
    con_mask = jnp.repeat(ct.mask, 3)
    row_mask = jnp.concatenate([pm.dyn_mask, pm.row_mask, pm.cpl_mask, lim_active, con_mask])
    v_star = jnp.concatenate([vs_dyn, vs_kin, vs_cpl, vs_lim, vs_con])
    R = jnp.concatenate([R_dyn, jnp.zeros(n_kin + n_lim + con_mask.shape[0], dtype)])
    inf = jnp.full(n_kin, jnp.inf, dtype)
    lo = jnp.concatenate([lo_dyn, -inf, jnp.zeros(n_lim, dtype)])
    hi = jnp.concatenate([hi_dyn, inf, jnp.full(n_lim, jnp.inf, dtype)])
    D = delassus(J, bd) + jnp.diag(R)
    v_f = J @ uf_vec + v_star  # §5

    refine = None
    if cfg.stabilisation.curvature_refinement and cfg.stabilisation.curvature_correction and n_kin:
        def refine(impulse):
            # the bilateral rows' curvature term predicted along the solved velocity (docs/conventions.md)
            u_sol = u_f + apply_inv_mass(bd, (J.T @ impulse).reshape(nb, 6))
            vk = joint_bias(pm, q_eval, u_sol, e_eval, e_start, J_kin, h, cfg) if e_eval.shape[0] else e_eval
            vc = coupling_bias(pm, q_eval, u_sol, e_cpl, e_cpl_start, J_cpl, h, cfg)
            return J @ uf_vec + jnp.concatenate([vs_dyn, vk, vc, vs_lim, vs_con])

    rho0 = jnp.where(cache.penalty > 0, cache.penalty, cfg.penalty.rho).astype(dtype)
    # only a world with joint or coupling rows refines (solver.solve): not the padding of a batch's other worlds
    refine_rows = jnp.any(pm.row_mask) | jnp.any(pm.cpl_mask)
    res = solver.solve(D, v_f, lo, hi, ct.mu, row_mask, impulse0, velocity0, cfg, refine, rho0, n_dyn + n_kin,
                       refine_rows)
    u_plus = constrained_velocity(bd, u_f, J, res.impulse)
    proj = None
    if cfg.stabilisation.post_stabilisation and n_dyn + n_kin:
        P = solver.jacobi_preconditioner(D, row_mask, n_box)
        proj = post.projector(J, D, P, n_dyn + n_kin, res.saturated, bd, cfg, R)
    return u_plus, res, ct, side, proj


def step_world(pm: PaddedModel, body_q: jax.Array, body_u: jax.Array, cache: WorldCache, ctrl: WorldControl,
               cfg: SolverConfig) -> WorldStep:
    """Advance one world by ``cfg.dt`` (docs/formulation.md §6.2 Euler, §6.3 Moreau-Jean midpoint)."""
    dt = cfg.dt
    if cfg.integrator == "euler":
        q_eval, h = body_q, dt
    else:
        q_eval, h = integrate_pose(body_q, body_u, 0.5 * dt), 0.5 * dt
    u_plus, res, ct, side, proj = _constrained_velocity(pm, body_q, q_eval, body_u, cache, ctrl, h, cfg)
    u_plus, q_plus = integrate(q_eval, u_plus, h, cfg)
    if proj is not None:
        q_plus = post.project(pm, q_plus, proj, cfg, res.converged)
    mask = pm.body_mask[:, None]
    q_plus = jnp.where(mask, q_plus, body_q)
    u_plus = jnp.where(mask, u_plus, body_u)
    unsound = too_fast(pm, u_plus, dt) | loop_opened(pm, body_q, q_plus)
    return WorldStep(body_q=q_plus, body_u=u_plus, cache=reactions(pm, q_eval, res, ct, side, ctrl, cfg),
                     solve=res, num_contacts=jnp.minimum(ct.count, pm.contact_capacity), contact_overflow=ct.overflow,
                     unsound=unsound)


@functools.partial(jax.jit, static_argnames=("cfg",))
@full_precision
def step_batch(pm: PaddedModel, body_q, body_u, cache: WorldCache, ctrl: WorldControl, cfg: SolverConfig,
               frozen: jax.Array):
    """``step_world`` vmapped over worlds (all arrays padded, leading axis = world).

    A world whose new state is non-finite or passes a health bound, or that is ``frozen`` (failed earlier), keeps its
    previous state; the last output flags the worlds that fail on this step, whose solve reports ``converged = False``
    (docs/conventions.md, "World health").
    """
    out = jax.vmap(step_world, in_axes=(0, 0, 0, 0, 0, None))(pm, body_q, body_u, cache, ctrl, cfg)
    q, u, new_cache, blown = commit(out.body_q, out.body_u, out.cache, body_q, body_u, cache, frozen, out.unsound)
    out = dataclasses.replace(out, solve=dataclasses.replace(out.solve, converged=out.solve.converged & ~blown))
    return q, u, new_cache, out, blown
