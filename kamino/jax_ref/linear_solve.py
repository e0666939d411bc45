"""The linear solve of PADMM: a dense block Cholesky of the shifted, scaled Delassus matrix (docs/formulation.md §8.1;
the Warp backend's ``linear_solve.py``).

Every PADMM iteration solves ``(Dt + diag(s)) x = b`` with ``Dt = P D P`` (§7.2) and the diagonal shift
``s = eta + rho`` of each row. The first ``nf`` rows (the fixed rows: joint-dynamics, joint and coupling rows) keep
their shift through a solve, the tail's (limit and contact rows) changes with the balanced penalty, so the factor is
kept in blocks ``[[L_f, 0], [L_tf, L_t]]``:

    L_f = chol(Dt_ff + diag(s_f)),   L_tf = Dt_tf L_f^-T,   S_t = Dt_tt - L_tf L_tf^T,   L_t = chol(S_t + diag(s_t)),

and a new tail shift only redoes ``L_t`` from the Schur complement ``S_t`` (the Warp backend's scheme,
docs/conventions.md "Penalty"). A factor is the tuple ``(L_f, L_tf, S_t, L_t)``; ``nf = 0`` is one dense Cholesky.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jax.scipy.linalg import solve_triangular


def factor_fixed(Dt: jax.Array, shift: jax.Array, nf: int) -> tuple[jax.Array, jax.Array, jax.Array]:
    """``(L_f, L_tf, S_t)``: the fixed rows' factor, the coupling block and the tail's Schur complement (§8.1).

    ``Dt`` is the scaled Delassus matrix ``[n, n]``, ``shift`` every row's diagonal shift ``eta + rho`` ``[n]``
    (only the first ``nf`` enter: the tail's shift is :func:`factor_tail`'s), ``nf`` the number of fixed rows.
    """
    n, dtype = Dt.shape[0], Dt.dtype
    A = Dt + jnp.diag(shift)
    L_f = jnp.linalg.cholesky(A[:nf, :nf]) if nf else jnp.zeros((0, 0), dtype)
    L_tf = solve_triangular(L_f, A[:nf, nf:], lower=True).T if nf else jnp.zeros((n - nf, 0), dtype)
    return L_f, L_tf, Dt[nf:, nf:] - L_tf @ L_tf.T


def factor_tail(fixed: tuple[jax.Array, jax.Array, jax.Array], shift_tail: jax.Array) -> tuple:
    """The whole factor ``(L_f, L_tf, S_t, L_t)`` from the fixed part ``fixed = (L_f, L_tf, S_t)`` of
    :func:`factor_fixed` and the tail rows' diagonal shift ``shift_tail = eta + rho_u`` ``[n - nf]`` (§8.1):
    ``L_t = chol(S_t + diag(shift_tail))``; empty when every row is fixed."""
    L_f, L_tf, S_t = fixed
    if S_t.shape[0] == 0:
        return L_f, L_tf, S_t, jnp.zeros((0, 0), S_t.dtype)
    return L_f, L_tf, S_t, jnp.linalg.cholesky(S_t + jnp.diag(shift_tail))


def solve(L: tuple, b: jax.Array) -> jax.Array:
    """``x = (Dt + diag(shift))^-1 b`` with the block factor ``L = (L_f, L_tf, S_t, L_t)`` of :func:`factor_tail`:
    forward then backward substitution, the fixed block first (§8.1 step 4)."""
    L_f, L_tf, _, L_t = L
    nf, n = L_f.shape[0], b.shape[0]
    y_f = solve_triangular(L_f, b[:nf], lower=True) if nf else b[:0]
    if nf == n:
        return solve_triangular(L_f, y_f, lower=True, trans="T")
    y_t = solve_triangular(L_t, b[nf:] - L_tf @ y_f, lower=True)
    x_t = solve_triangular(L_t, y_t, lower=True, trans="T")
    x_f = solve_triangular(L_f, y_f - L_tf.T @ x_t, lower=True, trans="T") if nf else b[:0]
    return jnp.concatenate([x_f, x_t])
