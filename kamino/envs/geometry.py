"""Kinematic read-outs for environments: actuated joint positions and rates, base frames, ground placement.

Everything here reads one world's State with the JAX reference's joint kinematics (``kamino/jax_ref/joints.py``:
``joint_frames``, ``dof_positions``, ``dof_jacobian``), the functions ``kamino.joint_positions`` and the step use,
so an observation and the PD actuator read the same angle. A DoF's rate is ``J_dofs u`` (the actuation Jacobian
of docs/formulation.md §2.5 applied to the body twists): the time derivative of the DoF position for hinges and
slides.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from kamino.hostmath import quat_to_matrix as host_quat_to_matrix
from kamino.jax_ref.joints import dof_jacobian, dof_positions, joint_frames
from kamino.jax_ref.layout import PaddedModel
from kamino.jax_ref.spatial import quat_to_matrix, rotate
from kamino.model import GeomType, Model


def one_world(pm: PaddedModel) -> PaddedModel:
    """World 0 of a padded model (drops the leading world axis)."""
    return jax.tree.map(lambda x: x[0], pm)


def dof_state(pm0: PaddedModel, body_q: jax.Array, body_u: jax.Array) -> tuple[jax.Array, jax.Array]:
    """``(positions, rates)`` of every DoF ``[nd]`` of a one-world model (``pm0`` from :func:`one_world`)."""
    jf = joint_frames(pm0, body_q)
    q = dof_positions(pm0, jf)
    J = dof_jacobian(pm0, jf, body_q.shape[0])
    return q, J @ body_u.reshape(-1)


def body_frame_vectors(body_q: jax.Array, body_u: jax.Array, body: int) -> dict[str, jax.Array]:
    """A body's gravity direction, linear and angular velocity in its own frame, and its height:
    ``gravity`` (the unit vector ``-z`` of the world in body axes: ``(0, 0, -1)`` when upright), ``lin_vel``,
    ``ang_vel``, ``height`` (CoM z) and ``up`` (the world z component of the body's z axis)."""
    quat = body_q[body, 3:]
    R = quat_to_matrix(quat)
    down = jnp.asarray([0.0, 0.0, -1.0], body_q.dtype)
    return {"gravity": R.T @ down, "lin_vel": R.T @ body_u[body, :3], "ang_vel": R.T @ body_u[body, 3:],
            "height": body_q[body, 2], "up": R[2, 2]}


def support_points(model: Model) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Points whose lowest one touches the ground when a floating robot is placed: per body-attached geom, the
    box corners, the sphere centre or the capsule's segment ends, in the body's CoM frame, with the body index
    and the radius to subtract. Other geom types (cylinder, ellipsoid) are not used for placement."""
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


def ground_height(model: Model) -> float:
    """Height of the highest world-attached PLANE geom whose normal is +z (0 without one)."""
    heights = [float(model.geom_pos[g, 2]) for g in range(model.num_geoms)
               if model.geom_body[g] < 0 and model.geom_type[g] == GeomType.PLANE]
    return max(heights, default=0.0)


def place_on_ground(body_q: jax.Array, points: jax.Array, bodies: np.ndarray, radii: jax.Array,
                    height: float) -> jax.Array:
    """``body_q`` moved vertically so that its lowest support point (:func:`support_points`) is at ``height``."""
    if bodies.size == 0:
        return body_q
    world = body_q[bodies, :3] + rotate(body_q[bodies, 3:], points)
    lowest = jnp.min(world[:, 2] - radii)
    return body_q.at[:, 2].add(height - lowest)


__all__ = ["body_frame_vectors", "dof_state", "ground_height", "one_world", "place_on_ground", "support_points"]
