"""Public entry points: ``step``, ``rollout``, ``init_state``, ``metrics``, ``joint_positions``.

Backends are looked up by name: ``"jax"`` is the reference in ``kamino/jax_ref``, ``"warp"`` the
production backend in ``kamino/warp_backend`` (docs/warp_backend.md).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from kamino.config import SolverConfig
from kamino.model import JointType, Model
from kamino.state import ContactState, Control, State, StepInfo

BACKENDS = ("jax", "warp")


def _backend(name: str):
    if name == "jax":
        from kamino.jax_ref import backend

        return backend
    if name == "warp":
        from kamino.warp_backend import backend

        return backend
    raise ValueError(f"unknown backend {name!r}; choose one of {BACKENDS}")


def init_state(model: Model, dtype=None, *, joint_positions=None, actuated_positions=None, base_pose=None,
               **fk_options) -> State:
    """The model's initial state: zero twists (the builder's, if set), reactions and contacts.

    Without coordinates the bodies are at the builder's (reference) poses. With ``joint_positions``,
    ``actuated_positions`` and/or ``base_pose`` the poses come from :func:`kamino.forward_kinematics`
    (consistent with every joint and loop closure; ``fk_options`` are passed on), which raises a
    ``ValueError`` naming the worlds that do not converge. ``dtype`` defaults to JAX's default float
    (float32, or float64 with ``jax_enable_x64``).
    """
    dtype = jnp.zeros(0).dtype if dtype is None else jnp.dtype(dtype)
    body_q = jnp.asarray(model.body_q0, dtype)
    body_u = jnp.asarray(model.body_u0, dtype)
    if joint_positions is not None or actuated_positions is not None or base_pose is not None:
        from kamino.kinematics import forward_kinematics

        fk = forward_kinematics(model, joint_positions, actuated_positions, base_pose, dtype=dtype, **fk_options)
        bad = np.nonzero(~np.asarray(fk.converged))[0]
        if bad.size:
            raise ValueError(f"init_state: forward kinematics did not converge in worlds {bad[:8].tolist()} "
                             f"(residual {np.asarray(fk.residual)[bad[:8]].tolist()}); the coordinates may be "
                             "unreachable")
        body_q, body_u = fk.body_q, jnp.zeros_like(body_u)
    return State(
        body_q=body_q,
        body_u=body_u,
        time=jnp.zeros(model.num_worlds, dtype),
        constraint_force=jnp.zeros(model.num_constraints, dtype),
        actuator_force=jnp.zeros(model.num_dofs, dtype),
        passive_force=jnp.zeros(model.num_dofs, dtype),
        limit_force=jnp.zeros(model.num_dofs, dtype),
        coupling_force=jnp.zeros(model.num_couplings, dtype),
        contacts=ContactState.empty(model.num_contacts, dtype),
        info=StepInfo.empty(model.num_worlds, dtype),
    )


def load_mjcf(source, **options) -> Model:
    """Load an MJCF file (path) or XML string as a single-world :class:`Model` (``kamino/io/mjcf.py``;
    mapping, options and what is unsupported: docs/mjcf.md). Imports ``mujoco`` on first use."""
    from kamino.io.mjcf import load_mjcf as _load_mjcf

    return _load_mjcf(source, **options)


def step(model: Model, state: State, control: Control | None = None, *, config: SolverConfig | None = None,
         backend: str = "jax") -> State:
    """Advance every world by ``config.dt``; returns a new :class:`State` (inputs are not mutated)."""
    return _backend(backend).step(model, state, control, config or SolverConfig())


def rollout(model: Model, state: State, controls: Control | None = None, *, num_steps: int | None = None,
            config: SolverConfig | None = None, backend: str = "jax") -> State:
    """Run many steps. ``controls`` fields carry a leading time axis (or pass ``num_steps`` and no
    controls). Returns the trajectory: a :class:`State` whose arrays have a leading time axis
    (the state after each step)."""
    return _backend(backend).rollout(model, state, controls, num_steps, config or SolverConfig())


def metrics(model: Model, state: State) -> dict[str, jax.Array]:
    """Per-world diagnostics ``[num_worlds]``: ``constraint_violation`` (max |residual| of the joint
    rows and couplings: m for translational rows, rad for rotational ones), ``kinetic_energy``,
    ``potential_energy`` (``-m g . r``) and ``total_energy``."""
    from kamino.jax_ref import backend

    return backend.metrics(model, state)


def joint_positions(model: Model, state: State) -> jax.Array:
    """Joint coordinates of all joints, flat ``[model.num_coords]`` in joint order
    (formulation.md §2.4): REVOLUTE angle, PRISMATIC t_x, CYLINDRICAL (t_x, angle), UNIVERSAL
    (theta_1, theta_2), SPHERICAL quaternion (x, y, z, w), CARTESIAN t, FREE (t, quaternion).
    Angles are in [-pi, pi]."""
    from kamino.jax_ref import backend

    packed = backend.joint_coordinates_padded(model, state.body_q)
    return packed.reshape(-1)[_coord_gather(model)]


def _coord_gather(model: Model) -> np.ndarray:
    """Flat index into the padded ``[W * max_joints * 7]`` coordinates for each model coordinate."""
    nj = int(model.world_joint_count.max()) if model.num_joints else 0
    local_j = np.arange(model.num_joints) - model.world_joint_start[model.joint_world]
    slot = model.joint_world * nj + local_j
    counts = model.joint_coord_count
    return np.repeat(slot * 7, counts) + (np.arange(int(counts.sum())) - np.repeat(model.joint_coord_start, counts))


__all__ = ["Control", "JointType", "SolverConfig", "State", "init_state", "joint_positions", "load_mjcf", "metrics",
           "rollout", "step"]
