"""kamino: simulation of robots and mechanisms with kinematic loops, in maximal coordinates.

Public API (docs/conventions.md): ``ModelBuilder``, ``Model``, ``JointType``, ``GeomType``,
``Actuation``, ``ActuationMode``, ``ModelError``, ``replicate``, ``concat``, ``SolverConfig`` (with
its nested ``Stabilisation``, ``Penalty`` and ``WarpSettings``), ``Simulator``
(one model stepped with one configuration on one backend: it owns what stepping builds),
``State``, ``ContactState``, ``Control``, ``StepInfo``, ``init_state``, ``step``, ``rollout``,
``metrics``, ``forward_kinematics``, ``set_joint_positions``, ``FKResult``, ``inverse_kinematics``, ``IKResult``,
``load_mjcf``, ``save_mjcf``, the
procedural ``models``, and the read-outs a task needs: ``joint_positions`` (every joint's coordinates),
``dof_state`` (every DoF's position and rate),
``joint_coordinates`` (one joint's, by name), ``body_frame`` (a body's velocity, gravity direction and height in
its own frame) and ``body_contact_forces`` (the net contact force on each body). The API reference is built from
these docstrings (docs/api.md). Submodules imported on use: ``kamino.viz`` (an HTML
page or a GIF of a rollout), ``kamino.plots`` (matplotlib), ``kamino.envs`` (Brax environments).

Importing kamino turns on JAX's persistent compilation cache in the user's cache directory (``~/.cache/kamino/jax``
on Linux), unless JAX's cache is already configured; ``KAMINO_JAX_CACHE=0`` turns it off, ``KAMINO_JAX_CACHE=/path``
moves it (``kamino/_jax_cache.py``; docs/first_step.md).
"""

from kamino import models
from kamino._jax_cache import enable as _enable_jax_cache
from kamino._jax_cache import quiet_cache_loads as _quiet_cache_loads
from kamino.api import load_mjcf, rollout, save_mjcf, step
from kamino.config import Penalty, SolverConfig, Stabilisation, WarpSettings
from kamino.kinematics import (
    FKResult,
    IKResult,
    forward_kinematics,
    init_state,
    inverse_kinematics,
    set_joint_positions,
)
from kamino.model import (
    Actuation,
    ActuationMode,
    GeomType,
    JointType,
    Model,
    ModelBuilder,
    ModelError,
    concat,
    replicate,
)
from kamino.readouts import (
    body_contact_forces,
    body_frame,
    dof_state,
    joint_coordinates,
    joint_positions,
    metrics,
)
from kamino.simulator import Simulator
from kamino.state import ContactState, Control, State, StepInfo

_enable_jax_cache()  # before the first compile: kamino/_jax_cache.py
_quiet_cache_loads()  # no XLA log lines when an entry loads: kamino/_jax_cache.py

__version__ = "0.1.0"

__all__ = [
    "Actuation",
    "ActuationMode",
    "ContactState",
    "Control",
    "FKResult",
    "GeomType",
    "IKResult",
    "JointType",
    "Model",
    "ModelBuilder",
    "ModelError",
    "Penalty",
    "Simulator",
    "SolverConfig",
    "Stabilisation",
    "State",
    "StepInfo",
    "WarpSettings",
    "body_contact_forces",
    "body_frame",
    "concat",
    "dof_state",
    "forward_kinematics",
    "init_state",
    "inverse_kinematics",
    "joint_coordinates",
    "joint_positions",
    "load_mjcf",
    "metrics",
    "models",
    "replicate",
    "rollout",
    "save_mjcf",
    "set_joint_positions",
    "step",
]
