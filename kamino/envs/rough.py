"""``dr_legs_rough``: the ``dr_legs_joystick`` task on a tiled rough terrain (docs/envs.md, "Rough terrain").

:class:`DrLegsRough` is :class:`kamino.envs.joystick.DrLegsJoystick` with a heightfield of
:func:`kamino.envs.terrain.generate_terrain` in place of the ground plane. What changes:

- **Resets** put the robot on the platform at the centre of a tile drawn uniformly from the tiles of the difficulty
  rows ``levels`` (its feet on the platform, at the tile's ground height), with the flat task's uniform heading.
  Brax's ``AutoResetWrapper`` restarts an episode from its first reset, so in training every environment keeps
  its tile; a batch of environments covers the tiles uniformly.
- **Heights** are measured from the terrain below (:meth:`DrLegsRough._above_ground`, the contact model's
  surface at the point's ``(x, y)``: :func:`kamino.envs.terrain.surface_height`): the fall test's ``min_height``
  (the base CoM above the ground below it), a foot's contact height and its lift for ``feet_phase``.
- **Nothing else**: the observation (blind, proprioceptive), actions, rewards and commands are the flat task's, so
  a policy of one runs on the other (the shipped ``dr_legs_walk`` is the rough task's baseline and starting point).

A robot that walks off the grid (past the flat border) has no contact and falls: its base drops below
``min_height`` over the border's height and the episode ends as a fall.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from kamino.envs.joystick import DrLegsJoystick
from kamino.envs.terrain import Terrain, add_terrain, generate_terrain, surface_height
from kamino.model import Model
from kamino.models import dr_legs


class DrLegsRough(DrLegsJoystick):
    """``dr_legs_rough``: ``dr_legs_joystick`` on rough terrain (the module doc).

    Args:
        terrain: keywords of :func:`kamino.envs.terrain.generate_terrain` (default: its defaults, sized for
            dr_legs: 5 difficulty rows x 6 types of 3 m tiles, 0.04 m grid).
        levels: ``(LOW, HIGH)``, the difficulty rows (0 to ``rows - 1``, both included) whose tiles resets draw
            from (default: all rows).
        **kwargs: :class:`kamino.envs.joystick.DrLegsJoystick` (``backend="jax"``: the Warp backend has no
            heightfield contact yet).
    """

    #: the rough walking test's bars: mean tracking error [m/s] and fall fraction (docs/envs.md, "Rough terrain")
    walking_bars = (0.15, 0.05)

    def __init__(self, *, terrain: dict | None = None, levels: tuple[int, int] | None = None, **kwargs):
        name = type(self).__name__
        if terrain is not None and not isinstance(terrain, dict):
            raise TypeError(f"{name}: terrain must be a dict of generate_terrain keywords, got "
                            f"{type(terrain).__name__}")
        try:
            self._terrain = generate_terrain(**(terrain or {}))
        except TypeError as exc:
            raise TypeError(f"{name}: terrain has a keyword generate_terrain does not take ({exc})") from None
        rows = self._terrain.shape[0]
        lo, hi = (0, rows - 1) if levels is None else levels
        if not (isinstance(lo, (int, np.integer)) and isinstance(hi, (int, np.integer)) and 0 <= lo <= hi < rows):
            raise ValueError(f"{name}: levels must be (LOW, HIGH) with 0 <= LOW <= HIGH <= {rows - 1} (the terrain's "
                             f"difficulty rows), got {levels!r}")
        self._levels = (int(lo), int(hi))
        self._origins = self._terrain.origins[lo:hi + 1].reshape(-1, 3)
        self._tile_difficulty = self._terrain.difficulty[lo:hi + 1].reshape(-1)
        super().__init__(**kwargs)
        self._heights = jnp.asarray(self._terrain.heights, self.dtype)

    @property
    def terrain(self) -> Terrain:
        """The :class:`kamino.envs.terrain.Terrain` the robot walks on."""
        return self._terrain

    @property
    def num_tiles(self) -> int:
        """The tiles resets draw from (those of the rows ``levels``)."""
        return len(self._origins)

    @property
    def tile_origins(self) -> np.ndarray:
        """``[num_tiles, 3]`` the reset tiles' origins (centre and ground height), row-major over ``levels``."""
        return self._origins.copy()

    @property
    def tile_difficulty(self) -> np.ndarray:
        """``[num_tiles]`` the reset tiles' difficulty in ``[0, 1]``."""
        return self._tile_difficulty.copy()

    def _robot(self, **gains) -> Model:
        """``kamino.models.dr_legs(**gains)`` on the terrain (one heightfield geom, no ground plane)."""
        return dr_legs(ground=lambda builder: add_terrain(builder, self._terrain), **gains)

    def _above_ground(self, z: jax.Array, xy: jax.Array) -> jax.Array:
        """``z`` minus the terrain's height at ``xy`` (:func:`kamino.envs.terrain.surface_height`)."""
        return z - surface_height(self._heights, self._terrain.resolution, xy[..., 0], xy[..., 1])

    def _move_rigidly(self, body_q: jax.Array, rng: jax.Array) -> jax.Array:
        """The flat task's uniform heading, then the whole robot moved onto a uniformly drawn tile's origin."""
        k_turn, k_tile = jax.random.split(rng)
        body_q = super()._move_rigidly(body_q, k_turn)
        tile = jax.random.randint(k_tile, (), 0, self.num_tiles)
        return body_q.at[:, :3].add(jnp.asarray(self._origins, body_q.dtype)[tile])

    def with_tile(self, state, tile):
        """``state`` (one environment, right after :meth:`reset`) moved rigidly onto tile ``tile`` (an index into
        :attr:`tile_origins`; may be traced): every body translated by the difference of the two tiles' origins,
        which keeps the robot's pose on the flat platform. For evaluations spread over the tiles
        (:func:`kamino.envs.evaluate.walking_test`)."""
        origins = jnp.asarray(self._origins, state.pipeline_state.body_q.dtype)
        body_q = state.pipeline_state.body_q
        base = body_q[self._base, :2]
        here = jnp.argmin(jnp.sum((origins[:, :2] - base) ** 2, axis=-1))
        body_q = body_q.at[:, :3].add(origins[tile] - origins[here])
        return state.replace(pipeline_state=state.pipeline_state.replace(body_q=body_q))


__all__ = ["DrLegsRough"]
