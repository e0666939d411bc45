"""Heightfields on the Warp backend: its HFIELD pairs (``kamino.warp_backend.collision.collide_hfield_func``)
against the JAX reference's, rollouts on heightfields on both backends, and a batch of worlds that share one grid.

Tests run in float64 (``conftest.py``). The Warp narrow phase evaluates the reference's formulas in the same order
(docs/conventions.md, "Heightfields"), so the two differ by the rounding of the two compilers only: ~1e-16 m per
operation on metre-sized geometry, over a few dozen operations per point. The tolerance ``ROUNDING`` = 1e-12 m
allows 1e4 of those. A point lying exactly on a cell edge or a cell's diagonal could see rounding pick the other
triangle; the pair test puts its geoms 1e-4 of a cell from those lines, far from that (1e-16 of a cell).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import warp as wp

import kamino
from kamino.jax_ref.collision import MAX_POINTS, HField
from kamino.jax_ref.collision import collide as jax_collide
from kamino.model import GeomType as G
from kamino.model import JointType, ModelBuilder, concat, replicate
from kamino.warp_backend.collision import collide_hfield_kernel
from kamino.warp_backend.model_data import warp_model
from kamino.warp_backend.types import types_of

ROUNDING = 1e-12  # see module docstring
DEVICE = "cpu"

# a bumpy grid: a ramp falling along +x with random bumps, in a frame turned about z and tilted, offset
NROW, NCOL = 5, 6
SIZE = np.array([1.2, 0.9, 0.5, 0.1])  # rx, ry, z_top, z_base
DATA = (np.tile(np.linspace(1.0, 0.0, NCOL), (NROW, 1)) * 0.7
        + 0.3 * np.random.default_rng(5).uniform(size=(NROW, NCOL))).ravel()
DATA = (DATA - DATA.min()) / (DATA.max() - DATA.min())  # normalised as the model stores them


def quat(axis, angle) -> np.ndarray:
    """Unit quaternion (x, y, z, w) of a rotation by ``angle`` about ``axis``."""
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    return np.r_[np.sin(angle / 2) * axis, np.cos(angle / 2)]


def qmul(a, b) -> np.ndarray:
    """Hamilton product of quaternions (x, y, z, w)."""
    av, aw, bv, bw = a[:3], a[3], b[:3], b[3]
    return np.r_[aw * bv + bw * av + np.cross(av, bv), aw * bw - av @ bv]


def rotate(q, v) -> np.ndarray:
    return qmul(qmul(q, np.r_[v, 0.0]), q * np.r_[-1.0, -1.0, -1.0, 1.0])[:3]


H_POSE = np.r_[0.2, -0.1, 0.3, qmul(quat((0, 0, 1), 0.5), quat((1, 0, 0), 0.1))]
GEOM_SIZES = {G.SPHERE: (0.1, 0.0, 0.0), G.CAPSULE: (0.07, 0.15, 0.0), G.BOX: (0.12, 0.08, 0.05),
              G.CYLINDER: (0.1, 0.06, 0.0)}


def surface(x, y) -> float:
    """The grid's height below the local point ``(x, y)`` (the triangles of docs/conventions.md, "Heightfields")."""
    dx, dy = 2 * SIZE[0] / (NCOL - 1), 2 * SIZE[1] / (NROW - 1)
    fx, fy = (x + SIZE[0]) / dx, (y + SIZE[1]) / dy
    c, r = min(int(fx), NCOL - 2), min(int(fy), NROW - 2)
    u, v = fx - c, fy - r
    h = DATA.reshape(NROW, NCOL) * SIZE[2]
    if u >= v:
        return h[r, c] + u * (h[r, c + 1] - h[r, c]) + v * (h[r + 1, c + 1] - h[r, c + 1])
    return h[r, c] + u * (h[r + 1, c + 1] - h[r + 1, c]) + v * (h[r + 1, c] - h[r, c])


def poses(n, rng) -> np.ndarray:
    """``n`` world poses of a geom whose centre lies 1e-4 of a cell beside a cell edge along x or y or a cell's
    diagonal, at -0.1 .. 0.25 m from the surface below it (penetrating to separated), turned at random; and two
    more: one 0.3 m beyond the grid's +x border, one astride its -y border."""
    dx, dy = 2 * SIZE[0] / (NCOL - 1), 2 * SIZE[1] / (NROW - 1)
    eps = 1e-4 * rng.choice([-1.0, 1.0], size=n)
    c, r = rng.integers(0, NCOL - 1, size=n), rng.integers(0, NROW - 1, size=n)
    t = rng.uniform(0.1, 0.9, size=n)
    line = rng.integers(0, 3, size=n)  # 0: an edge x = const, 1: an edge y = const, 2: the diagonal u = v
    u = np.where(line == 0, eps, np.where(line == 1, t, t + eps))
    v = np.where(line == 0, t, np.where(line == 1, eps, t))
    xy = np.stack([-SIZE[0] + (c + u) * dx, -SIZE[1] + (r + v) * dy], axis=1)
    z = [surface(x, y) for x, y in xy] + rng.uniform(-0.1, 0.25, size=n)
    local = [np.r_[p, zi] for p, zi in zip(xy, z, strict=True)]
    local += [np.r_[SIZE[0] + 0.3, 0.1, 0.1], np.r_[0.2, -SIZE[1] - 0.02, 0.3]]
    out = []
    for p in local:
        q = rng.normal(size=4)
        out.append(np.r_[H_POSE[:3] + rotate(H_POSE[3:], p), q / np.linalg.norm(q)])
    return np.array(out)


def warp_points(ta, pa, sa) -> dict:
    """``collide_hfield_kernel`` on the pairs (geom a of type ``ta`` at poses ``pa`` against the grid at ``H_POSE``,
    margin 0.05); every output slot starts as NaN / -1 (an unwritten slot is detectable)."""
    T = types_of(np.float64)
    n, k = len(pa), MAX_POINTS[(ta, G.HFIELD)]

    def arr(x, t):
        return wp.array(np.asarray(x, np.float64), dtype=t, device=DEVICE)

    def ints(x):
        return wp.array(np.asarray(x, np.int32), dtype=wp.int32, device=DEVICE)

    out = [arr(np.full((n * k, 3), np.nan), T.vec3), arr(np.full((n * k, 3), np.nan), T.vec3),
           arr(np.full(n * k, np.nan), T.scalar), ints(np.full(n * k, -1))]
    inputs = [ints(np.full(n, int(ta))), arr(pa, T.transform), arr(sa, T.vec3),
              arr(np.tile(H_POSE, (n, 1)), T.transform), arr(DATA, T.scalar), ints(np.zeros(n)),
              ints(np.full(n, NROW)), ints(np.full(n, NCOL)),
              arr(np.tile(SIZE, (n, 1)), T.vec4), arr(np.full(n, 0.05), T.scalar), ints(np.arange(n) * k)]
    wp.launch(collide_hfield_kernel(np.float64), dim=n, inputs=inputs + out, device=DEVICE)
    pos, normal, dist, valid = (a.numpy() for a in out)
    return {"pos": pos.reshape(n, k, 3), "normal": normal.reshape(n, k, 3), "dist": dist.reshape(n, k),
            "valid": valid.reshape(n, k).astype(bool)}


def jax_points(ta, pa, sa) -> dict:
    hf = HField(jnp.asarray(DATA), jnp.asarray(0), jnp.asarray(NROW), jnp.asarray(NCOL), jnp.asarray(SIZE))
    cp = jax.jit(jax.vmap(lambda p, s: jax_collide(ta, G.HFIELD, p, s, jnp.asarray(H_POSE), jnp.zeros(3), 0.05,
                                                   hfield=hf)))(pa, sa)
    return {k: np.asarray(getattr(cp, k)) for k in ("pos", "normal", "dist", "valid")}


def test_warp_heightfield_pairs_equal_the_reference():
    """SPHERE, CAPSULE, BOX and CYLINDER against a bumpy heightfield, 40 poses each beside the triangles' edges (and
    two at the grid's border): the Warp narrow phase gives the reference's K points in the same order, with the
    same positions, normals and distances to ``ROUNDING`` and the same valid flags (no distance lies within
    ``ROUNDING`` of the margin: asserted)."""
    rng = np.random.default_rng(11)
    for ta, size in GEOM_SIZES.items():
        pa = poses(40, rng)
        sa = np.tile(np.asarray(size, float), (len(pa), 1))
        w, j = warp_points(ta, pa, sa), jax_points(ta, pa, sa)
        for key in ("pos", "normal", "dist"):
            np.testing.assert_allclose(w[key], j[key], atol=ROUNDING, rtol=0, err_msg=f"{ta.name} {key}")
        assert np.abs(j["dist"] - 0.05).min() > ROUNDING
        np.testing.assert_array_equal(w["valid"], j["valid"], err_msg=ta.name)
        # non-trivial: penetrating, separated and off-grid points all occur
        assert j["valid"].any() and not j["valid"].all() and (j["dist"][j["valid"]] < 0).any(), ta.name
        assert not j["valid"][-2].any(), ta.name  # beyond the border: no contact


# ---------------------------------------------------------------------------------------------
# rollouts on both backends
# ---------------------------------------------------------------------------------------------

SLOPE = 0.3


def _world(terrain: str, geom: G) -> kamino.Model:
    """A free sphere (friction 0.8: it rolls) or box (friction 0.2, below the slope: it slides) of 0.1 m and 1 kg
    released at x = -0.8 above a plane falling along +x through (0, 0, 0.2) with slope ``SLOPE``, or above the same
    plane as a ramp heightfield, or above a bumpy heightfield (friction 0.2: a contact takes the larger of its two
    geoms')."""
    b = ModelBuilder()
    body = b.add_body(1.0, np.eye(3) * 0.004, pos=(-0.8, 0.0, 0.6), quat=quat((1, 1, 0), 0.3))
    b.add_joint(JointType.FREE, -1, body)
    if geom == G.SPHERE:
        b.add_geom(G.SPHERE, body, size=0.1, friction=0.8)
    else:
        b.add_geom(G.BOX, body, size=(0.1, 0.08, 0.06), friction=0.2)
    if terrain == "plane":
        b.add_geom(G.PLANE, -1, pos=(0, 0, 0.2), quat=quat((0, 1, 0), np.arctan(SLOPE)), friction=0.8)
    elif terrain == "ramp":  # heights 0.2 + SLOPE * (2 - x) - 0.6 over [-2, 2]: the same plane
        h = b.add_hfield(3, 9, (2.0, 1.0, 4 * SLOPE, 0.5), np.tile(np.linspace(1, 0, 9), (3, 1)))
        b.add_geom(G.HFIELD, -1, pos=(0, 0, 0.2 - 2 * SLOPE), hfield=h, friction=0.8)
    else:  # the ramp with bumps of up to ~0.1 m
        bumps = 0.1 / (4 * SLOPE) * np.random.default_rng(1).uniform(size=(5, 9))
        h = b.add_hfield(5, 9, (2.0, 1.0, 4 * SLOPE, 0.5), np.tile(np.linspace(1, 0, 9), (5, 1)) + bumps)
        b.add_geom(G.HFIELD, -1, pos=(0, 0, 0.2 - 2 * SLOPE), hfield=h, friction=0.2)
    return b.finalize()


def test_rollouts_on_heightfields_agree_with_a_plane_and_across_backends():
    """Four worlds of one model (one compilation per backend), float64, 40 steps of 15 ms: a sphere released on an
    inclined plane, on a ramp heightfield of the same slope and on a bumpy heightfield, and a box tumbling onto the
    bumpy one and sliding down across its triangles.

    (1) JAX reference: the sphere rolls down the ramp heightfield as down the plane, to 1e-9 m: the contact points,
    distances and normals are the plane's to rounding (tests/test_hfield.py), and the solver's iterations amplify
    those 1e-16 differences by far less than the 1e7 that this bound allows.

    (2) The Warp backend against the reference: equal contact counts at every step, and poses (m, and quaternion
    components) within 1e-9 for the rolling spheres, 1e-5 for the sliding box. The contacts are the reference's to
    rounding (test above). The spheres' solves run the same PADMM iterations on both backends (asserted, on the
    steps with a contact: without one Warp runs no iteration and the reference reports 2), so only rounding
    separates them, amplified by far less than the 1e7 the bound allows (measured: 1.4e-15). The sliding box is
    ill-conditioned (its friction is at the cone's boundary): rounding differences grow from 1e-15 to 1e-11 in the
    first steps of sliding, and then the solves stop at the tolerance (1e-6) one or more iterations apart, where
    the velocities differ by ~1e-6 of their ~1 m/s scale; over the ~30 steps of 15 ms that follow the poses differ
    by ~5e-7 at most (measured: 1.3e-7; with tolerance 1e-8: 5.5e-9, the same mechanism). 1e-5 leaves 70x.
    """
    model = concat([_world("plane", G.SPHERE), _world("ramp", G.SPHERE), _world("bumpy", G.SPHERE),
                    _world("bumpy", G.BOX)])
    state = kamino.init_state(model)
    cfg = kamino.SolverConfig(dt=0.015, tolerance=1e-6)
    jx, wa = (kamino.rollout(model, state, num_steps=40, config=cfg, backend=be) for be in ("jax", "warp"))
    q = np.asarray(jx.body_q)  # [steps, worlds, 7]
    np.testing.assert_allclose(q[:, 1, :3], q[:, 0, :3], atol=1e-9)
    start, end = np.array([-0.8, 0.0, 0.6]), q[-1, 1, :3]
    assert end[0] - start[0] > 0.2 and end[2] < start[2] - 0.05, end  # downhill (+x) and lower
    n_con = np.asarray(jx.info.num_contacts)
    np.testing.assert_array_equal(np.asarray(wa.info.num_contacts), n_con)
    touching = n_con[:, :3] > 0
    np.testing.assert_array_equal(np.asarray(wa.info.iterations)[:, :3][touching],
                                  np.asarray(jx.info.iterations)[:, :3][touching])
    np.testing.assert_allclose(np.asarray(wa.body_q)[:, :3], q[:, :3], atol=1e-9, rtol=0)
    np.testing.assert_allclose(np.asarray(wa.body_q)[:, 3], q[:, 3], atol=1e-5, rtol=0)
    assert n_con[-1, :3].tolist() == [1, 1, 1] and n_con[-1, 3] >= 3  # the box slides on a face, over bumps
    assert (q[-1, 2:, 0] - q[0, 2:, 0] > 0.2).all(), q[-1, :, :3]  # downhill on the bumpy terrain too


# ---------------------------------------------------------------------------------------------
# storage: one copy of a grid shared by the worlds
# ---------------------------------------------------------------------------------------------


def test_worlds_sharing_a_grid_store_it_once_on_warp():
    """``replicate`` of a world on the bumpy heightfield (8 copies) and a world on the ramp concatenated: the Warp
    model stores the two distinct grids' heights once each (the model itself holds 9 grids), every world's
    heightfield points into them, and a step of the batch gives each world the result of its model stepped alone,
    bit for bit (the worlds run the same operations on their own segments: test_cross_backend.py's heterogeneous
    worlds)."""
    bumpy, ramp = _world("bumpy", G.SPHERE), _world("ramp", G.SPHERE)
    batch = concat([replicate(bumpy, 8), ramp])
    wm = warp_model(batch, np.float64, DEVICE)
    n_bumpy, n_ramp = bumpy.hfield_data.size, ramp.hfield_data.size
    assert batch.hfield_data.size == 8 * n_bumpy + n_ramp
    assert wm.arrays.hfield_data.shape == (n_bumpy + n_ramp,)
    assert wm.arrays.hfield_adr.numpy().tolist() == [0] * 8 + [n_bumpy]
    cfg = kamino.SolverConfig(dt=0.015)
    state = kamino.init_state(batch)
    for _ in range(12):  # the sphere lands (step 6) and rolls
        state = kamino.step(batch, state, config=cfg, backend="warp")
    assert np.asarray(state.info.num_contacts).tolist() == [1] * 9
    alone = {}
    for name, m in (("bumpy", bumpy), ("ramp", ramp)):
        s = kamino.init_state(m)
        for _ in range(12):
            s = kamino.step(m, s, config=cfg, backend="warp")
        alone[name] = np.asarray(s.body_q)
    q = np.asarray(state.body_q)
    for w in range(8):
        np.testing.assert_array_equal(q[w:w + 1], alone["bumpy"])
    np.testing.assert_array_equal(q[8:9], alone["ramp"])
