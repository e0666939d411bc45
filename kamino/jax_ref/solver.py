"""Proximal-ADMM on the dual problem of one world (paper Alg. 1; docs/formulation.md §7-§8.1).

    lambda* = argmin_{x in K} 1/2 x^T D x + x^T (v_f + Gamma(v+(x)))

with the feasible set ``K`` of docs/formulation.md §4.3, extended with bounded rows:

- *box rows* ``[0, n_box)``: ``lo <= lambda <= hi``; bilateral joint rows have ``(-inf, inf)``,
  limit rows ``[0, inf)``, effort-limited actuator rows ``[-dt tau_max, dt tau_max]``;
- *contact rows* ``[n_box, n_box + 3 n_c)``: triples ``(t1, t2, n)`` in the Coulomb cone
  ``||lambda_t|| <= mu lambda_n``, with the De Saxcé correction ``Gamma(v) = (0, 0, mu ||v_t||)``.

The linear system ``(P D P + (eta + rho) I) x = rhs`` is factorised once per step by a dense block
Cholesky (``linear_solve``, §8.1) and reused by every iteration.
"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax.scipy.linalg import cho_solve, solve_triangular

from kamino.config import (
    NULL_DIRECTION_RATIO,
    PENALTY_INTERVAL,
    PENALTY_MAX_FACTOR,
    PENALTY_THRESHOLD,
    RESIDUAL_LOOSENING_MAX,
    RESTART_TOLERANCE,
    RHO_MAX,
    RHO_MIN,
    SATURATION_MARGIN,
    WARM_START_FILTER_SHIFT,
    SolverConfig,
)
from kamino.jax_ref import linear_solve, reduction


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class PADMMResult:
    """Solution (unscaled impulses ``lambda = P y``), constraint velocities and the solve's report."""

    impulse: jax.Array
    velocity: jax.Array  # v+ = D lambda + v_f per row (for contacts without the De Saxcé term)
    iterations: jax.Array
    primal_residual: jax.Array
    dual_residual: jax.Array
    complementarity_residual: jax.Array
    converged: jax.Array
    penalty: jax.Array  # the bounded rows' penalty at the end of the solve (the next step starts from it)
    saturated: jax.Array  # [n] the fixed rows with a finite bound that carried ``penalty.rho`` at the end of the solve


def jacobi_preconditioner(D: jax.Array, row_mask: jax.Array, n_box: int) -> jax.Array:
    """``P = diag(D)^-1/2`` on active rows, 1 on padded rows (docs/formulation.md §7.2, paper).

    A contact gets one scalar for its three rows, from the largest of their diagonal entries, so
    that the scaling keeps the isotropic Coulomb cone invariant (§7.2).
    """
    eps = jnp.finfo(D.dtype).eps
    d = jnp.abs(jnp.diagonal(D))
    tri = d[n_box:].reshape(-1, 3)
    d = jnp.concatenate([d[:n_box], jnp.repeat(jnp.max(tri, axis=1), 3)])
    return jnp.where(row_mask & (d > eps), 1.0 / jnp.sqrt(d + eps), 1.0)


def cone_project(x: jax.Array, mu: jax.Array) -> jax.Array:
    """Projection of triples ``x [n, 3] = (t1, t2, n)`` on the Coulomb cones ``K_mu`` (docs/formulation.md §4.2).

    The polar-cone case is tested first, so ``mu = 0`` and ``x_t = 0`` never divide by zero.
    """
    xt, xn = x[:, :2], x[:, 2]
    s2 = jnp.sum(xt * xt, axis=1)
    s = jnp.sqrt(jnp.where(s2 > 0, s2, 1.0)) * (s2 > 0)
    inside = s <= mu * xn
    polar = mu * s <= -xn
    yn = (mu * s + xn) / (1.0 + mu * mu)
    scale = jnp.where(s > 0, mu * yn / jnp.where(s > 0, s, 1.0), 0.0)
    boundary = jnp.concatenate([xt * scale[:, None], yn[:, None]], axis=1)
    return jnp.where(inside[:, None], x, jnp.where(polar[:, None], 0.0, boundary))


def de_saxce(z: jax.Array, mu: jax.Array, n_box: int) -> jax.Array:
    """``Gamma(z)``: ``mu ||z_t||`` on each contact's normal row, zero elsewhere (docs/formulation.md §4.2)."""
    zc = z[n_box:].reshape(-1, 3)
    nt = jnp.sqrt(jnp.sum(zc[:, :2] ** 2, axis=1) + jnp.finfo(z.dtype).tiny)
    corr = jnp.stack([jnp.zeros_like(nt), jnp.zeros_like(nt), mu * nt], axis=1)
    return jnp.concatenate([jnp.zeros(n_box, z.dtype), corr.reshape(-1)])


def project(x: jax.Array, lo: jax.Array, hi: jax.Array, mu: jax.Array, n_box: int) -> jax.Array:
    """Projection on ``K`` (§7.3 step 3): clip on box rows, Coulomb cone on contact triples."""
    box = jnp.clip(x[:n_box], lo, hi)
    cones = cone_project(x[n_box:].reshape(-1, 3), mu).reshape(-1)
    return jnp.concatenate([box, cones])


def redundant_limits(Dt: jax.Array, vt: jax.Array, lo: jax.Array, hi: jax.Array, row_mask: jax.Array) -> jax.Array:
    """Limit rows whose impulse is zero in a solution: ``True`` where PADMM may fix ``lambda = 0``.

    Works on the scaled problem (``Dt = P D P``, ``vt = P v_f``, §7.2; only signs and ratios are used, and
    ``P > 0`` keeps both). Let ``b`` be the active unbounded box rows (bilateral joint and coupling rows,
    ``lo = -inf``, ``hi = inf``) and ``u`` the active limit rows (``lo = 0``, ``hi = inf``, §4.1). Every solution
    has ``w_b = 0`` (``w = D lambda + v_f``, §7.1), so eliminating ``b`` gives, on every other row ``a``,

        w_a = (S lambda)_a + g~_a,   S = D - D_:b D_bb^-1 D_b:,   g~ = v - D_:b D_bb^-1 v_b,

    (``S`` is the Schur complement of ``D_bb``: the rows' Gram matrix in the ``M^-1`` metric after projecting
    out the span of the bilateral rows). Two limit rows ``t``, ``j`` are *equivalent* when their projected
    rows are parallel, ``rho_tj = S_tj / sqrt(S_tt S_jj) = 1`` (e.g. the hinges of a parallelogram loop:
    ``J_t = c J_j + sum_i c_i J_i``, ``c > 0``): row ``t`` of ``S`` (all columns, contacts included) is then ``c``
    times row ``j``, so with ``g_a = g~_a / sqrt(S_aa)``

        w_t / sqrt(S_tt) = w_j / sqrt(S_jj) + (g_t - g_j)     at every solution.

    If ``g_t > g_j``, ``w_j >= 0`` forces ``w_t > 0`` and complementarity (§4.1) ``lambda_t = 0``. If
    ``g_t = g_j`` the solutions form a family along ``D n = 0`` (``n = e_t - c e_j - sum_i c_i e_i``), and the
    one with ``lambda_t = 0`` is in it (``lambda_j + c lambda_t`` and ``w`` are unchanged along ``n``). So in each
    class of equivalent rows all rows but the one with the smallest ``g`` (ties: the lowest index) are fixed at
    zero: the solution set keeps ``w`` (``D lambda`` is unique for the convex part of the problem) and the
    group's generalised impulse ``sum_t c_t lambda_t``, and loses only the direction ``n`` along which PADMM
    otherwise creeps at the rate of the proximal term. Opposing rows (``rho = -1``, ``c < 0``: both sides of
    a locked mechanism) can bind together and are never fixed.

    Numerics (float64): ``D_bb`` is singular for redundant bilateral rows (planar loops), so it is
    regularised, ``D_bb + delta I`` with ``delta = 1e-10`` (``Dt`` has a unit diagonal); this lowers
    ``rho`` of exactly dependent rows by about ``delta / (2 sigma)``, ``sigma`` the smallest non-zero
    eigenvalue of ``Dt_bb`` (2e-9 on the benchmark four-bar, ``sigma = 0.03``). Rows count as equivalent when
    ``1 - rho <= tau = 1e-7``: exact dependencies are found for ``sigma >= 5e-4`` and rows further apart than
    ``sqrt(2 tau) = 4.5e-4`` rad (in the projected metric) never are. Rows with ``S_aa <= delta`` (a limit on a
    DoF the bilateral rows already lock) are left alone. In float32 the rounding of ``D`` alone puts ``1 - rho``
    of exactly dependent rows near 1e-3, too close to genuinely independent rows: float32 is refused.
    """
    n, n_box = Dt.shape[0], lo.shape[0]
    if Dt.dtype != jnp.float64:
        raise ValueError(f"SolverConfig.redundant_limits needs float64 (got {Dt.dtype}): in float32 equivalent limit "
                         "rows cannot be told from independent ones")
    if n_box == 0:
        return jnp.zeros(n, bool)
    delta, tau = 1e-10, 1e-7
    box = jnp.arange(n) < n_box
    lo_f = jnp.concatenate([lo, jnp.zeros(n - n_box, lo.dtype)])
    hi_f = jnp.concatenate([hi, jnp.zeros(n - n_box, hi.dtype)])
    bil = box & row_mask & jnp.isneginf(lo_f) & jnp.isposinf(hi_f)
    lim = box & row_mask & (lo_f == 0) & jnp.isposinf(hi_f)
    # D_bb + delta I on the bilateral rows, the identity elsewhere (fixed shapes)
    A = jnp.where(bil[:, None] & bil[None, :], Dt, 0.0) + jnp.diag(jnp.where(bil, delta, 1.0))
    rhs = jnp.where(bil[:, None], jnp.concatenate([Dt, vt[:, None]], axis=1), 0.0)
    X = cho_solve((jnp.linalg.cholesky(A), True), rhs)  # [D_bb^-1 D_b:, D_bb^-1 v_b]
    Dcb = jnp.where(bil[None, :], Dt, 0.0)
    S = Dt - Dcb @ X[:, :n]
    g_red = vt - Dcb @ X[:, n]
    S_diag = jnp.diagonal(S)
    ok = lim & (S_diag > delta)
    s = jnp.sqrt(jnp.where(ok, S_diag, 1.0))
    corr = S / (s[:, None] * s[None, :])
    g = g_red / s
    idx = jnp.arange(n)
    worse = (g[:, None] > g[None, :]) | ((g[:, None] == g[None, :]) & (idx[:, None] > idx[None, :]))
    equivalent = ok[:, None] & ok[None, :] & (corr >= 1.0 - tau) & (idx[:, None] != idx[None, :])
    return jnp.any(equivalent & worse, axis=1)


class Carry(NamedTuple):
    """The PADMM loop's state after iteration ``k`` (:func:`solve`; scaled units, §7.3-§7.5)."""

    k: jax.Array  #: iterations done
    x_p: jax.Array  #: the last linear solve's ``x``
    y_p: jax.Array  #: the projected iterate ``y``
    z_p: jax.Array  #: the dual iterate ``z``
    y_hat: jax.Array  #: the extrapolated ``y`` the next iteration starts from (§7.4)
    z_hat: jax.Array  #: the extrapolated ``z``
    a_p: jax.Array  #: the momentum coefficient ``a`` (§7.4)
    c_p: jax.Array  #: the combined residual of the restart test (§7.4)
    r_p: jax.Array  #: primal residual
    r_d: jax.Array  #: dual residual
    r_c: jax.Array  #: complementarity residual
    converged: jax.Array
    rho_u: jax.Array  #: the limit and contact rows' penalty ("Penalty")
    L: tuple  #: the block factor of the scaled system (``linear_solve.factor_tail``)
    k_rho: jax.Array  #: the iteration of the last penalty change or saturation
    e_p: jax.Array  #: the previous iteration's dual residual vector ("Null directions")
    sat: jax.Array  #: the saturated effort-limited rows ("Saturation")
    pending: jax.Array  #: a row saturated: the factor is redone before the next iteration
    vt: jax.Array  #: the scaled right-hand side ``P v_f`` (the refined one once the solve refines)
    hi_v: jax.Array  #: the box rows' scaled upper bounds for ``vt`` (:meth:`_Problem.upper`)
    cap: jax.Array  #: the iteration count at which the current solve stops unconverged
    refined: jax.Array  #: the curvature refinement has restarted the solve (:func:`solve`, ``refine``)
    y_first: jax.Array  #: the first solve's ``y`` once the refinement restarted (the refined ``vt`` depends on it)


class _Problem:
    """One world's PADMM problem in scaled units (docs/formulation.md §7.2-§7.3) and the operations every iteration
    of :func:`solve` uses: the rows' penalties, the shifts of the block factor (``linear_solve``), the projection on
    ``K`` and the complementarity residual. Built while tracing :func:`solve`: its arrays are traced values."""

    def __init__(self, D: jax.Array, v_f: jax.Array, lo: jax.Array, hi: jax.Array, mu: jax.Array,
                 row_mask: jax.Array, cfg: SolverConfig, rho0, n_fixed: int, P=None) -> None:
        dtype = self.dtype = D.dtype
        n = self.n = D.shape[0]
        n_box = self.n_box = lo.shape[0]
        self.cfg, self.mu, self.row_mask, self.lo, self.hi = cfg, mu, row_mask, lo, hi
        self.eta = jnp.asarray(cfg.penalty.eta, dtype)
        # the scaling: D's Jacobi preconditioner unless given (the reduced problem's, _solve_schur)
        P = self.P = jacobi_preconditioner(D, row_mask, n_box) if P is None else P
        self.Dt = P[:, None] * D * P[None, :]
        self.vt = jnp.where(row_mask, P * v_f, 0.0)
        P_ref = jnp.max(jnp.where(row_mask, P, 0.0), initial=0.0)
        P_ref = jnp.where(P_ref > 0, P_ref, 1.0)
        # residual weight of each row (solve's docstring, "Residuals")
        self.W = 1.0 / jnp.minimum(RESIDUAL_LOOSENING_MAX * jnp.where(row_mask & (P > 0), P, P_ref), P_ref)
        adaptive = self.adaptive = cfg.penalty.mode == "adaptive"
        fixed_row = self.fixed_row = jnp.arange(n) < n_fixed
        self.bound_rows = row_mask & ~fixed_row
        # fixed rows with a finite bound (effort-limited actuators): the proximal shift rho_free while the row is
        # inside its box (there it is a bilateral row), the constant rho once saturated (solve's docstring,
        # "Saturation")
        boxed = jnp.concatenate([jnp.isfinite(lo) | jnp.isfinite(hi), jnp.zeros(n - n_box, bool)])
        self.fixed_box = fixed_row & boxed & row_mask
        self.rho0 = jnp.asarray(cfg.penalty.rho if rho0 is None else rho0, dtype)
        self.rho_free = jnp.asarray(cfg.penalty.rho_free if adaptive else cfg.penalty.rho, dtype)
        self.rho_sat = jnp.asarray(cfg.penalty.rho, dtype)
        self.free_row = fixed_row & ~boxed  # the unbounded rows, whose penalty is always the proximal shift rho_free
        # block Cholesky [[L_f, 0], [L_tf, L_t]] of Dt + diag(eta + penalty) (linear_solve): L_f and L_tf do not
        # depend on the limit and contact rows' penalty rho_u, so a new rho_u only redoes L_t = chol(S_t + (eta +
        # rho_u) I) from the tail's Schur complement S_t (the Warp backend's scheme, docs/conventions.md "Penalty");
        # a fixed row that saturates redoes all of it
        self.nf = min(n_fixed, n) if adaptive else 0
        self.n_fixed = min(n_fixed, n)
        finite_lo, finite_hi = self.finite_lo, self.finite_hi = jnp.isfinite(lo), jnp.isfinite(hi)
        # bounds on scaled box rows (P > 0); infinite bounds stay infinite without touching P (no inf*0 in grads)
        self.lo_s = jnp.where(finite_lo, jnp.where(finite_lo, lo, 0.0) / P[:n_box], lo)
        self.hi_s = jnp.where(finite_hi, jnp.where(finite_hi, hi, 0.0) / P[:n_box], hi)
        self.tol = jnp.asarray(cfg.tolerance, dtype)
        self.restart_tol = jnp.asarray(RESTART_TOLERANCE, dtype)
        self.box_bounded = (finite_lo | finite_hi) & row_mask[:n_box]
        self.active_contact = row_mask[n_box:].reshape(-1, 3)[:, 2]

    def penalty(self, rho_u, sat) -> jax.Array:
        """Every row's penalty: the fixed rows' ``rho_free`` (``rho`` when saturated), the others' ``rho_u``."""
        if not self.adaptive:
            return jnp.full(self.n, self.cfg.penalty.rho, self.dtype)
        return jnp.where(self.fixed_row, jnp.where(sat, self.rho_sat, self.rho_free), rho_u)

    def factor_fixed(self, sat) -> tuple:
        """``linear_solve.factor_fixed`` with the fixed rows' shift ``eta + rho_free`` (``rho`` when saturated)."""
        return linear_solve.factor_fixed(self.Dt, self.eta + self.penalty(self.rho0, sat), self.nf)

    def factor(self, fixed, rho_u, sat) -> tuple:
        """``linear_solve.factor_tail`` with the tail rows' shift ``eta + rho_u`` (``eta + rho``: fixed penalty)."""
        nf, n = self.nf, self.n
        if nf == n:  # no tail rows (a host constant: nothing to trace)
            return linear_solve.factor_tail(fixed, np.zeros(0, self.dtype))
        tail = self.penalty(rho_u, sat)[nf:] if self.adaptive else jnp.full(n - nf, self.cfg.penalty.rho, self.dtype)
        return linear_solve.factor_tail(fixed, self.eta + tail)

    def upper(self, vt) -> jax.Array:
        """The box rows' scaled upper bounds; the redundant limit rows get 0 (their lower bound): ``lambda = 0``."""
        if not self.cfg.redundant_limits:
            return self.hi_s
        return jnp.where(redundant_limits(self.Dt, vt, self.lo, self.hi, self.row_mask)[:self.n_box], 0.0, self.hi_s)

    def proj(self, x, hi_v) -> jax.Array:
        """The projection on ``K`` (§4.3) with upper bounds ``hi_v``; zero on padded rows."""
        return jnp.where(self.row_mask, project(x, self.lo_s, hi_v, self.mu, self.n_box), 0.0)

    def natural_residual(self, y, vt, hi_v) -> jax.Array:
        """``F(y) = y - Proj_K(y - (w + Gamma(w)))``, ``w = Dt y + vt``: the natural map of the scaled problem
        (docs/formulation.md §7.10), zero exactly at its solutions (the projection's characterisation of
        ``y in K``, ``w + Gamma(w) in K*``, ``y . (w + Gamma(w)) = 0``). The unit step is the Jacobi scaling
        ``alpha = P^2`` of the unscaled problem, one scalar per contact, so that the cone stays isotropic. Padded
        and inactive rows project to zero: there ``F = y``."""
        w = self.Dt @ y + vt
        return y - self.proj(y - (w + de_saxce(w, self.mu, self.n_box)), hi_v)

    def complementarity(self, y, z) -> jax.Array:
        """``r_c`` (§7.5): the box rows' distance-to-bound times velocity, the contacts' ``|y . z|``."""
        n_box, lo_s, hi_s, finite_lo, finite_hi = self.n_box, self.lo_s, self.hi_s, self.finite_lo, self.finite_hi
        yb, zb = y[:n_box], z[:n_box]
        gap = jnp.minimum(jnp.where(finite_lo, jnp.abs(yb - jnp.where(finite_lo, lo_s, 0.0)), jnp.inf),
                          jnp.where(finite_hi, jnp.abs(jnp.where(finite_hi, hi_s, 0.0) - yb), jnp.inf))
        r_box = jnp.where(self.box_bounded, jnp.abs(zb) * jnp.where(self.box_bounded, gap, 0.0), 0.0)
        yc, zc = y[n_box:].reshape(-1, 3), z[n_box:].reshape(-1, 3)
        r_con = jnp.where(self.active_contact, jnp.abs(jnp.sum(yc * zc, axis=1)), 0.0)
        return jnp.maximum(jnp.max(r_box, initial=0.0), jnp.max(r_con, initial=0.0))

    def filter_warm_start(self, x0, hi_v) -> jax.Array:
        """The warm start without its part along the nearly null directions of the always-active rows' block
        (docs/conventions.md, "Warm start"): ``x_f <- x_f - (Dt_ff + s I)^-1 s x_f`` on the first ``n_fixed`` rows,
        ``s = WARM_START_FILTER_SHIFT``, then projected on ``K`` again. A world whose filter is not finite (a factor
        that rounding broke) keeps its warm start."""
        nf = self.n_fixed
        if nf == 0:
            return x0
        s = jnp.asarray(WARM_START_FILTER_SHIFT, self.dtype)
        L = jnp.linalg.cholesky(self.Dt[:nf, :nf] + s * jnp.eye(nf, dtype=self.dtype))
        t = solve_triangular(L, solve_triangular(L, s * x0[:nf], lower=True), lower=True, trans="T")
        x = self.proj(jnp.concatenate([x0[:nf] - t, x0[nf:]]), hi_v)
        return jnp.where(jnp.all(jnp.isfinite(x[:nf])), x, x0)

    def start(self, impulse0, velocity0) -> Carry:
        """The warm-started first carry (§7.8), with the box rows' upper bounds for ``vt``. Effort-limited rows whose
        warm start lies on a bound (to ``SATURATION_MARGIN`` of it) start saturated."""
        dtype, n, n_box, P, row_mask = self.dtype, self.n, self.n_box, self.P, self.row_mask
        finite_lo, finite_hi, lo_s, hi_s = self.finite_lo, self.finite_hi, self.lo_s, self.hi_s
        hi_v = self.upper(self.vt)
        x0 = self.proj(jnp.where(row_mask, impulse0 / P, 0.0), hi_v)
        z0 = jnp.where(row_mask, P * velocity0, 0.0)
        big = self.big = jnp.asarray(jnp.finfo(dtype).max, dtype)
        self.tiny = jnp.asarray(jnp.finfo(dtype).tiny, dtype)
        self.any_bound = jnp.any(self.bound_rows)
        lo_m = jnp.where(finite_lo, lo_s + SATURATION_MARGIN * jnp.abs(jnp.where(finite_lo, lo_s, 0.0)), lo_s)
        hi_m = jnp.where(finite_hi, hi_s - SATURATION_MARGIN * jnp.abs(jnp.where(finite_hi, hi_s, 0.0)), hi_s)
        on_bound = (finite_lo & (x0[:n_box] <= lo_m)) | (finite_hi & (x0[:n_box] >= hi_m))
        sat0 = self.fixed_box & jnp.concatenate([on_bound, jnp.zeros(n - n_box, bool)])
        if self.cfg.warm_start:
            x0 = self.filter_warm_start(x0, hi_v)
        init = Carry(k=jnp.int32(0), x_p=x0, y_p=x0, z_p=z0, y_hat=x0, z_hat=z0, a_p=jnp.asarray(1.0, dtype),
                     c_p=big, r_p=big, r_d=big, r_c=big, converged=jnp.asarray(False), rho_u=self.rho0,
                     L=self.factor(self.factor_fixed(sat0), self.rho0, sat0), k_rho=jnp.int32(0),
                     e_p=jnp.full(n, big, dtype), sat=sat0, pending=jnp.asarray(False), vt=self.vt, hi_v=hi_v,
                     cap=jnp.int32(self.cfg.max_iterations), refined=jnp.asarray(False), y_first=x0)
        return init


def _iterate(p: _Problem, carry: Carry, inline: bool = True) -> Carry:
    """One PADMM iteration (Alg. 1, §7.3-§7.5). A row that saturates refactorises here (``inline``) or marks the
    carry's ``pending`` for the caller to refactorise (the while loop: under ``vmap`` a ``lax.cond`` runs both
    branches, so an inline refactorisation would cost a factorisation per iteration)."""
    k, x_p, y_p, z_p, y_hat, z_hat, a_p, c_p, _, _, _, _, rho_u, L, k_rho, e_p, sat, pending, vt, hi_v, _, _, _ = carry
    cfg, eta, tol, W, P, big = p.cfg, p.eta, p.tol, p.W, p.P, p.big
    rho = p.penalty(rho_u, sat)
    # step 1-2: De Saxcé correction, linear solve with the cached factor
    s = de_saxce(z_hat, p.mu, p.n_box)
    x = linear_solve.solve(L, -vt - s + eta * x_p + rho * y_hat + z_hat)
    # steps 3-4: projection on K, dual update
    y = p.proj(x - z_hat / rho, hi_v)
    z = jnp.where(p.row_mask, z_hat + rho * (y - x), 0.0)
    # residuals in the energy norm, capped for light rows (solve's docstring, "Residuals")
    r_p = jnp.max(W * jnp.abs(x - y), initial=0.0)
    e = eta * (x - x_p) + rho * (y - y_hat)
    r_d = jnp.max(W * jnp.abs(e), initial=0.0)
    r_c = p.complementarity(y, z)
    converged = (k + 1 >= 2) & (r_p <= tol) & (r_d <= tol) & (r_c <= tol)
    if p.adaptive:
        # or a least-squares solution along a numerically null direction of Dt (solve's docstring, "Null
        # directions")
        free_row = p.free_row
        r_tail = jnp.max(jnp.where(free_row, 0.0, W * jnp.abs(e)), initial=0.0)
        de = jnp.max(jnp.where(free_row, jnp.abs(e - e_p), 0.0), initial=0.0)
        dx = jnp.max(jnp.where(free_row, jnp.abs(x - x_p), 0.0), initial=0.0)
        null = (de <= NULL_DIRECTION_RATIO * (eta + p.rho_free) * dx) & (dx > 0)
        converged |= (k + 1 >= 2) & (r_p <= tol) & (r_tail <= tol) & (r_c <= tol) & null
    # §7.4 Fast ADMM with restart on the combined residual (unscaled units)
    c = jnp.sum(rho * (P * (y - y_hat)) ** 2) + jnp.sum(((z - z_hat) / P) ** 2 / rho)
    if cfg.acceleration:
        keep = c < p.restart_tol * c_p
        a = jnp.where(keep, 0.5 * (1.0 + jnp.sqrt(1.0 + 4.0 * a_p * a_p)), 1.0)
        beta = jnp.where(keep, (a_p - 1.0) / a, 0.0)
        y_hat_n = jnp.where(keep, y + beta * (y - y_p), y_p)
        z_hat_n = jnp.where(keep, z + beta * (z - z_p), z_p)
        c_n = jnp.where(keep, c, c_p / p.restart_tol)
    else:
        a, y_hat_n, z_hat_n, c_n = a_p, y, z, c_p
    if p.adaptive:
        # residual balancing of the bounded rows' penalty; a change refactorises and restarts the momentum
        # a discrete choice: no gradient flows through it (fixed_iterations under jax.grad)
        ratio = jax.lax.stop_gradient(jnp.sqrt((r_p + p.tiny) / (r_d + p.tiny)))
        due = (k + 1 - k_rho >= PENALTY_INTERVAL) & p.any_bound & ~converged
        gain = jnp.clip(ratio, 1.0 / PENALTY_MAX_FACTOR, PENALTY_MAX_FACTOR)
        rho_n = jnp.clip(rho_u * gain, RHO_MIN, RHO_MAX).astype(p.dtype)
        change = due & ((ratio > PENALTY_THRESHOLD) | (ratio * PENALTY_THRESHOLD < 1.0)) & (rho_n != rho_u)
        rho_u = jnp.where(change, rho_n, rho_u)
        # an effort-limited row inside its box whose projection became active saturates: it takes rho from
        # now on, and the whole factor is redone (solve's docstring, "Saturation")
        clipped = jax.lax.stop_gradient(y != x - z_hat / rho)
        hit = p.fixed_box & ~sat & clipped & ~converged
        switch = jnp.any(hit)
        sat = sat | hit
        if inline:
            L = jax.lax.cond(switch, lambda: p.factor(p.factor_fixed(sat), rho_u, sat),
                             lambda: jax.lax.cond(change, lambda: p.factor(L[:3], rho_u, sat), lambda: L))
        else:
            L = jax.lax.cond(change & ~switch, lambda: p.factor(L[:3], rho_u, sat), lambda: L)
            pending = pending | switch
        change = change | switch
        a = jnp.where(change, 1.0, a)
        y_hat_n = jnp.where(change, y, y_hat_n)
        z_hat_n = jnp.where(change, z, z_hat_n)
        c_n = jnp.where(change, big, c_n)
        k_rho = jnp.where(change, k + 1, k_rho)
    return carry._replace(k=k + 1, x_p=x, y_p=y, z_p=z, y_hat=y_hat_n, z_hat=z_hat_n, a_p=a, c_p=c_n, r_p=r_p,
                          r_d=r_d, r_c=r_c, converged=converged, rho_u=rho_u, L=L, k_rho=k_rho, e_p=e, sat=sat,
                          pending=pending)


def _restart(p: _Problem, c: Carry, refine, go) -> Carry:
    """The carry of the refined solve (:func:`solve`, ``refine``) where ``go``, else ``c`` as it is: the right-hand
    side ``vt`` for the impulses ``P y`` of ``c``, its upper bounds, and PADMM restarted from ``c``'s iterate (``x_p``
    kept, ``y_hat = y``, ``z_hat = z``, no momentum) for up to ``cfg.max_iterations`` more iterations."""
    k, y, z, row_mask = c.k, c.y_p, c.z_p, p.row_mask
    vt = jnp.where(row_mask, p.P * refine(jnp.where(row_mask, p.P * y, 0.0)), 0.0)
    hi_v = p.upper(vt)
    if p.cfg.redundant_limits:
        y = p.proj(y, hi_v)  # the set of fixed rows may change with the right-hand side
    restart = c._replace(y_p=y, y_hat=y, z_hat=z, a_p=jnp.asarray(1.0, p.dtype), c_p=p.big,
                         converged=jnp.asarray(False), k_rho=k, vt=vt, hi_v=hi_v, cap=k + p.cfg.max_iterations,
                         refined=jnp.asarray(True), y_first=c.y_p)
    return jax.tree.map(lambda a, b: jnp.where(go, a, b), restart, c)


def _run(p: _Problem, carry: Carry, refine=None, refine_rows=True) -> Carry:
    """Iterations from ``carry`` until the solve converges or reaches ``carry.cap`` iterations; with ``refine``, a
    world whose solve converged unrefined and that has ``refine_rows`` restarts refined (:func:`_restart`) and goes on
    until the refined solve converges or reaches its own cap.

    One ``while_loop`` holds both solves, the refinement in its outer body: that body runs once per factorisation
    (a saturation, the convergence), and under ``vmap``, where a ``lax.cond`` is a select that runs both branches, the
    per-iteration body stays free of the refinement. A world's iterates are those of the two solves run one after
    the other; the worlds of a batch need not be in the same solve at the same time.

    ``cfg.fixed_iterations``: exactly ``cfg.max_iterations`` iterations (a differentiable ``fori_loop``), then, with
    ``refine``, ``cfg.max_iterations`` more from the restart, kept where the first solve converged and the world has
    ``refine_rows``."""
    cfg = p.cfg
    if cfg.fixed_iterations:
        def fixed(c):
            return jax.lax.fori_loop(0, cfg.max_iterations, lambda _, c: _iterate(p, c), c)

        out = fixed(carry)
        if refine is None:
            return out
        go = out.converged & refine_rows
        refined = fixed(_restart(p, out, refine, go))
        return jax.tree.map(lambda a, b: jnp.where(go, a, b), refined, out)

    def refines(c: Carry) -> jax.Array:
        return c.converged & ~c.refined & refine_rows

    def phase(c: Carry) -> Carry:
        # a converged world that refines restarts on the refined right-hand side; then the factor for the rows
        # saturated so far (where a row saturated), then iterations until the solve converges, reaches the cap or
        # another row saturates
        if refine is not None:
            c = _restart(p, c, refine, refines(c))
        L = jax.lax.cond(c.pending, lambda: p.factor(p.factor_fixed(c.sat), c.rho_u, c.sat), lambda: c.L)
        c = c._replace(L=L, pending=jnp.asarray(False))
        return jax.lax.while_loop(lambda c: (~c.converged) & (c.k < c.cap) & ~c.pending,
                                  lambda c: _iterate(p, c, inline=False), c)

    def running(c: Carry) -> jax.Array:
        going = (~c.converged) & (c.k < c.cap)
        return going if refine is None else going | refines(c)

    return jax.lax.while_loop(running, phase, carry)


def solve(D: jax.Array, v_f: jax.Array, lo: jax.Array, hi: jax.Array, mu: jax.Array, row_mask: jax.Array,
          impulse0: jax.Array, velocity0: jax.Array, cfg: SolverConfig, refine=None, rho0=None,
          n_fixed: int = 0, refine_rows=None) -> PADMMResult:
    """Accelerated PADMM with restart (docs/formulation.md §7.3-§7.5) from a warm start, with a penalty per row class.

    ``D`` already holds the regularisation ``R`` of the joint-dynamics rows. ``lo``/``hi`` bound the
    ``n_box = len(lo)`` box rows; the remaining rows are contact triples with friction ``mu``. The first
    ``n_fixed`` rows are the always-active ones (joint-dynamics, joint and coupling rows).
    ``impulse0`` and ``velocity0`` (the latter including the De Saxcé term on contacts) warm-start
    ``x``/``y`` and ``z`` (§7.8). All iterates are scaled (``lambda = P x``, ``v = P^-1 z``).

    **Penalty (departure from §7.6, docs/conventions.md "Penalty").** With ``cfg.penalty.mode = "adaptive"`` the
    fixed rows carry the small constant penalty ``cfg.penalty.rho_free`` (a saturated effort-limited actuator row the
    constant ``cfg.penalty.rho``, "Saturation" below): on a row whose projection is the identity
    the penalty is only a proximal shift, and PADMM on those rows is a proximal-point iteration that removes
    the fraction ``lambda / (lambda + eta + rho)`` of the error along an eigenvalue ``lambda`` of ``D~`` per
    iteration. The limit and contact rows carry ``rho_u``, which starts at ``rho0`` (the world's last
    penalty, else ``cfg.penalty.rho``) and is balanced: every ``PENALTY_INTERVAL`` iterations, if the primal and dual
    residuals differ by more than ``PENALTY_THRESHOLD``, ``rho_u <- rho_u sqrt(r_p / r_d)`` (the factor
    capped at ``PENALTY_MAX_FACTOR`` either way, the penalty clipped to ``[RHO_MIN, RHO_MAX]``), the Cholesky
    factor is recomputed and the momentum restarts. With ``cfg.penalty.mode = "fixed"``
    every row carries ``cfg.penalty.rho`` (§7.6 "fixed").

    **Saturation (adaptive penalty).** An effort-limited actuator row (a fixed row with a finite bound) is a
    bilateral row while its impulse is inside the box, and converges fastest with the proximal shift
    ``rho_free``; once its bound is active it needs ``cfg.penalty.rho``, with which the projection moves it onto the
    bound in a few iterations. So such a row starts the solve saturated (``rho``) when its projected warm start
    lies on a bound (to ``SATURATION_MARGIN`` of it), else with ``rho_free``; at the first iteration whose
    projection clips it (``y != x - z_hat / rho``, the solve not converged) it saturates for the rest of the
    solve: the whole factor is redone and the momentum restarts, as for a new ``rho_u``. Measured on
    dr_legs_joystick under PPO's exploration (CPU, float32, 16 environments x 20 env steps of random actions):
    51.9 -> 20.6 iterations on average on the Warp backend, 51.5 -> 19.9 on this one (docs/conventions.md, "What
    enforcing the effort limit costs"). ``PADMMResult.saturated`` returns the final flags: post-stabilisation
    shifts those rows like PADMM's factor. Under ``vmap`` a switch ends the inner ``while_loop`` and the outer one
    refactorises (a ``lax.cond`` there is a select that would refactorise on every iteration); the Warp backend
    refactorises the worlds that switched after the iteration.

    **Residuals (departure from §7.5).** ``r_p = max_i w_i |x - y|_i`` and ``r_d = max_i w_i |eta (x - x_p) + rho
    (y - y_hat)|_i`` in the scaled variables, with ``w_i = 1 / min(K P_i, P_ref)``: ``P_ref`` is the largest ``P``
    of the world's active rows (its heaviest constrained direction, ``P^2`` being an effective mass) and ``K =
    RESIDUAL_LOOSENING_MAX``. A row's impulse and velocity errors are weighted by the square root of its effective
    mass and expressed as a velocity of the heaviest row (m/s or rad/s), so that light rows (a thin rod's axial
    spin, ``D_ii ~ 1e5``) no longer hold the world to float32 rounding; but a light row's own velocity error stays
    within ``K`` times the tolerance (uncapped, the light rotational rows of a standing dr_legs let it lean by 1 cm
    in 5 s). ``r_c`` (§7.5) is unchanged. ``cfg.fixed_iterations`` runs exactly ``cfg.max_iterations``
    iterations (a ``fori_loop``, differentiable); otherwise a ``while_loop`` stops when ``r_p``, ``r_d`` and
    ``r_c`` are all ``<= cfg.tolerance``.

    **Null directions (float32; adaptive penalty).** On the rows whose penalty is the proximal shift
    ``sigma = eta + rho_free`` (unbounded fixed rows) the dual residual vector ``e = eta (x - x_p) + rho (y -
    y_hat)`` is minus the constraint velocity error ``Dt x + vt`` (the projection is the identity there), so ``e -
    e_p = -Dt (x - x_p)``. When the error no longer responds to the impulse change, ``max |e - e_p| <=
    NULL_DIRECTION_RATIO sigma max |x - x_p|`` (a Rayleigh quotient of the increment below 1e-2 sigma), the
    iterate moves along a numerically null direction of ``Dt``: an eigenvalue that float32 cannot resolve (``Dt``
    has a unit diagonal; the 1e4 mass-ratio pendulum's smallest is 2.8e-8, a four-bar with a hinge tilted by 1° has
    three at 1e-8) or the redundancy of a loop. The error left along it is what no impulse representable in the
    dtype removes; the proximal iteration would only pile impulse up along that direction (``e / sigma`` per
    iteration, carried by the warm start) until its rounding stalls the world. Such an iterate is a least-squares
    solution and counts as converged when the other rows' residuals, the primal and the complementarity residuals
    are below the tolerance (docs/conventions.md, "Null directions").

    ``refine`` (the curvature refinement, ``cfg.stabilisation.curvature_refinement``) maps the impulses of the converged
    solve to a new ``v_f``; PADMM then restarts from its last iterate (``x_p = x``, ``y_hat = y``,
    ``z_hat = z``, no momentum) on the new right-hand side for up to ``cfg.max_iterations`` more iterations. Only a
    world whose first solve converged and that has joint or coupling rows (``refine_rows``, a boolean; ``None``:
    it has) restarts; any other keeps its first solve exactly, whatever the worlds batched with it do.

    **Derivatives.** With ``cfg.fixed_iterations`` ``jax.grad`` differentiates the ``max_iterations`` iterations
    as they run (unrolled). Otherwise the solve is differentiated at its solution by the implicit function theorem on
    the natural map ``F(y) = y - Proj_K(y - (Dt y + vt + Gamma(Dt y + vt)))`` (docs/formulation.md §7.10;
    :func:`_implicit`): the impulses' derivative is ``P dy + dP y`` with ``dy = -(dF/dy)^+ dF/dtheta``
    (:func:`_tangent_solve`), the velocities' that of ``D lambda + v_f``; the values are PADMM's, unchanged, and no
    iteration is stored.

    ``cfg.redundant_limits`` fixes ``lambda = 0`` (bounds ``[0, 0]``) on the limit rows that
    :func:`redundant_limits` finds equivalent to another limit row with a smaller bias (all three hinge
    limits of a parallelogram loop), evaluated again for the refined right-hand side: the solution keeps
    ``v+`` and each group's generalised impulse, and PADMM no longer creeps along the null direction.

    ``cfg.reduction = "schur"`` eliminates the unbounded always-active rows first and runs all of the above on the
    reduced problem (:func:`_solve_schur`, docs/formulation.md §7.11).
    """
    if cfg.reduction == "schur":
        return _solve_schur(D, v_f, lo, hi, mu, row_mask, impulse0, velocity0, cfg, refine, rho0, n_fixed,
                            refine_rows)
    p = _Problem(D, v_f, lo, hi, mu, row_mask, cfg, rho0, n_fixed)
    init = p.start(impulse0, velocity0)
    refine_rows = True if refine_rows is None else refine_rows
    if cfg.fixed_iterations:
        out = _run(p, init, refine, refine_rows)
        y = out.y_p
        v = (out.z_p - de_saxce(out.z_p, mu, p.n_box)) / p.P  # §7.7: v+ = z - Gamma(z), unscaled
    else:
        out, y = _implicit(p, init, refine, refine_rows)
        v = jax.lax.stop_gradient((out.z_p - de_saxce(out.z_p, mu, p.n_box)) / p.P)
        # the derivative of v+ = D lambda + v_f at the solution (the value is PADMM's, unchanged: w - w = 0)
        w = D @ (p.P * y) + v_f
        v = v + (w - jax.lax.stop_gradient(w))
    return _result(out, jnp.where(row_mask, p.P * y, 0.0), jnp.where(row_mask, v, 0.0))


def _result(out: Carry, impulse: jax.Array, velocity: jax.Array) -> PADMMResult:
    """The :class:`PADMMResult` of a solve whose last carry is ``out``, with its unscaled ``impulse`` and
    ``velocity``."""
    return PADMMResult(impulse=impulse, velocity=velocity, iterations=out.k, primal_residual=out.r_p,
                       dual_residual=out.r_d, complementarity_residual=out.r_c, converged=out.converged,
                       penalty=out.rho_u, saturated=out.sat)


def _solve_schur(D: jax.Array, v_f: jax.Array, lo: jax.Array, hi: jax.Array, mu: jax.Array, row_mask: jax.Array,
                 impulse0: jax.Array, velocity0: jax.Array, cfg: SolverConfig, refine, rho0, n_fixed: int,
                 refine_rows) -> PADMMResult:
    """:func:`solve` with ``cfg.reduction = "schur"`` (docs/formulation.md §7.11; :mod:`kamino.jax_ref.reduction`):
    the unbounded always-active rows ``F`` are eliminated with the factor of ``P_F D_FF P_F + eps I``, ``eps = eta +
    rho_free`` (the adaptive penalty's shift on those rows, in either penalty mode), PADMM (penalty rules,
    saturation, warm start, redundant limits, curvature refinement as in :func:`solve`) runs on ``(S, v'_T)`` with the
    rows ``T`` active, scaled by the Jacobi preconditioner of the full ``D`` (§7.2: the scaling the full solve gives
    them), and ``lambda_F = -D_FF^-1 (v_F + D_FT lambda_T)`` is recovered.

    The result has the full row layout: the impulse on every row, the velocity ``D lambda + v_f`` on ``F`` (with the
    refined ``v_f`` where the solve refined) and PADMM's on ``T``; iterations, residuals, convergence, penalty and
    saturated rows are the reduced solve's. The curvature refinement maps the recovered full impulse to a new ``v_f``
    and PADMM restarts on its ``v'_T`` (``S`` is unchanged). The implicit derivative (§7.10) is that of the full
    problem's natural map at the recovered solution: the same as ``reduction = "none"``'s at the same point."""
    # the adaptive penalty's shift on F in either mode: the fixed penalty's eta + rho (0.1) lies above the smallest
    # eigenvalues of a loop's scaled D_FF (0.1 on the loop problem of the tests, 2e-3 on dr_legs), where two refinement
    # steps leave (eps / (sigma + eps))^3 of the solve's error (13 % at 0.1)
    eps = cfg.penalty.eta + cfg.penalty.rho_free
    el = reduction.eliminate(D, reduction.unbounded_rows(lo, hi, row_mask, n_fixed), row_mask, eps)
    t = el.t
    refine_t = None
    if refine is not None:
        def refine_t(lam_t):
            return reduction.reduced_rhs(el, refine(reduction.recover(el, v_f, lam_t)))

    # T scaled by the full D's diagonal, as the full solve scales those rows: diag(S)^-1/2 instead took 1.2x the mean
    # iterations on dr_legs under random PD targets (the slowest world alike) and 3.7x on the loop problem of
    # tests/test_schur_reduction.py
    P_t = jnp.where(t, jacobi_preconditioner(D, row_mask, lo.shape[0]), 1.0)
    p = _Problem(reduction.reduced_matrix(el), reduction.reduced_rhs(el, v_f), lo, hi, mu, t, cfg, rho0, n_fixed,
                 P_t)
    init = p.start(jnp.where(t, impulse0, 0.0), jnp.where(t, velocity0, 0.0))
    refine_rows = True if refine_rows is None else refine_rows

    def full(out: Carry):
        """The full impulses of the first and the last solve, and the last solve's ``v_f``."""
        lam_first = reduction.recover(el, v_f, p.P * out.y_first)
        v_last = v_f if refine is None else jnp.where(out.refined, refine(lam_first), v_f)
        return lam_first, reduction.recover(el, v_last, p.P * out.y_p), v_last

    if cfg.fixed_iterations:
        out = _run(p, init, refine_t, refine_rows)
        _, lam, v_last = full(out)
    else:
        pf = _Problem(D, v_f, lo, hi, mu, row_mask, cfg, rho0, n_fixed)  # the full problem's natural map

        def run():
            out = _run(p, init, refine_t, refine_rows)
            lam_first, lam_last, _ = full(out)
            return out, lam_first / pf.P, lam_last / pf.P

        hi_v = jnp.where(init.hi_v == 0.0, 0.0, pf.hi_s)  # the redundant limit rows the reduced solve fixes
        out, y = _implicit_roots(pf, init, jnp.where(row_mask, impulse0 / pf.P, 0.0), hi_v, run, refine)
        lam = pf.P * y
        v_last = jax.lax.stop_gradient(full(out)[2])
    v_t = (out.z_p - de_saxce(out.z_p, mu, p.n_box)) / p.P  # §7.7 on T
    v = jnp.where(el.f, D @ lam + v_last, v_t)
    if not cfg.fixed_iterations:
        # the derivative of v+ = D lambda + v_f at the solution, as in solve
        w = D @ lam + v_f
        v = jax.lax.stop_gradient(v) + (w - jax.lax.stop_gradient(w))
    return _result(out, jnp.where(row_mask, lam, 0.0), jnp.where(row_mask, v, 0.0))


def tangent_shift(dtype) -> float:
    """The diagonal shift ``delta`` of :func:`_tangent_solve`, relative to the largest diagonal entry of the
    linearised natural map: ``1e-2 sqrt(eps)`` of ``dtype`` (1.5e-10 in float64, 3.5e-6 in float32)."""
    return 1e-2 * float(jnp.finfo(dtype).eps) ** 0.5


def _tangent_solve(g, b: jax.Array) -> jax.Array:
    """``x`` with ``g(x) = b`` for the linearised natural map ``g`` (:func:`_implicit`; docs/formulation.md §7.10):
    with ``A`` the dense Jacobian of ``g`` (a world's rows) and ``A_d = A + delta I`` (``delta`` =
    :func:`tangent_shift` times ``max |A_ii|``), one LU solve and one step of iterative refinement,

        x0 = A_d^-1 b,    x = x0 + A_d^-1 (b - A x0).

    ``A`` is singular along the null directions of ``Dt`` on the active rows (redundant loop rows, four coplanar
    contacts), which move no body (``J^T P n = 0``). Along a direction of ``A`` with singular value ``sigma`` the
    refined ``x`` has the relative error ``(delta / sigma)^2`` (dr_legs: ``sigma >= 1e-4`` off its null space, so
    1e-12 in float64). Along a null direction ``x`` takes the part of ``b`` outside ``A``'s range (rounding) divided
    by ``delta``: it moves no body, so the velocities' derivative ``D P dx`` does not see it, and the impulses along
    a redundant row are not unique. Linear in ``b`` (matrix products and a factor of ``A``), so reverse mode
    transposes it."""
    A = jax.jacfwd(g)(jnp.zeros_like(b))
    delta = tangent_shift(b.dtype) * jnp.max(jnp.abs(jnp.diagonal(A)))
    lu = jax.scipy.linalg.lu_factor(A + delta * jnp.eye(b.shape[0], dtype=b.dtype))
    x = jax.scipy.linalg.lu_solve(lu, b)
    return x + jax.scipy.linalg.lu_solve(lu, b - A @ x)


def _implicit(p: _Problem, init: Carry, refine, refine_rows) -> tuple[Carry, jax.Array]:
    """PADMM (:func:`_run`, ``while_loop``) with the derivative of its solution by the implicit function theorem
    (docs/formulation.md §7.10): returns the final carry (no derivative) and ``y``, equal to the carry's
    ``y_p``, whose derivative with respect to the problem's data ``(Dt, vt, lo, hi, mu)`` is

        dy = -(dF/dy)^+ dF/dtheta,    F(y; theta) = y - Proj_K(y - (Dt y + vt + Gamma(Dt y + vt)))

    (:meth:`_Problem.natural_residual`) at the solution (:func:`_implicit_roots`)."""

    def run():
        out = _run(p, init, refine, refine_rows)
        return out, out.y_first, out.y_p

    return _implicit_roots(p, init, init.y_p, init.hi_v, run, refine)


def _implicit_roots(p: _Problem, init: Carry, guess, hi_v, run, refine) -> tuple[Carry, jax.Array]:
    """The roots of :func:`_implicit` for the problem ``p`` (upper bounds ``hi_v``, starting point ``guess``), found
    by ``run() -> (carry, y_first, y_last)``: a solve whose carry has the structure and dtypes of ``init`` and whose
    solutions ``y_first`` (the first solve's, before a curvature refinement) and ``y_last`` (the last one's) are in
    ``p``'s scaled units. The solve need not be PADMM on ``p`` itself: :func:`_solve_schur` runs it on the reduced
    problem and returns the full layout (§7.11).

    ``jax.lax.custom_root`` with ``(dF/dy)^+`` by the shifted LU solve of :func:`_tangent_solve`. No iteration is
    differentiated: the memory of a gradient does not grow with the iteration count, and the warm start and the
    penalty schedule get no derivative (the solution does not depend on them). With the curvature refinement, the
    refined solve's ``vt`` is ``P refine(P y_1)`` of the first solve's solution ``y_1``, itself a root of ``F`` with
    the first ``vt``: the two roots chain. A solve that stopped at ``max_iterations`` gets the derivative of the root
    the iterate approximates."""

    carry0 = init._replace(L=())
    # custom_root gives its auxiliary outputs integer tangents where JAX expects float0: the carry's integer and
    # boolean fields leave it as floats of the solve's dtype (exact: counts and flags) and are converted back
    kinds = jax.tree.map(lambda a: a.dtype, carry0)

    def solve_root(f, guess):
        out, y_first, y_last = run()
        out = out._replace(L=())
        aux = (jax.tree.map(lambda a: a.astype(p.dtype), out), y_last)
        return jnp.where(out.refined, y_first, y_last), aux

    y1, (out, y_last) = jax.lax.custom_root(lambda y: p.natural_residual(y, p.vt, hi_v), guess, solve_root,
                                            _tangent_solve, has_aux=True)
    out = jax.tree.map(lambda a, dtype: a.astype(dtype), out, kinds)
    if refine is None:
        return out, y1
    row_mask, P = p.row_mask, p.P
    vt2 = jnp.where(row_mask, P * refine(jnp.where(row_mask, P * y1, 0.0)), 0.0)  # as _restart
    hi2 = jnp.where(out.hi_v == 0.0, 0.0, p.hi_s)  # the refined solve's fixed redundant limit rows (p.upper)
    y2 = jax.lax.custom_root(lambda y: p.natural_residual(y, vt2, hi2), y_last, lambda f, guess: y_last,
                             _tangent_solve)
    return out, jnp.where(out.refined, y2, y1)
