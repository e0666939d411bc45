"""The per-iteration rules of accelerated PADMM shared by the two PADMM schedules (one thread per world in
``solver.py``, 32 threads per world in ``padmm_warp.py``): the dual update and a row's residuals (docs/formulation.md
§7.3-§7.5), the fast-ADMM momentum with restart (§7.4), the penalty of the limit and contact rows, and a box row's
complementarity residual (§7.5).
"""

import functools
from types import SimpleNamespace

import numpy as np
import warp as wp

from kamino.config import (
    PENALTY_INTERVAL,
    PENALTY_MAX_FACTOR,
    PENALTY_THRESHOLD,
    RESIDUAL_LOOSENING_MAX,
    RHO_MAX,
    RHO_MIN,
)
from kamino.warp_backend.types import types_of

#: what :func:`padmm_funcs` ``momentum`` asks the kernel to do with ``(y_hat, z_hat)``
NO_ACCELERATION, EXTRAPOLATE, RESTART = 0, 1, 2


@functools.cache
def padmm_funcs(np_dtype) -> SimpleNamespace:
    T = types_of(np_dtype)
    scalar = T.scalar
    vec4 = wp.types.vector(length=4, dtype=scalar)
    inf = scalar(wp.inf)
    one = scalar(1.0)
    zero = scalar(0.0)
    tiny = scalar(float(np.finfo(np_dtype).tiny))

    @wp.func
    def momentum(a_p: scalar, c_p: scalar, c_sum: scalar, restart_tol: scalar, accelerate: int):
        """§7.4 step 5: ``(a, c, beta, mode)`` from the previous momentum ``a_p``, the previous combined
        residual ``c_p`` and this iteration's ``c_sum``. ``mode`` (stored as a scalar): ``NO_ACCELERATION``
        (``hat = new``), ``EXTRAPOLATE`` (``hat = new + beta (new - prev)``, the residual dropped by ``restart_tol``) or
        ``RESTART`` (``hat = prev``, momentum reset, ``c = c_p / restart_tol``)."""
        if accelerate == 0:
            return vec4(a_p, c_p, zero, scalar(NO_ACCELERATION))
        if c_sum < restart_tol * c_p:
            a_new = scalar(0.5) * (one + wp.sqrt(one + scalar(4.0) * a_p * a_p))
            return vec4(a_new, c_sum, (a_p - one) / a_new, scalar(EXTRAPOLATE))
        return vec4(one, c_p / restart_tol, zero, scalar(RESTART))

    @wp.func
    def extrapolated(new: scalar, prev: scalar, beta: scalar, mode: int):
        """The next ``y_hat`` (or ``z_hat``) of a row after :func:`momentum`."""
        if mode == EXTRAPOLATE:
            return new + beta * (new - prev)
        if mode == RESTART:
            return prev
        return new

    @wp.func
    def residual_weight(P: scalar, p_ref: scalar):
        """A row's residual weight ``1 / min(K P, p_ref)``, ``K = RESIDUAL_LOOSENING_MAX``: its scaled error as a
        velocity of the world's heaviest row, capped at ``K`` times its own velocity error
        (``kamino.jax_ref.padmm.solve``, "Residuals")."""
        return one / wp.min(scalar(RESIDUAL_LOOSENING_MAX) * P, p_ref)

    @wp.func
    def dual_update(x: scalar, y: scalar, x_p: scalar, y_hat: scalar, z_hat: scalar, P: scalar, eta: scalar,
                    rho: scalar, p_ref: scalar):
        """§7.3 step 4 and the row's share of the residuals: ``(z, w |x - y|, w |eta (x - x_p) + rho (y - y_hat)|,
        rho |P dy|^2 + |dz / P|^2 / rho)`` with ``w`` the row's :func:`residual_weight`; the world takes the maxima
        of the first two (``kamino.jax_ref.padmm.solve``, "Residuals"). The last is the row's share of §7.4's
        combined residual."""
        z = z_hat + rho * (y - x)
        dy = P * (y - y_hat)
        dz = (z - z_hat) / P
        wgt = residual_weight(P, p_ref)
        return vec4(z, wgt * wp.abs(x - y), wgt * wp.abs(eta * (x - x_p) + rho * (y - y_hat)),
                    rho * dy * dy + dz * dz / rho)

    @wp.func
    def balanced_penalty(rho_u: scalar, r_p: scalar, r_d: scalar, k: int, k_rho: int):
        """The limit and contact rows' penalty after iteration ``k`` (the last change at ``k_rho``): residual
        balancing, ``rho_u sqrt(r_p / r_d)`` (the factor capped to ``[1 / PENALTY_MAX_FACTOR, PENALTY_MAX_FACTOR]``)
        clipped to ``[RHO_MIN, RHO_MAX]``, when ``PENALTY_INTERVAL`` iterations have passed and the balance is off by
        more than ``PENALTY_THRESHOLD``; else ``rho_u`` (``kamino.jax_ref.padmm.solve``)."""
        if k - k_rho < PENALTY_INTERVAL:
            return rho_u
        ratio = wp.sqrt((r_p + tiny) / (r_d + tiny))
        if ratio > scalar(PENALTY_THRESHOLD) or ratio * scalar(PENALTY_THRESHOLD) < one:
            gain = wp.clamp(ratio, one / scalar(PENALTY_MAX_FACTOR), scalar(PENALTY_MAX_FACTOR))
            return wp.clamp(rho_u * gain, scalar(RHO_MIN), scalar(RHO_MAX))
        return rho_u

    @wp.func
    def saturates(sat: int, lo: scalar, hi: scalar, v: scalar, y: scalar):
        """Whether a fixed row not yet saturated (``sat == 0``) saturates: it has a finite bound (an effort-limited
        actuator) and its projection ``y = clamp(v, lo, hi)`` clipped ``v = x - z_hat / rho``
        (``kamino.jax_ref.padmm.solve``, "Saturation")."""
        return sat == 0 and (wp.isfinite(lo) or wp.isfinite(hi)) and y != v

    @wp.func
    def box_complementarity(y: scalar, z: scalar, lo: scalar, hi: scalar):
        """``|z| * distance of y to its nearest finite bound`` (0 for an unbounded row), §7.5."""
        if not (wp.isfinite(lo) or wp.isfinite(hi)):
            return scalar(0.0)
        gap = inf
        if wp.isfinite(lo):
            gap = wp.abs(y - lo)
        if wp.isfinite(hi):
            gap = wp.min(gap, wp.abs(hi - y))
        return wp.abs(z) * gap

    return SimpleNamespace(momentum=momentum, extrapolated=extrapolated, dual_update=dual_update,
                           residual_weight=residual_weight,
                           balanced_penalty=balanced_penalty, saturates=saturates,
                           box_complementarity=box_complementarity)
