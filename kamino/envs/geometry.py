"""Kinematic read-outs for environments: a base body's frame, ground placement.

An environment steps one world at a time inside ``jax.vmap``, so these read one world's arrays (``body_q`` /
``body_u``). Whole-model read-outs by name, for any number of worlds and for trajectories, are in ``kamino`` itself:
``kamino.dof_state`` (every DoF's position and rate, what an actuated joint's observation reads),
``kamino.joint_coordinates`` (one joint's coordinates), ``kamino.body_frame`` (a body's velocity, gravity direction
and height in its own frame) and ``kamino.body_contact_forces`` (the net contact force on each body).

- :func:`body_frame_vectors`: a base body's frame (gravity direction, linear and angular velocity, height, up);
- :func:`support_points`, :func:`ground_height`, :func:`place_on_ground`: a floating robot set down on the ground;
- :func:`sole_offsets`: a foot's sole point, what a foot target of ``kamino.inverse_kinematics`` places.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from kamino.hostmath import quat_to_matrix as host_quat_to_matrix
from kamino.model import GeomType, Model
from kamino.readouts import frame_vectors
from kamino.spatial import rotate


def body_frame_vectors(body_q: jax.Array, body_u: jax.Array, body: int) -> dict[str, jax.Array]:
    """A body's frame, what a legged robot's base observes: ``gravity`` (the world's ``-z`` in body axes,
    ``(0, 0, -1)`` when upright), ``lin_vel`` (CoM velocity [m/s] in body axes), ``ang_vel`` (angular velocity
    [rad/s] in body axes), ``height`` (CoM z [m]) and ``up`` (the world z component of the body's z axis: 1
    upright). ``body`` indexes the rows of ``body_q`` ``[nb, 7]`` / ``body_u`` ``[nb, 6]``; by name and for a whole
    model: ``kamino.body_frame``."""
    return frame_vectors(body_q, body_u, body)


def support_points(model: Model) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Points whose lowest one touches the ground when a floating robot is placed: ``(points [n, 3], bodies [n],
    radii [n])``. Per body-attached geom of a one-world ``model``: the box corners, the sphere centre or the
    capsule's segment ends, in the body's CoM frame, with the body index and the radius to subtract. Other geom
    types (cylinder, ellipsoid) are not used for placement. Host NumPy, computed once per model."""
    pts, bodies, radii = [], [], []
    for g in np.nonzero(model.geom_body >= 0)[0]:
        t, size = int(model.geom_type[g]), model.geom_size[g]
        R = host_quat_to_matrix(np.asarray(model.geom_quat[g], float))
        pos = model.geom_pos[g]
        if t == GeomType.BOX:
            corners = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)]) * size[:3]
            local, r = pos + corners @ R.T, 0.0
        elif t == GeomType.SPHERE:
            local, r = pos[None], float(size[0])
        elif t == GeomType.CAPSULE:
            local, r = pos + np.array([[0, 0, -size[1]], [0, 0, size[1]]]) @ R.T, float(size[0])
        else:
            continue
        pts.append(local)
        bodies += [int(model.geom_body[g])] * len(local)
        radii += [r] * len(local)
    if not pts:
        return np.zeros((0, 3)), np.zeros(0, np.int32), np.zeros(0)
    return np.concatenate(pts), np.asarray(bodies, np.int32), np.asarray(radii)


def sole_offsets(model: Model, bodies) -> np.ndarray:
    """``[k, 3]`` each named body's sole point in its CoM frame (the frame of ``State.body_q``): the centre of the
    body's lowest :func:`support_points` at the reference pose ``model.body_q0`` (a flat foot's contact point, the
    point an inverse-kinematics foot target places: ``kamino.inverse_kinematics(..., offsets=)``). A body without
    support points raises a ``ValueError``."""
    pts, owner, _ = support_points(model)
    out = []
    for name in bodies:
        b = model.body_index(name)
        p = pts[owner == b]
        if not len(p):
            raise ValueError(f"sole_offsets: body {name!r} has no box, sphere or capsule geom")
        z = (p @ host_quat_to_matrix(np.asarray(model.body_q0[b, 3:], float)).T)[:, 2]
        out.append(p[z <= z.min() + 1e-9].mean(0))
    return np.asarray(out)


def ground_height(model: Model) -> float:
    """Height [m] of the ground: the highest world-attached PLANE geom of ``model`` (its normal is +z; 0 without
    one)."""
    heights = [float(model.geom_pos[g, 2]) for g in range(model.num_geoms)
               if model.geom_body[g] < 0 and model.geom_type[g] == GeomType.PLANE]
    return max(heights, default=0.0)


def place_on_ground(body_q: jax.Array, points: jax.Array, bodies: np.ndarray, radii: jax.Array,
                    height: float) -> jax.Array:
    """``body_q`` ``[nb, 7]`` moved vertically so that its lowest support point (``points``, ``bodies``, ``radii``
    from :func:`support_points`) is at ``height`` (:func:`ground_height`): a floating robot set down on the ground
    without penetration. Every body moves by the same offset, so joints and loops stay closed."""
    if bodies.size == 0:
        return body_q
    world = body_q[bodies, :3] + rotate(body_q[bodies, 3:], points)
    lowest = jnp.min(world[:, 2] - radii)
    return body_q.at[:, 2].add(height - lowest)


__all__ = ["body_frame_vectors", "ground_height", "place_on_ground", "sole_offsets", "support_points"]
