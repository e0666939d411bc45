"""Catch the finite blow-ups of training and save them for replay (issue 18): ``python benchmarks/rl_blowup_hunt.py
RUN --envs 16384 --chunks 40 --out DIR`` on the GPU, then ``python benchmarks/rl_blowup_hunt.py --replay
DIR/case_000.pkl`` anywhere.

Training logs about one episode in 1.3 M environment steps whose state blows up without turning non-finite (the
base spinning at hundreds of rad/s; docs/envs.md, "The eighth run"). The environment ends such an episode as
``failed`` through ``obs_limit``, but which simulator state does it is unknown: it is too rare to meet on a CPU.

**Hunt.** Plays the policy of ``RUN`` (a checkpoint or an ``rl_train.py`` folder) as training does: sampled actions,
commands drawn at reset and resampled every ``resample_steps``, ``--envs`` environments, in chunks of
``--chunk-steps`` policy steps (one compiled scan each); a finished episode restarts at the next chunk. An episode
whose step sets ``metrics["failed"]`` is a case: its environment state at the start of the chunk and the actions of
the chunk up to the failing step are pickled (numpy arrays), with the base's angular speed over those steps and the
last substep's PADMM report, as ``case_NNN.pkl`` under ``--out``, plus ``hunt.json`` (counts, environment steps,
wall time).

**Replay.** Rebuilds the environment with the saved keywords on this machine's default device and backend
``--backend``, steps the saved state through the saved actions and prints, per policy step, the base's angular speed,
``failed`` and the PADMM iterations of the last substep: whether the blow-up reproduces here, and from which step.
"""

from __future__ import annotations

import argparse
import json
import pickle
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))  # rl_eval, rl_train, beside this script


def base_spin(env, pipeline_state):
    """The base body's angular speed [rad/s] of a (batched) ``pipeline_state``."""
    import jax.numpy as jnp

    ps = env.full_state(pipeline_state)
    return jnp.linalg.norm(ps.body_u[..., env._base, 3:], axis=-1)


def hunt(env, make_policy, params, *, envs: int, chunks: int, chunk_steps: int, seed: int, out: Path,
         env_kwargs: dict, task: str, backend: str) -> dict:
    """Play ``chunks`` chunks of ``chunk_steps`` policy steps in ``envs`` environments; pickle every failed episode
    (the module doc). Returns the summary written to ``hunt.json``."""
    import jax
    import jax.numpy as jnp

    policy = make_policy(params, deterministic=False)

    def chunk(state, key):
        def body(s, k):
            action, _ = policy(s.obs, k)
            s2 = env.step(s, action)
            ps = s2.pipeline_state
            newly = (s2.metrics["failed"] > 0) & (s.done == 0)
            return s2, (action, newly, base_spin(env, ps), ps.info.iterations[0], ps.info.converged[0])

        return jax.lax.scan(body, state, jax.random.split(key, chunk_steps))

    def restart(state, key):
        fresh = env.reset(key)
        return jax.tree.map(lambda a, b: jnp.where(state.done > 0, a, b), fresh, state)

    with jax.enable_x64(False):
        run = jax.jit(jax.vmap(chunk))
        renew = jax.jit(jax.vmap(restart))
        key = jax.random.PRNGKey(seed)
        key, k0 = jax.random.split(key)
        states = jax.jit(jax.vmap(env.reset))(jax.random.split(k0, envs))
        cases, t0 = [], time.perf_counter()
        for c in range(chunks):
            key, k_run, k_new = jax.random.split(key, 3)
            new, (actions, newly, spin, iters, conv) = run(states, jax.random.split(k_run, envs))
            hits = np.argwhere(np.asarray(newly))
            for e, k in hits:
                n = len(cases)
                case = {"task": task, "backend": backend, "env_kwargs": env_kwargs, "chunk": c, "env": int(e),
                        "failing_step": int(k), "state": jax.tree.map(lambda x, e=e: np.asarray(x[e]), states),
                        "actions": np.asarray(actions[e, :k + 1]), "base_spin": np.asarray(spin[e, :k + 1]),
                        "iterations": np.asarray(iters[e, :k + 1]), "converged": np.asarray(conv[e, :k + 1])}
                (out / f"case_{n:03d}.pkl").write_bytes(pickle.dumps(case))
                cases.append({k2: case[k2] for k2 in ("chunk", "env", "failing_step")}
                             | {"max_spin": float(case["base_spin"].max()), "spin_before": float(case["base_spin"][-2])
                                if k > 0 else float("nan")})
                print(f"case {n}: chunk {c}, env {e}, step {k}: base spin {case['base_spin'][-4:]} rad/s, "
                      f"iterations {case['iterations'][-4:]}", flush=True)
            states = renew(new, jax.random.split(k_new, envs))
            print(f"chunk {c + 1}/{chunks}: {len(cases)} cases, {(c + 1) * envs * chunk_steps / 1e6:.1f} M env steps, "
                  f"{time.perf_counter() - t0:.0f} s", flush=True)
    summary = {"task": task, "backend": backend, "env_kwargs": env_kwargs, "envs": envs, "chunks": chunks,
               "chunk_steps": chunk_steps, "env_steps": envs * chunks * chunk_steps, "cases": cases,
               "wall_s": time.perf_counter() - t0, "seed": seed}
    (out / "hunt.json").write_text(json.dumps(summary, indent=1, default=float))
    return summary


def replay(path: Path, backend: str) -> list[dict]:
    """Step a saved case through its actions here (the module doc); returns one row per policy step."""
    import jax
    import jax.numpy as jnp

    from kamino.envs import make

    case = pickle.loads(path.read_bytes())
    env = make(case["task"], backend=backend, **case["env_kwargs"])
    rows = []
    with jax.enable_x64(False):
        state = jax.tree.map(jnp.asarray, case["state"])
        step = jax.jit(env.step)
        for k, action in enumerate(case["actions"]):
            state = step(state, jnp.asarray(action))
            ps = state.pipeline_state
            rows.append({"step": k, "base_spin": float(base_spin(env, ps)), "failed": float(state.metrics["failed"]),
                         "iterations": int(ps.info.iterations[0]), "converged": bool(ps.info.converged[0]),
                         "hunt_base_spin": float(case["base_spin"][k])})
    return rows


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("run", type=Path, nargs="?", help="a checkpoint, or an rl_train.py output folder (hunt)")
    p.add_argument("--replay", type=Path, help="a case_NNN.pkl to replay instead of hunting")
    p.add_argument("--task", default="dr_legs_joystick")
    p.add_argument("--backend", choices=("jax", "warp"), default="warp")
    p.add_argument("--envs", type=int, default=16384)
    p.add_argument("--chunks", type=int, default=20)
    p.add_argument("--chunk-steps", type=int, default=50, help="policy steps per compiled chunk")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--env", action="append", default=[], metavar="KEY=VALUE",
                   help="environment keyword over the task's config (repeat the run's own --env settings)")
    p.add_argument("--out", type=Path, default=Path("scratch/blowups"))
    args = p.parse_args(argv)
    if args.replay is not None:
        rows = replay(args.replay, args.backend)
        print("| policy step | base spin here [rad/s] | in the hunt | failed | PADMM iterations | converged |\n"
              "|---|---|---|---|---|---|")
        for r in rows:
            print(f"| {r['step']} | {r['base_spin']:.3g} | {r['hunt_base_spin']:.3g} | {r['failed']:.0f} | "
                  f"{r['iterations']} | {r['converged']} |")
        return 0
    if args.run is None:
        p.error("give a RUN to hunt in, or --replay CASE")
    if min(args.envs, args.chunks, args.chunk_steps) < 1:
        p.error("--envs, --chunks and --chunk-steps must be >= 1")
    from rl_eval import load_policy, newest_checkpoint
    from rl_train import key_values, run_env

    from kamino.envs import make

    env_kwargs = {**run_env(args.run.resolve(), args.task), **key_values(p, "--env", args.env)}
    env = make(args.task, backend=args.backend, **env_kwargs)
    make_policy, params = load_policy(newest_checkpoint(args.run.resolve()), args.task)
    args.out.mkdir(parents=True, exist_ok=True)
    s = hunt(env, make_policy, params, envs=args.envs, chunks=args.chunks, chunk_steps=args.chunk_steps,
             seed=args.seed, out=args.out, env_kwargs=env_kwargs, task=args.task, backend=args.backend)
    print(f"{len(s['cases'])} failed episodes in {s['env_steps'] / 1e6:.1f} M env steps ({s['wall_s']:.0f} s); "
          f"{args.out / 'hunt.json'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
