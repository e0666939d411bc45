"""Body dynamics of a step, as Warp kernels: world inertia, the non-linear force and the free velocity with the
implicit gyroscopic term (docs/formulation.md §1.3-§1.4; the JAX reference's ``dynamics.py``).

Each kernel and each ``wp.func`` comes from its own builder, cached per precision (``np_dtype``).
"""

import functools

import warp as wp

from kamino.config import GYRO_ITERATIONS
from kamino.warp_backend.spatial import spatial_funcs
from kamino.warp_backend.workspace import builder_types


@functools.cache
def gyroscopic_correction_func(np_dtype):
    """``gyroscopic_correction(Ib, R, w0, we, dt)``: the implicit-midpoint gyroscopic term (docs/conventions.md,
    "Gyroscopic term (departure from formulation.md §1.4)")."""
    scalar, vec3, mat33 = builder_types(np_dtype).take("scalar", "vec3", "mat33")

    @wp.func
    def gyroscopic_correction(Ib: mat33, R: mat33, w0: vec3, we: vec3, dt: scalar):
        """World-frame correction ``R d`` from the explicit free angular velocity ``we`` to the implicit-midpoint one
        (body frame: ``Ī (w_f - w0) = dt (tau_b - w̄ x Ī w̄)``, ``w̄ = (w0 + w_f) / 2``): ``GYRO_ITERATIONS`` Newton
        steps on ``F(d) = Ī d + dt (w̄ x Ī' w̄ - w0 x Ī' w0)``, ``w̄ = R^T (w0 + we) / 2 + d / 2``, ``Ī' = Ī - Ī_00 1``
        (exactly zero correction for a spherical inertia). docs/conventions.md, "Gyroscopic term";
        ``kamino.jax_ref.dynamics.gyroscopic_correction`` does the same operations."""
        Dv = Ib - Ib[0, 0] * wp.identity(n=3, dtype=scalar)
        Rt = wp.transpose(R)
        a = Rt * w0
        mid = Rt * (scalar(0.5) * (w0 + we))
        g0 = wp.cross(a, Dv * a)
        d = vec3()
        for _k in range(GYRO_ITERATIONS):
            wm = mid + scalar(0.5) * d
            Dw = Dv * wm
            F = Ib * d + dt * (wp.cross(wm, Dw) - g0)
            Jac = Ib + (scalar(0.5) * dt) * (wp.skew(wm) * Dv - wp.skew(Dw))
            d = d - wp.inverse(Jac) * F
        return R * d

    return gyroscopic_correction


@functools.cache
def bodies_kernel(np_dtype):
    """World inertia, the free velocity and the predicted pose (docs/formulation.md §1.4, §5)."""
    scalar, vec6, mat33, transform, M = builder_types(np_dtype).take("scalar", "vec6", "mat33", "transform", "M")
    sp = spatial_funcs(np_dtype)
    integrate_pose, lin, ang, twist, inverse_mass_times = (sp.integrate_pose, sp.lin, sp.ang, sp.twist,
                                                           sp.inverse_mass_times)
    gyroscopic_correction = gyroscopic_correction_func(np_dtype)

    @wp.kernel(module="unique", enable_backward=False)
    def bodies(
        # model (read only)
        m: M,
        # in
        dt: scalar,
        h: scalar,
        q_eval: wp.array(dtype=transform),
        wrench: wp.array(dtype=vec6),
        tau_explicit: wp.array(dtype=scalar),
        dof_JF: wp.array(dtype=vec6),
        dof_JB: wp.array(dtype=vec6),
        u: wp.array(dtype=vec6),
        # out
        inertia_w: wp.array(dtype=mat33),
        inv_inertia_w: wp.array(dtype=mat33),
        u_f: wp.array(dtype=vec6),
        q_pred: wp.array(dtype=transform),
    ):
        """World inertia, ``h = (m g, -w x I w) + w_ext + J_dofs^T tau`` (§1.4), free velocity
        ``u_f = u + dt M^-1 h`` with the implicit-midpoint gyroscopic term (:func:`gyroscopic_correction_func`,
        docs/conventions.md "Gyroscopic term") and the predicted pose ``q_eval ⊕ h u_f`` (curvature term, §5)."""
        wid, i = wp.tid()
        if i >= m.body_count[wid]:
            return
        b = m.body_start[wid] + i
        x = q_eval[b]
        R = wp.quat_to_matrix(wp.transform_get_rotation(x))
        I = R * m.inertia[b] * wp.transpose(R)
        I = scalar(0.5) * (I + wp.transpose(I))
        Ii = R * m.inv_inertia[b] * wp.transpose(R)
        Ii = scalar(0.5) * (Ii + wp.transpose(Ii))
        inertia_w[b] = I
        inv_inertia_w[b] = Ii
        # explicit joint efforts on this body (deterministic: scan the world's DoFs)
        ext = wrench[b]
        d0 = m.dof_start[wid]
        for k in range(m.dof_count[wid]):
            d = d0 + k
            tau = tau_explicit[d]
            if tau != scalar(0.0):
                j = m.dof_joint[d]
                if m.joint_child[j] == b:
                    ext += tau * dof_JF[d]
                if m.joint_parent[j] == b:
                    ext += tau * dof_JB[d]
        ub = u[b]
        om = ang(ub)
        hf = twist(m.mass[b] * m.gravity[wid], -wp.cross(om, I * om)) + ext
        uf = ub + dt * inverse_mass_times(m.inv_mass[b], Ii, hf)
        uf = twist(lin(uf), ang(uf) + gyroscopic_correction(m.inertia[b], R, om, ang(uf), dt))
        u_f[b] = uf
        q_pred[b] = integrate_pose(x, uf, h)

    return bodies
