"""Narrow-phase collision (``kamino.jax_ref.collision``): analytic placements, rigid-motion invariance,
agreement with MuJoCo's ``mj_geomDistance``, degenerate inputs, batching and float32.

Tests run in float64 (``conftest.py``); unless stated, "exact" tolerances of 1e-9 m allow for rounding
in the quaternion-to-matrix and frame changes (about 1e-15 m per operation on metre-sized geoms).
"""

from __future__ import annotations

import functools
import itertools

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest

from kamino.jax_ref.collision import MAX_POINTS, collide
from kamino.model import GeomType as G
from kamino.spatial import quat_mul, quat_to_matrix

IDENT = (0.0, 0.0, 0.0, 1.0)
S2 = np.sqrt(2.0)
EXACT = 1e-9  # see module docstring
ALL_PAIRS = sorted(k for k in MAX_POINTS if G.HFIELD not in k)  # heightfield pairs: tests/test_hfield.py


def quat(axis, angle) -> np.ndarray:
    """Unit quaternion (x, y, z, w) of a rotation by ``angle`` about ``axis``."""
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    return np.r_[np.sin(angle / 2) * axis, np.cos(angle / 2)]


def rot(q) -> np.ndarray:
    return np.asarray(quat_to_matrix(jnp.asarray(q, float)))


def pose(p, q=IDENT) -> np.ndarray:
    return np.r_[np.asarray(p, float), np.asarray(q, float)]


BATCH = 160  # every call is padded to one batch size: one compilation per pair type and dtype


@functools.cache
def _batched(ta, tb):
    return jax.jit(jax.vmap(functools.partial(collide, ta, tb)))


def run_batch(ta, tb, pa, sa, pb, sb, margin, dtype=jnp.float64) -> dict[str, np.ndarray]:
    """``collide`` vmapped over pairs (``margin`` per pair, traced)."""
    pa, pb = np.asarray(pa, float), np.asarray(pb, float)
    n = len(pa)
    assert n <= BATCH

    def pad(x):
        return np.concatenate([x, np.broadcast_to(x[:1], (BATCH - n, *x.shape[1:]))])

    args = [pa, np.broadcast_to(np.asarray(sa, float), (n, 3)), pb, np.broadcast_to(np.asarray(sb, float), (n, 3)),
            np.broadcast_to(np.asarray(margin, float), (n,))]
    cp = _batched(ta, tb)(*(jnp.asarray(pad(x), dtype) for x in args))
    return {k: np.asarray(v)[:n] for k, v in vars(cp).items()}


def run(ta, tb, pa, sa, pb, sb, margin=0.0) -> dict[str, np.ndarray]:
    """One pair (through the batched function)."""
    return {k: v[0] for k, v in run_batch(ta, tb, [pa], sa, [pb], sb, margin).items()}


def valid_points(cp) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    v = cp["valid"]
    return cp["pos"][v], cp["normal"][v], cp["dist"][v]


def assert_same_points(got, want, atol=EXACT):
    """The rows of ``got`` are a permutation of the rows of ``want``."""
    got, want = np.asarray(got), np.asarray(want)
    assert got.shape == want.shape, (got, want)
    for w in want:
        assert np.min(np.linalg.norm(got - w, axis=1)) < atol, (got, w)


# ---------------------------------------------------------------------------------------------
# API
# ---------------------------------------------------------------------------------------------


def test_pair_validation_and_shapes():
    z = jnp.zeros(3)
    p = jnp.asarray(pose((0, 0, 0)))
    with pytest.raises(ValueError, match=r"unsupported geom pair \(PLANE, PLANE\)"):
        collide(G.PLANE, G.PLANE, p, z, p, z, 0.0)
    with pytest.raises(ValueError, match=r"unordered geom pair \(BOX, SPHERE\)"):
        collide(G.BOX, G.SPHERE, p, z, p, z, 0.0)
    assert len(MAX_POINTS) == 19 and all(a <= b for a, b in MAX_POINTS)
    with pytest.raises(ValueError, match=r"a \(SPHERE, HFIELD\) pair needs the heightfield's grid \(hfield=\)"):
        collide(G.SPHERE, G.HFIELD, p, z, p, z, 0.0)
    assert max(MAX_POINTS.values()) == 8 and MAX_POINTS[(G.BOX, G.BOX)] == 8
    for ta, tb in ALL_PAIRS:
        size = jnp.array([0.3, 0.2, 0.1])
        # abstract evaluation (shapes and dtypes only); plain ints work as types too
        cp = jax.eval_shape(lambda pa, sa, pb, sb, ta=int(ta), tb=int(tb): collide(ta, tb, pa, sa, pb, sb, 0.1),
                            p, size, p, size)
        k = MAX_POINTS[(ta, tb)]
        assert cp.pos.shape == (k, 3) and cp.normal.shape == (k, 3) and cp.dist.shape == (k,)
        assert cp.valid.shape == (k,) and cp.valid.dtype == jnp.bool_


# ---------------------------------------------------------------------------------------------
# analytic placements
# ---------------------------------------------------------------------------------------------


def test_plane_sphere():
    q = quat([1, 2, 3], 0.4)
    R, p0 = rot(q), np.array([0.1, -0.2, 0.3])
    n, t = R[:, 2], R[:, 0]
    for height, dist in [(0.7, 0.2), (0.3, -0.2)]:
        c = p0 + height * n + 0.3 * t
        cp = run(G.PLANE, G.SPHERE, pose(p0, q), [0, 0, 0], pose(c), [0.5, 0, 0], margin=0.25)
        assert cp["valid"][0]
        np.testing.assert_allclose(cp["dist"][0], dist, atol=EXACT)
        np.testing.assert_allclose(cp["normal"][0], n, atol=EXACT)
        # midpoint of the plane point c - height n and the sphere's lowest point c - 0.5 n
        np.testing.assert_allclose(cp["pos"][0], c - n * (height + 0.5) / 2, atol=EXACT)


def test_plane_ellipsoid_support_point():
    """Gap of an ellipsoid above a tilted plane = centre height - sqrt(n^T R S^2 R^T n) (its support
    function), the witness point the support point; exact in both separated and penetrating poses."""
    qp = quat([1, -2, 0.5], 0.3)
    n = rot(qp)[:, 2]
    semi = np.array([0.3, 0.2, 0.1])
    for axis, angle, height in [([0.2, 1, 0.4], 0.9, 0.5), ([1, 0, 0], 1.2, 0.05)]:
        q = quat(axis, angle)
        R = rot(q)
        support = np.sqrt(n @ R @ np.diag(semi**2) @ R.T @ n)
        c = np.array([0.1, 0.2, -0.1]) + height * n
        cp = run(G.PLANE, G.ELLIPSOID, pose((0.1, 0.2, -0.1), qp), [0] * 3, pose(c, q), semi, margin=1.0)
        np.testing.assert_allclose(cp["dist"][0], height - support, atol=EXACT)
        np.testing.assert_allclose(cp["normal"][0], n, atol=EXACT)
        lowest = c - R @ (semi**2 * (R.T @ n)) / support  # support point along -n
        np.testing.assert_allclose(cp["pos"][0], lowest - n * (height - support) / 2, atol=EXACT)


def test_plane_capsule_lying_and_standing():
    plane, size = pose((0, 0, 0)), [0.1, 0.5, 0]
    cp = run(G.PLANE, G.CAPSULE, plane, [0] * 3, pose((0, 0, 0.1), quat([1, 0, 0], np.pi / 2)), size, 0.01)
    pos, nrm, dist = valid_points(cp)
    assert_same_points(pos, [[0, 0.5, 0], [0, -0.5, 0]])
    np.testing.assert_allclose(dist, 0.0, atol=EXACT)
    np.testing.assert_allclose(nrm, [[0, 0, 1]] * 2, atol=EXACT)
    cp = run(G.PLANE, G.CAPSULE, plane, [0] * 3, pose((0.2, 0, 0.55)), size, 0.01)
    np.testing.assert_allclose(np.sort(cp["dist"]), [-0.05, 0.95], atol=EXACT)
    assert cp["valid"].sum() == 1
    np.testing.assert_allclose(valid_points(cp)[0], [[0.2, 0, -0.025]], atol=EXACT)


def test_plane_box_flat_gives_the_four_bottom_corners():
    half, q = np.array([0.5, 0.3, 0.2]), quat([0, 0, 1], 0.3)
    cp = run(G.PLANE, G.BOX, pose((0, 0, 0)), [0] * 3, pose((1, 2, 0.2), q), half, 0.0)
    assert cp["valid"].all()
    np.testing.assert_allclose(cp["dist"], 0.0, atol=EXACT)
    np.testing.assert_allclose(cp["normal"], [[0, 0, 1]] * 4, atol=EXACT)
    corners = np.array([1, 2, 0.2]) + (np.array(list(itertools.product([-1, 1], repeat=3))) * half) @ rot(q).T
    assert_same_points(cp["pos"], corners[corners[:, 2] < 0.1])


def test_plane_box_on_edge_and_tilted():
    # resting on an edge: the 2 corners of the edge touch; the next 2 deepest are 0.5*sqrt(2) up
    cp = run(G.PLANE, G.BOX, pose((0, 0, 0)), [0] * 3, pose((0, 0, 0.5 * S2), quat([1, 0, 0], np.pi / 4)),
             [0.5] * 3, 0.01)
    np.testing.assert_allclose(np.sort(cp["dist"]), [0, 0, 0.5 * S2, 0.5 * S2], atol=EXACT)
    assert_same_points(valid_points(cp)[0], [[0.5, 0, 0], [-0.5, 0, 0]])
    # generic tilt on a tilted plane: the deepest corner is at h - sum_i e_i |R_i . n|
    qp, qb, half = quat([1, -1, 0.5], 0.3), quat([0.3, 1, 2], 1.1), np.array([0.4, 0.3, 0.2])
    n = rot(qp)[:, 2]
    c = np.array([0.2, 0.1, 0.0]) + 0.3 * n
    cp = run(G.PLANE, G.BOX, pose((0.2, 0.1, 0), qp), [0] * 3, pose(c, qb), half, 0.0)
    np.testing.assert_allclose(cp["dist"].min(), 0.3 - np.abs(rot(qb).T @ n) @ half, atol=EXACT)


def test_plane_cylinder_standing_lying_tilted():
    plane, size = pose((0, 0, 0)), [0.3, 0.4, 0]
    cp = run(G.PLANE, G.CYLINDER, plane, [0] * 3, pose((0.1, 0, 0.4)), size, 0.01)
    pos, _, dist = valid_points(cp)
    assert len(dist) >= 3, "a standing cylinder needs a support polygon"
    np.testing.assert_allclose(dist, 0.0, atol=EXACT)
    np.testing.assert_allclose(np.linalg.norm(pos[:, :2] - [0.1, 0], axis=1), 0.3, atol=EXACT)  # on the rim
    e1, e2 = pos[1] - pos[0], pos[2] - pos[0]
    assert abs(e1[0] * e2[1] - e1[1] * e2[0]) / 2 > 0.1  # a real triangle (equilateral on the rim: 0.117)
    cp = run(G.PLANE, G.CYLINDER, plane, [0] * 3, pose((0, 0, 0.3), quat([1, 0, 0], np.pi / 2)), size, 0.01)
    assert_same_points(valid_points(cp)[0], [[0, 0.4, 0], [0, -0.4, 0]])
    theta, h = 0.3, 1.0
    cp = run(G.PLANE, G.CYLINDER, plane, [0] * 3, pose((0, 0, h), quat([1, 0, 0], theta)), size, 0.0)
    np.testing.assert_allclose(cp["dist"].min(), h - 0.4 * np.cos(theta) - 0.3 * np.sin(theta), atol=EXACT)


def test_sphere_sphere_overlap_and_concentric():
    ca, u = np.array([0.1, 0.2, 0.3]), np.array([1.0, 2.0, 2.0]) / 3
    cp = run(G.SPHERE, G.SPHERE, pose(ca), [0.5, 0, 0], pose(ca + 0.8 * u), [0.4, 0, 0])
    np.testing.assert_allclose(cp["dist"], [-0.1], atol=EXACT)
    np.testing.assert_allclose(cp["normal"], [u], atol=EXACT)
    np.testing.assert_allclose(cp["pos"], [ca + u * 0.45], atol=EXACT)  # midway between 0.4 u and 0.5 u
    q = quat([1, 1, 0], 0.7)
    cp = run(G.SPHERE, G.SPHERE, pose(ca, q), [0.5, 0, 0], pose(ca), [0.4, 0, 0])
    np.testing.assert_allclose(cp["dist"], [-0.9], atol=EXACT)
    np.testing.assert_allclose(cp["normal"], [rot(q)[:, 2]], atol=EXACT)  # documented fallback: a's local z


def test_sphere_capsule_side_and_end():
    cap = pose((0, 0, 0))
    cp = run(G.SPHERE, G.CAPSULE, pose((0.6, 0, 0.25)), [0.3, 0, 0], cap, [0.2, 0.5, 0], 0.2)
    np.testing.assert_allclose(cp["dist"], [0.1], atol=EXACT)
    np.testing.assert_allclose(cp["normal"], [[-1, 0, 0]], atol=EXACT)
    np.testing.assert_allclose(cp["pos"], [[0.25, 0, 0.25]], atol=EXACT)
    cp = run(G.SPHERE, G.CAPSULE, pose((0, 0, 1.0)), [0.3, 0, 0], cap, [0.2, 0.5, 0], 0.0)
    np.testing.assert_allclose(cp["dist"], [0.0], atol=EXACT)
    np.testing.assert_allclose(cp["normal"], [[0, 0, -1]], atol=EXACT)
    assert cp["valid"][0]


def test_capsule_capsule_crossed_and_parallel():
    along_x, along_y = quat([0, 1, 0], np.pi / 2), quat([1, 0, 0], np.pi / 2)
    size = [0.2, 0.5, 0]
    cp = run(G.CAPSULE, G.CAPSULE, pose((0, 0, 0), along_x), size, pose((0, 0, 0.5), along_y), size, 0.2)
    pos, nrm, dist = valid_points(cp)
    np.testing.assert_allclose(dist, [0.1], atol=EXACT)
    np.testing.assert_allclose(nrm, [[0, 0, 1]], atol=EXACT)
    np.testing.assert_allclose(pos, [[0, 0, 0.25]], atol=EXACT)
    # a capsule lying on a parallel one: two points spanning the overlap x in [-0.2, 0.5]
    cp = run(G.CAPSULE, G.CAPSULE, pose((0, 0, 0), along_x), size, pose((0.3, 0, 0.4), along_x), size, 0.0)
    pos, nrm, dist = valid_points(cp)
    assert_same_points(pos, [[-0.2, 0, 0.2], [0.5, 0, 0.2]])
    np.testing.assert_allclose(dist, 0.0, atol=EXACT)
    np.testing.assert_allclose(nrm, [[0, 0, 1]] * 2, atol=EXACT)


def test_sphere_box_outside_corner_inside():
    q, c, half = quat([1, 2, 0.5], 0.8), np.array([0.3, -0.1, 0.2]), np.array([0.5, 0.4, 0.3])
    R = rot(q)
    box = pose(c, q)

    def sphere_at(local, r, margin=1.0):
        return run(G.SPHERE, G.BOX, pose(c + R @ local), [r, 0, 0], box, half, margin)

    cp = sphere_at([1.2, 0.1, -0.1], 0.5)  # over the +x face
    np.testing.assert_allclose(cp["dist"], [0.2], atol=EXACT)
    np.testing.assert_allclose(cp["normal"], [-R[:, 0]], atol=EXACT)
    np.testing.assert_allclose(cp["pos"], [c + R @ [0.6, 0.1, -0.1]], atol=EXACT)
    cp = sphere_at([0.8, 0.8, 0.3], 0.2)  # off the corner region (0.5, 0.4, 0.3) by (0.3, 0.4, 0)
    np.testing.assert_allclose(cp["dist"], [0.3], atol=EXACT)
    np.testing.assert_allclose(cp["normal"], [-R @ [0.6, 0.8, 0]], atol=EXACT)
    cp = sphere_at([0.35, 0.0, 0.1], 0.2)  # centre inside: nearest face is +x at depth 0.15
    np.testing.assert_allclose(cp["dist"], [-0.35], atol=EXACT)
    np.testing.assert_allclose(cp["normal"], [-R[:, 0]], atol=EXACT)  # pushes the box towards -x


def test_capsule_box_lying_overhanging_standing():
    box, half, size = pose((0, 0, 0)), [1.0, 1.0, 1.0], [0.2, 0.5, 0]
    along_x, along_y = quat([0, 1, 0], np.pi / 2), quat([1, 0, 0], np.pi / 2)
    cp = run(G.CAPSULE, G.BOX, pose((0, 0, 1.2), along_y), size, box, half, 0.0)
    pos, nrm, dist = valid_points(cp)
    assert_same_points(pos, [[0, 0.5, 1], [0, -0.5, 1]])
    np.testing.assert_allclose(dist, 0.0, atol=EXACT)
    np.testing.assert_allclose(nrm, [[0, 0, -1]] * 2, atol=EXACT)  # from the capsule down into the box
    # overhanging the +x edge: supported from x = 0.7 to the edge at x = 1
    cp = run(G.CAPSULE, G.BOX, pose((1.2, 0, 1.2), along_x), size, box, half, 0.0)
    assert_same_points(valid_points(cp)[0], [[0.7, 0, 1], [1.0, 0, 1]])
    cp = run(G.CAPSULE, G.BOX, pose((0.2, 0.1, 1.75)), size, box, half, 0.1)
    np.testing.assert_allclose(np.sort(cp["dist"]), [0.05, 1.05], atol=EXACT)
    np.testing.assert_allclose(valid_points(cp)[0], [[0.2, 0.1, 1.025]], atol=EXACT)


def test_box_box_small_box_on_big_box_gives_its_bottom_corners():
    q = quat([0, 0, 1], 0.3)
    small, big = pose((0.2, 0.1, 1.5), q), pose((0, 0, 0))
    corners = np.array([0.2, 0.1, 1.5]) + (np.array(list(itertools.product([-1, 1], repeat=3))) * 0.5) @ rot(q).T
    bottom = corners[corners[:, 2] < 1.2]
    for pa, sa, pb, sb, nz in [(big, [1] * 3, small, [0.5] * 3, 1.0), (small, [0.5] * 3, big, [1] * 3, -1.0)]:
        pos, nrm, dist = valid_points(run(G.BOX, G.BOX, pa, sa, pb, sb, 0.0))
        assert_same_points(pos, bottom)
        np.testing.assert_allclose(dist, 0.0, atol=EXACT)
        np.testing.assert_allclose(nrm, [[0, 0, nz]] * 4, atol=EXACT)


def test_box_box_equal_stack_edge_and_separated():
    b = [0.5] * 3
    pos, _, dist = valid_points(run(G.BOX, G.BOX, pose((0, 0, 0)), b, pose((0, 0, 0.99)), b, 0.0))
    assert_same_points(pos, [[x, y, 0.495] for x in (-0.5, 0.5) for y in (-0.5, 0.5)])
    np.testing.assert_allclose(dist, -0.01, atol=EXACT)
    # tilted by 45 deg onto one edge: the 2 ends of that edge
    cp = run(G.BOX, G.BOX, pose((0, 0, 0)), [1] * 3, pose((0, 0, 1 + 0.5 * S2), quat([1, 0, 0], np.pi / 4)), b, 0.01)
    pos, _, dist = valid_points(cp)
    assert_same_points(pos, [[0.5, 0, 1], [-0.5, 0, 1]])
    np.testing.assert_allclose(dist, 0.0, atol=EXACT)
    # separated by 5 mm: speculative face points within a 1 cm margin, none within 4 mm
    sep = (pose((0, 0, 0)), [1] * 3, pose((0.1, 0, 1.505), quat([0, 0, 1], 0.2)), b)
    pos, _, dist = valid_points(run(G.BOX, G.BOX, *sep, 0.01))
    assert len(dist) == 4
    np.testing.assert_allclose(dist, 0.005, atol=EXACT)
    np.testing.assert_allclose(pos[:, 2], 1.0025, atol=EXACT)
    assert not run(G.BOX, G.BOX, *sep, 0.004)["valid"].any()


@pytest.mark.parametrize("gap", [0.01, -0.02])
def test_box_box_crossed_edges_give_one_point(gap):
    # a's top edge runs along x at z = sqrt(2)/2, b's bottom edge along y at z = c - sqrt(2)/2
    c = S2 + gap
    cp = run(G.BOX, G.BOX, pose((0, 0, 0), quat([1, 0, 0], np.pi / 4)), [0.5] * 3,
             pose((0, 0, c), quat([0, 1, 0], np.pi / 4)), [0.5] * 3, 0.02)
    pos, nrm, dist = valid_points(cp)
    np.testing.assert_allclose(dist, [gap], atol=EXACT)
    np.testing.assert_allclose(nrm, [[0, 0, 1]], atol=EXACT)
    np.testing.assert_allclose(pos, [[0, 0, 0.5 * S2 + gap / 2]], atol=EXACT)


def test_sphere_cylinder_side_cap_rim_inside():
    q, c = quat([1, 0, 1], 0.5), np.array([0.1, 0.2, -0.3])
    R, cyl, size = rot(q), pose(c, q), [0.3, 0.4, 0]
    cases = [  # local centre, radius, dist, local normal (sphere -> cylinder)
        ([0.6, 0, 0.1], 0.2, 0.1, [-1, 0, 0]),
        ([0.1, 0.1, 0.7], 0.2, 0.1, [0, 0, -1]),
        ([0.6, 0, 0.8], 0.2, 0.3, [-0.6, 0, -0.8]),  # off the rim by (0.3, 0.4)
        ([0.25, 0, 0.1], 0.1, -0.15, [-1, 0, 0]),  # inside, 0.05 from the side
    ]
    for local, r, dist, n in cases:
        cp = run(G.SPHERE, G.CYLINDER, pose(c + R @ local), [r, 0, 0], cyl, size, 0.5)
        np.testing.assert_allclose(cp["dist"], [dist], atol=EXACT)
        np.testing.assert_allclose(cp["normal"], [R @ n], atol=EXACT)


def test_capsule_cylinder_on_cap_and_along_side():
    cyl, size, cap = pose((0, 0, 0)), [0.5, 0.4, 0], [0.1, 0.3, 0]
    along_x = quat([0, 1, 0], np.pi / 2)
    # lying on the top cap, overhanging its rim at x = 0.5: supported from x = 0.1 to the rim
    cp = run(G.CAPSULE, G.CYLINDER, pose((0.4, 0, 0.5), along_x), cap, cyl, size, 0.0)
    pos, nrm, dist = valid_points(cp)
    assert_same_points(pos, [[0.1, 0, 0.4], [0.5, 0, 0.4]], atol=1e-7)  # golden-section tie tolerance
    np.testing.assert_allclose(dist, 0.0, atol=EXACT)
    np.testing.assert_allclose(nrm, [[0, 0, -1]] * 2, atol=EXACT)
    # parallel to the axis, against the side: both segment ends
    cp = run(G.CAPSULE, G.CYLINDER, pose((0.65, 0, 0.1)), cap, cyl, size, 0.1)
    pos, nrm, dist = valid_points(cp)
    assert_same_points(pos, [[0.525, 0, -0.2], [0.525, 0, 0.4]], atol=1e-7)
    np.testing.assert_allclose(dist, 0.05, atol=EXACT)
    np.testing.assert_allclose(nrm, [[-1, 0, 0]] * 2, atol=EXACT)


def test_box_cylinder_standing_and_lying():
    box, half, size = pose((0, 0, 0)), [1.0, 1.0, 1.0], [0.3, 0.4, 0]
    pos, nrm, dist = valid_points(run(G.BOX, G.CYLINDER, box, half, pose((0.2, 0, 1.4)), size, 0.0))
    assert len(dist) >= 3  # rim triangle (+ the cap centre)
    np.testing.assert_allclose(dist, 0.0, atol=EXACT)
    np.testing.assert_allclose(pos[:, 2], 1.0, atol=EXACT)
    np.testing.assert_allclose(nrm, [[0, 0, 1]] * len(dist), atol=EXACT)
    cp = run(G.BOX, G.CYLINDER, box, half, pose((0, 0, 1.3), quat([1, 0, 0], np.pi / 2)), size, 0.0)
    assert_same_points(valid_points(cp)[0], [[0, 0.4, 1], [0, -0.4, 1]])
    # a small box standing on a big cylinder's cap: the box's 4 bottom corners
    cp = run(G.BOX, G.CYLINDER, pose((0.1, 0, 0.1)), [0.1] * 3, pose((0, 0, -1)), [1.0, 1.0, 0], 0.0)
    assert_same_points(valid_points(cp)[0], [[x, y, 0] for x in (0, 0.2) for y in (-0.1, 0.1)])


def test_cylinder_cylinder_stacked_crossed_parallel():
    size = [0.3, 0.4, 0]
    pos, _, dist = valid_points(run(G.CYLINDER, G.CYLINDER, pose((0, 0, 0)), size, pose((0.1, 0, 0.8)), size, 0.0))
    assert len(dist) >= 3
    np.testing.assert_allclose(dist, 0.0, atol=EXACT)
    np.testing.assert_allclose(pos[:, 2], 0.4, atol=EXACT)
    along_x, along_y = quat([0, 1, 0], np.pi / 2), quat([1, 0, 0], np.pi / 2)
    cp = run(G.CYLINDER, G.CYLINDER, pose((0, 0, 0), along_x), size, pose((0, 0, 0.62), along_y), size, 0.05)
    pos, nrm, dist = valid_points(cp)
    # the golden-section search along the generator stops within its tie tolerance (1e-12 m) of the
    # minimum, which for a smooth minimum locates the point only to ~sqrt(1e-12 * radius) ~ 1e-6 m
    np.testing.assert_allclose(dist, [0.02], atol=EXACT)
    np.testing.assert_allclose(nrm, [[0, 0, 1]], atol=1e-5)
    np.testing.assert_allclose(pos, [[0, 0, 0.31]], atol=1e-5)
    cp = run(G.CYLINDER, G.CYLINDER, pose((0, 0, 0), along_x), size, pose((0.2, 0, 0.6), along_x), size, 0.0)
    assert_same_points(valid_points(cp)[0], [[-0.2, 0, 0.3], [0.4, 0, 0.3]])


def test_valid_is_false_beyond_the_margin():
    a, b = pose((0, 0, 0)), pose((0, 0, 1.2))
    for margin, valid in [(0.1, False), (0.2 - 1e-9, False), (0.2 + 1e-9, True), (0.3, True)]:
        cp = run(G.SPHERE, G.SPHERE, a, [0.5, 0, 0], b, [0.5, 0, 0], margin)
        np.testing.assert_allclose(cp["dist"], [0.2], atol=EXACT)
        assert cp["valid"][0] == valid


# ---------------------------------------------------------------------------------------------
# random placements: invariance and MuJoCo
# ---------------------------------------------------------------------------------------------

SIZES = {G.PLANE: (0.0, 0.0, 0.0), G.SPHERE: (0.3, 0.0, 0.0), G.CAPSULE: (0.2, 0.5, 0.0),
         G.BOX: (0.3, 0.4, 0.5), G.CYLINDER: (0.3, 0.4, 0.0), G.ELLIPSOID: (0.3, 0.2, 0.4)}


def random_poses(rng, n, ta, spread_a=0.2, spread_b=1.2):
    q = rng.normal(size=(2, n, 4))
    q /= np.linalg.norm(q, axis=-1, keepdims=True)
    pa = np.c_[rng.uniform(-spread_a, spread_a, (n, 3)) * (ta != G.PLANE), q[0]]
    pb = np.c_[rng.uniform(-spread_b, spread_b, (n, 3)), q[1]]
    return pa, pb


@pytest.mark.parametrize("ta, tb", ALL_PAIRS, ids=lambda t: t.name)
def test_rigid_motion_invariance(ta, tb):
    rng = np.random.default_rng(int(ta) * 10 + int(tb))
    n, margin = 48, 0.2
    pa, pb = random_poses(rng, n, ta, spread_b=0.8)
    qt = rng.normal(size=4)
    qt /= np.linalg.norm(qt)
    R, t = rot(qt), rng.uniform(-3, 3, 3)

    def move(p):
        q = np.asarray(quat_mul(jnp.asarray(qt), jnp.asarray(p[:, 3:])))
        return np.c_[p[:, :3] @ R.T + t, q]

    c0 = run_batch(ta, tb, pa, SIZES[ta], pb, SIZES[tb], margin)
    c1 = run_batch(ta, tb, move(pa), SIZES[ta], move(pb), SIZES[tb], margin)
    assert c0["valid"].any(axis=1).mean() > 0.3, "the placements should produce contacts"
    np.testing.assert_array_equal(c0["valid"], c1["valid"])
    v = c0["valid"]
    # float64 rounding (~1e-15) is amplified only by near-degenerate features and the tie
    # tolerances of the iterative searches (1e-7 of the geom size); 1e-7 m has no physical effect
    np.testing.assert_allclose(c1["dist"][v], c0["dist"][v], atol=1e-7)
    np.testing.assert_allclose(c1["pos"][v], c0["pos"][v] @ R.T + t, atol=1e-7)
    np.testing.assert_allclose(c1["normal"][v], c0["normal"][v] @ R.T, atol=1e-7)


_MJ_NAME = {G.PLANE: "plane", G.SPHERE: "sphere", G.CAPSULE: "capsule", G.BOX: "box", G.CYLINDER: "cylinder",
            G.ELLIPSOID: "ellipsoid"}


def mujoco_distances(ta, sa, pa, tb, sb, pb, distmax) -> np.ndarray:
    """``mj_geomDistance`` of two mocap-body geoms at each pose pair (MuJoCo quaternions are w-first)."""

    def geom(t, s):
        s = {G.PLANE: (1, 1, 0.1), G.SPHERE: s[:1], G.CAPSULE: s[:2], G.CYLINDER: s[:2], G.BOX: s, G.ELLIPSOID: s}[t]
        return f'<geom type="{_MJ_NAME[t]}" size="{" ".join(map(str, s))}"/>'

    m = mujoco.MjModel.from_xml_string(
        f'<mujoco><worldbody><body mocap="true">{geom(ta, sa)}</body>'
        f'<body mocap="true">{geom(tb, sb)}</body></worldbody></mujoco>')
    d = mujoco.MjData(m)
    out = np.empty(len(pa))
    for i, (x, y) in enumerate(zip(pa, pb, strict=True)):
        d.mocap_pos[:], d.mocap_quat[:] = [x[:3], y[:3]], [np.r_[x[6], x[3:6]], np.r_[y[6], y[3:6]]]
        mujoco.mj_kinematics(m, d)
        out[i] = mujoco.mj_geomDistance(m, d, 0, 1, distmax, None)
    return out


APPROXIMATE = {(G.BOX, G.CYLINDER), (G.CYLINDER, G.CYLINDER)}


@pytest.mark.parametrize("ta, tb", ALL_PAIRS, ids=lambda t: t.name)
def test_distance_agrees_with_mujoco(ta, tb):
    """Minimum ``dist`` over valid points against ``mj_geomDistance`` (distmax = margin).

    MuJoCo computes box-box and the cylinder pairs other than sphere/plane-cylinder with its GJK/EPA
    (tolerance 1e-6; EPA on curved surfaces is less accurate, see below), the others analytically.
    """
    rng = np.random.default_rng(100 + int(ta) * 10 + int(tb))
    n, margin = 150, 0.3
    pa, pb = random_poses(rng, n, ta, spread_b=0.9)
    sa, sb = SIZES[ta], SIZES[tb]
    cp = run_batch(ta, tb, pa, sa, pb, sb, margin)
    ours = np.where(cp["valid"], cp["dist"], np.inf).min(axis=1)
    mj = mujoco_distances(ta, sa, pa, tb, sb, pb, margin)
    near = mj < margin - 1e-6
    assert (mj[near] > 0).sum() > 10 and (mj < 0).sum() > 10, "need separated-within-margin and penetrating samples"
    assert np.all(np.isfinite(ours[near])), "every pair within the margin must give a valid point"
    assert not np.isfinite(ours[mj >= margin + 1e-6]).any(), "no valid point beyond the margin"
    ours, mj = ours[near], mj[near]
    sep, pen = mj > 0, mj <= 0
    if (ta, tb) in APPROXIMATE:
        # Each point is a true surface point with its true signed distance to the other geom, so the
        # minimum is never below the true distance (nor, penetrating, below minus the minimum
        # translation distance): 1e-3 covers EPA's inexact depth on curved surfaces (~1e-4 here).
        assert np.all(ours >= mj - 1e-3)
        # Separated: alternating projections converge slowly for near-tangent features; 1 cm is the
        # documented looser bound (measured worst case ~2 mm, 95 % of cases below 1e-5 m).
        assert np.all(ours[sep] - mj[sep] <= 1e-2)
        # Overlapping geoms are found as touching at least (the depth itself is underestimated):
        # measured distance <= 0.2 mm, bound 1 mm.
        assert np.all(ours[pen] <= 1e-3)
        return
    tol = 1e-6 if (ta, tb) in {(G.BOX, G.BOX), (G.CAPSULE, G.CYLINDER)} else 1e-8  # GJK tolerance vs analytic
    if ta == G.CAPSULE and tb in (G.BOX, G.CYLINDER):
        # Our depth is that of the deepest point of the capsule's axis plus the radius: the minimum
        # translation distance while the axis is outside the other geom (ours > -radius). Once the
        # axis enters a box MuJoCo's capsule-box is not a minimum translation distance (it can report
        # less depth than our axis point alone proves), so only the shallow cases compare.
        sel = (ours > -sa[0]) & (mj > -sa[0])
        assert sel.sum() > 20
        np.testing.assert_allclose(ours[sel], mj[sel], atol=tol)
        if tb == G.CYLINDER:  # MuJoCo's EPA: ours is never deeper than the true depth (EPA ~1e-4 off)
            assert np.all(ours >= mj - 1e-3)
        return
    if (ta, tb) == (G.BOX, G.BOX):
        np.testing.assert_allclose(ours[sep], mj[sep], atol=tol)
        # The face-axis bias (an edge axis must be 5 % + 1e-5 * size better) can report up to that
        # much more depth than the minimum translation distance (EPA's value); clipping never less.
        scale = sum(sa) + sum(sb)
        assert np.all(ours[pen] >= mj[pen] * 1.05 - 1e-5 * scale - tol)
        assert np.all(ours[pen] <= mj[pen] + tol)
        return
    np.testing.assert_allclose(ours, mj, atol=tol)


# ---------------------------------------------------------------------------------------------
# degenerate inputs, batching, float32
# ---------------------------------------------------------------------------------------------

DEGENERATE = [
    (G.SPHERE, G.SPHERE, pose((0, 0, 0)), [0.3, 0, 0], pose((0, 0, 0)), [0.2, 0, 0]),  # concentric
    (G.SPHERE, G.SPHERE, pose((0, 0, 0)), [0, 0, 0], pose((0, 0, 0)), [0, 0, 0]),  # two points
    (G.SPHERE, G.CAPSULE, pose((0, 0, 0.1)), [0.3, 0, 0], pose((0, 0, 0)), [0.2, 0.5, 0]),  # centre on axis
    (G.SPHERE, G.CAPSULE, pose((0, 0, 0)), [0.3, 0, 0], pose((0, 0, 0)), [0.2, 0.0, 0]),  # zero segment
    (G.SPHERE, G.BOX, pose((0, 0, 0)), [0.3, 0, 0], pose((0, 0, 0)), [0.5, 0.5, 0.5]),  # centre at centre
    (G.SPHERE, G.CYLINDER, pose((0, 0, 0)), [0.3, 0, 0], pose((0, 0, 0)), [0.5, 0.5, 0]),
    (G.SPHERE, G.CYLINDER, pose((0, 0, 0.7)), [0.3, 0, 0], pose((0, 0, 0)), [0.5, 0.5, 0]),  # on the axis
    (G.CAPSULE, G.CAPSULE, pose((0, 0, 0)), [0.2, 0.5, 0], pose((0, 0, 0)), [0.2, 0.5, 0]),  # coincident
    (G.CAPSULE, G.CAPSULE, pose((0, 0, 0)), [0.2, 0.5, 0], pose((0, 0, 0), quat([1, 0, 0], 1)), [0.2, 0.5, 0]),
    (G.CAPSULE, G.CAPSULE, pose((0, 0, 0)), [0.2, 0.0, 0], pose((0, 0, 0)), [0.2, 0.0, 0]),  # both points
    (G.CAPSULE, G.BOX, pose((0, 0, 0)), [0.2, 0.5, 0], pose((0, 0, 0)), [0.5, 0.5, 0.5]),
    (G.CAPSULE, G.BOX, pose((0, 0, 0.6)), [0.2, 0.0, 0], pose((0, 0, 0)), [0.5, 0.5, 0.5]),  # zero segment
    (G.CAPSULE, G.CYLINDER, pose((0, 0, 0)), [0.2, 0.5, 0], pose((0, 0, 0)), [0.5, 0.5, 0]),
    (G.CAPSULE, G.CYLINDER, pose((0, 0, 0.6)), [0.2, 0.0, 0], pose((0, 0, 0)), [0.5, 0.5, 0]),  # zero segment
    (G.BOX, G.BOX, pose((0, 0, 0)), [0.5, 0.5, 0.5], pose((0, 0, 0)), [0.5, 0.5, 0.5]),  # coincident
    (G.BOX, G.BOX, pose((0, 0, 0)), [0.5, 0.4, 0.3], pose((0, 0, 0), quat([1, 1, 1], 2.0)), [0.5, 0.4, 0.3]),
    (G.BOX, G.BOX, pose((0, 0, 1.05)), [0.5, 0.5, 0.5], pose((0, 0, 0)), [0.5, 0.5, 0.5]),  # separated, aligned
    (G.BOX, G.CYLINDER, pose((0, 0, 0)), [0.5, 0.5, 0.5], pose((0, 0, 0)), [0.3, 0.4, 0]),
    (G.BOX, G.CYLINDER, pose((0, 0, 0)), [0.5, 0.5, 0.5], pose((0, 0, 0)), [0.3, 0.0, 0]),  # flat disk
    (G.CYLINDER, G.CYLINDER, pose((0, 0, 0)), [0.3, 0.4, 0], pose((0, 0, 0)), [0.3, 0.4, 0]),
    (G.PLANE, G.CYLINDER, pose((0, 0, 0)), [0, 0, 0], pose((0, 0, 0)), [0.3, 0.4, 0]),
    (G.PLANE, G.BOX, pose((0, 0, 0)), [0, 0, 0], pose((0, 0, 0)), [0.5, 0.5, 0.5]),
    (G.PLANE, G.CAPSULE, pose((0, 0, 0)), [0, 0, 0], pose((0, 0, 0)), [0.2, 0.0, 0]),
]


@pytest.mark.parametrize("case", DEGENERATE, ids=lambda c: f"{c[0].name}-{c[1].name}")
def test_degenerate_inputs_give_finite_points_and_unit_normals(case):
    ta, tb, pa, sa, pb, sb = case
    cp = run(ta, tb, pa, sa, pb, sb, 0.1)
    for key in ("pos", "normal", "dist"):
        assert np.all(np.isfinite(cp[key])), (key, cp)
    np.testing.assert_allclose(np.linalg.norm(cp["normal"], axis=1), 1.0, atol=1e-12)
    assert cp["valid"].any()  # every case is within the margin


def test_jit_vmap_batch_matches_single_calls():
    rng = np.random.default_rng(7)
    n, ta, tb = 8, G.CAPSULE, G.CAPSULE
    pa, pb = random_poses(rng, n, ta, spread_b=0.9)
    margins = rng.uniform(0.0, 0.2, n)  # a traced, per-pair margin
    cb = run_batch(ta, tb, pa, SIZES[ta], pb, SIZES[tb], margins)
    assert cb["valid"].any(axis=1).sum() > n // 3
    for i in range(n):  # eager (un-jitted, un-batched) calls
        c1 = collide(ta, tb, pa[i], np.array(SIZES[ta]), pb[i], np.array(SIZES[tb]), margins[i])
        np.testing.assert_array_equal(np.asarray(c1.valid), cb["valid"][i])
        np.testing.assert_allclose(np.asarray(c1.dist), cb["dist"][i], atol=1e-12)
        np.testing.assert_allclose(np.asarray(c1.pos), cb["pos"][i], atol=1e-12)


@pytest.mark.parametrize("ta, tb", ALL_PAIRS, ids=lambda t: t.name)
def test_float32_follows_dtype_and_matches_float64(ta, tb):
    rng = np.random.default_rng(3)
    n, margin = 32, 10.0  # every existing point is valid: compares distances, not margin flips
    pa, pb = random_poses(rng, n, ta, spread_b=0.8)
    sa, sb = np.broadcast_to(SIZES[ta], (n, 3)), np.broadcast_to(SIZES[tb], (n, 3))
    c64 = run_batch(ta, tb, pa, sa, pb, sb, margin)
    c32 = run_batch(ta, tb, pa, sa, pb, sb, margin, dtype=jnp.float32)
    assert c32["pos"].dtype == c32["normal"].dtype == c32["dist"].dtype == np.float32
    for k in ("pos", "normal", "dist"):
        assert np.all(np.isfinite(c32[k]))
    d32 = np.where(c32["valid"], c32["dist"], np.inf).min(axis=1)
    d64 = np.where(c64["valid"], c64["dist"], np.inf).min(axis=1)
    assert np.all(np.isfinite(d64))
    # float32 rounding (~1e-7 relative, amplified by near-parallel features) and its looser tie
    # tolerance in the searches (1e-4 of the geoms' size, about 2e-4 m here)
    np.testing.assert_allclose(d32, d64, atol=1e-3)
