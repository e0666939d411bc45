"""Joint couplings (mimic joints): ``q_a = p(q_b) = sum_k c_k q_b^k`` (docs/conventions.md "Couplings").

One bilateral row per coupling, residual ``e = q_a - p(q_b)`` in joint a's units (wrapped to
``[-pi, pi]`` when joint a is a hinge, whose angle is defined modulo ``2 pi``), Jacobian
``J_a - p'(q_b) J_b`` with ``J_a``, ``J_b`` the two DoF rows of ``J_dofs`` (docs/formulation.md §2.5).
This is MuJoCo's ``<equality><joint polycoef>`` with coordinates measured from the reference pose.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from kamino.jax_ref.types import PaddedModel


def _poly(coef: jax.Array, x: jax.Array) -> tuple[jax.Array, jax.Array]:
    """``p(x)`` and ``p'(x)`` of the quartic ``coef [nk, 5]`` (Horner)."""
    p = jnp.zeros_like(x)
    dp = jnp.zeros_like(x)
    for k in range(4, -1, -1):
        dp = dp * x + p
        p = p * x + coef[:, k]
    return p, dp


def coupling_residual(pm: PaddedModel, q_dof: jax.Array) -> jax.Array:
    """``e [nk]``: ``q_a - p(q_b)`` (``q_b = 0`` without joint b), zero on padding."""
    qb = jnp.where(pm.cpl_has_b, q_dof[pm.cpl_dof_b], 0.0)
    p, _ = _poly(pm.cpl_coef, qb)
    e = q_dof[pm.cpl_dof_a] - p
    e = jnp.where(pm.cpl_wrap, jnp.mod(e + jnp.pi, 2.0 * jnp.pi) - jnp.pi, e)
    return jnp.where(pm.cpl_mask, e, 0.0)


def coupling_jacobian(pm: PaddedModel, q_dof: jax.Array, J_dofs: jax.Array) -> jax.Array:
    """``[nk, 6 nb]``: ``J_dofs[a] - p'(q_b) J_dofs[b]``, zero rows on padding."""
    qb = jnp.where(pm.cpl_has_b, q_dof[pm.cpl_dof_b], 0.0)
    _, dp = _poly(pm.cpl_coef, qb)
    dp = jnp.where(pm.cpl_has_b, dp, 0.0)
    J = J_dofs[pm.cpl_dof_a] - dp[:, None] * J_dofs[pm.cpl_dof_b]
    return jnp.where(pm.cpl_mask[:, None], J, 0.0)
