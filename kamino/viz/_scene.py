"""What every ``kamino.viz`` renderer draws, read once from a model and a trajectory.

A :class:`Scene` is one world of a trajectory: its single-world model, the frames kept (all steps, or one per
``1 / fps`` of simulated time), the body poses and active contact points of those frames, the loop-closing
joints (the joints the MJCF export's spanning tree cuts, ``kamino/io/mjcf_export.py``), the stand-in links of
bodies without geoms, and the bounds of the motion (for the cameras).
"""

from __future__ import annotations

import dataclasses
import math
import numbers

import numpy as np

from kamino.io.mjcf_export import loop_closing_joints
from kamino.model import GeomType, Model
from kamino.viz._world import world_model

#: The default view direction of the page and the GIFs [deg] (MuJoCo's free-camera convention): azimuth 90 looks
#: along +y at the xz plane, where ``kamino.models`` builds its planar mechanisms; elevation -20 from a little above.
AZIMUTH, ELEVATION = 90.0, -20.0

__all__ = ["AZIMUTH", "ELEVATION", "Scene", "body_links", "geom_radius", "loop_joints", "make_scene", "pose_matrices"]


@dataclasses.dataclass(frozen=True)
class Scene:
    """One world of a trajectory, as drawn.

    Attributes:
        model: the world's single-world model (bodies, joints and geoms numbered from 0).
        world: the world's index in the trajectory's model.
        num_worlds: the trajectory model's world count.
        steps: ``[F]`` the trajectory step of each frame.
        time: ``[F]`` simulated time of each frame [s] (``traj.time`` of the world; ``step / 30`` where it does not
            increase).
        body_q: ``[F, B, 7]`` CoM poses ``(px, py, pz, qx, qy, qz, qw)`` of the world's bodies.
        contacts: ``F`` arrays ``[n, 3]``: the world points of the frame's active contacts (``pair >= 0``).
        loop_joints: world-local indices of the loop-closing joints.
        links: per body, the anchors (body frame) of its joints: the rods drawn for a body without geoms.
        has_geom: per body, whether a geom is attached to it.
        center, radius: a sphere holding the whole motion (body reach included) [m].
    """

    model: Model
    world: int
    num_worlds: int
    steps: np.ndarray
    time: np.ndarray
    body_q: np.ndarray
    contacts: list[np.ndarray]
    loop_joints: list[int]
    links: list[list[np.ndarray]]
    has_geom: list[bool]
    center: np.ndarray
    radius: float

    @property
    def num_frames(self) -> int:
        return int(self.body_q.shape[0])


def _check_world(world: object, num_worlds: int, fn: str) -> int:
    """``world`` as an index in ``[0, num_worlds)`` (negative counts from the end), or a clear error."""
    if isinstance(world, bool) or not isinstance(world, numbers.Integral):
        raise TypeError(f"{fn}: world must be an integer (a world index), got {world!r}")
    w = int(world)
    if not -num_worlds <= w < num_worlds:
        raise ValueError(f"{fn}: world {w} is out of range for a model of {num_worlds} world(s) "
                         f"(valid: 0..{num_worlds - 1}, or negative from the end)")
    return w % num_worlds


def _trajectory_body_q(model: Model, traj: object, fn: str) -> np.ndarray:
    """``traj.body_q`` as ``[T, num_bodies, 7]``, or an error that says what is wrong with ``traj``."""
    from kamino.state import State

    if not isinstance(model, Model):
        raise TypeError(f"{fn}: model must be a kamino.Model, got {type(model).__name__}")
    if not isinstance(traj, State):
        raise TypeError(f"{fn}: traj must be a kamino.State with a leading time axis (what kamino.rollout returns), "
                        f"got {type(traj).__name__}")
    body_q = np.asarray(traj.body_q)
    if body_q.ndim == 2:
        raise ValueError(f"{fn}: traj has no time axis (body_q has shape {body_q.shape}: one state). Pass the "
                         "trajectory kamino.rollout returns, or a single state as a one-frame trajectory: "
                         "jax.tree.map(lambda x: x[None], state)")
    if body_q.ndim != 3 or body_q.shape[2] != 7:
        raise ValueError(f"{fn}: traj.body_q has shape {body_q.shape}; expected [num_steps, num_bodies, 7]")
    if body_q.shape[1] != model.num_bodies:
        raise ValueError(f"{fn}: the trajectory does not match the model: traj.body_q has {body_q.shape[1]} bodies "
                         f"per step, the model {model.num_bodies} ({model.num_worlds} world(s)); pass the model the "
                         "trajectory was run on")
    if body_q.shape[0] == 0:
        raise ValueError(f"{fn}: the trajectory has no steps")
    return body_q


#: Steps per second assumed for a trajectory whose ``time`` does not increase (one frame, or a frozen world).
STEPS_PER_SECOND_WITHOUT_TIME = 30.0


def _trajectory_time(model: Model, traj: object, num_steps: int, world: int, fn: str) -> np.ndarray:
    """``[T]`` simulated time of ``world`` (``step / STEPS_PER_SECOND_WITHOUT_TIME`` when ``traj.time`` does not
    increase from the first step to the last)."""
    time = np.asarray(traj.time, dtype=float)
    if time.shape != (num_steps, model.num_worlds):
        raise ValueError(f"{fn}: the trajectory does not match the model: traj.time has shape {time.shape}, "
                         f"expected ({num_steps}, {model.num_worlds}) (steps, worlds)")
    t = time[:, world]
    if num_steps > 1 and not t[-1] > t[0]:
        return np.arange(num_steps, dtype=float) / STEPS_PER_SECOND_WITHOUT_TIME
    return t


def _world_contacts(model: Model, traj: object, world: int, fn: str) -> tuple[np.ndarray, np.ndarray]:
    """``(pair [T, C], pos [T, C, 3])`` of the world's contact slots."""
    contacts = traj.contacts
    pair, pos = np.asarray(contacts.pair), np.asarray(contacts.pos, dtype=float)
    if pair.ndim != 2 or pair.shape[1] != model.num_contacts:
        raise ValueError(f"{fn}: the trajectory does not match the model: traj.contacts.pair has shape {pair.shape}, "
                         f"expected (num_steps, {model.num_contacts}) (the model's contact capacity)")
    start = int(np.sum(model.world_contact_capacity[:world]))
    seg = slice(start, start + int(model.world_contact_capacity[world]))
    return pair[:, seg], pos[:, seg]


def frame_steps(time: np.ndarray, fps: float | None, *, unique: bool) -> np.ndarray:
    """The trajectory steps drawn: all (``fps=None``), or the last step at or before each multiple of ``1 / fps``
    of simulated time from the first frame's (``unique``: each step once). A trajectory whose time does not
    increase keeps every step."""
    num_steps = time.shape[0]
    if fps is None:
        return np.arange(num_steps)
    if isinstance(fps, bool) or not isinstance(fps, numbers.Real) or not math.isfinite(fps) or fps <= 0:
        raise ValueError(f"fps must be a positive number of frames per second of simulated time, got {fps!r}")
    span = float(time[-1] - time[0])
    if num_steps == 1 or not span > 0:
        return np.arange(num_steps)
    tol = 1e-3 / fps  # float32 times drift from exact multiples of the step
    targets = time[0] + np.arange(math.floor(span * fps + 1e-3) + 1) / fps
    steps = np.clip(np.searchsorted(time, targets + tol, side="right") - 1, 0, num_steps - 1)
    return np.unique(steps) if unique else steps


def loop_joints(model: Model) -> list[int]:
    """The loop-closing joints of ``model`` (``kamino.io.mjcf_export.loop_closing_joints``)."""
    return loop_closing_joints(model)


def body_links(model: Model) -> list[list[np.ndarray]]:
    """Per body of a single-world model, the anchors (in its CoM frame) of the joints it takes part in."""
    links: list[list[np.ndarray]] = [[] for _ in range(model.num_bodies)]
    for j in range(model.num_joints):
        parent, child = int(model.joint_parent[j]), int(model.joint_child[j])
        if parent >= 0:
            links[parent].append(np.asarray(model.joint_anchor_B[j], float))
        links[child].append(np.asarray(model.joint_anchor_F[j], float))
    return links


def geom_radius(gtype: int, size: np.ndarray) -> float:
    """Radius of a sphere about the geom's origin holding the geom (0 for a plane)."""
    g = GeomType(int(gtype))
    s = np.asarray(size, float)
    if g == GeomType.PLANE:
        return 0.0
    if g == GeomType.SPHERE:
        return float(s[0])
    if g in (GeomType.CAPSULE,):
        return float(s[0] + s[1])
    if g == GeomType.CYLINDER:
        return float(math.hypot(s[0], s[1]))
    if g in (GeomType.BOX, GeomType.HFIELD):  # a heightfield's size: the half-extents of a box holding it
        return float(np.linalg.norm(s[:3]))
    return float(np.max(s[:3]))  # ELLIPSOID


def _body_reach(model: Model, links: list[list[np.ndarray]]) -> np.ndarray:
    """Per body, how far its geoms and joint anchors reach from its CoM [m]."""
    reach = np.zeros(model.num_bodies)
    for b, anchors in enumerate(links):
        for a in anchors:
            reach[b] = max(reach[b], float(np.linalg.norm(a)))
    for g in range(model.num_geoms):
        b = int(model.geom_body[g])
        if b >= 0:
            extent = float(np.linalg.norm(model.geom_pos[g])) + geom_radius(model.geom_type[g], model.geom_size[g])
            reach[b] = max(reach[b], extent)
    return reach


def _bounds(model: Model, body_q: np.ndarray, links: list[list[np.ndarray]]) -> tuple[np.ndarray, float]:
    """Centre and radius of a sphere holding every frame's bodies (with their reach) and the world's bounded
    geoms and joint anchors."""
    reach = _body_reach(model, links)
    pos = body_q[..., :3].reshape(-1, 3)
    r = np.tile(reach, body_q.shape[0])
    points, radii = [pos], [r]
    for g in range(model.num_geoms):
        if int(model.geom_body[g]) < 0 and GeomType(int(model.geom_type[g])) != GeomType.PLANE:
            points.append(np.asarray(model.geom_pos[g], float)[None])
            radii.append(np.array([geom_radius(model.geom_type[g], model.geom_size[g])]))
    for j in range(model.num_joints):
        if int(model.joint_parent[j]) < 0:
            points.append(np.asarray(model.joint_anchor_B[j], float)[None])
            radii.append(np.zeros(1))
    p, rr = np.concatenate(points), np.concatenate(radii)
    lo, hi = (p - rr[:, None]).min(axis=0), (p + rr[:, None]).max(axis=0)
    center = 0.5 * (lo + hi)
    radius = float(np.max(np.linalg.norm(p - center, axis=1) + rr))
    return center, max(radius, 0.05)


def pose_matrices(q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(positions [..., 3], rotation matrices [..., 3, 3])`` of poses ``[..., 7]`` (quaternions x, y, z, w,
    normalised; the vectorised ``kamino.hostmath.quat_to_matrix``)."""
    q = np.asarray(q, float)
    quat = q[..., 3:] / np.linalg.norm(q[..., 3:], axis=-1, keepdims=True)
    x, y, z, w = np.moveaxis(quat, -1, 0)
    rot = np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], axis=-1),
        np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], axis=-1),
        np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], axis=-1),
    ], axis=-2)
    return q[..., :3], rot


def make_scene(model: Model, traj: object, *, world: int, fps: float | None, fn: str, unique: bool = True) -> Scene:
    """Check ``model``, ``traj`` and ``world`` against each other and read the frames drawn (see :class:`Scene`).

    Raises:
        TypeError: ``model`` is not a Model, ``traj`` not a State, ``world`` not an integer.
        ValueError: ``traj`` has no time axis or does not match ``model``, ``world`` is out of range, ``fps`` is not
            positive, or a drawn pose is not finite.
    """
    body_q_all = _trajectory_body_q(model, traj, fn)
    w = _check_world(world, model.num_worlds, fn)
    num_steps = body_q_all.shape[0]
    time = _trajectory_time(model, traj, num_steps, w, fn)
    pair, cpos = _world_contacts(model, traj, w, fn)
    try:
        steps = frame_steps(time, fps, unique=unique)
    except ValueError as e:
        raise ValueError(f"{fn}: {e}") from None
    seg = slice(int(model.world_body_start[w]), int(model.world_body_start[w] + model.world_body_count[w]))
    body_q = np.asarray(body_q_all[steps, seg], dtype=float)
    bad = np.nonzero(~np.all(np.isfinite(body_q), axis=(1, 2)))[0]
    if bad.size:
        raise ValueError(f"{fn}: world {w} has non-finite body poses at steps {steps[bad[:8]].tolist()}")
    single = world_model(model, w)
    links = body_links(single)
    center, radius = _bounds(single, body_q, links)
    has_geom = [False] * single.num_bodies
    for b in single.geom_body:
        if int(b) >= 0:
            has_geom[int(b)] = True
    return Scene(model=single, world=w, num_worlds=model.num_worlds, steps=steps, time=time[steps], body_q=body_q,
                 contacts=[cpos[k][pair[k] >= 0] for k in steps], loop_joints=loop_joints(single), links=links,
                 has_geom=has_geom, center=center, radius=radius)


def camera_position(center: np.ndarray, radius: float, azimuth: float, elevation: float,
                    fovy: float = 45.0) -> np.ndarray:
    """Where a camera with vertical field of view ``fovy`` [deg] sits to see the sphere ``(center, radius)`` whole,
    looking along ``azimuth``/``elevation`` [deg] (MuJoCo's free-camera convention: azimuth 90 looks along +y,
    negative elevation looks down)."""
    az, el = math.radians(azimuth), math.radians(elevation)
    forward = np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)])
    return np.asarray(center, float) - forward * camera_distance(radius, fovy)


def camera_distance(radius: float, fovy: float = 45.0) -> float:
    """Distance from which a camera of vertical field of view ``fovy`` [deg] sees a sphere of ``radius`` whole."""
    return 1.1 * radius / math.sin(math.radians(fovy) / 2)
