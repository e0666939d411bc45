"""``kamino.viz.html``: a rollout as one self-contained, interactive HTML page that needs no network."""

from __future__ import annotations

import functools
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
#: The JavaScript libraries every page carries inline (package data, MIT license in ``vendor/LICENSE``): the
#: template placeholder each fills, and its file under ``kamino/viz/``: three.js r170's minified ES module build and
#: its OrbitControls addon, both as npm's ``three@0.170.0`` ships them.
VENDOR = {"__KAMINO_THREE__": "vendor/three.module.min.js",
          "__KAMINO_ORBIT_CONTROLS__": "vendor/OrbitControls.js"}
#: What the template's placeholders are replaced by: the title (HTML-escaped) and the data (JSON).
_TITLE, _DATA = "__KAMINO_TITLE__", "__KAMINO_DATA__"
#: What would end or confuse the ``<script type="text/plain">`` element that carries a library (HTML's script data)
_SCRIPT_BREAKERS = re.compile(r"</script|<!--", re.IGNORECASE)
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


def _package_text(name: str) -> str:
    """A text file of the installed ``kamino.viz`` package (works in editable installs too)."""
    return importlib.resources.files("kamino.viz").joinpath(name).read_text(encoding="utf-8")


def _template() -> str:
    """The viewer template, read from the installed package."""
    return _package_text(TEMPLATE)


@functools.cache
def _vendor_scripts() -> dict[str, str]:
    """The inline libraries by placeholder (:data:`VENDOR`), read once per process (about 0.7 MB).

    Raises:
        RuntimeError: a library file holds ``</script`` or ``<!--``, which would end its element early (the files
            npm ships hold neither: a changed file is not the vendored one).
    """
    scripts = {}
    for placeholder, name in VENDOR.items():
        text = _package_text(name)
        if _SCRIPT_BREAKERS.search(text):
            raise RuntimeError(f"kamino/viz/{name} contains '</script' or '<!--' and cannot be inlined in a page; "
                               "reinstall kamino to restore the vendored file")
        scripts[placeholder] = text
    return scripts


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

    The page needs no network: it embeds its data as JSON (``<script type="application/json" id="kamino-data">``:
    every frame's body poses, exactly the trajectory's values; the layout is in docs/viz.md) and carries three.js
    r170 (its minified ES module build and the OrbitControls addon, MIT license, vendored in ``kamino/viz/vendor``)
    inline, so it opens offline and on a cluster node. The libraries add about 0.73 MB to every page; the data adds
    about 150 bytes per body and frame (``fps`` thins the frames).

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
    fill = {_TITLE: _html.escape(title), _DATA: _embed(data), **_vendor_scripts()}
    text = re.sub("|".join(fill), lambda match: fill[match.group(0)], _template())  # one pass: no re-substitution
    if path is not None:
        with open(os.fspath(path), "w", encoding="utf-8") as f:
            f.write(text)
    return text
