"""``KaminoEnv``: a Brax environment (``brax.envs.base.Env``) around one kamino world (docs/envs.md).

What every task shares:

- **Rates.** The simulator runs at ``sim_dt``; one ``step`` is ``decimation`` simulator steps (a ``lax.scan``), so
  the policy runs at ``1 / (sim_dt * decimation)`` Hz (``env.dt``).
- **Actions.** ``action_size`` = the model's actuators (POSITION mode only); an action in ``[-1, 1]`` (clipped) maps
  linearly onto ``[action_lower, action_upper]`` per actuator, the intersection of the joint limits, the actuator's
  ``ctrl_range`` and the task's range, and becomes the implicit PD's position target
  (``kamino.Control.position_target``).
- **Resets close the loops.** A reset configuration is a draw of actuated coordinates (and a floating base's
  pose) solved by ``kamino.forward_kinematics`` (every joint and loop closure, to its 1e-6 tolerance); a floating
  robot is then lowered onto the ground, and a task may move the whole configuration rigidly (a heading). Two
  modes (``reset_bank``): FK inside the traced reset (it is jit- and vmap-able: a damped Gauss-Newton in a
  ``lax.while_loop``; a draw that does not converge falls back to the nominal configuration, solved and checked on
  the host at construction), or a bank of draws solved at construction by one batched FK, from which ``reset``
  samples (no FK compiled into the jitted resets).
- **Randomization.** ``env.sys`` (:class:`kamino.envs.system.EnvSystem`) holds masses, inertias, friction, PD gains,
  armature, damping, effort limits, gravity and an actuator delay; ``step`` reads them from ``self.sys``, so Brax's
  ``DomainRandomizationVmapWrapper`` (``randomization_fn``) randomizes the dynamics per environment, on both
  backends (on ``"warp"`` the FFI step takes the environments' parameters as inputs when ``sys`` differs from the
  nominal one, and steps the model's own, with no parameter copies, when it does not).
- **Observation noise** ``obs_noise`` times a per-entry scale the task gives.
- **done** = the task's fall test, or the world's health flag (``state.info.failed``: non-finite or persistently
  unconverged solve, docs/conventions.md "World health"), or an observation entry beyond ``obs_limit`` or non-finite
  (a blown-up state, which the world's flag does not see while it stays finite). The last two count in
  ``metrics["failed"]``; observations are clipped to ``obs_limit``.
- **``pipeline_state``** is the world's :class:`kamino.State` without its zero-size arrays (``None`` in the fields the
  model does not use, e.g. ``contacts`` of a robot without contact capacity): XLA's GPU compiler crashes on a
  zero-size array carried through a loop on several GPUs (:func:`kamino.state.drop_empty`). ``env.full_state``
  gives the whole State.
- **Fixed structure.** ``metrics`` (the reward terms and ``failed``) and ``info`` have the same keys, shapes and
  dtypes at reset and at step (Brax's ``lax.scan`` over steps and ``AutoResetWrapper`` need it).

Brax's ``AutoResetWrapper`` resets ``pipeline_state`` and ``obs`` of a finished episode to those of its first
reset but keeps ``info``; when ``info["steps"]`` (Brax's ``EpisodeWrapper`` counter) reads 0 the episode has
restarted, and the environment restores its episode memory (last action, task variables) from the reset's copy in
``info["reset_memory"]``, so obs, info and the simulator state agree again.
"""

from __future__ import annotations

import dataclasses
from typing import ClassVar

import jax
import jax.numpy as jnp
import numpy as np
from brax.envs.base import Env
from brax.envs.base import State as BraxState

from kamino.checks import check_state
from kamino.config import BACKENDS, SolverConfig
from kamino.envs.geometry import ground_height, place_on_ground, support_points
from kamino.envs.system import EnvSystem
from kamino.kinematics import base_bodies, forward_kinematics, init_state
from kamino.model import ActuationMode, Model, replicate
from kamino.readouts import dof_state
from kamino.simulator import DEFAULT_BACKEND, Simulator
from kamino.state import Control, State, bind, drop_empty, fill_empty


def actuator_target_range(model: Model) -> tuple[np.ndarray, np.ndarray]:
    """``(lower, upper)`` PD targets of ``model``'s actuators (actuator order): their DoFs' limits within their
    control ranges; an environment's actions ``-1`` and ``+1`` map to them."""
    dof = np.asarray(model.actuator_dof)
    return (np.maximum(model.dof_lower[dof], model.actuator_ctrl_range[:, 0]),
            np.minimum(model.dof_upper[dof], model.actuator_ctrl_range[:, 1]))


class KaminoEnv(Env):
    """A Brax ``Env`` simulating one world of ``model`` with kamino (subclass it for a task: docs/envs.md).

    Args:
        model: a one-world :class:`kamino.Model` whose actuators are all POSITION (PD) actuators.
        sim_dt: the simulator step [s].
        decimation: simulator steps per environment step (the policy period is ``sim_dt * decimation``).
        backend: ``"warp"`` (the default, ``kamino.DEFAULT_BACKEND``: kamino's Warp step through its JAX FFI, which
            ``jax.vmap`` batches over environments: ``kamino.warp_backend.jit.batchable_step``; domain
            randomization passes each environment's parameters to that step) or ``"jax"`` (the reference; gradients
            too).
        solver_config: the :class:`kamino.SolverConfig` of each simulator step; its ``dt`` is replaced by
            ``sim_dt``.
        action_lower, action_upper: the PD-target range per actuator (scalars broadcast), intersected with the
            joint limits and ``ctrl_range``; required where those are unbounded.
        obs_noise: scale of the Gaussian observation noise (times the task's per-entry scale; 0: none).
        obs_limit: the bound on every observation entry (legged_gym's ``clip_observations``, 100). An entry beyond
            it, or non-finite, means the simulated state has blown up: the episode ends and counts as ``failed``, and
            the observation passed on is clipped, so that such a state reaches neither the policy nor the
            observation normaliser. A task scales its entries to order one (velocities by 0.05-0.25), so 100 lies
            far beyond any state a robot reaches.
        reset_noise: half-width of the uniform draw of the actuated coordinates at reset, as a fraction of each
            actuator's half-range, about the nominal (centre) target.
        resample_steps: policy steps between draws of the task variables (``None``: once per episode).
        reset_bank: ``None``: every ``reset`` solves its own draw by forward kinematics (traced, inside
            ``jit``/``vmap``); an integer ``n``: ``n`` draws solved at construction by one batched FK (seed
            ``reset_seed``), and ``reset`` picks one at random: no FK to compile into every jitted reset (brax compiles
            reset for training and again for evaluation), the same distribution up to the bank's size.
        reset_seed: the seed of the bank's draws.
        dtype: the simulation and observation dtype (float32 for learning, whatever ``jax_enable_x64`` says).
        compile_for: Warp backend: the number of environments that ``jax.vmap`` will step together (brax's
            ``num_envs`` per device); their step's Warp kernels start compiling in a background thread before the
            reset bank is solved, so that compilation overlaps the rest of the setup
            (``kamino.warp_backend.backend.Engine.compile_in_background``). ``None``: they compile at the first
            traced step.
    """

    #: names of the reward terms (``metrics`` keys, with ``failed``); set by each task
    reward_terms: ClassVar[tuple[str, ...]] = ()
    #: task variables kept in ``info`` (e.g. a target), redrawn every ``resample_steps`` policy steps
    task_keys: ClassVar[tuple[str, ...]] = ()
    #: the test ``kamino eval`` and ``kamino train --walk-test`` run (:func:`kamino.envs.evaluate.task_test`):
    #: ``"walking"`` (joystick tasks), ``"show"`` (``olaf_show``) or ``"return"`` (the episode return)
    evaluation: ClassVar[str] = "return"

    def __init__(self, model: Model, *, sim_dt: float, decimation: int, backend: str = DEFAULT_BACKEND,
                 solver_config: SolverConfig | None = None, action_lower=None, action_upper=None,
                 obs_noise: float = 0.0, reset_noise: float = 0.1, resample_steps: int | None = None,
                 reset_bank: int | None = None, reset_seed: int = 0, obs_limit: float = 100.0, dtype=jnp.float32,
                 compile_for: int | None = None):
        if not isinstance(model, Model):
            raise TypeError(f"{type(self).__name__}: model must be a kamino.Model, got {type(model).__name__}")
        if model.num_worlds != 1:
            raise ValueError(f"{type(self).__name__}: model has {model.num_worlds} worlds; an environment is one "
                             "world (brax vmaps environments)")
        if backend not in BACKENDS:
            raise ValueError(f"{type(self).__name__}: unknown backend {backend!r} (the backend= argument); choose "
                             f"one of {BACKENDS}")
        if not (isinstance(sim_dt, (int, float)) and np.isfinite(sim_dt) and sim_dt > 0):
            raise ValueError(f"{type(self).__name__}: sim_dt must be a positive number of seconds, got {sim_dt!r}")
        if isinstance(decimation, bool) or not isinstance(decimation, (int, np.integer)) or decimation < 1:
            raise ValueError(f"{type(self).__name__}: decimation must be an integer >= 1, got {decimation!r}")
        for name, value in (("obs_noise", obs_noise), ("reset_noise", reset_noise)):
            if not (isinstance(value, (int, float)) and np.isfinite(value) and value >= 0):
                raise ValueError(f"{type(self).__name__}: {name} must be a finite number >= 0, got {value!r}")
        if not (isinstance(obs_limit, (int, float)) and np.isfinite(obs_limit) and obs_limit > 0):
            raise ValueError(f"{type(self).__name__}: obs_limit must be a finite number > 0, got {obs_limit!r}")
        if resample_steps is not None and (not isinstance(resample_steps, (int, np.integer)) or resample_steps < 1):
            raise ValueError(f"{type(self).__name__}: resample_steps must be None or an integer >= 1, got "
                             f"{resample_steps!r}")
        if compile_for is not None and (isinstance(compile_for, bool) or not isinstance(compile_for, (int, np.integer))
                                        or compile_for < 1 or backend != "warp"):
            raise ValueError(f"{type(self).__name__}: compile_for must be None or an integer >= 1 with the Warp "
                             f"backend, got {compile_for!r} with backend {backend!r}")
        if solver_config is not None and not isinstance(solver_config, SolverConfig):
            raise TypeError(f"{type(self).__name__}: solver_config must be a kamino.SolverConfig, got "
                            f"{type(solver_config).__name__}")
        self._model = model
        self._backend = backend
        self._dtype = jnp.dtype(dtype)
        self._decimation = int(decimation)
        self._config = dataclasses.replace(solver_config or self.default_solver_config(), dt=float(sim_dt))
        self._obs_noise = float(obs_noise)
        self._obs_limit = float(obs_limit)
        self._reset_noise = float(reset_noise)
        self._resample_steps = None if resample_steps is None else int(resample_steps)
        self._sim = Simulator(model, self._config, backend=backend)
        if compile_for is not None:
            self._sim.engine.compile_in_background(int(compile_for), self._dtype)
        self._pm, self._tables = self._sim.parameters(self._dtype) if backend == "jax" else (None, None)
        self.sys = EnvSystem.from_model(model, self._dtype)
        self._nominal_sys = self.sys
        self._act_dof = np.asarray(model.actuator_dof, np.int32)  # int32: indices stay valid whatever x64 says
        self._act_lo, self._act_hi = self._action_range(action_lower, action_upper)
        self._base = int(base_bodies(model)[0])
        self._support = support_points(model)
        self._ground = ground_height(model)
        self._template = init_state(model, dtype=self._dtype)
        check_state(model, self._template, type(self).__name__)
        if reset_bank is None:
            self._bank = None
            self._nominal_q = self._nominal_body_q()
        else:
            if isinstance(reset_bank, bool) or not isinstance(reset_bank, (int, np.integer)) or reset_bank < 1:
                raise ValueError(f"{type(self).__name__}: reset_bank must be None (forward kinematics in every "
                                 f"reset) or an integer >= 1 (configurations solved at construction), got "
                                 f"{reset_bank!r}")
            self._bank = self._solve_bank(int(reset_bank), int(reset_seed))

    @classmethod
    def default_solver_config(cls) -> SolverConfig:
        """The :class:`kamino.SolverConfig` the task steps with when no ``solver_config`` is given (its ``dt`` is
        replaced by ``sim_dt``)."""
        return SolverConfig()

    @property
    def simulator(self) -> Simulator:
        """The :class:`kamino.Simulator` that steps this environment's world."""
        return self._sim

    # ------------------------------------------------------------------ Brax's Env interface

    @property
    def observation_size(self) -> int:
        return int(self._obs_size())

    @property
    def action_size(self) -> int:
        return int(self._model.num_actuators)

    @property
    def backend(self) -> str:
        return self._backend

    @property
    def dt(self) -> float:
        """The policy period [s]: ``sim_dt * decimation``."""
        return self._config.dt * self._decimation

    @property
    def sim_dt(self) -> float:
        return self._config.dt

    @property
    def decimation(self) -> int:
        return self._decimation

    @property
    def model(self) -> Model:
        return self._model

    @property
    def solver_config(self) -> SolverConfig:
        return self._config

    @property
    def dtype(self) -> np.dtype:
        return self._dtype

    @property
    def action_lower(self) -> np.ndarray:
        """``[action_size]`` PD target at action -1."""
        return self._act_lo.copy()

    @property
    def action_upper(self) -> np.ndarray:
        """``[action_size]`` PD target at action +1."""
        return self._act_hi.copy()

    def reset(self, rng: jax.Array) -> BraxState:
        """A new episode: loop-closed random configuration at rest, fresh task variables (docs/envs.md)."""
        self._check_sys("reset")
        rng, k_pose, k_task, k_noise = jax.random.split(rng, 4)
        ps = self.reset_state(k_pose)
        task = {k: jnp.asarray(v) for k, v in self._sample_task(k_task).items()}
        last_action = jnp.zeros(self.action_size, self._dtype)
        memory = {"last_action": last_action, "task_steps": jnp.zeros((), jnp.int32), **task,
                  **self._episode_memory()}
        info = {"rng": rng, **memory, "reset_memory": dict(memory)}
        obs = self._bounded(self._noisy(self._observe(ps, info), k_noise))
        zero = jnp.zeros((), self._dtype)
        metrics = {name: zero for name in self.reward_terms} | {"failed": zero}
        return BraxState(pipeline_state=drop_empty(ps), obs=obs, reward=zero, done=zero, metrics=metrics, info=info)

    def step(self, state: BraxState, action: jax.Array) -> BraxState:
        """``decimation`` simulator steps towards the PD targets of ``action``; reward, done, next observation."""
        self._check_sys("step")
        action = jnp.asarray(action, self._dtype)
        if action.shape != (self.action_size,):
            raise ValueError(f"{type(self).__name__}.step: action has shape {action.shape}, expected "
                             f"({self.action_size},) (one per actuator; brax's VmapWrapper batches environments)")
        info = dict(state.info)
        if "steps" in info:  # brax's EpisodeWrapper counter: 0 right after an (auto-)reset
            restarted = info["steps"] == 0
            info.update(jax.tree.map(lambda first, now: jnp.where(restarted, first, now), info["reset_memory"],
                                     {k: info[k] for k in info["reset_memory"]}))
        a = jnp.clip(action, -1.0, 1.0)
        prev_ps = self.full_state(state.pipeline_state)
        ps = self._simulate(prev_ps, self.action_to_target(info["last_action"]), self.action_to_target(a))
        reward, terms = self._reward(prev_ps, ps, a, info)
        failed = ps.info.failed[0]
        terminated = self._terminated(ps, info)
        rng, k_task, k_noise = jax.random.split(info["rng"], 3)
        steps = info["task_steps"] + 1
        info.update(self._update_memory(ps, info), rng=rng, last_action=a, task_steps=steps)
        if self.task_keys and self._resample_steps is not None:
            new = self._sample_task(k_task)
            due = steps % self._resample_steps == 0
            info.update({k: jnp.where(due, jnp.asarray(new[k]), info[k]) for k in self.task_keys})
        obs = self._observe(ps, info)
        blown_up = ~jnp.all(jnp.abs(obs) <= self._obs_limit)  # also true for a non-finite entry
        failed = failed | blown_up
        done = terminated | failed
        obs = self._bounded(self._noisy(jnp.where(jnp.isfinite(obs), obs, 0.0), k_noise))
        reward = jnp.where(jnp.isfinite(reward), reward, 0.0).astype(self._dtype)
        # update the incoming dicts: wrappers add their own keys (brax's EvalWrapper: metrics["reward"])
        metrics = dict(state.metrics)
        metrics.update({k: jnp.asarray(v, self._dtype) for k, v in terms.items()}, failed=failed.astype(self._dtype))
        return state.replace(pipeline_state=drop_empty(ps), obs=obs, reward=reward, done=done.astype(self._dtype),
                             metrics=metrics, info=info)

    # ------------------------------------------------------------------ shared machinery

    def action_to_target(self, action: jax.Array) -> jax.Array:
        """PD position targets ``[action_size]`` of actions in ``[-1, 1]`` (clipped): a linear map onto
        ``[action_lower, action_upper]``."""
        lo, hi = jnp.asarray(self._act_lo, self._dtype), jnp.asarray(self._act_hi, self._dtype)
        a = jnp.clip(jnp.asarray(action, self._dtype), -1.0, 1.0)
        return 0.5 * (lo + hi) + 0.5 * (hi - lo) * a

    def reset_state(self, rng: jax.Array) -> State:
        """A kamino State at rest in a random loop-closed configuration (traced: FK inside ``jit``/``vmap``)."""
        k_config, k_pose = jax.random.split(rng)
        if self._bank is not None:
            body_q = jnp.asarray(self._bank)[jax.random.randint(k_config, (), 0, self._bank.shape[0])]
        else:
            q_act, base_pose = self._sample_configuration(k_config)
            fk = forward_kinematics(self._model, actuated_positions=q_act, base_pose=base_pose, dtype=self._dtype)
            body_q = jnp.where(fk.converged[0], fk.body_q, jnp.asarray(self._nominal_q, self._dtype))
            body_q = self._place(body_q)
        return self._template.replace(body_q=self._move_rigidly(body_q, k_pose))

    def full_state(self, pipeline_state: State) -> State:
        """The whole :class:`kamino.State` of a ``pipeline_state``: the environment carries it without its zero-size
        arrays (``None`` fields; :func:`kamino.state.drop_empty` says why). Leading axes (a batch, a time axis)
        are kept."""
        return fill_empty(pipeline_state, self._template)

    def actuated_state(self, ps: State) -> tuple[jax.Array, jax.Array]:
        """``(positions, rates)`` of the actuated DoFs ``[action_size]`` (actuator order)."""
        q, qd = dof_state(self._model, ps)
        return q[self._act_dof], qd[self._act_dof]

    def _simulate(self, ps: State, prev_target: jax.Array, target: jax.Array) -> State:
        """``decimation`` simulator steps; substeps starting before ``sys.action_delay`` keep ``prev_target``."""
        sys = self.sys
        nd = self._model.num_dofs

        def control(tgt):
            return Control(position_target=jnp.zeros(nd, self._dtype).at[self._act_dof].set(tgt))

        # the loop neither carries nor closes over a zero-size array (kamino.state.drop_empty says why)
        if self._backend == "jax":
            params = (sys.apply(self._pm), self._tables)
        else:  # the Warp step reads the model's own parameters unless a randomization changed env.sys
            params = None if sys is self._nominal_sys else sys.world_parameters()
        compact = drop_empty(params)

        def body(s, k):
            late = k * self._config.dt < sys.action_delay
            s = self._physics_step(None if params is None else fill_empty(compact, params), self.full_state(s),
                                   control(jnp.where(late, prev_target, target)))
            return drop_empty(s), None

        ps, _ = jax.lax.scan(body, drop_empty(ps), jnp.arange(self._decimation, dtype=self._dtype))
        return self.full_state(ps)

    def _physics_step(self, params, ps: State, control: Control) -> State:
        """One simulator step. JAX reference: ``params`` is the padded model carrying this environment's parameters
        (``sys.apply``) and the layout tables (``Simulator.step_with``: the host Model cannot carry traced
        parameters). Warp: ``params`` is ``None`` (the model's own parameters) or this environment's
        (``sys.world_parameters()``), inputs of the FFI step (``kamino.warp_backend.parameters``)."""
        if params is None:
            return self._sim.step(ps, control)
        if self._backend == "jax":
            return self._sim.step_with(params, ps, control)
        return bind(self._sim.engine.step(bind(ps, None), control, params), ps.model_fingerprint)

    def _check_sys(self, where: str) -> None:
        """``env.sys`` must be an :class:`EnvSystem` with the nominal one's shapes (a randomization scales values,
        it does not change the model's structure)."""
        sys = self.sys
        if sys is self._nominal_sys:
            return
        if not isinstance(sys, EnvSystem):
            raise TypeError(f"{type(self).__name__}.{where}: env.sys must be a kamino.envs.EnvSystem, got "
                            f"{type(sys).__name__}")
        for f in dataclasses.fields(EnvSystem):
            got, want = jnp.shape(getattr(sys, f.name)), jnp.shape(getattr(self._nominal_sys, f.name))
            if got != want:
                raise ValueError(f"{type(self).__name__}.{where}: env.sys.{f.name} has shape {got} (per environment), "
                                 f"expected {want}")

    def _bounded(self, obs: jax.Array) -> jax.Array:
        """``obs`` clipped to ``[-obs_limit, obs_limit]`` (the constructor's ``obs_limit``)."""
        return jnp.clip(obs, -self._obs_limit, self._obs_limit)

    def _noisy(self, obs: jax.Array, rng: jax.Array) -> jax.Array:
        obs = jnp.asarray(obs, self._dtype)
        if self._obs_noise == 0.0:
            return obs
        scale = jnp.asarray(self._obs_noise_scale(), self._dtype)
        return obs + self._obs_noise * scale * jax.random.normal(rng, obs.shape, self._dtype)

    def _action_range(self, lower, upper) -> tuple[np.ndarray, np.ndarray]:
        m, name = self._model, type(self).__name__
        na = m.num_actuators
        if na == 0:
            raise ValueError(f"{name}: the model has no actuators (nothing for a policy to act on)")
        modes = m.dof_act_mode[self._act_dof]
        bad = [m.actuator_names[i] for i in np.nonzero(modes != int(ActuationMode.POSITION))[0]]
        if bad:
            raise ValueError(f"{name}: actuators {bad} are not POSITION (PD) actuators; actions map to PD position "
                             "targets (kamino.Actuation('position', kp, kd))")
        lo, hi = actuator_target_range(m)
        for arg, value, pick in (("action_lower", lower, np.maximum), ("action_upper", upper, np.minimum)):
            if value is None:
                continue
            v = np.broadcast_to(np.asarray(value, float), (na,)) if np.ndim(value) == 0 else np.asarray(value, float)
            if v.shape != (na,) or not np.all(np.isfinite(v)):
                raise ValueError(f"{name}: {arg} must be a finite scalar or {na} finite values (one per actuator "
                                 f"{list(m.actuator_names)}), got {value!r}")
            if arg == "action_lower":
                lo = pick(lo, v)
            else:
                hi = pick(hi, v)
        unbounded = [m.actuator_names[i] for i in np.nonzero(~(np.isfinite(lo) & np.isfinite(hi)))[0]]
        if unbounded:
            raise ValueError(f"{name}: actuators {unbounded} have no finite joint limit or ctrl_range; give "
                             "action_lower and action_upper (the PD-target range an action of -1 and +1 maps to)")
        empty = [m.actuator_names[i] for i in np.nonzero(lo >= hi)[0]]
        if empty:
            raise ValueError(f"{name}: actuators {empty} have an empty action range (action_lower >= action_upper "
                             "after intersecting with the joint limits)")
        return lo.astype(np.float64), hi.astype(np.float64)

    def _solve_bank(self, size: int, seed: int) -> np.ndarray:
        """``[n <= size, num_bodies, 7]``: ``size`` draws of :meth:`_sample_configuration` solved by one batched
        ``kamino.forward_kinematics`` over ``kamino.replicate(model, size)``, placed; unconverged draws dropped."""
        many = replicate(self._model, size)

        @jax.jit  # one compiled program instead of FK's host-side operations one by one
        def solve(keys):
            q_act, base_pose = jax.vmap(self._sample_configuration)(keys)
            fk = forward_kinematics(many, actuated_positions=jnp.reshape(q_act, -1), base_pose=base_pose,
                                    dtype=self._dtype)
            body_q = jax.vmap(self._place)(jnp.reshape(fk.body_q, (size, self._model.num_bodies, 7)))
            return body_q, fk.converged, fk.residual

        body_q, ok, residual = (np.asarray(x) for x in solve(jax.random.split(jax.random.PRNGKey(seed), size)))
        if not ok.any():
            raise ValueError(f"{type(self).__name__}: forward kinematics converged for none of the {size} reset "
                             f"configurations (largest residual {float(residual.max()):.2e}); check the action "
                             "range and reset_noise")
        return body_q[ok]

    def _nominal_body_q(self) -> np.ndarray:
        """The nominal reset (centre targets, nominal base pose) solved on the host; raises if FK fails."""
        q_act, base_pose = self._nominal_configuration()

        @jax.jit  # one compiled program instead of FK's host-side operations one by one
        def solve(q_act, base_pose):
            fk = forward_kinematics(self._model, actuated_positions=q_act, base_pose=base_pose, dtype=self._dtype)
            return self._place(fk.body_q), fk.converged[0], fk.residual[0]

        body_q, ok, residual = solve(jnp.asarray(q_act, self._dtype), base_pose)
        if not bool(ok):
            raise ValueError(f"{type(self).__name__}: forward kinematics of the nominal reset configuration did not "
                             f"converge (residual {float(residual):.2e}); check the action range")
        return np.asarray(body_q)

    def _place(self, body_q: jax.Array) -> jax.Array:
        """A floating robot lowered (or raised) so that its lowest geom touches the ground; fixed bases as is."""
        if self._base < 0:
            return body_q
        pts, bodies, radii = self._support
        return place_on_ground(body_q, jnp.asarray(pts, body_q.dtype), bodies, jnp.asarray(radii, body_q.dtype),
                               self._ground + self._ground_clearance())

    # ------------------------------------------------------------------ task hooks (override in a task)

    def _nominal_configuration(self) -> tuple[np.ndarray, np.ndarray | None]:
        """Actuated coordinates and base pose of the nominal reset: centre targets, the builder's base pose."""
        return 0.5 * (self._act_lo + self._act_hi), None

    def _sample_configuration(self, rng: jax.Array) -> tuple[jax.Array, jax.Array | None]:
        """Random reset coordinates: the nominal ones plus ``reset_noise`` of each half-range, uniform."""
        mid, half = 0.5 * (self._act_lo + self._act_hi), 0.5 * (self._act_hi - self._act_lo)
        u = jax.random.uniform(rng, (self.action_size,), self._dtype, -1.0, 1.0)
        q = jnp.asarray(mid, self._dtype) + self._reset_noise * jnp.asarray(half, self._dtype) * u
        return jnp.clip(q, self._act_lo, self._act_hi).astype(self._dtype), None

    def _move_rigidly(self, body_q: jax.Array, rng: jax.Array) -> jax.Array:
        """A rigid motion of the whole solved configuration at reset (a floating robot's heading, say): it keeps
        every joint and loop closed, and costs no FK iterations. Default: none."""
        return body_q

    def _ground_clearance(self) -> float:
        """Gap [m] between the lowest geom and the ground after placement."""
        return 0.0

    def _episode_memory(self) -> dict[str, jax.Array]:
        """Per-episode state a task's reward reads (``info`` entries), at its values at reset; an auto-reset restores
        them (``info["reset_memory"]``). Default: none."""
        return {}

    def _update_memory(self, ps: State, info: dict) -> dict[str, jax.Array]:
        """The entries of :meth:`_episode_memory` after a policy step that reached ``ps`` (``info`` as the reward saw
        it). Default: none."""
        return {}

    def _sample_task(self, rng: jax.Array) -> dict[str, jax.Array]:
        """Task variables (the keys of ``task_keys``), drawn at reset and every ``resample_steps``."""
        return {}

    def _obs_size(self) -> int:
        raise NotImplementedError

    def _observe(self, ps: State, info: dict) -> jax.Array:
        raise NotImplementedError

    def _obs_noise_scale(self) -> np.ndarray:
        """Per-entry scale of the observation noise ``[observation_size]`` (default: all ones)."""
        return np.ones(self._obs_size())

    def _reward(self, prev: State, ps: State, action: jax.Array, info: dict) -> tuple[jax.Array, dict]:
        raise NotImplementedError

    def _terminated(self, ps: State, info: dict) -> jax.Array:
        """The task's own termination (a fall); the health flag is added by ``step``."""
        return jnp.zeros((), bool)


__all__ = ["BACKENDS", "KaminoEnv", "actuator_target_range"]
