"""Body dynamics for one world: mass matrix, non-linear forces, free velocity, Delassus (formulation.md §1, §7.1)."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp

from kamino.jax_ref.layout import PaddedModel
from kamino.jax_ref.spatial import quat_to_matrix


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class BodyDynamics:
    """World-frame inverse mass data of every body (§1.3)."""

    inv_mass: jax.Array  # [nb] (0 on padding)
    inertia: jax.Array  # [nb, 3, 3] world inertia R I R^T
    inv_inertia: jax.Array  # [nb, 3, 3] world inverse inertia R I^-1 R^T (0 on padding)


def body_dynamics(pm: PaddedModel, body_q: jax.Array) -> BodyDynamics:
    """World inertias ``I = R Ī R^T`` and ``I^-1 = R Ī^-1 R^T``, symmetrised (formulation.md §1.3)."""
    R = quat_to_matrix(body_q[:, 3:])
    I = jnp.einsum("bij,bjk,blk->bil", R, pm.inertia, R)
    I_inv = jnp.einsum("bij,bjk,blk->bil", R, jnp.linalg.inv(pm.inertia), R)
    sym = lambda A: 0.5 * (A + jnp.swapaxes(A, -1, -2))  # noqa: E731
    mask = pm.body_mask
    return BodyDynamics(
        inv_mass=jnp.where(mask, 1.0 / pm.mass, 0.0),
        inertia=sym(I),
        inv_inertia=jnp.where(mask[:, None, None], sym(I_inv), 0.0),
    )


def apply_inv_mass(bd: BodyDynamics, w: jax.Array) -> jax.Array:
    """``M^-1 w`` for body wrenches ``w`` ``[..., nb, 6]`` (block-diagonal M, §1.3)."""
    lin = bd.inv_mass[..., :, None] * w[..., :3]
    ang = jnp.einsum("bij,...bj->...bi", bd.inv_inertia, w[..., 3:])
    return jnp.concatenate([lin, ang], axis=-1)


def nonlinear_force(pm: PaddedModel, bd: BodyDynamics, body_u: jax.Array, gravity: jax.Array,
                    external: jax.Array) -> jax.Array:
    """``h_i = (m_i g, -w_i x (I_i w_i)) + w^e_i`` per body ``[nb, 6]`` (formulation.md §1.4).

    The gyroscopic term is explicit (evaluated at the configuration the dynamics are built at).
    ``external`` holds the external and explicit actuation wrenches.
    """
    w = body_u[:, 3:]
    gyro = -jnp.cross(w, jnp.einsum("bij,bj->bi", bd.inertia, w))
    f = pm.mass[:, None] * gravity[None, :]
    h = jnp.concatenate([f, gyro], axis=-1) + external
    return jnp.where(pm.body_mask[:, None], h, 0.0)


def delassus(J: jax.Array, bd: BodyDynamics) -> jax.Array:
    """``D = J M^-1 J^T`` for a dense ``J`` ``[n, nb*6]`` (formulation.md §7.1, without R)."""
    n = J.shape[0]
    nb = bd.inv_mass.shape[0]
    MinvJt = apply_inv_mass(bd, J.reshape(n, nb, 6)).reshape(n, nb * 6)
    D = J @ MinvJt.T
    return 0.5 * (D + D.T)


def kinetic_energy(bd: BodyDynamics, pm: PaddedModel, body_u: jax.Array) -> jax.Array:
    """``T = sum_i 1/2 m_i |v_i|^2 + 1/2 w_i^T I_i w_i``."""
    v, w = body_u[:, :3], body_u[:, 3:]
    t = 0.5 * pm.mass * jnp.sum(v * v, -1) + 0.5 * jnp.einsum("bi,bij,bj->b", w, bd.inertia, w)
    return jnp.sum(jnp.where(pm.body_mask, t, 0.0))


def potential_energy(pm: PaddedModel, body_q: jax.Array) -> jax.Array:
    """Gravitational potential ``V = -sum_i m_i g . r_i`` (zero at the world origin)."""
    v = -pm.mass * (body_q[:, :3] @ pm.gravity)
    return jnp.sum(jnp.where(pm.body_mask, v, 0.0))
