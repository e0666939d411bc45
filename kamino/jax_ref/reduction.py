"""Elimination of the unbounded always-active rows before PADMM (``SolverConfig.reduction = "schur"``;
docs/formulation.md §7.11).

The rows of a world split into ``F``, the always-active rows without a bound (bilateral joint, loop-closure and
coupling rows, actuator rows without an effort limit), and ``T``, every other active row (effort-limited actuator
rows, limit rows, contact triples). Every solution has ``w_F = (D lambda + v_f)_F = 0``, so

    lambda_F = -D_FF^-1 (v_F + D_FT lambda_T),                                            (R)
    w_T = S lambda_T + v'_T,   S = D_TT - D_TF D_FF^-1 D_FT,   v'_T = v_T - D_TF D_FF^-1 v_F,   (S)

and PADMM runs on ``(S, v'_T)`` with the bounds and cones of ``T``. ``D_FF`` is singular along the redundant rows of
a loop (a planar loop's out-of-plane rows), so ``D_FF^-1`` is applied through the Jacobi-scaled, shifted factor

    A = P_F D_FF P_F  (unit diagonal, P_F = diag(D_FF)^-1/2),   L L^T = A + eps I,   eps = eta + rho_free,

the shift PADMM itself gives those rows, followed by ``SCHUR_REFINEMENT_STEPS`` steps of iterative refinement
against the unshifted ``A``: ``x_0 = (A + eps I)^-1 b``, ``x_{k+1} = x_k + (A + eps I)^-1 (b - A x_k)``. Along an
eigenvalue ``sigma`` of ``A`` the relative error of ``x_k`` is ``(eps / (sigma + eps))^(k+1)``; the
null eigenvalues of redundant loops (1e-12 on dr_legs) lie far below ``eps = 1.1e-4`` and every other one above it
(``>= 2e-3`` on dr_legs), so the refined solve is exact on the range of ``A`` to float32 rounding and adds along
its null space only the ``(k + 1) / eps`` multiple of the right-hand side's null part, which moves no body.

Shapes stay static under ``jit``/``vmap``: ``F`` and ``T`` are masks, ``A`` is the identity off ``F`` and ``S`` the
identity off ``T`` with a zero right-hand side there, so PADMM keeps those rows at zero.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
from jax.scipy.linalg import cho_solve

from kamino.config import SCHUR_REFINEMENT_STEPS


class Elimination(NamedTuple):
    """The factor of one world's eliminated rows (:func:`eliminate`)."""

    D: jax.Array  #: the full Delassus matrix ``[n, n]`` (with the regularisation ``R``)
    f: jax.Array  #: ``[n]`` the eliminated rows ``F``
    t: jax.Array  #: ``[n]`` the rows PADMM solves, ``T`` (active, not in ``F``)
    s: jax.Array  #: ``[n]`` the Jacobi scaling ``P_F`` on ``F``, 1 elsewhere
    A: jax.Array  #: ``P_F D_FF P_F`` on ``F x F``, zero elsewhere
    L: jax.Array  #: lower Cholesky factor of ``A + eps I`` on ``F`` (the identity elsewhere)


def unbounded_rows(lo: jax.Array, hi: jax.Array, row_mask: jax.Array, n_fixed: int) -> jax.Array:
    """``F``: the active rows among the first ``n_fixed`` (always-active) ones whose bounds are both infinite."""
    n, n_box = row_mask.shape[0], lo.shape[0]
    pad = jnp.zeros(n - n_box, bool)
    free = jnp.concatenate([jnp.isneginf(lo) & jnp.isposinf(hi), pad])
    return (jnp.arange(n) < n_fixed) & free & row_mask


def eliminate(D: jax.Array, f: jax.Array, row_mask: jax.Array, eps) -> Elimination:
    """The scaled block ``A = P_F D_FF P_F`` and the Cholesky factor of ``A + eps I`` (module docstring)."""
    s = jnp.where(f, 1.0 / jnp.sqrt(jnp.where(f, jnp.diagonal(D), 1.0)), 1.0)
    ff = f[:, None] & f[None, :]
    A = jnp.where(ff, s[:, None] * D * s[None, :], 0.0)
    L = jnp.linalg.cholesky(A + jnp.diag(jnp.where(f, jnp.asarray(eps, D.dtype), 1.0)))
    return Elimination(D=D, f=f, t=row_mask & ~f, s=s, A=A, L=L)


def ff_solve(el: Elimination, b: jax.Array) -> jax.Array:
    """``D_FF^-1 b`` on ``F`` (zero elsewhere) for ``b`` of shape ``[n]`` or ``[n, m]``: the shifted factor and
    ``SCHUR_REFINEMENT_STEPS`` refinement steps against the unshifted ``A`` in scaled units,
    ``x = P_F A^-1 P_F b`` (module docstring)."""
    col = (lambda v: v[:, None]) if b.ndim == 2 else (lambda v: v)
    bs = jnp.where(col(el.f), col(el.s) * b, 0.0)
    x = cho_solve((el.L, True), bs)
    for _ in range(SCHUR_REFINEMENT_STEPS):
        x = x + cho_solve((el.L, True), bs - el.A @ x)
    return jnp.where(col(el.f), col(el.s) * x, 0.0)


def reduced_matrix(el: Elimination) -> jax.Array:
    """``S = D_TT - D_TF D_FF^-1 D_FT`` (§7.11 (S)) on ``T x T``, the identity on every other row, symmetrised."""
    f, t, D = el.f, el.t, el.D
    X = ff_solve(el, jnp.where(f[:, None] & t[None, :], D, 0.0))  # D_FF^-1 D_FT
    tt = t[:, None] & t[None, :]
    S = jnp.where(tt, D - jnp.where(f[None, :], D, 0.0) @ X, 0.0)
    S = 0.5 * (S + S.T)
    return S + jnp.diag(jnp.where(t, 0.0, 1.0).astype(D.dtype))


def reduced_rhs(el: Elimination, v_f: jax.Array) -> jax.Array:
    """``v'_T = v_T - D_TF D_FF^-1 v_F`` (§7.11 (S)) on ``T``, zero elsewhere."""
    y = ff_solve(el, v_f)
    return jnp.where(el.t, v_f - jnp.where(el.f[None, :], el.D, 0.0) @ y, 0.0)


def recover(el: Elimination, v_f: jax.Array, lam_t: jax.Array) -> jax.Array:
    """The full impulse: ``lam_t`` on ``T`` and ``lambda_F = -D_FF^-1 (v_F + D_FT lambda_T)`` (§7.11 (R)) on
    ``F``, zero on inactive rows."""
    lt = jnp.where(el.t, lam_t, 0.0)
    lam_f = -ff_solve(el, v_f + el.D @ lt)
    return jnp.where(el.f, lam_f, lt)
