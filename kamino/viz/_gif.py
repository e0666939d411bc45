"""``kamino.viz.gif``: a rollout as an animated GIF (or MP4), through MuJoCo's renderer or matplotlib."""

from __future__ import annotations

import numbers
import os
import pathlib
import warnings
from collections.abc import Iterable
from typing import Any

import numpy as np

from kamino.model import Model
from kamino.viz._mpl import matplotlib_frames
from kamino.viz._mujoco import RendererUnavailable, mujoco_frames
from kamino.viz._scene import AZIMUTH, ELEVATION, Scene, make_scene

RENDERERS = ("auto", "mujoco", "matplotlib")
_FN = "kamino.viz.gif"


def _check_size(width: Any, height: Any, mp4: bool) -> tuple[int, int]:
    for name, v in (("width", width), ("height", height)):
        if isinstance(v, bool) or not isinstance(v, numbers.Integral) or v < 16:
            raise ValueError(f"{_FN}: {name} must be an integer number of pixels >= 16, got {v!r}")
        if mp4 and v % 2:
            raise ValueError(f"{_FN}: an MP4 (H.264, yuv420p) needs an even {name}, got {v}")
    return int(width), int(height)


def _check_path(path: str | os.PathLike) -> tuple[pathlib.Path, bool]:
    """The output path and whether it is an MP4; ``.gif`` or ``.mp4`` only (MP4 needs imageio-ffmpeg)."""
    p = pathlib.Path(os.fspath(path))
    suffix = p.suffix.lower()
    if suffix not in (".gif", ".mp4"):
        raise ValueError(f"{_FN}: path must end in .gif or .mp4, got {str(p)!r}")
    if suffix == ".mp4":
        try:
            import imageio_ffmpeg  # noqa: F401
        except ImportError as e:
            raise ImportError(f"{_FN}: writing an MP4 needs imageio-ffmpeg (pip install imageio-ffmpeg); a .gif needs "
                              "nothing more") from e
    return p, suffix == ".mp4"


def _write_gif(path: pathlib.Path, frames: Iterable[np.ndarray], fps: float) -> int:
    """Frames as a looping GIF (Pillow; consecutive identical frames are merged, their durations added)."""
    from PIL import Image

    images = [Image.fromarray(f) for f in frames]
    images[0].save(path, save_all=True, append_images=images[1:], duration=round(1000.0 / fps), loop=0)
    return len(images)


def _write_mp4(path: pathlib.Path, frames: Iterable[np.ndarray], fps: float, size: tuple[int, int]) -> int:
    """Frames as an H.264 MP4 through imageio-ffmpeg's bundled ffmpeg."""
    import imageio_ffmpeg

    writer = imageio_ffmpeg.write_frames(str(path), size, fps=fps, codec="libx264", pix_fmt_out="yuv420p",
                                         macro_block_size=1)
    writer.send(None)
    count = 0
    try:
        for f in frames:
            writer.send(np.ascontiguousarray(f))
            count += 1
    finally:
        writer.close()
    return count


def _frames(scene: Scene, renderer: str, options: dict[str, Any]) -> tuple[str, Iterable[np.ndarray]]:
    """``(renderer used, frames)``: MuJoCo when asked or, for ``"auto"``, when it can draw here; else matplotlib."""
    if renderer in ("auto", "mujoco"):
        try:
            return "mujoco", mujoco_frames(scene, **options)
        except RendererUnavailable as e:
            if renderer == "mujoco":
                raise RuntimeError(f"{_FN}(renderer='mujoco'): {e}") from e
            warnings.warn(f"{_FN}: drawing with matplotlib: {e}", RuntimeWarning, stacklevel=3)
    return "matplotlib", matplotlib_frames(scene, **options)


def gif(model: Model, traj: Any, path: str | os.PathLike, *, world: int = 0, fps: float = 30.0,
        renderer: str = "auto", width: int = 480, height: int = 360, show_joints: bool = True,
        show_contacts: bool = True, azimuth: float = AZIMUTH, elevation: float = ELEVATION) -> str:
    """One world of a rollout as an animated GIF (or an MP4 if ``path`` ends in ``.mp4``), for offline viewing.

    The frames play in simulated time: one frame per ``1 / fps`` of ``traj.time`` (the last step at or before it).

    - ``renderer="mujoco"``: MuJoCo's renderer (``mujoco.Renderer``) on the ``kamino.save_mjcf`` export of the
      world, flattened so that every body carries a free joint and ``qpos`` is exactly kamino's body pose (the
      exported body frame is the kamino CoM frame; ``kamino/viz/_mujoco.py``). Needs an OpenGL context:
      ``MUJOCO_GL=egl`` (GPU or Mesa) or ``osmesa`` on a machine without a display, set before ``mujoco`` is
      imported.
    - ``renderer="matplotlib"``: a line drawing on matplotlib's 3D axes (geom outlines; bodies without geoms as
      rods from the CoM to their joints' anchors); needs only matplotlib (the ``bench`` extra).
    - ``renderer="auto"`` (default): MuJoCo when it can open a context and export the world, else matplotlib with
      a ``RuntimeWarning`` saying why.

    Both draw joint markers (loop-closing joints large and red) and contact points as the HTML page does
    (:func:`kamino.viz.html`).

    Args:
        model: the model the trajectory was run on (any number of worlds).
        traj: the trajectory, a :class:`kamino.State` with a leading time axis (:func:`kamino.rollout`'s result).
        path: the file to write, ``.gif`` (Pillow) or ``.mp4`` (needs ``imageio-ffmpeg``).
        world: which world to draw (negative counts from the end).
        fps: frames per second, of simulated time and of playback (GIF delays are whole centiseconds, and
            browsers slow down delays under 20 ms: keep ``fps <= 50``).
        renderer: ``"auto"``, ``"mujoco"`` or ``"matplotlib"``.
        width, height: the image size [pixels].
        show_joints, show_contacts: draw the joint markers, the contact points.
        azimuth, elevation: the view direction [deg], MuJoCo's free-camera convention (default: along +y, from
            20 degrees above, the plane of ``kamino.models``' planar mechanisms).

    Returns:
        The renderer used: ``"mujoco"`` or ``"matplotlib"``.

    Raises:
        TypeError, ValueError: as :func:`kamino.viz.html` for the model, trajectory, world and ``fps``; a path that
            is not ``.gif``/``.mp4``; a bad size.
        ImportError: an MP4 without imageio-ffmpeg; matplotlib needed but not installed.
        RuntimeError: ``renderer="mujoco"`` where MuJoCo cannot draw (no OpenGL context, or no MJCF export).
    """
    if renderer not in RENDERERS:
        raise ValueError(f"{_FN}: renderer must be one of {RENDERERS}, got {renderer!r}")
    if fps is None:
        raise ValueError(f"{_FN}: fps must be a positive number of frames per second, got None")
    out, mp4 = _check_path(path)
    width, height = _check_size(width, height, mp4)
    scene = make_scene(model, traj, world=world, fps=fps, fn=_FN, unique=False)
    options = {"width": width, "height": height, "show_joints": show_joints, "show_contacts": show_contacts,
               "azimuth": float(azimuth), "elevation": float(elevation)}
    used, frames = _frames(scene, renderer, options)
    if mp4:
        _write_mp4(out, frames, float(fps), (width, height))
    else:
        _write_gif(out, frames, float(fps))
    return used
