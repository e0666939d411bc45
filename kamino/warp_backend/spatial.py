"""Quaternion and SE(3) helpers as Warp functions (docs/formulation.md §1.1, §2.3, §6.1).

The same formulas as ``kamino/spatial.py`` (small-angle series below ``|phi|^2 < 1e-12``),
so that both backends round the same way up to the order of operations. Each ``wp.func`` comes from its own
builder, cached per precision (``np_dtype``); :func:`spatial_funcs` names them all.
"""

import functools
from types import SimpleNamespace

import warp as wp

from kamino.warp_backend.types import types_of


def spatial_funcs(np_dtype) -> SimpleNamespace:
    """The spatial ``wp.func``s by name, each from its builder (cached per precision, ``np_dtype``)."""
    return SimpleNamespace(quat_exp=quat_exp_func(np_dtype), quat_log=quat_log_func(np_dtype),
                           integrate_pose=integrate_pose_func(np_dtype), deadband=deadband_func(np_dtype),
                           lin=lin_func(np_dtype), ang=ang_func(np_dtype), twist=twist_func(np_dtype),
                           inverse_mass_times=inverse_mass_times_func(np_dtype))


@functools.cache
def quat_exp_func(np_dtype):
    """The exponential map of a rotation vector (docs/formulation.md §6.1)."""
    T = types_of(np_dtype)
    scalar, vec3, quat = T.scalar, T.vec3, T.quat

    @wp.func
    def quat_exp(phi: vec3):
        """``Exp(phi) = (sin(|phi|/2) phi/|phi|, cos(|phi|/2))``; ``(phi/2 (1 - |phi|^2/24), 1 - |phi|^2/8)`` near 0."""
        sq = wp.dot(phi, phi)
        if sq < scalar(1e-12):
            v = scalar(0.5) * phi * (scalar(1.0) - sq / scalar(24.0))
            return quat(v[0], v[1], v[2], scalar(1.0) - sq / scalar(8.0))
        n = wp.sqrt(sq)
        v = wp.sin(scalar(0.5) * n) / n * phi
        return quat(v[0], v[1], v[2], wp.cos(scalar(0.5) * n))

    return quat_exp


@functools.cache
def quat_log_func(np_dtype):
    """The rotation vector of a unit quaternion (docs/formulation.md §2.3)."""
    T = types_of(np_dtype)
    scalar, vec3, quat = T.scalar, T.vec3, T.quat

    @wp.func
    def quat_log(q_in: quat):
        """Rotation vector ``Log(q)`` of a unit quaternion, shortest way round (§2.3)."""
        q = q_in
        if q[3] < scalar(0.0):
            q = -q
        v = vec3(q[0], q[1], q[2])
        w = q[3]
        sq = wp.dot(v, v)
        if sq < scalar(1e-12):
            return (scalar(2.0) - scalar(2.0 / 3.0) * sq / (w * w)) * v / w
        s = wp.sqrt(sq)
        return scalar(2.0) * wp.atan2(s, w) / s * v

    return quat_log


@functools.cache
def integrate_pose_func(np_dtype):
    """The pose update ``x ⊕ h u`` (docs/formulation.md §6.1)."""
    T = types_of(np_dtype)
    scalar, vec3, vec6, transform = T.scalar, T.vec3, T.vec6, T.transform
    quat_exp = quat_exp_func(np_dtype)

    @wp.func
    def integrate_pose(x: transform, u: vec6, h: scalar):
        """``r+ = r + h v``, ``q+ = normalize(Exp(h w) ⊗ q)`` (docs/formulation.md §6.1)."""
        p = wp.transform_get_translation(x) + h * vec3(u[0], u[1], u[2])
        q = quat_exp(h * vec3(u[3], u[4], u[5])) * wp.transform_get_rotation(x)
        return transform(p, wp.normalize(q))

    return integrate_pose


@functools.cache
def deadband_func(np_dtype):
    """The dead band (docs/formulation.md §4.2)."""
    scalar = types_of(np_dtype).scalar

    @wp.func
    def deadband(x: scalar, delta: scalar):
        """``sign(x) max(0, |x| - delta)`` (docs/formulation.md §4.2)."""
        a = wp.abs(x) - delta
        if a <= scalar(0.0):
            return scalar(0.0)
        return wp.sign(x) * a

    return deadband


@functools.cache
def lin_func(np_dtype):
    """The linear part of a twist or wrench (docs/formulation.md §1.1)."""
    T = types_of(np_dtype)
    vec3, vec6 = T.vec3, T.vec6

    @wp.func
    def lin(u: vec6):
        return vec3(u[0], u[1], u[2])

    return lin


@functools.cache
def ang_func(np_dtype):
    """The angular part of a twist or wrench (docs/formulation.md §1.1)."""
    T = types_of(np_dtype)
    vec3, vec6 = T.vec3, T.vec6

    @wp.func
    def ang(u: vec6):
        return vec3(u[3], u[4], u[5])

    return ang


@functools.cache
def twist_func(np_dtype):
    """A twist or wrench from its linear and angular parts (docs/formulation.md §1.1)."""
    T = types_of(np_dtype)
    vec3, vec6 = T.vec3, T.vec6

    @wp.func
    def twist(v: vec3, w: vec3):
        return vec6(v[0], v[1], v[2], w[0], w[1], w[2])

    return twist


@functools.cache
def inverse_mass_times_func(np_dtype):
    """``M_b^-1 f`` on one body (docs/formulation.md §1.3)."""
    T = types_of(np_dtype)
    scalar, vec6, mat33 = T.scalar, T.vec6, T.mat33
    lin = lin_func(np_dtype)
    ang = ang_func(np_dtype)
    twist = twist_func(np_dtype)

    @wp.func
    def inverse_mass_times(inv_mass: scalar, inv_inertia: mat33, f: vec6):
        """``M_b^-1 f`` on one body for a wrench or a 1x6 Jacobian block ``f``: ``(f_lin / m, I_w^-1 f_ang)``
        (the block-diagonal mass matrix of docs/formulation.md §1.3, ``I_w^-1`` in the world frame)."""
        return twist(inv_mass * lin(f), inv_inertia * ang(f))

    return inverse_mass_times
