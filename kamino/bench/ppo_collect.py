"""The simulator in PPO's regime: brax-style collection with random actions, and what the solver does there.

    python -m kamino.bench.ppo_collect [TASK] [--backend warp] [--num-envs 4096] [--unroll 20] [--action-scale 1]
                                         [--set tolerance=0.01 ...] [--env kp=75 ...] [--out FILE]
    python -m kamino.bench.ppo_collect --policy dr_legs_walk [--num-envs 4096] ...    # the walking load

brax's PPO collects ``unroll_length`` env steps of every environment per batch, with actions drawn around its
policy's mean; early in training that is close to uniform noise in ``[-1, 1]``. This runs the same loop without the
learning: the task through brax's training wrappers (Vmap, Episode, AutoReset), ``--unroll`` steps of uniform
random actions in ``[-scale, scale]`` in one jitted ``lax.scan``, three batches timed after one warm-up batch.
``--policy NAME`` (a shipped policy, ``kamino.envs.shipped_policies()``, or a run folder or checkpoint) runs its task
with its training keywords and takes the policy's deterministic actions instead, inside the same scan: with
``dr_legs_walk``, dr_legs walking at the commands its task draws (the walking load).
It reports collection env steps/s, ms per simulator step, the PADMM iterations of each env step's last substep
(mean, median, 90th and 99th percentiles, max; the GPU waits for the slowest world), the fraction of unconverged
solves, and the worst loop closure over the environments at the end (``kamino.metrics``). ``--set KEY=VALUE``
overrides a :class:`kamino.SolverConfig` setting, a nested one by its path (``--set penalty.rho=0.05``; the task's
``sim_dt`` is kept); ``--env KEY=VALUE`` passes a
keyword to the task (``kamino.envs.make``), e.g. the PD gains. ``--no-effort-limits`` (a diagnostic) builds the
robot with unbounded actuator efforts. ``--profile STEPS`` (Warp) then times each kernel of STEPS more simulator
steps of the environments' stepper from where the collection left it, and the same steps replayed as one CUDA
graph, as the FFI call replays its step (``kamino.bench.profile_step.profile``; the record's ``profile``). The
figure to compare with PPO's end-to-end env steps/s (``kamino train``) is the collection share of it.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import pathlib
import time


def parse_args(argv: list[str] | None = None, prog: str | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(prog=prog or "kamino bench ppo_collect", description=__doc__.splitlines()[0])
    p.add_argument("task", nargs="?", default="dr_legs_joystick", help="a kamino.envs task (default dr_legs_joystick)")
    p.add_argument("--backend", choices=("jax", "warp"), default="warp")
    p.add_argument("--num-envs", type=int, default=4096)
    p.add_argument("--unroll", type=int, default=20, help="env steps per collected batch (brax's unroll_length)")
    p.add_argument("--action-scale", type=float, default=1.0, help="actions uniform in [-scale, scale]")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="a SolverConfig setting (dotted for a nested one: --set penalty.rho=0.05), VALUE a Python "
                        "literal or a bare word (repeatable): --set tolerance=0.01")
    p.add_argument("--env", action="append", default=[], metavar="KEY=VALUE",
                   help="a keyword of the task's constructor, VALUE a Python literal (repeatable): --env kp=75")
    p.add_argument("--no-effort-limits", action="store_true",
                   help="diagnostic: build the robot with unbounded actuator efforts (kamino.models' builders patched)")
    p.add_argument("--profile", type=int, default=0, metavar="STEPS",
                   help="Warp backend: after the collection, time each kernel of STEPS more simulator steps of the "
                        "environments' stepper from where the collection left it, and their graph replay")
    p.add_argument("--policy", default=None, metavar="NAME",
                   help="actions from a trained policy (a shipped one, e.g. dr_legs_walk, or a run folder or "
                        "checkpoint) on its own task instead of random ones")
    p.add_argument("--out", type=pathlib.Path, default=None, help="append the JSON record to this file")
    args = p.parse_args(argv)
    if args.profile and args.backend != "warp":
        p.error("--profile times Warp kernels: it needs --backend warp")
    if args.num_envs < 1 or args.unroll < 1:
        p.error("--num-envs and --unroll must be positive")
    if not 0.0 <= args.action_scale <= 1.0:
        p.error(f"--action-scale must be in [0, 1] (actions are clipped to [-1, 1]), got {args.action_scale}")
    from kamino.config import solver_settings
    from kamino.envs.runs import key_values

    try:
        args.overrides, args.env_kwargs = solver_settings(args.set, "--set"), key_values(args.env, "--env")
    except ValueError as e:
        p.error(str(e))
    return args


def _unbounded_efforts() -> None:
    """Make ``kamino.models``' robot builders return their model with every actuator's effort limit infinite
    (``--no-effort-limits``: what the effort-limited actuator rows cost the solve)."""

    import numpy as np

    import kamino.envs.joystick as joystick
    import kamino.models as models
    import kamino.models.robots as robots

    for name in ("dr_legs", "bdx", "olaf"):
        build = getattr(robots, name)

        def unbounded(*a, _build=build, **k):
            m = _build(*a, **k)
            return dataclasses.replace(m, dof_effort_limit=np.full_like(np.asarray(m.dof_effort_limit), np.inf))

        for module in (robots, models, joystick):
            if hasattr(module, name):
                setattr(module, name, unbounded)


def main(argv: list[str] | None = None, prog: str | None = None) -> int:
    args = parse_args(argv, prog)
    import jax
    import numpy as np
    from brax.envs.wrappers import training

    import kamino
    from kamino.envs import make

    if args.no_effort_limits:
        _unbounded_efforts()
    task, env_kwargs, act = args.task, args.env_kwargs, None
    if args.policy is not None:
        from kamino.envs.evaluate import resolve

        policy = resolve(args.policy)
        task, env_kwargs = policy.task, {**policy.env, **args.env_kwargs}
        inference = policy.make_policy(policy.params, deterministic=True)

        def act(obs, key):
            return inference(obs, key)[0]
    probe = make(task, backend=args.backend, **env_kwargs)
    config = probe.solver_config.replace(**args.overrides) if args.overrides else None
    raw = make(task, backend=args.backend, solver_config=config, **env_kwargs) if config else probe
    if act is not None and raw.observation_size != policy.observation_size:
        raise SystemExit(f"ppo_collect: the policy {args.policy} takes {policy.observation_size} observations, "
                         f"{task} built with {env_kwargs} gives {raw.observation_size}")
    env = training.wrap(raw, episode_length=1000)
    n, scale = args.num_envs, args.action_scale

    @jax.jit
    def collect(state, key):
        def body(s, k):
            a = (jax.random.uniform(k, (n, env.action_size), minval=-scale, maxval=scale) if act is None
                 else act(s.obs, k))
            s = env.step(s, a)
            info = s.pipeline_state.info
            return s, (info.iterations, info.converged, s.done)

        return jax.lax.scan(body, state, jax.random.split(key, args.unroll))

    with jax.enable_x64(False):
        state = jax.jit(env.reset)(jax.random.split(jax.random.PRNGKey(0), n))
        state, _ = collect(state, jax.random.PRNGKey(1))
        jax.block_until_ready(state)
        times, iters, converged, done = [], [], [], []
        for r in range(3):
            t0 = time.perf_counter()
            state, (it, conv, dn) = collect(state, jax.random.PRNGKey(2 + r))
            jax.block_until_ready(state)
            times.append(time.perf_counter() - t0)
            iters.append(np.asarray(it))
            converged.append(np.asarray(conv))
            done.append(np.asarray(dn))
        whole = raw.full_state(state.pipeline_state)
        closure = jax.vmap(lambda s: kamino.metrics(raw.model, s)["constraint_violation"])(whole)
    t = float(np.median(times))
    it = np.concatenate(iters).reshape(-1)
    record = {
        "task": task, "policy": args.policy, "backend": args.backend, "num_envs": n, "unroll": args.unroll,
        "action_scale": None if act is not None else scale, "solver_overrides": args.overrides,
        "env_kwargs": env_kwargs,
        "effort_limits": not args.no_effort_limits, "sim_dt": raw.sim_dt,
        "decimation": raw.decimation, "collect_env_steps_per_s": args.unroll * n / t,
        "ms_per_sim_step": t / args.unroll / raw.decimation * 1e3,
        "iterations": {"mean": float(it.mean()), "p50": float(np.percentile(it, 50)),
                       "p90": float(np.percentile(it, 90)), "p99": float(np.percentile(it, 99)),
                       "max": int(it.max())},
        "unconverged_fraction": float(1.0 - np.concatenate(converged).mean()),
        "episodes_ended_fraction": float(np.concatenate(done).mean()),
        "closure_max_m": float(np.max(np.asarray(closure))), "device": str(jax.devices()[0]),
    }
    if args.profile:
        record["profile"] = _profile(raw.simulator, n, args.profile)
    emit_record(record, args.out)
    return 0


def emit_record(record: dict, out: pathlib.Path | None) -> None:
    """Print ``record`` as one JSON line and, with ``out``, append the line to that file (JSON lines)."""
    line = json.dumps(record)
    print(line, flush=True)
    if out is not None:
        out.parent.mkdir(parents=True, exist_ok=True)
        with out.open("a") as f:
            f.write(line + "\n")


def _profile(sim, num_envs: int, steps: int) -> dict:
    """``profile_step.profile`` of the stepper that ran the batched environments (the ``num_envs``-world replica
    of the environment's model, ``Engine.replica``, behind ``jit.batchable_step``), from its last state and targets:
    each kernel timed in un-graphed steps, then the wall time of the same steps replayed as one CUDA graph, as the FFI
    call replays its step."""
    import warp as wp

    from kamino.bench.profile_step import profile

    st = sim.engine.replica(num_envs).stepper("float32", wp.get_device(), for_jit=True)
    use_graph, st.use_graph = st.use_graph, st.device.is_cuda
    try:
        result = profile(st, steps)
    finally:
        st.use_graph = use_graph
    print(f"{result['graph_step_time_s']} s per step (graph replay), iterations {result['iterations']}", flush=True)
    for name, k in sorted(result["kernels"].items(), key=lambda kv: -kv[1]["ms_per_step"])[:10]:
        print(f"  {name:40s} {k['ms_per_step']:9.3f} ms/step {k['launches_per_step']:6.1f} launches", flush=True)
    return result


if __name__ == "__main__":
    raise SystemExit(main())
