"""MuJoCo's contact-pair rules, reproduced at build time (docs/mjcf.md, "Contacts").

MuJoCo checks a geom pair when it is an explicit ``<pair>``, or when all of these hold
(``engine_collision_driver.c``, MuJoCo's "Collision detection" documentation):

* the geoms' bodies are in different weld groups (bodies joined without joints are one group;
  the world and everything welded to it is group 0);
* unless ``filterparent`` is disabled: the weld groups are not parent and child, where a group
  whose parent is the world group is exempt (a link still touches the static floor);
* not both weld groups are without degrees of freedom (static and mocap geometry never touch);
* ``(contype1 & conaffinity2) || (contype2 & conaffinity1)``;
* the two bodies are not listed in a ``<contact><exclude>``.

The contact parameters of a pair: an explicit pair's own ``condim``/``friction``/``margin``/``gap``;
otherwise, if the geoms' ``priority`` differ, those of the higher-priority geom, else the larger
``condim`` and the larger friction, with ``margin`` and ``gap`` the larger of the two.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np


@dataclasses.dataclass(frozen=True)
class PairInfo:
    """One MuJoCo candidate geom pair and the contact parameters MuJoCo gives it."""

    geom1: int  # MuJoCo geom ids, geom1 < geom2
    geom2: int
    explicit: int  # index of the <pair> element, -1 for a pair from the contype/conaffinity rules
    condim: int
    friction: float  # sliding friction
    margin: float
    gap: float


def _pair_params(mj: Any, g1: int, g2: int) -> tuple[int, float, float, float]:
    p1, p2 = int(mj.geom_priority[g1]), int(mj.geom_priority[g2])
    if p1 != p2:
        g = g1 if p1 > p2 else g2
        condim, friction = int(mj.geom_condim[g]), float(mj.geom_friction[g, 0])
    else:
        condim = max(int(mj.geom_condim[g1]), int(mj.geom_condim[g2]))
        friction = max(float(mj.geom_friction[g1, 0]), float(mj.geom_friction[g2, 0]))
    margin = max(float(mj.geom_margin[g1]), float(mj.geom_margin[g2]))
    gap = max(float(mj.geom_gap[g1]), float(mj.geom_gap[g2]))
    return condim, friction, margin, gap


def candidate_pairs(mujoco: Any, mj: Any) -> list[PairInfo]:
    """All geom pairs MuJoCo would pass to its narrow phase (before the bounding-volume tests),
    sorted by ``(geom1, geom2)``; empty when contacts are disabled."""
    dis = int(mj.opt.disableflags)
    D = mujoco.mjtDisableBit
    if dis & int(D.mjDSBL_CONTACT) or dis & int(D.mjDSBL_CONSTRAINT):
        return []
    filterparent = not dis & int(D.mjDSBL_FILTERPARENT)
    weld = np.asarray(mj.body_weldid)
    parent = np.asarray(mj.body_parentid)
    weld_parent = weld[parent[weld]]
    movable = np.asarray(mj.body_dofnum)[weld] > 0  # per body: does its weld group have DoFs?
    body = np.asarray(mj.geom_bodyid)
    ctype, caff = np.asarray(mj.geom_contype), np.asarray(mj.geom_conaffinity)
    excluded = set()
    for sig in np.asarray(mj.exclude_signature).reshape(-1):
        b1, b2 = int(sig) >> 16, int(sig) & 0xFFFF
        excluded.add((min(b1, b2), max(b1, b2)))

    pairs: dict[tuple[int, int], PairInfo] = {}
    for g1 in range(mj.ngeom):
        if not (ctype[g1] or caff[g1]):
            continue
        for g2 in range(g1 + 1, mj.ngeom):
            b1, b2 = int(body[g1]), int(body[g2])
            w1, w2 = int(weld[b1]), int(weld[b2])
            if w1 == w2:
                continue
            if filterparent and w1 != 0 and w2 != 0 and (w1 == weld_parent[b2] or w2 == weld_parent[b1]):
                continue
            if not (movable[b1] or movable[b2]):
                continue
            if not ((ctype[g1] & caff[g2]) or (ctype[g2] & caff[g1])):
                continue
            if (min(b1, b2), max(b1, b2)) in excluded:
                continue
            pairs[(g1, g2)] = PairInfo(g1, g2, -1, *_pair_params(mj, g1, g2))
    for k in range(mj.npair):
        a, b = int(mj.pair_geom1[k]), int(mj.pair_geom2[k])
        g1, g2 = min(a, b), max(a, b)
        pairs[(g1, g2)] = PairInfo(g1, g2, k, int(mj.pair_dim[k]), float(mj.pair_friction[k, 0]),
                                   float(mj.pair_margin[k]), float(mj.pair_gap[k]))
    return [pairs[key] for key in sorted(pairs)]
