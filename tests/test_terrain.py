"""Rough terrain: the tiled heightfield generator, the terrain's height in JAX against the contact model's surface
(kamino/envs/terrain.py), and the ``dr_legs_rough`` task (kamino/envs/rough.py) on the Warp backend (its step
compiles in a third of the JAX reference's time on the CPU).

Tests run in float64 (``conftest.py``). "Rounding" tolerances of 1e-12 m allow for a handful of operations on
heights and coordinates of metres (about 1e-15 m each); the heightfield geom stores heights normalised by their
range (0.5 m) and offset by the lowest, which adds a few more.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from kamino.envs.terrain import TERRAIN_TYPES, add_terrain, generate_terrain, surface_height
from kamino.jax_ref.collision import HField, collide
from kamino.model import GeomType, ModelBuilder

ROUNDING = 1e-12  # see module docstring


@pytest.fixture(scope="module")
def terrain():
    return generate_terrain(seed=3)


@pytest.fixture(scope="module")
def small():
    """Every tile type at difficulty 0 and 1 inside a 1 m border: a quarter of the default grid's points."""
    return generate_terrain(rows=2, border=1.0, seed=3)


def _tile(terrain, row: int, kind: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The heights of tile ``(row, column of kind)`` of a terrain with the default 4 m border, and the tile-local
    ``x, y`` of its grid points (from the tile's centre)."""
    col = terrain.types.index(kind)
    res, n = terrain.resolution, round(terrain.tile_size / terrain.resolution)
    border = round(4.0 / res)
    c0, r0 = border + row * n, border + col * n  # difficulty rows along x, types along y
    local = (np.arange(n + 1) - 0.5 * n) * res
    return terrain.heights[r0:r0 + n + 1, c0:c0 + n + 1], local, local


def test_slope_tiles_follow_their_slope(terrain):
    """Along the tile's x axis (y = 0), from the platform's edge to the tile's, the heights of the hardest row's
    slope tiles fall (``slope_down``: the platform is high) or rise (``slope_up``) at tan(12 degrees) per metre,
    reaching 0 at the tile's edge; the platform is flat."""
    grade = np.tan(np.deg2rad(12.0))
    for kind, sign in (("slope_down", -1.0), ("slope_up", 1.0)):
        h, x, y = _tile(terrain, 4, kind)
        mid = h[np.argmin(np.abs(y))]
        run = (x > 0.3) & (x <= 1.5 + 1e-9)
        np.testing.assert_allclose(np.diff(mid[run]) / np.diff(x[run]), sign * grade, atol=ROUNDING)
        assert abs(mid[-1]) < ROUNDING  # the tile's edge: 0, where the neighbours meet it
        platform = h[np.ix_(np.abs(y) <= 0.3, np.abs(x) <= 0.3)]
        np.testing.assert_allclose(platform, -sign * grade * 1.2, atol=ROUNDING)
        assert terrain.origins[4, terrain.types.index(kind), 2] == pytest.approx(-sign * grade * 1.2, abs=ROUNDING)


def test_stair_tiles_have_their_step_height(terrain):
    """Difficulty 0.5 (row 2 of 5): steps of 0.01 + 0.5 * 0.03 = 0.025 m, 4 treads of 0.3 m over the 1.2 m run:
    the heights along a tile's axis take the levels 0, 1, ..., 4 steps, rising inwards (``stairs_down``: a robot
    walking out steps down) or falling inwards (``stairs_up``), and each tread is 0.3 m deep."""
    step = 0.025
    for kind, sign in (("stairs_down", 1.0), ("stairs_up", -1.0)):
        h, x, y = _tile(terrain, 2, kind)
        mid = h[np.argmin(np.abs(y))]
        levels = np.unique(np.round(sign * mid / step, 9))
        np.testing.assert_array_equal(levels, [0, 1, 2, 3, 4])
        out = x > 0  # the outward half: one step down (or up) every 0.3 m
        edges = x[out][1:][np.diff(mid[out]) != 0]
        np.testing.assert_allclose(np.diff(edges), 0.3, atol=terrain.resolution / 2)


def test_generator_is_deterministic_from_its_seed(terrain):
    """The same arguments give the same heights bit for bit; another seed changes the noise tiles only."""
    again = generate_terrain(seed=3)
    other = generate_terrain(seed=4)
    np.testing.assert_array_equal(again.heights, terrain.heights)
    np.testing.assert_array_equal(again.origins, terrain.origins)
    diff = np.nonzero(np.any(other.heights != terrain.heights, axis=1))[0]  # the rows (y) that differ
    noise = terrain.origins[0, terrain.types.index("noise"), 1]
    y = (diff - 0.5 * (terrain.heights.shape[0] - 1)) * terrain.resolution
    assert len(diff) > 0 and np.all(np.abs(y - noise) < 0.5 * terrain.tile_size)
    assert terrain.types == TERRAIN_TYPES and terrain.shape == (5, 6)
    np.testing.assert_array_equal(terrain.difficulty[:, 0], [0.0, 0.25, 0.5, 0.75, 1.0])


@pytest.mark.parametrize("kwargs, name", [
    ({"rows": 0}, "rows"), ({"resolution": -0.01}, "resolution"), ({"tile_size": 3.01}, "tile_size"),
    ({"platform": 3.0}, "platform"), ({"max_slope": 75.0}, "max_slope"), ({"step_height": (0.04, 0.01)},
                                                                        "step_height"),
    ({"step_width": 2.0}, "step_width"), ({"noise": (0.01,)}, "noise"), ({"noise_spacing": 0.01}, "noise_spacing"),
    ({"types": ("flat", "lava")}, "types"), ({"border": float("nan")}, "border"), ({"seed": 1.5}, "seed"),
])
def test_bad_parameters_raise_naming_the_parameter(kwargs, name):
    with pytest.raises(ValueError, match=name):
        generate_terrain(**kwargs)


def test_height_is_the_grid_at_its_points_and_continuous(small):
    """``surface_height`` at the grid points returns the heights exactly (u = v = 0); across every cell edge and
    diagonal it is continuous: points 1e-9 m either side of a random cell's edges differ by at most slope * 2e-9
    (the steepest cell: a 0.04 m step over 0.04 m, slope 1, so 1e-8 m bounds it)."""
    h = jnp.asarray(small.heights)
    res = small.resolution
    nrow, ncol = small.heights.shape
    X = (np.arange(ncol) - 0.5 * (ncol - 1)) * res
    Y = (np.arange(nrow) - 0.5 * (nrow - 1)) * res
    gx, gy = np.meshgrid(X, Y)
    np.testing.assert_allclose(np.asarray(surface_height(h, res, gx, gy)), small.heights, atol=ROUNDING)
    rng = np.random.default_rng(0)
    c, r = rng.integers(0, ncol - 1, 2000), rng.integers(0, nrow - 1, 2000)
    t = rng.uniform(0, 1, 2000)
    eps = 1e-9
    x0, y0 = X[c], Y[r]
    for px, py, dx, dy in ((x0, y0 + t * res, eps, 0.0), (x0 + t * res, y0, 0.0, eps),  # cell edges
                           (x0 + t * res, y0 + t * res, eps, -eps)):  # the diagonal between the two triangles
        a = np.asarray(surface_height(h, res, px - dx, py - dy))
        b = np.asarray(surface_height(h, res, px + dx, py + dy))
        assert np.max(np.abs(a - b)) < 1e-8


def test_height_is_where_the_contact_model_puts_the_surface(small):
    """A sphere of radius 0.05 m centred ``r / n_z`` above ``surface_height(x, y)`` (n the triangle's normal the
    contact model reports) touches the model's heightfield geom: the JAX reference's SPHERE-HFIELD distance is 0
    to rounding at 500 random points over the tiles. The geom is the one :func:`add_terrain` builds (heights
    normalised by their range, the geom at the lowest height), so this checks the heights and the triangles."""
    b = ModelBuilder()
    b.add_body(1.0, np.eye(3) * 1e-3)  # a model needs a body
    add_terrain(b, small)
    m = b.finalize()
    g = int(np.nonzero(m.geom_type == GeomType.HFIELD)[0][0])
    hf = HField(jnp.asarray(m.hfield_data), jnp.asarray(m.hfield_adr[0]), jnp.asarray(m.hfield_nrow[0]),
                jnp.asarray(m.hfield_ncol[0]), jnp.asarray(m.hfield_size[0]))
    pose_h = jnp.asarray(np.r_[m.geom_pos[g], m.geom_quat[g]])
    rng = np.random.default_rng(1)
    rx, ry = 0.5 * np.asarray(small.extent) - 1.0  # inside the border: the tiles
    x, y = rng.uniform(-rx, rx, 500), rng.uniform(-ry, ry, 500)
    z = np.asarray(surface_height(jnp.asarray(small.heights), small.resolution, x, y))
    radius = 0.05

    def contact(px, py, pz):
        cp = collide(GeomType.SPHERE, GeomType.HFIELD, jnp.array([px, py, pz, 0.0, 0.0, 0.0, 1.0]),
                     jnp.array([radius, 0.0, 0.0]), pose_h, jnp.zeros(3), 0.0, hfield=hf)
        return cp.dist[0], -cp.normal[0, 2]

    _, nz = jax.vmap(contact)(x, y, z + radius)
    dist, _ = jax.vmap(contact)(x, y, z + radius / nz)
    np.testing.assert_allclose(np.asarray(dist), 0.0, atol=1e-10)


# ---------------------------------------------------------------- the task (Warp backend)

#: a small terrain (2 rows: difficulty 0 and 1; flat and stairs_down) keeps the environment cheap to build
SMALL = {"rows": 2, "types": ["flat", "stairs_down"], "border": 1.0}
#: its tiles' ground heights (row-major): flat, stairs of 4 x 0.01 m, flat, stairs of 4 x 0.04 m
SMALL_Z = [0.0, 0.04, 0.0, 0.16]


@pytest.fixture(scope="module")
def rough():
    """The task on :data:`SMALL` with its curriculum, and 16 resets (one compilation for both tests)."""
    from kamino.envs import make

    env = make("dr_legs_rough", backend="warp", reset_bank=8, terrain=SMALL, curriculum=True)
    return env, jax.jit(jax.vmap(env.reset))(jax.random.split(jax.random.PRNGKey(0), 16))


def test_rough_resets_start_above_the_local_ground(rough):
    """Resets land on the 4 tiles, whose platforms are up to 0.16 m high. Every reset stands on its tile's
    origin: the base within 0.3 m (the platform's half side) of its centre, its lowest foot corner on the platform
    to float32 rounding (1e-5 m), the pelvis at its flat-ground height above the local ground (the heights the fall
    test reads), so no reset has fallen; ``with_tile`` moves a reset onto another tile. The observation is
    dr_legs_joystick's (48 entries, the same function)."""
    from kamino.envs.joystick import Joystick
    from kamino.spatial import rotate

    rough, s = rough
    assert rough.observation_size == 48 and type(rough)._observe is Joystick._observe
    origins = rough.tile_origins
    np.testing.assert_allclose(origins[:, 2], SMALL_Z, atol=ROUNDING)
    q = np.asarray(s.pipeline_state.body_q)
    base = q[:, rough._base, :3]
    tile = np.argmin(np.linalg.norm(base[:, None, :2] - origins[None, :, :2], axis=-1), axis=1)
    assert set(tile) == {0, 1, 2, 3}  # every tile drawn
    np.testing.assert_array_equal(np.asarray(s.info["tile"]), tile)  # the curriculum's record
    assert np.all(np.abs(base[:, :2] - origins[tile, :2]) < 0.3)
    pts, bodies, radii = rough._support
    lowest = [np.min(np.asarray(w[bodies, 2] + rotate(jnp.asarray(w[bodies, 3:]), jnp.asarray(pts, w.dtype))[:, 2])
                     - radii) for w in q]
    np.testing.assert_allclose(lowest, origins[tile, 2], atol=1e-5)
    above = np.asarray(jax.vmap(rough._above_ground)(jnp.asarray(base[:, 2]), jnp.asarray(base[:, :2])))
    np.testing.assert_allclose(above, base[:, 2] - origins[tile, 2], atol=1e-5)
    assert np.all(above > rough._min_height + 0.2)
    assert not np.any(np.asarray(jax.vmap(rough._terminated)(
        jax.vmap(rough.full_state)(s.pipeline_state), s.info)))
    moved = jax.vmap(rough.with_tile)(s, jnp.zeros(16, jnp.int32))  # everything onto the flat tile
    np.testing.assert_allclose(np.asarray(moved.pipeline_state.body_q[:, rough._base, 2]), base[:, 2] -
                               origins[tile, 2], atol=1e-5)


def test_curriculum_moves_one_row_by_the_episode_outcome(rough):
    """Isaac Lab's rule on the 2 x 2 tiles: walked far -> one row harder, fell (and not far) -> one row easier,
    else the same tile; the column (the terrain type) stays and the rows are clipped to ``levels``."""
    env, _ = rough
    tiles = jnp.array([0, 0, 1, 2, 3, 3, 2])
    far = jnp.array([True, False, False, True, False, True, False])
    fell = jnp.array([False, True, False, True, True, True, False])
    np.testing.assert_array_equal(np.asarray(jax.vmap(env.next_tile)(tiles, far, fell)), [2, 0, 1, 2, 1, 3, 2])


def test_rough_steps_run_stand_on_the_stairs_and_restart_on_the_next_tile(rough):
    """A few policy steps under jit + vmap (Warp backend) from the high stairs tile (3). At a restart (``steps`` 0,
    what brax's EpisodeWrapper writes after a reset) the curriculum moves an episode that fell to the row below
    (tile 1, 0.12 m lower), and keeps one that walked far on the top row (tile 3). Then at a zero action both
    robots stand on their platforms as on flat ground: the pelvis ends within 2 cm of its height above the local
    ground at reset (a robot standing on nothing would fall 0.12-0.16 m), and no episode ends. The two feet are two
    BOX-HFIELD pairs."""
    env, s = rough
    s = jax.vmap(env.with_tile)(jax.tree.map(lambda x: x[:2], s), jnp.full(2, 3, jnp.int32))
    s = s.replace(info={**s.info, "steps": jnp.zeros(2), "fell": jnp.array([True, True]),
                        "far": jnp.array([False, True])})
    above0 = np.asarray(s.pipeline_state.body_q[:, env._base, 2]) - 0.16
    step = jax.jit(jax.vmap(env.step))
    for _ in range(10):
        s = step(s, jnp.zeros((2, 12), jnp.float32))
        assert not np.any(np.asarray(s.done) > 0)
        s = s.replace(info={**s.info, "steps": s.info["steps"] + 1})
    np.testing.assert_array_equal(np.asarray(s.info["tile"]), [1, 3])
    base = np.asarray(s.pipeline_state.body_q[:, env._base, :3])
    np.testing.assert_allclose(base[:, :2], env.tile_origins[[1, 3], :2], atol=0.1)
    np.testing.assert_allclose(base[:, 2] - np.array([0.04, 0.16]), above0, atol=0.02)


def test_kamino_eval_scores_the_flat_policy_on_the_rough_task():
    """``kamino eval dr_legs_walk --task dr_legs_rough`` resolves the shipped flat policy onto the rough task (a
    subclass of its environment, with its observation), not onto an unrelated one; the rough test's bars are
    0.15 m/s and 5 %, on the rows of difficulty 0.5 to 1 of the default terrain."""
    from kamino.envs import DrLegsRough
    from kamino.envs.evaluate import resolve

    policy = resolve("dr_legs_walk", "dr_legs_rough")
    assert policy.task == "dr_legs_rough" and policy.observation_size == 50
    with pytest.raises(ValueError, match="trained on dr_legs_joystick"):
        resolve("dr_legs_walk", "bdx_joystick")
    assert DrLegsRough.walking_bars == (0.15, 0.05) and DrLegsRough.walking_levels == (2, 4)
    np.testing.assert_array_equal(generate_terrain().difficulty[2:5, 0], [0.5, 0.75, 1.0])
