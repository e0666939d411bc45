"""Sim-to-sim: a joystick policy trained in kamino, walking in C MuJoCo (``python -m kamino.envs.sim2sim``).

The robot is :func:`kamino.save_mjcf`'s export of the task's model: a spanning tree of hinges under a free joint, the
loop-closing joints as soft ``<connect>`` equalities, the PD actuators as MuJoCo ``<position>`` actuators (``kp``,
``kv``, ``forcerange`` = kamino's gains and effort limits; the joints' armature). MuJoCo steps it; everything else is
kamino's environment (``kamino.envs.make(policy.task, **policy.env)``, built on the JAX backend and never stepped):

- **State.** The export places every MJCF body frame at its kamino body's CoM frame, so a MuJoCo body's pose is
  kamino's ``body_q`` row (``xpos``, ``xquat``), and its twist (the spatial velocity ``cvel`` shifted from the
  subtree CoM to the body's origin) kamino's ``body_u`` row (CoM velocity, angular velocity, both world frame).
  :func:`kamino_state` reads a kamino :class:`kamino.State` off ``MjData``; :func:`set_mujoco_state` writes one into
  it (the free joint from the base's pose and twist, each tree hinge from kamino's ``dof_state``: the export keeps
  a hinge's ``qpos`` equal to kamino's coordinate).
- **Observation, action, clock.** Each policy step reads the state as above and calls the environment's own
  ``_observe`` (base angular velocity, gravity and linear velocity in the base frame, the command, actuated
  positions about the range's centre and rates, the previous action, the gait clock), adds the environment's
  observation noise (``obs_noise`` times ``_obs_noise_scale``) and clips to ``obs_limit``; the action is clipped to
  ``[-1, 1]`` and mapped by ``env.action_to_target`` onto the PD targets (MuJoCo's ``ctrl``), held for the
  ``env.dt / timestep`` MuJoCo steps of one policy period (50 Hz); the gait phase advances by ``gait_frequency
  env.dt`` per step. The noise is drawn by NumPy (seeded by ``seed``): the same scale as kamino's, not the same
  samples. A fall is the environment's ``_fallen`` (base height, tilt), an observation entry beyond ``obs_limit`` or
  non-finite (kamino's ``failed``), or MuJoCo's reset of a diverged world (``mjWARN_BADQACC``).
- **Resets and commands.** :func:`walking_test` draws them as :func:`kamino.envs.evaluate.walking_test` does (the
  same keys from ``seed``): the same loop-closed start configurations and headings and the same forward commands, so
  the two simulators' figures compare episode by episode; :func:`kamino.envs.evaluate.summarize` scores both.

The MuJoCo settings a user may change (:class:`MujocoOptions`): the time step, the integrator, the ``<connect>``
equalities' ``solref``, and the contact ``solref``. docs/envs.md, "Sim-to-sim in MuJoCo", has the measured figures.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from pathlib import Path

import numpy as np

from kamino.envs.policy import Policy

#: MuJoCo integrators by name (``mjtIntegrator``)
INTEGRATORS = ("euler", "rk4", "implicit", "implicitfast")


@dataclasses.dataclass(frozen=True)
class MujocoOptions:
    """MuJoCo settings over the export's.

    ``timestep``: MuJoCo's step [s]; it must divide the policy period (``None``: the export's, MuJoCo's default 2 ms,
    half kamino's 4 ms: MuJoCo makes a constraint's time constant at least two steps, so at 4 ms the export's 4 ms
    loop closures would become 8 ms ones, which open twice as far under load; docs/envs.md, "Sim-to-sim in
    MuJoCo").
    ``integrator``: one of :data:`INTEGRATORS` (``None``: the export's, ``implicitfast``). ``equality_solref``: the
    ``(timeconst [s], dampratio)`` of every ``<connect>`` (``None``: the export's, 4 ms and 1). ``contact_solref``:
    the same for contacts (``None``: MuJoCo's default, 20 ms and 1)."""

    timestep: float | None = None
    integrator: str | None = None
    equality_solref: tuple[float, float] | None = None
    contact_solref: tuple[float, float] | None = None


def mujoco_model(env, options: MujocoOptions = MujocoOptions()):
    """The ``mujoco.MjModel`` of ``env.model`` (:func:`kamino.save_mjcf`) with ``options`` applied."""
    import mujoco

    from kamino.io.mjcf_export import save_mjcf

    mj = mujoco.MjModel.from_xml_string(save_mjcf(env.model))
    if options.timestep is not None:
        mj.opt.timestep = float(options.timestep)
    if options.integrator is not None:
        if options.integrator not in INTEGRATORS:
            raise ValueError(f"mujoco_model: integrator must be one of {INTEGRATORS}, got {options.integrator!r}")
        mj.opt.integrator = {"euler": mujoco.mjtIntegrator.mjINT_EULER, "rk4": mujoco.mjtIntegrator.mjINT_RK4,
                             "implicit": mujoco.mjtIntegrator.mjINT_IMPLICIT,
                             "implicitfast": mujoco.mjtIntegrator.mjINT_IMPLICITFAST}[options.integrator]
    if options.equality_solref is not None:
        mj.eq_solref[:] = np.asarray(options.equality_solref, float)
    if options.contact_solref is not None:
        mj.geom_solref[:] = np.asarray(options.contact_solref, float)
    return mj


class Layout:
    """Index maps between a kamino model and its MuJoCo export: bodies by name, the free joint, and each tree hinge's
    ``qpos`` / ``qvel`` address with its kamino DoF."""

    def __init__(self, model, mj):
        import mujoco

        names = list(model.body_names)
        self.body_ids = np.array([mujoco.mj_name2id(mj, mujoco.mjtObj.mjOBJ_BODY, n) for n in names], np.int64)
        if np.any(self.body_ids < 0):
            missing = [n for n, i in zip(names, self.body_ids, strict=True) if i < 0]
            raise ValueError(f"Layout: bodies {missing} are not in the MuJoCo model")
        self.root_ids = np.asarray(mj.body_rootid[self.body_ids], np.int64)
        free = [j for j in range(mj.njnt) if int(mj.jnt_type[j]) == int(mujoco.mjtJoint.mjJNT_FREE)]
        if len(free) != 1:
            raise ValueError(f"Layout: expected one free joint in the MuJoCo model, found {len(free)}")
        self.free_body = names.index(mujoco.mj_id2name(mj, mujoco.mjtObj.mjOBJ_BODY, int(mj.jnt_bodyid[free[0]])))
        self.free_qpos, self.free_qvel = int(mj.jnt_qposadr[free[0]]), int(mj.jnt_dofadr[free[0]])
        qpos, qvel, dofs = [], [], []
        for j in range(mj.njnt):
            if j == free[0]:
                continue
            if int(mj.jnt_type[j]) not in (int(mujoco.mjtJoint.mjJNT_HINGE), int(mujoco.mjtJoint.mjJNT_SLIDE)):
                raise ValueError("Layout: the MuJoCo tree has a ball joint; only hinges and slides under one free "
                                 "joint are mapped")
            k = model.joint_names.index(mujoco.mj_id2name(mj, mujoco.mjtObj.mjOBJ_JOINT, j))
            qpos.append(int(mj.jnt_qposadr[j]))
            qvel.append(int(mj.jnt_dofadr[j]))
            dofs.append(int(model.joint_dof_start[k]))
        self.hinge_qpos, self.hinge_qvel, self.hinge_dof = (np.array(x, np.int64) for x in (qpos, qvel, dofs))
        act = [mujoco.mj_name2id(mj, mujoco.mjtObj.mjOBJ_ACTUATOR, n) for n in model.actuator_names]
        if act != list(range(mj.nu)):
            raise ValueError("Layout: the MuJoCo actuators are not kamino's, in kamino's order")


def kamino_body_state(layout: Layout, data) -> tuple[np.ndarray, np.ndarray]:
    """``(body_q [nb, 7], body_u [nb, 6])`` of ``data`` (after ``mj_forward`` or a step) in kamino's layout: CoM
    position and ``xyzw`` quaternion; CoM velocity and angular velocity, world frame. MuJoCo's ``cvel`` is the
    spatial velocity ``(w, v_c)`` at the subtree CoM ``c`` of the body's root; a body origin ``p`` moves at
    ``v_c + w x (p - c)``."""
    ids = layout.body_ids
    pos = data.xpos[ids]
    quat = data.xquat[ids][:, [1, 2, 3, 0]]
    w, v = data.cvel[ids, :3], data.cvel[ids, 3:]
    c = data.subtree_com[layout.root_ids]
    return np.concatenate([pos, quat], 1), np.concatenate([v + np.cross(w, pos - c), w], 1)


def kamino_state(env, layout: Layout, data):
    """The kamino :class:`kamino.State` of ``data``: :func:`kamino_body_state` in ``env``'s template state."""
    import jax.numpy as jnp

    body_q, body_u = kamino_body_state(layout, data)
    return env._template.replace(body_q=jnp.asarray(body_q, env.dtype), body_u=jnp.asarray(body_u, env.dtype))


def set_mujoco_state(env, layout: Layout, mj, data, state) -> None:
    """Write the kamino ``state`` (one world) into ``data`` (``qpos``, ``qvel``; then ``mj_forward``): the free
    joint from the base body's pose and twist (``qvel``: the origin's world velocity, the angular velocity in the
    body frame), each tree hinge from kamino's ``dof_state``."""
    import mujoco

    from kamino.hostmath import quat_to_matrix
    from kamino.readouts import dof_state

    state = env.full_state(state)
    body_q = np.asarray(state.body_q, float)
    body_u = np.asarray(state.body_u, float)
    q, qd = (np.asarray(x, float) for x in dof_state(env.model, state))
    b = layout.free_body
    data.qpos[layout.free_qpos:layout.free_qpos + 3] = body_q[b, :3]
    data.qpos[layout.free_qpos + 3:layout.free_qpos + 7] = body_q[b, [6, 3, 4, 5]]
    data.qvel[layout.free_qvel:layout.free_qvel + 3] = body_u[b, :3]
    data.qvel[layout.free_qvel + 3:layout.free_qvel + 6] = quat_to_matrix(body_q[b, 3:]).T @ body_u[b, 3:]
    data.qpos[layout.hinge_qpos] = q[layout.hinge_dof]
    data.qvel[layout.hinge_qvel] = qd[layout.hinge_dof]
    mujoco.mj_forward(mj, data)


def _observer(env):
    """A jitted ``(body_q [E, nb, 7], body_u [E, nb, 6], command [E, 3], last_action [E, A], phase [E]) -> (obs,
    fallen, lin_vel, ang_vel)``, each ``[E, ...]``: the environment's ``_observe`` and ``_fallen`` on the states, and
    the base's velocities in its frame (what the walking test scores)."""
    import jax

    from kamino.envs.geometry import body_frame_vectors

    def one(body_q, body_u, command, last_action, phase):
        ps = env._template.replace(body_q=body_q, body_u=body_u)
        obs = env._observe(ps, {"command": command, "last_action": last_action, "phase": phase})
        frame = body_frame_vectors(body_q, body_u, env._base)
        return obs, env._fallen(ps), frame["lin_vel"], frame["ang_vel"]

    return jax.jit(jax.vmap(one))


def start_states(env, *, episodes: int, speed: tuple[float, float], seed: int = 0):
    """``(commands [E, 3], states)``: the resets and forward commands of :func:`kamino.envs.evaluate.walking_test`
    for the same ``seed`` (its key split: reset keys, command key, policy keys)."""
    import jax
    import jax.numpy as jnp

    key_reset, key_cmd, _ = jax.random.split(jax.random.PRNGKey(seed), 3)
    vx = jax.random.uniform(key_cmd, (episodes,), jnp.float32, speed[0], speed[1])
    commands = jnp.stack([vx, jnp.zeros_like(vx), jnp.zeros_like(vx)], -1)
    with jax.enable_x64(False):
        states = jax.jit(jax.vmap(env.reset))(jax.random.split(key_reset, episodes))
    return np.asarray(commands), env.full_state(states.pipeline_state)


def walking_test(env, policy: Policy, *, episodes: int, seconds: float, speed: tuple[float, float], seed: int = 0,
                 options: MujocoOptions = MujocoOptions(), obs_noise: float | None = None,
                 stats: dict | None = None):
    """The walking test of :func:`kamino.envs.evaluate.walking_test` with MuJoCo stepping the robot: the same
    starts and commands (:func:`start_states`), the policy's deterministic action, ``episodes`` MuJoCo worlds
    stepped one after another within each policy step. ``obs_noise``: the observation noise's scale (``None``:
    the environment's). Returns ``(commands [E], lin_vel [E, T, 3], ang_vel [E, T, 3], counted [E, T],
    fell [E])`` as kamino's does. ``stats``, a dict, receives ``loop_gap_max`` (the largest violation [m], per
    axis, of a ``<connect>`` equality at the end of a policy step of a robot still up) and ``saturated_fraction``
    (the fraction of actuator forces at their ``forcerange`` bound then)."""
    import jax
    import jax.numpy as jnp
    import mujoco

    mj = mujoco_model(env, options)
    substeps = env.dt / mj.opt.timestep
    if abs(substeps - round(substeps)) > 1e-6 or round(substeps) < 1:
        raise ValueError(f"walking_test: the MuJoCo time step {mj.opt.timestep:g} s does not divide the policy "
                         f"period {env.dt:g} s")
    substeps = round(substeps)
    layout = Layout(env.model, mj)
    steps = round(seconds / env.dt)
    commands, states = start_states(env, episodes=episodes, speed=speed, seed=seed)
    datas = [mujoco.MjData(mj) for _ in range(episodes)]
    for e, d in enumerate(datas):
        set_mujoco_state(env, layout, mj, d, jax.tree.map(lambda x, e=e: x[e], states))
    observe = _observer(env)
    act = jax.jit(policy.make_policy(policy.params, deterministic=True))
    noise = env._obs_noise if obs_noise is None else float(obs_noise)
    scale = noise * np.asarray(env._obs_noise_scale(), np.float32)
    rng = np.random.default_rng(seed)
    freq = getattr(env, "_gait_frequency", None)
    na = env.action_size
    last = np.zeros((episodes, na), np.float32)
    alive = np.ones(episodes, bool)
    lin = np.zeros((episodes, steps, 3), np.float32)
    ang = np.zeros((episodes, steps, 3), np.float32)
    counted = np.zeros((episodes, steps), bool)
    key = jax.random.PRNGKey(0)
    gaps, saturated, forces = 0.0, 0, 0
    limits = np.where(mj.actuator_forcelimited.astype(bool), mj.actuator_forcerange[:, 1], np.inf)

    def read(phase):
        bq, bu = zip(*(kamino_body_state(layout, d) for d in datas), strict=True)
        obs, fallen, v, w = (np.asarray(x) for x in observe(
            jnp.asarray(np.stack(bq), env.dtype), jnp.asarray(np.stack(bu), env.dtype),
            jnp.asarray(commands, env.dtype), jnp.asarray(last, env.dtype), jnp.full(episodes, phase, env.dtype)))
        blown = ~np.all(np.abs(obs) <= env._obs_limit, 1)  # a non-finite entry too
        # MuJoCo resets a world whose accelerations turn non-finite to its reference pose (mjWARN_BADQACC): a failure
        diverged = np.array([d.warning[int(mujoco.mjtWarning.mjWARN_BADQACC)].number > 0 for d in datas])
        obs = np.where(np.isfinite(obs), obs, 0.0) + scale * rng.standard_normal(obs.shape).astype(np.float32)
        return np.clip(obs, -env._obs_limit, env._obs_limit), fallen | blown | diverged, v, w

    obs, _, _, _ = read(0.0)
    phase = 0.0
    for t in range(steps):
        action = np.clip(np.asarray(act(jnp.asarray(obs), key)[0]), -1.0, 1.0)
        target = np.asarray(env.action_to_target(jnp.asarray(action)))
        for e, d in enumerate(datas):
            if not alive[e]:
                continue
            d.ctrl[:] = target[e]
            for _ in range(substeps):
                mujoco.mj_step(mj, d)
        up = [d for e, d in enumerate(datas) if alive[e]]
        for d in up:
            rows = d.efc_type[:d.nefc] == int(mujoco.mjtConstraint.mjCNSTR_EQUALITY)
            gap = float(np.abs(d.efc_pos[:d.nefc][rows]).max()) if rows.any() else 0.0
            gaps = max(gaps, gap)
            saturated += int(np.sum(np.abs(d.actuator_force) >= limits * (1 - 1e-6)))
            forces += mj.nu
        last = action.astype(np.float32)
        if freq is not None:
            phase = float(np.mod(phase + freq * env.dt, 1.0))
        obs, down, v, w = read(phase)
        counted[:, t] = alive
        lin[:, t], ang[:, t] = v, w
        alive &= ~down
    if stats is not None:
        stats.update(loop_gap_max=gaps, saturated_fraction=saturated / max(forces, 1))
    return commands[:, 0], lin, ang, counted, ~alive


def evaluate_mujoco(policy: Policy | str | Path, *, episodes: int = 64, seconds: float = 10.0,
                    speed: tuple[float, float] = (0.3, 0.5), seed: int = 0, options: MujocoOptions = MujocoOptions(),
                    obs_noise: float | None = None, env: dict | None = None, max_error: float = 0.1,
                    max_falls: float = 0.05) -> dict:
    """The walking test of a joystick ``policy`` (a :class:`~kamino.envs.policy.Policy`, a shipped policy's name,
    or a run or checkpoint path) in MuJoCo (:func:`walking_test`); the report of
    :func:`kamino.envs.evaluate.evaluate`, with ``sim="mujoco"`` and the MuJoCo settings."""
    from kamino.envs import make
    from kamino.envs.evaluate import check_walk, resolve, summarize

    check_walk(episodes, seconds, speed, "evaluate_mujoco")
    if not isinstance(policy, Policy):
        policy = resolve(policy)
    overrides = dict(env or {})
    environment = make(policy.task, backend="jax", **{**policy.env, **overrides, "resample_steps": None})
    if environment.evaluation != "walking":
        raise ValueError(f"evaluate_mujoco: {policy.task} has no walking test (its test: {environment.evaluation!r}); "
                         "the MuJoCo walking test needs a joystick task")
    if environment.observation_size != policy.observation_size:
        raise ValueError(f"evaluate_mujoco: the policy takes {policy.observation_size} observations, {policy.task} "
                         f"gives {environment.observation_size}")
    t0 = time.perf_counter()
    stats: dict = {}
    vx, lin, _, counted, fell = walking_test(environment, policy, episodes=episodes, seconds=seconds,
                                             speed=tuple(speed), seed=seed, options=options, obs_noise=obs_noise,
                                             stats=stats)
    report = {**summarize(vx, lin, counted, fell), **stats}
    mj = mujoco_model(environment, options)
    report.update(speed_range=list(speed), bars={"max_error": max_error, "max_falls": max_falls},
                  passed=report["tracking_error_mean"] <= max_error and report["fall_fraction"] <= max_falls,
                  seconds=seconds, seed=seed, deterministic=True, wall_s=time.perf_counter() - t0, task=policy.task,
                  sim="mujoco", checkpoint=policy.source, step=policy.step, env=overrides,
                  mujoco={"timestep": float(mj.opt.timestep), "integrator": INTEGRATORS[_integrator_index(mj)],
                          "equality_solref": [float(x) for x in mj.eq_solref[0]] if mj.neq else None,
                          "contact_solref": [float(x) for x in mj.geom_solref[0]],
                          "obs_noise": environment._obs_noise if obs_noise is None else float(obs_noise)})
    return report


def _integrator_index(mj) -> int:
    import mujoco

    order = (mujoco.mjtIntegrator.mjINT_EULER, mujoco.mjtIntegrator.mjINT_RK4, mujoco.mjtIntegrator.mjINT_IMPLICIT,
             mujoco.mjtIntegrator.mjINT_IMPLICITFAST)
    return [int(x) for x in order].index(int(mj.opt.integrator))


def add_mujoco_arguments(p: argparse.ArgumentParser) -> None:
    """The MuJoCo options of ``kamino eval --sim mujoco`` and ``python -m kamino.envs.sim2sim``."""
    g = p.add_argument_group("MuJoCo (--sim mujoco)")
    g.add_argument("--mj-timestep", type=float, help="MuJoCo's time step [s] (default: the export's, 0.002); "
                   "it must divide the policy period")
    g.add_argument("--mj-integrator", choices=INTEGRATORS, help="MuJoCo's integrator (default: the export's, "
                   "implicitfast)")
    g.add_argument("--mj-equality-solref", type=float, nargs=2, metavar=("TIMECONST", "DAMPRATIO"),
                   help="solref of the loop closures' <connect> equalities (default: the export's, 0.004 1)")
    g.add_argument("--mj-contact-solref", type=float, nargs=2, metavar=("TIMECONST", "DAMPRATIO"),
                   help="solref of the contacts (default: MuJoCo's, 0.02 1)")
    g.add_argument("--obs-noise", type=float, help="scale of the observation noise (default: the task's, 1)")


def options_from(args: argparse.Namespace) -> MujocoOptions:
    """The :class:`MujocoOptions` of parsed :func:`add_mujoco_arguments`."""
    return MujocoOptions(timestep=args.mj_timestep, integrator=args.mj_integrator,
                         equality_solref=None if args.mj_equality_solref is None else tuple(args.mj_equality_solref),
                         contact_solref=None if args.mj_contact_solref is None else tuple(args.mj_contact_solref))


def main(argv: list[str] | None = None) -> int:
    """``python -m kamino.envs.sim2sim ARGS`` (the same as ``kamino eval --sim mujoco ARGS``)."""
    from kamino.envs import evaluate

    return evaluate.main(["--sim", "mujoco", *(sys.argv[1:] if argv is None else argv)])


if __name__ == "__main__":
    raise SystemExit(main())
