"""Score a trained policy: ``kamino eval RUN_OR_POLICY`` or :func:`evaluate`.

``RUN_OR_POLICY`` is a shipped policy's name (``dr_legs_walk``), a ``kamino train`` run folder (its newest complete
checkpoint) or one checkpoint. The environment is built with the keywords the policy was trained with.

A joystick task gets the walking test (``olaf_show`` its show test: :mod:`kamino.envs.olaf_show`): episodes of
``--seconds`` at forward commands uniform in ``--speed`` (no lateral or yaw command), the policy's deterministic
action. Over the episodes it reports the velocity-tracking error (per episode, the mean over its policy steps up to
a fall of ``|cmd_xy - v_xy|``, the base's planar velocity in its own frame), the fall fraction (episodes that end
early), the forward speed, and whether the bars hold (``--max-error``, ``--max-falls``). Where the error comes from
is reported too: the error of the mean velocity (per episode ``|cmd_xy - mean v_xy|``) and the fluctuation (per
episode the standard deviation of ``v_x`` and ``v_y``). Any other task gets the mean and spread of the episode
return and the fraction of episodes that end early.

``--sim mujoco`` runs the walking test in C MuJoCo on ``kamino.save_mjcf``'s export of the robot, with kamino's
observations, actions, resets and commands (:mod:`kamino.envs.sim2sim`; the ``--mj-*`` options set MuJoCo's).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import Any

from kamino._progress import announce_compile
from kamino.envs import runs
from kamino.envs.policy import Policy


def walking_test(env, make_policy, *, episodes: int, seconds: float, speed: tuple[float, float], seed: int = 0,
                 deterministic: bool = True):
    """The walking test's rollout, compiled once for any parameters of ``make_policy``: returns ``run(params)``.

    ``run`` plays ``episodes`` episodes of ``seconds`` at forward commands uniform in ``speed`` [m/s] (no lateral or
    yaw command), the policy's deterministic action (its mode; ``deterministic=False``: actions sampled as in
    training), and returns numpy arrays ``(commands [E], lin_vel [E, T, 3], ang_vel [E, T, 3], counted [E, T],
    fell [E])``: the base body's velocities in its own frame after each policy step; ``counted`` is True for the
    steps that began with the robot up (the step that ends an episode is its last counted one); ``fell`` marks the
    episodes that ended before ``seconds``. On a terrain task (an environment with ``with_tile``:
    :class:`kamino.envs.rough.DrLegsRough`) episode ``i`` of ``E`` starts on tile ``floor(i num_tiles / E)``, so
    the episodes spread evenly over the tiles of its difficulty rows (each tile ``E / num_tiles`` of them, up to
    one; fewer episodes than tiles take every ``num_tiles / E``-th tile)."""
    import jax
    import jax.numpy as jnp
    import numpy as np

    from kamino.envs.geometry import body_frame_vectors

    steps = round(seconds / env.dt)
    key_reset, key_cmd, key_policy = jax.random.split(jax.random.PRNGKey(seed), 3)
    vx = jax.random.uniform(key_cmd, (episodes,), jnp.float32, speed[0], speed[1])
    commands = jnp.stack([vx, jnp.zeros_like(vx), jnp.zeros_like(vx)], -1)

    def start(rng, command, index):
        state = env.with_command(env.reset(rng), command)
        return env.with_tile(state, index * env.num_tiles // episodes) if hasattr(env, "with_tile") else state

    def rollout(params, state, key):
        policy = make_policy(params, deterministic=deterministic)

        def body(carry, k):
            s, alive = carry
            action, _ = policy(s.obs, k)
            s = env.step(s, action)
            ps = env.full_state(s.pipeline_state)
            frame = body_frame_vectors(ps.body_q, ps.body_u, env._base)
            return (s, alive & (s.done == 0)), (frame["lin_vel"], frame["ang_vel"], alive)

        (_, alive_end), out = jax.lax.scan(body, (state, jnp.bool_(True)), jax.random.split(key, steps))
        return (*out, ~alive_end)

    with jax.enable_x64(False):
        states = jax.jit(jax.vmap(start))(jax.random.split(key_reset, episodes), commands, jnp.arange(episodes))
    play = jax.jit(jax.vmap(rollout, in_axes=(None, 0, 0)))
    keys = jax.random.split(key_policy, episodes)

    def run(params):
        with jax.enable_x64(False):
            out = play(params, states, keys)
        return (np.asarray(vx), *(np.asarray(x) for x in out))

    return run


def summarize(vx, lin, counted, fell) -> dict:
    """The walking test's figures (the module doc) of a :func:`walking_test` rollout."""
    import numpy as np

    cmd = np.stack([vx, np.zeros_like(vx)], -1)
    err = np.linalg.norm(cmd[:, None, :] - lin[..., :2], axis=-1)
    n = np.maximum(counted.sum(1), 1)
    err = np.where(counted, err, 0.0).sum(1) / n
    mean_v = np.where(counted[..., None], lin[..., :2], 0.0).sum(1) / n[:, None]  # [E, 2] per episode
    var = np.where(counted[..., None], (lin[..., :2] - mean_v[:, None, :]) ** 2, 0.0).sum(1) / n[:, None]
    std = np.sqrt(var).mean(0)
    return {"episodes": len(vx), "policy_steps": lin.shape[1], "tracking_error_mean": float(err.mean()),
            "tracking_error_p90": float(np.quantile(err, 0.9)), "forward_speed_mean": float(mean_v[:, 0].mean()),
            "command_mean": float(vx.mean()), "fall_fraction": float(fell.mean()),
            "mean_velocity_error": float(np.linalg.norm(cmd - mean_v, axis=-1).mean()),
            "fluctuation_std_x": float(std[0]), "fluctuation_std_y": float(std[1])}


def episode_returns(env, make_policy, params, *, episodes: int, seconds: float, seed: int = 0,
                    deterministic: bool = True) -> dict:
    """Mean and spread of the return of ``episodes`` episodes of at most ``seconds``, and the fraction that ended
    early (the reward of a step counts while the episode is running; a step that ends it is its last)."""
    import jax
    import jax.numpy as jnp
    import numpy as np

    steps = max(1, round(seconds / env.dt))
    key_reset, key_policy = jax.random.split(jax.random.PRNGKey(seed))
    policy = make_policy(params, deterministic=deterministic)

    def rollout(state, key):
        def body(carry, k):
            s, alive, total = carry
            action, _ = policy(s.obs, k)
            s = env.step(s, action)
            total = total + jnp.where(alive, s.reward, 0.0)
            return (s, alive & (s.done == 0), total), None

        (_, alive, total), _ = jax.lax.scan(body, (state, jnp.bool_(True), jnp.float32(0.0)),
                                            jax.random.split(key, steps))
        return total, ~alive

    with jax.enable_x64(False), announce_compile(f"and running {episodes} episodes"):
        states = jax.jit(jax.vmap(env.reset))(jax.random.split(key_reset, episodes))
        total, ended = jax.jit(jax.vmap(rollout))(states, jax.random.split(key_policy, episodes))
    total, ended = np.asarray(total), np.asarray(ended)
    return {"episodes": episodes, "policy_steps": steps, "return_mean": float(total.mean()),
            "return_std": float(total.std()), "ended_fraction": float(ended.mean())}


def resolve(source: str | Path, task: str | None = None) -> Policy:
    """The policy named by ``source``: a shipped policy's name, or a run folder or checkpoint path. ``task`` may
    name a variant of a shipped policy's task (a subclass of its environment, with its observation and keywords:
    ``dr_legs_rough`` for ``dr_legs_walk``), to score the policy there."""
    import dataclasses

    from kamino.envs.policy import load_checkpoint, load_policy, shipped_policies

    if str(source) in shipped_policies() and not Path(source).exists():
        policy = load_policy(str(source))
        if task is not None and task != policy.task:
            if not issubclass(_task_class(task), _task_class(policy.task)):
                raise ValueError(f"the shipped policy {source} was trained on {policy.task}, not {task}")
            policy = dataclasses.replace(policy, task=task)
        return policy
    path = Path(source)
    if not path.exists():
        raise FileNotFoundError(f"{source} is neither a shipped policy ({', '.join(shipped_policies())}) nor an "
                                "existing run folder or checkpoint")
    return load_checkpoint(path, task)


def check_walk(episodes: int, seconds: float, speed: tuple[float, float], caller: str) -> None:
    """Raise ``ValueError`` naming ``caller`` unless ``episodes >= 1``, ``seconds > 0`` and ``speed`` is
    ``(LOW, HIGH)`` with ``LOW <= HIGH``: the walking test's settings."""
    if episodes < 1 or seconds <= 0 or not speed[0] <= speed[1]:
        raise ValueError(f"{caller}: episodes must be >= 1 (got {episodes}), seconds > 0 (got {seconds}) and speed "
                         f"LOW <= HIGH (got {tuple(speed)})")


def task_test(env, make_policy, *, episodes: int, seconds: float, speed: tuple[float, float] = (0.3, 0.5),
              seed: int = 0, deterministic: bool = True):
    """The test of ``env``'s task (its ``evaluation``), compiled once: returns ``run(params)`` giving the summary.
    ``"walking"``: :func:`walking_test` at forward commands in ``speed``, then :func:`summarize`; ``"show"``:
    :func:`kamino.envs.olaf_show.show_test`, then :func:`~kamino.envs.olaf_show.summarize_show`. Raises
    ``ValueError`` for a task with neither."""
    if env.evaluation == "walking":
        play = walking_test(env, make_policy, episodes=episodes, seconds=seconds, speed=tuple(speed), seed=seed,
                            deterministic=deterministic)

        def run(params):
            with announce_compile(f"and running {episodes} walking episodes"):
                vx, lin, _, counted, fell = play(params)
            return summarize(vx, lin, counted, fell)

        return run
    if env.evaluation == "show":
        from kamino.envs.olaf_show import show_test, summarize_show

        play = show_test(env, make_policy, episodes=episodes, seconds=seconds, seed=seed, deterministic=deterministic)

        def run_show(params):
            with announce_compile(f"and running {episodes} show episodes"):
                return summarize_show(*play(params))

        return run_show
    raise ValueError(f"task_test: {type(env).__name__} has no walking or show test (its evaluation is "
                     f"{env.evaluation!r})")


def evaluate(policy: Policy | str | Path, *, backend: str = "warp", episodes: int = 256, seconds: float = 10.0,
             speed: tuple[float, float] = (0.3, 0.5), seed: int = 0, deterministic: bool = True,
             env: dict | None = None, max_error: float | None = None,
             max_falls: float | None = None) -> dict[str, Any]:
    """Score ``policy`` (a :class:`~kamino.envs.policy.Policy`, a shipped policy's name, or a run or checkpoint
    path) in its task's environment, built with its training keywords and ``env`` over them, by its task's test
    (:func:`task_test`). A joystick task gets the walking test (the module doc), with ``passed`` against
    ``max_error`` [m/s] and ``max_falls`` (default: the task's ``walking_bars``: 0.1 m/s and 5 % on flat ground,
    0.15 m/s and 5 % on ``dr_legs_rough``; a terrain task plays the test on its ``walking_levels`` rows of its
    default terrain, unless ``env`` gives ``levels`` or a ``terrain``); ``olaf_show`` the show test, ``max_error``
    in rad (default its ``show_bars``: 0.05 rad, 5 %); another task the episode return. Returns the report."""
    from kamino.envs import make

    check_walk(episodes, seconds, speed, "evaluate")
    if not isinstance(policy, Policy):
        policy = resolve(policy)
    env_overrides = dict(env or {})
    kwargs = {**policy.env, **env_overrides}
    cls = _task_class(policy.task)
    if cls.evaluation in ("walking", "show"):
        bars = cls.walking_bars if cls.evaluation == "walking" else cls.show_bars
        max_error = bars[0] if max_error is None else max_error
        max_falls = bars[1] if max_falls is None else max_falls
    if cls.evaluation == "walking":
        kwargs["resample_steps"] = None  # the command stays as the test sets it
        levels = getattr(cls, "walking_levels", None)
        if levels is not None and "levels" not in env_overrides and not kwargs.get("terrain"):
            kwargs["levels"] = levels  # a terrain task on its default terrain: the test's difficulty rows
    # the test's episodes are one batch: on the Warp backend its step compiles while the environment builds
    environment = make(policy.task, backend=backend, **kwargs,
                       **({"compile_for": episodes} if backend == "warp" else {}))
    if environment.observation_size != policy.observation_size:
        raise ValueError(f"evaluate: the policy takes {policy.observation_size} observations, {policy.task} built "
                         f"with {kwargs} gives {environment.observation_size}")
    t0 = time.perf_counter()
    if cls.evaluation in ("walking", "show"):
        report = task_test(environment, policy.make_policy, episodes=episodes, seconds=seconds, speed=speed,
                           seed=seed, deterministic=deterministic)(policy.params)
        error = report["tracking_error_mean" if cls.evaluation == "walking" else "show_error_mean"]
        report.update(bars={"max_error": max_error, "max_falls": max_falls},
                      passed=error <= max_error and report["fall_fraction"] <= max_falls)
        if cls.evaluation == "walking":
            report["speed_range"] = list(speed)
    else:
        report = episode_returns(environment, policy.make_policy, policy.params, episodes=episodes, seconds=seconds,
                                 seed=seed, deterministic=deterministic)
    report.update(seconds=seconds, seed=seed, deterministic=deterministic, wall_s=time.perf_counter() - t0,
                  task=policy.task, backend=backend, checkpoint=policy.source, step=policy.step, env=env_overrides)
    if "levels" in kwargs:
        report["levels"] = list(kwargs["levels"])
    return report


def _task_class(task: str):
    from kamino.envs import TASKS

    if task not in TASKS:
        raise ValueError(f"unknown task {task!r}; choose one of {sorted(TASKS)}")
    return TASKS[task]


def format_report(r: dict) -> str:
    """The report as a short table."""
    if "tracking_error_mean" in r:
        lo, hi = r["speed_range"]
        bars = r["bars"]
        return ("| episodes | command [m/s] | forward speed [m/s] | tracking error, mean / p90 [m/s] | falls | passes "
                "|\n"
                f"|---|---|---|---|---|---|\n"
                f"| {r['episodes']} x {r['seconds']:g} s | {lo:g}-{hi:g} (mean {r['command_mean']:.3f}) | "
                f"{r['forward_speed_mean']:.3f} | {r['tracking_error_mean']:.3f} / {r['tracking_error_p90']:.3f} | "
                f"{100 * r['fall_fraction']:.1f} % | {'yes' if r['passed'] else 'no'} (<= {bars['max_error']:g} m/s, "
                f"<= {100 * bars['max_falls']:g} %) |\n"
                f"error of the mean velocity {r['mean_velocity_error']:.3f} m/s; fluctuation (std within episodes) "
                f"v_x {r['fluctuation_std_x']:.3f}, v_y {r['fluctuation_std_y']:.3f} m/s")
    if "show_error_mean" in r:
        bars = r["bars"]
        return (f"{r['task']}: {r['episodes']} episodes of {r['seconds']:g} s, show error {r['show_error_mean']:.3f} "
                f"/ {r['show_error_p90']:.3f} rad (mean / p90), {100 * r['fall_fraction']:.1f} % falls; passes: "
                f"{'yes' if r['passed'] else 'no'} (<= {bars['max_error']:g} rad, <= {100 * bars['max_falls']:g} %)")
    return (f"{r['task']}: {r['episodes']} episodes of {r['seconds']:g} s, return {r['return_mean']:.3f} "
            f"+- {r['return_std']:.3f}, {100 * r['ended_fraction']:.1f} % ended early")


def main(argv: list[str] | None = None) -> int:
    """``kamino eval ARGS``: returns the exit status."""
    from kamino.envs import sim2sim
    from kamino.envs.policy import shipped_policies

    p = argparse.ArgumentParser(prog="kamino eval", description="Score a trained policy: the walking test for a "
                                "joystick task, the show test for olaf_show, the episode return for any other.",
                                epilog=f"Shipped policies: {', '.join(shipped_policies())}.")
    p.add_argument("policy", metavar="RUN_OR_POLICY", help="a shipped policy's name, a run folder or a checkpoint")
    p.add_argument("--task", help="the task (default: the run's, else dr_legs_joystick)")
    p.add_argument("--backend", choices=("jax", "warp"), default="warp", help="kamino backend (default warp)")
    p.add_argument("--sim", choices=("kamino", "mujoco"), default="kamino",
                   help="the simulator: kamino (default) or C MuJoCo on kamino.save_mjcf's export, with kamino's "
                   "observations, actions and resets (joystick tasks; kamino.envs.sim2sim)")
    p.add_argument("--episodes", type=int, default=256, help="episodes (default 256)")
    p.add_argument("--seconds", type=float, default=10.0, help="episode length [s] (default 10)")
    p.add_argument("--speed", type=float, nargs=2, default=(0.3, 0.5), metavar=("LOW", "HIGH"),
                   help="joystick tasks: forward command range [m/s] (default 0.3 0.5)")
    p.add_argument("--max-error", type=float, help="the bar on the mean tracking error [m/s] (default: the task's, "
                   "0.1 on flat ground, 0.15 on dr_legs_rough), or on the show error [rad] (olaf_show: 0.05)")
    p.add_argument("--max-falls", type=float, help="the bar on the fall fraction (default: the task's, 0.05)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--stochastic", action="store_true", help="sample actions as in training (default: the mode)")
    p.add_argument("--env", action="append", default=[], metavar="KEY=VALUE",
                   help="an environment keyword over the policy's, VALUE a Python literal (repeatable)")
    p.add_argument("--out", type=Path, help="write the JSON report here")
    sim2sim.add_mujoco_arguments(p)
    args = p.parse_args(sys.argv[1:] if argv is None else argv)
    if args.episodes < 1 or args.seconds <= 0 or not args.speed[0] <= args.speed[1]:
        p.error("--episodes must be >= 1, --seconds > 0 and --speed LOW <= HIGH")
    try:
        env_overrides = runs.key_values(args.env, "--env")
        policy = resolve(args.policy, args.task)
    except (runs.OptionError, FileNotFoundError, ValueError) as e:
        p.error(str(e))
    bars = getattr(_task_class(policy.task), "walking_bars", (0.1, 0.05))
    max_error = bars[0] if args.max_error is None else args.max_error
    max_falls = bars[1] if args.max_falls is None else args.max_falls
    if args.sim == "mujoco":
        if args.stochastic:
            p.error("--sim mujoco plays the deterministic policy (no --stochastic)")
        try:
            report = sim2sim.evaluate_mujoco(policy, episodes=args.episodes, seconds=args.seconds,
                                             speed=tuple(args.speed), seed=args.seed,
                                             options=sim2sim.options_from(args), obs_noise=args.obs_noise,
                                             env=env_overrides, max_error=max_error, max_falls=max_falls)
        except ValueError as e:
            p.error(str(e))
        print(f"C MuJoCo {report['mujoco']}", flush=True)
        print(format_report(report), flush=True)
        if args.out:
            runs.write_json(args.out, report)
        return 0
    report = evaluate(policy, backend=args.backend, episodes=args.episodes, seconds=args.seconds,
                      speed=tuple(args.speed), seed=args.seed, deterministic=not args.stochastic, env=env_overrides,
                      max_error=max_error, max_falls=max_falls)
    print(format_report(report), flush=True)
    if args.out:
        runs.write_json(args.out, report)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
