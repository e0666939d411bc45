"""Rough terrain for legged tasks: a heightfield of square tiles, difficulty along one axis and terrain types along
the other (the tiled curriculum terrain of legged_gym and Isaac Lab), and the height of its surface in JAX.

:func:`generate_terrain` builds a :class:`Terrain` (NumPy, deterministic from its seed): ``rows x cols`` tiles of
``tile_size`` metres, row ``i`` at difficulty ``d_i = i / (rows - 1)`` (0 for one row) along world ``x``, column
``j`` of type ``types[j]`` along world ``y``, inside a flat border. Every tile has a flat square platform of side
``platform`` at its centre, where a robot starts (the tile's origin), and meets its neighbours at height 0 along
its edges (pyramid slopes and stairs start and end there), so the seams between tiles are continuous except for
the noise. The types, each a function of the distance ``r = max(|x - x_c|, |y - y_c|)`` from the tile's centre
(a square pyramid) beyond the platform, over the run ``R = tile_size / 2 - platform / 2`` to the edge:

- ``flat``: height 0;
- ``slope_up`` / ``slope_down``: a slope of ``max_slope * d`` degrees that rises (``up``) or falls (``down``) from
  the platform to the edge: the platform sits ``tan(slope) R`` below or above the edge;
- ``stairs_up`` / ``stairs_down``: steps of height ``step_height[0] + d (step_height[1] - step_height[0])`` and
  tread ``step_width`` from the edge inwards, ``floor(R / step_width)`` of them, rising or falling outwards;
- ``noise``: heights uniform in ``[-a/2, a/2]``, ``a = noise[0] + d (noise[1] - noise[0])``, drawn on a lattice of
  ``noise_spacing`` and interpolated bilinearly (a smooth bumpy ground, not a needle field), 0 on the platform.

"up" and "down" say what a robot walking out of the platform meets. :func:`add_terrain` puts a terrain in a
:class:`kamino.ModelBuilder` as one ``GeomType.HFIELD`` geom (in place of a ground plane);
:func:`surface_height` is the height of the contact model's surface at world ``(x, y)`` (JAX, traceable, the
triangles of kamino/jax_ref/collision.py, "Heightfields").

Sizes for ``dr_legs`` (:func:`kamino.models.dr_legs`: 0.28 m thigh and shank, box feet 0.20 x 0.09 x 0.035 m, a
gait clock that lifts a foot 0.05 m): steps of 1-4 cm stay below the swing lift and about the foot's height;
treads of 0.30 m hold a whole foot (1.5 foot lengths); slopes up to 12 degrees leave most of the ankle pitch's
+-0.6 rad range to the gait; the noise of 1-2 cm peak to peak on a 0.10 m lattice (half a foot) tilts the ground
under a foot by at most 11 degrees; a 0.04 m grid puts about 5 x 2 cells under a foot. The 4 m border keeps a
robot on the grid for 10 s at 0.5 m/s from any tile's origin (a point off the grid has no contact).
"""

from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np

from kamino.model import GeomType, ModelBuilder

#: the tile types :func:`generate_terrain` knows (its ``types`` argument takes any sequence of them)
TERRAIN_TYPES = ("flat", "slope_up", "slope_down", "stairs_up", "stairs_down", "noise")


@dataclasses.dataclass(frozen=True)
class Terrain:
    """A tiled heightfield (:func:`generate_terrain`).

    ``heights`` ``[nrow, ncol]``: world heights [m], row ``r`` at ``y = y0 + r * resolution``, column ``c`` at
    ``x = x0 + c * resolution``, ``(x0, y0) = -extent / 2`` (the grid is centred on the world origin).
    ``origins`` ``[rows, cols, 3]``: each tile's centre ``(x, y)`` and its ground height there; ``difficulty``
    ``[rows, cols]`` in ``[0, 1]``; ``types``: the type of each column; ``tile_size`` [m]."""

    heights: np.ndarray
    resolution: float
    origins: np.ndarray
    difficulty: np.ndarray
    types: tuple[str, ...]
    tile_size: float

    @property
    def shape(self) -> tuple[int, int]:
        """``(rows, cols)`` of tiles."""
        return self.origins.shape[:2]

    @property
    def extent(self) -> tuple[float, float]:
        """``(x, y)`` size of the grid [m]."""
        nrow, ncol = self.heights.shape
        return (ncol - 1) * self.resolution, (nrow - 1) * self.resolution

    def hfield(self) -> dict:
        """:meth:`kamino.ModelBuilder.add_hfield`'s arguments (``nrow``, ``ncol``, ``size``, ``elevation``) and the
        geom's position ``pos``: the heights span ``z_top = max - min`` above the geom at ``z = min`` (at least 1 mm
        for a flat grid, whose normalised heights are all 0), with a solid of 0.1 m below."""
        nrow, ncol = self.heights.shape
        lo, hi = float(self.heights.min()), float(self.heights.max())
        rx, ry = 0.5 * np.asarray(self.extent)
        return {"nrow": nrow, "ncol": ncol, "size": (float(rx), float(ry), max(hi - lo, 1e-3), 0.1),
                "elevation": self.heights, "pos": (0.0, 0.0, lo)}


def _check(name: str, value, low: float, *, integer: bool = False, strict: bool = True) -> None:
    ok = (not isinstance(value, bool) and isinstance(value, (int, np.integer)) if integer
          else isinstance(value, (int, float, np.floating, np.integer)) and not isinstance(value, bool)
          and math.isfinite(value))
    if not ok or (value <= low if strict else value < low):
        kind = "an integer" if integer else "a finite number"
        raise ValueError(f"generate_terrain: {name} must be {kind} {'>' if strict else '>='} {low:g}, got "
                         f"{value!r}")


def _range(name: str, value) -> tuple[float, float]:
    try:
        lo, hi = (float(v) for v in value)
    except (TypeError, ValueError):
        raise ValueError(f"generate_terrain: {name} must be a pair (LOW, HIGH) of numbers, got {value!r}") from None
    if not (math.isfinite(lo) and math.isfinite(hi) and 0 <= lo <= hi):
        raise ValueError(f"generate_terrain: {name} must be a pair (LOW, HIGH) with 0 <= LOW <= HIGH, got {value!r}")
    return lo, hi


def generate_terrain(*, rows: int = 5, types: tuple[str, ...] = TERRAIN_TYPES, tile_size: float = 3.0,
                     platform: float = 0.6, border: float = 4.0, resolution: float = 0.04, max_slope: float = 12.0,
                     step_height: tuple[float, float] = (0.01, 0.04), step_width: float = 0.3,
                     noise: tuple[float, float] = (0.01, 0.02), noise_spacing: float = 0.1,
                     seed: int = 0) -> Terrain:
    """A tiled rough terrain (the module doc describes the tiles; the defaults are sized for ``dr_legs``).

    Args:
        rows: difficulty levels (tile rows along ``x``), difficulty ``i / (rows - 1)`` in row ``i``.
        types: the type of each tile column (along ``y``), names from :data:`TERRAIN_TYPES` (repeats allowed).
        tile_size: side of a square tile [m]; a multiple of ``resolution`` (so that every tile has the same grid).
        platform: side of the flat square at each tile's centre [m], less than ``tile_size``.
        border: width of the flat border around the tiles [m] (>= 0).
        resolution: grid spacing [m].
        max_slope: the slope tiles' angle at difficulty 1 [degrees], in ``[0, 60]``.
        step_height: stair step height [m] at difficulty 0 and 1.
        step_width: stair tread [m], at most the run ``(tile_size - platform) / 2``.
        noise: peak-to-peak height of the noise [m] at difficulty 0 and 1.
        noise_spacing: the noise lattice's spacing [m], at least ``resolution``.
        seed: the noise's seed (the same arguments give the same terrain).

    Raises ``ValueError`` naming the argument that is out of range."""
    _check("rows", rows, 0, integer=True)
    _check("resolution", resolution, 0)
    _check("tile_size", tile_size, 0)
    _check("platform", platform, 0)
    _check("border", border, 0, strict=False)
    _check("max_slope", max_slope, 0, strict=False)
    _check("step_width", step_width, 0)
    _check("noise_spacing", noise_spacing, 0)
    _check("seed", seed, -1, integer=True)
    step_lo, step_hi = _range("step_height", step_height)
    noise_lo, noise_hi = _range("noise", noise)
    types = tuple(types) if not isinstance(types, str) else (types,)
    if not types or any(t not in TERRAIN_TYPES for t in types):
        raise ValueError(f"generate_terrain: types must be a non-empty sequence of {TERRAIN_TYPES}, got {types!r}")
    if max_slope > 60:
        raise ValueError(f"generate_terrain: max_slope must be at most 60 degrees, got {max_slope!r}")
    cells = tile_size / resolution
    if abs(cells - round(cells)) > 1e-6 * cells:
        raise ValueError(f"generate_terrain: tile_size ({tile_size}) must be a multiple of resolution "
                         f"({resolution})")
    if platform >= tile_size:
        raise ValueError(f"generate_terrain: platform ({platform}) must be less than tile_size ({tile_size})")
    run = 0.5 * (tile_size - platform)
    if step_width > run + 1e-12:
        raise ValueError(f"generate_terrain: step_width ({step_width}) must be at most the run from the platform to "
                         f"the tile's edge, (tile_size - platform) / 2 = {run:g}")
    if noise_spacing < resolution:
        raise ValueError(f"generate_terrain: noise_spacing ({noise_spacing}) must be at least resolution "
                         f"({resolution})")
    n_tile = round(cells)
    n_border = math.ceil(border / resolution - 1e-9)
    cols = len(types)
    nx, ny = rows * n_tile + 2 * n_border + 1, cols * n_tile + 2 * n_border + 1
    heights = np.zeros((ny, nx))  # [row = y, column = x], the hfield's order
    x0, y0 = -0.5 * (nx - 1) * resolution, -0.5 * (ny - 1) * resolution
    local = (np.arange(n_tile + 1) - 0.5 * n_tile) * resolution  # tile-local coordinates of its grid lines
    dist = np.maximum(np.abs(local)[None, :], np.abs(local)[:, None])  # [y, x] pyramid distance from the centre
    beyond = np.clip(0.5 * tile_size - dist, 0.0, run)  # distance inside the tile's edge, up to the platform
    rng = np.random.default_rng(seed)
    levels = np.linspace(0.0, 1.0, rows) if rows > 1 else np.zeros(1)
    origins = np.zeros((rows, cols, 3))
    for i, d in enumerate(levels):
        for j, kind in enumerate(types):
            if kind.startswith("slope"):
                tile = np.tan(np.deg2rad(max_slope * d)) * beyond
            elif kind.startswith("stairs"):
                tile = (step_lo + d * (step_hi - step_lo)) * np.floor(beyond / step_width + 1e-9)
            elif kind == "noise":
                tile = _noise(rng, n_tile, resolution, noise_spacing, noise_lo + d * (noise_hi - noise_lo))
                tile = np.where(dist <= 0.5 * platform + 1e-9, 0.0, tile)
            else:
                tile = np.zeros_like(dist)
            if kind.endswith("_up"):
                tile = -tile
            r0, c0 = n_border + j * n_tile, n_border + i * n_tile
            heights[r0:r0 + n_tile + 1, c0:c0 + n_tile + 1] = tile
            centre = np.array([x0 + (c0 + 0.5 * n_tile) * resolution, y0 + (r0 + 0.5 * n_tile) * resolution])
            origins[i, j] = [*centre, tile[n_tile // 2, n_tile // 2]]
    difficulty = np.broadcast_to(levels[:, None], (rows, cols)).copy()
    return Terrain(heights=heights, resolution=float(resolution), origins=origins, difficulty=difficulty,
                   types=types, tile_size=float(tile_size))


def _noise(rng: np.random.Generator, n_tile: int, resolution: float, spacing: float, amplitude: float) -> np.ndarray:
    """``[n_tile + 1, n_tile + 1]`` heights uniform in ``[-amplitude/2, amplitude/2]`` on a lattice of ``spacing``,
    interpolated bilinearly onto the grid; 0 along the tile's edges (it meets its neighbours at height 0)."""
    size = n_tile * resolution
    m = max(round(size / spacing), 1)
    lattice = rng.uniform(-0.5 * amplitude, 0.5 * amplitude, (m + 1, m + 1))
    lattice[0, :] = lattice[-1, :] = lattice[:, 0] = lattice[:, -1] = 0.0
    t = np.arange(n_tile + 1) * resolution / size * m  # grid positions in lattice units
    k = np.clip(np.floor(t).astype(int), 0, m - 1)
    f = t - k
    rows = lattice[k] * (1 - f)[:, None] + lattice[k + 1] * f[:, None]  # interpolate along y (rows)
    return rows[:, k] * (1 - f)[None, :] + rows[:, k + 1] * f[None, :]


def add_terrain(builder: ModelBuilder, terrain: Terrain, friction: float = 1.0, group: int = 1,
                name: str = "terrain") -> int:
    """Add ``terrain`` to ``builder`` as one world ``GeomType.HFIELD`` geom (its grid from :meth:`Terrain.hfield`);
    returns the geom's index. The terrain is the ground: a builder that already has a world PLANE geom raises
    ``ValueError`` (build the robot without its plane: ``kamino.models.dr_legs(ground=...)`` takes this function).
    ``friction`` and ``group`` as :meth:`kamino.ModelBuilder.add_geom` (group 1 is the robots' ground group)."""
    planes = [g.name for g in builder._geoms if g.type == GeomType.PLANE and g.body < 0]
    if planes:
        raise ValueError(f"add_terrain: the builder already has ground plane geoms {planes}; the terrain replaces "
                         "the ground plane (build the model without it)")
    hf = terrain.hfield()
    index = builder.add_hfield(hf["nrow"], hf["ncol"], hf["size"], hf["elevation"], name=name)
    return builder.add_geom(GeomType.HFIELD, -1, hfield=index, pos=hf["pos"], friction=friction, group=group,
                            name=name)


def surface_height(heights: jax.Array, resolution: float, x: jax.Array, y: jax.Array) -> jax.Array:
    """The terrain's height at world ``(x, y)`` (any matching shapes; traceable, no Python loops): the surface of
    the heightfield's contact model, each grid cell split along the diagonal from its ``(-x, -y)`` corner to its
    ``(+x, +y)`` corner into two planar triangles (MuJoCo's split; kamino/jax_ref/collision.py,
    ``_hfield_surface``). With ``u, v`` in ``[0, 1]`` across cell ``(r, c)``: ``z = h00 + u (h10 - h00) + v (h11 -
    h10)`` for ``u >= v``, else ``z = h00 + u (h11 - h01) + v (h01 - h00)`` (``h10`` the corner at ``c + 1``,
    ``h01`` at ``r + 1``): continuous, equal to ``heights`` at the grid points. ``heights`` ``[nrow, ncol]`` as in
    :class:`Terrain` (the grid centred on the world origin); off the grid the nearest edge's height."""
    nrow, ncol = heights.shape
    dtype = jnp.result_type(heights.dtype, x, y)
    fx = (x + 0.5 * (ncol - 1) * resolution) / resolution
    fy = (y + 0.5 * (nrow - 1) * resolution) / resolution
    c = jnp.clip(jnp.floor(fx), 0, ncol - 2).astype(jnp.int32)
    r = jnp.clip(jnp.floor(fy), 0, nrow - 2).astype(jnp.int32)
    u = jnp.clip(fx - c, 0.0, 1.0)
    v = jnp.clip(fy - r, 0.0, 1.0)
    h00, h10 = heights[r, c], heights[r, c + 1]
    h01, h11 = heights[r + 1, c], heights[r + 1, c + 1]
    lower = u >= v
    z = h00 + u * jnp.where(lower, h10 - h00, h11 - h01) + v * jnp.where(lower, h11 - h10, h01 - h00)
    return z.astype(dtype)


__all__ = ["TERRAIN_TYPES", "Terrain", "add_terrain", "generate_terrain", "surface_height"]
