"""Forward kinematics for resets: batched damped Gauss-Newton on the body poses (docs/formulation.md §9).

Unknowns are the poses of all bodies of a world; a step is a twist per body ``delta`` applied with
the exponential map (``integrate_pose(q, delta, 1)``), so the quaternions stay unit and the step is
measured in the tangent space (docs/conventions.md "Forward kinematics" on this departure from the
additive quaternion update of §9). Residual rows, in order:

- the kinematic rows of every joint that is not targeted (``constraint_residual``, §2.3-2.4);
- six fixed-joint rows (``t``, ``Log Q``) per targeted joint, measured against the target relative
  transform ``T* = (t*, Q*)`` built from its coordinates: the follower's joint frame is replaced by
  ``(a_F, X_F) T*^-1``, so the fixed-joint residual reads ``T0^-1 T*``-type errors with the joint
  rows' own Jacobian (§9 "a non-identity offset is folded into Q*");
- one row per joint coupling (``coupling_residual``);
- six rows ``(r - r*, Log(q q*^-1))`` on the base body when a base pose is requested.

Step: ``(J^T J + mu I) delta = -J^T C`` (Cholesky; ``mu`` keeps free directions, e.g. a floating base
without a target or a tie rod's spin, at the initial guess), Armijo line search on ``phi = |C|^2 / 2``
over ``alpha = 1, 1/2, ..., 2^-9``. Large target changes are approached in sub-targets of at most
``max_angle_step`` / ``max_translation_step`` per iteration (§9 "incremental solve"). A world stops when
``max |C| <= tolerance`` at the final target, when its line search fails, or at the iteration budget.
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp

from kamino.jax_ref.couplings import coupling_jacobian, coupling_residual
from kamino.jax_ref.jacobians import (
    constraint_jacobian,
    constraint_residual,
    dof_jacobian,
    dof_positions,
    joint_coordinates,
    joint_frames,
)
from kamino.jax_ref.precision import full_precision
from kamino.jax_ref.types import PaddedModel
from kamino.model import JointType
from kamino.spatial import integrate_pose, quat_conj, quat_exp, quat_log, quat_mul, rotate

_ALPHAS = tuple(0.5**k for k in range(10))
_ARMIJO = 1e-4
_RHO_MAX = 1e8
_MU_MAX = 1e2
_IK_ALPHAS = tuple(0.5**k for k in range(6))


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class FKTables:
    """Per-world FK row structure (padded, leading axis world), built on the host per model and mode."""

    row_joint: jax.Array  # [W, nr]
    row_axis: jax.Array
    row_kind: jax.Array
    row_mask: jax.Array
    targeted: jax.Array  # [W, nj] bool
    base_body: jax.Array  # [W] local body index (-1: none)


@dataclasses.dataclass(frozen=True)
class FKSettings:
    """Solver settings (static under ``jit``): stop at ``max |C| <= tolerance`` or after
    ``max_iterations`` beyond the sub-target stages; ``damping`` is ``mu`` relative to ``1 + max diag
    J^T J``, never below ``10 eps`` of the dtype (1.2e-6 in float32: below that, rounding of ``J^T J`` leaves a
    floating base's free directions indefinite); sub-targets move at most ``max_angle_step`` [rad] /
    ``max_translation_step`` [m]."""

    tolerance: float = 1e-6
    max_iterations: int = 30
    damping: float = 1e-9
    max_angle_step: float = 0.17453292519943295  # 10 degrees
    max_translation_step: float = 0.05


def target_transform(jtype: jax.Array, c: jax.Array) -> tuple[jax.Array, jax.Array]:
    """Relative transform ``(t*, Q*)`` of a joint from its packed coordinates ``c [nj, 7]``: the inverse
    of ``joints.joint_coordinates`` (REVOLUTE ``Rx(angle)``; PRISMATIC ``t = (d, 0, 0)``; CYLINDRICAL
    both; UNIVERSAL ``Rx(theta_1) Ry(theta_2)``; SPHERICAL ``Q``; CARTESIAN ``t``; FREE ``(t, Q)``)."""
    z = jnp.zeros_like(c[:, 0])
    one = jnp.ones_like(z)

    def axis_quat(angle, k):
        v = [z, z, z]
        v[k] = jnp.sin(0.5 * angle)
        return jnp.stack([*v, jnp.cos(0.5 * angle)], -1)

    ident = jnp.stack([z, z, z, one], -1)
    zero3 = jnp.zeros_like(c[:, :3])
    tx = jnp.stack([c[:, 0], z, z], -1)
    table = {
        JointType.REVOLUTE: (zero3, axis_quat(c[:, 0], 0)),
        JointType.PRISMATIC: (tx, ident),
        JointType.CYLINDRICAL: (tx, axis_quat(c[:, 1], 0)),
        JointType.UNIVERSAL: (zero3, quat_mul(axis_quat(c[:, 0], 0), axis_quat(c[:, 1], 1))),
        JointType.SPHERICAL: (zero3, c[:, 0:4]),
        JointType.CARTESIAN: (c[:, 0:3], ident),
        JointType.FREE: (c[:, 0:3], c[:, 3:7]),
    }
    t, Q = zero3, ident
    for jt, (tt, qq) in table.items():
        sel = (jtype == int(jt))[:, None]
        t, Q = jnp.where(sel, tt, t), jnp.where(sel, qq, Q)
    Q = Q / jnp.linalg.norm(Q, axis=-1, keepdims=True)
    return t, Q


def _interpolate(jtype, c0, c1, p):
    """Coordinates a fraction ``p`` of the way from ``c0`` to ``c1``: linear, quaternions by slerp."""
    lin = c0 + p * (c1 - c0)
    out = lin
    for jt, k in ((JointType.SPHERICAL, 0), (JointType.FREE, 3)):
        q0, q1 = c0[:, k:k + 4], c1[:, k:k + 4]
        qp = quat_mul(q0, quat_exp(p * quat_log(quat_mul(quat_conj(q0), q1))))
        out = jnp.where((jtype == int(jt))[:, None], out.at[:, k:k + 4].set(qp), out)
    return out


def _stages(jtype, targeted, c0, c1, base_from, base_to, has_base, s: FKSettings):
    """Number of sub-targets so that no coordinate moves more than the step limits per iteration."""
    d = jnp.abs(c1 - c0)
    ang = jnp.zeros_like(d[:, 0])
    lin = jnp.zeros_like(d[:, 0])
    rot_angle = lambda q0, q1: jnp.linalg.norm(quat_log(quat_mul(quat_conj(q0), q1)), axis=-1)  # noqa: E731
    for jt, a_cols, l_cols in ((JointType.REVOLUTE, [0], []), (JointType.PRISMATIC, [], [0]),
                               (JointType.CYLINDRICAL, [1], [0]), (JointType.UNIVERSAL, [0, 1], []),
                               (JointType.CARTESIAN, [], [0, 1, 2]), (JointType.FREE, [], [0, 1, 2])):
        sel = jtype == int(jt)
        if a_cols:
            ang = jnp.where(sel, jnp.max(d[:, a_cols], axis=-1), ang)
        if l_cols:
            lin = jnp.where(sel, jnp.max(d[:, l_cols], axis=-1), lin)
    ang = jnp.where(jtype == int(JointType.SPHERICAL), rot_angle(c0[:, 0:4], c1[:, 0:4]), ang)
    ang = jnp.where(jtype == int(JointType.FREE), rot_angle(c0[:, 3:7], c1[:, 3:7]), ang)
    need = jnp.maximum(ang / s.max_angle_step, lin / s.max_translation_step)
    need = jnp.max(jnp.where(targeted, need, 0.0), initial=0.0)
    base_need = jnp.maximum(rot_angle(base_from[3:], base_to[3:]) / s.max_angle_step,
                            jnp.linalg.norm(base_to[:3] - base_from[:3]) / s.max_translation_step)
    need = jnp.maximum(need, jnp.where(has_base, base_need, 0.0))
    return jnp.maximum(jnp.ceil(need), 1.0)


def _with_targets(pm: PaddedModel, tab, t_star, Q_star) -> PaddedModel:
    """``pm`` with the FK rows and the targeted joints' follower frames replaced by ``(a_F, X_F) T*^-1``."""
    Qi = quat_conj(Q_star)
    frame_F = quat_mul(pm.frame_F, Qi)
    anchor_F = pm.anchor_F - rotate(frame_F, t_star)
    sel = tab.targeted[:, None]
    return dataclasses.replace(pm, row_joint=tab.row_joint, row_axis=tab.row_axis, row_kind=tab.row_kind,
                               row_mask=tab.row_mask, anchor_F=jnp.where(sel, anchor_F, pm.anchor_F),
                               frame_F=jnp.where(sel, frame_F, pm.frame_F))


def _residual_and_jacobian(pm, pm_t, tab, q, base_target, with_jacobian: bool):
    nb = q.shape[0]
    jf_t = joint_frames(pm_t, q)
    jf = joint_frames(pm, q)
    q_dof = dof_positions(pm, jf)
    C = [constraint_residual(pm_t, jf_t), coupling_residual(pm, q_dof)]
    has_base = tab.base_body >= 0
    b = jnp.maximum(tab.base_body, 0)
    rot_err = quat_log(quat_mul(q[b, 3:], quat_conj(base_target[3:])))
    C.append(jnp.where(has_base, jnp.concatenate([q[b, :3] - base_target[:3], rot_err]), 0.0))
    C = jnp.concatenate(C)
    if not with_jacobian:
        return C, None
    J_base = jnp.zeros((6, nb, 6), q.dtype).at[jnp.arange(6), b, jnp.arange(6)].set(jnp.where(has_base, 1.0, 0.0))
    J = jnp.concatenate([constraint_jacobian(pm_t, jf_t, nb),
                         coupling_jacobian(pm, q_dof, dof_jacobian(pm, jf, nb)),
                         J_base.reshape(6, nb * 6)])
    return C, J


def solve_world(pm: PaddedModel, tab: FKTables, q_init, coords, base_target, s: FKSettings):
    """Gauss-Newton FK of one world. ``coords [nj, 7]`` are the targets of the targeted joints,
    ``base_target [7]`` the base pose (ignored without a base). Returns ``(q, converged, residual,
    iterations)``."""
    nb = q_init.shape[0]
    dtype = q_init.dtype
    jtype = pm.joint_type
    c0 = joint_coordinates(pm, joint_frames(pm, q_init))
    has_base = tab.base_body >= 0
    base_from = q_init[jnp.maximum(tab.base_body, 0)]
    n_stages = _stages(jtype, tab.targeted, c0, coords, base_from, base_target, has_base, s)
    eye = jnp.eye(nb * 6, dtype=dtype)

    def targets(it):
        p = jnp.minimum((it + 1.0) / n_stages, 1.0)
        c = _interpolate(jtype, c0, coords, p)
        t_star, Q_star = target_transform(jtype, c)
        rot = quat_mul(base_from[3:], quat_exp(p * quat_log(quat_mul(quat_conj(base_from[3:]), base_target[3:]))))
        base = jnp.concatenate([base_from[:3] + p * (base_target[:3] - base_from[:3]), rot])
        return _with_targets(pm, tab, t_star, Q_star), base, p

    def phi(pm_t, q, base):
        C, _ = _residual_and_jacobian(pm, pm_t, tab, q, base, False)
        return 0.5 * jnp.sum(C * C), jnp.max(jnp.abs(C), initial=0.0)

    def body(carry):
        q, it, _, _, _ = carry
        pm_t, base, p = targets(it)
        C, J = _residual_and_jacobian(pm, pm_t, tab, q, base, True)
        g = J.T @ C
        A = J.T @ J
        # the relative shift never below rounding of A's entries: a floating base without a target leaves six
        # null directions, which float32 rounding of J^T J would otherwise make indefinite (NaN step)
        mu = max(s.damping, 10.0 * float(jnp.finfo(dtype).eps))
        A = A + (mu * (1.0 + jnp.max(jnp.diag(A)))) * eye
        delta = -jax.scipy.linalg.cho_solve(jax.scipy.linalg.cho_factor(A), g)
        phi0 = 0.5 * jnp.sum(C * C)
        slope = g @ delta
        alphas = jnp.asarray(_ALPHAS, dtype)
        cand = jax.vmap(lambda a: integrate_pose(q, (a * delta).reshape(nb, 6), 1.0))(alphas)
        phis, cmax = jax.vmap(lambda qq: phi(pm_t, qq, base))(cand)
        ok = jnp.isfinite(phis) & (phis <= phi0 + _ARMIJO * alphas * slope)
        k = jnp.argmax(ok)
        accepted = jnp.any(ok)
        q_new = jnp.where(accepted, cand[k], q)
        res = jnp.where(accepted, cmax[k], jnp.max(jnp.abs(C), initial=0.0))
        done = (p >= 1.0) & (res <= s.tolerance)
        stalled = ~accepted & (res > s.tolerance)
        return q_new, it + 1.0, res, done, stalled

    def cond(carry):
        _, it, _, done, stalled = carry
        return (~done) & (~stalled) & (it < s.max_iterations + n_stages)

    pm0, base0, _ = targets(n_stages - 1.0)  # the final targets
    _, r0 = phi(pm0, q_init, base0)
    init = (q_init, jnp.asarray(0.0, dtype), r0, (n_stages <= 1.0) & (r0 <= s.tolerance), jnp.asarray(False))
    q, it, _, _, _ = jax.lax.while_loop(cond, body, init)
    _, res = phi(pm0, q, base0)
    return q, res <= s.tolerance, res, it


@functools.partial(jax.jit, static_argnames=("settings",))
@full_precision
def solve_batch(pm: PaddedModel, tab: FKTables, q_init, coords, base_target, settings: FKSettings):
    """``solve_world`` vmapped over worlds (padded arrays, leading axis world)."""
    return jax.vmap(solve_world, in_axes=(0, 0, 0, 0, 0, None))(pm, tab, q_init, coords, base_target, settings)


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class IKTargets:
    """Task-space targets of one world (leading axis world when batched), ``k`` per world: the point ``offset``
    (body CoM frame) of body ``body`` (world-local index) at ``position`` (world), the body's orientation at
    ``orientation`` (``x, y, z, w``), with weights (``0``: that row is not a target)."""

    body: jax.Array  # [k] int32
    offset: jax.Array  # [k, 3]
    position: jax.Array  # [k, 3]
    orientation: jax.Array  # [k, 4]
    position_weight: jax.Array  # [k]
    orientation_weight: jax.Array  # [k]


@dataclasses.dataclass(frozen=True)
class IKSettings:
    """Inverse-kinematics settings (static under ``jit``): stop when the closure, the joint limits and the targets
    hold to ``tolerance``, or when a step moves no body by more than ``step_tolerance`` (a stationary point: an
    unreachable target), or after ``max_iterations``; ``regularization`` weighs ``|q - q_ref|^2 / 2``; ``damping`` is
    the starting Levenberg-Marquardt ``mu`` (relative to ``1 + max diag A``; divided by 10 after a full step, kept
    after a half step, multiplied by 10 after a shorter one or a failed line search); a step rotates no body by more
    than ``max_angle_step`` [rad] nor moves it by more than ``max_translation_step`` [m] (scaled down as a whole)."""

    tolerance: float = 1e-6
    max_iterations: int = 100
    regularization: float = 0.0
    damping: float = 1e-4
    step_tolerance: float = 1e-12
    max_angle_step: float = 0.5
    max_translation_step: float = 0.1


def _pose_error(q, q_star):
    """``(r - r*, Log(q q*^-1))`` per pose ``[..., 6]``: the error whose derivative along the step of
    ``integrate_pose`` is the identity at ``q = q*``."""
    return jnp.concatenate([q[..., :3] - q_star[..., :3], quat_log(quat_mul(q[..., 3:], quat_conj(q_star[..., 3:])))],
                           axis=-1)


def ik_target_residual(q, tg: IKTargets):
    """Weighted target rows ``[6k]`` — per target ``w_p (r_b + R_b o - p*)`` and ``w_R Log(q_b q*^-1)`` — and the
    unweighted errors ``(|p - p*| [k], rotation angle [k])``."""
    qb = q[tg.body]
    arm = rotate(qb[:, 3:], tg.offset)
    e_p = qb[:, :3] + arm - tg.position
    e_r = quat_log(quat_mul(qb[:, 3:], quat_conj(tg.orientation)))
    T = jnp.concatenate([tg.position_weight[:, None] * e_p, tg.orientation_weight[:, None] * e_r], -1)
    return T.reshape(-1), jnp.linalg.norm(e_p, axis=-1), jnp.linalg.norm(e_r, axis=-1), arm


def ik_target_jacobian(nb: int, tg: IKTargets, arm):
    """``[6k, nb*6]``: ``d(r_b + R_b o) = v_b - [R_b o]x w_b`` and ``d Log(q_b q*^-1) = w_b`` (exact at the target)
    for the twist ``(v_b, w_b)`` of ``integrate_pose``, times the rows' weights."""
    k = arm.shape[0]
    eye = jnp.eye(3, dtype=arm.dtype)
    skew = jnp.cross(arm[:, :, None], eye[None, :, :], axis=1)  # [k, 3, 3]: skew(arm) @ e_j = arm x e_j
    pos = jnp.concatenate([jnp.broadcast_to(eye, (k, 3, 3)), -skew], -1) * tg.position_weight[:, None, None]
    rot = jnp.concatenate([jnp.zeros((k, 3, 3), arm.dtype), jnp.broadcast_to(eye, (k, 3, 3))], -1)
    rot = rot * tg.orientation_weight[:, None, None]
    blocks = jnp.concatenate([pos, rot], 1)  # [k, 6, 6]
    J = jnp.zeros((k, 6, nb, 6), arm.dtype).at[jnp.arange(k), :, tg.body, :].set(blocks)
    return J.reshape(k * 6, nb * 6)


def _limit_rows(pm: PaddedModel, q_dof, J_dof, active_hi, active_lo):
    """Rows ``q_d - bound`` (and their Jacobian) of the active joint limits; inactive rows are zero."""
    r = jnp.where(active_hi, q_dof - pm.dof_upper, jnp.where(active_lo, q_dof - pm.dof_lower, 0.0))
    on = active_hi | active_lo
    return r, J_dof * on[:, None]


def ik_world(pm: PaddedModel, tab: FKTables, q_init, q_ref, tg: IKTargets, base_target, s: IKSettings):
    """Loop-aware inverse kinematics of one world (docs/formulation.md §9 "Inverse kinematics"): Gauss-Newton SQP on

    ``min 1/2 |T(q)|^2 + lambda/2 |q - q_ref|^2``  subject to  ``C(q) = 0``, ``lower <= q_dof <= upper``,

    ``T`` the weighted target rows, ``C`` the joint, loop-closure, coupling (and pinned-base) rows of forward
    kinematics with no joint targeted. Step: ``A = J_T^T J_T + (lambda + mu) I``, ``g = J_T^T T + lambda e_ref``,
    ``[A J_C^T; J_C -eps I] [delta; nu] = [-g; -C]`` through the Schur complement ``J_C A^-1 J_C^T + eps I``
    (two Cholesky factorisations). Joint limits are an active set of equality rows ``q_d = bound``: a limit is
    active when the DoF lies beyond it (by more than ``tolerance / 2``). Armijo line search on
    ``f + rho/2 |C|^2`` (the limit violations counted in ``C``) with ``rho`` large enough for descent.
    Returns ``(q, closure, target_position_error, target_angle_error, within_limits, iterations)``."""
    nb = q_init.shape[0]
    dtype = q_init.dtype
    lam = s.regularization
    mu_min = 10.0 * float(jnp.finfo(dtype).eps)
    eps_S = max(FKSettings.damping, mu_min)  # the Schur complement's shift: redundant rows (a planar loop's)
    eye = jnp.eye(nb * 6, dtype=dtype)
    pm_c = _with_targets(pm, tab, jnp.zeros_like(pm.anchor_F), pm.frame_F)  # nothing targeted: the rows only
    has_lim = jnp.isfinite(pm.dof_lower) | jnp.isfinite(pm.dof_upper)
    lim_tol = 0.5 * s.tolerance

    def evaluate(q):
        C, _ = _residual_and_jacobian(pm, pm_c, tab, q, base_target, False)
        jf = joint_frames(pm, q)
        q_dof = dof_positions(pm, jf)
        over = jnp.where(pm.dof_mask, jnp.maximum(q_dof - pm.dof_upper, 0.0) + jnp.maximum(pm.dof_lower - q_dof, 0.0),
                         0.0)
        T, ep, er, _ = ik_target_residual(q, tg)
        e_ref = _pose_error(q, q_ref)
        f = 0.5 * jnp.sum(T * T) + 0.5 * lam * jnp.sum(e_ref * e_ref)
        viol = jnp.concatenate([C, over])
        return f, 0.5 * jnp.sum(viol * viol), jnp.max(jnp.abs(C), initial=0.0), jnp.max(over, initial=0.0), ep, er

    def body(carry):
        q, it, _, _, _, mu = carry
        C, J_C = _residual_and_jacobian(pm, pm_c, tab, q, base_target, True)
        jf = joint_frames(pm, q)
        q_dof = dof_positions(pm, jf)
        J_dof = dof_jacobian(pm, jf, nb)
        T, _, _, arm = ik_target_residual(q, tg)
        J_T = ik_target_jacobian(nb, tg, arm)
        e_ref = _pose_error(q, q_ref).reshape(-1)
        # J_C^T J_C in the Hessian leaves delta unchanged (it shifts nu by C) and keeps A, and with it the Schur
        # complement, well scaled where the targets leave directions free
        A = J_T.T @ J_T + J_C.T @ J_C + lam * eye
        A = A + (mu * (1.0 + jnp.max(jnp.diag(A)))) * eye
        g = J_T.T @ T + lam * e_ref
        cho = jax.scipy.linalg.cho_factor(A)
        Ainv_g = jax.scipy.linalg.cho_solve(cho, g)
        valid = pm.dof_mask & has_lim

        def step(active_hi, active_lo):
            r_l, J_l = _limit_rows(pm, q_dof, J_dof, active_hi & valid, active_lo & valid)
            Jc = jnp.concatenate([J_C, J_l])
            AJ = jax.scipy.linalg.cho_solve(cho, Jc.T)
            S = Jc @ AJ
            S = S + (eps_S * (1.0 + jnp.max(jnp.diag(S)))) * jnp.eye(S.shape[0], dtype=dtype)
            S_cho = jax.scipy.linalg.cho_factor(S)
            nu = jax.scipy.linalg.cho_solve(S_cho, jnp.concatenate([C, r_l]) - Jc @ Ainv_g)
            return -(Ainv_g + AJ @ nu), AJ, S_cho

        def step_scale(d):
            d6 = d.reshape(nb, 6)
            return jnp.maximum(jnp.max(jnp.linalg.norm(d6[:, 3:], axis=-1)) / s.max_angle_step,
                               jnp.max(jnp.linalg.norm(d6[:, :3], axis=-1)) / s.max_translation_step)

        hi1, lo1 = q_dof > pm.dof_upper + lim_tol, q_dof < pm.dof_lower - lim_tol
        delta, AJ, S_cho = step(hi1, lo1)
        scale = step_scale(delta)
        delta = delta / jnp.maximum(scale, 1.0)
        f0, v0, _, _, _, _ = evaluate(q)
        # directional derivatives of f and of |C|^2 / 2 (limit violations included) along delta
        slope_f = g @ delta
        dq = J_dof @ delta
        over_hi = jnp.where(pm.dof_mask, jnp.maximum(q_dof - pm.dof_upper, 0.0), 0.0)
        over_lo = jnp.where(pm.dof_mask, jnp.maximum(pm.dof_lower - q_dof, 0.0), 0.0)
        slope_c = C @ (J_C @ delta) + over_hi @ dq - over_lo @ dq
        # the penalty makes delta a descent direction of the merit where the closure error allows (at most _RHO_MAX)
        rho = jnp.clip(2.0 * slope_f / jnp.maximum(-slope_c, jnp.finfo(dtype).tiny), 1.0, _RHO_MAX)
        slope = slope_f + rho * slope_c
        alphas = jnp.asarray(_IK_ALPHAS, dtype)

        def corrected(a):
            # second-order correction (against the Maratos effect): the trial point moved back to the linearised
            # constraints, ``delta_r = -A^-1 J_c^T S^-1 c(q + a delta)``, on the same factorisations
            qa = integrate_pose(q, (a * delta).reshape(nb, 6), 1.0)
            Ca, _ = _residual_and_jacobian(pm, pm_c, tab, qa, base_target, False)
            qd = dof_positions(pm, joint_frames(pm, qa))
            r_l, _ = _limit_rows(pm, qd, J_dof, hi1 & valid, lo1 & valid)
            d_r = -AJ @ jax.scipy.linalg.cho_solve(S_cho, jnp.concatenate([Ca, r_l]))
            return integrate_pose(qa, d_r.reshape(nb, 6), 1.0)

        plain = jax.vmap(lambda a: integrate_pose(q, (a * delta).reshape(nb, 6), 1.0))(alphas)
        # candidates in the order tried: each step length plain, then corrected
        cand = jnp.stack([plain, jax.vmap(corrected)(alphas)], 1).reshape(2 * len(_IK_ALPHAS), nb, 7)
        alphas = jnp.repeat(alphas, 2)
        fs, vs, cl, ov, eps_, ers = jax.vmap(evaluate)(cand)
        m0 = f0 + rho * v0
        ms = fs + rho * vs
        ok = jnp.isfinite(ms) & (ms <= m0 + _ARMIJO * alphas * jnp.minimum(slope, 0.0))
        k = jnp.argmax(ok)
        accepted = jnp.any(ok)
        q_new = jnp.where(accepted, cand[k], q)
        moved = alphas[k] * jnp.max(jnp.abs(delta), initial=0.0)
        done = accepted & _finished(cl[k], ov[k], eps_[k], ers[k])
        # Levenberg-Marquardt update of the damping: down after a full step, kept after a half step, up after a step
        # cut further or none. Raising it after every cut step ratchets it up while the iteration restores a closure
        # that a long step opened (half steps, several in a row): from float32's floor (1.2e-6) eight such steps reach
        # the cap, where steps are too short to converge and the world stops at a failed line search
        mu_new = jnp.clip(jnp.where(accepted & (alphas[k] >= 1.0), mu / 10.0,
                                    jnp.where(accepted & (alphas[k] >= 0.5), mu, mu * 10.0)), mu_min, _MU_MAX)
        return q_new, it + 1.0, ~accepted & (mu >= _MU_MAX), accepted & (moved <= s.step_tolerance), done, mu_new

    def _finished(closure, over, ep, er):
        return ((closure <= s.tolerance) & (over <= s.tolerance)
                & (jnp.max(jnp.where(tg.position_weight > 0, ep, 0.0), initial=0.0) <= s.tolerance)
                & (jnp.max(jnp.where(tg.orientation_weight > 0, er, 0.0), initial=0.0) <= s.tolerance))

    def cond(carry):
        _, it, failed, still, done, _ = carry
        return (~failed) & (~still) & (it < s.max_iterations) & (~done)

    _, _, cl0, ov0, ep0, er0 = evaluate(q_init)
    init = (q_init, jnp.asarray(0.0, dtype), jnp.asarray(False), jnp.asarray(False), _finished(cl0, ov0, ep0, er0),
            jnp.asarray(max(s.damping, mu_min), dtype))
    q, it, _, _, _, _ = jax.lax.while_loop(cond, body, init)
    _, _, closure, over, ep, er = evaluate(q)
    ep = jnp.max(jnp.where(tg.position_weight > 0, ep, 0.0), initial=0.0)
    er = jnp.max(jnp.where(tg.orientation_weight > 0, er, 0.0), initial=0.0)
    return q, closure, ep, er, over <= s.tolerance, it


@functools.partial(jax.jit, static_argnames=("settings",))
@full_precision
def ik_batch(pm: PaddedModel, tab: FKTables, q_init, q_ref, targets: IKTargets, base_target, settings: IKSettings):
    """``ik_world`` vmapped over worlds (padded arrays, leading axis world)."""
    return jax.vmap(ik_world, in_axes=(0, 0, 0, 0, 0, 0, None))(pm, tab, q_init, q_ref, targets, base_target,
                                                                 settings)
