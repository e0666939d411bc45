"""The object a user holds: :class:`Simulator`, one model stepped with one configuration on one backend.

``sim = kamino.Simulator(model, config, backend="warp")`` builds what stepping needs on first use and keeps it:
the padded layout (the JAX reference), or the device model, the steppers and their CUDA graphs (Warp), and the
programs that step a state spread over several devices. Dropping the simulator frees them. ``kamino.step`` and
``kamino.rollout`` are the one-call entry points over it: they step with the simulator that a frozen model keeps
for each (backend, configuration) (:func:`kamino.model.derived`).

Threads: a simulator's JAX reference holds no state a step changes; its Warp backend's steppers own device buffers,
and an eager step or rollout holds the simulator's lock from loading the state to reading the result, so two
threads sharing one simulator take turns and each gets its own, correct result. Two simulators of the same model
share nothing but the model.
"""

from __future__ import annotations

import threading

from kamino.checks import check_config, check_control, check_dt, check_model, check_rollout_controls, check_state
from kamino.config import BACKENDS, SolverConfig
from kamino.model import Model, derived
from kamino.sharding import group_model, num_shards, sharded_program, world_sharding
from kamino.state import Control, State, bind

#: the backend a :class:`Simulator`, ``kamino.step`` and ``kamino.rollout`` use unless told otherwise: Warp, on the
#: GPU and on the CPU (a 1-world Menagerie humanoid steps 17x faster than on the JAX reference on a CPU, and starts
#: in seconds instead of a minute of XLA compilation: docs/first_step.md, "The default backend")
DEFAULT_BACKEND = "warp"


def _engine(model: Model, config: SolverConfig, backend: str):
    """The backend's engine for ``model`` and ``config`` (``kamino.jax_ref.backend.Engine`` or
    ``kamino.warp_backend.backend.Engine``); Warp is imported on first use."""
    if backend == "jax":
        from kamino.jax_ref.backend import Engine

        return Engine(model, config)
    from kamino._warp import quiet_warp

    quiet_warp()  # Warp's banner and module-load lines off, unless asked for (kamino/_warp.py)
    from kamino.warp_backend.backend import Engine

    return Engine(model, config)


def check_backend(backend, fn: str) -> None:
    """Raise a ``ValueError`` naming ``fn`` unless ``backend`` is one of :data:`kamino.config.BACKENDS`."""
    if backend not in BACKENDS:
        raise ValueError(f"{fn}: unknown backend {backend!r} (the backend= argument); choose one of {BACKENDS}")


class Simulator:
    """Steps the worlds of ``model`` with ``config`` (default :class:`SolverConfig`) on ``backend``: ``"warp"``
    (the default), the production backend in ``kamino/warp_backend`` (docs/warp_backend.md), on the GPU when there is
    one, else on the CPU; or ``"jax"``, the reference in ``kamino/jax_ref``. Both are differentiable (``jax.grad`` and
    ``jax.jvp`` at any configuration, by the implicit function theorem at each solve's solution: docs/formulation.md
    §7.10; the Warp step's derivative is the reference's at the Warp solution) and take traced model parameters
    (:meth:`step_with`)::

        sim = kamino.Simulator(kamino.models.fourbar(), backend="warp")
        state = sim.step(kamino.init_state(sim.model))
        trajectory = sim.rollout(state, num_steps=240)

    A model, configuration or backend of the wrong kind raises here, naming the argument; a state or control of the
    wrong kind or shape raises in :meth:`step` / :meth:`rollout` before the backend runs.
    """

    def __init__(self, model: Model, config: SolverConfig | None = None, *, backend: str = DEFAULT_BACKEND) -> None:
        check_backend(backend, "Simulator")
        check_model(model, "Simulator")
        check_config(config, backend, "Simulator")
        check_dt(model, config, "Simulator")
        self._model, self._config, self._backend = model, config or SolverConfig(), backend
        self._engine = _engine(model, self._config, backend)
        self._sharded: dict = {}
        self._lock = threading.Lock()

    @property
    def model(self) -> Model:
        """The model this simulator steps."""
        return self._model

    @property
    def config(self) -> SolverConfig:
        """The solver configuration of every step."""
        return self._config

    @property
    def backend(self) -> str:
        """``"jax"`` or ``"warp"``."""
        return self._backend

    @property
    def engine(self):
        """The backend's engine (``kamino.jax_ref.backend.Engine`` or ``kamino.warp_backend.backend.Engine``): what
        the benchmarks and profilers read the Warp steppers' buffers through."""
        return self._engine

    def __repr__(self) -> str:
        return (f"Simulator({self._model.num_worlds} worlds, {self._model.num_bodies} bodies, "
                f"backend={self._backend!r})")

    def step(self, state: State, control: Control | None = None) -> State:
        """Advance every world by ``config.dt``; returns a new :class:`State` (inputs are not mutated).

        ``control`` holds one step's inputs (arrays flat over all worlds, no time axis). Works under ``jax.jit``,
        ``lax.scan``, ``vmap``, ``jax.grad`` and ``jax.jvp`` on both backends (the Warp step's derivative is the JAX
        reference's at the Warp solution: docs/formulation.md §7.10). A state whose worlds are sharded
        over devices (``kamino.sharding.shard_worlds``) is stepped on each device in place."""
        check_state(self._model, state, "step")
        check_control(self._model, control)
        key, state = state.model_fingerprint, bind(state, None)  # the engines see unbound states
        sharding = world_sharding(state)
        if sharding is not None:  # worlds spread over devices: each steps its own (kamino/sharding.py)
            return bind(self._sharded_program("step", sharding, None)(state, control), key)
        return bind(self._engine.step(state, control), key)

    def rollout(self, state: State, controls: Control | None = None, *, num_steps: int | None = None) -> State:
        """Run many steps. ``controls`` fields carry a leading time axis (or pass ``num_steps`` and no controls).
        Returns the trajectory: a :class:`State` whose arrays have a leading time axis (the state after each step);
        ``kamino.metrics`` reads it whole (``[num_steps, num_worlds]``). A state sharded over devices gives a
        trajectory sharded the same way along its world axis."""
        check_state(self._model, state, "rollout")
        num_steps = check_rollout_controls(self._model, controls, num_steps)
        key, state = state.model_fingerprint, bind(state, None)
        sharding = world_sharding(state)
        if sharding is not None:
            return bind(self._sharded_program("rollout", sharding, num_steps)(state, controls), key)
        return bind(self._engine.rollout(state, controls, num_steps), key)

    def parameters(self, dtype):
        """The physical parameters that every step reads, in ``dtype``, for :meth:`step_with` to take with arrays a
        caller has replaced (traced per environment: ``kamino.envs``' domain randomization; or differentiated). On
        the JAX reference ``(padded model, layout tables)`` (the padded model, ``kamino.jax_ref.types.PaddedModel``,
        holds the physical parameters); on the Warp backend a ``kamino.warp_backend.parameters.WorldParameters``
        (masses, inertias, friction, gains, armature, damping, effort limits, flat over worlds, and gravity)."""
        if self._backend == "warp":
            from kamino.warp_backend.parameters import nominal

            return nominal(self._model, dtype)
        return self._engine.parameters(dtype)

    def step_with(self, parameters, state: State, control: Control | None = None) -> State:
        """:meth:`step` with ``parameters`` (a :meth:`parameters` pytree, its arrays possibly traced) in place of the
        model's own; ``jax.grad`` differentiates with respect to them on both backends. The control's shapes are
        checked (at trace time: a ``[num_worlds]`` array where ``[num_dofs]`` belongs would otherwise be read with
        clamped indices); the rest is unchecked: it runs inside an environment's traced step."""
        check_control(self._model, control)
        if self._backend == "warp":
            from kamino.warp_backend.parameters import WorldParameters

            if not isinstance(parameters, WorldParameters):
                raise TypeError(f"Simulator.step_with: the Warp backend takes a WorldParameters "
                                f"(Simulator.parameters), got {type(parameters).__name__}")
        return bind(self._engine.step(bind(state, None), control, parameters), state.model_fingerprint)

    def _sharded_program(self, fn: str, sharding, num_steps: int | None):
        """The jitted sharded step or rollout for ``sharding`` (``(mesh, axis)``), built once: every device's block
        of worlds steps as the group model's simulator (:func:`kamino.sharding.sharded_program`)."""
        mesh, axis = sharding
        key = (fn, num_steps, mesh, axis)
        with self._lock:
            if key not in self._sharded:
                group = Simulator(group_model(self._model, num_shards(mesh, axis), fn), self._config,
                                  backend=self._backend)
                self._sharded[key] = (group, sharded_program(fn, group.step, mesh, axis, num_steps))
            return self._sharded[key][1]


def simulator_of(model: Model, config: SolverConfig | None, backend: str, fn: str) -> Simulator:
    """The simulator ``kamino.step`` / ``rollout`` (named ``fn`` in errors) step ``model`` with: one per (backend,
    configuration), kept on a frozen model (:func:`kamino.model.derived`), built anew for a model whose arrays can
    still change."""
    check_backend(backend, fn)
    check_model(model, fn)
    check_config(config, backend, fn)
    config = config or SolverConfig()
    return derived(model, ("simulator", backend, config), lambda: Simulator(model, config, backend=backend))


__all__ = ["DEFAULT_BACKEND", "Simulator", "simulator_of"]
