"""Narrow-phase collision between two convex geoms, as Warp functions (float32 or float64).

A port of :mod:`kamino.jax_ref.collision` (read its module docstring for the pairs, the algorithms,
the accuracy and the degenerate fallbacks): the same candidate points, in the same order, by the
same algorithms (the same SAT axes and 5 % edge bias, the same golden-section, bisection and
alternating-projection iteration counts, the same tolerances), so that both backends produce the
same contacts up to rounding. The Warp backend does not import the JAX one. The candidate points
feed the contacts of docs/formulation.md §4.2 (:mod:`kamino.warp_backend.contacts`).

``collide_pair_func(np_dtype)`` builds, once per precision, the ``@wp.func`` ``collide_pair``::

    collide_pair(type_a: int, type_b: int, pose_a: transform, size_a: vec3, pose_b: transform,
                 size_b: vec3, margin: scalar, base: int, out_pos: wp.array(dtype=vec3),
                 out_normal: wp.array(dtype=vec3), out_dist: wp.array(dtype=scalar),
                 out_valid: wp.array(dtype=wp.int32))

which writes the ``K = MAX_POINTS[(type_a, type_b)]`` candidate points of one pair (``type_a <=
type_b``) into the slots ``base .. base + K - 1``: ``pos`` (midpoint of the witness points),
``normal`` (unit, from geom a to geom b), ``dist`` (signed, < 0 penetration) and ``valid`` (int32
1 where the point exists and ``dist <= margin``). Every written entry is finite. An unsupported or
unordered pair writes nothing (the JAX backend raises a ``ValueError`` instead; on the host,
:func:`max_points` raises it). ``collide_kernel(np_dtype)`` is a kernel calling it, one thread per pair.

A pair whose geom b is a heightfield (``GeomType.HFIELD``) also needs its grid, so it has its own entry,
``collide_hfield_func(np_dtype)``'s ``@wp.func``::

    collide_hfield(type_a: int, pose_a: transform, size_a: vec3, pose_b: transform,
                   hf_data: wp.array(dtype=scalar), hf_adr: int, hf_nrow: int, hf_ncol: int,
                   hf_size: vec4, margin: scalar, base: int, out_pos, out_normal, out_dist, out_valid)

with the grid's normalised heights starting at ``hf_data[hf_adr]``, ``hf_nrow x hf_ncol`` of them,
and ``hf_size = (rx, ry, z_top, z_base)`` (``kamino.Model.hfield_*``); the outputs are those of
``collide_pair``. ``collide_hfield_kernel(np_dtype)`` is a kernel calling it, one thread per pair.

The routines come from small builders cached per precision, each named after what it builds: the
per-pair routines (:func:`plane_pair_funcs`, :func:`sphere_capsule_pair_funcs`,
:func:`sdf_pair_funcs`, :func:`box_box_func`, :func:`cylinder_pair_funcs`, :func:`hfield_funcs`)
and the helpers they share (:func:`basic_funcs`, :func:`box_feature_funcs`, :func:`sdf_funcs`,
:func:`face_interval_funcs`, :func:`search_funcs`, :func:`segment_funcs`, the box-box steps and the
cylinder families). The pair types stay runtime values: they vary from pair to pair within a world.

Poses are Warp transforms (position, then the quaternion ``(x, y, z, w)``: the same 7 numbers as
the JAX pose), sizes ``vec3`` as in :class:`kamino.model.GeomType`.

Compile-time notes: the fixed-size loops with more than a handful of iterations (box-box
candidates and edge pairs, the searches) are written with bounds that Warp keeps as dynamic loops,
and kernels calling ``collide_pair`` should be built with ``enable_backward=False`` (there is no
adjoint of the searches); :data:`KERNEL_OPTIONS` are the module options used here.
"""

import functools
import math
from types import SimpleNamespace

import numpy as np
import warp as wp

from kamino.config import BISECTION_STEPS, GOLDEN_STEPS, PARALLEL_SIN2, PROJECTION_ROUNDS
from kamino.model import CONTACT_POINTS, GeomType
from kamino.warp_backend.types import types_of

#: candidate points per supported pair (``type_a <= type_b``): the model's table (``kamino.model.CONTACT_POINTS``)
MAX_POINTS = CONTACT_POINTS

KERNEL_OPTIONS: dict[str, object] = {"enable_backward": False}
"""Module options of :func:`collide_kernel` (forward only)."""

_EDGE_BIAS_REL = 0.05  # an edge axis must beat the best face axis by 5 % of its separation ...
_EDGE_BIAS_ABS = 1e-5  # ... plus this fraction of the boxes' size

PLANE, SPHERE, CAPSULE = int(GeomType.PLANE), int(GeomType.SPHERE), int(GeomType.CAPSULE)
BOX, CYLINDER, ELLIPSOID = int(GeomType.BOX), int(GeomType.CYLINDER), int(GeomType.ELLIPSOID)
HFIELD = int(GeomType.HFIELD)

_func = functools.partial(wp.func, module="unique")  # one module per func: no key clash between precisions


def _namespace(*funcs: wp.Function) -> SimpleNamespace:
    """The Warp functions of a builder, by name."""
    return SimpleNamespace(**{f.func.__name__: f for f in funcs})


def max_points(type_a: int, type_b: int) -> int:
    """``K`` of an ordered pair of geom types (``ValueError`` for an unsupported or unordered pair)."""
    try:
        pair = (GeomType(int(type_a)), GeomType(int(type_b)))
    except (TypeError, ValueError) as err:
        raise ValueError(f"collide: unknown geom type in pair ({type_a!r}, {type_b!r})") from err
    if pair not in MAX_POINTS:
        raise ValueError(f"collide: unsupported or unordered geom pair ({pair[0].name}, {pair[1].name})")
    return MAX_POINTS[pair]


@functools.cache
def _constants(np_dtype) -> SimpleNamespace:
    """The narrow phase's numbers in one precision, rounded once like the Python floats of the JAX code
    (``_rtol``, ``_tie_tol`` and the literals of :mod:`kamino.jax_ref.collision`), and its fixed-size
    vector and matrix types."""
    T = types_of(np_dtype)
    scalar, dt = T.scalar, T.np_dtype
    f64 = dt == np.float64
    rtol = 1e-7 if f64 else 1e-4  # _rtol
    tie = 1e-12 if f64 else 1e-5  # _tie_tol
    return SimpleNamespace(
        vec24=wp.types.vector(24, scalar), vec24i=wp.types.vector(24, wp.int32), vec8i=wp.types.vector(8, wp.int32),
        mat43=wp.types.matrix((4, 3), scalar),
        EPS2=scalar(float(np.finfo(dt).eps) ** 2), TINY=scalar(float(np.finfo(dt).tiny) ** 0.5),
        RTOL=scalar(rtol), RTOL2=scalar(rtol * rtol), RTOL10=scalar(10.0 * rtol), TIE=scalar(tie),
        INF=scalar(math.inf), ZERO=scalar(0.0), HALF=scalar(0.5), ONE=scalar(1.0), TWO=scalar(2.0),
        GOLD=scalar((math.sqrt(5.0) - 1.0) / 2.0), SQRT3_2=scalar(0.5 * math.sqrt(3.0)), MILLI=scalar(1e-3),
        PAR=scalar(PARALLEL_SIN2), BIAS_REL=scalar(_EDGE_BIAS_REL), BIAS_ABS=scalar(_EDGE_BIAS_ABS),
    )


@_func
def quad_x(c: int) -> int:
    """x sign of corner ``c`` of a face quad ``(1, 1), (-1, 1), (-1, -1), (1, -1)`` (``_QUAD``)."""
    return wp.where(c == 0 or c == 3, 1, -1)


@_func
def quad_y(c: int) -> int:
    """y sign of corner ``c`` of a face quad (``_QUAD``)."""
    return wp.where(c < 2, 1, -1)


@functools.cache
def basic_funcs(np_dtype) -> SimpleNamespace:
    """Small helpers of every routine: the rotation of a quaternion, matrix columns, the guarded
    normalisation, sign and division of :mod:`kamino.jax_ref.collision` (``_normalize``, ``_sign``,
    ``_safe_div``), ``clip01`` and ``put_point``, the writer of one candidate point."""
    T = types_of(np_dtype)
    scalar, vec3, quat, mat33 = T.scalar, T.vec3, T.quat, T.mat33
    K = _constants(np_dtype)
    EPS2, TINY, ZERO, ONE, TWO = K.EPS2, K.TINY, K.ZERO, K.ONE, K.TWO

    @_func
    def rot(q: quat) -> mat33:
        """Rotation matrix of a unit quaternion ``(x, y, z, w)`` (``kamino.spatial.quat_to_matrix``)."""
        x, y, z, w = q[0], q[1], q[2], q[3]
        return mat33(
            ONE - TWO * (y * y + z * z), TWO * (x * y - z * w), TWO * (x * z + y * w),
            TWO * (x * y + z * w), ONE - TWO * (x * x + z * z), TWO * (y * z - x * w),
            TWO * (x * z - y * w), TWO * (y * z + x * w), ONE - TWO * (x * x + y * y),
        )

    @_func
    def col(R: mat33, k: int) -> vec3:
        """Column ``k`` of ``R`` (``R[:, k]``)."""
        return vec3(R[0, k], R[1, k], R[2, k])

    @_func
    def normalize(v: vec3, fallback: vec3):
        """``(v / |v|, |v|)``, ``(fallback, 0)`` where ``|v|`` is ~0 (``_normalize``)."""
        n2 = wp.dot(v, v)
        if n2 > EPS2:
            n = wp.sqrt(n2)
            return v / n, n
        return fallback, ZERO

    @_func
    def sign(x: scalar) -> scalar:
        """``+1`` for ``x >= 0``, else ``-1`` (``_sign``)."""
        return wp.where(x >= ZERO, ONE, -ONE)

    @_func
    def safe_div(num: scalar, den: scalar) -> scalar:
        """``num / den``, 0 where ``den`` is ~0 (``_safe_div``)."""
        if wp.abs(den) > TINY:
            return num / den
        return ZERO

    @_func
    def clip01(x: scalar) -> scalar:
        """``clip(x, 0, 1)``."""
        return wp.min(wp.max(x, ZERO), ONE)

    @_func
    def put_point(slot: int, pos: vec3, normal: vec3, dist: scalar, exists: bool, margin: scalar,
                  out_pos: wp.array(dtype=vec3), out_normal: wp.array(dtype=vec3), out_dist: wp.array(dtype=scalar),
                  out_valid: wp.array(dtype=wp.int32)):
        """Write one candidate point; valid = exists and ``dist <= margin``."""
        out_pos[slot] = pos
        out_normal[slot] = normal
        out_dist[slot] = dist
        out_valid[slot] = wp.where(exists and dist <= margin, 1, 0)

    return _namespace(rot, col, normalize, sign, safe_div, clip01, put_point)


@functools.cache
def box_feature_funcs(np_dtype) -> SimpleNamespace:
    """The corners and edges of a box in the fixed orders of ``_box_corners`` and ``_box_edges``
    (:mod:`kamino.jax_ref.collision`)."""
    T = types_of(np_dtype)
    scalar, vec3, mat33 = T.scalar, T.vec3, T.mat33
    TWO = _constants(np_dtype).TWO

    @_func
    def box_corner(c: vec3, R: mat33, half: vec3, i: int) -> vec3:
        """Corner ``i`` of a box in the ``itertools.product((-1, 1), repeat=3)`` order (``_box_corners``)."""
        s = vec3(scalar(2 * ((i // 4) % 2) - 1), scalar(2 * ((i // 2) % 2) - 1), scalar(2 * (i % 2) - 1))
        return c + R * wp.cw_mul(s, half)

    @_func
    def box_edge(c: vec3, R: mat33, half: vec3, e: int):
        """Start point and direction vector of box edge ``e`` in the fixed order of ``_box_edges``
        (axis ``e // 4``, then the sign pattern of the two other coordinates)."""
        i = e // 4
        mid = vec3()
        mid[(i + 1) % 3] = scalar(2 * ((e // 2) % 2) - 1) * half[(i + 1) % 3]
        mid[(i + 2) % 3] = scalar(2 * (e % 2) - 1) * half[(i + 2) % 3]
        d = vec3()
        d[i] = half[i]
        dw = R * d
        return c + R * mid - dw, TWO * dw

    return _namespace(box_corner, box_edge)


@functools.cache
def sdf_funcs(np_dtype) -> SimpleNamespace:
    """Signed distances of the primitive solids (``_box_sdf``, ``_cylinder_sdf``, ``_world_sdf``,
    ``_project`` of :mod:`kamino.jax_ref.collision`): local and world frame, with the outward normal and
    the nearest surface point, and the projection onto the solid."""
    T = types_of(np_dtype)
    scalar, vec3, mat33 = T.scalar, T.vec3, T.mat33
    K = _constants(np_dtype)
    ZERO, ONE = K.ZERO, K.ONE
    bf = basic_funcs(np_dtype)
    normalize, sign = bf.normalize, bf.sign

    @_func
    def box_sdf(p: vec3, half: vec3):
        """Signed distance from local ``p`` to the box, outward normal at the nearest surface point and
        that point; inside, out through the face of least depth, the first on ties (``_box_sdf``)."""
        q = vec3(wp.abs(p[0]) - half[0], wp.abs(p[1]) - half[1], wp.abs(p[2]) - half[2])
        k = int(0)
        for i in range(1, 3):
            if q[i] > q[k]:
                k = i
        face_n = vec3()
        face_n[k] = sign(p[k])
        face_pt = vec3(p[0], p[1], p[2])
        face_pt[k] = sign(p[k]) * half[k]
        clamped = vec3(wp.min(wp.max(p[0], -half[0]), half[0]), wp.min(wp.max(p[1], -half[1]), half[1]),
                       wp.min(wp.max(p[2], -half[2]), half[2]))
        if q[0] > ZERO or q[1] > ZERO or q[2] > ZERO:
            n_out, d_out = normalize(p - clamped, face_n)
            return d_out, n_out, clamped
        return q[k], face_n, face_pt

    @_func
    def cylinder_sdf(p: vec3, radius: scalar, half_height: scalar):
        """Signed distance from local ``p`` to the solid cylinder (axis local z), outward normal at the
        nearest surface point and that point; inside, out through the side or a cap, whichever is
        nearer, the side on ties (``_cylinder_sdf``)."""
        e_r, rho = normalize(vec3(p[0], p[1], ZERO), vec3(ONE, ZERO, ZERO))
        z = p[2]
        qr = rho - radius
        qz = wp.abs(z) - half_height
        in_n = vec3(ZERO, ZERO, sign(z))
        in_pt = vec3(p[0], p[1], sign(z) * half_height)
        if qr >= qz:
            in_n = e_r
            in_pt = vec3(radius * e_r[0], radius * e_r[1], z)
        rc = wp.min(rho, radius)
        clamped = vec3(rc * e_r[0], rc * e_r[1], wp.min(wp.max(z, -half_height), half_height))
        if qr > ZERO or qz > ZERO:
            n_out, d_out = normalize(p - clamped, in_n)
            return d_out, n_out, clamped
        return wp.max(qr, qz), in_n, in_pt

    @_func
    def sdf(gtype: int, size: vec3, p: vec3):
        """Local signed distance of a BOX or (otherwise) a CYLINDER of ``size``."""
        if gtype == BOX:
            return box_sdf(p, size)
        return cylinder_sdf(p, size[0], size[1])

    @_func
    def sdf_world(gtype: int, size: vec3, c: vec3, R: mat33, x: vec3):
        """``sdf`` of the geom at ``(c, R)`` for the world point ``x``: distance, world outward normal,
        world nearest surface point (``_world_sdf``)."""
        d, n, q = sdf(gtype, size, wp.transpose(R) * (x - c))
        return d, R * n, c + R * q

    @_func
    def dist_world(gtype: int, size: vec3, c: vec3, R: mat33, x: vec3) -> scalar:
        """The distance of ``sdf_world`` only."""
        d, n, q = sdf_world(gtype, size, c, R, x)
        return d

    @_func
    def project(gtype: int, size: vec3, c: vec3, R: mat33, y: vec3) -> vec3:
        """Nearest point of the solid to ``y`` (``y`` itself inside) (``_project``)."""
        d, _n, q = sdf_world(gtype, size, c, R, y)
        return wp.where(d > ZERO, q, y)

    return _namespace(box_sdf, cylinder_sdf, sdf, sdf_world, dist_world, project)


@functools.cache
def face_interval_funcs(np_dtype) -> SimpleNamespace:
    """The ``t``-intervals where a segment lies over the touched feature of a box or cylinder
    (``_slab_interval``, ``_box_face_interval``, ``_cylinder_face_interval`` of
    :mod:`kamino.jax_ref.collision`): the second point of the capsule pairs."""
    T = types_of(np_dtype)
    scalar, vec3 = T.scalar, T.vec3
    K = _constants(np_dtype)
    TINY, INF, ZERO = K.TINY, K.INF, K.ZERO

    @_func
    def slab(p0: scalar, d: scalar, half: scalar):
        """Interval of ``t`` with ``|p0 + t d| <= half`` (empty: lo > hi) (``_slab_interval``)."""
        inside = wp.abs(p0) <= half
        if wp.abs(d) > TINY:
            ta = (-half - p0) / d
            tb = (half - p0) / d
            return wp.min(ta, tb), wp.max(ta, tb)
        if inside:
            return -INF, INF
        return INF, -INF

    @_func
    def box_face_interval(p0: vec3, d: vec3, n_out: vec3, half: vec3):
        """``t``-interval where the segment ``p0 + t d`` lies over the box face whose normal is the
        dominant direction of ``n_out``, box frame (``_box_face_interval``)."""
        k = int(0)
        for i in range(1, 3):
            if wp.abs(n_out[i]) > wp.abs(n_out[k]):
                k = i
        lo = -INF
        hi = INF
        for i in range(3):
            if i != k:
                a, b = slab(p0[i], d[i], half[i])
                lo = wp.max(lo, a)
                hi = wp.min(hi, b)
        return lo, hi

    @_func
    def cylinder_face_interval(p0: vec3, d: vec3, n_out: vec3, radius: scalar, half_height: scalar):
        """``t``-interval where the segment lies over the cylinder feature touched with normal ``n_out``:
        the cap disk for a cap normal, the axial band for a side normal (``_cylinder_face_interval``)."""
        if wp.abs(n_out[2]) >= wp.sqrt(n_out[0] * n_out[0] + n_out[1] * n_out[1]):
            a = d[0] * d[0] + d[1] * d[1]
            b = p0[0] * d[0] + p0[1] * d[1]
            c = p0[0] * p0[0] + p0[1] * p0[1] - radius * radius
            disc = b * b - a * c
            if a > TINY:
                if disc >= ZERO:
                    root = wp.sqrt(wp.max(disc, ZERO))
                    return (-b - root) / a, (-b + root) / a
                return INF, -INF
            if c <= ZERO:
                return -INF, INF
            return INF, -INF
        return slab(p0[2], d[2], half_height)

    @_func
    def face_interval(gtype: int, size: vec3, p0: vec3, d: vec3, n_out: vec3):
        """``_box_face_interval`` for a BOX, else ``_cylinder_face_interval``."""
        if gtype == BOX:
            return box_face_interval(p0, d, n_out, size)
        return cylinder_face_interval(p0, d, n_out, size[0], size[1])

    return _namespace(slab, box_face_interval, cylinder_face_interval, face_interval)


@functools.cache
def search_funcs(np_dtype) -> SimpleNamespace:
    """The searches along a segment against a geom's signed distance (``_golden_min`` and ``_reach`` of
    :mod:`kamino.jax_ref.collision`): ``GOLDEN_STEPS`` golden-section and ``BISECTION_STEPS`` bisection
    steps."""
    T = types_of(np_dtype)
    scalar, vec3, mat33 = T.scalar, T.vec3, T.mat33
    K = _constants(np_dtype)
    ZERO, HALF, ONE, GOLD = K.ZERO, K.HALF, K.ONE, K.GOLD
    dist_world = sdf_funcs(np_dtype).dist_world

    @_func
    def golden_min(gtype: int, size: vec3, c: vec3, R: mat33, p0: vec3, d: vec3, tol: scalar) -> scalar:
        """Minimise ``t -> dist(p0 + t d)`` on ``[0, 1]`` (``dist``: ``dist_world`` of the geom at
        ``(c, R)``) by ``GOLDEN_STEPS`` golden-section steps; values within ``tol`` are ties, which
        move right; the result snaps to an end as good as it (``_golden_min``)."""
        lo = ZERO
        hi = ONE
        a = ONE - GOLD
        b = ZERO + GOLD
        fa = dist_world(gtype, size, c, R, p0 + a * d)
        fb = dist_world(gtype, size, c, R, p0 + b * d)
        for _it in range(int(GOLDEN_STEPS)):
            if fa < fb - tol:  # the minimum lies in [lo, b]
                hi = b
                new = hi - GOLD * (hi - lo)
                fn = dist_world(gtype, size, c, R, p0 + new * d)
                b = a
                fb = fa
                a = new
                fa = fn
            else:
                lo = a
                new = lo + GOLD * (hi - lo)
                fn = dist_world(gtype, size, c, R, p0 + new * d)
                a = b
                fa = fb
                b = new
                fb = fn
        t = HALF * (lo + hi)
        ft = dist_world(gtype, size, c, R, p0 + t * d)
        f0 = dist_world(gtype, size, c, R, p0 + ZERO * d)
        f1 = dist_world(gtype, size, c, R, p0 + ONE * d)
        if f1 <= ft + tol:
            t = ONE
        if f0 < wp.min(ft, f1) - tol:
            t = ZERO
        return t

    @_func
    def reach(gtype: int, size: vec3, c: vec3, R: mat33, start: vec3, end: vec3, level: scalar) -> vec3:
        """The point farthest along ``start -> end`` where the distance to the geom at ``(c, R)`` is still
        ``<= level``: ``end`` if possible, else by ``BISECTION_STEPS`` bisection steps (``_reach``)."""
        lo = ZERO
        hi = ONE
        for _it in range(int(BISECTION_STEPS)):
            mid = HALF * (lo + hi)
            if dist_world(gtype, size, c, R, start + mid * (end - start)) <= level:
                lo = mid
            else:
                hi = mid
        if dist_world(gtype, size, c, R, end) <= level:
            return end
        return start + lo * (end - start)

    return _namespace(golden_min, reach)


@functools.cache
def segment_funcs(np_dtype) -> SimpleNamespace:
    """Closest-point building blocks (:mod:`kamino.jax_ref.collision`): two spheres (``_sphere_pair``),
    a capsule's segment (``_capsule_segment``), the closest points of two segments (``_segment_closest``)
    and the support rim points of a cylinder (``_cylinder_support``)."""
    T = types_of(np_dtype)
    scalar, vec3, mat33, transform = T.scalar, T.vec3, T.mat33, T.transform
    K = _constants(np_dtype)
    mat43, TINY, RTOL2, SQRT3_2 = K.mat43, K.TINY, K.RTOL2, K.SQRT3_2
    ZERO, HALF, ONE, TWO = K.ZERO, K.HALF, K.ONE, K.TWO
    bf = basic_funcs(np_dtype)
    clip01, col, normalize, rot, safe_div, sign = bf.clip01, bf.col, bf.normalize, bf.rot, bf.safe_div, bf.sign

    @_func
    def sphere_pair(ca: vec3, ra: scalar, cb: vec3, rb: scalar, fallback: vec3):
        """Two spheres, exact; ``fallback`` is the normal for coincident centres (``_sphere_pair``)."""
        n, length = normalize(cb - ca, fallback)
        dist = length - ra - rb
        return ca + n * (ra + HALF * dist), n, dist

    @_func
    def capsule_segment(pose: transform, size: vec3):
        """Start point (local z = -half-length), direction vector and rotation of a capsule's segment
        (``_capsule_segment``)."""
        R = rot(wp.transform_get_rotation(pose))
        axis = col(R, 2) * size[1]
        return wp.transform_get_translation(pose) - axis, TWO * axis, R

    @_func
    def segment_closest(p1: vec3, d1: vec3, p2: vec3, d2: vec3):
        """Parameters ``(s, t)`` of the closest points of two segments ``p1 + s d1``, ``p2 + t d2``
        (Ericson 5.1.9; parallel: ``s = 0`` first; zero-length segments handled) (``_segment_closest``)."""
        r = p1 - p2
        a = wp.dot(d1, d1)
        e = wp.dot(d2, d2)
        b = wp.dot(d1, d2)
        c = wp.dot(d1, r)
        f = wp.dot(d2, r)
        denom = a * e - b * b
        s = ZERO
        if denom > RTOL2 * a * e:
            s = clip01(safe_div(b * f - c * e, denom))
        t = safe_div(b * s + f, e)
        if t < ZERO:
            s = clip01(safe_div(-c, a))
        elif t > ONE:
            s = clip01(safe_div(b - c, a))
        t = clip01(t)
        if e <= TINY:
            t = ZERO
        elif a <= TINY:
            t = clip01(safe_div(f, e))
        if a <= TINY:
            s = ZERO
        elif e <= TINY:
            s = clip01(safe_div(-c, a))
        return s, t

    @_func
    def cylinder_support(c: vec3, R: mat33, size: vec3, direction: vec3):
        """Rim points of a cylinder for a support ``direction``: deepest rim point of the cap further
        along it, the same on the other cap, the two points of the first cap at +-120 deg (as the rows
        of a 4x3 matrix), and that cap's centre (``_cylinder_support``)."""
        radius = size[0]
        hh = size[1]
        axis = col(R, 2)
        s = sign(wp.dot(direction, axis))
        cap = c + s * hh * axis
        other = c - s * hh * axis
        r_dir, _n = normalize(direction - wp.dot(direction, axis) * axis, col(R, 0))
        t_dir = wp.cross(axis, r_dir)
        rim = mat43()
        rim[0] = cap + radius * r_dir
        rim[1] = other + radius * r_dir
        rim[2] = cap + radius * (-HALF * r_dir + SQRT3_2 * t_dir)
        rim[3] = cap + radius * (-HALF * r_dir - SQRT3_2 * t_dir)
        return rim, cap

    return _namespace(sphere_pair, capsule_segment, segment_closest, cylinder_support)


@functools.cache
def plane_pair_funcs(np_dtype) -> SimpleNamespace:
    """The routines of the plane pairs (``_plane_sphere`` .. ``_plane_cylinder`` of
    :mod:`kamino.jax_ref.collision`): points of geom b, each a sphere against the plane."""
    T = types_of(np_dtype)
    scalar, vec3, transform = T.scalar, T.vec3, T.transform
    K = _constants(np_dtype)
    ZERO, HALF, ONE = K.ZERO, K.HALF, K.ONE
    box_corner = box_feature_funcs(np_dtype).box_corner
    bf = basic_funcs(np_dtype)
    col, put_point, rot = bf.col, bf.put_point, bf.rot
    cylinder_support = segment_funcs(np_dtype).cylinder_support

    @_func
    def plane_point(pose_plane: transform, pt: vec3, radius: scalar, slot: int, margin: scalar,
                    out_pos: wp.array(dtype=vec3), out_normal: wp.array(dtype=vec3),
                    out_dist: wp.array(dtype=scalar), out_valid: wp.array(dtype=wp.int32)):
        """A sphere of ``radius`` centred at ``pt`` against the plane (``_plane_vs_points``)."""
        n = col(rot(wp.transform_get_rotation(pose_plane)), 2)
        dist = wp.dot(pt - wp.transform_get_translation(pose_plane), n) - radius
        put_point(slot, pt - n * (radius + HALF * dist), n, dist, True, margin, out_pos, out_normal, out_dist,
                  out_valid)

    @_func
    def plane_sphere(pose_a: transform, size_a: vec3, pose_b: transform, size_b: vec3, margin: scalar, base: int,
                     out_pos: wp.array(dtype=vec3), out_normal: wp.array(dtype=vec3),
                     out_dist: wp.array(dtype=scalar), out_valid: wp.array(dtype=wp.int32)):
        """K = 1, exact (``_plane_sphere``)."""
        plane_point(pose_a, wp.transform_get_translation(pose_b), size_b[0], base, margin,
                    out_pos, out_normal, out_dist, out_valid)

    @_func
    def plane_capsule(pose_a: transform, size_a: vec3, pose_b: transform, size_b: vec3, margin: scalar, base: int,
                      out_pos: wp.array(dtype=vec3), out_normal: wp.array(dtype=vec3),
                      out_dist: wp.array(dtype=scalar), out_valid: wp.array(dtype=wp.int32)):
        """K = 2, exact: the end spheres, local -z first (``_plane_capsule``)."""
        c = wp.transform_get_translation(pose_b)
        ax = size_b[1] * col(rot(wp.transform_get_rotation(pose_b)), 2)
        plane_point(pose_a, c + -ONE * ax, size_b[0], base, margin, out_pos, out_normal, out_dist, out_valid)
        plane_point(pose_a, c + ONE * ax, size_b[0], base + 1, margin, out_pos, out_normal, out_dist, out_valid)

    @_func
    def plane_box(pose_a: transform, size_a: vec3, pose_b: transform, size_b: vec3, margin: scalar, base: int,
                  out_pos: wp.array(dtype=vec3), out_normal: wp.array(dtype=vec3),
                  out_dist: wp.array(dtype=scalar), out_valid: wp.array(dtype=wp.int32)):
        """K = 4, exact: the 4 corners deepest below the plane, ties in corner order (``_plane_box``)."""
        c = wp.transform_get_translation(pose_b)
        R = rot(wp.transform_get_rotation(pose_b))
        n = col(rot(wp.transform_get_rotation(pose_a)), 2)
        for i in range(int(8)):
            hi = wp.dot(box_corner(c, R, size_b, i), n)
            rank = int(0)  # position of corner i in a stable sort by height
            for j in range(int(8)):
                hj = wp.dot(box_corner(c, R, size_b, j), n)
                if hj < hi or (hj == hi and j < i):
                    rank += 1
            if rank < 4:
                plane_point(pose_a, box_corner(c, R, size_b, i), ZERO, base + rank, margin,
                            out_pos, out_normal, out_dist, out_valid)

    @_func
    def plane_ellipsoid(pose_a: transform, size_a: vec3, pose_b: transform, size_b: vec3, margin: scalar,
                        base: int, out_pos: wp.array(dtype=vec3), out_normal: wp.array(dtype=vec3),
                        out_dist: wp.array(dtype=scalar), out_valid: wp.array(dtype=wp.int32)):
        """K = 1, exact: the support point ``c + R S^2 d / |S d|``, ``d = -R^T n`` (``_plane_ellipsoid``)."""
        n = col(rot(wp.transform_get_rotation(pose_a)), 2)
        R = rot(wp.transform_get_rotation(pose_b))
        d = -(wp.transpose(R) * n)
        sd = wp.cw_mul(size_b, d)
        x = wp.cw_mul(size_b, sd) / wp.sqrt(wp.dot(sd, sd))
        plane_point(pose_a, wp.transform_get_translation(pose_b) + R * x, ZERO, base, margin,
                    out_pos, out_normal, out_dist, out_valid)

    @_func
    def plane_cylinder(pose_a: transform, size_a: vec3, pose_b: transform, size_b: vec3, margin: scalar, base: int,
                       out_pos: wp.array(dtype=vec3), out_normal: wp.array(dtype=vec3),
                       out_dist: wp.array(dtype=scalar), out_valid: wp.array(dtype=wp.int32)):
        """K = 4, MuJoCo's four rim points with their exact heights (``_plane_cylinder``)."""
        n = col(rot(wp.transform_get_rotation(pose_a)), 2)
        rim, _cap = cylinder_support(wp.transform_get_translation(pose_b), rot(wp.transform_get_rotation(pose_b)),
                                     size_b, -n)
        for i in range(4):
            plane_point(pose_a, rim[i], ZERO, base + i, margin, out_pos, out_normal, out_dist, out_valid)

    return _namespace(plane_point, plane_sphere, plane_capsule, plane_box, plane_ellipsoid, plane_cylinder)


@functools.cache
def sphere_capsule_pair_funcs(np_dtype) -> SimpleNamespace:
    """The routines of the sphere and capsule pairs (``_sphere_sphere``, ``_sphere_capsule``,
    ``_capsule_capsule`` of :mod:`kamino.jax_ref.collision`): closest points of their core point or
    segment."""
    T = types_of(np_dtype)
    scalar, vec3, transform = T.scalar, T.vec3, T.transform
    K = _constants(np_dtype)
    ZERO, ONE, MILLI, PAR = K.ZERO, K.ONE, K.MILLI, K.PAR
    sg = segment_funcs(np_dtype)
    capsule_segment, segment_closest, sphere_pair = sg.capsule_segment, sg.segment_closest, sg.sphere_pair
    bf = basic_funcs(np_dtype)
    clip01, col, normalize, rot, safe_div = bf.clip01, bf.col, bf.normalize, bf.rot, bf.safe_div
    put_point = bf.put_point

    @_func
    def sphere_sphere(pose_a: transform, size_a: vec3, pose_b: transform, size_b: vec3, margin: scalar, base: int,
                      out_pos: wp.array(dtype=vec3), out_normal: wp.array(dtype=vec3),
                      out_dist: wp.array(dtype=scalar), out_valid: wp.array(dtype=wp.int32)):
        """K = 1, exact; concentric spheres get a's local +z (``_sphere_sphere``)."""
        pos, n, dist = sphere_pair(wp.transform_get_translation(pose_a), size_a[0],
                                   wp.transform_get_translation(pose_b), size_b[0],
                                   col(rot(wp.transform_get_rotation(pose_a)), 2))
        put_point(base, pos, n, dist, True, margin, out_pos, out_normal, out_dist, out_valid)

    @_func
    def sphere_capsule(pose_a: transform, size_a: vec3, pose_b: transform, size_b: vec3, margin: scalar, base: int,
                       out_pos: wp.array(dtype=vec3), out_normal: wp.array(dtype=vec3),
                       out_dist: wp.array(dtype=scalar), out_valid: wp.array(dtype=wp.int32)):
        """K = 1, exact; a centre on the segment uses the capsule's local +x (``_sphere_capsule``)."""
        p0, d, R = capsule_segment(pose_b, size_b)
        ca = wp.transform_get_translation(pose_a)
        t = clip01(safe_div(wp.dot(ca - p0, d), wp.dot(d, d)))
        pos, n, dist = sphere_pair(ca, size_a[0], p0 + t * d, size_b[0], col(R, 0))
        put_point(base, pos, n, dist, True, margin, out_pos, out_normal, out_dist, out_valid)

    @_func
    def capsule_capsule(pose_a: transform, size_a: vec3, pose_b: transform, size_b: vec3, margin: scalar,
                        base: int, out_pos: wp.array(dtype=vec3), out_normal: wp.array(dtype=vec3),
                        out_dist: wp.array(dtype=scalar), out_valid: wp.array(dtype=wp.int32)):
        """K = 2: closest points of the segments, and for near-parallel segments the far end of their
        overlap (``_capsule_capsule``)."""
        pa, da, Ra = capsule_segment(pose_a, size_a)
        pb, db, _Rb = capsule_segment(pose_b, size_b)
        s1, t1 = segment_closest(pa, da, pb, db)
        a = wp.dot(da, da)
        e = wp.dot(db, db)
        sb0 = safe_div(wp.dot(pb - pa, da), a)
        sb1 = safe_div(wp.dot(pb + db - pa, da), a)
        lo = wp.max(wp.min(sb0, sb1), ZERO)
        hi = wp.min(wp.max(sb0, sb1), ONE)
        s2 = clip01(wp.where(wp.abs(s1 - lo) >= wp.abs(s1 - hi), lo, hi))
        t2 = clip01(safe_div(wp.dot(pa + s2 * da - pb, db), e))
        cross = wp.cross(da, db)
        parallel = wp.dot(cross, cross) <= PAR * a * e
        second = parallel and lo <= hi and wp.abs(s2 - s1) > MILLI and a > ZERO
        fallback, _n = normalize(cross, col(Ra, 0))
        pos, n, dist = sphere_pair(pa + s1 * da, size_a[0], pb + t1 * db, size_b[0], fallback)
        put_point(base, pos, n, dist, True, margin, out_pos, out_normal, out_dist, out_valid)
        pos, n, dist = sphere_pair(pa + s2 * da, size_a[0], pb + t2 * db, size_b[0], fallback)
        put_point(base + 1, pos, n, dist, second, margin, out_pos, out_normal, out_dist, out_valid)

    return _namespace(sphere_sphere, sphere_capsule, capsule_capsule)


@functools.cache
def sdf_pair_funcs(np_dtype) -> SimpleNamespace:
    """The routines of a sphere or capsule against a box or cylinder (``_sphere_vs_sdf`` and
    ``_capsule_vs_sdf`` of :mod:`kamino.jax_ref.collision`): the core point or segment against the exact
    signed distance of geom b, whose type stays a run-time argument."""
    T = types_of(np_dtype)
    scalar, vec3, transform = T.scalar, T.vec3, T.transform
    K = _constants(np_dtype)
    TIE, ZERO, HALF, ONE, MILLI = K.TIE, K.ZERO, K.HALF, K.ONE, K.MILLI
    capsule_segment = segment_funcs(np_dtype).capsule_segment
    bf = basic_funcs(np_dtype)
    clip01, put_point, rot = bf.clip01, bf.put_point, bf.rot
    face_interval = face_interval_funcs(np_dtype).face_interval
    golden_min = search_funcs(np_dtype).golden_min
    sd = sdf_funcs(np_dtype)
    sdf, sdf_world = sd.sdf, sd.sdf_world

    @_func
    def sphere_sdf_pair(type_b: int, pose_a: transform, size_a: vec3, pose_b: transform, size_b: vec3,
                        margin: scalar, base: int, out_pos: wp.array(dtype=vec3), out_normal: wp.array(dtype=vec3),
                        out_dist: wp.array(dtype=scalar), out_valid: wp.array(dtype=wp.int32)):
        """K = 1, exact: the sphere centre against the signed distance of the box or cylinder b, minus the
        radius (``_sphere_box``, ``_sphere_cylinder`` via ``_sphere_vs_sdf``)."""
        x = wp.transform_get_translation(pose_a)
        d, n_out, q = sdf_world(type_b, size_b, wp.transform_get_translation(pose_b),
                                rot(wp.transform_get_rotation(pose_b)), x)
        n = -n_out
        r = size_a[0]
        put_point(base, HALF * (x + q) + HALF * r * n, n, d - r, True, margin, out_pos, out_normal, out_dist, out_valid)

    @_func
    def capsule_sdf_pair(type_b: int, pose_a: transform, size_a: vec3, pose_b: transform, size_b: vec3,
                         margin: scalar, base: int, out_pos: wp.array(dtype=vec3), out_normal: wp.array(dtype=vec3),
                         out_dist: wp.array(dtype=scalar), out_valid: wp.array(dtype=wp.int32)):
        """K = 2: a capsule against the signed distance of the box or cylinder b (``_capsule_vs_sdf``):
        the minimum along the segment (golden section), and the far end of the part of the segment
        lying over the feature it touches."""
        p0w, dw, _Ra = capsule_segment(pose_a, size_a)
        cb = wp.transform_get_translation(pose_b)
        Rb = rot(wp.transform_get_rotation(pose_b))
        Rt = wp.transpose(Rb)
        p0 = Rt * (p0w - cb)
        d = Rt * dw
        tol = TIE * (size_a[0] + size_a[1] + (size_b[0] + size_b[1] + size_b[2]))
        eye = wp.identity(n=3, dtype=scalar)
        t1 = golden_min(type_b, size_b, vec3(), eye, p0, d, tol)
        _d1, n1, _q1 = sdf(type_b, size_b, p0 + t1 * d)
        lo, hi = face_interval(type_b, size_b, p0, d, n1)
        lo = wp.max(lo, ZERO)
        hi = wp.min(hi, ONE)
        has = lo <= hi
        lo = clip01(lo)
        hi = clip01(hi)
        t2 = wp.where(wp.abs(t1 - lo) >= wp.abs(t1 - hi), lo, hi)
        second = has and wp.abs(t2 - t1) > MILLI and wp.dot(d, d) > ZERO
        r = size_a[0]
        for i in range(2):
            t = wp.where(i == 0, t1, t2)
            x = p0 + t * d
            dist, n_out, q = sdf(type_b, size_b, x)
            n = -n_out
            pos = HALF * (x + q) + HALF * r * n
            put_point(base + i, cb + Rb * pos, Rb * n, dist - r, i == 0 or second, margin,
                      out_pos, out_normal, out_dist, out_valid)

    return _namespace(sphere_sdf_pair, capsule_sdf_pair)


@functools.cache
def box_box_sat_funcs(np_dtype) -> SimpleNamespace:
    """Step 1 of the box-box routine (``_box_box`` of :mod:`kamino.jax_ref.collision`): the separating-axis
    test over the 15 axes (3 + 3 face normals, 9 edge crosses) with the 5 % edge bias."""
    T = types_of(np_dtype)
    scalar, vec3, mat33 = T.scalar, T.vec3, T.mat33
    K = _constants(np_dtype)
    RTOL, RTOL10, INF, ZERO, ONE = K.RTOL, K.RTOL10, K.INF, K.ZERO, K.ONE
    BIAS_REL, BIAS_ABS = K.BIAS_REL, K.BIAS_ABS
    bf = basic_funcs(np_dtype)
    col, normalize = bf.col, bf.normalize

    @_func
    def bb_axis(idx: int, Ra: mat33, Rb: mat33):
        """SAT axis ``idx`` of ``_box_box``: a's face normals, b's, then the 9 normalised edge crosses
        ``a_i x b_j`` (``i = (idx - 6) // 3``; fallback a's x axis), with the cross's length."""
        if idx < 3:
            return col(Ra, idx), ONE
        if idx < 6:
            return col(Rb, idx - 3), ONE
        return normalize(wp.cross(col(Ra, (idx - 6) // 3), col(Rb, (idx - 6) % 3)), col(Ra, 0))

    @_func
    def bb_sep(axis: vec3, t: vec3, Ra: mat33, ea: vec3, Rb: mat33, eb: vec3) -> scalar:
        """Separation of the boxes along ``axis`` (``|axis.t|`` minus the two projected radii)."""
        ra = wp.abs(wp.dot(axis, col(Ra, 0))) * ea[0] + wp.abs(wp.dot(axis, col(Ra, 1))) * ea[1] + wp.abs(
            wp.dot(axis, col(Ra, 2))) * ea[2]
        rb = wp.abs(wp.dot(axis, col(Rb, 0))) * eb[0] + wp.abs(wp.dot(axis, col(Rb, 1))) * eb[1] + wp.abs(
            wp.dot(axis, col(Rb, 2))) * eb[2]
        return wp.abs(wp.dot(axis, t)) - ra - rb

    @_func
    def bb_sat(t: vec3, Ra: mat33, ea: vec3, Rb: mat33, eb: vec3, scale: scalar):
        """The 15 axes for boxes at ``c_b - c_a = t``: whether a usable axis (a face axis, or an edge cross
        longer than ``10 RTOL``) separates them; the reference face (0-2 on a, 3-5 on b: b's best face when
        it beats a's by ``RTOL`` of ``scale``); whether the best usable edge axis beats that face by the
        bias; that edge pair ``3 i + j`` and its separation (``-inf`` when no edge axis is usable)."""
        separated = bool(False)
        ia = int(0)
        sa = -INF
        ib = int(0)
        sb = -INF
        ie = int(0)
        s_edge = -INF
        for idx in range(int(15)):
            axis, length = bb_axis(idx, Ra, Rb)
            s = bb_sep(axis, t, Ra, ea, Rb, eb)
            usable = idx < 6 or length > RTOL10
            if usable and s > ZERO:
                separated = True
            if idx < 3:
                if idx == 0 or s > sa:
                    ia = idx
                    sa = s
            elif idx < 6:
                if idx == 3 or s > sb:
                    ib = idx - 3
                    sb = s
            elif usable and s > s_edge:
                ie = idx - 6
                s_edge = s
        use_b = sb > sa + RTOL * scale
        face = wp.where(use_b, 3 + ib, ia)
        s_face = wp.where(use_b, sb, sa)
        use_edge = s_edge > s_face + BIAS_REL * wp.abs(s_face) + BIAS_ABS * scale
        return separated, face, use_edge, ie, s_edge

    return _namespace(bb_axis, bb_sep, bb_sat)


@functools.cache
def face_manifold_func(np_dtype) -> wp.Function:
    """Step 2a of the box-box routine (``_face_manifold`` of :mod:`kamino.jax_ref.collision`):
    the 24 clipping candidates of the incident face against the reference face."""
    T = types_of(np_dtype)
    scalar, vec3, vec4, mat33 = T.scalar, T.vec3, T.vec4, T.mat33
    K = _constants(np_dtype)
    vec24, vec24i, RTOL, ZERO, ONE = K.vec24, K.vec24i, K.RTOL, K.ZERO, K.ONE
    bf = basic_funcs(np_dtype)
    col, sign = bf.col, bf.sign

    @_func
    def face_manifold(c_ref: vec3, R_ref: mat33, e_ref: vec3, k: int, nf: vec3, c_inc: vec3, R_inc: mat33,
                      e_inc: vec3):
        """The 24 clipping candidates of ``_face_manifold``: incident corners inside the reference face,
        reference corners inside the incident face, incident edges crossing the reference face's sides
        (edge-major, lines ``x = +e, x = -e, y = +e, y = -e``); near-duplicates of an earlier existing
        candidate dropped. Returns their reference-face coordinates ``x, y``, heights ``h`` above the
        reference face along ``nf``, existence flags, and the face centre and tangents ``cf, t1, t2``."""
        k1 = (k + 1) % 3
        k2 = (k + 2) % 3
        cf = c_ref + e_ref[k] * nf
        t1 = col(R_ref, k1)
        t2 = col(R_ref, k2)
        ext0 = e_ref[k1]
        ext1 = e_ref[k2]
        tol = RTOL * wp.max(wp.max(e_ref[0], e_ref[1]), e_ref[2])
        # incident face: outward normal most opposed to nf
        proj = wp.transpose(R_inc) * nf
        j = int(0)
        for i in range(1, 3):
            if wp.abs(proj[i]) > wp.abs(proj[j]):
                j = i
        n_inc = -sign(proj[j]) * col(R_inc, j)
        j1 = (j + 1) % 3
        j2 = (j + 2) % 3
        fc = c_inc + e_inc[j] * n_inc
        u1 = e_inc[j1] * col(R_inc, j1)
        u2 = e_inc[j2] * col(R_inc, j2)
        qx = vec4()
        qy = vec4()
        hq = vec4()
        for c in range(4):
            rel = fc + (scalar(quad_x(c)) * u1 + scalar(quad_y(c)) * u2) - cf
            qx[c] = wp.dot(rel, t1)
            qy[c] = wp.dot(rel, t2)
            hq[c] = wp.dot(rel, nf)
        ex = vec4()
        ey = vec4()
        el = vec4()
        area = ZERO
        for c in range(4):
            ex[c] = qx[(c + 1) % 4] - qx[c]
            ey[c] = qy[(c + 1) % 4] - qy[c]
            el[c] = wp.sqrt(ex[c] * ex[c] + ey[c] * ey[c])
            area += qx[c] * qy[(c + 1) % 4] - qy[c] * qx[(c + 1) % 4]
        orient = sign(area)
        X = vec24()
        Y = vec24()
        H = vec24()
        E = vec24i()
        # (1) incident corners inside the reference face
        for c in range(4):
            X[c] = qx[c]
            Y[c] = qy[c]
            H[c] = hq[c]
            E[c] = wp.where(wp.abs(qx[c]) <= ext0 + tol and wp.abs(qy[c]) <= ext1 + tol, 1, 0)
        # (2) reference corners inside the incident face, height from its plane
        h0 = wp.dot(fc - cf, n_inc)
        tn1 = wp.dot(t1, n_inc)
        tn2 = wp.dot(t2, n_inc)
        nn = wp.dot(nf, n_inc)
        for r in range(4):
            rx = scalar(quad_x(r)) * ext0
            ry = scalar(quad_y(r)) * ext1
            inside = int(1)
            for c in range(4):
                side = orient * (ex[c] * (ry - qy[c]) - ey[c] * (rx - qx[c]))
                if side < -tol * el[c]:
                    inside = 0
            X[4 + r] = rx
            Y[4 + r] = ry
            H[4 + r] = (h0 - (rx * tn1 + ry * tn2)) / nn
            E[4 + r] = inside
        # (3) incident edges crossing the lines x = +-ext0, y = +-ext1
        for idx in range(int(16)):
            c = idx // 4
            ln = idx % 4
            s = wp.where(ln % 2 == 0, ONE, -ONE)
            pm = qx[c]
            em = ex[c]
            po = qy[c]
            eo = ey[c]
            ext_m = ext0
            ext_o = ext1
            if ln >= 2:
                pm = qy[c]
                em = ey[c]
                po = qx[c]
                eo = ex[c]
                ext_m = ext1
                ext_o = ext0
            ok = wp.abs(em) > tol
            alpha = (s * ext_m - pm) / wp.where(ok, em, ONE)
            other = po + alpha * eo
            X[8 + idx] = wp.where(ln >= 2, other, s * ext_m)
            Y[8 + idx] = wp.where(ln >= 2, s * ext_m, other)
            H[8 + idx] = hq[c] + alpha * (hq[(c + 1) % 4] - hq[c])
            crosses = ok and alpha >= ZERO and alpha <= ONE and wp.abs(other) <= ext_o + tol
            E[8 + idx] = wp.where(crosses, 1, 0)
        # drop near-duplicates of an earlier existing candidate
        dup_tol = (scalar(10.0) * tol) * (scalar(10.0) * tol)
        F = vec24i()
        for i in range(int(24)):
            F[i] = E[i]
            for jj in range(i):
                dx = X[i] - X[jj]
                dy = Y[i] - Y[jj]
                if E[jj] == 1 and dx * dx + dy * dy <= dup_tol:
                    F[i] = 0
        return X, Y, H, F, cf, t1, t2

    return face_manifold


@functools.cache
def box_box_step_funcs(np_dtype) -> SimpleNamespace:
    """Steps 2 and 3 of the box-box routine (``_box_box`` of :mod:`kamino.jax_ref.collision`): the 8 slots
    of the face manifold, the edge-edge point, the exact closest pair of separated boxes."""
    T = types_of(np_dtype)
    scalar, vec3, mat33 = T.scalar, T.vec3, T.mat33
    K = _constants(np_dtype)
    vec24, vec24i, vec8i, INF, HALF, TWO = K.vec24, K.vec24i, K.vec8i, K.INF, K.HALF, K.TWO
    bx = box_feature_funcs(np_dtype)
    box_corner, box_edge = bx.box_corner, bx.box_edge
    bf = basic_funcs(np_dtype)
    col, sign = bf.col, bf.sign
    sdf_world = sdf_funcs(np_dtype).sdf_world
    segment_closest = segment_funcs(np_dtype).segment_closest
    bb_axis = box_box_sat_funcs(np_dtype).bb_axis

    @_func
    def face_slots(F: vec24i, H: vec24, margin: scalar):
        """The 8 slots of the face manifold: the kept candidates (existing, ``h <= margin``) first, then the
        others, in candidate order. Returns the candidate of each slot, whether one is kept, and, over the
        slots with a missing candidate counting as ``+inf`` high, the least height and the first slot of the
        greatest."""
        sel = vec8i()
        n_kept = int(0)
        for i in range(int(24)):
            if F[i] == 1 and H[i] <= margin and n_kept < 8:
                sel[n_kept] = i
                n_kept += 1
        n_sel = n_kept
        for i in range(int(24)):
            if not (F[i] == 1 and H[i] <= margin) and n_sel < 8:
                sel[n_sel] = i
                n_sel += 1
        any_in = bool(False)
        f_min = INF
        slot = int(0)
        slot_val = -INF
        for i in range(int(8)):
            c = sel[i]
            v = wp.where(F[c] == 1, H[c], INF)
            if F[c] == 1 and H[c] <= margin:
                any_in = True
            f_min = wp.min(f_min, v)
            if v > slot_val:
                slot = i
                slot_val = v
        return sel, any_in, f_min, slot

    @_func
    def edge_point(ie: int, t: vec3, ca: vec3, Ra: mat33, ea: vec3, cb: vec3, Rb: mat33, eb: vec3):
        """The edge-edge point of edge pair ``ie`` (a's axis ``ie // 3``, b's ``ie % 3``): the normal along
        their cross, pointing from a to b, and the midpoint of the closest points of the two edges most
        advanced along it."""
        ia_e = ie // 3
        ib_e = ie % 3
        axis_e, _len_e = bb_axis(6 + ie, Ra, Rb)
        n_e = sign(wp.dot(axis_e, t)) * axis_e
        va = vec3()
        vb = vec3()
        for i in range(3):
            if i != ia_e:
                va[i] = sign(wp.dot(n_e, col(Ra, i))) * ea[i]
            if i != ib_e:
                vb[i] = sign(-wp.dot(n_e, col(Rb, i))) * eb[i]
        mid_a = ca + Ra * va
        mid_b = cb + Rb * vb
        da = col(Ra, ia_e) * ea[ia_e]
        db = col(Rb, ib_e) * eb[ib_e]
        s_a, s_b = segment_closest(mid_a - da, TWO * da, mid_b - db, TWO * db)
        e_pos = HALF * (mid_a - da + s_a * TWO * da + mid_b - db + s_b * TWO * db)
        return n_e, e_pos

    @_func
    def bb_closest(ca: vec3, Ra: mat33, ea: vec3, cb: vec3, Rb: mat33, eb: vec3):
        """Closest pair of two boxes among: a's corners and their nearest points of b, b's corners and
        their nearest points of a, the closest points of the 144 edge pairs (first minimum, in that
        order); exact for separated boxes (``_box_box`` step 3). Returns the points on a and on b."""
        best = INF
        on_a = vec3()
        on_b = vec3()
        for idx in range(int(160)):
            pa = vec3()
            pb = vec3()
            if idx < 8:
                pa = box_corner(ca, Ra, ea, idx)
                _d, _n, pb = sdf_world(BOX, eb, cb, Rb, pa)
            elif idx < 16:
                pb = box_corner(cb, Rb, eb, idx - 8)
                _d, _n, pa = sdf_world(BOX, ea, ca, Ra, pb)
            else:
                pe, de = box_edge(ca, Ra, ea, (idx - 16) // 12)
                qe, fe = box_edge(cb, Rb, eb, (idx - 16) % 12)
                s, u = segment_closest(pe, de, qe, fe)
                pa = pe + s * de
                pb = qe + u * fe
            gap = wp.length(pb - pa)
            if gap < best:
                best = gap
                on_a = pa
                on_b = pb
        return on_a, on_b

    return _namespace(face_slots, edge_point, bb_closest)


@functools.cache
def box_box_func(np_dtype) -> wp.Function:
    """The box-box routine, K = 8 (``_box_box`` of :mod:`kamino.jax_ref.collision`): the separating-axis
    test, then the clipped face manifold or one edge-edge point, and for separated boxes their exact
    closest pair."""
    T = types_of(np_dtype)
    scalar, vec3, transform = T.scalar, T.vec3, T.transform
    K = _constants(np_dtype)
    RTOL, INF, ZERO, HALF = K.RTOL, K.INF, K.ZERO, K.HALF
    bf = basic_funcs(np_dtype)
    col, normalize, put_point, rot, sign = bf.col, bf.normalize, bf.put_point, bf.rot, bf.sign
    bb_sat = box_box_sat_funcs(np_dtype).bb_sat
    st = box_box_step_funcs(np_dtype)
    face_slots, edge_point, bb_closest = st.face_slots, st.edge_point, st.bb_closest
    face_manifold = face_manifold_func(np_dtype)

    @_func
    def box_box(pose_a: transform, size_a: vec3, pose_b: transform, size_b: vec3, margin: scalar, base: int,
                out_pos: wp.array(dtype=vec3), out_normal: wp.array(dtype=vec3),
                out_dist: wp.array(dtype=scalar), out_valid: wp.array(dtype=wp.int32)):
        """K = 8: separating-axis test, face clipping or one edge-edge point, exact closest pair of
        separated boxes (``_box_box``; its docstring has the details)."""
        ca = wp.transform_get_translation(pose_a)
        cb = wp.transform_get_translation(pose_b)
        Ra = rot(wp.transform_get_rotation(pose_a))
        Rb = rot(wp.transform_get_rotation(pose_b))
        ea = size_a
        eb = size_b
        scale = (ea[0] + ea[1] + ea[2]) + (eb[0] + eb[1] + eb[2])
        t = cb - ca

        # 1. separating axes
        separated, face, use_edge, ie, s_edge = bb_sat(t, Ra, ea, Rb, eb, scale)

        # 2a. face manifold
        ref_a = face < 3
        c_ref = wp.where(ref_a, ca, cb)
        R_ref = wp.where(ref_a, Ra, Rb)
        e_ref = wp.where(ref_a, ea, eb)
        c_inc = wp.where(ref_a, cb, ca)
        R_inc = wp.where(ref_a, Rb, Ra)
        e_inc = wp.where(ref_a, eb, ea)
        k = face % 3
        axis_f = col(R_ref, k)
        nf = sign(wp.dot(c_inc - c_ref, axis_f)) * axis_f
        X, Y, H, F, cf, t1, t2 = face_manifold(c_ref, R_ref, e_ref, k, nf, c_inc, R_inc, e_inc)
        sel, any_in, f_min, slot = face_slots(F, H, margin)
        f_normal = wp.where(ref_a, nf, -nf)

        # 2b. edge-edge point
        n_e, e_pos = edge_point(ie, t, ca, Ra, ea, cb, Rb, eb)
        edge_ok = s_edge > -INF

        # 3. exact closest pair of separated boxes (only used when separated)
        x_pos = vec3()
        x_n = vec3()
        x_d = ZERO
        if separated:
            on_a, on_b = bb_closest(ca, Ra, ea, cb, Rb, eb)
            x_n, x_d = normalize(on_b - on_a, wp.where(use_edge, n_e, f_normal))
            x_pos = HALF * (on_a + on_b)

        # assemble
        point_case = (use_edge or not any_in) and (edge_ok or separated)
        p_pos = wp.where(separated, x_pos, e_pos)
        p_n = wp.where(separated, x_n, n_e)
        p_d = wp.where(separated, x_d, wp.where(edge_ok, s_edge, ZERO))
        add = separated and x_d < f_min - RTOL * scale
        for i in range(int(8)):
            c = sel[i]
            put = wp.where(point_case, i == 0, i == slot and add)
            exists = wp.where(point_case, i == 0, F[c] == 1 or put)
            pos = cf + X[c] * t1 + Y[c] * t2 + HALF * H[c] * nf
            if put:
                put_point(base + i, p_pos, p_n, p_d, exists, margin, out_pos, out_normal, out_dist, out_valid)
            else:
                put_point(base + i, pos, f_normal, H[c], exists, margin, out_pos, out_normal, out_dist, out_valid)

    return box_box


@functools.cache
def cylinder_family_funcs(np_dtype) -> SimpleNamespace:
    """The point families of the cylinder pairs (``_cylinder_family`` and ``_pick_family`` of
    :mod:`kamino.jax_ref.collision`): four points of a cylinder against the exact signed distance of the
    other geom, their writer, and the choice between two families."""
    T = types_of(np_dtype)
    scalar, vec3, vec4, mat33 = T.scalar, T.vec3, T.vec4, T.mat33
    K = _constants(np_dtype)
    mat43, TIE, INF, ZERO, HALF, ONE, MILLI = K.mat43, K.TIE, K.INF, K.ZERO, K.HALF, K.ONE, K.MILLI
    bf = basic_funcs(np_dtype)
    col, normalize, put_point = bf.col, bf.normalize, bf.put_point
    cylinder_support = segment_funcs(np_dtype).cylinder_support
    sd = sdf_funcs(np_dtype)
    dist_world, project, sdf_world = sd.dist_world, sd.project, sd.sdf_world
    se = search_funcs(np_dtype)
    golden_min, reach = se.golden_min, se.reach

    @_func
    def cylinder_family(c: vec3, R: mat33, size: vec3, type_o: int, size_o: vec3, c_o: vec3, R_o: mat33,
                        margin: scalar, tol: scalar):
        """Four points of the cylinder at ``(c, R)`` against the exact signed distance of the other geom
        (box or cylinder at ``(c_o, R_o)``): three pulled rim points of the cap facing it, and the first
        nearest of the support-generator minimum, the alternating-projection point and the anchor
        (``_cylinder_family``, with ``on_a=False``). Returns positions and normals (rows of 4x3
        matrices; normals are the other geom's outward normals), distances, existence (1/0)."""
        radius = size[0]
        hh = size[1]
        _d0, u, q = sdf_world(type_o, size_o, c_o, R_o, c)
        rim, cap = cylinder_support(c, R, size, -u)
        axis = col(R, 2)
        off = q - cap
        off = off - wp.dot(off, axis) * axis
        off_u, off_len = normalize(off, col(R, 0))
        anchor = cap + wp.min(off_len, radius) * off_u
        level = wp.max(dist_world(type_o, size_o, c_o, R_o, anchor), margin)
        pts = mat43()
        for i in range(int(3)):
            pts[i] = reach(type_o, size_o, c_o, R_o, anchor, rim[wp.where(i == 0, 0, i + 1)], level)
        gen = rim[1] - rim[0]
        tg = golden_min(type_o, size_o, c_o, R_o, rim[0], gen, TIE * (radius + hh))
        # alternating projections from the other geom's centre
        x = project(CYLINDER, size, c, R, c_o)
        for _it in range(int(PROJECTION_ROUNDS)):
            x = project(CYLINDER, size, c, R, project(type_o, size_o, c_o, R_o, x))
        e0 = rim[0] + tg * gen
        d0 = dist_world(type_o, size_o, c_o, R_o, e0)
        if not (tg > MILLI and hh > ZERO):
            d0 = INF
        d1 = dist_world(type_o, size_o, c_o, R_o, x)
        d2 = dist_world(type_o, size_o, c_o, R_o, anchor)
        m = wp.min(wp.min(d0, d1), d2)
        fourth = anchor
        if d1 <= m + tol:
            fourth = x
        if d0 <= m + tol:
            fourth = e0
        pts[3] = fourth
        P = mat43()
        N = mat43()
        D = vec4()
        Ex = vec4()
        near = (scalar(1e-3) * radius) * (scalar(1e-3) * radius)
        for i in range(4):
            xi = pts[i]
            Ex[i] = ONE
            for j in range(i):
                if wp.length_sq(xi - pts[j]) <= near:
                    Ex[i] = ZERO
            di, ni, qi = sdf_world(type_o, size_o, c_o, R_o, xi)
            P[i] = HALF * (xi + qi)
            N[i] = ni
            D[i] = di
        return P, N, D, Ex

    @_func
    def put_family(P: mat43, N: mat43, D: vec4, Ex: vec4, margin: scalar, base: int,
                   out_pos: wp.array(dtype=vec3), out_normal: wp.array(dtype=vec3),
                   out_dist: wp.array(dtype=scalar), out_valid: wp.array(dtype=wp.int32)):
        """Write the 4 points of a family."""
        for i in range(4):
            put_point(base + i, P[i], N[i], D[i], Ex[i] > ZERO, margin, out_pos, out_normal, out_dist, out_valid)

    @_func
    def pick_second(D1: vec4, E1: vec4, D2: vec4, E2: vec4, margin: scalar, tol: scalar) -> bool:
        """Whether the second family is kept: smaller minimum distance, or within ``tol`` of a tie more
        points within the margin (``_pick_family``)."""
        m1 = INF
        m2 = INF
        n1 = int(0)
        n2 = int(0)
        for i in range(4):
            if E1[i] > ZERO:
                m1 = wp.min(m1, D1[i])
                if D1[i] <= margin:
                    n1 += 1
            if E2[i] > ZERO:
                m2 = wp.min(m2, D2[i])
                if D2[i] <= margin:
                    n2 += 1
        return m2 < m1 - tol or (m2 <= m1 + tol and n2 > n1)

    return _namespace(cylinder_family, put_family, pick_second)


@functools.cache
def cylinder_pair_funcs(np_dtype) -> SimpleNamespace:
    """The routines of the cylinder pairs, K = 4 (``_box_cylinder`` and ``_cylinder_cylinder``
    of :mod:`kamino.jax_ref.collision`): approximations, the better of two point families."""
    T = types_of(np_dtype)
    scalar, vec3, vec4, transform = T.scalar, T.vec3, T.vec4, T.transform
    K = _constants(np_dtype)
    mat43, RTOL, HALF, ONE = K.mat43, K.RTOL, K.HALF, K.ONE
    box_corner = box_feature_funcs(np_dtype).box_corner
    cy = cylinder_family_funcs(np_dtype)
    cylinder_family, pick_second, put_family = cy.cylinder_family, cy.pick_second, cy.put_family
    sd = sdf_funcs(np_dtype)
    dist_world, sdf_world = sd.dist_world, sd.sdf_world
    rot = basic_funcs(np_dtype).rot

    @_func
    def box_cylinder(pose_a: transform, size_a: vec3, pose_b: transform, size_b: vec3, margin: scalar, base: int,
                     out_pos: wp.array(dtype=vec3), out_normal: wp.array(dtype=vec3),
                     out_dist: wp.array(dtype=scalar), out_valid: wp.array(dtype=wp.int32)):
        """K = 4, approximation: the cylinder's family against the box, or the 4 box corners nearest the
        cylinder, stable order (``_box_cylinder``)."""
        ca = wp.transform_get_translation(pose_a)
        cb = wp.transform_get_translation(pose_b)
        Ra = rot(wp.transform_get_rotation(pose_a))
        Rb = rot(wp.transform_get_rotation(pose_b))
        tol = RTOL * ((size_a[0] + size_a[1] + size_a[2]) + (size_b[0] + size_b[1] + size_b[2]))
        P1, N1, D1, E1 = cylinder_family(cb, Rb, size_b, BOX, size_a, ca, Ra, margin, tol)
        P2 = mat43()
        N2 = mat43()
        D2 = vec4()
        E2 = vec4(ONE, ONE, ONE, ONE)
        for i in range(int(8)):
            x = box_corner(ca, Ra, size_a, i)
            di, ni, qi = sdf_world(CYLINDER, size_b, cb, Rb, x)
            rank = int(0)  # position of corner i in a stable sort by distance
            for j in range(int(8)):
                dj = dist_world(CYLINDER, size_b, cb, Rb, box_corner(ca, Ra, size_a, j))
                if dj < di or (dj == di and j < i):
                    rank += 1
            if rank < 4:
                P2[rank] = HALF * (x + qi)
                N2[rank] = -ni
                D2[rank] = di
        if pick_second(D1, E1, D2, E2, margin, tol):
            put_family(P2, N2, D2, E2, margin, base, out_pos, out_normal, out_dist, out_valid)
        else:
            put_family(P1, N1, D1, E1, margin, base, out_pos, out_normal, out_dist, out_valid)

    @_func
    def cylinder_cylinder(pose_a: transform, size_a: vec3, pose_b: transform, size_b: vec3, margin: scalar,
                          base: int, out_pos: wp.array(dtype=vec3), out_normal: wp.array(dtype=vec3),
                          out_dist: wp.array(dtype=scalar), out_valid: wp.array(dtype=wp.int32)):
        """K = 4, approximation: each cylinder's family against the other; the better one is kept
        (``_cylinder_cylinder``)."""
        ca = wp.transform_get_translation(pose_a)
        cb = wp.transform_get_translation(pose_b)
        Ra = rot(wp.transform_get_rotation(pose_a))
        Rb = rot(wp.transform_get_rotation(pose_b))
        tol = RTOL * ((size_a[0] + size_a[1]) + (size_b[0] + size_b[1]))
        P1, N1, D1, E1 = cylinder_family(ca, Ra, size_a, CYLINDER, size_b, cb, Rb, margin, tol)
        P2, N2, D2, E2 = cylinder_family(cb, Rb, size_b, CYLINDER, size_a, ca, Ra, margin, tol)
        if pick_second(D1, E1, D2, E2, margin, tol):
            put_family(P2, N2, D2, E2, margin, base, out_pos, out_normal, out_dist, out_valid)
        else:  # a's points: flip the normals to point from a to b
            put_family(P1, -N1, D1, E1, margin, base, out_pos, out_normal, out_dist, out_valid)

    return _namespace(box_cylinder, cylinder_cylinder)


@functools.cache
def hfield_funcs(np_dtype) -> SimpleNamespace:
    """The heightfield pairs (``_hfield_surface``, ``_hfield_vs_points`` and ``_sphere_hfield`` ..
    ``_cylinder_hfield`` of :mod:`kamino.jax_ref.collision`; docs/conventions.md, "Heightfields"): candidate
    points of geom a, each a sphere (radius 0 for box corners and cylinder rim points) against the grid
    triangle below it; the heightfield is geom b. A grid is read as ``hf_data`` (normalised heights, the
    grid's first at ``hf_adr``, row-major), ``hf_nrow`` rows along local y, ``hf_ncol`` columns along
    local x and ``hf_size = (rx, ry, z_top, z_base)``."""
    T = types_of(np_dtype)
    scalar, vec3, vec4, transform = T.scalar, T.vec3, T.vec4, T.transform
    vec8 = wp.types.vector(8, scalar)
    K = _constants(np_dtype)
    INF, ZERO, HALF, ONE, TWO = K.INF, K.ZERO, K.HALF, K.ONE, K.TWO
    bf = basic_funcs(np_dtype)
    col, normalize, clip01, put_point, rot = bf.col, bf.normalize, bf.clip01, bf.put_point, bf.rot
    box_corner = box_feature_funcs(np_dtype).box_corner
    cylinder_support = segment_funcs(np_dtype).cylinder_support

    @_func
    def hfield_surface(hf_data: wp.array(dtype=scalar), hf_adr: int, hf_nrow: int, hf_ncol: int, hf_size: vec4,
                       x: scalar, y: scalar):
        """Height ``z`` and upward unit normal ``n`` of the grid triangle below the local point ``(x, y)``, and
        whether ``(x, y)`` lies on the grid (``_hfield_surface``). Cell ``(r, c)`` spans columns ``c, c + 1``
        and rows ``r, r + 1``; with ``u, v`` in ``[0, 1]`` across it, ``u >= v`` is the triangle ``(r, c),
        (r, c + 1), (r + 1, c + 1)`` and ``u < v`` the triangle ``(r, c), (r + 1, c), (r + 1, c + 1)``
        (MuJoCo's split); ``z = h00 + u ex + v ey`` and ``n = (-ex / dx, -ey / dy, 1) / |.|`` with ``ex, ey``
        the triangle's height changes across the cell. Off the grid the nearest cell is read (finite values)."""
        rx = hf_size[0]
        ry = hf_size[1]
        zt = hf_size[2]
        dx = TWO * rx / scalar(hf_ncol - 1)
        dy = TWO * ry / scalar(hf_nrow - 1)
        fx = (x + rx) / dx
        fy = (y + ry) / dy
        c = int(wp.min(wp.max(wp.floor(fx), ZERO), scalar(hf_ncol - 2)))
        r = int(wp.min(wp.max(wp.floor(fy), ZERO), scalar(hf_nrow - 2)))
        u = clip01(fx - scalar(c))
        v = clip01(fy - scalar(r))
        k = hf_adr + r * hf_ncol + c
        h00 = hf_data[k] * zt
        h10 = hf_data[k + 1] * zt
        h01 = hf_data[k + hf_ncol] * zt
        h11 = hf_data[k + hf_ncol + 1] * zt
        ex = h11 - h01  # height change across the cell along x (upper triangle, u < v)
        ey = h01 - h00  # ... along y
        if u >= v:  # lower triangle
            ex = h10 - h00
            ey = h11 - h10
        z = h00 + u * ex + v * ey
        n, _len = normalize(vec3(-ex / dx, -ey / dy, ONE), vec3(ZERO, ZERO, ONE))
        inside = wp.abs(x) <= rx and wp.abs(y) <= ry
        return z, n, inside

    @_func
    def hfield_point(pose_h: transform, hf_data: wp.array(dtype=scalar), hf_adr: int, hf_nrow: int, hf_ncol: int,
                     hf_size: vec4, pt: vec3, radius: scalar, slot: int, margin: scalar,
                     out_pos: wp.array(dtype=vec3), out_normal: wp.array(dtype=vec3),
                     out_dist: wp.array(dtype=scalar), out_valid: wp.array(dtype=wp.int32)):
        """A sphere of ``radius`` centred at the world point ``pt`` against the triangle below it
        (``_hfield_vs_points``): in the heightfield's frame ``x = R^T (pt - c)``, the distance ``(x_z - z) n_z - r``
        along the triangle's normal ``n``, the contact normal ``-n`` (from geom a to the terrain), the point midway
        between the witness points; a point off the grid does not exist."""
        c = wp.transform_get_translation(pose_h)
        R = rot(wp.transform_get_rotation(pose_h))
        x = wp.transpose(R) * (pt - c)
        z, n, inside = hfield_surface(hf_data, hf_adr, hf_nrow, hf_ncol, hf_size, x[0], x[1])
        dist = (x[2] - z) * n[2] - radius
        pos = x - n * (radius + HALF * dist)
        put_point(slot, c + R * pos, -(R * n), dist, inside, margin, out_pos, out_normal, out_dist, out_valid)

    @_func
    def sphere_hfield(pose_a: transform, size_a: vec3, pose_b: transform, hf_data: wp.array(dtype=scalar),
                      hf_adr: int, hf_nrow: int, hf_ncol: int, hf_size: vec4, margin: scalar, base: int,
                      out_pos: wp.array(dtype=vec3), out_normal: wp.array(dtype=vec3),
                      out_dist: wp.array(dtype=scalar), out_valid: wp.array(dtype=wp.int32)):
        """K = 1: the sphere's centre against the triangle below it (``_sphere_hfield``)."""
        hfield_point(pose_b, hf_data, hf_adr, hf_nrow, hf_ncol, hf_size, wp.transform_get_translation(pose_a),
                     size_a[0], base, margin, out_pos, out_normal, out_dist, out_valid)

    @_func
    def capsule_hfield(pose_a: transform, size_a: vec3, pose_b: transform, hf_data: wp.array(dtype=scalar),
                       hf_adr: int, hf_nrow: int, hf_ncol: int, hf_size: vec4, margin: scalar, base: int,
                       out_pos: wp.array(dtype=vec3), out_normal: wp.array(dtype=vec3),
                       out_dist: wp.array(dtype=scalar), out_valid: wp.array(dtype=wp.int32)):
        """K = 2: the capsule's end spheres, local -z first (``_capsule_hfield``)."""
        c = wp.transform_get_translation(pose_a)
        ax = size_a[1] * col(rot(wp.transform_get_rotation(pose_a)), 2)
        hfield_point(pose_b, hf_data, hf_adr, hf_nrow, hf_ncol, hf_size, c + -ONE * ax, size_a[0], base, margin,
                     out_pos, out_normal, out_dist, out_valid)
        hfield_point(pose_b, hf_data, hf_adr, hf_nrow, hf_ncol, hf_size, c + ONE * ax, size_a[0], base + 1, margin,
                     out_pos, out_normal, out_dist, out_valid)

    @_func
    def box_hfield(pose_a: transform, size_a: vec3, pose_b: transform, hf_data: wp.array(dtype=scalar),
                   hf_adr: int, hf_nrow: int, hf_ncol: int, hf_size: vec4, margin: scalar, base: int,
                   out_pos: wp.array(dtype=vec3), out_normal: wp.array(dtype=vec3),
                   out_dist: wp.array(dtype=scalar), out_valid: wp.array(dtype=wp.int32)):
        """K = 4: the 4 corners nearest the terrain, corners off the grid last, ties in corner order
        (``_box_hfield``)."""
        ca = wp.transform_get_translation(pose_a)
        Ra = rot(wp.transform_get_rotation(pose_a))
        c = wp.transform_get_translation(pose_b)
        R = rot(wp.transform_get_rotation(pose_b))
        key = vec8()  # each corner's distance to the triangle below it, inf off the grid (the sort key)
        for i in range(int(8)):
            x = wp.transpose(R) * (box_corner(ca, Ra, size_a, i) - c)
            z, n, inside = hfield_surface(hf_data, hf_adr, hf_nrow, hf_ncol, hf_size, x[0], x[1])
            key[i] = INF
            if inside:
                key[i] = (x[2] - z) * n[2]
        for i in range(int(8)):
            rank = int(0)  # position of corner i in a stable sort by key
            for j in range(int(8)):
                if key[j] < key[i] or (key[j] == key[i] and j < i):
                    rank += 1
            if rank < 4:
                hfield_point(pose_b, hf_data, hf_adr, hf_nrow, hf_ncol, hf_size, box_corner(ca, Ra, size_a, i), ZERO,
                             base + rank, margin, out_pos, out_normal, out_dist, out_valid)

    @_func
    def cylinder_hfield(pose_a: transform, size_a: vec3, pose_b: transform, hf_data: wp.array(dtype=scalar),
                        hf_adr: int, hf_nrow: int, hf_ncol: int, hf_size: vec4, margin: scalar, base: int,
                        out_pos: wp.array(dtype=vec3), out_normal: wp.array(dtype=vec3),
                        out_dist: wp.array(dtype=scalar), out_valid: wp.array(dtype=wp.int32)):
        """K = 4: PLANE-CYLINDER's four rim points for the terrain normal below the cylinder's centre (the
        heightfield's +z when the centre is off the grid), each against the triangle below it
        (``_cylinder_hfield``)."""
        ca = wp.transform_get_translation(pose_a)
        c = wp.transform_get_translation(pose_b)
        R = rot(wp.transform_get_rotation(pose_b))
        x = wp.transpose(R) * (ca - c)
        _z, n, inside = hfield_surface(hf_data, hf_adr, hf_nrow, hf_ncol, hf_size, x[0], x[1])
        if not inside:
            n = vec3(ZERO, ZERO, ONE)
        rim, _cap = cylinder_support(ca, rot(wp.transform_get_rotation(pose_a)), size_a, -(R * n))
        for i in range(4):
            hfield_point(pose_b, hf_data, hf_adr, hf_nrow, hf_ncol, hf_size, rim[i], ZERO, base + i, margin,
                         out_pos, out_normal, out_dist, out_valid)

    return _namespace(hfield_surface, hfield_point, sphere_hfield, capsule_hfield, box_hfield, cylinder_hfield)


@functools.cache
def collide_hfield_func(np_dtype) -> wp.Function:
    """``collide_hfield`` of one precision (see the module docstring; ``collide`` of :mod:`kamino.jax_ref.collision`
    with ``hfield=``): the routine of geom a's type against the heightfield geom b, found at run time in a table
    unrolled at compile time."""
    T = types_of(np_dtype)
    scalar, vec3, vec4, transform = T.scalar, T.vec3, T.vec4, T.transform
    hf = hfield_funcs(np_dtype)
    #: ``(type_a, routine)``: the routines of the pairs ``(type_a, HFIELD)``
    pairs = ((SPHERE, hf.sphere_hfield), (CAPSULE, hf.capsule_hfield), (BOX, hf.box_hfield),
             (CYLINDER, hf.cylinder_hfield))

    @_func
    def collide_hfield(type_a: int, pose_a: transform, size_a: vec3, pose_b: transform,
                       hf_data: wp.array(dtype=scalar), hf_adr: int, hf_nrow: int, hf_ncol: int, hf_size: vec4,
                       margin: scalar, base: int, out_pos: wp.array(dtype=vec3), out_normal: wp.array(dtype=vec3),
                       out_dist: wp.array(dtype=scalar), out_valid: wp.array(dtype=wp.int32)):
        """Write the ``K = MAX_POINTS[(type_a, HFIELD)]`` candidate points of geom a against the heightfield geom b
        (its grid: ``hf_*``, :func:`hfield_funcs`) into slots ``base .. base + K - 1``; an unsupported ``type_a``
        writes nothing."""
        for i in range(wp.static(len(pairs))):
            if type_a == wp.static(pairs[i][0]):
                wp.static(pairs[i][1])(pose_a, size_a, pose_b, hf_data, hf_adr, hf_nrow, hf_ncol, hf_size, margin,
                                       base, out_pos, out_normal, out_dist, out_valid)

    return collide_hfield


@functools.cache
def collide_pair_func(np_dtype) -> wp.Function:
    """``collide_pair`` of one precision (see the module docstring; ``collide`` of
    :mod:`kamino.jax_ref.collision`): the routine of the pair's types, found at run time in a table unrolled
    at compile time (the types vary from pair to pair)."""
    T = types_of(np_dtype)
    scalar, vec3, transform = T.scalar, T.vec3, T.transform
    pp, sc, cp = plane_pair_funcs(np_dtype), sphere_capsule_pair_funcs(np_dtype), cylinder_pair_funcs(np_dtype)
    sp = sdf_pair_funcs(np_dtype)
    #: ``(type_a, type_b, routine)``: the routines of one pair of types
    pairs = ((PLANE, SPHERE, pp.plane_sphere), (PLANE, CAPSULE, pp.plane_capsule), (PLANE, BOX, pp.plane_box),
             (PLANE, CYLINDER, pp.plane_cylinder), (PLANE, ELLIPSOID, pp.plane_ellipsoid),
             (SPHERE, SPHERE, sc.sphere_sphere), (SPHERE, CAPSULE, sc.sphere_capsule),
             (CAPSULE, CAPSULE, sc.capsule_capsule), (BOX, BOX, box_box_func(np_dtype)),
             (BOX, CYLINDER, cp.box_cylinder), (CYLINDER, CYLINDER, cp.cylinder_cylinder))
    #: ``(type_a, routine)``: a sphere or capsule against a box or cylinder, the routine taking ``type_b`` first
    sdf_pairs = ((SPHERE, sp.sphere_sdf_pair), (CAPSULE, sp.capsule_sdf_pair))

    @_func
    def collide_pair(type_a: int, type_b: int, pose_a: transform, size_a: vec3, pose_b: transform, size_b: vec3,
                     margin: scalar, base: int, out_pos: wp.array(dtype=vec3), out_normal: wp.array(dtype=vec3),
                     out_dist: wp.array(dtype=scalar), out_valid: wp.array(dtype=wp.int32)):
        """Write the ``K = MAX_POINTS[(type_a, type_b)]`` candidate points of one geom pair
        (``type_a <= type_b``) into slots ``base .. base + K - 1`` (``jax_ref.collision.collide``); an
        unsupported or unordered pair writes nothing."""
        for i in range(wp.static(len(pairs))):
            if type_a == wp.static(pairs[i][0]) and type_b == wp.static(pairs[i][1]):
                wp.static(pairs[i][2])(pose_a, size_a, pose_b, size_b, margin, base, out_pos, out_normal, out_dist,
                                       out_valid)
        for i in range(wp.static(len(sdf_pairs))):
            if type_a == wp.static(sdf_pairs[i][0]) and (type_b == BOX or type_b == CYLINDER):
                wp.static(sdf_pairs[i][1])(type_b, pose_a, size_a, pose_b, size_b, margin, base, out_pos,
                                           out_normal, out_dist, out_valid)

    return collide_pair


@functools.cache
def collide_kernel(np_dtype) -> wp.Kernel:
    """A kernel running ``collide_pair`` one thread per pair, for one precision.

    Inputs (``n`` pairs): ``type_a, type_b: wp.array(dtype=wp.int32)``, ``pose_a, pose_b:
    wp.array(dtype=transform)``, ``size_a, size_b: wp.array(dtype=vec3)``, ``margin:
    wp.array(dtype=scalar)``, ``base: wp.array(dtype=wp.int32)`` (first output slot of each pair),
    then the outputs ``out_pos, out_normal: wp.array(dtype=vec3)``, ``out_dist:
    wp.array(dtype=scalar)``, ``out_valid: wp.array(dtype=wp.int32)`` sized for the slots. Launch with
    ``dim=n``.
    """
    T = types_of(np_dtype)
    scalar, vec3, transform = T.scalar, T.vec3, T.transform
    collide_pair = collide_pair_func(np_dtype)

    @wp.kernel(module="unique", module_options=KERNEL_OPTIONS)
    def collide_pairs(type_a: wp.array(dtype=wp.int32), type_b: wp.array(dtype=wp.int32),
                      pose_a: wp.array(dtype=transform), size_a: wp.array(dtype=vec3),
                      pose_b: wp.array(dtype=transform), size_b: wp.array(dtype=vec3),
                      margin: wp.array(dtype=scalar), base: wp.array(dtype=wp.int32),
                      out_pos: wp.array(dtype=vec3), out_normal: wp.array(dtype=vec3),
                      out_dist: wp.array(dtype=scalar), out_valid: wp.array(dtype=wp.int32)):
        i = wp.tid()
        collide_pair(type_a[i], type_b[i], pose_a[i], size_a[i], pose_b[i], size_b[i], margin[i], base[i],
                     out_pos, out_normal, out_dist, out_valid)

    return collide_pairs


@functools.cache
def collide_hfield_kernel(np_dtype) -> wp.Kernel:
    """A kernel running ``collide_hfield`` one thread per pair, for one precision.

    Inputs (``n`` pairs): ``type_a: wp.array(dtype=wp.int32)``, ``pose_a, pose_b: wp.array(dtype=transform)``,
    ``size_a: wp.array(dtype=vec3)``, the grids ``hf_data: wp.array(dtype=scalar)`` (shared by all pairs) and,
    per pair, ``hf_adr, hf_nrow, hf_ncol: wp.array(dtype=wp.int32)``, ``hf_size: wp.array(dtype=vec4)``, then
    ``margin: wp.array(dtype=scalar)``, ``base: wp.array(dtype=wp.int32)`` and the outputs of
    :func:`collide_kernel`. Launch with ``dim=n``.
    """
    T = types_of(np_dtype)
    scalar, vec3, vec4, transform = T.scalar, T.vec3, T.vec4, T.transform
    collide_hfield = collide_hfield_func(np_dtype)

    @wp.kernel(module="unique", module_options=KERNEL_OPTIONS)
    def collide_hfield_pairs(type_a: wp.array(dtype=wp.int32), pose_a: wp.array(dtype=transform),
                             size_a: wp.array(dtype=vec3), pose_b: wp.array(dtype=transform),
                             hf_data: wp.array(dtype=scalar), hf_adr: wp.array(dtype=wp.int32),
                             hf_nrow: wp.array(dtype=wp.int32), hf_ncol: wp.array(dtype=wp.int32),
                             hf_size: wp.array(dtype=vec4), margin: wp.array(dtype=scalar),
                             base: wp.array(dtype=wp.int32), out_pos: wp.array(dtype=vec3),
                             out_normal: wp.array(dtype=vec3), out_dist: wp.array(dtype=scalar),
                             out_valid: wp.array(dtype=wp.int32)):
        i = wp.tid()
        collide_hfield(type_a[i], pose_a[i], size_a[i], pose_b[i], hf_data, hf_adr[i], hf_nrow[i], hf_ncol[i],
                       hf_size[i], margin[i], base[i], out_pos, out_normal, out_dist, out_valid)

    return collide_hfield_pairs
