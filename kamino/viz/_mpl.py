"""GIF frames drawn with matplotlib's 3D axes, for machines without an OpenGL context (CI, laptops over SSH).

A line drawing: each geom as its outline (box edges, circles and generatrices of capsules and cylinders, great
circles of spheres and ellipsoids, a grid for a plane), a body without geoms as a dot at its CoM with rods to its
joints' anchors, joint markers on both sides (loop-closing joints large and red), contacts as black dots. The
figure is drawn on an Agg canvas of its own (no pyplot, no backend change), one image per frame.
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import numpy as np

from kamino.model import GeomType, Model
from kamino.viz._mujoco import PALETTE
from kamino.viz._scene import Scene, pose_matrices

_BREAK = np.full((1, 3), np.nan)  # separates polylines within one Line3D
_DPI = 100


def _circle(radius_x: float, radius_y: float, z: float = 0.0, plane: str = "xy", n: int = 25) -> np.ndarray:
    """A closed ellipse of the given radii in a coordinate plane, offset by ``z`` along the third axis."""
    t = np.linspace(0.0, 2 * np.pi, n)
    a, b, c = radius_x * np.cos(t), radius_y * np.sin(t), np.full(n, z)
    pts = {"xy": (a, b, c), "xz": (a, c, b), "yz": (c, a, b)}[plane]
    return np.column_stack(pts)


def _join(parts: list[np.ndarray]) -> np.ndarray:
    """Polylines as one array with NaN rows between them."""
    out: list[np.ndarray] = []
    for p in parts:
        out.extend([p, _BREAK])
    return np.concatenate(out[:-1]) if out else np.zeros((0, 3))


def _box(s: np.ndarray) -> np.ndarray:
    corners = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], float) * s[:3]
    edges = [(a, b) for a in range(8) for b in range(a + 1, 8) if bin(a ^ b).count("1") == 1]
    return _join([corners[[a, b]] for a, b in edges])


def _round(radius: float, half: float, caps: bool) -> np.ndarray:
    """A cylinder (or capsule: ``caps``) of ``radius`` along z from ``-half`` to ``half``."""
    parts = [_circle(radius, radius, -half), _circle(radius, radius, half)]
    for angle in np.arange(4) * np.pi / 2:
        x, y = radius * np.cos(angle), radius * np.sin(angle)
        parts.append(np.array([[x, y, -half], [x, y, half]]))
    if caps:
        t = np.linspace(0.0, np.pi, 13)
        for sign in (-1.0, 1.0):
            arc = np.column_stack([radius * np.cos(t), np.zeros_like(t), sign * (half + radius * np.sin(t))])
            parts += [arc, arc[:, [1, 0, 2]]]
    return _join(parts)


def geom_outline(gtype: int, size: np.ndarray, plane_half: float = 1.0) -> np.ndarray:
    """Polylines of a geom in its own frame (MuJoCo size conventions), NaN rows between them."""
    g, s = GeomType(int(gtype)), np.asarray(size, float)
    if g in (GeomType.BOX, GeomType.HFIELD):  # a heightfield: the box of half-extents size that holds it
        return _box(s)
    if g in (GeomType.CAPSULE, GeomType.CYLINDER):
        return _round(s[0], s[1], caps=g == GeomType.CAPSULE)
    if g in (GeomType.SPHERE, GeomType.ELLIPSOID):
        a, b, c = (s[0], s[0], s[0]) if g == GeomType.SPHERE else s[:3]
        return _join([_circle(a, b, plane="xy"), _circle(a, c, plane="xz"), _circle(b, c, plane="yz")])
    ticks = np.linspace(-plane_half, plane_half, 9)  # PLANE: a grid
    return _join([np.array([[t, -plane_half, 0.0], [t, plane_half, 0.0]]) for t in ticks]
                 + [np.array([[-plane_half, t, 0.0], [plane_half, t, 0.0]]) for t in ticks])


def _geom_local(model: Model, g: int, scene: Scene) -> np.ndarray:
    """Geom ``g``'s outline in its body's frame (a plane's grid centred under the scene)."""
    _, rot = pose_matrices(np.concatenate([model.geom_pos[g], model.geom_quat[g]]))
    pos = np.asarray(model.geom_pos[g], float)
    pts = geom_outline(model.geom_type[g], model.geom_size[g], plane_half=1.5 * scene.radius)
    if GeomType(int(model.geom_type[g])) == GeomType.PLANE:
        under = rot.T @ (scene.center - pos)
        pts = pts + np.array([under[0], under[1], 0.0])
    return pts @ rot.T + pos


def _to_world(q: np.ndarray, local: np.ndarray) -> np.ndarray:
    """Points ``local`` of a body frame in world coordinates at pose ``q``."""
    pos, rot = pose_matrices(q)
    return local @ rot.T + pos


def _colour(b: int) -> tuple[float, float, float]:
    return PALETTE[b % len(PALETTE)]


class _Drawing:
    """The artists of one world, moved frame by frame."""

    def __init__(self, scene: Scene, ax: Any, show_joints: bool, show_contacts: bool):
        self.scene, self.ax = scene, ax
        m = scene.model
        self.geoms = []  # (body, local points, Line3D)
        for g in range(m.num_geoms):
            b = int(m.geom_body[g])
            local = _geom_local(m, g, scene)
            colour = (0.55, 0.57, 0.6) if b < 0 else _colour(b)
            (line,) = ax.plot(*local.T, color=colour, lw=1.0)
            self.geoms.append((b, local, line))
        self.rods = []  # (body, local points, Line3D): bodies without geoms
        for b in range(m.num_bodies):
            if not scene.has_geom[b]:
                local = _join([np.array([np.zeros(3), a]) for a in scene.links[b]] + [np.zeros((1, 3))])
                (line,) = ax.plot(*local.T, color=_colour(b), lw=3.0, marker="o", markevery=[len(local) - 1], ms=5)
                self.rods.append((b, local, line))
        self.joints = None
        if show_joints and m.num_joints:
            loops = np.zeros(m.num_joints, bool)
            loops[scene.loop_joints] = True
            self.loop_mask = np.concatenate([loops, loops])
            (plain,) = ax.plot([], [], [], ls="", marker="o", ms=3, color="0.2")
            (loop,) = ax.plot([], [], [], ls="", marker="o", ms=8, color=(0.88, 0.13, 0.11))
            self.joints = (plain, loop)
        self.contacts = ax.plot([], [], [], ls="", marker=".", ms=5, color="k")[0] if show_contacts else None
        self.clock = ax.text2D(0.02, 0.96, "", transform=ax.transAxes, fontsize=8)

    def _anchors(self, q: np.ndarray) -> np.ndarray:
        """World points of every joint's base-side anchors, then its follower-side anchors."""
        m = self.scene.model
        base, follower = [], []
        for j in range(m.num_joints):
            p, c = int(m.joint_parent[j]), int(m.joint_child[j])
            a_b = np.asarray(m.joint_anchor_B[j], float)
            base.append(a_b if p < 0 else _to_world(q[p], a_b))
            follower.append(_to_world(q[c], np.asarray(m.joint_anchor_F[j], float)))
        return np.array(base + follower)

    def show(self, k: int) -> None:
        """Move every artist to frame ``k``."""
        q = self.scene.body_q[k]
        for b, local, line in self.geoms + self.rods:
            if b >= 0:
                line.set_data_3d(*_to_world(q[b], local).T)
        if self.joints is not None:
            pts = self._anchors(q)
            self.joints[0].set_data_3d(*pts[~self.loop_mask].T)
            self.joints[1].set_data_3d(*pts[self.loop_mask].T)
        if self.contacts is not None:
            self.contacts.set_data_3d(*np.asarray(self.scene.contacts[k]).reshape(-1, 3).T)
        self.clock.set_text(f"t = {self.scene.time[k]:.3f} s (step {int(self.scene.steps[k])})")


def _figure(scene: Scene, width: int, height: int, azimuth: float, elevation: float) -> tuple[Any, Any, Any]:
    """A figure of ``width`` x ``height`` pixels on its own Agg canvas, with equal 3D axes around the motion."""
    try:
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.figure import Figure
    except ImportError as e:
        raise ImportError("kamino.viz.gif(renderer='matplotlib') needs matplotlib, which is not installed; install "
                          "the bench extra: pip install 'kamino[bench]'") from e
    fig = Figure(figsize=(width / _DPI, height / _DPI), dpi=_DPI)
    canvas = FigureCanvasAgg(fig)
    ax = fig.add_axes((0.0, 0.0, 1.0, 1.0), projection="3d")
    c, r = scene.center, scene.radius
    ax.set(xlim=(c[0] - r, c[0] + r), ylim=(c[1] - r, c[1] + r), zlim=(c[2] - r, c[2] + r))
    ax.set_box_aspect((1, 1, 1))
    ax.view_init(elev=-elevation, azim=azimuth - 180.0)  # MuJoCo's view direction -> matplotlib's camera place
    ax.tick_params(labelsize=6)
    ax.set_xlabel("x", fontsize=7)
    ax.set_ylabel("y", fontsize=7)
    ax.set_zlabel("z", fontsize=7)
    return fig, canvas, ax


def _pixels(canvas: Any, width: int, height: int) -> np.ndarray:
    """The canvas as ``[height, width, 3]`` uint8 (cropped or padded white if the canvas rounded its size)."""
    canvas.draw()
    rgba = np.asarray(canvas.buffer_rgba())
    out = np.full((height, width, 3), 255, np.uint8)
    h, w = min(height, rgba.shape[0]), min(width, rgba.shape[1])
    out[:h, :w] = rgba[:h, :w, :3]
    return out


def matplotlib_frames(scene: Scene, *, width: int, height: int, show_joints: bool, show_contacts: bool,
                      azimuth: float, elevation: float) -> Iterator[np.ndarray]:
    """Draw ``scene``'s frames as ``[height, width, 3]`` uint8 images (the figure is made by this call)."""
    fig, canvas, ax = _figure(scene, width, height, azimuth, elevation)
    drawing = _Drawing(scene, ax, show_joints, show_contacts)

    def frames() -> Iterator[np.ndarray]:
        for k in range(scene.num_frames):
            drawing.show(k)
            yield _pixels(canvas, width, height)
        fig.clear()

    return frames()
