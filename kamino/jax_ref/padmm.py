"""Proximal-ADMM on the dual problem of one world (paper Alg. 1; formulation.md §7-§8.1).

    lambda* = argmin_{x in K} 1/2 x^T D x + x^T v_f

with ``K = R^{n_bilateral} x R_+^{n_unilateral}`` (contact cones arrive with the contacts issue).
The linear system ``(P D P + (eta + rho) I) x = rhs`` is factorised once per step by a dense
Cholesky and reused by every iteration (§8.1).
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
from jax.scipy.linalg import cho_solve

from kamino.config import SolverConfig

ROW_BILATERAL, ROW_UNILATERAL = 0, 1


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class PADMMResult:
    """Solution (unscaled impulses ``lambda = P y``) and the solve's report."""

    impulse: jax.Array
    iterations: jax.Array
    primal_residual: jax.Array
    dual_residual: jax.Array
    complementarity_residual: jax.Array
    converged: jax.Array


def jacobi_preconditioner(D: jax.Array, row_mask: jax.Array, enabled: bool) -> jax.Array:
    """``P = diag(D)^-1/2`` on active rows, 1 on padded rows (formulation.md §7.2, paper)."""
    if not enabled:
        return jnp.ones(D.shape[0], D.dtype)
    eps = jnp.finfo(D.dtype).eps
    d = jnp.abs(jnp.diagonal(D))
    return jnp.where(row_mask & (d > eps), 1.0 / jnp.sqrt(d + eps), 1.0)


def project(x: jax.Array, row_type: jax.Array) -> jax.Array:
    """Projection on ``K``: identity on bilateral rows, ``max(0, .)`` on unilateral rows (§7.3 step 3)."""
    return jnp.where(row_type == ROW_UNILATERAL, jnp.maximum(x, 0.0), x)


def solve(D: jax.Array, v_f: jax.Array, row_type: jax.Array, row_mask: jax.Array, impulse0: jax.Array,
          cfg: SolverConfig) -> PADMMResult:
    """Accelerated PADMM with restart (formulation.md §7.3-§7.5) from the warm start ``impulse0``.

    All iterates are in scaled variables (``lambda = P x``, ``v = P^-1 z``); residuals are reported in
    unscaled units (§7.5). With ``cfg.fixed_iterations`` exactly ``cfg.max_iterations`` iterations run
    (a ``fori_loop``: differentiable with ``jax.grad``); otherwise a ``while_loop`` stops when the
    primal, dual and complementarity residuals are all ``<= cfg.tolerance`` (after >= 2 iterations).
    """
    dtype = D.dtype
    n = D.shape[0]
    eta, rho = jnp.asarray(cfg.eta, dtype), jnp.asarray(cfg.rho, dtype)
    P = jacobi_preconditioner(D, row_mask, cfg.preconditioning)
    Dt = P[:, None] * D * P[None, :]
    vt = jnp.where(row_mask, P * v_f, 0.0)
    L = jnp.linalg.cholesky(Dt + (eta + rho) * jnp.eye(n, dtype=dtype))
    unilateral = (row_type == ROW_UNILATERAL) & row_mask
    tol = jnp.asarray(cfg.tolerance, dtype)
    restart_tol = jnp.asarray(cfg.restart_tolerance, dtype)

    x0 = project(jnp.where(row_mask, impulse0 / P, 0.0), row_type)
    zeros = jnp.zeros_like(x0)
    big = jnp.asarray(jnp.finfo(dtype).max, dtype)
    # carry: k, x_p, y_p, z_p, y_hat, z_hat, a_p, c_p, r_p, r_d, r_c, converged
    init = (jnp.int32(0), x0, x0, zeros, x0, zeros, jnp.asarray(1.0, dtype), big,
            big, big, big, jnp.asarray(False))

    def iterate(carry):
        k, x_p, y_p, z_p, y_hat, z_hat, a_p, c_p, _, _, _, _ = carry
        # step 2 (linear solve with the cached factor), steps 3-4 (projection, dual update)
        x = cho_solve((L, True), -vt + eta * x_p + rho * y_hat + z_hat)
        y = project(x - z_hat / rho, row_type)
        z = z_hat + rho * (y - x)
        # §7.5 residuals in unscaled units
        r_p = jnp.max(jnp.abs(P * (x - y)), initial=0.0)
        r_d = jnp.max(jnp.abs((eta * (x - x_p) + rho * (y - y_hat)) / P), initial=0.0)
        r_c = jnp.max(jnp.where(unilateral, jnp.abs(x * z), 0.0), initial=0.0)
        converged = (k + 1 >= 2) & (r_p <= tol) & (r_d <= tol) & (r_c <= tol)
        if cfg.acceleration:
            # §7.4 Fast ADMM with restart on the combined residual
            c = rho * jnp.sum((P * (y - y_hat)) ** 2) + jnp.sum(((z - z_hat) / P) ** 2) / rho
            keep = c < restart_tol * c_p
            a = jnp.where(keep, 0.5 * (1.0 + jnp.sqrt(1.0 + 4.0 * a_p * a_p)), 1.0)
            beta = jnp.where(keep, (a_p - 1.0) / a, 0.0)
            y_hat_n = jnp.where(keep, y + beta * (y - y_p), y_p)
            z_hat_n = jnp.where(keep, z + beta * (z - z_p), z_p)
            c_n = jnp.where(keep, c, c_p / restart_tol)
        else:
            a, y_hat_n, z_hat_n, c_n = a_p, y, z, c_p
        # a converged world keeps its final iterate: report y (the feasible point) as y_p
        return (k + 1, x, y, z, y_hat_n, z_hat_n, a, c_n, r_p, r_d, r_c, converged)

    if cfg.fixed_iterations:
        out = jax.lax.fori_loop(0, cfg.max_iterations, lambda _, c: iterate(c), init)
    else:
        out = jax.lax.while_loop(
            lambda c: (~c[-1]) & (c[0] < cfg.max_iterations), iterate, init
        )
    k, _, y, _, _, _, _, _, r_p, r_d, r_c, converged = out
    return PADMMResult(
        impulse=jnp.where(row_mask, P * y, 0.0),
        iterations=k,
        primal_residual=r_p,
        dual_residual=r_d,
        complementarity_residual=r_c,
        converged=converged,
    )
