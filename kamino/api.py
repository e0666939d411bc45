"""Public entry points: ``step``, ``rollout``, ``init_state``, ``metrics``, ``joint_positions``.

Backends are looked up by name: ``"jax"`` is the reference in ``kamino/jax_ref``, ``"warp"`` the
production backend in ``kamino/warp_backend`` (docs/warp_backend.md).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from kamino.checks import check_config, check_control, check_control_type, check_model, check_state
from kamino.config import SolverConfig
from kamino.model import JointType, Model
from kamino.sharding import sharded_call, world_sharding
from kamino.state import ContactState, Control, State, StepInfo

BACKENDS = ("jax", "warp")


def _backend(name: str):
    if name == "jax":
        from kamino.jax_ref import backend

        return backend
    if name == "warp":
        from kamino._warp import quiet_warp

        quiet_warp()  # Warp's banner and module-load lines off, unless asked for (kamino/_warp.py)
        from kamino.warp_backend import backend

        return backend
    raise ValueError(f"unknown backend {name!r} (the backend= argument); choose one of {BACKENDS}")


def _check_call(fn: str, model, state, control, config, backend: str) -> None:
    """What ``step`` / ``rollout`` check before a backend runs (``kamino/checks.py``): the kinds of the arguments,
    the backend's name, the config against the backend, and the state's and a step's control's shapes."""
    if backend not in BACKENDS:
        raise ValueError(f"{fn}: unknown backend {backend!r} (the backend= argument); choose one of "
                         f"{BACKENDS}")
    check_model(model, fn)
    check_config(config, backend, fn)
    check_state(model, state, fn)
    if fn == "step":
        check_control(model, control)
    else:
        check_control_type(control, "controls", fn)


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


def save_mjcf(model: Model, path=None, **options) -> str:
    """Export a single-world :class:`Model` as MJCF (``kamino/io/mjcf_export.py``; mapping, the spanning-tree
    choice and what raises: docs/mjcf.md, "Export"). Returns the XML text and writes it to ``path`` if given;
    ``load_mjcf(save_mjcf(model))`` simulates like ``model``, and MuJoCo (its viewer, MuJoCo Warp, Newton) loads
    the file. ``options``: ``lossy`` (drop geom restitution and initial velocities instead of raising),
    ``model_name``. Raises ``ValueError`` naming every feature MJCF cannot represent."""
    from kamino.io.mjcf_export import save_mjcf as _save_mjcf

    return _save_mjcf(model, path, **options)


def step(model: Model, state: State, control: Control | None = None, *, config: SolverConfig | None = None,
         backend: str = "jax") -> State:
    """Advance every world by ``config.dt``; returns a new :class:`State` (inputs are not mutated).

    ``control`` holds one step's inputs (arrays flat over all worlds, no time axis); ``config`` is a
    :class:`SolverConfig` (docs/settings.md: the defaults and the speed-against-accuracy knob). Arguments of the
    wrong kind or shape raise a ``TypeError`` / ``ValueError`` naming the argument before a backend runs. A state
    whose worlds are sharded over devices (``kamino.sharding.shard_worlds``) is stepped on each device in place.
    """
    _check_call("step", model, state, control, config, backend)
    sharding = world_sharding(state)
    if sharding is not None:  # worlds spread over devices: each steps its own (kamino/sharding.py)
        return sharded_call("step", _backend(backend), model, state, control, sharding, config or SolverConfig())
    return _backend(backend).step(model, state, control, config or SolverConfig())


def rollout(model: Model, state: State, controls: Control | None = None, *, num_steps: int | None = None,
            config: SolverConfig | None = None, backend: str = "jax") -> State:
    """Run many steps. ``controls`` fields carry a leading time axis (or pass ``num_steps`` and no
    controls). Returns the trajectory: a :class:`State` whose arrays have a leading time axis
    (the state after each step); :func:`metrics` reads it whole (``[num_steps, num_worlds]``). A state sharded
    over devices (``kamino.sharding.shard_worlds``) gives a trajectory sharded the same way along its world axis."""
    _check_call("rollout", model, state, controls, config, backend)
    sharding = world_sharding(state)
    if sharding is not None:
        return sharded_call("rollout", _backend(backend), model, state, controls, sharding, config or SolverConfig(),
                            num_steps)
    return _backend(backend).rollout(model, state, controls, num_steps, config or SolverConfig())


def metrics(model: Model, state: State) -> dict[str, jax.Array]:
    """Per-world diagnostics ``[num_worlds]``: ``constraint_violation`` (max |residual| of the joint
    rows and couplings: m for translational rows, rad for rotational ones), ``kinetic_energy``,
    ``potential_energy`` (``-m g . r``) and ``total_energy``.

    ``state`` may also be a trajectory from :func:`rollout` (a leading time axis on every field): then each
    entry is ``[num_steps, num_worlds]``, the diagnostics after every step."""
    from kamino.jax_ref import backend

    check_model(model, "metrics")
    if not isinstance(state, State):
        raise TypeError(f"metrics: state must be a kamino.State (or a rollout's trajectory), got "
                        f"{type(state).__name__}")
    if state.body_q.ndim == 3:  # a trajectory [num_steps, num_bodies, 7]
        return jax.vmap(lambda q, u: backend.metrics(model, state.replace(body_q=q, body_u=u)))(state.body_q,
                                                                                               state.body_u)
    return backend.metrics(model, state)


def joint_positions(model: Model, state: State) -> jax.Array:
    """Joint coordinates of all joints, flat ``[model.num_coords]`` in joint order
    (docs/formulation.md §2.4): REVOLUTE angle, PRISMATIC t_x, CYLINDRICAL (t_x, angle), UNIVERSAL
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
           "rollout", "save_mjcf", "step"]
