"""GIF frames through MuJoCo's renderer (``mujoco.Renderer``) on the ``kamino.save_mjcf`` export of one world.

The export is a kinematic tree plus equalities; to show kamino's poses *exactly* (a loop that opens by 1 mm shows
as 1 mm, whatever the tree), the drawing model flattens it: every exported body moves to the world body with a
free joint of its own (the exported body frame is the kamino CoM frame, so a body's ``qpos`` is its kamino pose,
quaternion reordered to ``w, x, y, z``), and the equalities, actuators and contact rules go. ``mj_kinematics`` then
places every geom. Bodies without geoms get visual-only stand-ins (a sphere and rods to their joints' anchors),
joints their markers (loop-closing ones larger and red), as in the HTML page; contacts are added to the scene.
"""

from __future__ import annotations

import warnings
import xml.etree.ElementTree as ET
from collections.abc import Iterator

import numpy as np

from kamino.io.mjcf_export import _fmt
from kamino.viz._scene import Scene, camera_distance

#: Body colours (RGB 0..1), the HTML page's palette (Tableau 10).
PALETTE = ((0.306, 0.475, 0.655), (0.949, 0.557, 0.169), (0.349, 0.631, 0.310), (0.690, 0.478, 0.631),
           (0.463, 0.718, 0.698), (0.929, 0.788, 0.282), (1.0, 0.616, 0.655), (0.612, 0.459, 0.373),
           (0.729, 0.690, 0.675), (0.882, 0.341, 0.349))
_WORLD_RGBA, _FLOOR_RGBA = "0.6 0.63 0.65 1", "0.72 0.74 0.77 1"
_JOINT_RGBA, _LOOP_RGBA, _CONTACT_RGBA = "0.2 0.2 0.2 1", "0.88 0.13 0.11 1", (0.07, 0.07, 0.07, 1.0)
#: Sizes relative to the motion's radius: stand-in sphere, rods, joint markers, loop markers, contact points.
SPHERE, ROD, JOINT, LOOP, CONTACT = 0.03, 0.012, 0.018, 0.035, 0.012
_DROPPED_SECTIONS = ("equality", "actuator", "contact", "tendon", "sensor", "keyframe")


class RendererUnavailable(RuntimeError):
    """MuJoCo cannot draw this scene here: no OpenGL context, or the world has no MJCF export."""


def _rgba(b: int) -> str:
    return " ".join(f"{c:g}" for c in (*PALETTE[b % len(PALETTE)], 1.0))


def _visual_geom(parent: ET.Element, kind: str, rgba: str, size: float, **attrs: str) -> None:
    """A visual-only geom (collides with nothing) on ``parent``."""
    ET.SubElement(parent, "geom", type=kind, size=_fmt(size), rgba=rgba, contype="0", conaffinity="0", group="1",
                  **attrs)


def _flatten(worldbody: ET.Element, root: ET.Element) -> dict[str, ET.Element]:
    """Every exported body moved to the world body with a free joint and a unit inertia; by name."""
    parents = {child: parent for parent in root.iter() for child in parent}
    bodies = list(worldbody.iter("body"))
    for body in bodies:
        parents[body].remove(body)
    for body in bodies:
        for child in list(body):
            if child.tag in ("joint", "freejoint", "inertial"):
                body.remove(child)
        body.insert(0, ET.Element("freejoint"))
        body.insert(0, ET.Element("inertial", pos="0 0 0", mass="1", diaginertia="1 1 1"))
        worldbody.append(body)
    return {body.get("name"): body for body in bodies}


def _colour_geoms(scene: Scene, worldbody: ET.Element, by_name: dict[str, ET.Element]) -> None:
    """The exported geoms coloured by body (world geoms grey, planes light)."""
    for geom in worldbody.findall("geom"):
        geom.set("rgba", _FLOOR_RGBA if geom.get("type") == "plane" else _WORLD_RGBA)
    for b, name in enumerate(scene.model.body_names):
        for geom in by_name[name].findall("geom"):
            geom.set("rgba", _FLOOR_RGBA if geom.get("type") == "plane" else _rgba(b))


def _stand_ins(scene: Scene, worldbody: ET.Element, by_name: dict[str, ET.Element], show_joints: bool) -> None:
    """Spheres and rods for the bodies without geoms; markers on both sides of every joint."""
    m, r = scene.model, scene.radius
    for b, name in enumerate(m.body_names):
        if scene.has_geom[b]:
            continue
        _visual_geom(by_name[name], "sphere", _rgba(b), SPHERE * r, pos="0 0 0")
        for anchor in scene.links[b]:
            if np.linalg.norm(anchor) > 1e-9:
                _visual_geom(by_name[name], "capsule", _rgba(b), ROD * r, fromto=_fmt([0.0, 0.0, 0.0, *anchor]))
    if not show_joints:
        return
    loops = set(scene.loop_joints)
    for j in range(m.num_joints):
        rgba, size = (_LOOP_RGBA, LOOP * r) if j in loops else (_JOINT_RGBA, JOINT * r)
        parent = int(m.joint_parent[j])
        base = worldbody if parent < 0 else by_name[m.body_names[parent]]
        _visual_geom(base, "sphere", rgba, size, pos=_fmt(m.joint_anchor_B[j]))
        _visual_geom(by_name[m.body_names[int(m.joint_child[j])]], "sphere", rgba, size,
                     pos=_fmt(m.joint_anchor_F[j]))


def visual_mjcf(scene: Scene, *, width: int, height: int, show_joints: bool) -> str:
    """The drawing model of ``scene``'s world (module docstring) as MJCF text.

    Raises:
        RendererUnavailable: ``kamino.save_mjcf`` cannot export the world (its ``ValueError`` is the cause).
    """
    from kamino.io.mjcf_export import save_mjcf

    try:
        xml = save_mjcf(scene.model, lossy=True, model_name="kamino_viz")
    except ValueError as e:
        raise RendererUnavailable(f"kamino.save_mjcf cannot export world {scene.world}: {e}") from e
    root = ET.fromstring(xml)
    for tag in _DROPPED_SECTIONS:
        for section in root.findall(tag):
            root.remove(section)
    visual = ET.Element("visual")
    ET.SubElement(visual, "global", offwidth=str(width), offheight=str(height))
    ET.SubElement(visual, "headlight", ambient="0.55 0.55 0.55", diffuse="0.45 0.45 0.45", specular="0.1 0.1 0.1")
    root.insert(0, visual)
    asset = root.find("asset")
    if asset is None:
        asset = ET.Element("asset")
        root.insert(1, asset)
    ET.SubElement(asset, "texture", type="skybox", builtin="gradient", rgb1="0.96 0.96 0.97", rgb2="0.8 0.83 0.87",
                  width="64", height="64")
    worldbody = root.find("worldbody")
    assert worldbody is not None
    worldbody.insert(0, ET.Element("light", directional="true", pos="0 0 10", dir="0 0.3 -1", diffuse="0.4 0.4 0.4",
                                   specular="0.1 0.1 0.1", castshadow="false"))
    by_name = _flatten(worldbody, root)
    _colour_geoms(scene, worldbody, by_name)
    _stand_ins(scene, worldbody, by_name, show_joints)
    return ET.tostring(root, encoding="unicode")


def _open_renderer(mj_model, width: int, height: int):
    """A ``mujoco.Renderer``, or :class:`RendererUnavailable` when no OpenGL context can be made (GLFW without a
    display, EGL without a device: ``MUJOCO_GL``, read when ``mujoco`` is first imported, picks the platform)."""
    import mujoco

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # GLFW warns before failing without a display
        try:
            return mujoco.Renderer(mj_model, height=height, width=width)
        except Exception as e:  # mujoco.FatalError, ImportError of the GL platform, RuntimeError...
            raise RendererUnavailable(f"mujoco.Renderer could not make an OpenGL context ({type(e).__name__}: {e}); "
                                      "on a machine without a display set MUJOCO_GL=egl (GPU) or osmesa before "
                                      "mujoco is imported") from e


def mujoco_frames(scene: Scene, *, width: int, height: int, show_joints: bool, show_contacts: bool,
                  azimuth: float, elevation: float) -> Iterator[np.ndarray]:
    """Render ``scene``'s frames as ``[height, width, 3]`` uint8 images. The model is compiled and the renderer
    opened before the first frame is asked for, so :class:`RendererUnavailable` is raised by this call."""
    import mujoco

    mj_model = mujoco.MjModel.from_xml_string(visual_mjcf(scene, width=width, height=height,
                                                          show_joints=show_joints))
    renderer = _open_renderer(mj_model, width, height)
    return _render(scene, mj_model, renderer, show_contacts, azimuth, elevation)


def qpos_addresses(scene: Scene, mj_model) -> np.ndarray:
    """The ``qpos`` address of each kamino body's free joint in the drawing model."""
    import mujoco

    ids = [mujoco.mj_name2id(mj_model, mujoco.mjtObj.mjOBJ_BODY, name) for name in scene.model.body_names]
    return np.array([mj_model.jnt_qposadr[mj_model.body_jntadr[i]] for i in ids], dtype=np.int64)


def set_poses(mj_model, data, qpos_adr: np.ndarray, body_q: np.ndarray) -> None:
    """Put the drawing model's bodies at kamino poses ``body_q [B, 7]`` and place geoms and lights."""
    import mujoco

    for i in range(3):
        data.qpos[qpos_adr + i] = body_q[:, i]
    data.qpos[qpos_adr + 3] = body_q[:, 6]  # MuJoCo quaternions are (w, x, y, z)
    for i in range(3):
        data.qpos[qpos_adr + 4 + i] = body_q[:, 3 + i]
    mujoco.mj_kinematics(mj_model, data)
    mujoco.mj_comPos(mj_model, data)
    mujoco.mj_camlight(mj_model, data)  # places the lights (mj_kinematics does not)


def _add_points(mj_scene, points: np.ndarray, radius: float) -> None:
    """Small spheres at ``points`` appended to a rendered scene (as many as it has room for)."""
    import mujoco

    rgba = np.asarray(_CONTACT_RGBA, np.float32)
    for p in points:
        if mj_scene.ngeom >= mj_scene.maxgeom:
            return
        mujoco.mjv_initGeom(mj_scene.geoms[mj_scene.ngeom], int(mujoco.mjtGeom.mjGEOM_SPHERE),
                            np.array([radius, 0.0, 0.0]), np.asarray(p, float), np.eye(3).ravel(), rgba)
        mj_scene.ngeom += 1


def _render(scene: Scene, mj_model, renderer, show_contacts: bool, azimuth: float,
            elevation: float) -> Iterator[np.ndarray]:
    import mujoco

    data = mujoco.MjData(mj_model)
    adr = qpos_addresses(scene, mj_model)
    camera = mujoco.MjvCamera()
    camera.type = mujoco.mjtCamera.mjCAMERA_FREE
    camera.lookat[:] = scene.center
    camera.distance = camera_distance(scene.radius, float(mj_model.vis.global_.fovy))
    camera.azimuth, camera.elevation = azimuth, elevation
    try:
        for k in range(scene.num_frames):
            set_poses(mj_model, data, adr, scene.body_q[k])
            renderer.update_scene(data, camera=camera)
            if show_contacts:
                _add_points(renderer.scene, scene.contacts[k], CONTACT * scene.radius)
            yield renderer.render().copy()
    finally:
        renderer.close()
