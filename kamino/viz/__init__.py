"""Looking at a rollout: one world of a trajectory as an interactive HTML page or an animated GIF.

- :func:`html` writes a self-contained page that needs no network (three.js r170 carried inline, the trajectory
  embedded as JSON): bodies from their geoms, loop-closing joints highlighted, contacts, a time slider,
  play/pause and an orbit camera. Opens from disk in a browser, offline too.
- :func:`gif` writes a GIF (or MP4) through MuJoCo's renderer on the ``kamino.save_mjcf`` export of the world where
  an OpenGL context exists, else a matplotlib line drawing.
- :func:`world_model` is one world of a multi-world model as a single-world model (``kamino.concat``'s inverse).

For MuJoCo's interactive viewer: ``kamino.save_mjcf(model, "robot.xml")``, then
``python -m mujoco.viewer --mjcf=robot.xml``. docs/viz.md has the details.
"""

from kamino.viz._gif import RENDERERS, gif
from kamino.viz._html import html
from kamino.viz._scene import loop_joints
from kamino.viz._world import world_model

RENDERERS: tuple[str, ...]  # the imported tuple, declared here for its docstring in the API reference
"""The renderers :func:`gif` takes (``renderer=``): ``"auto"`` picks MuJoCo's when it can render, else matplotlib."""

__all__ = ["RENDERERS", "gif", "html", "loop_joints", "world_model"]
