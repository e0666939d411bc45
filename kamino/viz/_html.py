"""``kamino.viz.html``: a rollout as one self-contained, interactive HTML page (three.js, loaded from a CDN)."""

from __future__ import annotations

import html as _html
import importlib.resources
import json
import os
import re
from typing import Any

import numpy as np

from kamino.model import GeomType, JointType, Model
from kamino.viz._scene import AZIMUTH, ELEVATION, Scene, camera_position, make_scene

#: The page template (package data next to this module): the viewer's HTML, CSS and JavaScript.
TEMPLATE = "viewer.html"
#: What the template's placeholders are replaced by: the title (HTML-escaped) and the data (JSON).
_TITLE, _DATA = "__KAMINO_TITLE__", "__KAMINO_DATA__"
#: Version of the data embedded in the page (``data["format"]``).
DATA_FORMAT = "kamino.viz/1"


def _floats(a: Any) -> Any:
    """Nested lists of Python floats (``json`` writes each float64 as its shortest round-trip decimal)."""
    return np.asarray(a, dtype=float).tolist()


def _geoms(model: Model) -> list[dict[str, Any]]:
    """The world's geoms: MuJoCo size conventions, pose in the body's CoM frame (``body`` -1: the world frame)."""
    return [{"name": model.geom_names[g], "type": GeomType(int(model.geom_type[g])).name.lower(),
             "body": int(model.geom_body[g]), "size": _floats(model.geom_size[g]), "pos": _floats(model.geom_pos[g]),
             "quat": _floats(model.geom_quat[g])} for g in range(model.num_geoms)]


def _joints(model: Model, loops: list[int]) -> list[dict[str, Any]]:
    """The world's joints: bodies, anchors in each side's CoM frame (the world frame for ``parent`` -1), and
    whether the joint closes a loop."""
    loop_set = set(loops)
    return [{"name": model.joint_names[j], "type": JointType(int(model.joint_type[j])).name.lower(),
             "parent": int(model.joint_parent[j]), "child": int(model.joint_child[j]),
             "anchor_parent": _floats(model.joint_anchor_B[j]), "anchor_child": _floats(model.joint_anchor_F[j]),
             "loop": j in loop_set} for j in range(model.num_joints)]


def page_data(scene: Scene, *, title: str, show_joints: bool, show_contacts: bool) -> dict[str, Any]:
    """The JSON the page embeds (``<script type="application/json" id="kamino-data">``); see docs/viz.md."""
    m = scene.model
    frames: dict[str, Any] = {"step": [int(s) for s in scene.steps], "time": _floats(scene.time),
                              "body_q": _floats(scene.body_q)}
    if show_contacts:
        frames["contacts"] = [_floats(c) for c in scene.contacts]
    return {
        "format": DATA_FORMAT,
        "title": title,
        "world": scene.world,
        "num_worlds": scene.num_worlds,
        "bodies": [{"name": m.body_names[b], "has_geom": scene.has_geom[b], "links": _floats(scene.links[b])}
                   for b in range(m.num_bodies)],
        "geoms": _geoms(m),
        "joints": _joints(m, scene.loop_joints),
        "loop_joints": [m.joint_names[j] for j in scene.loop_joints],
        "show_joints": bool(show_joints),
        "show_contacts": bool(show_contacts),
        "camera": {"target": _floats(scene.center), "radius": scene.radius,
                   "position": _floats(camera_position(scene.center, scene.radius, AZIMUTH, ELEVATION))},
        "frames": frames,
    }


def _template() -> str:
    """The viewer template, read from the installed package (works in editable installs too)."""
    return importlib.resources.files("kamino.viz").joinpath(TEMPLATE).read_text(encoding="utf-8")


def _embed(data: dict[str, Any]) -> str:
    """``data`` as JSON that is safe inside a ``<script>`` element: every ``<`` is written ``\\u003c`` (still the
    same JSON), so no ``</script>`` or ``<!--`` can end the element early."""
    return json.dumps(data, allow_nan=False, separators=(",", ":")).replace("<", "\\u003c")


def html(model: Model, traj: Any, path: str | os.PathLike | None = None, *, world: int = 0, show_joints: bool = True,
         show_contacts: bool = True, fps: float | None = None, title: str | None = None) -> str:
    """One world of a rollout as a self-contained, interactive HTML page; returns the HTML and writes it to ``path``.

    Open the file in a browser (from disk, no server needed): the bodies drawn from the model's geoms (a body with
    no geom, like the links of ``kamino.models.fourbar()``, as a small sphere at its centre of mass with its frame
    axes and rods to its joints' anchors), a marker on both sides of every joint with the **loop-closing joints**
    large and red (the joints ``kamino.save_mjcf``'s spanning tree leaves out; two markers drifting apart show the
    loop opening), the active contact points as small black dots, a time slider, play/pause (space bar), a
    playback speed, and an orbit camera (drag to rotate, scroll to zoom, right-drag to pan). Playback runs in
    simulated time (``traj.time``).

    The page embeds its data as JSON (``<script type="application/json" id="kamino-data">``: every frame's body
    poses, exactly the trajectory's values; the layout is in docs/viz.md) and loads three.js as an ES module from
    a pinned CDN URL (``cdn.jsdelivr.net/npm/three@0.170.0``) through an import map, as Brax's HTML viewer does.
    The browser therefore needs the network the first time (then its cache); for a picture that needs none, use
    :func:`kamino.viz.gif`.

    Args:
        model: the model the trajectory was run on (any number of worlds).
        traj: the trajectory, a :class:`kamino.State` with a leading time axis (:func:`kamino.rollout`'s result).
        path: where to write the page (``None``: only return it).
        world: which world to draw (negative counts from the end).
        show_joints: draw the joint markers.
        show_contacts: draw the contact points (``traj.contacts``, the slots with ``pair >= 0``).
        fps: keep one frame per ``1 / fps`` of simulated time (smaller pages for long runs); ``None`` keeps
            every step.
        title: the page title (default: ``"kamino: world <world>"``).

    Returns:
        The HTML text.

    Raises:
        TypeError: ``model`` is not a Model, ``traj`` not a State, ``world`` not an integer.
        ValueError: ``traj`` has no time axis or was not run on ``model``, ``world`` is out of range, ``fps`` is not
            positive, or a pose of the world is not finite.
    """
    scene = make_scene(model, traj, world=world, fps=fps, fn="kamino.viz.html")
    title = title if title is not None else f"kamino: world {scene.world}"
    data = page_data(scene, title=title, show_joints=show_joints, show_contacts=show_contacts)
    fill = {_TITLE: _html.escape(title), _DATA: _embed(data)}
    text = re.sub("|".join(fill), lambda match: fill[match.group(0)], _template())  # one pass: no re-substitution
    if path is not None:
        with open(os.fspath(path), "w", encoding="utf-8") as f:
            f.write(text)
    return text
