"""Post-stabilisation on the device: the position projection of ``kamino/jax_ref/post_stabilisation.py``.

Once per step, after the pose update, the always-active rows' scaled block ``P D_ff P + diag(s)`` is factorised
(``SolverConfig.projection_shifts``). Where PADMM's sparse factor already holds it (the adaptive penalty: the
leading block ``L_f`` of PADMM's factor carries the shifts ``eta + rho_free`` / ``eta + rho``), the projection
solves with that ``L_f``; otherwise the block is assembled on the fixed rows' static sparse pattern and
factorised in a storage of its own (``linear_solve.assemble_fixed``, then ``solver_lanes.factor_kernel`` on the
32-thread schedule or ``linear_solve.factor_fixed`` on the one-thread one; ``kamino/warp_backend/pipeline.py``).
A world whose PADMM did not converge, or whose anchors the passes left open past ``REPROJECTION_GAP``, gets one
pass more (the kernels' flag ``extra``; the reference's docstring):
the extra pass's ``residual`` sets ``w.reproject`` where a gap is open, and its solve and displacement run where
PADMM did not converge or that flag is set. One pass is three launches: the
residuals at ``q_new`` in PADMM's units (``x = -P e``), one thread per world solving with the sparse factor,
and the displacement ``d = M^-1 J_f^T P y`` applied as ``q_new ⊕ d``. The factorisation and the solve read
the block-sparse rows, which every configuration builds, so the projection works with either Jacobian and
either linear solver.

A world whose anchors the extra pass found open gets up to ``REPROJECTION_PASSES`` Gauss-Newton passes more
(``extra`` 2, 3, ...; ``pipeline.Stepper._gauss_newton_pass``): the residual kernel marks the worlds still open
(``reproject = extra``) and counts them, and, only where one is open (``wp.capture_if``), ``jacobian`` writes the
joint rows' blocks at the projected pose, the fixed rows' block is assembled and factorised again in a storage of
its own, and the solve and displacement run, all in the marked worlds only.

Each kernel comes from its own builder, cached per precision (``np_dtype``).
"""

import functools
from types import SimpleNamespace

import warp as wp

from kamino.config import REPROJECTION_GAP
from kamino.model import RES_TRANS
from kamino.warp_backend.indexing import index_funcs
from kamino.warp_backend.integrate import rows_on_body_func
from kamino.warp_backend.jacobians import coupling_residual_func, cts_residual_func, cts_row_func, dof_position_func
from kamino.warp_backend.linear_solve import (
    bases_func,
    factor_fixed_rows_func,
    fixed_entry_func,
    solve_inplace_func,
)
from kamino.warp_backend.rows import set_blocks_func
from kamino.warp_backend.spatial import spatial_funcs
from kamino.warp_backend.workspace import builder_types


def post_stabilisation_kernels(np_dtype) -> SimpleNamespace:
    """The three kernels of a projection pass and the joint rows' blocks at the projected pose of a Gauss-Newton
    pass (the launches in ``pipeline.py``)."""
    return SimpleNamespace(residual=residual_kernel(np_dtype), solve=solve_kernel(np_dtype),
                           displace=displace_kernel(np_dtype), jacobian=jacobian_kernel(np_dtype),
                           assemble=assemble_kernel(np_dtype), factor=factor_kernel(np_dtype))


@wp.func
def acts(extra: int, converged: int, reproject: int) -> bool:
    """Whether a world takes pass ``extra``: every world in a regular pass (0); in the extra pass (1) a world whose
    PADMM did not converge or whose anchors are open (``reproject`` 1); in Gauss-Newton pass ``extra >= 2`` a world
    whose anchors that pass's residual found still open (``reproject == extra``)."""
    if extra == 0:
        return True
    if extra == 1:
        return converged == 0 or reproject != 0
    return reproject == extra


@functools.cache
def residual_kernel(np_dtype):
    """The fixed rows' position residuals in PADMM's units, ``x = -P e(q_new)`` (docs/formulation.md §2.3, §8)."""
    scalar, transform, M = builder_types(np_dtype).take("scalar", "transform", "M")
    ridx = index_funcs(np_dtype).ridx
    deadband = spatial_funcs(np_dtype).deadband
    cts_residual, dof_position = cts_residual_func(np_dtype), dof_position_func(np_dtype)
    coupling_residual = coupling_residual_func(np_dtype)

    @wp.kernel(module="unique", enable_backward=False)
    def residual(
        # model (read only)
        m: M,
        # in
        delta: scalar,
        extra: int,
        row_stride: int,
        q_new: wp.array(dtype=transform),
        P: wp.array(dtype=scalar),
        # out
        reproject: wp.array(dtype=wp.int32),
        x: wp.array(dtype=scalar),
        count: wp.array(dtype=wp.int32),
    ):
        """``x_a = -P_a e_a(q_new)`` on the always-active rows (``fixed_row_residual`` of the reference); in the
        ``extra`` pass (``extra`` 1) it also sets ``reproject`` to 1 where an anchor gap exceeds ``REPROJECTION_GAP``
        or is not finite (``anchors_open`` of the reference), which the first pass clears. Gauss-Newton pass
        ``extra >= 2`` evaluates only the worlds still open at the pass before (``reproject == extra - 1``), sets
        ``reproject = extra`` where an anchor is still open, and counts those anchors in ``count[0]``."""
        wid, a = wp.tid()
        if extra == 0 and a == 0:
            reproject[wid] = 0
        if a >= m.row_fixed[wid]:
            return
        if extra >= 2 and reproject[wid] != extra - 1 and reproject[wid] != extra:
            return
        nd = m.dyn_count[wid]
        nc = m.cts_count[wid]
        e = scalar(0.0)
        if a >= nd and a < nd + nc:
            c = m.cts_start[wid] + a - nd
            e = deadband(cts_residual(m, q_new, c), delta)
            if extra != 0 and m.cts_kind[c] == RES_TRANS and not (wp.abs(e) <= scalar(REPROJECTION_GAP)):
                reproject[wid] = extra
                if extra >= 2:
                    wp.atomic_add(count, 0, 1)
        elif a >= nd + nc:
            k = m.cpl_start[wid] + a - nd - nc
            db = m.cpl_dof_b[k]
            qb = scalar(0.0)
            if db >= 0:
                qb = dof_position(m, q_new, db)
            ek, dp = coupling_residual(m, k, dof_position(m, q_new, m.cpl_dof_a[k]), qb)
            e = deadband(ek, delta)
        r = ridx(m, row_stride, wid, a)
        x[r] = -P[r] * e

    return residual


@functools.cache
def solve_kernel(np_dtype):
    """The projection's solve with the fixed rows' sparse factor, one thread per world (docs/formulation.md §8.1)."""
    scalar, M, SP = builder_types(np_dtype).take("scalar", "M", "SP")
    ridx = index_funcs(np_dtype).ridx
    sparse_solve = solve_inplace_func(np_dtype)

    @wp.kernel(module="unique", enable_backward=False)
    def solve(
        # model (read only)
        m: M,
        # in
        extra: int,
        row_stride: int,
        sp: SP,  # the fixed rows' sparse factor (tables and values, read)
        converged: wp.array(dtype=wp.int32),
        reproject: wp.array(dtype=wp.int32),
        P: wp.array(dtype=scalar),
        # out
        x: wp.array(dtype=scalar),  # also read
    ):
        """``lambda = P (P D_ff P + s I)^-1 x`` with the fixed rows' sparse factor (into ``x``), in the worlds that
        take the pass (:func:`acts`)."""
        wid = wp.tid()
        if not acts(extra, converged[wid], reproject[wid]):
            return
        nf = m.row_fixed[wid]
        sparse_solve(m, sp, row_stride, wid, nf, x)
        for a in range(nf):  # lambda = P y
            r = ridx(m, row_stride, wid, a)
            x[r] = P[r] * x[r]

    return solve


@functools.cache
def displace_kernel(np_dtype):
    """The projection's displacement ``q_new <- q_new ⊕ M^-1 J_f^T lambda`` (docs/formulation.md §6.1)."""
    scalar, vec6, mat33, transform, M = builder_types(np_dtype).take("scalar", "vec6", "mat33", "transform", "M")
    sp = spatial_funcs(np_dtype)
    integrate_pose, inverse_mass_times = sp.integrate_pose, sp.inverse_mass_times
    rows_on_body = rows_on_body_func(np_dtype)

    @wp.kernel(module="unique", enable_backward=False)
    def displace(
        # model (read only)
        m: M,
        # in
        nblk: int,
        extra: int,
        row_stride: int,
        converged: wp.array(dtype=wp.int32),
        reproject: wp.array(dtype=wp.int32),
        row_body: wp.array(dtype=wp.int32),
        row_J: wp.array(dtype=vec6),
        x: wp.array(dtype=scalar),
        inv_inertia_w: wp.array(dtype=mat33),
        # out
        failed: wp.array(dtype=wp.int32),
        q_new: wp.array(dtype=transform),  # also read
    ):
        """``q_new <- q_new ⊕ M^-1 J_f^T lambda`` (the body's share of every fixed row, summed in row order), in the
        worlds that take the pass (:func:`acts`)."""
        wid, i = wp.tid()
        if i >= m.body_count[wid] or not acts(extra, converged[wid], reproject[wid]):
            return
        b = m.body_start[wid] + i
        acc = rows_on_body(m, row_stride, row_body, row_J, wid, b, m.row_fixed[wid], nblk, x)
        d = inverse_mass_times(m.inv_mass[b], inv_inertia_w[b], acc)
        xb = integrate_pose(q_new[b], d, scalar(1.0))
        ok = True
        for c in range(7):
            ok = ok and wp.isfinite(xb[c])
        if not ok:
            failed[wid] = 1
        q_new[b] = xb

    return displace


@functools.cache
def jacobian_kernel(np_dtype):
    """The joint rows' blocks at the projected pose ``q_new``, for a Gauss-Newton pass (docs/formulation.md §2.5)."""
    transform, vec6, M = builder_types(np_dtype).take("transform", "vec6", "M")
    ridx = index_funcs(np_dtype).ridx
    cts_row, set_blocks = cts_row_func(np_dtype), set_blocks_func(np_dtype)

    @wp.kernel(module="unique", enable_backward=False)
    def jacobian(
        # model (read only)
        m: M,
        # in
        nblk: int,
        extra: int,
        row_stride: int,
        reproject: wp.array(dtype=wp.int32),
        q_new: wp.array(dtype=transform),
        # out
        row_body: wp.array(dtype=wp.int32),
        row_J: wp.array(dtype=vec6),
    ):
        """Joint row ``i``'s blocks evaluated at ``q_new`` (``joint_rows`` of ``rows.py`` at that pose), in the worlds
        that take Gauss-Newton pass ``extra`` (``reproject == extra``). The joint-dynamics and coupling rows keep
        the step's blocks."""
        wid, i = wp.tid()
        if i >= m.cts_count[wid] or reproject[wid] != extra:
            return
        c = m.cts_start[wid] + i
        j = m.cts_joint[c]
        e, JF, JB = cts_row(m, q_new, c)
        set_blocks(row_body, row_J, ridx(m, row_stride, wid, m.dyn_count[wid] + i), nblk, m.joint_child[j], JF,
                   m.joint_parent[j], JB)

    return jacobian


@functools.cache
def assemble_kernel(np_dtype):
    """The fixed rows' block ``P D_ff P + s I`` on their sparse pattern, in the worlds of a Gauss-Newton pass
    (``linear_solve.assemble_fixed`` of those worlds only)."""
    scalar, vec6, mat33, M, SP = builder_types(np_dtype).take("scalar", "vec6", "mat33", "M", "SP")
    fixed_entry = fixed_entry_func(np_dtype)

    @wp.kernel(module="unique", enable_backward=False)
    def assemble(
        # model (read only)
        m: M,
        # in
        nblk: int, shift: scalar, shift_sat: scalar, extra: int,
        row_stride: int,
        reproject: wp.array(dtype=wp.int32),
        row_body: wp.array(dtype=wp.int32),
        row_J: wp.array(dtype=vec6),
        row_info: wp.array(dtype=wp.int32),
        reg: wp.array(dtype=scalar),
        P: wp.array(dtype=scalar),
        inertia_w: wp.array(dtype=mat33),
        inv_inertia_w: wp.array(dtype=mat33),
        # out: the factor values sp.val (the pattern's index tables are read)
        sp: SP,
    ):
        """Entry ``k`` of the block of a world with ``reproject == extra``."""
        wid, k = wp.tid()
        if k >= sp.nnz[wid] or reproject[wid] != extra:
            return
        fixed_entry(m, sp, row_stride, row_body, row_J, row_info, reg, P, inertia_w, inv_inertia_w, wid, k, nblk,
                    shift, shift_sat)

    return assemble


@functools.cache
def factor_kernel(np_dtype):
    """The fixed rows' Cholesky factor in the worlds of a Gauss-Newton pass (``linear_solve.factor_fixed`` of those
    worlds only)."""
    M, SP = builder_types(np_dtype).take("M", "SP")
    bases, factor_fixed_rows = bases_func(np_dtype), factor_fixed_rows_func(np_dtype)

    @wp.kernel(module="unique", enable_backward=False)
    def factor(
        # model (read only)
        m: M,
        # in
        extra: int,
        row_stride: int,
        reproject: wp.array(dtype=wp.int32),
        # out: the factor values sp.val, in place
        sp: SP,
    ):
        """``L_f`` of a world with ``reproject == extra``."""
        wid = wp.tid()
        if reproject[wid] != extra:
            return
        factor_fixed_rows(sp, wid, bases(m, sp, row_stride, wid)[1])

    return factor
