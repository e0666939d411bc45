"""End of a step in Warp: ``u+ = u_f + M^-1 J^T lambda``, the pose update, the State's forces, commit.

Formulation.md §6.2 (Euler: ``q+ = q ⊕ dt u+``) and §6.3 (midpoint: ``q+ = q_m ⊕ dt/2 u+``); the
forces are ``lambda / dt`` split by row family as ``_new_cache`` of the JAX reference. A world
whose new pose, twist or impulses are not finite keeps its previous state and is flagged
``failed`` (docs/architecture.md: never a silent NaN, never contaminating other worlds). So is a world whose
joints open past :data:`LOOP_OPEN_BOUND` in a step (:func:`closure_check_kernel`), or whose bodies pass the speed
bounds ``HEALTH_TURN`` and ``HEALTH_SPEED`` (:func:`speed_check_kernel`; ``kamino.config``): its finite state is
already meaningless. The JAX reference applies the same checks (``kamino.jax_ref.integrate``).

Each kernel and each ``wp.func`` comes from its own builder, cached per precision (``np_dtype``).
"""

import functools
from types import SimpleNamespace

import warp as wp

from kamino.config import LOOP_OPEN_BOUND as LOOP_OPEN_BOUND  # the health bound its closure check reads
from kamino.model import RES_TRANS
from kamino.warp_backend.indexing import index_funcs
from kamino.warp_backend.jacobians import cts_residual_func
from kamino.warp_backend.rows import ROW_ACTUATOR, ROW_COUPLING, ROW_JOINT, ROW_LIMIT, ROW_PASSIVE
from kamino.warp_backend.spatial import spatial_funcs
from kamino.warp_backend.workspace import builder_types


def end_step_kernels(np_dtype, dense: bool, screened: bool) -> SimpleNamespace:
    """The kernels of the end of a step (the launches in ``pipeline.py``): ``u+`` from the dense Jacobian (``dense``)
    or the block-sparse rows, the closure check of every world or of the projected ones (``screened``,
    :func:`closure_check_kernel`)."""
    return SimpleNamespace(integrate=integrate_kernel(np_dtype, bool(dense)), dof_forces=dof_forces_kernel(np_dtype),
                           row_forces=row_forces_kernel(np_dtype), commit_bodies=commit_bodies_kernel(np_dtype),
                           commit_time=commit_time_kernel(np_dtype),
                           closure_check=closure_check_kernel(np_dtype, bool(screened)),
                           speed_check=speed_check_kernel(np_dtype))


@functools.cache
def rows_on_body_func(np_dtype):
    """``rows_on_body(m, row_stride, row_body, row_J, wid, b, n, nblk, lam)``: ``(J^T lambda)_b`` from the
    block-sparse rows (§6.2)."""
    scalar, vec6, M = builder_types(np_dtype).take("scalar", "vec6", "M")
    ridx = index_funcs(np_dtype).ridx

    @wp.func
    def rows_on_body(m: M, row_stride: int, row_body: wp.array(dtype=wp.int32), row_J: wp.array(dtype=vec6), wid: int,
                     b: int, n: int, nblk: int, lam: wp.array(dtype=scalar)):
        """``(J^T lambda)_b`` over the first ``n`` rows of world ``wid`` (block-sparse rows, summed in row order)."""
        acc = vec6()
        for a in range(n):
            r = ridx(m, row_stride, wid, a)
            for k in range(nblk):
                if row_body[r * nblk + k] == b:
                    acc += lam[r] * row_J[r * nblk + k]
        return acc

    return rows_on_body


@functools.cache
def live_item_func(np_dtype):
    """``live_item(failed, wid, i, start, count)``: item ``i`` of a world's segment, or -1 (the commit kernels,
    §6.2)."""

    @wp.func
    def live_item(failed: wp.array(dtype=wp.int32), wid: int, i: int, start: int, count: int):
        """``start + i`` (a body or DoF of world ``wid``), or -1 past the world's ``count`` or in a ``failed``
        world."""
        if i >= count or failed[wid] != 0:
            return -1
        return start + i

    return live_item


@functools.cache
def integrate_kernel(np_dtype, dense: bool):
    """``u+`` and the pose update (docs/formulation.md §6.2, §6.3), from the dense Jacobian (``dense``) or the
    block-sparse rows."""
    scalar, vec6, mat33, transform, M = builder_types(np_dtype).take("scalar", "vec6", "mat33", "transform", "M")
    ix = index_funcs(np_dtype)
    ridx, jidx = ix.ridx, ix.jidx
    sp = spatial_funcs(np_dtype)
    lin, ang, twist, integrate_pose, inverse_mass_times = (sp.lin, sp.ang, sp.twist, sp.integrate_pose,
                                                           sp.inverse_mass_times)
    rows_on_body = rows_on_body_func(np_dtype)

    @wp.kernel(module="unique", enable_backward=False)
    def integrate(
        # model (read only)
        m: M,
        # in
        nblk: int,
        h: scalar,
        damping: scalar,
        row_stride: int,
        n_rows: wp.array(dtype=wp.int32),
        impulse: wp.array(dtype=scalar),
        Jd: wp.array(dtype=scalar),
        row_body: wp.array(dtype=wp.int32),
        row_J: wp.array(dtype=vec6),
        u_f: wp.array(dtype=vec6),
        inv_inertia_w: wp.array(dtype=mat33),
        q_eval: wp.array(dtype=transform),
        # out
        u_new: wp.array(dtype=vec6),
        q_new: wp.array(dtype=transform),
        failed: wp.array(dtype=wp.int32),
    ):
        """``u+ = u_f + M^-1 J^T lambda`` (the body's share of every active row, summed in row order) and
        ``q+ = q_eval ⊕ h u+``."""
        wid, i = wp.tid()
        if i >= m.body_count[wid]:
            return
        b = m.body_start[wid] + i
        n = n_rows[wid]
        acc = vec6()
        if wp.static(dense):
            for a in range(n):
                lam = impulse[ridx(m, row_stride, wid, a)]
                for c in range(6):
                    acc[c] += lam * Jd[jidx(m, wid, a, 6 * i + c)]
        else:
            acc = rows_on_body(m, row_stride, row_body, row_J, wid, b, n, nblk, impulse)
        u = u_f[b] + inverse_mass_times(m.inv_mass[b], inv_inertia_w[b], acc)
        if damping != scalar(0.0):
            u = twist(lin(u), (scalar(1.0) - damping) * ang(u))
        x = integrate_pose(q_eval[b], u, h)
        u_new[b] = u
        q_new[b] = x
        ok = True
        for c in range(6):
            ok = ok and wp.isfinite(u[c])
        for c in range(7):
            ok = ok and wp.isfinite(x[c])
        if not ok:
            failed[wid] = 1

    return integrate


@functools.cache
def dof_forces_kernel(np_dtype):
    """The per-DoF forces' reset before the rows' share (§6.2)."""
    scalar, M = builder_types(np_dtype).take("scalar", "M")
    live_item = live_item_func(np_dtype)

    @wp.kernel(module="unique", enable_backward=False)
    def dof_forces(
        # model (read only)
        m: M,
        # in
        failed: wp.array(dtype=wp.int32),
        tau_explicit: wp.array(dtype=scalar),
        # out
        act_force: wp.array(dtype=scalar),
        pas_force: wp.array(dtype=scalar),
        lim_force: wp.array(dtype=scalar),
    ):
        """Reset the per-DoF forces: the actuator force starts from the explicit effort."""
        wid, i = wp.tid()
        d = live_item(failed, wid, i, m.dof_start[wid], m.dof_count[wid])
        if d < 0:
            return
        act_force[d] = tau_explicit[d]
        pas_force[d] = scalar(0.0)
        lim_force[d] = scalar(0.0)

    return dof_forces


@functools.cache
def row_forces_kernel(np_dtype):
    """The State's forces ``lambda / dt`` by row family (docs/formulation.md §6.2)."""
    scalar, M = builder_types(np_dtype).take("scalar", "M")
    ix = index_funcs(np_dtype)
    ridx, row_kind, row_source, row_side = ix.ridx, ix.row_kind, ix.row_source, ix.row_side

    @wp.kernel(module="unique", enable_backward=False)
    def row_forces(
        # model (read only)
        m: M,
        # in
        inv_dt: scalar,
        row_stride: int,
        n_box: wp.array(dtype=wp.int32),
        failed: wp.array(dtype=wp.int32),
        impulse: wp.array(dtype=scalar),
        row_info: wp.array(dtype=wp.int32),
        # out
        act_force: wp.array(dtype=scalar),  # also read
        pas_force: wp.array(dtype=scalar),
        kin_force: wp.array(dtype=scalar),
        cpl_force: wp.array(dtype=scalar),
        lim_force: wp.array(dtype=scalar),
    ):
        """``lambda / dt`` of each box row into the State's field of its family."""
        wid, a = wp.tid()
        if a >= n_box[wid] or failed[wid] != 0:
            return
        r = ridx(m, row_stride, wid, a)
        f = impulse[r] * inv_dt
        src = row_source(row_info, r)
        t = row_kind(row_info, r)
        if t == ROW_ACTUATOR:
            act_force[src] += f
        elif t == ROW_PASSIVE:
            pas_force[src] = f
        elif t == ROW_JOINT:
            kin_force[src] = f
        elif t == ROW_COUPLING:
            cpl_force[src] = f
        elif t == ROW_LIMIT:
            lim_force[src] = row_side(row_info, r) * f

    return row_forces


@functools.cache
def commit_bodies_kernel(np_dtype):
    """The new body state committed (§6.2)."""
    vec6, transform, M = builder_types(np_dtype).take("vec6", "transform", "M")
    live_item = live_item_func(np_dtype)

    @wp.kernel(module="unique", enable_backward=False)
    def commit_bodies(
        # model (read only)
        m: M,
        # in
        failed: wp.array(dtype=wp.int32),
        q_new: wp.array(dtype=transform),
        u_new: wp.array(dtype=vec6),
        # out
        q: wp.array(dtype=transform),
        u: wp.array(dtype=vec6),
    ):
        """``q <- q+``, ``u <- u+`` in the worlds that did not fail."""
        wid, i = wp.tid()
        b = live_item(failed, wid, i, m.body_start[wid], m.body_count[wid])
        if b < 0:
            return
        q[b] = q_new[b]
        u[b] = u_new[b]

    return commit_bodies


@functools.cache
def commit_time_kernel(np_dtype):
    """The worlds' time and health after a step (docs/conventions.md, "World health")."""
    scalar = builder_types(np_dtype).scalar

    @wp.kernel(module="unique", enable_backward=False)
    def commit_time(
        # in
        dt: scalar,
        max_unconverged: int,
        # out
        converged: wp.array(dtype=wp.int32),  # also read
        frozen: wp.array(dtype=wp.int32),
        failed: wp.array(dtype=wp.int32),
        time: wp.array(dtype=scalar),
        unconverged: wp.array(dtype=wp.int32),
    ):
        """Advance the time of the worlds that stepped, and their health (docs/conventions.md, "World health"):
        a world that failed on this step (a non-finite result, a health bound passed: ``converged`` is then
        cleared) or whose PADMM has not converged for more than ``max_unconverged`` consecutive steps is frozen at
        its last sound state until the caller resets it."""
        wid = wp.tid()
        if frozen[wid] != 0:
            failed[wid] = 1
            converged[wid] = 0
            return
        if failed[wid] != 0:
            frozen[wid] = 1
            converged[wid] = 0
            return
        time[wid] = time[wid] + dt
        if converged[wid] != 0:
            unconverged[wid] = 0
        else:
            unconverged[wid] = unconverged[wid] + 1
            if unconverged[wid] > max_unconverged:
                failed[wid] = 1
                frozen[wid] = 1

    return commit_time


@functools.cache
def closure_check_kernel(np_dtype, screened: bool):
    """The loop-closure health check (docs/conventions.md, "World health"; :data:`LOOP_OPEN_BOUND`) of every world
    or, ``screened``, of the worlds post-stabilisation's extra pass projected."""
    scalar, transform, M = builder_types(np_dtype).take("scalar", "transform", "M")
    cts_residual = cts_residual_func(np_dtype)

    @wp.kernel(module="unique", enable_backward=False)
    def closure_check(
        # model (read only)
        m: M,
        # in
        bound: scalar,
        converged: wp.array(dtype=wp.int32),
        reproject: wp.array(dtype=wp.int32),
        q_new: wp.array(dtype=transform),
        q: wp.array(dtype=transform),
        # out
        failed: wp.array(dtype=wp.int32),
    ):
        """Flag ``failed`` on a world whose translational joint row ``i`` (an anchor gap) opens past ``bound`` in this
        step: ``|e(q_new)| > bound`` and ``|e(q_new)| > |e(q)|`` (a world assembled open, and closing, is not
        flagged). ``screened``: post-stabilisation's extra pass has screened the worlds (``post_stabilisation.py``),
        and a world it did not project has every anchor gap within ``REPROJECTION_GAP``, below ``bound``: only the
        projected worlds are checked."""
        wid, i = wp.tid()
        if i >= m.cts_count[wid] or failed[wid] != 0:
            return
        if wp.static(screened):
            if converged[wid] != 0 and reproject[wid] == 0:
                return
        c = m.cts_start[wid] + i
        if m.cts_kind[c] != RES_TRANS:
            return
        e_new = wp.abs(cts_residual(m, q_new, c))
        if e_new > bound or not wp.isfinite(e_new):
            if not (e_new <= wp.abs(cts_residual(m, q, c))):
                failed[wid] = 1

    return closure_check


@functools.cache
def speed_check_kernel(np_dtype):
    """The speed health check (docs/conventions.md, "World health"; ``kamino.config.HEALTH_TURN``,
    ``HEALTH_SPEED``)."""
    scalar, vec6, M = builder_types(np_dtype).take("scalar", "vec6", "M")
    sp = spatial_funcs(np_dtype)
    lin, ang = sp.lin, sp.ang

    @wp.kernel(module="unique", enable_backward=False)
    def speed_check(
        # model (read only)
        m: M,
        # in
        turn_rate: scalar,
        speed_bound: wp.array(dtype=scalar),
        u_new: wp.array(dtype=vec6),
        # out
        failed: wp.array(dtype=wp.int32),
    ):
        """Flag ``failed`` on a world whose body ``i`` ends the step turning faster than ``turn_rate``
        (``HEALTH_TURN / dt``) or moving faster than the world's ``speed_bound``
        (``kamino.tables.health_speed_bound``); a non-finite twist fails too."""
        wid, i = wp.tid()
        if i >= m.body_count[wid] or failed[wid] != 0:
            return
        u = u_new[m.body_start[wid] + i]
        v, w = lin(u), ang(u)
        vb = speed_bound[wid]
        if not (wp.dot(v, v) <= vb * vb) or not (wp.dot(w, w) <= turn_rate * turn_rate):
            failed[wid] = 1

    return speed_check
