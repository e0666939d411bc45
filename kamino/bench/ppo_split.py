"""PPO's time split into collection and learning, and the learner's ceiling (the null environment).

    python -m kamino.bench.ppo_split [TASK] [--backend warp] [--steps-per-epoch 2] [--epochs 3]
                                       [--num-envs N] [--set KEY=VALUE ...] [--solver KEY=VALUE ...]
                                       [--env KEY=VALUE ...] [--out FILE]

The training configuration is the one ``kamino train TASK`` starts a new run with: the task's
``kamino.envs.configs.PPO_CONFIGS`` entry (its network sizes, ``num_envs``, ``batch_size``, ``unroll_length``,
``num_minibatches``, ``num_updates_per_batch``, ...), ``--num-envs`` and ``--set`` (any ``ppo.train`` keyword)
over it, ``--env`` over the task's environment keywords and ``--solver`` over its ``SolverConfig``; one device
(``max_devices_per_host=1`` unless ``--set`` says otherwise). Brax's training step collects
``batch_size x num_minibatches`` trajectories of ``unroll_length`` env steps (``batch_size x num_minibatches /
num_envs`` unrolls of every environment), then learns from them: the observation normaliser's update and
``num_updates_per_batch x num_minibatches`` SGD steps. ``E = batch_size x unroll_length x num_minibatches x
action_repeat`` env steps per training step.

Two environments run the same measurement: the **null environment** (:class:`NullEnv`: the task's observation and
action sizes, a reset and step that do no physics, only a few cheap deterministic arrays), then the task. For each:

1. **PPO** (``train``): brax's ``ppo.train``, unchanged, with the configuration above, for ``2 + epochs`` epochs of
   ``steps-per-epoch`` training steps each and no evaluations (``run_evals=False``). Brax times each epoch itself
   (``training/walltime`` in its ``progress_fn``: the jitted epoch from its call until its metrics are ready). The
   first two epochs are the warm-up (:data:`WARMUP_EPOCHS`: the first compiles the epoch, the second compiles it
   again for the training state the first returns), the median of the other ``epochs`` is the epoch time
   ``T_epoch``.
   PPO env steps/s = ``steps-per-epoch x E / T_epoch`` (brax's ``training/sps``; ``kamino train`` reports the
   same figure for each epoch, which excludes the evaluations).
2. **Collection alone** (``collect``): the training step's collection on its own, built from brax's pieces:
   the environment through brax's training wrappers (``envs.training.wrap``: Vmap, Episode, AutoReset), the
   policy of the same networks (``network_factory``, ``make_inference_fn``, the observation normaliser; the initial
   parameters, as in the first epochs of training), stochastic actions, and ``acting.generate_unroll`` with the
   extra fields PPO keeps, in the same nesting of ``lax.scan`` as brax's epoch. Each training step's transitions
   are summed to a scalar so that no field of them is left out of the compiled program. One jitted call per epoch;
   two warm-up calls, then the median of ``epochs`` calls is ``T_collect``.
3. **The split**: collection ``T_collect / steps-per-epoch`` and learning ``(T_epoch - T_collect) /
   steps-per-epoch`` seconds per training step, and their shares of ``T_epoch`` (learning here is everything of
   brax's training step that is not the collection: the batch's reshaping, the normaliser update and the SGD).
   Learning is a difference of two medians: on a machine shared with other work it can come out below zero when
   the learning is small against the collection; ``epoch_min_s`` (the fastest epoch of each) is the steadier
   figure there, since other work only adds time.

The learner does not see the physics, so the learning time of the task and of the null environment estimate the same
thing; the record gives both (``learn_s_per_training_step``) and the task's epoch time predicted as its collection
plus the null environment's learning (``predicted_epoch_s``). The null environment's PPO env steps/s is the
**ceiling**: what brax's learner (and the policy's inference in the collection) allows at these sizes whatever the
simulator costs. The record also carries ``environment()`` of :mod:`kamino.bench.throughput` (GPU, versions,
command) without that benchmark's own solver settings.
"""

from __future__ import annotations

import argparse
import itertools
import pathlib
import statistics
import time

import jax
import jax.numpy as jnp
from brax.envs.base import Env
from brax.envs.base import State as BraxState

from kamino.bench.ppo_collect import emit_record

#: untimed epochs before the timed ones, in PPO and in the collection alone
WARMUP_EPOCHS = 2


class NullEnv(Env):
    """A Brax environment of ``observation_size`` observations and ``action_size`` actions whose reset and step do
    no physics: the learner's ceiling (module docstring).

    ``reset`` gives the observation ``linspace(-1, 1, observation_size)``; ``step`` moves it halfway to the action
    tiled over the observation's length, ``o' = (o + tile(a)) / 2`` with ``a`` the action clipped to ``[-1, 1]``,
    with the reward ``-mean(a^2)`` and never ``done`` (episodes end by brax's ``episode_length`` only). The
    observation depends on the actions so that the collection's chain policy -> step -> policy stays a chain in the
    compiled program."""

    def __init__(self, observation_size: int, action_size: int):
        if observation_size < 1 or action_size < 1:
            raise ValueError(f"NullEnv: sizes must be >= 1, got {observation_size} observations and "
                             f"{action_size} actions")
        self._obs_size, self._act_size = int(observation_size), int(action_size)

    @property
    def observation_size(self) -> int:
        return self._obs_size

    @property
    def action_size(self) -> int:
        return self._act_size

    @property
    def backend(self) -> str:
        return "null"

    def reset(self, rng: jax.Array) -> BraxState:
        obs = jnp.linspace(-1.0, 1.0, self._obs_size, dtype=jnp.float32)
        zero = jnp.zeros((), jnp.float32)
        return BraxState(pipeline_state=None, obs=obs, reward=zero, done=zero, metrics={}, info={})

    def step(self, state: BraxState, action: jax.Array) -> BraxState:
        a = jnp.clip(jnp.asarray(action, jnp.float32), -1.0, 1.0)
        reps = -(-self._obs_size // self._act_size)
        obs = 0.5 * (state.obs + jnp.tile(a, reps)[: self._obs_size])
        return state.replace(obs=obs, reward=-jnp.mean(a * a), done=jnp.zeros((), jnp.float32))


def parse_args(argv: list[str] | None = None, prog: str | None = None) -> argparse.Namespace:
    from kamino.envs.configs import PPO_CONFIGS
    from kamino.simulator import DEFAULT_BACKEND

    p = argparse.ArgumentParser(prog=prog or "kamino bench ppo_split", description=__doc__.splitlines()[0])
    p.add_argument("task", nargs="?", default="dr_legs_joystick", choices=sorted(PPO_CONFIGS),
                   help="a task of kamino train (default dr_legs_joystick)")
    p.add_argument("--backend", choices=("jax", "warp"), default=DEFAULT_BACKEND)
    p.add_argument("--steps-per-epoch", type=int, default=2, metavar="N",
                   help="training steps per epoch (default 2)")
    p.add_argument("--epochs", type=int, default=3, metavar="K",
                   help=f"timed epochs after the {WARMUP_EPOCHS} warm-up ones (default 3)")
    p.add_argument("--num-envs", type=int, default=None, help="parallel environments (default: the task's config)")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="a ppo.train keyword, VALUE a Python literal (repeatable), as kamino train --set")
    p.add_argument("--solver", action="append", default=[], metavar="KEY=VALUE",
                   help="a SolverConfig setting, dotted for a nested one, VALUE as kamino train --solver (repeatable)")
    p.add_argument("--env", action="append", default=[], metavar="KEY=VALUE",
                   help="an environment keyword, VALUE a Python literal (repeatable)")
    p.add_argument("--out", type=pathlib.Path, default=None, help="append the JSON record to this file")
    args = p.parse_args(argv)
    if args.steps_per_epoch < 1 or args.epochs < 1:
        p.error("--steps-per-epoch and --epochs must be >= 1")
    if args.num_envs is not None and args.num_envs < 1:
        p.error(f"--num-envs must be >= 1, got {args.num_envs}")
    from kamino.config import solver_settings
    from kamino.envs.runs import key_values

    try:
        args.ppo_overrides = key_values(args.set, "--set")
        args.solver_overrides = solver_settings(args.solver)
        args.env_overrides = key_values(args.env, "--env")
    except ValueError as e:
        p.error(str(e))
    for name in ("num_timesteps", "num_evals", "run_evals", "progress_fn"):
        if name in args.ppo_overrides:
            p.error(f"--set {name}: the benchmark sets it (--steps-per-epoch and --epochs size the run)")
    return args


def training_config(task: str, num_envs: int | None = None, ppo: dict | None = None) -> dict:
    """The ``ppo.train`` keywords of a new ``kamino train`` run of ``task`` (``kamino.envs.configs.ppo_kwargs``)
    with ``num_envs`` and ``ppo`` over them, on one device unless ``ppo`` sets ``max_devices_per_host``. Raises
    ``ValueError`` when a training step's ``batch_size x num_minibatches`` trajectories are not whole unrolls of the
    ``num_envs`` environments (brax's own condition)."""
    from kamino.envs.configs import ppo_kwargs

    overrides = {"max_devices_per_host": 1, **(ppo or {})}
    if num_envs is not None:
        overrides["num_envs"] = num_envs
    kwargs = ppo_kwargs(task, **overrides)
    n, trajectories = int(kwargs["num_envs"]), int(kwargs["batch_size"]) * int(kwargs["num_minibatches"])
    if trajectories % n:
        raise ValueError(f"batch_size x num_minibatches = {trajectories} trajectories per training step are not "
                         f"whole unrolls of num_envs = {n} environments; choose sizes that divide")
    return kwargs


def env_steps_per_training_step(kwargs: dict) -> int:
    """``E = batch_size x unroll_length x num_minibatches x action_repeat`` (brax's ``env_step_per_training_step``)."""
    return (int(kwargs["batch_size"]) * int(kwargs["unroll_length"]) * int(kwargs["num_minibatches"])
            * int(kwargs.get("action_repeat", 1)))


def time_ppo(env: Env, kwargs: dict, steps_per_epoch: int, epochs: int) -> dict:
    """Brax's ``ppo.train`` of ``env`` for ``WARMUP_EPOCHS + epochs`` epochs of ``steps_per_epoch`` training steps, no
    evaluations; each epoch's time as brax measures it (the differences of ``training/walltime``), the warm-up's kept
    apart. Returns ``epoch_s`` (the median timed epoch), ``epoch_min_s`` (the fastest), ``epochs_s`` (every timed
    epoch), ``warmup_epochs_s``, ``env_steps_per_s`` and ``setup_s`` (from the call to the first epoch's start:
    building, resets)."""
    from brax.training.agents.ppo import train as ppo_train

    walls: list[tuple[float, float]] = []
    unit, total = env_steps_per_training_step(kwargs), WARMUP_EPOCHS + epochs
    run = dict(kwargs, num_timesteps=total * steps_per_epoch * unit, num_evals=total + 1, run_evals=False,
               progress_fn=lambda step, metrics: walls.append((float(metrics["training/walltime"]),
                                                                time.perf_counter())))
    t0 = time.perf_counter()
    with jax.enable_x64(False):  # as kamino train: brax's wrappers build float32 info entries at step only
        ppo_train.train(environment=env, **run)
    if len(walls) != total:
        raise RuntimeError(f"ppo.train reported {len(walls)} epochs, expected {total}")
    brax_walls = [0.0] + [w for w, _ in walls]
    times = [b - a for a, b in itertools.pairwise(brax_walls)]
    epoch = statistics.median(times[WARMUP_EPOCHS:])
    return {"epoch_s": epoch, "epoch_min_s": min(times[WARMUP_EPOCHS:]), "epochs_s": times[WARMUP_EPOCHS:],
            "warmup_epochs_s": times[:WARMUP_EPOCHS],
            "setup_s": walls[0][1] - t0 - times[0], "env_steps_per_s": steps_per_epoch * unit / epoch}


def time_collection(env: Env, kwargs: dict, steps_per_epoch: int, epochs: int) -> dict:
    """The collection of ``steps_per_epoch`` training steps of brax's PPO (module docstring, 2.), one jitted call
    per epoch: ``WARMUP_EPOCHS`` warm-up calls, then ``epochs`` timed calls. Returns ``epoch_s`` (the median),
    ``epoch_min_s`` (the fastest), ``epochs_s``, ``warmup_epochs_s`` and ``env_steps_per_s``."""
    from brax import envs as brax_envs
    from brax.training import acting
    from brax.training.acme import running_statistics, specs
    from brax.training.agents.ppo import networks as ppo_networks

    n, unroll = int(kwargs["num_envs"]), int(kwargs["unroll_length"])
    unrolls = int(kwargs["batch_size"]) * int(kwargs["num_minibatches"]) // n
    wrapped = brax_envs.training.wrap(env, episode_length=int(kwargs["episode_length"]),
                                      action_repeat=int(kwargs.get("action_repeat", 1)))
    normalize = running_statistics.normalize if kwargs.get("normalize_observations") else (lambda x, y: x)
    network = kwargs["network_factory"](env.observation_size, env.action_size, preprocess_observations_fn=normalize)
    make_policy = ppo_networks.make_inference_fn(
        network, compute_value=bool(kwargs.get("bootstrap_on_timeout")) or
        kwargs.get("clipping_epsilon_value") is not None)
    key_policy, key_value = jax.random.split(jax.random.PRNGKey(int(kwargs.get("seed", 0))))
    params = (running_statistics.init_state(specs.Array((env.observation_size,), jnp.dtype("float32"))),
              network.policy_network.init(key_policy), network.value_network.init(key_value))
    policy = make_policy(params, deterministic=False)
    fields = ("truncation", "episode_metrics", "episode_done") + (
        ("time_out",) if kwargs.get("bootstrap_on_timeout") else ())

    def epoch(state, key):
        def training_step(carry, _):
            s, k = carry
            k, k_unroll = jax.random.split(k)

            def one_unroll(c, _):
                s, kk = c
                kk, k_next = jax.random.split(kk)
                s, data = acting.generate_unroll(wrapped, s, policy, kk, unroll, extra_fields=fields)
                return (s, k_next), data

            (s, _), data = jax.lax.scan(one_unroll, (s, k_unroll), (), length=unrolls)
            total = sum(jnp.sum(x.astype(jnp.float32)) for x in jax.tree.leaves(data))
            return (s, k), total

        (state, _), totals = jax.lax.scan(training_step, (state, key), (), length=steps_per_epoch)
        return state, totals

    with jax.enable_x64(False):
        run = jax.jit(epoch, donate_argnums=0)
        state = jax.jit(wrapped.reset)(jax.random.split(jax.random.PRNGKey(0), n))
        jax.block_until_ready(state)
        times = []
        for r in range(WARMUP_EPOCHS + epochs):
            t0 = time.perf_counter()
            state, totals = run(state, jax.random.PRNGKey(1 + r))
            jax.block_until_ready((state, totals))
            times.append(time.perf_counter() - t0)
    warmup, times = times[:WARMUP_EPOCHS], times[WARMUP_EPOCHS:]
    t = statistics.median(times)
    return {"epoch_s": t, "epoch_min_s": min(times), "epochs_s": times, "warmup_epochs_s": warmup,
            "env_steps_per_s": steps_per_epoch * env_steps_per_training_step(kwargs) / t}


def measure(env: Env, kwargs: dict, steps_per_epoch: int, epochs: int) -> dict:
    """PPO and its collection alone on ``env`` (module docstring, 1.-3.): ``train``, ``collect``, the split per
    training step and its shares of the PPO epoch."""
    train = time_ppo(env, kwargs, steps_per_epoch, epochs)
    collect = time_collection(env, kwargs, steps_per_epoch, epochs)
    collect_s, learn_s = collect["epoch_s"], train["epoch_s"] - collect["epoch_s"]
    return {"ppo_env_steps_per_s": train["env_steps_per_s"], "train": train, "collect": collect,
            "collect_s_per_training_step": collect_s / steps_per_epoch,
            "learn_s_per_training_step": learn_s / steps_per_epoch,
            "collect_share": collect_s / train["epoch_s"], "learn_share": learn_s / train["epoch_s"]}


def main(argv: list[str] | None = None, prog: str | None = None) -> int:
    args = parse_args(argv, prog)
    from kamino.bench.throughput import environment
    from kamino.envs import make
    from kamino.envs.configs import task_config
    from kamino.envs.train import _version

    try:
        kwargs = training_config(args.task, args.num_envs, args.ppo_overrides)
    except ValueError as e:
        raise SystemExit(f"ppo_split: {e}") from None
    env_kwargs = {**task_config(args.task)["env"], **args.env_overrides}
    task_env = make(args.task, backend=args.backend, **env_kwargs)
    if args.solver_overrides:
        config = task_env.solver_config.replace(**args.solver_overrides)
        task_env = make(args.task, backend=args.backend, solver_config=config, **env_kwargs)
    null_env = NullEnv(task_env.observation_size, task_env.action_size)
    T, K = args.steps_per_epoch, args.epochs
    unit = env_steps_per_training_step(kwargs)
    print(f"ppo_split {args.task}: {task_env.observation_size} observations, {task_env.action_size} actions, "
          f"num_envs {kwargs['num_envs']}, {unit} env steps per training step, {WARMUP_EPOCHS} warm-up and {K} "
          f"timed epochs of {T} training steps", flush=True)
    results = {}
    for name, env in (("null", null_env), ("task", task_env)):
        results[name] = r = measure(env, kwargs, T, K)
        print(f"  {name:4s}: PPO {r['ppo_env_steps_per_s']:.4g} env steps/s; per training step "
              f"{r['collect_s_per_training_step'] * 1e3:.4g} ms collecting ({100 * r['collect_share']:.1f} %) + "
              f"{r['learn_s_per_training_step'] * 1e3:.4g} ms learning ({100 * r['learn_share']:.1f} %); "
              f"collection alone {r['collect']['env_steps_per_s']:.4g} env steps/s", flush=True)
    null, task = results["null"], results["task"]
    predicted = T * (task["collect_s_per_training_step"] + null["learn_s_per_training_step"])
    print(f"  ceiling (null env) / task = {null['ppo_env_steps_per_s'] / task['ppo_env_steps_per_s']:.3g}; "
          f"task epoch {task['train']['epoch_s']:.4g} s, its collection + the null env's learning "
          f"{predicted:.4g} s", flush=True)
    ppo = {k: v for k, v in kwargs.items() if (isinstance(v, (int, float, str, bool)) or v is None)
           and k not in ("num_timesteps", "num_evals")}  # the run's length is steps_per_epoch and the epochs
    host = {k: v for k, v in environment().items() if k not in ("solver", "dt")}
    record = {
        "benchmark": "ppo_split", "task": args.task, "backend": args.backend, "ppo": ppo,
        "network": task_config(args.task)["network"], "env_kwargs": env_kwargs,
        "solver_overrides": args.solver_overrides,
        "observation_size": task_env.observation_size, "action_size": task_env.action_size,
        "env_steps_per_training_step": unit, "steps_per_epoch": T, "timed_epochs": K,
        "timed_env_steps": K * T * unit,
        "null": null, "task_run": task,
        "ceiling_env_steps_per_s": null["ppo_env_steps_per_s"], "ppo_env_steps_per_s": task["ppo_env_steps_per_s"],
        "collect_share": task["collect_share"], "learn_share": task["learn_share"],
        "predicted_epoch_s": predicted, "device": str(jax.devices()[0]), **host, "brax": _version("brax"),
    }
    emit_record(record, args.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
