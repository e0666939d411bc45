"""The Warp narrow phase (``kamino.warp_backend.collision``) against the JAX reference
(``kamino.jax_ref.collision``): the same K candidate points per pair, in the same order, with the same
valid flags, positions, normals and distances, in float64 and float32.

Per pair kind and precision, one batch of a few hundred pairs (random poses from separated to deeply
penetrating, resting configurations, degenerate inputs; margins 0 and 0.01) goes through one jitted,
vmapped JAX call (as ``kamino/jax_ref/contacts.py`` does) and one Warp launch of ``collide_kernel``
on the CPU device.

Tolerances. The algorithms are identical, so the results differ by rounding only (the two compilers
order and fuse the arithmetic differently): about 1e-16 m in float64 and 1e-7 m in float32 per
operation on metre-sized coordinates. Rounding is amplified where the reference is ill-conditioned:
  * a normal is the direction of a vector of length ``L`` (the surface gap plus the radii of sphere-
    swept geoms): its error is ~ rounding / L, large for touching points, so normals get an extra
    allowance of 1e-15 m / L in float64 and 1e-6 m / L in float32;
  * the golden-section searches (capsule-box, capsule-cylinder, the cylinder pairs) treat values within
    their tie tolerance (1e-12 of the geom size in float64, 1e-5 in float32) as equal, so around a
    smooth minimum the search is undecided over a bracket ~ sqrt(tie / curvature) wide and rounding
    picks the point in it: up to ~1e-6 m in float64, ~1e-3 m in float32; the distance there differs
    only to second order; the face-interval roots (square roots of near-zero discriminants for near-
    tangent segments) and near-parallel segment pairs have the same square-root sensitivity.
Hence: float64, 1e-9 on everything for the closed-form pairs (identical algorithms, rounding only)
and 1e-6 m / 1e-6 on positions / normals of the iterative pairs (distances 1e-9); float32, 1e-4 m /
1e-4 for at least 99 % of the points and, for all of them, 1e-2 m / 0.1 (the ill-conditioned ones
above), with distances always within 1e-5 m (1e-4 m for the iterative pairs). Valid flags are equal
except for points whose JAX distance is within that distance tolerance of the margin: rounding
decides ``dist <= margin`` there (exactly touching resting configurations with margin 0 are such
points). Degenerate inputs whose fallback depends on an exactly zero vector use exactly
representable poses, so that both backends see the degeneracy.
"""

import functools

import jax
import numpy as np
import pytest
import warp as wp

from kamino.jax_ref.collision import MAX_POINTS as JAX_MAX_POINTS
from kamino.jax_ref.collision import collide
from kamino.model import GeomType as G
from kamino.warp_backend.collision import MAX_POINTS, collide_kernel, max_points
from kamino.warp_backend.types import types_of

DEVICE = "cpu"
KINDS = sorted(k for k in JAX_MAX_POINTS if G.HFIELD not in k)  # the HFIELD pairs need a grid: test_hfield_warp.py
DTYPES = (np.float64, np.float32)
N_RANDOM = 200  # random pairs per kind (plus the resting and degenerate ones)
ITERATIVE = {(G.CAPSULE, G.BOX), (G.CAPSULE, G.CYLINDER), (G.BOX, G.CYLINDER), (G.CYLINDER, G.CYLINDER)}
SWEPT = (G.SPHERE, G.CAPSULE)  # geoms whose normals come from core points (centre, segment)

IDENT = np.array([0.0, 0.0, 0.0, 1.0])
Z_TO_X = np.array([0.5, 0.5, 0.5, 0.5])  # exact rotation: local z -> world x (x -> y, y -> z)
Z_TO_Y = np.array([-0.5, -0.5, -0.5, 0.5])  # exact rotation: local z -> world y


def quat(axis, angle) -> np.ndarray:
    """Unit quaternion (x, y, z, w) of a rotation by ``angle`` about ``axis``."""
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    return np.r_[np.sin(angle / 2) * axis, np.cos(angle / 2)]


def qmul(a, b) -> np.ndarray:
    """Hamilton product of quaternions (x, y, z, w)."""
    ax, ay, az, aw = a
    bx, by, bz, bw = b
    return np.array([aw * bx + ax * bw + ay * bz - az * by, aw * by - ax * bz + ay * bw + az * bx,
                     aw * bz + ax * by - ay * bx + az * bw, aw * bw - ax * bx - ay * by - az * bz])


def axis_z(q) -> np.ndarray:
    """Local +z axis of a rotation in world coordinates."""
    x, y, z, w = q
    return np.array([2 * (x * z + y * w), 2 * (y * z - x * w), 1 - 2 * (x * x + y * y)])


def rand_quat(rng) -> np.ndarray:
    q = rng.normal(size=4)
    return q / np.linalg.norm(q)


def rand_size(rng, t) -> np.ndarray:
    """MuJoCo-convention size of a geom of type ``t``, dimensions in 0.05-0.5 m."""
    u = rng.uniform(0.05, 0.5, 3)
    return {G.PLANE: np.zeros(3), G.SPHERE: np.r_[u[0], 0, 0], G.CAPSULE: np.r_[u[:2], 0], G.BOX: u,
            G.CYLINDER: np.r_[u[:2], 0], G.ELLIPSOID: u}[t]


def bounding_radius(t, s) -> float:
    return {G.SPHERE: s[0], G.CAPSULE: s[0] + s[1], G.BOX: np.linalg.norm(s), G.CYLINDER: np.hypot(s[0], s[1]),
            G.ELLIPSOID: s.max()}[t]


def random_pairs(rng, ta, tb, n) -> list:
    """Random poses, from separated to deeply penetrating (centre distance 0-1.2 bounding radii; for
    planes, heights from -1 to 1.3 bounding radii)."""
    out = []
    for _ in range(n):
        sa, sb = rand_size(rng, ta), rand_size(rng, tb)
        qa, qb = rand_quat(rng), rand_quat(rng)
        pa = rng.uniform(-1, 1, 3)
        if ta == G.PLANE:
            n = axis_z(qa)
            along = rng.uniform(-0.5, 0.5, 3)
            pb = pa + rng.uniform(-1.0, 1.3) * bounding_radius(tb, sb) * n + along - (along @ n) * n
        else:
            d = rng.normal(size=3)
            reach = bounding_radius(ta, sa) + bounding_radius(tb, sb)
            pb = pa + d / np.linalg.norm(d) * rng.uniform(0.0, 1.2) * reach
        out.append((np.r_[pa, qa], sa, np.r_[pb, qb], sb))
    return out


def resting_pairs(rng, ta, tb) -> list:
    """Resting, stacked and crossed configurations (geom a below), penetrating by 2 mm, exactly touching
    and 4 mm apart, with random yaws and offsets (offsets keep ties the reference does not order)."""
    out = []

    def add(pa, qa, sa, pb, qb, sb):
        out.append((np.r_[pa, qa], np.asarray(sa, float), np.r_[pb, qb], np.asarray(sb, float)))

    lying = quat([1, 0, 0], np.pi / 2)  # local z -> world -y
    # a cylinder lying exactly flat on a box or cylinder has two equally deep caps, and the sign of a
    # rounding-level number picks the cap of its support points (the reference does not order this
    # tie): against those geoms, "lying" cylinders are tilted by 10 mrad
    tilted = quat([1, 0, 0], np.pi / 2 + 0.01)
    tilted_x = qmul(quat([0, 1, 0], 0.01), Z_TO_X)
    for gap in (-0.002, 0.0, 0.004):
        for _ in range(2):
            yq = quat([0, 0, 1], rng.uniform(0, np.pi))
            off = np.r_[rng.uniform(-0.05, 0.05, 2), 0.0]

            def above(h, off=off):
                return off + np.array([0.0, 0.0, h])

            sa, sb = rand_size(rng, ta), rand_size(rng, tb)
            o = np.zeros(3)
            if (ta, tb) == (G.PLANE, G.SPHERE):
                add(o, IDENT, sa, above(sb[0] + gap), rand_quat(rng), sb)
            elif (ta, tb) == (G.PLANE, G.CAPSULE):
                add(o, IDENT, sa, above(sb[0] + gap), qmul(yq, lying), sb)  # lying
                add(o, IDENT, sa, above(sb[0] + sb[1] + gap), yq, sb)  # standing
            elif (ta, tb) == (G.PLANE, G.BOX):
                add(o, IDENT, sa, above(sb[2] + gap), yq, sb)  # flat
                add(o, IDENT, sa, above(np.hypot(sb[1], sb[2]) + gap), quat([1, 0, 0], np.pi / 4), sb)  # edge
            elif (ta, tb) == (G.PLANE, G.CYLINDER):
                add(o, IDENT, sa, above(sb[1] + gap), yq, sb)  # standing
                add(o, IDENT, sa, above(sb[0] + gap), qmul(yq, lying), sb)  # lying
            elif (ta, tb) == (G.PLANE, G.ELLIPSOID):
                add(o, IDENT, sa, above(sb[2] + gap), yq, sb)
                add(o, IDENT, sa, above(sb[0] + gap), quat([0, 1, 0], np.pi / 2), sb)
            elif (ta, tb) == (G.SPHERE, G.SPHERE):
                add(o, IDENT, sa, [0, 0, sa[0] + sb[0] + gap], yq, sb)
            elif (ta, tb) == (G.SPHERE, G.CAPSULE):
                add([0, 0, sb[1] + sb[0] + sa[0] + gap], IDENT, sa, o, yq, sb)  # on the end
                add(above(sb[0] + sa[0] + gap), IDENT, sa, o, lying, sb)  # on the side
            elif (ta, tb) == (G.SPHERE, G.BOX):
                add(above(sb[2] + sa[0] + gap), IDENT, sa, o, yq, sb)  # on the top face
            elif (ta, tb) == (G.SPHERE, G.CYLINDER):
                add(above(sb[1] + sa[0] + gap), IDENT, sa, o, yq, sb)  # on the cap
                add([sb[0] + sa[0] + gap, 0, 0.5 * off[0]], IDENT, sa, o, yq, sb)  # at the side
            elif (ta, tb) == (G.CAPSULE, G.CAPSULE):
                shift = [0.3 * sa[1], 0, 0]  # the closest point is off-centre: no tie between overlap ends
                add(o, Z_TO_X, sa, np.r_[shift] + [0, 0.02, sa[0] + sb[0] + gap], qmul(quat([0, 0, 1], 0.03), Z_TO_X),
                    sb)  # lying side by side
                add(o, Z_TO_X, sa, [0, 0, sa[0] + sb[0] + gap], qmul(yq, Z_TO_X), sb)  # crossed
            elif (ta, tb) == (G.CAPSULE, G.BOX):
                add(above(sb[2] + sa[0] + gap), qmul(yq, lying), sa, o, IDENT, sb)  # lying on the box
                add(above(sb[2] + sa[0] + sa[1] + gap), yq, sa, o, IDENT, sb)  # standing on it
            elif (ta, tb) == (G.CAPSULE, G.CYLINDER):
                add(above(sb[1] + sa[0] + gap), qmul(yq, lying), sa, o, IDENT, sb)  # lying on the cap
                add([0, 0.3 * sb[1], sb[0] + sa[0] + gap], Z_TO_X, sa, o, tilted, sb)  # across a lying cylinder
                add([0, 0.1, sb[0] + sa[0] + gap], lying, sa, o, tilted, sb)  # along a lying cylinder
            elif (ta, tb) == (G.BOX, G.BOX):
                add(o, IDENT, sa, above(sa[2] + sb[2] + gap), yq, sb)  # stacked, yawed
                add(o, IDENT, sa, [0, 0, sa[2] + sb[2] + gap], IDENT, sb)  # stacked, aligned
                add(o, IDENT, sa, [0, 0, sa[2] + np.hypot(sb[1], sb[2]) + gap], quat([1, 0, 0], np.pi / 4), sb)
            elif (ta, tb) == (G.BOX, G.CYLINDER):
                add(o, IDENT, sa, above(sa[2] + sb[1] + gap), yq, sb)  # standing on the box
                add(o, IDENT, sa, above(sa[2] + sb[0] + gap), qmul(yq, tilted), sb)  # lying on it
                add(above(0.3 + 0.03 + gap), yq, [0.03, 0.03, 0.03], o, IDENT, [0.3, 0.3, 0])  # box on a cap
            elif (ta, tb) == (G.CYLINDER, G.CYLINDER):
                add(o, IDENT, sa, above(sa[1] + sb[1] + gap), yq, sb)  # stacked
                add(o, tilted, sa, [0, 0, sa[0] + sb[0] + gap], tilted_x, sb)  # lying, crossed
                add(o, tilted, sa, [0.1, 0.2 * sa[1], sa[0] + sb[0] + gap], lying, sb)  # lying, parallel
    return out


def degenerate_pairs(ta, tb) -> list:
    """The degenerate inputs of the reference's docstring, with exactly representable poses."""
    o = np.zeros(3)
    cases = {
        (G.PLANE, G.CAPSULE): [(o, IDENT, [0, 0, 0], [0, 0, 0.25], IDENT, [0.25, 0.0, 0])],  # zero segment
        (G.PLANE, G.BOX): [(o, IDENT, [0, 0, 0], [0, 0, 0.5], IDENT, [0.5, 0.5, 0.5])],  # 4-fold tie
        (G.PLANE, G.CYLINDER): [(o, IDENT, [0, 0, 0], [0, 0, 0.25], IDENT, [0.25, 0.25, 0])],  # axis along normal
        (G.SPHERE, G.SPHERE): [(o, IDENT, [0.25, 0, 0], o, IDENT, [0.125, 0, 0]),  # concentric
                               (o, IDENT, [0, 0, 0], o, IDENT, [0, 0, 0])],  # two points
        (G.SPHERE, G.CAPSULE): [([0, 0, 0.125], IDENT, [0.25, 0, 0], o, IDENT, [0.125, 0.5, 0]),  # on the axis
                                (o, IDENT, [0.25, 0, 0], o, IDENT, [0.125, 0.0, 0])],  # zero segment
        (G.SPHERE, G.BOX): [(o, IDENT, [0.25, 0, 0], o, IDENT, [0.5, 0.5, 0.5]),  # centre at the centre: tie
                            ([0.125, 0, 0], IDENT, [0.25, 0, 0], o, IDENT, [0.5, 0.25, 0.5])],
        (G.SPHERE, G.CYLINDER): [(o, IDENT, [0.25, 0, 0], o, IDENT, [0.5, 0.5, 0]),  # centre: side/cap tie
                                 ([0, 0, 0.75], IDENT, [0.25, 0, 0], o, IDENT, [0.5, 0.5, 0])],  # on the axis
        (G.CAPSULE, G.CAPSULE): [(o, IDENT, [0.25, 0.5, 0], o, IDENT, [0.25, 0.5, 0]),  # coincident
                                 (o, IDENT, [0.25, 0.5, 0], o, Z_TO_X, [0.125, 0.5, 0]),  # intersecting axes
                                 ([0, 0, 0.25], Z_TO_Y, [0.25, 0.5, 0], [0, 0, 0.25], Z_TO_X, [0.125, 0.5, 0]),
                                 (o, IDENT, [0.25, 0.0, 0], o, IDENT, [0.25, 0.0, 0])],  # both points
        (G.CAPSULE, G.BOX): [(o, IDENT, [0.25, 0.5, 0], o, IDENT, [0.5, 0.5, 0.5]),
                             ([0, 0, 0.625], IDENT, [0.25, 0.0, 0], o, IDENT, [0.5, 0.5, 0.5])],  # zero segment
        (G.CAPSULE, G.CYLINDER): [(o, IDENT, [0.25, 0.5, 0], o, IDENT, [0.5, 0.5, 0]),
                                  ([0, 0, 0.625], IDENT, [0.25, 0.0, 0], o, IDENT, [0.5, 0.5, 0])],
        (G.BOX, G.BOX): [(o, IDENT, [0.5, 0.5, 0.5], o, IDENT, [0.5, 0.5, 0.5]),  # coincident
                         (o, IDENT, [0.5, 0.25, 0.125], o, Z_TO_X, [0.5, 0.25, 0.125]),
                         ([0, 0, 1.0625], IDENT, [0.5, 0.5, 0.5], o, IDENT, [0.5, 0.5, 0.5])],  # separated, aligned
        (G.BOX, G.CYLINDER): [(o, IDENT, [0.5, 0.5, 0.5], o, IDENT, [0.25, 0.375, 0]),
                              (o, IDENT, [0.5, 0.5, 0.5], o, IDENT, [0.25, 0.0, 0])],  # flat disk
        (G.CYLINDER, G.CYLINDER): [(o, IDENT, [0.25, 0.375, 0], o, IDENT, [0.25, 0.375, 0])],  # coincident
    }.get((ta, tb), [])
    return [(np.r_[pa, qa], np.asarray(sa, float), np.r_[pb, qb], np.asarray(sb, float))
            for pa, qa, sa, pb, qb, sb in cases]


@functools.cache
def batch(ta, tb) -> tuple[np.ndarray, ...]:
    """``pose_a, size_a, pose_b, size_b, margin`` of all test pairs of one kind (float64)."""
    rng = np.random.default_rng(100 * int(ta) + int(tb))
    pairs = random_pairs(rng, ta, tb, N_RANDOM) + resting_pairs(rng, ta, tb) + degenerate_pairs(ta, tb)
    cols = [np.stack([p[i] for p in pairs]) for i in range(4)]
    margin = np.where(np.arange(len(pairs)) % 2 == 0, 0.0, 0.01)
    return (*cols, margin)


def run_jax(ta, tb, dtype) -> dict[str, np.ndarray]:
    """``collide`` jitted and vmapped over the batch, as ``kamino/jax_ref/contacts.py`` runs it. XLA's
    backend optimisation is off: it halves the compile time (the test's largest cost) and changes the
    reference's results by rounding only."""
    args = [np.asarray(x, dtype) for x in batch(ta, tb)]
    fn = jax.jit(jax.vmap(functools.partial(collide, ta, tb)))
    cp = fn.lower(*args).compile(compiler_options={"xla_backend_optimization_level": 0})(*args)
    return {k: np.asarray(v) for k, v in vars(cp).items()}


def run_warp(ta, tb, dtype, type_a=None, type_b=None) -> dict[str, np.ndarray]:
    """``collide_kernel`` on the batch; every output slot starts as NaN / -1 (untouched = detectable)."""
    T = types_of(dtype)
    pa, sa, pb, sb, margin = batch(ta, tb)
    n, k = len(pa), MAX_POINTS[(ta, tb)]

    def arr(x, t):
        return wp.array(np.asarray(x, dtype), dtype=t, device=DEVICE)

    def ints(x):
        return wp.array(np.asarray(x, np.int32), dtype=wp.int32, device=DEVICE)

    out = [arr(np.full((n * k, 3), np.nan), T.vec3), arr(np.full((n * k, 3), np.nan), T.vec3),
           arr(np.full(n * k, np.nan), T.scalar), ints(np.full(n * k, -1))]
    inputs = [ints(np.full(n, int(ta if type_a is None else type_a))),
              ints(np.full(n, int(tb if type_b is None else type_b))),
              arr(pa, T.transform), arr(sa, T.vec3), arr(pb, T.transform), arr(sb, T.vec3), arr(margin, T.scalar),
              ints(np.arange(n) * k)]
    wp.launch(collide_kernel(dtype), dim=n, inputs=inputs + out, device=DEVICE)
    pos, normal, dist, valid = (a.numpy() for a in out)
    return {"pos": pos.reshape(n, k, 3), "normal": normal.reshape(n, k, 3), "dist": dist.reshape(n, k),
            "valid": valid.reshape(n, k)}


def tolerances(ta, tb, dtype) -> dict[str, float]:
    """See the module docstring: ``strict`` on every point (float64) or on >= 99 % of them (float32),
    ``loose`` on every point; ``dist`` on every point and as the valid-flag band around the margin."""
    iterative = (ta, tb) in ITERATIVE
    if dtype == np.float64:
        pos = 1e-6 if iterative else 1e-9
        return {"pos": pos, "normal": pos, "dist": 1e-9, "loose_pos": pos, "loose_normal": pos, "cond": 1e-15}
    return {"pos": 1e-4, "normal": 1e-4, "dist": 1e-4 if iterative else 1e-5, "loose_pos": 1e-2,
            "loose_normal": 0.1, "cond": 1e-6}


def test_max_points_answers_supported_pairs_and_names_the_others():
    assert max_points(G.BOX, G.BOX) == 8 and max_points(int(G.PLANE), int(G.SPHERE)) == 1
    with pytest.raises(ValueError, match="unordered"):
        max_points(G.BOX, G.PLANE)
    with pytest.raises(ValueError, match="unknown"):
        max_points(99, 0)


@pytest.mark.parametrize("dtype", DTYPES, ids=lambda d: np.dtype(d).name)
@pytest.mark.parametrize("ta, tb", KINDS, ids=lambda t: t.name)
def test_warp_matches_jax(ta, tb, dtype):
    want = run_jax(ta, tb, dtype)
    got = run_warp(ta, tb, dtype)
    tol = tolerances(ta, tb, dtype)
    margin = batch(ta, tb)[4][:, None]

    # every slot is written, finite and a 0/1 flag
    for key in ("pos", "normal", "dist"):
        assert np.all(np.isfinite(got[key])), key
    assert set(np.unique(got["valid"])) <= {0, 1}
    # the batch covers separated, touching and penetrating pairs
    assert want["valid"].any(axis=1).mean() > 0.25 and (~want["valid"].any(axis=1)).mean() > 0.1
    assert np.any(want["valid"] & (want["dist"] < -0.01))

    # valid flags: equal, except where rounding decides dist <= margin
    differ = want["valid"] != got["valid"].astype(bool)
    near_margin = np.abs(want["dist"] - margin) <= tol["dist"]
    assert not np.any(differ & ~near_margin), np.argwhere(differ & ~near_margin)

    # compared: the points valid in both, away from the margin (at the margin, rounding also decides
    # e.g. whether exactly touching stacked boxes report their face points or one of their equally
    # close corner / edge pairs)
    both = want["valid"] & got["valid"].astype(bool) & ~near_margin
    d_err = np.abs(got["dist"] - want["dist"])[both]
    p_err = np.abs(got["pos"] - want["pos"]).max(axis=-1)[both]
    n_err = np.abs(got["normal"] - want["normal"]).max(axis=-1)[both]
    # a normal is the direction of a vector of length L: the gap plus the radii of sphere-swept geoms
    _, sa, _, sb, _ = batch(ta, tb)
    radii = sa[:, 0] * (ta in SWEPT) + sb[:, 0] * (tb in SWEPT)
    length = (np.abs(want["dist"]) + radii[:, None])[both]
    n_allow = tol["cond"] / np.maximum(length, tol["cond"])
    assert d_err.max(initial=0) <= tol["dist"], d_err.max()
    assert p_err.max(initial=0) <= tol["loose_pos"], p_err.max()
    assert np.all(n_err <= tol["loose_normal"] + n_allow), (n_err - n_allow).max()
    strict = (p_err <= tol["pos"]) & (n_err <= tol["normal"] + n_allow)
    if dtype == np.float64:
        assert strict.all(), (p_err.max(), (n_err - n_allow).max())
    else:
        assert strict.mean() >= 0.99, strict.mean()


def test_unsupported_or_unordered_pairs_write_nothing():
    got = run_warp(G.PLANE, G.SPHERE, np.float64, type_a=G.SPHERE, type_b=G.PLANE)  # unordered
    assert np.all(got["valid"] == -1) and np.all(np.isnan(got["dist"]))
    got = run_warp(G.PLANE, G.SPHERE, np.float64, type_a=G.SPHERE, type_b=G.ELLIPSOID)  # unsupported
    assert np.all(got["valid"] == -1) and np.all(np.isnan(got["dist"]))
