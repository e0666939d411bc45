"""``dr_legs_rough``: the ``dr_legs_joystick`` task on a tiled rough terrain (docs/envs.md, "Rough terrain").

:class:`DrLegsRough` is :class:`kamino.envs.joystick.DrLegsJoystick` with a heightfield of
:func:`kamino.envs.terrain.generate_terrain` in place of the ground plane. What changes:

- **Resets** put the robot on the platform at the centre of a tile drawn uniformly from the tiles of the difficulty
  rows ``levels`` (its feet on the platform, at the tile's ground height), with the flat task's uniform heading.
  Brax's ``AutoResetWrapper`` restarts an episode from its first reset, so in training every environment keeps
  its tile; a batch of environments covers the tiles uniformly.
- **A curriculum** (``curriculum=True``; Isaac Lab's terrain-levels rule): an episode whose robot walked farther
  than half a tile from its origin restarts one row harder, one that ended in a fall without walking that far one
  row easier (within ``levels``; the column, the terrain type, stays). Brax's ``AutoResetWrapper`` restores the
  first reset's state; the first step after it (``info["steps"] == 0``, as :class:`kamino.envs.base.KaminoEnv`
  detects a restart) moves that state rigidly onto the new tile (``info["tile"]``).
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
        curriculum: move an environment between rows at its restarts (the module doc); ``info`` then carries
            ``tile`` (its index into :attr:`tile_origins`), ``far`` and ``fell`` (the running episode's outcome).
        **kwargs: :class:`kamino.envs.joystick.DrLegsJoystick`.
    """

    #: the rough walking test's bars: mean tracking error [m/s] and fall fraction (docs/envs.md, "dr_legs_rough")
    walking_bars = (0.15, 0.05)
    #: the rough walking test's difficulty rows (``levels``) of the default terrain: difficulty 0.5 to 1
    walking_levels = (2, 4)

    def __init__(self, *, terrain: dict | None = None, levels: tuple[int, int] | None = None,
                 curriculum: bool = False, **kwargs):
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
        self._curriculum = bool(curriculum)
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

    def _tile_of(self, body_q: jax.Array) -> jax.Array:
        """The index of the reset tile whose origin is nearest the base body's ``(x, y)``."""
        origins = jnp.asarray(self._origins[:, :2], body_q.dtype)
        return jnp.argmin(jnp.sum((origins - body_q[self._base, :2]) ** 2, axis=-1)).astype(jnp.int32)

    def next_tile(self, tile: jax.Array, far: jax.Array, fell: jax.Array) -> jax.Array:
        """The curriculum's tile after an episode on ``tile`` (an index into :attr:`tile_origins`): one row harder
        if the robot walked ``far`` (beyond half a tile from the origin), one row easier if it ``fell`` and did not
        walk far, the same column, clipped to the rows of ``levels``."""
        cols = self._terrain.shape[1]
        rows = self.num_tiles // cols
        row = tile // cols + jnp.where(far, 1, jnp.where(fell, -1, 0))
        return (jnp.clip(row, 0, rows - 1) * cols + tile % cols).astype(jnp.int32)

    def reset(self, rng: jax.Array):
        """The flat task's reset on a random tile (:meth:`_move_rigidly`); with the curriculum, ``info`` also holds
        ``tile``, ``far`` and ``fell``."""
        state = super().reset(rng)
        if not self._curriculum:
            return state
        info = dict(state.info, tile=self._tile_of(state.pipeline_state.body_q), far=jnp.zeros((), bool),
                    fell=jnp.zeros((), bool))
        return state.replace(info=info)

    def step(self, state, action: jax.Array):
        """The flat task's step; with the curriculum, a restarted episode (``info["steps"] == 0``) first moves onto
        :meth:`next_tile` of the one that ended, and the step records whether the robot walked far or fell."""
        if not self._curriculum:
            return super().step(state, action)
        info = dict(state.info)
        if "steps" in info:  # brax's EpisodeWrapper: 0 right after an (auto-)reset restored the first reset's state
            restarted = info["steps"] == 0
            body_q = state.pipeline_state.body_q
            tile = jnp.where(restarted, self.next_tile(info["tile"], info["far"], info["fell"]), info["tile"])
            origins = jnp.asarray(self._origins, body_q.dtype)
            shift = jnp.where(restarted, origins[tile] - origins[self._tile_of(body_q)], 0.0)
            state = state.replace(pipeline_state=state.pipeline_state.replace(body_q=body_q.at[:, :3].add(shift)))
            info.update(tile=tile, far=info["far"] & ~restarted, fell=info["fell"] & ~restarted)
        state = super().step(state.replace(info=info), action)
        body_q = state.pipeline_state.body_q
        walked = jnp.linalg.norm(body_q[self._base, :2] - jnp.asarray(self._origins[:, :2], body_q.dtype)[info["tile"]])
        far = info["far"] | (walked > 0.5 * self._terrain.tile_size)
        return state.replace(info=dict(state.info, far=far, fell=info["fell"] | (state.done > 0)))

    def with_tile(self, state, tile):
        """``state`` (one environment, right after :meth:`reset`) moved rigidly onto tile ``tile`` (an index into
        :attr:`tile_origins`; may be traced): every body translated by the difference of the two tiles' origins,
        which keeps the robot's pose on the flat platform. For evaluations spread over the tiles
        (:func:`kamino.envs.evaluate.walking_test`)."""
        body_q = state.pipeline_state.body_q
        origins = jnp.asarray(self._origins, body_q.dtype)
        body_q = body_q.at[:, :3].add(origins[tile] - origins[self._tile_of(body_q)])
        state = state.replace(pipeline_state=state.pipeline_state.replace(body_q=body_q))
        if self._curriculum:
            state = state.replace(info=dict(state.info, tile=jnp.asarray(tile, jnp.int32)))
        return state


__all__ = ["DrLegsRough"]
