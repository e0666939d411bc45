"""One world of a multi-world :class:`~kamino.Model` as a single-world model (the inverse of ``kamino.concat``).

``kamino.viz`` draws one world; the MJCF export (``kamino.save_mjcf``) and its spanning tree take a single-world
model. Storage is flat over worlds with ``world_<entity>_start/count`` segments (docs/conventions.md, "Data
layout"), so a world is a slice of every per-entity array with its index fields shifted back to the world's own
numbering (the shifts ``concat`` applies, read from ``kamino.model._INDEX_FIELDS``).
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

from kamino.model import _INDEX_FIELDS, Model

#: Field-name prefix -> the entity whose ``world_<entity>_start/count`` segment the field is sliced by.
_ENTITY_OF_PREFIX = {"body": "body", "joint": "joint", "dof": "dof", "geom": "geom", "pair": "pair",
                     "coupling": "coupling", "actuator": "actuator", "hfield": "hfield"}
#: ``joint_<x>_start`` fields: offsets into the DoF, coordinate and row arrays, recomputed from their counts.
_JOINT_OFFSETS = ("joint_dof_start", "joint_coord_start", "joint_cts_start")


def _prefix(counts: np.ndarray) -> np.ndarray:
    """Exclusive prefix sum: the start offsets of consecutive segments of ``counts``."""
    counts = np.asarray(counts, dtype=np.int64)
    return (np.cumsum(counts) - counts).astype(np.int64)


def _segment(model: Model, entity: str, world: int) -> slice:
    """The slice of ``world``'s entities in the flat per-entity arrays."""
    start = int(getattr(model, f"world_{entity}_start")[world])
    return slice(start, start + int(getattr(model, f"world_{entity}_count")[world]))


def _shift_back(model: Model, name: str, value: np.ndarray, world: int) -> np.ndarray:
    """An index field of one world renumbered from the global to the world's own numbering (-1 stays -1)."""
    target = _INDEX_FIELDS.get(name)
    if target is None:
        return value
    if target == "world":
        return np.zeros_like(value)
    offset = int(getattr(model, f"world_{target}_start")[world])
    return np.where(value >= 0, value - offset, value) if target in ("body", "joint", "hfield") else value - offset


def _world_field(model: Model, name: str, world: int) -> Any:
    """Field ``name`` of the single-world model of ``world``."""
    value = getattr(model, name)
    if name == "num_worlds":
        return 1
    if name.startswith("world_"):
        return np.zeros(1, np.int64) if name.endswith("_start") else np.asarray(value[world:world + 1]).copy()
    if name == "gravity":
        return np.asarray(value[world:world + 1]).copy()
    entity = "hfield_data" if name == "hfield_data" else _ENTITY_OF_PREFIX.get(name.split("_", 1)[0])
    if entity is None:
        raise AssertionError(f"kamino.viz: Model field {name!r} has no known entity (update kamino/viz/_world.py)")
    part = value[_segment(model, entity, world)]
    if isinstance(part, tuple):
        return part
    return _shift_back(model, name, np.asarray(part).copy(), world)


def world_model(model: Model, world: int) -> Model:
    """World ``world`` of ``model`` as a single-world :class:`~kamino.Model` (``concat`` of every world's model is
    ``model`` again). Global body, joint, geom and DoF indices become the world's own (``-1`` stays the world)."""
    if not 0 <= world < model.num_worlds:
        raise ValueError(f"world {world} is out of range for a model of {model.num_worlds} world(s)")
    out = {f.name: _world_field(model, f.name, world) for f in dataclasses.fields(Model)}
    for name in _JOINT_OFFSETS:
        out[name] = _prefix(out[name.replace("_start", "_count")])
    single = Model(**out)
    for f in dataclasses.fields(single):
        v = getattr(single, f.name)
        if isinstance(v, np.ndarray):
            v.flags.writeable = False
    return single
