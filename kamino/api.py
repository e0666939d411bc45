"""The one-call entry points: ``step`` and ``rollout`` (over the :class:`~kamino.simulator.Simulator` a model keeps
for each backend and configuration: ``"warp"``, the production backend in ``kamino/warp_backend``
(docs/warp_backend.md), or ``"jax"``, the reference in ``kamino/jax_ref``), and MJCF in and out (``load_mjcf``,
``save_mjcf``). The initial state is ``kamino.kinematics.init_state``; the read-outs a task needs are in
``kamino/readouts.py``.
"""

from __future__ import annotations

from kamino.config import SolverConfig
from kamino.model import Model
from kamino.simulator import DEFAULT_BACKEND, simulator_of
from kamino.state import Control, State


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
         backend: str = DEFAULT_BACKEND) -> State:
    """Advance every world by ``config.dt``; returns a new :class:`State` (inputs are not mutated): one call of
    :meth:`Simulator.step` with the simulator that ``model`` keeps for ``(backend, config)``.

    ``control`` holds one step's inputs (arrays flat over all worlds, no time axis); ``config`` is a
    :class:`SolverConfig` (docs/settings.md: the defaults and the speed-against-accuracy knob). Arguments of the
    wrong kind or shape raise a ``TypeError`` / ``ValueError`` naming the argument before a backend runs, and so
    does a state of another mechanism (``State.model_fingerprint``, set by ``kamino.init_state``) or of a dtype
    other than float32 and float64. A ``config.dt`` above 0.05 s warns. A state
    whose worlds are sharded over devices (``kamino.sharding.shard_worlds``) is stepped on each device in place.
    """
    return simulator_of(model, config, backend, "step").step(state, control)


def rollout(model: Model, state: State, controls: Control | None = None, *, num_steps: int | None = None,
            config: SolverConfig | None = None, backend: str = DEFAULT_BACKEND) -> State:
    """Run many steps: one call of :meth:`Simulator.rollout` with the simulator that ``model`` keeps for
    ``(backend, config)``. ``controls`` fields carry a leading time axis (or pass ``num_steps`` and no
    controls). Returns the trajectory: a :class:`State` whose arrays have a leading time axis
    (the state after each step); :func:`metrics` reads it whole (``[num_steps, num_worlds]``). A state sharded
    over devices (``kamino.sharding.shard_worlds``) gives a trajectory sharded the same way along its world axis."""
    return simulator_of(model, config, backend, "rollout").rollout(state, controls, num_steps=num_steps)


__all__ = ["load_mjcf", "rollout", "save_mjcf", "step"]
