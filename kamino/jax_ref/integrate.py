"""Integration: the constrained velocity, the pose update, the reactions a world carries, and the commit of a batch
(docs/formulation.md §6; the Warp backend's ``integrate.py``).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from kamino.config import ANGULAR_DAMPING, HEALTH_TURN, LOOP_OPEN_BOUND, SolverConfig
from kamino.jax_ref import contacts as cts
from kamino.jax_ref import solver
from kamino.jax_ref.dynamics import BodyDynamics, apply_inv_mass
from kamino.jax_ref.jacobians import constraint_residual, joint_frames
from kamino.jax_ref.rows import WorldControl, explicit_effort
from kamino.jax_ref.types import DYN_ACTUATOR, PaddedModel, WorldCache
from kamino.model import RES_TRANS
from kamino.spatial import integrate_pose
from kamino.tables import health_speed_bound


def constrained_velocity(bd: BodyDynamics, u_f: jax.Array, J: jax.Array, impulse: jax.Array) -> jax.Array:
    """``u+ = u_f + M^-1 J^T lambda`` (docs/formulation.md §6.2, step 3): ``J`` is ``[rows, 6 nb]``."""
    nb = u_f.shape[0]
    return u_f + apply_inv_mass(bd, (J.T @ impulse).reshape(nb, 6))


def integrate(q_eval: jax.Array, u_plus: jax.Array, h, cfg: SolverConfig) -> tuple[jax.Array, jax.Array]:
    """The end-of-step velocity (``ANGULAR_DAMPING`` applied) and the pose ``q+ = q_eval ⊕ h u+``
    (docs/formulation.md §6.1; ``q_eval`` is the start pose for Euler, the midpoint pose for Moreau-Jean, §6.3)."""
    u_plus = _angular_damping(u_plus, cfg)
    return u_plus, integrate_pose(q_eval, u_plus, h)


def _angular_damping(u: jax.Array, cfg: SolverConfig) -> jax.Array:
    """``ANGULAR_DAMPING`` on the angular velocities (none at its default, 0)."""
    if ANGULAR_DAMPING == 0.0:
        return u
    return u.at[:, 3:].multiply(1.0 - ANGULAR_DAMPING * cfg.dt)


def reactions(pm: PaddedModel, q_eval, res: solver.PADMMResult, ct: cts.Contacts, side, ctrl: WorldControl,
               cfg: SolverConfig) -> WorldCache:
    """Split the solve's impulses into the per-family forces ``lambda / dt`` the State carries (the Warp backend's
    ``dof_forces`` / ``row_forces``), with the contacts the next step warm-starts from (docs/formulation.md §7.8)."""
    dt = cfg.dt
    nd = pm.dof_mask.shape[0]
    n_dyn, n_jnt, n_cpl, n_lim = (pm.dyn_mask.shape[0], pm.row_mask.shape[0], pm.cpl_mask.shape[0],
                                  pm.lim_mask.shape[0])
    n_kin = n_jnt + n_cpl
    if res.impulse.shape[0] == 0:
        f = jnp.zeros(0, q_eval.dtype)
        v = jnp.zeros(0, q_eval.dtype)
    else:
        f, v = res.impulse / dt, res.velocity
    f_dyn, f_lim = f[:n_dyn], f[n_dyn + n_kin:n_dyn + n_kin + n_lim]
    f_kin, f_cpl = f[n_dyn:n_dyn + n_jnt], f[n_dyn + n_jnt:n_dyn + n_kin]
    C = ct.pair.shape[0]
    f_con = f[n_dyn + n_kin + n_lim:].reshape(C, 3)
    v_con = v[n_dyn + n_kin + n_lim:].reshape(C, 3)
    frames = cts.contact_frames(ct.normal)
    d = pm.dyn_dof
    is_act = (pm.dyn_kind == DYN_ACTUATOR) & pm.dyn_mask
    is_pas = (pm.dyn_kind != DYN_ACTUATOR) & pm.dyn_mask
    zeros = jnp.zeros(nd, q_eval.dtype)
    actuator = explicit_effort(pm, ctrl.effort).at[d].add(jnp.where(is_act, f_dyn, 0.0))
    passive = zeros.at[d].add(jnp.where(is_pas, f_dyn, 0.0))
    limit = zeros.at[pm.lim_dof].add(jnp.where(pm.lim_mask, side * f_lim, 0.0))
    cmask = ct.mask[:, None]
    return WorldCache(
        kin=f_kin,
        coupling=f_cpl,
        actuator=actuator,
        passive=passive,
        limit=limit,
        contact_pair=ct.pair,
        contact_pos=ct.pos,
        contact_normal=ct.normal,
        contact_dist=ct.dist,
        contact_force=jnp.where(cmask, jnp.einsum("cij,cj->ci", frames, f_con), 0.0),
        contact_velocity=jnp.where(cmask, jnp.einsum("cij,cj->ci", frames, v_con), 0.0),
        contact_point_b=jnp.where(cmask, cts.local_point_b(ct, q_eval), 0.0),
        penalty=res.penalty,
    )


def too_fast(pm: PaddedModel, u_plus: jax.Array, dt: float) -> jax.Array:
    """Whether one world's end-of-step twists ``u_plus`` ``[nb, 6]`` pass the health bounds (docs/conventions.md,
    "World health"): a body turning faster than ``HEALTH_TURN / dt`` or moving faster than
    ``max(HEALTH_SPEED, HEALTH_TURN * reach / dt)`` (``kamino.tables.health_speed_bound``; the Warp backend's
    ``speed_check``)."""
    speed_bound = health_speed_bound(pm.reach, dt)
    v2 = jnp.sum(u_plus[:, :3] ** 2, axis=-1)
    w2 = jnp.sum(u_plus[:, 3:] ** 2, axis=-1)
    fast = ~(v2 <= speed_bound ** 2) | ~(w2 <= (HEALTH_TURN / dt) ** 2)
    return jnp.any(fast & pm.body_mask)


def loop_opened(pm: PaddedModel, q_prev: jax.Array, q_plus: jax.Array) -> jax.Array:
    """Whether one world's step opened a joint past ``LOOP_OPEN_BOUND``: a translational joint row's residual above
    the bound at the end pose ``q_plus`` and above what it was at the start pose ``q_prev`` (a world assembled open,
    and closing, is not flagged; docs/conventions.md, "World health"; the Warp backend's ``closure_check``)."""
    e_new = jnp.abs(constraint_residual(pm, joint_frames(pm, q_plus)))
    e_old = jnp.abs(constraint_residual(pm, joint_frames(pm, q_prev)))
    opened = ~(e_new <= LOOP_OPEN_BOUND) & ~(e_new <= e_old)
    return jnp.any(opened & (pm.row_kind == RES_TRANS) & pm.row_mask)


def commit(new_q: jax.Array, new_u: jax.Array, new_cache: WorldCache, body_q: jax.Array, body_u: jax.Array,
           cache: WorldCache, frozen: jax.Array, unsound: jax.Array) -> tuple[jax.Array, jax.Array, WorldCache,
                                                                                jax.Array]:
    """The batch's new state, world by world (leading axis: world): a world whose new state is non-finite or
    ``unsound`` (a health bound passed: :func:`too_fast`, :func:`loop_opened`), or that is ``frozen`` (failed
    earlier), keeps its previous state. Returns ``(q, u, cache, blown)``, ``blown`` flagging the worlds that fail on
    this step (docs/conventions.md, "World health"; the Warp backend's ``commit_bodies``)."""
    finite = jnp.all(jnp.isfinite(new_q), axis=(1, 2)) & jnp.all(jnp.isfinite(new_u), axis=(1, 2))
    for leaf in jax.tree_util.tree_leaves(new_cache):
        if jnp.issubdtype(leaf.dtype, jnp.floating):
            finite = finite & jnp.all(jnp.isfinite(leaf).reshape(leaf.shape[0], -1), axis=1)
    sound = finite & ~unsound
    blown = ~sound & ~frozen
    advance = sound & ~frozen

    def keep(new, old):
        return jnp.where(advance.reshape((-1,) + (1,) * (new.ndim - 1)), new, old)

    return keep(new_q, body_q), keep(new_u, body_u), jax.tree_util.tree_map(keep, new_cache, cache), blown
