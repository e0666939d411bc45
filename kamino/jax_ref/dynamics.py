"""Body dynamics for one world: mass matrix, non-linear forces, free velocity, Delassus (docs/formulation.md §1,
§7.1)."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp

from kamino.config import GYRO_ITERATIONS
from kamino.jax_ref.types import PaddedModel
from kamino.spatial import quat_to_matrix


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class BodyDynamics:
    """World-frame inverse mass data of every body (§1.3)."""

    inv_mass: jax.Array  # [nb] (0 on padding)
    inertia: jax.Array  # [nb, 3, 3] world inertia R I R^T
    inv_inertia: jax.Array  # [nb, 3, 3] world inverse inertia R I^-1 R^T (0 on padding)


def body_dynamics(pm: PaddedModel, body_q: jax.Array) -> BodyDynamics:
    """World inertias ``I = R Ī R^T`` and ``I^-1 = R Ī^-1 R^T``, symmetrised (docs/formulation.md §1.3)."""
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
    """``h_i = (m_i g, -w_i x (I_i w_i)) + w^e_i`` per body ``[nb, 6]`` (docs/formulation.md §1.4).

    The gyroscopic term is explicit (evaluated at the configuration the dynamics are built at);
    :func:`free_velocity` replaces it by the implicit-midpoint one (docs/conventions.md, "Gyroscopic term").
    ``external`` holds the external and explicit actuation wrenches.
    """
    w = body_u[:, 3:]
    gyro = -jnp.cross(w, jnp.einsum("bij,bj->bi", bd.inertia, w))
    f = pm.mass[:, None] * gravity[None, :]
    h = jnp.concatenate([f, gyro], axis=-1) + external
    return jnp.where(pm.body_mask[:, None], h, 0.0)




def _skew(a: jax.Array) -> jax.Array:
    """``[a]x`` with ``[a]x b = a x b``, for ``a`` ``[..., 3]``."""
    z = jnp.zeros_like(a[..., 0])
    return jnp.stack([jnp.stack([z, -a[..., 2], a[..., 1]], -1),
                      jnp.stack([a[..., 2], z, -a[..., 0]], -1),
                      jnp.stack([-a[..., 1], a[..., 0], z], -1)], -2)


def gyroscopic_correction(inertia: jax.Array, R: jax.Array, w0: jax.Array, w_explicit: jax.Array, dt,
                          iterations: int | None = None) -> jax.Array:
    """World-frame correction ``R d`` that turns the explicit free angular velocity into the implicit-midpoint one.

    Body frame (``Ī`` = ``inertia`` ``[..., 3, 3]``, ``R`` the rotation at the evaluation pose, ``w_b = R^T w``):
    the free angular velocity solves ``Ī (w_f - w0) = dt (tau_b - w̄ x Ī w̄)``, ``w̄ = (w0 + w_f) / 2``
    (docs/conventions.md, "Gyroscopic term"). With ``w_f = w_e + d`` and the explicit ``w_e`` (§1.4:
    ``Ī (w_e - w0) = dt (tau_b - w0 x Ī w0)``) this is ``F(d) = Ī d + dt (w̄ x Ī' w̄ - w0 x Ī' w0) = 0``,
    ``w̄ = (w0 + w_e) / 2 + d / 2``, solved by ``iterations`` (default :data:`GYRO_ITERATIONS`; 0 gives the
    explicit term back) Newton steps from ``d = 0`` with
    ``dF/dd = Ī + dt/2 ([w̄]x Ī' - [Ī' w̄]x)``. ``Ī' = Ī - Ī_00 1`` has the same gyroscopic torque
    (``w x w = 0``) and is exactly zero for a spherical inertia, whose correction is then exactly zero.
    ``w0``, ``w_explicit`` are world-frame ``[..., 3]``; returns ``[..., 3]`` (world frame).
    """
    Ib = inertia
    Dv = Ib - Ib[..., 0:1, 0:1] * jnp.eye(3, dtype=Ib.dtype)
    mv = lambda A, x: jnp.einsum("...ij,...j->...i", A, x)  # noqa: E731
    Rt = jnp.swapaxes(R, -1, -2)
    a = mv(Rt, w0)
    m = mv(Rt, 0.5 * (w0 + w_explicit))
    g0 = jnp.cross(a, mv(Dv, a))
    d = jnp.zeros_like(a)
    for _ in range(GYRO_ITERATIONS if iterations is None else iterations):
        wm = m + 0.5 * d
        Dw = mv(Dv, wm)
        F = mv(Ib, d) + dt * (jnp.cross(wm, Dw) - g0)
        Jac = Ib + (0.5 * dt) * (_skew(wm) @ Dv - _skew(Dw))
        d = d - jnp.linalg.solve(Jac, F[..., None])[..., 0]
    return mv(R, d)


def free_velocity(pm: PaddedModel, bd: BodyDynamics, body_q: jax.Array, body_u: jax.Array, h_force: jax.Array,
                  dt) -> jax.Array:
    """Free velocity ``u_f`` ``[nb, 6]`` at the evaluation pose ``body_q`` (docs/formulation.md §1.4, departure in
    docs/conventions.md, "Gyroscopic term").

    ``u_e = u + dt M^-1 h`` (§1.4, ``h`` from :func:`nonlinear_force`, explicit gyroscopic torque), then the angular
    part is replaced by the implicit-midpoint solution of the body-frame Euler equation
    (:func:`gyroscopic_correction`). The linear part and the constraint impulses (ordinary ``M^-1``) are unchanged.
    """
    u_e = body_u + dt * apply_inv_mass(bd, h_force)
    R = quat_to_matrix(body_q[:, 3:])
    corr = gyroscopic_correction(pm.inertia, R, body_u[:, 3:], u_e[:, 3:], dt)
    corr = jnp.where(pm.body_mask[:, None], corr, 0.0)
    return jnp.concatenate([u_e[:, :3], u_e[:, 3:] + corr], axis=-1)


def delassus(J: jax.Array, bd: BodyDynamics) -> jax.Array:
    """``D = J M^-1 J^T`` for a dense ``J`` ``[n, nb*6]`` (docs/formulation.md §7.1, without R)."""
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
