"""One iteration of accelerated PADMM, as both PADMM schedules run it (one thread per world in ``solver.py``, 32
threads per world in ``solver_lanes.py``): a row's right-hand side (docs/formulation.md §7.3 steps 1-2), its
projection, dual update and residual terms (§7.3 steps 3-4, §7.5), the world's convergence test, the fast-ADMM
momentum with restart (§7.4), the penalty of the limit and contact rows and the saturation of effort-limited rows
(``kamino.jax_ref.solver.solve``, "Penalty", "Saturation", "Null directions"), and the move to the next iterate.

A schedule keeps only what is its own: which rows a thread visits (``for a in range(lane, n, lanes)``), where the
linear solve leaves ``x``, the block reductions of the world's :func:`residuals_struct` and the barriers. Each
``wp.func`` comes from a small builder cached per precision (and per compile-time mode where it has one).
"""

import functools

import numpy as np
import warp as wp

from kamino import config
from kamino.warp_backend.cone import cone_funcs
from kamino.warp_backend.indexing import index_funcs
from kamino.warp_backend.types import types_of
from kamino.warp_backend.workspace import builder_types

#: what :func:`momentum_func` asks the kernel to do with ``(y_hat, z_hat)``; ``RESTART_HERE``: a new penalty or a
#: saturating row restarts the momentum at the current iterate (``y_hat = y``, ``z_hat = z``)
NO_ACCELERATION, EXTRAPOLATE, RESTART, RESTART_HERE = 0, 1, 2, 3

#: Threads per world of the 32-thread schedule (one GPU warp).
LANES = 32


@wp.func_native("WP_TILE_SYNC();")
def sync():
    """Barrier of the threads of a block (``__syncthreads`` on CUDA, the fiber barrier on the CPU)."""
    ...


@functools.cache
def lane_reduce_func(np_dtype, lanes: int, op: str):
    """The world's ``op`` (``"max"`` or ``"sum"``) of a value over its ``lanes`` threads: a block reduction that
    every thread gets, or the value itself for one thread per world."""
    if op not in ("max", "sum"):
        raise ValueError(f"lane_reduce_func: op must be 'max' or 'sum', got {op!r}")
    scalar = types_of(np_dtype).scalar

    @wp.func
    def lane_reduce(v: scalar):
        """The world's maximum or sum of ``v``."""
        if wp.static(lanes == 1):
            return v
        if wp.static(op == "max"):
            return wp.tile_extract(wp.tile_max(wp.tile(v)), 0)
        return wp.tile_extract(wp.tile_sum(wp.tile(v)), 0)

    return lane_reduce


# --- what an iteration reads and what it carries to the next ------------------------------------------------------

@functools.cache
def problem_struct(np_dtype):
    """``Problem``: what every PADMM iteration of both schedules reads and never writes, the Warp counterpart of
    ``kamino.jax_ref.solver._Problem`` (scaled units, docs/formulation.md §7.2-§7.3). The launch's settings
    (``SolverConfig``), the worlds' row counts, reference scale and iteration caps, the rows' Jacobian blocks and
    scaling, their bounds and free velocity, the bodies' world-frame inverse inertia, and the pattern of the linear
    solve: ``sdiag`` (the dense factor's diagonal shifts) and ``cr_ent``, ``cr_end`` (Conjugate Residual's row blocks
    by body); a field a linear solve does not use is an empty array."""
    T = builder_types(np_dtype)
    farr, iarr = wp.array(dtype=T.scalar), wp.array(dtype=wp.int32)

    @wp.struct
    class Problem:
        row_stride: int  # storage distance between a world's consecutive rows (Work.row_stride)
        nblk: int  # blocks per row of the Jacobian
        cr_budget: int  # Conjugate Residual iterations per linear solve (SolverConfig.warp.cr_iterations)
        eta: T.scalar  # the proximal term (SolverConfig.penalty.eta)
        rho_free: T.scalar  # the always-active rows' penalty
        rho_box: T.scalar  # the penalty of a saturated effort-limited row
        tol: T.scalar  # the residuals' tolerance (§7.5)
        restart_tol: T.scalar  # the momentum's restart factor (§7.4)
        n_rows: iarr  # per world
        n_box: iarr
        p_ref: farr
        it_cap: iarr
        row_body: iarr  # per row
        row_J: wp.array(dtype=T.vec6)
        reg: farr
        P: farr
        ct_mu: farr
        vt: farr
        lo_s: farr
        hi_s: farr
        sdiag: farr
        inv_inertia_w: wp.array(dtype=T.mat33)  # per body
        cr_ent: iarr  # Conjugate Residual's pattern
        cr_end: iarr

    return Problem


@functools.cache
def carry_struct(np_dtype):
    """``Carry``: what a PADMM iteration hands to the next, across launches, the Warp counterpart of
    ``kamino.jax_ref.solver.Carry`` (§7.3-§7.5): per row the previous iterate ``x_p``, ``y_p``, ``z_p``, the
    extrapolated ``y_hat``, ``z_hat`` and the last dual residual vector ``e_p``; per world the iteration count
    ``iters``, the momentum ``a_p``, ``c_p``, the residuals ``r_p``, ``r_d``, ``r_c``, the limit and contact rows'
    penalty ``rho_u`` and the iteration of its last change ``k_rho``, ``converged``, ``done``, ``pending`` (a row
    saturated: the factor is redone before the next launch); and ``remaining``, the count of worlds still iterating
    (one entry)."""
    T = builder_types(np_dtype)
    farr, iarr = wp.array(dtype=T.scalar), wp.array(dtype=wp.int32)

    @wp.struct
    class Carry:
        x_p: farr  # per row
        y_p: farr
        z_p: farr
        y_hat: farr
        z_hat: farr
        e_p: farr
        iters: iarr  # per world
        a_p: farr
        c_p: farr
        r_p: farr
        r_d: farr
        r_c: farr
        rho_u: farr
        k_rho: iarr
        converged: iarr
        done: iarr
        pending: iarr
        remaining: iarr  # one entry

    return Carry


def fill_struct(struct_type, source, **values):
    """An instance of the ``wp.struct`` ``struct_type`` (:func:`problem_struct`, :func:`carry_struct`) whose fields
    are ``values``' entries, the others ``source``'s attributes of the same name (the ``Work`` arrays): the field
    list lives in the struct alone."""
    out = struct_type()
    for name in struct_type.vars:
        setattr(out, name, values[name] if name in values else getattr(source, name))
    return out


# --- the momentum and the penalty (§7.4) ---------------------------------------------------------------------

@functools.cache
def momentum_func(np_dtype, accelerate: bool):
    """§7.4 step 5, the fast-ADMM momentum with restart (``accelerate``, compile-time; else none).
    ``momentum(a_p, c_p, c_sum, restart_tol)``, once per iteration of a world."""
    scalar, vec4 = builder_types(np_dtype).take("scalar", "vec4")
    one = scalar(1.0)
    zero = scalar(0.0)

    @wp.func
    def momentum(a_p: scalar, c_p: scalar, c_sum: scalar, restart_tol: scalar):
        """``(a, c, beta, mode)`` from the previous momentum ``a_p``, the previous combined residual ``c_p`` and
        this iteration's ``c_sum``. ``mode`` (stored as a scalar): ``NO_ACCELERATION`` (``hat = new``),
        ``EXTRAPOLATE`` (``hat = new + beta (new - prev)``, the residual dropped by ``restart_tol``) or ``RESTART``
        (``hat = prev``, momentum reset, ``c = c_p / restart_tol``)."""
        if wp.static(not accelerate):
            return vec4(a_p, c_p, zero, scalar(NO_ACCELERATION))
        if c_sum < restart_tol * c_p:
            a_new = scalar(0.5) * (one + wp.sqrt(one + scalar(4.0) * a_p * a_p))
            return vec4(a_new, c_sum, (a_p - one) / a_new, scalar(EXTRAPOLATE))
        return vec4(one, c_p / restart_tol, zero, scalar(RESTART))

    return momentum


@functools.cache
def extrapolated_func(np_dtype):
    """§7.4: a row's next ``y_hat`` (or ``z_hat``) under a momentum mode.
    ``extrapolated(new, prev, beta, mode)`` (:func:`advance_row_func`)."""
    scalar = builder_types(np_dtype).scalar

    @wp.func
    def extrapolated(new: scalar, prev: scalar, beta: scalar, mode: int):
        """The next ``y_hat`` (or ``z_hat``) of a row after :func:`momentum_func`'s ``(beta, mode)``."""
        if mode == EXTRAPOLATE:
            return new + beta * (new - prev)
        if mode == RESTART:
            return prev
        return new

    return extrapolated


@functools.cache
def balanced_penalty_func(np_dtype):
    """The residual-balancing penalty of the limit and contact rows (``kamino.jax_ref.solver.solve``, "Penalty").
    ``balanced_penalty(rho_u, r_p, r_d, k, k_rho)`` (:func:`outcome_func`)."""
    scalar = builder_types(np_dtype).scalar
    one = scalar(1.0)
    tiny = scalar(float(np.finfo(np_dtype).tiny))
    interval, threshold = config.PENALTY_INTERVAL, scalar(config.PENALTY_THRESHOLD)
    max_factor, rho_min, rho_max = scalar(config.PENALTY_MAX_FACTOR), scalar(config.RHO_MIN), scalar(config.RHO_MAX)

    @wp.func
    def balanced_penalty(rho_u: scalar, r_p: scalar, r_d: scalar, k: int, k_rho: int):
        """The limit and contact rows' penalty after iteration ``k`` (the last change at ``k_rho``): residual
        balancing, ``rho_u sqrt(r_p / r_d)`` (the factor capped to ``[1 / PENALTY_MAX_FACTOR, PENALTY_MAX_FACTOR]``)
        clipped to ``[RHO_MIN, RHO_MAX]``, when ``PENALTY_INTERVAL`` iterations have passed and the balance is off by
        more than ``PENALTY_THRESHOLD``; else ``rho_u``."""
        if k - k_rho < interval:
            return rho_u
        ratio = wp.sqrt((r_p + tiny) / (r_d + tiny))
        if ratio > threshold or ratio * threshold < one:
            gain = wp.clamp(ratio, one / max_factor, max_factor)
            return wp.clamp(rho_u * gain, rho_min, rho_max)
        return rho_u

    return balanced_penalty


@functools.cache
def row_penalty_func(np_dtype):
    """A row's penalty (``kamino.jax_ref.solver.solve``, "Penalty" and "Saturation").
    ``row_penalty(row_info, r, a, nf, rho_free, rho_box, rho_u)``."""
    scalar = builder_types(np_dtype).scalar
    row_saturated = index_funcs(np_dtype).row_saturated

    @wp.func
    def row_penalty(row_info: wp.array(dtype=wp.int32), r: int, a: int, nf: int, rho_free: scalar, rho_box: scalar,
                    rho_u: scalar):
        """Row ``a``'s penalty: ``rho_free`` on a fixed row, ``rho_box`` on a saturated effort-limited one (a flag),
        the world's ``rho_u`` on limit and contact rows."""
        if a >= nf:
            return rho_u
        if row_saturated(row_info, r) != 0:
            return rho_box
        return rho_free

    return row_penalty


# --- a row's share of an iteration (§7.3, §7.5) ----------------------------------------------------------------

@functools.cache
def residuals_struct(np_dtype):
    """The world's residual terms of one iteration, as its rows fold them in (the schedule reduces them over its
    threads): the maxima ``r_p``, ``r_d``, ``r_c`` (§7.5), the sum ``c_sum`` of §7.4's combined residual, the
    null-direction test's ``r_tail``, ``de`` and ``dx`` (``kamino.jax_ref.solver.solve``, "Null directions") and
    ``hit`` (> 0: an effort-limited row's projection clipped it, "Saturation")."""
    scalar = builder_types(np_dtype).scalar

    @wp.struct
    class Residuals:
        r_p: scalar
        r_d: scalar
        r_c: scalar
        c_sum: scalar
        r_tail: scalar
        de: scalar
        dx: scalar
        hit: scalar

    return Residuals


@functools.cache
def residual_weight_func(np_dtype):
    """A row's residual weight (``kamino.jax_ref.solver.solve``, "Residuals").
    ``residual_weight(P, p_ref)`` (:func:`dual_update_func`, :func:`cr_residual_func`)."""
    scalar = builder_types(np_dtype).scalar
    one = scalar(1.0)
    loosening = scalar(config.RESIDUAL_LOOSENING_MAX)

    @wp.func
    def residual_weight(P: scalar, p_ref: scalar):
        """``1 / min(K P, p_ref)``, ``K = RESIDUAL_LOOSENING_MAX``: the row's scaled error as a velocity of the
        world's heaviest row, capped at ``K`` times its own velocity error."""
        return one / wp.min(loosening * P, p_ref)

    return residual_weight


@functools.cache
def dual_update_func(np_dtype):
    """§7.3 step 4 and a row's share of the residuals (§7.4, §7.5).
    ``dual_update(x, y, x_p, y_hat, z_hat, P, eta, rho, p_ref)``."""
    scalar, vec4 = builder_types(np_dtype).take("scalar", "vec4")
    residual_weight = residual_weight_func(np_dtype)

    @wp.func
    def dual_update(x: scalar, y: scalar, x_p: scalar, y_hat: scalar, z_hat: scalar, P: scalar, eta: scalar,
                    rho: scalar, p_ref: scalar):
        """``(z, w |x - y|, w |eta (x - x_p) + rho (y - y_hat)|, rho |P dy|^2 + |dz / P|^2 / rho)`` with ``w`` the
        row's :func:`residual_weight_func`; the world takes the maxima of the first two
        (``kamino.jax_ref.solver.solve``, "Residuals"). The last is the row's share of §7.4's combined residual."""
        z = z_hat + rho * (y - x)
        dy = P * (y - y_hat)
        dz = (z - z_hat) / P
        wgt = residual_weight(P, p_ref)
        return vec4(z, wgt * wp.abs(x - y), wgt * wp.abs(eta * (x - x_p) + rho * (y - y_hat)),
                    rho * dy * dy + dz * dz / rho)

    return dual_update


@functools.cache
def saturates_func(np_dtype):
    """Whether an effort-limited row saturates (``kamino.jax_ref.solver.solve``, "Saturation").
    ``saturates(sat, lo, hi, v, y)`` (:func:`box_row_func`, :func:`mark_saturated_func`)."""
    scalar = builder_types(np_dtype).scalar

    @wp.func
    def saturates(sat: int, lo: scalar, hi: scalar, v: scalar, y: scalar):
        """Whether a fixed row not yet saturated (``sat == 0``) saturates: it has a finite bound (an effort-limited
        actuator) and its projection ``y = clamp(v, lo, hi)`` clipped ``v = x - z_hat / rho``."""
        return sat == 0 and (wp.isfinite(lo) or wp.isfinite(hi)) and y != v

    return saturates


@functools.cache
def box_complementarity_func(np_dtype):
    """A box row's complementarity residual (§7.5).
    ``box_complementarity(y, z, lo, hi)`` (:func:`box_row_func`)."""
    scalar, inf = builder_types(np_dtype).take("scalar", "inf")

    @wp.func
    def box_complementarity(y: scalar, z: scalar, lo: scalar, hi: scalar):
        """``|z| * distance of y to its nearest finite bound`` (0 for an unbounded row)."""
        if not (wp.isfinite(lo) or wp.isfinite(hi)):
            return scalar(0.0)
        gap = inf
        if wp.isfinite(lo):
            gap = wp.abs(y - lo)
        if wp.isfinite(hi):
            gap = wp.min(gap, wp.abs(hi - y))
        return wp.abs(z) * gap

    return box_complementarity


@functools.cache
def row_rhs_func(np_dtype):
    """§7.3 steps 1-2: a row's right-hand side of the linear solve.
    ``row_rhs(vt, x_p, y_hat, z_hat, r, rho, eta)``."""
    scalar = builder_types(np_dtype).scalar

    @wp.func
    def row_rhs(vt: wp.array(dtype=scalar), x_p: wp.array(dtype=scalar), y_hat: wp.array(dtype=scalar),
                z_hat: wp.array(dtype=scalar), r: int, rho: scalar, eta: scalar):
        """``-v~_f + eta x_p + rho y_hat + z_hat`` of row ``r`` (penalty ``rho``); a contact's normal row also
        subtracts :func:`contact_correction_func`'s correction."""
        return -vt[r] + eta * x_p[r] + rho * y_hat[r] + z_hat[r]

    return row_rhs


@functools.cache
def contact_correction_func(np_dtype):
    """§7.3 step 1: the De Saxcé correction ``s = Gamma(z_hat)`` of a contact (docs/formulation.md §4.3).
    ``contact_correction(ct_mu, row_info, z_hat, r, rs)``."""
    scalar = builder_types(np_dtype).scalar
    de_saxce = cone_funcs(np_dtype).de_saxce
    row_mu = index_funcs(np_dtype).row_mu

    @wp.func
    def contact_correction(ct_mu: wp.array(dtype=scalar), row_info: wp.array(dtype=wp.int32),
                           z_hat: wp.array(dtype=scalar), r: int, rs: int):
        """The De Saxcé correction ``Gamma(z_hat)_n`` of the contact whose first row is ``r`` (rows ``rs`` apart)."""
        return de_saxce(z_hat[r], z_hat[r + rs], row_mu(ct_mu, row_info, r))

    return contact_correction


@functools.cache
def box_row_func(np_dtype, adaptive: bool):
    """§7.3 steps 3-4 on a box row (fixed or limit): projection, dual update and residual terms; ``adaptive``
    (compile-time): the penalty adapts, and the free fixed rows feed the null-direction test.
    ``box_row(row_info, lo_s, hi_s, x_p, y_hat, z_hat, P, y, z, e_p, r, a, nf, x, rho, eta, p_ref, acc)``."""
    scalar = builder_types(np_dtype).scalar
    Residuals = residuals_struct(np_dtype)
    dual_update = dual_update_func(np_dtype)
    saturates = saturates_func(np_dtype)
    box_complementarity = box_complementarity_func(np_dtype)
    row_saturated = index_funcs(np_dtype).row_saturated

    @wp.func
    def box_row(row_info: wp.array(dtype=wp.int32), lo_s: wp.array(dtype=scalar), hi_s: wp.array(dtype=scalar),
                x_p: wp.array(dtype=scalar), y_hat: wp.array(dtype=scalar), z_hat: wp.array(dtype=scalar),
                P: wp.array(dtype=scalar), y: wp.array(dtype=scalar), z: wp.array(dtype=scalar),
                e_p: wp.array(dtype=scalar), r: int, a: int, nf: int, x: scalar, rho: scalar, eta: scalar,
                p_ref: scalar, acc: Residuals) -> Residuals:
        """Row ``a`` (storage ``r``, the linear solve's ``x``, penalty ``rho``): ``y = clamp(x - z_hat / rho)``,
        ``z`` into ``y`` / ``z``, and its terms folded into ``acc``. A free fixed row (no finite bound) of an
        adaptive penalty feeds the null-direction test (``e_p``, ``de``, ``dx``) instead of ``r_tail``; an
        effort-limited fixed row whose projection clips it sets ``hit``."""
        out = acc
        zh = z_hat[r]
        lo = lo_s[r]
        hi = hi_s[r]
        v = x - zh / rho
        yr = wp.clamp(v, lo, hi)
        y[r] = yr
        if a < nf and saturates(row_saturated(row_info, r), lo, hi, v, yr):
            out.hit = scalar(1.0)
        du = dual_update(x, yr, x_p[r], y_hat[r], zh, P[r], eta, rho, p_ref)
        z[r] = du[0]
        out.r_p = wp.max(acc.r_p, du[1])
        out.r_d = wp.max(acc.r_d, du[2])
        out.c_sum = acc.c_sum + du[3]
        out.r_c = wp.max(acc.r_c, box_complementarity(yr, du[0], lo, hi))
        if wp.static(adaptive) and a < nf and not (wp.isfinite(lo) or wp.isfinite(hi)):
            e = eta * (x - x_p[r]) + rho * (yr - y_hat[r])
            out.de = wp.max(acc.de, wp.abs(e - e_p[r]))
            out.dx = wp.max(acc.dx, wp.abs(x - x_p[r]))
            e_p[r] = e
        else:
            out.r_tail = wp.max(acc.r_tail, du[2])
        return out

    return box_row


@functools.cache
def contact_rows_func(np_dtype):
    """§7.3 steps 3-4 on a contact's three rows: the cone projection, dual update and residual terms.
    ``contact_rows(ct_mu, row_info, z_hat, x, x_p, y_hat, P, y, z, r, rs, x3, inv_rho, rho, eta, p_ref, acc)``
    returns ``acc`` with the contact's terms."""
    scalar, vec3 = builder_types(np_dtype).take("scalar", "vec3")
    Residuals = residuals_struct(np_dtype)
    dual_update = dual_update_func(np_dtype)
    cone_project = cone_funcs(np_dtype).cone_project
    row_mu = index_funcs(np_dtype).row_mu

    @wp.func
    def contact_rows(ct_mu: wp.array(dtype=scalar), row_info: wp.array(dtype=wp.int32),
                     z_hat: wp.array(dtype=scalar), x: wp.array(dtype=scalar), x_p: wp.array(dtype=scalar),
                     y_hat: wp.array(dtype=scalar), P: wp.array(dtype=scalar), y: wp.array(dtype=scalar),
                     z: wp.array(dtype=scalar), r: int, rs: int, x3: vec3, inv_rho: scalar, rho: scalar, eta: scalar,
                     p_ref: scalar, acc: Residuals) -> Residuals:
        """The contact whose first row is ``r`` (rows ``rs`` apart, the linear solve's ``x3``, penalty ``rho =
        1 / inv_rho``): ``y = Pi_K(x3 - z_hat / rho)``, ``z`` into ``y`` / ``z``, its terms folded into ``acc``
        (complementarity ``|y . z|``)."""
        out = acc
        cp = cone_project(x3[0] - inv_rho * z_hat[r], x3[1] - inv_rho * z_hat[r + rs],
                          x3[2] - inv_rho * z_hat[r + 2 * rs], row_mu(ct_mu, row_info, r))
        yz = scalar(0.0)
        for t in range(3):
            rt = r + t * rs
            yt = cp[t]
            y[rt] = yt
            du = dual_update(x[rt], yt, x_p[rt], y_hat[rt], z_hat[rt], P[rt], eta, rho, p_ref)
            z[rt] = du[0]
            out.r_p = wp.max(out.r_p, du[1])
            out.r_d = wp.max(out.r_d, du[2])
            out.r_tail = wp.max(out.r_tail, du[2])
            out.c_sum = out.c_sum + du[3]
            yz += yt * du[0]
        out.r_c = wp.max(out.r_c, wp.abs(yz))
        return out

    return contact_rows


@functools.cache
def cr_residual_func(np_dtype):
    """The Conjugate Residual solve's share of the dual residual (§8.2).
    ``cr_residual(P, cr_r, r, p_ref, acc)`` returns ``acc`` with row ``r``'s terms."""
    scalar = builder_types(np_dtype).scalar
    Residuals = residuals_struct(np_dtype)
    residual_weight = residual_weight_func(np_dtype)

    @wp.func
    def cr_residual(P: wp.array(dtype=scalar), cr_r: wp.array(dtype=scalar), r: int, p_ref: scalar,
                    acc: Residuals) -> Residuals:
        """Row ``r`` of the inner solve's residual ``b - A x`` (``cr_r``), a scaled velocity like the dual
        residual's rows, folded into ``r_d`` and ``r_tail``: an inexact solve (a small ``cr_iterations`` budget)
        must not let the world report convergence."""
        out = acc
        e_cr = residual_weight(P[r], p_ref) * wp.abs(cr_r[r])
        out.r_d = wp.max(acc.r_d, e_cr)
        out.r_tail = wp.max(acc.r_tail, e_cr)
        return out

    return cr_residual


@functools.cache
def reduce_residuals_func(np_dtype, lanes: int):
    """The world's residual terms from its threads' (block reductions; nothing for one thread per world).
    ``reduce_residuals(acc)``; every thread of the world gets the result."""
    Residuals = residuals_struct(np_dtype)
    lane_max = lane_reduce_func(np_dtype, lanes, "max")
    lane_sum = lane_reduce_func(np_dtype, lanes, "sum")

    @wp.func
    def reduce_residuals(acc: Residuals) -> Residuals:
        """The maxima and the sum of :func:`residuals_struct` over the world's threads."""
        if wp.static(lanes == 1):
            return acc
        out = acc
        out.r_p = lane_max(acc.r_p)
        out.r_d = lane_max(acc.r_d)
        out.r_c = lane_max(acc.r_c)
        out.c_sum = lane_sum(acc.c_sum)
        out.r_tail = lane_max(acc.r_tail)
        out.de = lane_max(acc.de)
        out.dx = lane_max(acc.dx)
        out.hit = lane_max(acc.hit)
        return out

    return reduce_residuals


# --- the world's decision after an iteration (§7.4, §7.5) ------------------------------------------------------

@functools.cache
def outcome_struct(np_dtype):
    """What the world does after an iteration: ``converged``, ``saturates`` (an effort-limited row saturates:
    ``rho_box`` on it from now on, "Saturation"), the limit and contact rows' next penalty ``rho`` and the momentum
    ``mom = (a, c, beta, mode)`` (§7.4; ``mode`` ``RESTART_HERE`` after a new penalty or a saturation)."""
    scalar, vec4 = builder_types(np_dtype).take("scalar", "vec4")

    @wp.struct
    class Outcome:
        converged: int
        saturates: int
        rho: scalar
        mom: vec4

    return Outcome


@functools.cache
def outcome_func(np_dtype, adaptive: bool, accelerate: bool):
    """The convergence test (§7.5 and "Null directions"), the penalty rule and the momentum (§7.4) of a world after
    an iteration; compile-time: ``adaptive``, the penalty adapts; ``accelerate``, the momentum extrapolates."""
    scalar, vec4 = builder_types(np_dtype).take("scalar", "vec4")
    Residuals = residuals_struct(np_dtype)
    Outcome = outcome_struct(np_dtype)
    momentum = momentum_func(np_dtype, accelerate)
    balanced_penalty = balanced_penalty_func(np_dtype)
    big = scalar(float(np.finfo(np_dtype).max))
    null_ratio = scalar(config.NULL_DIRECTION_RATIO)
    zero = scalar(0.0)

    @wp.func
    def outcome(a_p: wp.array(dtype=scalar), c_p: wp.array(dtype=scalar), k_rho: wp.array(dtype=wp.int32), wid: int,
                acc: Residuals, k: int, n: int, nf: int, rho_u: scalar, tol: scalar, eta: scalar, rho_free: scalar,
                restart_tol: scalar) -> Outcome:
        """Iteration ``k`` of world ``wid`` (``n`` rows, ``nf`` fixed, the world's reduced ``acc``): converged when
        every residual is below ``tol`` from ``k = 2`` on, or along a numerically null direction (the free rows'
        change of ``e`` small against the change of ``x``; ``e_p`` of iteration 1 is stale); else (adaptive) a
        saturating row or a rebalanced penalty restarts the momentum here. Reads the world's ``a_p``, ``c_p`` and
        ``k_rho``, writes nothing."""
        out = Outcome()
        conv = k >= 2 and acc.r_p <= tol and acc.r_d <= tol and acc.r_c <= tol
        if k >= 2 and acc.r_p <= tol and acc.r_tail <= tol and acc.r_c <= tol and acc.dx > zero:
            if acc.de <= null_ratio * (eta + rho_free) * acc.dx:
                conv = True
        out.converged = int(conv)
        out.rho = rho_u
        if wp.static(adaptive):
            out.saturates = int(acc.hit > zero and not conv)
            if n > nf and not conv:
                out.rho = balanced_penalty(rho_u, acc.r_p, acc.r_d, k, k_rho[wid])
        if out.saturates != 0 or out.rho != rho_u:
            out.mom = vec4(scalar(1.0), big, zero, scalar(RESTART_HERE))
        else:
            out.mom = momentum(a_p[wid], c_p[wid], acc.c_sum, restart_tol)
        return out

    return outcome


@functools.cache
def mark_saturated_func(np_dtype):
    """An effort-limited row that saturated takes ``rho_box`` from now on (``kamino.jax_ref.solver.solve``,
    "Saturation"). ``mark_saturated(lo_s, hi_s, x, z_hat, y, row_info, r, rho_free)``."""
    scalar = builder_types(np_dtype).scalar
    row_saturated = index_funcs(np_dtype).row_saturated
    set_saturated = index_funcs(np_dtype).set_saturated
    saturates = saturates_func(np_dtype)

    @wp.func
    def mark_saturated(lo_s: wp.array(dtype=scalar), hi_s: wp.array(dtype=scalar), x: wp.array(dtype=scalar),
                       z_hat: wp.array(dtype=scalar), y: wp.array(dtype=scalar), row_info: wp.array(dtype=wp.int32),
                       r: int, rho_free: scalar):
        """Flag fixed row ``r`` saturated (in ``row_info``) if its last projection (penalty ``rho_free``) clipped
        it."""
        if saturates(row_saturated(row_info, r), lo_s[r], hi_s[r], x[r] - z_hat[r] / rho_free, y[r]):
            set_saturated(row_info, r, 1)

    return mark_saturated


@functools.cache
def advance_row_func(np_dtype):
    """§7.4 steps 5-6 on a row: the next ``(y_hat, z_hat)`` and the previous iterate.
    ``advance_row(y, z, x_p, y_p, z_p, y_hat, z_hat, r, x, mom)``."""
    scalar, vec4 = builder_types(np_dtype).take("scalar", "vec4")
    extrapolated = extrapolated_func(np_dtype)

    @wp.func
    def advance_row(y: wp.array(dtype=scalar), z: wp.array(dtype=scalar), x_p: wp.array(dtype=scalar),
                    y_p: wp.array(dtype=scalar), z_p: wp.array(dtype=scalar), y_hat: wp.array(dtype=scalar),
                    z_hat: wp.array(dtype=scalar), r: int, x: scalar, mom: vec4):
        """Row ``r`` moves to the next iteration under the momentum ``mom`` (:func:`outcome_func`): ``y_hat``,
        ``z_hat`` from ``y``, ``z`` (restarted here, or :func:`extrapolated_func`), and ``(x, y, z)`` kept as the
        previous iterate (``x_p``, ``y_p``, ``z_p``)."""
        yr = y[r]
        zr = z[r]
        mode = int(mom[3])
        if mode == RESTART_HERE:
            y_hat[r] = yr
            z_hat[r] = zr
        else:
            y_hat[r] = extrapolated(yr, y_p[r], mom[2], mode)
            z_hat[r] = extrapolated(zr, z_p[r], mom[2], mode)
        x_p[r] = x
        y_p[r] = yr
        z_p[r] = zr

    return advance_row


@functools.cache
def store_world_func(np_dtype):
    """The world's scalars after an iteration (one thread writes them).
    ``store_world(a_p, c_p, iters, r_p, r_d, r_c, converged, done, remaining, wid, k, acc, res, finished)``."""
    scalar = builder_types(np_dtype).scalar
    Residuals = residuals_struct(np_dtype)
    Outcome = outcome_struct(np_dtype)

    @wp.func
    def store_world(a_p: wp.array(dtype=scalar), c_p: wp.array(dtype=scalar), iters: wp.array(dtype=wp.int32),
                    r_p: wp.array(dtype=scalar), r_d: wp.array(dtype=scalar), r_c: wp.array(dtype=scalar),
                    converged: wp.array(dtype=wp.int32), done: wp.array(dtype=wp.int32),
                    remaining: wp.array(dtype=wp.int32), wid: int, k: int, acc: Residuals, res: Outcome,
                    finished: bool):
        """Iteration ``k``'s momentum, count and residuals; once ``finished`` the world is ``done`` and leaves
        ``remaining``."""
        a_p[wid] = res.mom[0]
        c_p[wid] = res.mom[1]
        iters[wid] = k
        r_p[wid] = acc.r_p
        r_d[wid] = acc.r_d
        r_c[wid] = acc.r_c
        if finished:
            converged[wid] = res.converged
            done[wid] = 1
            wp.atomic_sub(remaining, 0, 1)

    return store_world


@functools.cache
def tail_dot_func(np_dtype):
    """The dot products of the tail rows' dense Cholesky ``L_t = chol(S_t + shift I)`` (``linear_solve.factor_tail``,
    ``solver_lanes.factor_tail``; ``kamino.jax_ref.solver.solve``, "Penalty")."""
    scalar = builder_types(np_dtype).scalar

    @wp.func
    def tail_dot(tail: wp.array(dtype=scalar), tc: int, tr: int, jr: int, kt: int, j: int, s: scalar):
        """``s - sum_{i < j} L_t[t, i] L_t[j, i]`` with tail rows ``t``, ``j`` at ``tr``, ``jr`` of ``tail`` (slots
        ``tc`` apart, ``L_t`` from slot ``kt``), ``i`` ascending: entry ``(t, j)`` of ``L_t`` before its square root
        (``t = j``) or its division by ``L_t[j, j]``."""
        for i in range(j):
            s -= tail[tr + (kt + i) * tc] * tail[jr + (kt + i) * tc]
        return s

    return tail_dot
