"""Post-stabilisation: projecting the poses back onto the joint constraints after a step.

Velocity-level Baumgarte stabilisation (docs/formulation.md §5) closes a loop only as fast as ``alpha`` allows, and
a stiff ``alpha`` gives redundant unilateral rows inconsistent biases that PADMM resolves slowly
(docs/warp_backend.md, "Convergence on the four-bar"). Post-stabilisation (Cline and Pai 2003) instead corrects
the positions after the pose update: with ``e(q)`` the residuals of the always-active rows (zero on the
joint-dynamics rows, the joint residual of docs/formulation.md §2.4 on the kinematic rows, ``q_a - p(q_b)`` on the
coupling rows), one pass is the Gauss-Newton step of

    min_d 1/2 d^T M d   subject to   e(q) + J d = 0,    d = -M^-1 J^T (J M^-1 J^T + R)^-1 e,
    q <- q ⊕ d,

with the step's ``J``, ``M`` and joint-dynamics compliance ``R`` (the actuators' implicit inertia resists the
correction as it resists motion). The system is solved in PADMM's Jacobi scaling ``P``: ``(P D_ff P + diag(s)) y
= -P e``, ``lambda = P y``, with the small shifts ``s`` of ``cfg.projection_shifts(dtype)`` (PADMM's own ``eta +
rho_free`` in every dtype, so that the Warp backend reuses PADMM's factor): redundant loop rows make ``D_ff``
singular, and a null direction of ``D_ff`` moves no body (``J^T v = 0``). The shift leaves ``s / (sigma + s)`` of
the error along a direction of scaled curvature ``sigma``: the projection holds back where the velocity solve does,
and does not drive a nearly singular loop along its nearly free motion (docs/conventions.md,
"Post-stabilisation"). A second pass (``Stabilisation.post_stabilisation = 2``) evaluates ``e`` again at the
corrected pose but keeps the step's ``J`` and factor (a chord iteration, no second factorisation): each pass
leaves about ``h |omega|`` of the error, the change of ``J`` over the step (a light slider carrying a swinging
1 kg load, float64: 6.3e-4 m without projection, 2.7e-5 m after one pass, 5.4e-7 m after two). (Under the fixed
penalty PADMM's factor carries ``eta + rho``, 0.1-1: reusing it left 5-20 % of the four-bar's loop error per pass,
measured; docs/conventions.md, "Post-stabilisation".)

An unconverged step: PADMM's residuals bound a converged step's velocity error by the tolerance, so the position
error a pass starts from is at most about ``dt`` times it; a step that ran to ``max_iterations`` has no such bound
(light rows' velocity errors of several ``tolerance`` times ``RESIDUAL_LOOSENING_MAX``), and one pass with the
step's ``J`` left the benchmark four-bar open by up to 1.4e-4 m after such steps. Such a world gets one pass more,
and so does a world whose anchors a converged step's passes left open past ``kamino.config.REPROJECTION_GAP`` (a
foot landing on the Jansen walker; docs/conventions.md, "Post-stabilisation").

Gauss-Newton passes: a chord pass leaves about ``h |omega|`` of its error, and a link that turns 0.5 rad in a step
(a whipping chain) leaves the step's ``J`` so far behind that more chord passes stop helping. A world whose anchors
the extra pass left open past ``REPROJECTION_GAP`` gets up to ``kamino.config.REPROJECTION_PASSES`` passes more,
each with the joint rows' ``J`` evaluated again at the projected pose (the joint-dynamics and coupling rows keep the
step's) and the system factorised again with it, until its gaps are below ``REPROJECTION_GAP``; the other worlds
are left as they are.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
from jax.scipy.linalg import cho_factor, cho_solve

from kamino.config import REPROJECTION_GAP, REPROJECTION_PASSES, SolverConfig, joint_deadband
from kamino.jax_ref.contacts import deadband
from kamino.jax_ref.couplings import coupling_residual
from kamino.jax_ref.dynamics import BodyDynamics, apply_inv_mass, delassus
from kamino.jax_ref.jacobians import constraint_jacobian, constraint_residual, dof_positions, joint_frames
from kamino.jax_ref.types import PaddedModel
from kamino.model import RES_TRANS
from kamino.spatial import integrate_pose


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Projector:
    """The always-active rows' data a projection needs: their Jacobian ``J_f`` (dynamics, joint, coupling
    rows), PADMM's row scaling ``P_f``, the Cholesky factor of ``P_f D_ff P_f + s I``, and the rows' compliance
    ``R_f`` and shifts ``s`` (for the Gauss-Newton passes)."""

    J: jax.Array  # [nf, 6 nb]
    P: jax.Array  # [nf]
    factor: jax.Array  # [nf, nf] lower Cholesky factor
    bodies: BodyDynamics
    R: jax.Array  # [nf] the joint-dynamics rows' compliance (zero on the others)
    shift: jax.Array  # [nf]


def projector(J: jax.Array, D: jax.Array, P: jax.Array, n_fixed: int, bounded: jax.Array, bd: BodyDynamics,
              cfg: SolverConfig, R: jax.Array) -> Projector:
    """The projection's system from the step's ``J``, Delassus ``D`` (with ``R``) and scaling ``P``; ``bounded``
    marks the always-active rows that carry PADMM's larger penalty (the saturated effort-limited rows,
    ``PADMMResult.saturated``); they take the second of ``cfg.projection_shifts()``. ``R`` is the rows' compliance
    (the diagonal ``D`` holds besides ``J M^-1 J^T``)."""
    Pf = P[:n_fixed]
    free_shift, bounded_shift = cfg.projection_shifts(D.dtype)
    shift = jnp.where(bounded[:n_fixed], bounded_shift, free_shift).astype(D.dtype)
    A = Pf[:, None] * D[:n_fixed, :n_fixed] * Pf[None, :] + jnp.diag(shift)
    return Projector(J=J[:n_fixed], P=Pf, factor=cho_factor(A, lower=True)[0], bodies=bd, R=R[:n_fixed], shift=shift)


def fixed_row_residual(pm: PaddedModel, q: jax.Array, delta) -> jax.Array:
    """``e(q)`` of the always-active rows in row order (zero on the joint-dynamics rows), with the joint
    dead band ``delta`` (errors below it are rounding noise on redundant rows, as for the bias; ``None``: none)."""
    band = (lambda x: x) if delta is None else (lambda x: deadband(x, delta))
    jf = joint_frames(pm, q)
    e_kin = jnp.where(pm.row_mask, band(constraint_residual(pm, jf)), 0.0)
    e_cpl = jnp.where(pm.cpl_mask, band(coupling_residual(pm, dof_positions(pm, jf))), 0.0)
    return jnp.concatenate([jnp.zeros(pm.dyn_mask.shape[0], q.dtype), e_kin, e_cpl])


def anchors_open(pm: PaddedModel, e: jax.Array) -> jax.Array:
    """Whether an anchor gap of ``e`` (``fixed_row_residual``: a translational joint row's residual, dead band
    applied) exceeds ``REPROJECTION_GAP`` or is not finite."""
    nd, nr = pm.dyn_mask.shape[0], pm.row_mask.shape[0]
    gap = jnp.where(pm.row_mask & (pm.row_kind == RES_TRANS), jnp.abs(e[nd:nd + nr]), 0.0)
    return ~jnp.all(gap <= REPROJECTION_GAP)


def project(pm: PaddedModel, q: jax.Array, proj: Projector, cfg: SolverConfig, converged: jax.Array) -> jax.Array:
    """``cfg.stabilisation.post_stabilisation`` projection passes of the poses ``q`` [nb, 7], and one more where
    PADMM did not converge (``converged`` False; module docstring, "An unconverged step") or where the passes left
    an anchor gap above ``REPROJECTION_GAP`` (:func:`anchors_open`); then, where that extra pass found the anchors
    open, up to ``REPROJECTION_PASSES`` Gauss-Newton passes while they stay open (:func:`gauss_newton_pass`; module
    docstring). ``cfg.fixed_iterations`` runs every Gauss-Newton pass, selecting (differentiable); otherwise a
    ``while_loop`` runs them, differentiated as the projection onto the joints' manifold that they converge to
    (:func:`_passes_while`; docs/formulation.md §7.10)."""
    delta = joint_deadband(q.dtype)
    for k in range(cfg.stabilisation.post_stabilisation + 1):
        e = fixed_row_residual(pm, q, delta)
        q_next = chord_pass(q, e, proj)
        if k < cfg.stabilisation.post_stabilisation:
            q = q_next
        else:
            open_ = anchors_open(pm, e)
            q = jnp.where(converged & ~open_, q, q_next)
    if not REPROJECTION_PASSES or pm.row_mask.shape[0] == 0:
        return q
    if cfg.fixed_iterations:
        return _passes(pm, q, open_, proj, True)
    return _passes_while(pm, q, open_, proj)


def _passes(pm: PaddedModel, q: jax.Array, open_: jax.Array, proj: Projector, every: bool) -> jax.Array:
    """The Gauss-Newton passes of :func:`project` from the poses ``q`` while the anchors are ``open_``: every one of
    the ``REPROJECTION_PASSES`` passes, selecting (``every``: a ``fori_loop`` with static bounds, differentiable in
    both modes), or only until the anchors close (a ``while_loop``). Both give the same poses: a pass after the
    anchors closed keeps them."""
    delta = joint_deadband(q.dtype)

    def one(carry):
        i, q, open_ = carry
        e = fixed_row_residual(pm, q, delta)
        open_ = open_ & anchors_open(pm, e)
        q = jnp.where(open_, gauss_newton_pass(pm, q, e, proj), q)
        return i + 1, q, open_

    carry = (jnp.int32(0), q, open_)
    if every:
        carry = jax.lax.fori_loop(0, REPROJECTION_PASSES, lambda _, c: one(c), carry)
    else:
        carry = jax.lax.while_loop(lambda c: c[2] & (c[0] < REPROJECTION_PASSES), one, carry)
    return carry[1]


def chord_pass(q: jax.Array, e: jax.Array, proj: Projector) -> jax.Array:
    """One projection of the poses ``q`` [nb, 7] with the residuals ``e`` and the step's system (the module
    docstring): ``q ⊕ d``, ``d = -M^-1 J_f^T P_f (P_f D_ff P_f + s I)^-1 P_f e``."""
    y = cho_solve((proj.factor, True), -proj.P * e)
    d = apply_inv_mass(proj.bodies, (proj.J.T @ (proj.P * y)).reshape(q.shape[0], 6))
    return integrate_pose(q, d, 1.0)


@jax.custom_jvp
def _passes_while(pm: PaddedModel, q: jax.Array, open_: jax.Array, proj: Projector) -> jax.Array:
    """:func:`_passes` with the ``while_loop``. Its derivative: the identity where no pass ran; where passes ran,
    that of the projection onto the manifold ``e(q; pm) = 0`` that they converge to, at the projected poses ``q*``:
    the tangent of one Gauss-Newton pass at ``q*`` with its system (:func:`refactorised` at ``q*``) held fixed and
    no dead band (the projection's derivative does not depend on how small the gaps left are),

        dq* = dq ⊕ (-M^-1 J_f^T P_f (P_f D_ff P_f + s I)^-1 P_f (J_f dq + de/dpm dpm)),    J_f = J_f(q*),

    the ``M``-orthogonal projection of ``dq`` onto the joints' tangent space at ``q*``, moved with the joints'
    geometry ``pm``. It differs from the derivative of the passes as they run by about the gap they start from times
    the joints' curvature, and by the shifts ``s``; the masses move ``q*`` by as little. The passes as they run (the
    selecting ``fori_loop`` of :func:`_passes`, every pass factorised again, each factor differentiated) cost more
    than the rest of a step's derivative."""
    return _passes(pm, q, open_, proj, False)


@_passes_while.defjvp
def _passes_while_jvp(primals, tangents):
    pm, q, open_, proj = primals
    dpm, dq = tangents[0], tangents[1]
    q_out = _passes_while(pm, q, open_, proj)
    system = jax.lax.stop_gradient(refactorised(pm, q_out, proj))
    _, dq_projected = jax.jvp(lambda p, x: chord_pass(x, fixed_row_residual(p, x, None), system), (pm, q_out),
                              (dpm, dq))
    ran = jnp.any(q_out != q)
    return q_out, jnp.where(ran, dq_projected, dq)


def refactorised(pm: PaddedModel, q: jax.Array, proj: Projector) -> Projector:
    """The projection's system with the joint rows' Jacobian evaluated at the poses ``q`` (the joint-dynamics and
    coupling rows keep the step's) and ``P_f (J_f M^-1 J_f^T + R_f) P_f + s I`` factorised again."""
    nb = q.shape[0]
    nd, nk = pm.dyn_mask.shape[0], pm.row_mask.shape[0]
    J_kin = jnp.where(pm.row_mask[:, None], constraint_jacobian(pm, joint_frames(pm, q), nb), proj.J[nd:nd + nk])
    J = proj.J.at[nd:nd + nk].set(J_kin)
    A = proj.P[:, None] * (delassus(J, proj.bodies) + jnp.diag(proj.R)) * proj.P[None, :] + jnp.diag(proj.shift)
    return dataclasses.replace(proj, J=J, factor=cho_factor(A, lower=True)[0])


def gauss_newton_pass(pm: PaddedModel, q: jax.Array, e: jax.Array, proj: Projector) -> jax.Array:
    """One projection of the poses ``q`` [nb, 7] with residuals ``e`` (:func:`fixed_row_residual`) and the system
    :func:`refactorised` at ``q``."""
    return chord_pass(q, e, refactorised(pm, q, proj))
