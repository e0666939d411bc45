"""Narrow-phase collision between two convex geoms, in pure JAX (jit- and vmap-able).

``collide(type_a, type_b, pose_a, size_a, pose_b, size_b, margin)`` handles ONE pair of geoms whose
types are static and ordered (``type_a <= type_b``); the caller vmaps it over the pairs of one type
combination. It returns ``K = MAX_POINTS[(type_a, type_b)]`` candidate points (``ContactPoints``):
``normal`` points from geom a to geom b, ``dist`` is the signed distance along it (< 0: penetration),
the witness points are ``pos -/+ normal * dist / 2`` on a / b, and ``valid`` marks the points that
exist and have ``dist <= margin`` (speculative contacts included). Every entry is finite, valid or
not, and the order of the points is a fixed function of the input. Poses are ``(p, q)`` with the
quaternion ``(x, y, z, w)``; sizes follow MuJoCo (``kamino.model.GeomType``). Everything follows the
dtype of the inputs (float32 or float64). The candidate points feed the contacts of docs/formulation.md §4.2
(:mod:`kamino.jax_ref.contacts`).

Supported pairs, K and algorithm (exact = the distance of separated geoms is the Euclidean one):

===================  ==  ==========================================================================
pair                 K   algorithm
===================  ==  ==========================================================================
PLANE-SPHERE         1   exact
PLANE-CAPSULE        2   exact, the two segment ends
PLANE-BOX            4   exact, the 4 deepest of the 8 corners (a box lying flat: its bottom face)
PLANE-ELLIPSOID      1   exact, the support point along the plane normal
PLANE-CYLINDER       4   MuJoCo's choice: the deepest rim point of each cap, and two more rim points
                         of the deeper cap at +-120 deg from its deepest one (a standing cylinder gets
                         a support triangle, a lying one its two line-contact ends)
SPHERE-SPHERE        1   exact
SPHERE-CAPSULE       1   exact
SPHERE-BOX           1   exact signed distance to the box (centre inside too)
SPHERE-CYLINDER      1   exact signed distance to the cylinder
CAPSULE-CAPSULE      2   exact closest points of the segments; when the segments are near parallel
                         (sin angle < 0.1) also the far end of their overlap (a capsule lying on one)
CAPSULE-BOX          2   exact minimum of the box's signed distance along the segment (golden-section
                         search to ~1e-10 of the segment), plus the far end of the part of the segment
                         lying over the touched face
CAPSULE-CYLINDER     2   the same with the cylinder's signed distance (cap disk or side band)
BOX-BOX              8   separating-axis test over the 15 axes (edge axes need a 5 % better value than
                         the best face axis), then the incident face clipped against the reference
                         face (candidate enumeration), or one edge-edge point; for separated boxes the
                         exact closest pair (vertex-box and edge-edge) is added when it is closer than
                         the clipped points
BOX-CYLINDER         4   APPROXIMATION: two families of points, each a true surface point of one geom
                         with its exact signed distance to the other; the family with the smaller
                         distance is kept (on near ties, the one with more points within the margin).
                         (1) On the cylinder: the three rim points of the cap facing the box (as
                         PLANE-CYLINDER), each pulled towards the cap point under the box until within
                         max(that point's distance, margin) (a cap on a smaller face keeps a support
                         triangle on it), and the nearest of: the minimum along the support generator
                         line, the point of 64 rounds of alternating projections between the solids,
                         that cap point. (2) The 4 box corners nearest the cylinder.
CYLINDER-CYLINDER    4   APPROXIMATION: family (1) of each cylinder against the other; the better kept
SPHERE-HFIELD        1   APPROXIMATION (all HFIELD pairs): candidate points of the geom, each against
CAPSULE-HFIELD       2   the grid triangle below it (see "Heightfields" below). Sphere: its centre;
BOX-HFIELD           4   capsule: its two end centres; box: the 4 of its 8 corners nearest the
CYLINDER-HFIELD      4   terrain; cylinder: PLANE-CYLINDER's four rim points for the terrain normal
                         below its centre
===================  ==  ==========================================================================

Heightfields (``GeomType.HFIELD``, always geom b: its type sorts last). The terrain is MuJoCo's surface: the
grid of ``nrow x ncol`` heights over ``[-rx, rx] x [-ry, ry]`` of the heightfield's frame, each cell split into
two triangles along the diagonal from its ``(-x, -y)`` corner to its ``(+x, +y)`` corner. A candidate point
``x`` (with the radius ``r`` of the sphere or capsule around it, 0 for box corners and cylinder rim points)
takes the triangle below its local ``(x, y)``, with height ``z(x, y)`` and upward unit normal ``n``; its
distance is ``(x_z - z(x, y)) n_z - r``, the distance to that triangle's plane along ``n`` (exact for a
sphere over the inside of a triangle), and the contact normal is ``-n`` (from the geom to the terrain). A
point whose ``(x, y)`` lies outside the grid has no contact. What the model misses: contact away from the
candidate points (a box edge or a capsule's middle across a ridge, a cylinder's side on a bump, a sphere
touching a steep neighbouring triangle before the one below its centre), and the triangle's edges and
extent (a point is measured against the plane of the triangle below it, which is inexact near a ridge or a
valley, and the terrain has no walls at the grid's border nor a bottom at ``z_base``). On a flat or planar
terrain (all heights equal, or a ramp) every HFIELD pair equals the PLANE pair of its geom.

Penetration depth: exact (minimum translation) for the sphere pairs, the plane pairs and BOX-BOX
(up to the 5 % face bias and the clipping); for CAPSULE-BOX / CAPSULE-CYLINDER it is that of the
deepest point of the capsule's axis, and for the approximated cylinder pairs that of the deepest
sampled point; both can be less than the minimum translation distance for deep penetrations.

Accuracy of the approximated pairs: each point is a true point of one solid with its true signed
distance to the other, so the reported distance is never below the true one (nor, penetrating, below
minus the minimum translation distance). Resting configurations (standing, lying, stacked, crossed,
a small box on a cap) are exact. On random poses of 0.3-0.5 m geoms against MuJoCo's GJK/EPA: for
separated geoms the error was below 1e-5 m in 95 % of cases and at most ~2 mm (slow convergence of
the alternating projections for near-tangent features); overlapping geoms were always found
(distance <= ~0.2 mm), but with the depth underestimated by ~10-30 % (median) and up to ~60 %.
Degenerate inputs (concentric spheres, a sphere centre on a capsule axis, intersecting capsule
axes, coincident boxes, zero-length segments) fall back to body-fixed directions: geom a's local +z
for SPHERE-SPHERE, the capsule's local +x for SPHERE-CAPSULE, ``axis_a x axis_b`` (else a's local +x)
for CAPSULE-CAPSULE; a point inside a box leaves through the face of least depth (the first axis and
the + side on ties); a point on a cylinder axis uses the cylinder's local +x as radial direction.
"""

from __future__ import annotations

import dataclasses
import itertools
import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from kamino.config import BISECTION_STEPS, GOLDEN_STEPS, PARALLEL_SIN2, PROJECTION_ROUNDS
from kamino.model import CONTACT_POINTS, GeomType
from kamino.spatial import quat_to_matrix


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class ContactPoints:
    """Candidate contact points of one geom pair (arrays ``[K, ...]``)."""

    pos: jax.Array  # [K, 3] world point midway between the two surfaces' witness points
    normal: jax.Array  # [K, 3] unit normal pointing from geom a to geom b
    dist: jax.Array  # [K] signed distance between the surfaces along normal (negative = penetration)
    valid: jax.Array  # [K] bool: the point exists and dist <= margin


# ---------------------------------------------------------------------------------------------
# constants and small helpers
# ---------------------------------------------------------------------------------------------

_EDGE_BIAS_REL = 0.05  # an edge axis must beat the best face axis by 5 % of its separation ...
_EDGE_BIAS_ABS = 1e-5  # ... plus this fraction of the boxes' size
_BOX_SIGNS = np.array(list(itertools.product((-1.0, 1.0), repeat=3)))  # [8, 3] corner pattern
_QUAD = np.array([[1.0, 1.0], [-1.0, 1.0], [-1.0, -1.0], [1.0, -1.0]])  # a face's corners, in order


def _edge_tables():
    """The 12 box edges in a fixed order: midpoint sign pattern (0 along the edge) and unit direction."""
    mid, direction = [], []
    for i in range(3):
        for s1, s2 in itertools.product((-1.0, 1.0), repeat=2):
            m = np.zeros(3)
            m[(i + 1) % 3], m[(i + 2) % 3] = s1, s2
            mid.append(m)
            direction.append(np.eye(3)[i])
    return np.array(mid), np.array(direction)


_EDGE_MID, _EDGE_DIR = _edge_tables()


def _rtol(dtype) -> float:
    """Relative tolerance for geometric comparisons (insideness, duplicates, ties)."""
    return 1e-7 if jnp.finfo(dtype).bits >= 64 else 1e-4


def _tie_tol(dtype) -> float:
    """Relative tolerance below which the searches treat values as equal (rounding noise)."""
    return 1e-12 if jnp.finfo(dtype).bits >= 64 else 1e-5


def _tiny(dtype) -> float:
    """A positive number whose inverse is still finite (safe divisions)."""
    return float(jnp.finfo(dtype).tiny) ** 0.5


def _frame(pose):
    """World position and rotation matrix of a pose ``(px, py, pz, qx, qy, qz, qw)``."""
    return pose[:3], quat_to_matrix(pose[3:7])


def _normalize(v, fallback):
    """``(v / |v|, |v|)`` over the last axis, ``(fallback, 0)`` where ``|v|`` is ~0 (finite gradients)."""
    n2 = jnp.sum(v * v, axis=-1, keepdims=True)
    ok = n2 > jnp.finfo(v.dtype).eps ** 2
    n = jnp.sqrt(jnp.where(ok, n2, 1.0))
    return jnp.where(ok, v / n, fallback), jnp.where(ok, n, 0.0)[..., 0]


def _sign(x):
    """``+1`` for ``x >= 0``, else ``-1`` (never 0)."""
    return jnp.where(x >= 0, 1.0, -1.0).astype(x.dtype)


def _safe_div(num, den):
    """``num / den``, 0 where ``den`` is ~0."""
    ok = jnp.abs(den) > _tiny(den.dtype)
    return jnp.where(ok, num / jnp.where(ok, den, 1.0), 0.0)


def _world_sdf(local_sdf, pose):
    """Lift a local signed-distance function ``p -> (dist, outward normal, closest surface point)``
    to world coordinates."""
    c, R = _frame(pose)

    def sdf(p):
        d, n, q = local_sdf((p - c) @ R)
        return d, n @ R.T, c + q @ R.T

    return sdf


def _points_vs_sdf(x, sdf, on_a: bool):
    """Contacts of surface points ``x [N, 3]`` of one geom against the exact signed distance of the
    other: the witness on the other geom is its surface point nearest to ``x``."""
    d, n_out, q = jax.vmap(sdf)(x)
    normal = -n_out if on_a else n_out  # n_out is the other geom's outward normal
    return 0.5 * (x + q), normal, d, jnp.ones(d.shape, bool)


def _golden_min(f, tol):
    """Minimise a convex ``f`` on ``[0, 1]`` by golden-section search (a fixed number of steps).

    Values within ``tol`` count as ties (rounding noise); ties move right, so a flat minimum resolves
    to its largest ``t``. The result is snapped to an end of the interval when that end is as good.
    """
    g = (math.sqrt(5.0) - 1.0) / 2.0
    zero, one = jnp.zeros_like(tol), jnp.ones_like(tol)
    c, d = one - g, zero + g

    def step(_, s):
        lo, hi, c, d, fc, fd = s
        left = fc < fd - tol  # the minimum lies in [lo, d]
        lo, hi = jnp.where(left, lo, c), jnp.where(left, d, hi)
        new = jnp.where(left, hi - g * (hi - lo), lo + g * (hi - lo))
        fn = f(new)
        c, d = jnp.where(left, new, d), jnp.where(left, c, new)
        fc, fd = jnp.where(left, fn, fd), jnp.where(left, fc, fn)
        return lo, hi, c, d, fc, fd

    lo, hi, *_ = jax.lax.fori_loop(0, GOLDEN_STEPS, step, (zero, one, c, d, f(c), f(d)))
    t = 0.5 * (lo + hi)
    ft, f0, f1 = f(t), f(zero), f(one)
    t = jnp.where(f1 <= ft + tol, one, t)
    return jnp.where(f0 < jnp.minimum(ft, f1) - tol, zero, t)


# ---------------------------------------------------------------------------------------------
# signed distances of the primitive solids (local frame)
# ---------------------------------------------------------------------------------------------


def _box_sdf(p, half):
    """Signed distance from local point ``p`` to the box ``|x_i| <= half_i``, its outward normal at the
    nearest surface point, and that point. Inside, the point leaves through the face of least depth."""
    q = jnp.abs(p) - half
    k = jnp.argmax(q)
    face = jnp.arange(3) == k
    s = _sign(p)
    face_n = jnp.where(face, s, 0.0)
    face_pt = jnp.where(face, s * half, p)
    clamped = jnp.clip(p, -half, half)
    n_out, d_out = _normalize(p - clamped, face_n)
    outside = jnp.any(q > 0)
    return (jnp.where(outside, d_out, q[k]), jnp.where(outside, n_out, face_n),
            jnp.where(outside, clamped, face_pt))


def _cylinder_sdf(p, radius, half_height):
    """Signed distance from local point ``p`` to the solid cylinder (axis local z), outward normal at
    the nearest surface point, and that point. Inside, the point leaves through the side or a cap,
    whichever is nearer (the side on ties)."""
    x_hat = jnp.array([1.0, 0.0, 0.0], p.dtype)
    z_hat = jnp.array([0.0, 0.0, 1.0], p.dtype)
    e_r, rho = _normalize(p * jnp.array([1.0, 1.0, 0.0], p.dtype), x_hat)
    z = p[2]
    qr, qz = rho - radius, jnp.abs(z) - half_height
    side = qr >= qz
    in_n = jnp.where(side, e_r, _sign(z) * z_hat)
    in_pt = jnp.where(side, radius * e_r + z * z_hat, p.at[2].set(_sign(z) * half_height))
    clamped = jnp.minimum(rho, radius) * e_r + jnp.clip(z, -half_height, half_height) * z_hat
    n_out, d_out = _normalize(p - clamped, in_n)
    outside = (qr > 0) | (qz > 0)
    return (jnp.where(outside, d_out, jnp.maximum(qr, qz)), jnp.where(outside, n_out, in_n),
            jnp.where(outside, clamped, in_pt))


def _slab_interval(p0, d, half):
    """Per coordinate, the interval of ``t`` with ``|p0 + t d| <= half`` (empty: lo > hi)."""
    moving = jnp.abs(d) > _tiny(d.dtype)
    ds = jnp.where(moving, d, 1.0)
    ta, tb = (-half - p0) / ds, (half - p0) / ds
    inside = jnp.abs(p0) <= half
    lo = jnp.where(moving, jnp.minimum(ta, tb), jnp.where(inside, -jnp.inf, jnp.inf))
    hi = jnp.where(moving, jnp.maximum(ta, tb), jnp.where(inside, jnp.inf, -jnp.inf))
    return lo, hi


def _box_face_interval(p0, d, n_out, half):
    """``t``-interval where the segment ``p0 + t d`` lies over the box face whose normal is the dominant
    direction of ``n_out`` (all in the box frame)."""
    lo, hi = _slab_interval(p0, d, half)
    normal_axis = jnp.arange(3) == jnp.argmax(jnp.abs(n_out))
    return jnp.max(jnp.where(normal_axis, -jnp.inf, lo)), jnp.min(jnp.where(normal_axis, jnp.inf, hi))


def _cylinder_face_interval(p0, d, n_out, radius, half_height):
    """``t``-interval where the segment lies over the cylinder feature touched with normal ``n_out``:
    within the cap disk for a cap normal, within the axial band for a side normal (cylinder frame)."""
    cap = jnp.abs(n_out[2]) >= jnp.linalg.norm(n_out[:2])
    a = d[0] * d[0] + d[1] * d[1]
    b = p0[0] * d[0] + p0[1] * d[1]
    c = p0[0] * p0[0] + p0[1] * p0[1] - radius * radius
    disc = b * b - a * c
    moving = a > _tiny(d.dtype)
    root = jnp.sqrt(jnp.where(disc > 0, disc, 0.0))
    a_s = jnp.where(moving, a, 1.0)
    lo_c = jnp.where(moving, jnp.where(disc >= 0, (-b - root) / a_s, jnp.inf), jnp.where(c <= 0, -jnp.inf, jnp.inf))
    hi_c = jnp.where(moving, jnp.where(disc >= 0, (-b + root) / a_s, -jnp.inf), jnp.where(c <= 0, jnp.inf, -jnp.inf))
    lo_s, hi_s = _slab_interval(p0[2], d[2], half_height)
    return jnp.where(cap, lo_c, lo_s), jnp.where(cap, hi_c, hi_s)


# ---------------------------------------------------------------------------------------------
# plane pairs
# ---------------------------------------------------------------------------------------------


def _plane_vs_points(pose_plane, pts, radius):
    """Spheres of ``radius`` centred at ``pts [N, 3]`` against the plane (exact)."""
    p, R = _frame(pose_plane)
    n = R[:, 2]
    dist = (pts - p) @ n - radius
    pos = pts - n * (radius + 0.5 * dist)[:, None]
    return pos, jnp.broadcast_to(n, pts.shape), dist, jnp.ones(dist.shape, bool)


def _plane_sphere(pose_a, size_a, pose_b, size_b, margin):
    """Exact: height of the centre above the plane minus the radius."""
    return _plane_vs_points(pose_a, pose_b[None, :3], size_b[0])


def _plane_capsule(pose_a, size_a, pose_b, size_b, margin):
    """Exact: the two end spheres of the capsule (segment end at local -z first)."""
    c, R = _frame(pose_b)
    ends = c + jnp.array([-1.0, 1.0], c.dtype)[:, None] * (size_b[1] * R[:, 2])
    return _plane_vs_points(pose_a, ends, size_b[0])


def _box_corners(pose, half):
    """The 8 corners ``[8, 3]`` of a box, in the fixed ``_BOX_SIGNS`` order."""
    c, R = _frame(pose)
    return c + (jnp.asarray(_BOX_SIGNS, half.dtype) * half) @ R.T


def _plane_box(pose_a, size_a, pose_b, size_b, margin):
    """Exact: the 4 corners deepest below the plane (stable sort: ties keep the corner order)."""
    corners = _box_corners(pose_b, size_b)
    _, R = _frame(pose_a)
    order = jnp.argsort(corners @ R[:, 2], stable=True)[:4]
    return _plane_vs_points(pose_a, corners[order], jnp.zeros((), size_b.dtype))


def _plane_ellipsoid(pose_a, size_a, pose_b, size_b, margin):
    """Exact: the ellipsoid's support point along the plane's inward normal, ``c + R S^2 d / |S d|``
    with ``d = -R^T n`` and ``S = diag(semi-axes)``."""
    _, Ra = _frame(pose_a)
    c, R = _frame(pose_b)
    d = -(R.T @ Ra[:, 2])
    sd = size_b * d
    x = size_b * sd / jnp.sqrt(jnp.sum(sd * sd))
    return _plane_vs_points(pose_a, (c + R @ x)[None, :], jnp.zeros((), size_b.dtype))


def _cylinder_support(pose, size, direction):
    """Rim points of a cylinder for a support ``direction``: ``[deepest rim point of the cap further
    along it, the same on the other cap, the two points of the first cap at +-120 deg]`` and that
    cap's centre. The radial direction falls back to the local x axis when ``direction`` is along the
    axis."""
    c, R = _frame(pose)
    radius, hh = size[0], size[1]
    axis = R[:, 2]
    s = _sign(direction @ axis)
    cap, other = c + s * hh * axis, c - s * hh * axis
    r_dir, _ = _normalize(direction - (direction @ axis) * axis, R[:, 0])
    t_dir = jnp.cross(axis, r_dir)
    h = 0.5 * math.sqrt(3.0)
    pts = jnp.stack([cap + radius * r_dir, other + radius * r_dir,
                     cap + radius * (-0.5 * r_dir + h * t_dir), cap + radius * (-0.5 * r_dir - h * t_dir)])
    return pts, cap


def _plane_cylinder(pose_a, size_a, pose_b, size_b, margin):
    """MuJoCo's four rim points (see module docstring); each has its exact height over the plane."""
    _, R = _frame(pose_a)
    pts, _ = _cylinder_support(pose_b, size_b, -R[:, 2])
    return _plane_vs_points(pose_a, pts, jnp.zeros((), size_b.dtype))


# ---------------------------------------------------------------------------------------------
# sphere and capsule pairs
# ---------------------------------------------------------------------------------------------


def _sphere_pair(ca, ra, cb, rb, fallback):
    """Two spheres (exact); ``fallback`` is the normal when the centres coincide. Broadcasts."""
    n, length = _normalize(cb - ca, fallback)
    dist = length - ra - rb
    pos = ca + n * (ra + 0.5 * dist)[..., None]
    return pos, n, dist


def _sphere_sphere(pose_a, size_a, pose_b, size_b, margin):
    """Exact; concentric spheres get geom a's local +z as normal."""
    _, R = _frame(pose_a)
    pos, n, dist = _sphere_pair(pose_a[:3], size_a[0], pose_b[:3], size_b[0], R[:, 2])
    return pos[None], n[None], dist[None], jnp.ones((1,), bool)


def _capsule_segment(pose, size):
    """Start point (local z = -half-length) and direction vector (start -> end) of a capsule's segment."""
    c, R = _frame(pose)
    axis = R[:, 2] * size[1]
    return c - axis, 2.0 * axis, R


def _sphere_capsule(pose_a, size_a, pose_b, size_b, margin):
    """Exact: the sphere against the nearest point of the capsule's segment (fallback normal: the
    capsule's local +x when the centre is on the segment)."""
    p0, d, R = _capsule_segment(pose_b, size_b)
    t = jnp.clip(_safe_div((pose_a[:3] - p0) @ d, d @ d), 0.0, 1.0)
    pos, n, dist = _sphere_pair(pose_a[:3], size_a[0], p0 + t * d, size_b[0], R[:, 0])
    return pos[None], n[None], dist[None], jnp.ones((1,), bool)


def _segment_closest(p1, d1, p2, d2):
    """Parameters ``(s, t)`` of the closest points ``p1 + s d1``, ``p2 + t d2`` of two segments
    (Ericson, Real-Time Collision Detection, 5.1.9; parallel segments take ``s = 0`` first).
    Broadcasts over leading axes; zero-length segments are handled."""
    r = p1 - p2
    a, e = jnp.sum(d1 * d1, -1), jnp.sum(d2 * d2, -1)
    b, c, f = jnp.sum(d1 * d2, -1), jnp.sum(d1 * r, -1), jnp.sum(d2 * r, -1)
    denom = a * e - b * b
    rtol = _rtol(p1.dtype)
    s = jnp.where(denom > rtol * rtol * a * e, jnp.clip(_safe_div(b * f - c * e, denom), 0.0, 1.0), 0.0)
    t = _safe_div(b * s + f, e)
    s_lo, s_hi = jnp.clip(_safe_div(-c, a), 0.0, 1.0), jnp.clip(_safe_div(b - c, a), 0.0, 1.0)
    s = jnp.where(t < 0, s_lo, jnp.where(t > 1, s_hi, s))  # t clamped: recompute s
    t = jnp.clip(t, 0.0, 1.0)
    # degenerate segments: a point against a segment, or two points
    tiny = _tiny(p1.dtype)
    t = jnp.where(e <= tiny, 0.0, jnp.where(a <= tiny, jnp.clip(_safe_div(f, e), 0.0, 1.0), t))
    s = jnp.where(a <= tiny, 0.0, jnp.where(e <= tiny, jnp.clip(_safe_div(-c, a), 0.0, 1.0), s))
    return s, t


def _capsule_capsule(pose_a, size_a, pose_b, size_b, margin):
    """Exact closest points of the two segments, as two spheres. When the segments are near parallel
    (sin angle < 0.1) and their projections overlap, a second point at the end of the overlap (in
    a's parameter) farther from the first, against its nearest point on b's segment; otherwise the
    second point does not exist. Intersecting axes use ``axis_a x axis_b`` (else a's local +x)."""
    pa, da, Ra = _capsule_segment(pose_a, size_a)
    pb, db, _ = _capsule_segment(pose_b, size_b)
    s1, t1 = _segment_closest(pa, da, pb, db)
    a, e = da @ da, db @ db
    # overlap of b's segment projected on a's line, in a's parameter
    sb = _safe_div(jnp.stack([(pb - pa) @ da, (pb + db - pa) @ da]), a)
    lo, hi = jnp.maximum(jnp.min(sb), 0.0), jnp.minimum(jnp.max(sb), 1.0)
    s2 = jnp.clip(jnp.where(jnp.abs(s1 - lo) >= jnp.abs(s1 - hi), lo, hi), 0.0, 1.0)
    t2 = jnp.clip(_safe_div((pa + s2 * da - pb) @ db, e), 0.0, 1.0)
    cross = jnp.cross(da, db)
    parallel = cross @ cross <= PARALLEL_SIN2 * a * e
    second = parallel & (lo <= hi) & (jnp.abs(s2 - s1) > 1e-3) & (a > 0)
    fallback, _ = _normalize(cross, Ra[:, 0])
    s, t = jnp.stack([s1, s2]), jnp.stack([t1, t2])
    pos, n, dist = _sphere_pair(pa + s[:, None] * da, size_a[0], pb + t[:, None] * db, size_b[0], fallback)
    return pos, n, dist, jnp.stack([jnp.ones((), bool), second])


def _sphere_vs_sdf(pose_a, size_a, pose_b, local_sdf):
    """A sphere (geom a) against the exact signed distance of geom b."""
    pos, n, d, ok = _points_vs_sdf(pose_a[None, :3], _world_sdf(local_sdf, pose_b), on_a=True)
    r = size_a[0]
    return pos + 0.5 * r * n, n, d - r, ok


def _sphere_box(pose_a, size_a, pose_b, size_b, margin):
    """Exact signed distance of the centre to the box minus the radius (centre inside: out through
    the face of least depth)."""
    return _sphere_vs_sdf(pose_a, size_a, pose_b, lambda p: _box_sdf(p, size_b))


def _sphere_cylinder(pose_a, size_a, pose_b, size_b, margin):
    """Exact signed distance of the centre to the cylinder minus the radius."""
    return _sphere_vs_sdf(pose_a, size_a, pose_b, lambda p: _cylinder_sdf(p, size_b[0], size_b[1]))


def _capsule_vs_sdf(pose_a, size_a, pose_b, size_b, local_sdf, face_interval):
    """A capsule (geom a) against geom b with exact signed distance ``local_sdf`` (b's frame).

    Point 1: the minimum of b's signed distance along the segment (convex in the segment parameter,
    golden-section search). Point 2: the end, farther from point 1, of the part of the segment lying
    over the feature of b that point 1 touches (``face_interval``); it does not exist when that part
    is empty or shorter than 1e-3 of the segment.
    """
    p0w, dw, _ = _capsule_segment(pose_a, size_a)
    cb, Rb = _frame(pose_b)
    p0, d = (p0w - cb) @ Rb, dw @ Rb
    tie = _tie_tol(d.dtype) * (jnp.sum(size_a[:2]) + jnp.sum(size_b))
    t1 = _golden_min(lambda t: local_sdf(p0 + t * d)[0], tie)
    _, n1, _ = local_sdf(p0 + t1 * d)
    lo, hi = face_interval(p0, d, n1)
    lo, hi = jnp.maximum(lo, 0.0), jnp.minimum(hi, 1.0)
    has = lo <= hi
    lo, hi = jnp.clip(lo, 0.0, 1.0), jnp.clip(hi, 0.0, 1.0)
    t2 = jnp.where(jnp.abs(t1 - lo) >= jnp.abs(t1 - hi), lo, hi)
    second = has & (jnp.abs(t2 - t1) > 1e-3) & (jnp.sum(d * d) > 0)
    t = jnp.stack([t1, t2])
    pos, n, dist, _ = _points_vs_sdf(p0 + t[:, None] * d, local_sdf, on_a=True)
    r = size_a[0]
    pos = pos + 0.5 * r * n
    return cb + pos @ Rb.T, n @ Rb.T, dist - r, jnp.stack([jnp.ones((), bool), second])


def _capsule_box(pose_a, size_a, pose_b, size_b, margin):
    """Segment against the box's signed distance; the second point spans the face the capsule lies on."""
    return _capsule_vs_sdf(pose_a, size_a, pose_b, size_b, lambda p: _box_sdf(p, size_b),
                           lambda p0, d, n: _box_face_interval(p0, d, n, size_b))


def _capsule_cylinder(pose_a, size_a, pose_b, size_b, margin):
    """Segment against the cylinder's signed distance; the second point spans the cap disk or the
    axial band of the side that the capsule lies on."""
    return _capsule_vs_sdf(pose_a, size_a, pose_b, size_b, lambda p: _cylinder_sdf(p, size_b[0], size_b[1]),
                           lambda p0, d, n: _cylinder_face_interval(p0, d, n, size_b[0], size_b[1]))


# ---------------------------------------------------------------------------------------------
# box-box
# ---------------------------------------------------------------------------------------------


def _box_edges(pose, half):
    """Start points and direction vectors ``[12, 3]`` of the box's edges (fixed order)."""
    c, R = _frame(pose)
    mid = (jnp.asarray(_EDGE_MID, half.dtype) * half) @ R.T
    d = (jnp.asarray(_EDGE_DIR, half.dtype) * half) @ R.T
    return c + mid - d, 2.0 * d


def _face_manifold(c_ref, R_ref, e_ref, k, nf, c_inc, R_inc, e_inc, rtol):
    """Clip the incident box's face most opposed to ``nf`` against the reference face (axis ``k`` of
    the reference box, outward normal ``nf``) by candidate enumeration: incident corners inside the
    reference face, reference corners inside the incident face, and crossings of the incident edges
    with the reference face's sides (24 candidates). Near-duplicates (1e-6 of the face) are dropped.

    Returns the candidates' reference-face points ``[24, 3]``, their heights ``[24]`` above the
    reference face along ``nf`` (the incident face's height there) and whether they exist ``[24]``.
    """
    dtype = c_ref.dtype
    k1, k2 = (k + 1) % 3, (k + 2) % 3
    cf = c_ref + e_ref[k] * nf
    t1, t2 = R_ref[:, k1], R_ref[:, k2]
    ext = jnp.stack([e_ref[k1], e_ref[k2]])
    tol = rtol * jnp.max(e_ref)
    # incident face: outward normal n_inc most opposed to nf
    proj = nf @ R_inc
    j = jnp.argmax(jnp.abs(proj))
    n_inc = -_sign(proj[j]) * R_inc[:, j]
    j1, j2 = (j + 1) % 3, (j + 2) % 3
    fc = c_inc + e_inc[j] * n_inc
    quad3 = fc + jnp.asarray(_QUAD, dtype) @ jnp.stack([e_inc[j1] * R_inc[:, j1], e_inc[j2] * R_inc[:, j2]])
    rel = quad3 - cf
    quad = jnp.stack([rel @ t1, rel @ t2], axis=-1)  # [4, 2] in the reference face's coordinates
    h_quad = rel @ nf
    # (1) incident corners inside the reference face
    in1 = jnp.all(jnp.abs(quad) <= ext + tol, axis=-1)
    # (2) reference corners inside the incident face (projected along nf), height from its plane
    ref = jnp.asarray(_QUAD, dtype) * ext
    edge = jnp.roll(quad, -1, axis=0) - quad
    edge_len = jnp.linalg.norm(edge, axis=-1)
    orient = _sign(jnp.sum(quad[:, 0] * jnp.roll(quad[:, 1], -1) - quad[:, 1] * jnp.roll(quad[:, 0], -1)))
    rc = ref[:, None, :] - quad[None, :, :]
    side = orient * (edge[None, :, 0] * rc[..., 1] - edge[None, :, 1] * rc[..., 0])
    in2 = jnp.all(side >= -tol * edge_len[None, :], axis=-1)
    h_ref = ((fc - cf) @ n_inc - ref @ jnp.stack([t1 @ n_inc, t2 @ n_inc])) / (nf @ n_inc)
    # (3) incident edges crossing the lines x = +-ext_x, y = +-ext_y
    lines = np.array([(0, 1.0), (0, -1.0), (1, 1.0), (1, -1.0)])
    m, s = lines[:, 0].astype(int), jnp.asarray(lines[:, 1], dtype)
    o = 1 - m
    pm, em = quad[:, m], edge[:, m]  # [4 edges, 4 lines]
    ok = jnp.abs(em) > tol
    alpha = (s * ext[m] - pm) / jnp.where(ok, em, 1.0)
    other = quad[:, o] + alpha * edge[:, o]
    in3 = ok & (alpha >= 0) & (alpha <= 1) & (jnp.abs(other) <= ext[o] + tol)
    xy3 = jnp.where((m == 0)[None, :, None], jnp.stack([jnp.broadcast_to(s * ext[m], other.shape), other], -1),
                    jnp.stack([other, jnp.broadcast_to(s * ext[m], other.shape)], -1))
    h3 = h_quad[:, None] + alpha * (jnp.roll(h_quad, -1) - h_quad)[:, None]
    xy = jnp.concatenate([quad, ref, xy3.reshape(16, 2)])
    h = jnp.concatenate([h_quad, h_ref, h3.reshape(16)])
    exists = jnp.concatenate([in1, in2, in3.reshape(16)])
    # drop near-duplicates of an earlier existing candidate
    d2 = jnp.sum((xy[:, None, :] - xy[None, :, :]) ** 2, axis=-1)
    earlier = jnp.arange(24)[None, :] < jnp.arange(24)[:, None]
    dup = jnp.any(earlier & exists[None, :] & (d2 <= (10.0 * tol) ** 2), axis=1)
    return cf + xy[:, :1] * t1 + xy[:, 1:] * t2, h, exists & ~dup


def _box_box(pose_a, size_a, pose_b, size_b, margin):
    """Separating-axis test and face clipping (see module docstring).

    1. Separation of the boxes along the 15 axes (3 + 3 face normals, 9 edge cross products; near
       parallel edge pairs are skipped). The best face axis wins unless an edge axis beats it by 5 %
       of its separation plus 1e-5 of the boxes' size; face axes of a win ties over b's.
    2. Face axis: up to 8 points of the incident face clipped to the reference face, each with its
       height above the reference face. Edge axis (or no clipped point): one point midway between
       the closest points of the two supporting edges, with the axis' separation as distance.
    3. Separated boxes: the exact closest pair (corners against the other box, all 144 edge pairs)
       replaces the edge point, and is added to the face points (in an empty slot, else over the
       farthest) when it is closer than all of them.
    """
    dtype = pose_a.dtype
    rtol = _rtol(dtype)
    ca, Ra = _frame(pose_a)
    cb, Rb = _frame(pose_b)
    ea, eb = size_a, size_b
    scale = jnp.sum(ea) + jnp.sum(eb)
    t = cb - ca

    # 1. separating axes
    cross = jnp.cross(Ra.T[:, None, :], Rb.T[None, :, :]).reshape(9, 3)
    cross_u, cross_len = _normalize(cross, Ra[:, 0])
    axes = jnp.concatenate([Ra.T, Rb.T, cross_u])
    sep = jnp.abs(axes @ t) - jnp.abs(axes @ Ra) @ ea - jnp.abs(axes @ Rb) @ eb
    usable = jnp.concatenate([jnp.ones(6, bool), cross_len > 10.0 * rtol])
    separated = jnp.max(jnp.where(usable, sep, -jnp.inf)) > 0
    ia, ib = jnp.argmax(sep[:3]), jnp.argmax(sep[3:6])
    use_b = sep[3 + ib] > sep[ia] + rtol * scale
    face = jnp.where(use_b, 3 + ib, ia)
    s_face = sep[face]
    sep_edge = jnp.where(usable[6:], sep[6:], -jnp.inf)
    ie = jnp.argmax(sep_edge)
    s_edge = sep_edge[ie]
    use_edge = s_edge > s_face + _EDGE_BIAS_REL * jnp.abs(s_face) + _EDGE_BIAS_ABS * scale

    # 2a. face manifold
    ref_a = face < 3
    c_ref, R_ref, e_ref = jnp.where(ref_a, ca, cb), jnp.where(ref_a, Ra, Rb), jnp.where(ref_a, ea, eb)
    c_inc, R_inc, e_inc = jnp.where(ref_a, cb, ca), jnp.where(ref_a, Rb, Ra), jnp.where(ref_a, eb, ea)
    k = face % 3
    axis = R_ref[:, k]
    nf = _sign((c_inc - c_ref) @ axis) * axis
    pts, h, exists = _face_manifold(c_ref, R_ref, e_ref, k, nf, c_inc, R_inc, e_inc, rtol)
    keep = exists & (h <= margin)
    order = jnp.argsort((~keep).astype(jnp.int32), stable=True)[:8]  # kept points first, candidate order
    f_pos = pts[order] + 0.5 * h[order, None] * nf
    f_normal = jnp.broadcast_to(jnp.where(ref_a, nf, -nf), (8, 3))
    f_dist, f_exists = h[order], exists[order]

    # 2b. edge-edge point
    ia_e, ib_e = ie // 3, ie % 3
    n_e = _sign(axes[6 + ie] @ t) * axes[6 + ie]
    mid_a = ca + Ra @ (jnp.where(jnp.arange(3) == ia_e, 0.0, _sign(n_e @ Ra)) * ea)
    mid_b = cb + Rb @ (jnp.where(jnp.arange(3) == ib_e, 0.0, _sign(-n_e @ Rb)) * eb)
    da, db = Ra[:, ia_e] * ea[ia_e], Rb[:, ib_e] * eb[ib_e]
    s, u = _segment_closest(mid_a - da, 2.0 * da, mid_b - db, 2.0 * db)
    e_pos = 0.5 * (mid_a - da + s * 2.0 * da + mid_b - db + u * 2.0 * db)
    edge_ok = jnp.isfinite(s_edge)

    # 3. exact closest pair of separated boxes
    va, vb = _box_corners(pose_a, ea), _box_corners(pose_b, eb)
    _, _, qa = jax.vmap(_world_sdf(lambda p: _box_sdf(p, ea), pose_a))(vb)  # b's corners onto a
    _, _, qb = jax.vmap(_world_sdf(lambda p: _box_sdf(p, eb), pose_b))(va)  # a's corners onto b
    pa_e, da_e = _box_edges(pose_a, ea)
    pb_e, db_e = _box_edges(pose_b, eb)
    s_ee, u_ee = _segment_closest(pa_e[:, None], da_e[:, None], pb_e[None], db_e[None])
    on_a = jnp.concatenate([va, qa, (pa_e[:, None] + s_ee[..., None] * da_e[:, None]).reshape(144, 3)])
    on_b = jnp.concatenate([qb, vb, (pb_e[None] + u_ee[..., None] * db_e[None]).reshape(144, 3)])
    gap = jnp.linalg.norm(on_b - on_a, axis=-1)
    i = jnp.argmin(gap)
    x_n, x_d = _normalize(on_b[i] - on_a[i], jnp.where(use_edge, n_e, f_normal[0]))
    x_pos = 0.5 * (on_a[i] + on_b[i])

    # assemble
    point_case = (use_edge | ~jnp.any(f_exists & (f_dist <= margin))) & (edge_ok | separated)
    p_pos = jnp.where(separated, x_pos, e_pos)
    p_n = jnp.where(separated, x_n, n_e)
    p_d = jnp.where(separated, x_d, jnp.where(edge_ok, s_edge, 0.0))
    first = jnp.arange(8) == 0
    slot = jnp.arange(8) == jnp.argmax(jnp.where(f_exists, f_dist, jnp.inf))
    add = separated & (x_d < jnp.min(jnp.where(f_exists, f_dist, jnp.inf)) - rtol * scale)
    put = jnp.where(point_case, first, slot & add)
    pos = jnp.where(put[:, None], p_pos, f_pos)
    normal = jnp.where(put[:, None], p_n, f_normal)
    dist = jnp.where(put, p_d, f_dist)
    exists = jnp.where(point_case, first, f_exists | put)
    return pos, normal, dist, exists


# ---------------------------------------------------------------------------------------------
# cylinder pairs (approximations)
# ---------------------------------------------------------------------------------------------


def _project(sdf, y):
    """Nearest point of a solid to ``y`` (``y`` itself when inside)."""
    d, _, q = sdf(y)
    return jnp.where(d > 0, q, y)


def _alternating_projections(own_sdf, other_sdf, start):
    """A point of the own solid nearest to the other solid, by alternating projections between them
    (von Neumann; ``PROJECTION_ROUNDS`` rounds from the own point nearest ``start``). For separated solids it
    converges to a closest pair; for overlapping ones to a common point."""
    x = _project(own_sdf, start)
    return jax.lax.fori_loop(0, PROJECTION_ROUNDS, lambda _, x: _project(own_sdf, _project(other_sdf, x)), x)


def _first_min(dist, tol):
    """Index of the first entry within ``tol`` of the minimum."""
    return jnp.argmax(dist <= jnp.min(dist) + tol)


def _reach(f, start, end, level):
    """The point farthest along ``start -> end`` at which ``f`` (convex on the segment, with
    ``f(start) <= level``) is still ``<= level``: ``end`` itself if possible, else by bisection."""

    def step(_, s):
        lo, hi = s
        mid = 0.5 * (lo + hi)
        ok = f(start + mid * (end - start)) <= level
        return jnp.where(ok, mid, lo), jnp.where(ok, hi, mid)

    lo, _ = jax.lax.fori_loop(0, BISECTION_STEPS, step, (jnp.zeros_like(level), jnp.ones_like(level)))
    return jnp.where(f(end) <= level, end, start + lo * (end - start))


def _cylinder_family(pose, size, own_sdf, other_sdf, other_centre, on_a: bool, margin, tol):
    """Four points of a cylinder tested against the other geom's exact signed distance.

    Support direction: minus the other geom's outward normal at its point nearest to the cylinder
    centre. The cap facing the other geom has an
    anchor point: the point of its disk nearest to the other geom's point nearest to the centre.
    Points: the three rim points of that cap (as PLANE-CYLINDER), each pulled towards the anchor
    until its distance is within ``max(anchor distance, margin)`` (so a cap resting on a smaller
    face keeps a support triangle on it), and the first (within ``tol``) nearest of: the minimum of
    the signed distance along the support generator line (rim point of that cap to the rim point of
    the other cap, the largest parameter on ties; skipped when it is the first rim point), the point
    found by alternating projections from the other geom's centre, and the anchor.
    """
    c, R = _frame(pose)
    radius, hh = size[0], size[1]

    def dist(x):
        return other_sdf(x)[0]

    _, u, q = other_sdf(c)
    rim, cap = _cylinder_support(pose, size, -u)
    off = q - cap
    off = off - (off @ R[:, 2]) * R[:, 2]
    off_u, off_len = _normalize(off, R[:, 0])
    anchor = cap + jnp.minimum(off_len, radius) * off_u
    level = jnp.maximum(dist(anchor), margin)
    tri = jax.vmap(lambda x: _reach(dist, anchor, x, level))(rim[jnp.array([0, 2, 3])])
    gen = rim[1] - rim[0]
    tg = _golden_min(lambda t: dist(rim[0] + t * gen), _tie_tol(c.dtype) * (radius + hh))
    extra = jnp.stack([rim[0] + tg * gen, _alternating_projections(own_sdf, other_sdf, other_centre), anchor])
    d_extra = jax.vmap(dist)(extra)
    d_extra = d_extra.at[0].set(jnp.where((tg > 1e-3) & (hh > 0), d_extra[0], jnp.inf))
    fourth = extra[_first_min(d_extra, tol)]
    pts = jnp.concatenate([tri, fourth[None]])
    # a rim point pulled onto the anchor (or onto another point) would only duplicate it
    near = jnp.sum((pts[:, None] - pts[None]) ** 2, axis=-1) <= (1e-3 * radius) ** 2
    dup = jnp.any(near & (jnp.arange(4)[None, :] < jnp.arange(4)[:, None]), axis=1)  # [i, j]: j earlier
    pos, normal, d, _ = _points_vs_sdf(pts, other_sdf, on_a)
    return pos, normal, d, ~dup


def _pick_family(f1, f2, margin, tol):
    """The family with the smaller minimum distance; within ``tol`` of a tie, the one with more points
    within the margin (``f1`` on a full tie)."""
    (_, _, d1, e1), (_, _, d2, e2) = f1, f2
    m1, m2 = jnp.min(jnp.where(e1, d1, jnp.inf)), jnp.min(jnp.where(e2, d2, jnp.inf))
    n1, n2 = jnp.sum(e1 & (d1 <= margin)), jnp.sum(e2 & (d2 <= margin))
    second = (m2 < m1 - tol) | ((m2 <= m1 + tol) & (n2 > n1))
    return tuple(jnp.where(second, y, x) for x, y in zip(f1, f2, strict=True))


def _box_cylinder(pose_a, size_a, pose_b, size_b, margin):
    """Approximation (K = 4): the cylinder's family of surface points against the box's signed distance,
    or the 4 box corners with the smallest signed distance to the cylinder (stable order)."""
    box_sdf = _world_sdf(lambda p: _box_sdf(p, size_a), pose_a)
    cyl_sdf = _world_sdf(lambda p: _cylinder_sdf(p, size_b[0], size_b[1]), pose_b)
    tol = _rtol(pose_a.dtype) * (jnp.sum(size_a) + jnp.sum(size_b))
    f1 = _cylinder_family(pose_b, size_b, cyl_sdf, box_sdf, pose_a[:3], on_a=False, margin=margin, tol=tol)
    corners = _box_corners(pose_a, size_a)
    d = jax.vmap(cyl_sdf)(corners)[0]
    f2 = _points_vs_sdf(corners[jnp.argsort(d, stable=True)[:4]], cyl_sdf, on_a=True)
    return _pick_family(f1, f2, margin, tol)


def _cylinder_cylinder(pose_a, size_a, pose_b, size_b, margin):
    """Approximation (K = 4): each cylinder's family of surface points against the other's signed
    distance; the better family is kept. (Both families come from one vmapped call: one compilation.)"""
    tol = _rtol(pose_a.dtype) * (jnp.sum(size_a[:2]) + jnp.sum(size_b[:2]))

    def family(pose, size, other_pose, other_size):  # points on the first cylinder, normals as if it were b
        own = _world_sdf(lambda p: _cylinder_sdf(p, size[0], size[1]), pose)
        other = _world_sdf(lambda p: _cylinder_sdf(p, other_size[0], other_size[1]), other_pose)
        return _cylinder_family(pose, size, own, other, other_pose[:3], on_a=False, margin=margin, tol=tol)

    pos, normal, dist, exists = jax.vmap(family)(jnp.stack([pose_a, pose_b]), jnp.stack([size_a, size_b]),
                                                 jnp.stack([pose_b, pose_a]), jnp.stack([size_b, size_a]))
    f1 = (pos[0], -normal[0], dist[0], exists[0])  # a's points: flip to point from a to b
    f2 = (pos[1], normal[1], dist[1], exists[1])
    return _pick_family(f1, f2, margin, tol)


# ---------------------------------------------------------------------------------------------
# heightfield pairs (approximations: candidate points against the grid triangle below each)
# ---------------------------------------------------------------------------------------------


class HField(NamedTuple):
    """One heightfield grid, as :func:`collide` reads it (``kamino.Model.hfield_*``; arrays may be traced)."""

    data: jax.Array  # [N] normalised heights in [0, 1] (a world's hfield_data; the grid starts at adr)
    adr: jax.Array  # [] index of the grid's first height in data
    nrow: jax.Array  # [] rows (local y), >= 2
    ncol: jax.Array  # [] columns (local x), >= 2
    size: jax.Array  # [4] (rx, ry, z_top, z_base) [m]


def _hfield_surface(hf: HField, x, y):
    """Height ``z``, upward unit normal ``n`` of the grid triangle below the local point ``(x, y)``, and
    whether ``(x, y)`` lies on the grid. Cell ``(r, c)`` spans columns ``c, c + 1`` and rows ``r, r + 1``;
    with ``u, v`` in ``[0, 1]`` across it, ``u >= v`` is the triangle ``(r, c), (r, c + 1), (r + 1, c + 1)`` and
    ``u < v`` the triangle ``(r, c), (r + 1, c), (r + 1, c + 1)`` (MuJoCo's split). Off the grid the nearest
    cell is read (finite values) and the flag is False."""
    dtype = x.dtype
    rx, ry, zt = hf.size[0], hf.size[1], hf.size[2]
    ncol, nrow = hf.ncol.astype(jnp.int32), hf.nrow.astype(jnp.int32)
    dx = 2.0 * rx / (ncol - 1).astype(dtype)
    dy = 2.0 * ry / (nrow - 1).astype(dtype)
    fx, fy = (x + rx) / dx, (y + ry) / dy
    c = jnp.clip(jnp.floor(fx), 0, ncol - 2).astype(jnp.int32)
    r = jnp.clip(jnp.floor(fy), 0, nrow - 2).astype(jnp.int32)
    u = jnp.clip(fx - c.astype(dtype), 0.0, 1.0)
    v = jnp.clip(fy - r.astype(dtype), 0.0, 1.0)
    k = hf.adr.astype(jnp.int32) + r * ncol + c
    h00, h10 = hf.data[k] * zt, hf.data[k + 1] * zt
    h01, h11 = hf.data[k + ncol] * zt, hf.data[k + ncol + 1] * zt
    lower = u >= v
    ex = jnp.where(lower, h10 - h00, h11 - h01)  # height change across the cell along x
    ey = jnp.where(lower, h11 - h10, h01 - h00)  # ... along y
    z = h00 + u * ex + v * ey
    n, _ = _normalize(jnp.stack([-ex / dx, -ey / dy, jnp.ones_like(x)]), jnp.array([0.0, 0.0, 1.0], dtype))
    inside = (jnp.abs(x) <= rx) & (jnp.abs(y) <= ry)
    return z.astype(dtype), n.astype(dtype), inside


def _hfield_vs_points(pose_h, hf: HField, pts, radius):
    """Spheres of ``radius`` centred at world points ``pts [N, 3]`` against the grid triangle below each
    (module docstring, "Heightfields"); the heightfield is geom b, so the normal is minus the terrain's."""
    c, R = _frame(pose_h)
    x = (pts - c) @ R
    z, n, inside = jax.vmap(lambda p: _hfield_surface(hf, p[0], p[1]))(x)
    dist = (x[:, 2] - z) * n[:, 2] - radius
    pos = x - n * (radius + 0.5 * dist)[:, None]
    return c + pos @ R.T, -(n @ R.T), dist, inside


def _sphere_hfield(pose_a, size_a, pose_b, hf, margin):
    """The sphere's centre against the triangle below it."""
    return _hfield_vs_points(pose_b, hf, pose_a[None, :3], size_a[0])


def _capsule_hfield(pose_a, size_a, pose_b, hf, margin):
    """The capsule's two end spheres (segment end at local -z first)."""
    c, R = _frame(pose_a)
    ends = c + jnp.array([-1.0, 1.0], c.dtype)[:, None] * (size_a[1] * R[:, 2])
    return _hfield_vs_points(pose_b, hf, ends, size_a[0])


def _box_hfield(pose_a, size_a, pose_b, hf, margin):
    """The 4 corners nearest the terrain (corners off the grid last; stable sort: ties keep the corner order)."""
    pos, normal, dist, inside = _hfield_vs_points(pose_b, hf, _box_corners(pose_a, size_a),
                                                  jnp.zeros((), size_a.dtype))
    order = jnp.argsort(jnp.where(inside, dist, jnp.inf), stable=True)[:4]
    return pos[order], normal[order], dist[order], inside[order]


def _cylinder_hfield(pose_a, size_a, pose_b, hf, margin):
    """PLANE-CYLINDER's four rim points for the terrain normal below the cylinder's centre (the heightfield's
    +z when the centre is off the grid), each against the triangle below it."""
    c, R = _frame(pose_b)
    x = (pose_a[:3] - c) @ R
    _, n, inside = _hfield_surface(hf, x[0], x[1])
    n = jnp.where(inside, n, jnp.array([0.0, 0.0, 1.0], n.dtype))
    pts, _ = _cylinder_support(pose_a, size_a, -(R @ n))
    return _hfield_vs_points(pose_b, hf, pts, jnp.zeros((), size_a.dtype))


_HFIELD_PAIRS = {
    GeomType.SPHERE: _sphere_hfield,
    GeomType.CAPSULE: _capsule_hfield,
    GeomType.BOX: _box_hfield,
    GeomType.CYLINDER: _cylinder_hfield,
}


# ---------------------------------------------------------------------------------------------
# dispatch
# ---------------------------------------------------------------------------------------------

_G = GeomType
_PAIRS = {
    (_G.PLANE, _G.SPHERE): _plane_sphere,
    (_G.PLANE, _G.CAPSULE): _plane_capsule,
    (_G.PLANE, _G.BOX): _plane_box,
    (_G.PLANE, _G.CYLINDER): _plane_cylinder,
    (_G.PLANE, _G.ELLIPSOID): _plane_ellipsoid,
    (_G.SPHERE, _G.SPHERE): _sphere_sphere,
    (_G.SPHERE, _G.CAPSULE): _sphere_capsule,
    (_G.SPHERE, _G.BOX): _sphere_box,
    (_G.SPHERE, _G.CYLINDER): _sphere_cylinder,
    (_G.CAPSULE, _G.CAPSULE): _capsule_capsule,
    (_G.CAPSULE, _G.BOX): _capsule_box,
    (_G.CAPSULE, _G.CYLINDER): _capsule_cylinder,
    (_G.BOX, _G.BOX): _box_box,
    (_G.BOX, _G.CYLINDER): _box_cylinder,
    (_G.CYLINDER, _G.CYLINDER): _cylinder_cylinder,
    **{(t, _G.HFIELD): fn for t, fn in _HFIELD_PAIRS.items()},
}

#: candidate points per pair: the model's table (``kamino.model.CONTACT_POINTS``), which sizes the contact capacity
MAX_POINTS = CONTACT_POINTS


def _pair(type_a, type_b) -> tuple[GeomType, GeomType]:
    try:
        pair = (GeomType(int(type_a)), GeomType(int(type_b)))
    except (TypeError, ValueError) as err:
        raise ValueError(f"collide: unknown geom type in pair ({type_a!r}, {type_b!r})") from err
    if pair not in _PAIRS:
        names = f"({pair[0].name}, {pair[1].name})"
        if (pair[1], pair[0]) in _PAIRS:
            raise ValueError(f"collide: unordered geom pair {names}; pass the types with type_a <= type_b")
        raise ValueError(f"collide: unsupported geom pair {names}")
    return pair


def collide(type_a, type_b, pose_a, size_a, pose_b, size_b, margin, hfield: HField | None = None) -> ContactPoints:
    """Contact points between geom a and geom b (one pair; see the module docstring).

    ``type_a <= type_b`` are static geom types, ``pose_*`` ``[7]`` world poses (quaternion x, y, z, w),
    ``size_*`` ``[3]``, ``margin`` a scalar >= 0 (may be traced). An HFIELD geom b also needs its grid,
    ``hfield`` (:class:`HField`). Returns ``K = MAX_POINTS[(type_a, type_b)]`` points; raises ``ValueError``
    for an unsupported or unordered pair, or an HFIELD pair without ``hfield``.
    """
    pair = _pair(type_a, type_b)
    fn = _PAIRS[pair]
    dtype = jnp.result_type(pose_a, size_a, pose_b, size_b)
    if not jnp.issubdtype(dtype, jnp.floating):
        dtype = jnp.result_type(float)
    pose_a, size_a, pose_b, size_b = (jnp.asarray(x, dtype) for x in (pose_a, size_a, pose_b, size_b))
    margin = jnp.asarray(margin, dtype)
    if pair[1] == GeomType.HFIELD:
        if hfield is None:
            raise ValueError(f"collide: a ({pair[0].name}, HFIELD) pair needs the heightfield's grid (hfield=)")
        hf = HField(jnp.asarray(hfield.data, dtype), jnp.asarray(hfield.adr), jnp.asarray(hfield.nrow),
                    jnp.asarray(hfield.ncol), jnp.asarray(hfield.size, dtype))
        pos, normal, dist, exists = fn(pose_a, size_a, pose_b, hf, margin)
    else:
        pos, normal, dist, exists = fn(pose_a, size_a, pose_b, size_b, margin)
    return ContactPoints(pos=pos, normal=normal, dist=dist, valid=exists & (dist <= margin))
