"""Environments on Brax's API (kamino/envs; docs/envs.md).

Brax's wrappers build ``info`` entries with the default float (``jp.zeros``) at reset and float32 ones at step, so
they need ``jax_enable_x64`` off (this suite turns it on: tests/conftest.py); every test that goes through them runs
under ``jax.enable_x64(False)``. The environments themselves keep their own dtype (float32) either way, which the
first test checks with x64 on.

The four-bar's contract tests run on the JAX backend. The robots' (dr_legs, bdx) run on the Warp backend, on Warp's
CPU device: dr_legs' JAX step takes 18 s to trace, lower and compile on the 2-core machine (5.0, 1.1 and 11.9
s), and the environment code above the step is the same on both backends
(test_warp_backend_env_matches_jax_under_jit_and_vmap checks the two steps agree).
"""

from __future__ import annotations

import dataclasses
import functools
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

pytest.importorskip("brax")

from brax.envs.wrappers import training

import kamino
from kamino.envs import DrLegsJoystick, EnvSystem, FourbarTrack, make, randomize
from kamino.spatial import quat_to_matrix
from tests.helpers import ALL_CORES, jax_on_gpu

N = 4  # environments per batch: small (CI has two cores), more than one (vmap)
EPISODE = 6  # brax EpisodeWrapper length in the auto-reset test


def _violation(env, body_q: jax.Array) -> np.ndarray:
    """Worst joint/loop residual [m or rad] of each configuration ``body_q [B, nb, 7]``."""
    state = env._template
    return np.asarray(jax.vmap(lambda q: kamino.metrics(env.model, state.replace(body_q=q))["constraint_violation"])(
        body_q)).reshape(-1)


def _signature(tree) -> dict:
    return jax.tree.map(lambda x: (tuple(x.shape), x.dtype), tree)


@pytest.fixture(scope="module")
def fourbar():
    return FourbarTrack(backend="jax")


@pytest.fixture(scope="module")
def wrapped(fourbar):
    """The four-bar through brax's training wrappers (Vmap / Episode / AutoReset), jitted, and a short run of it:
    ``N`` environments, a sinusoidal action, ``2 EPISODE`` steps; the states after each step."""
    with jax.enable_x64(False):
        env = training.wrap(fourbar, episode_length=EPISODE)
        reset, step = jax.jit(env.reset), jax.jit(env.step)
        states = [reset(jax.random.split(jax.random.PRNGKey(0), N))]
        for k in range(2 * EPISODE):
            states.append(step(states[-1], jnp.full((N, 1), 0.8 * np.sin(0.7 * k), jnp.float32)))
    return {"env": env, "reset": reset, "step": step, "states": states}


@pytest.fixture(scope="module")
def shapes(fourbar):
    """The four-bar's state after reset and after one step, as shapes and dtypes (``jax.eval_shape``, with this
    suite's jax_enable_x64 on): traced once for the tests that read them (the JAX step's trace takes seconds)."""
    s0 = jax.eval_shape(fourbar.reset, jax.random.PRNGKey(1))
    return s0, jax.eval_shape(fourbar.step, s0, jax.ShapeDtypeStruct((1,), jnp.float32))


def test_reset_and_step_keep_keys_shapes_and_dtypes(fourbar, shapes):
    """``metrics`` and ``info`` have the same keys, shapes and dtypes at reset and at step (brax scans over steps),
    everything in the environment's float32 although this suite runs with jax_enable_x64 on."""
    s0, s1 = shapes
    assert _signature(s0.metrics) == _signature(s1.metrics)
    assert _signature(s0.info) == _signature(s1.info)
    assert _signature(s0.pipeline_state) == _signature(s1.pipeline_state)
    assert set(s0.metrics) == {"tracking", "action_rate", "failed"}
    for s in (s0, s1):
        assert s.obs.shape == (fourbar.observation_size,) and s.obs.dtype == jnp.float32
        assert s.reward.shape == () and s.reward.dtype == jnp.float32
        assert s.done.shape == () and s.done.dtype == jnp.float32


def test_state_carries_no_zero_size_array(fourbar, wrapped, shapes):
    """No leaf of the environment's state has zero size: XLA's GPU compiler (jax 0.11.2) crashes on a zero-size
    array in the carry of a loop on several GPUs (brax's pmap of a scan; kamino.state.drop_empty). The four-bar has
    no contact capacity and no couplings, so its kamino State has such arrays; ``full_state`` gives them back, with
    the batch axis, as ``init_state`` shapes them."""
    s0, s1 = shapes
    template = kamino.init_state(fourbar.model, jnp.float32)
    assert any(np.size(x) == 0 for x in jax.tree.leaves(template))  # the case the test is about
    for s in (s0, s1, wrapped["states"][-1]):
        assert all(np.prod(x.shape) > 0 for x in jax.tree.leaves(s)), _signature(s)
    whole = fourbar.full_state(wrapped["states"][-1].pipeline_state)
    assert _signature(whole) == jax.tree.map(lambda x: ((N, *x.shape), x.dtype), template)
    with pytest.raises(ValueError, match=r"state.coupling_force is None.*full_state"):
        kamino.step(fourbar.model, jax.tree.map(lambda x: x[0], wrapped["states"][-1].pipeline_state))


def test_jit_vmap_reset_and_step(fourbar, wrapped):
    """Batched, jitted reset and step: finite observations of the declared size, rewards in the kernel's range,
    no world failed, time advancing by the policy period."""
    s0, s1 = wrapped["states"][0], wrapped["states"][1]
    assert s0.obs.shape == (N, 7) and s1.obs.shape == (N, 7)
    assert np.all(np.isfinite(np.asarray(s1.obs)))
    # tracking is exp(-err^2) in (0, 1]; the action-rate penalty is at most 0.02 * 2^2
    r = np.asarray(s1.reward)
    assert np.all((r > -0.08 - 1e-6) & (r <= 1.0 + 1e-6))
    assert not np.any(np.asarray(s1.pipeline_state.info.failed))
    # one policy step = decimation simulator steps: 5 x 10 ms (float32 sum of five 0.01 s steps)
    np.testing.assert_allclose(np.asarray(s1.pipeline_state.time), fourbar.dt, rtol=1e-5)
    assert fourbar.dt == pytest.approx(0.05)


def test_auto_reset_through_brax_wrap(wrapped):
    """brax's EpisodeWrapper ends the episode after EPISODE steps and its AutoResetWrapper puts every world back to
    its first state; the environment's episode memory (last action, target) is restored at the next step."""
    states = wrapped["states"]
    first = states[0]
    end = states[EPISODE]
    assert np.all(np.asarray(end.done) == 1.0)
    np.testing.assert_array_equal(np.asarray(end.pipeline_state.body_q), np.asarray(first.pipeline_state.body_q))
    np.testing.assert_array_equal(np.asarray(end.obs), np.asarray(first.obs))
    restarted = states[EPISODE + 1]
    assert np.all(np.asarray(restarted.done) == 0.0)
    # the first step after the reset tracks the episode's first target again, and its action-rate term compares
    # with the reset's zero action (the last action of the previous episode is forgotten)
    np.testing.assert_array_equal(np.asarray(restarted.info["target"]), np.asarray(first.info["target"]))
    np.testing.assert_array_equal(np.asarray(restarted.info["task_steps"]), 1)
    a = np.float32(0.8 * np.sin(0.7 * EPISODE))
    np.testing.assert_allclose(np.asarray(restarted.metrics["action_rate"]), -0.02 * a * a, rtol=1e-5)


def test_world_health_sets_done_and_auto_reset_recovers(wrapped):
    """A world whose health flag is set (``state.info.failed``: kamino freezes it) ends its episode; the others go
    on; brax's auto-reset gives the failed world its first state back, healthy."""
    with jax.enable_x64(False):
        s = wrapped["states"][1]
        ps = s.pipeline_state
        sick = ps.replace(info=dataclasses.replace(ps.info, failed=ps.info.failed.at[0].set(True)))
        out = wrapped["step"](s.replace(pipeline_state=sick), jnp.zeros((N, 1), jnp.float32))
    done = np.asarray(out.done)
    assert done[0] == 1.0 and np.all(done[1:] == 0.0)
    assert float(out.metrics["failed"][0]) == 1.0
    first = wrapped["states"][0].pipeline_state
    np.testing.assert_array_equal(np.asarray(out.pipeline_state.body_q[0]), np.asarray(first.body_q[0]))
    assert not bool(out.pipeline_state.info.failed[0, 0])


def test_a_blown_up_observation_ends_the_episode_as_failed(wrapped):
    """A finite state gone wild ends its episode: an observation entry beyond ``obs_limit`` (here the four-bar's
    observation scaled 1e4-fold, standing in for a velocity blow-up that the world's health flag, which checks
    finiteness and convergence, does not see) sets ``done``, counts in ``metrics["failed"]``, and reaches the policy
    clipped to the limit, so that neither the policy nor the observation normaliser sees it. The unscaled task goes
    on: over the first episode of the ``wrapped`` run (the same steps from the same kind of reset; its limit is the
    default 100) every observation entry stays below 50 and no episode ends, so under a limit of 50 none would
    either (``done`` is the limit test, the health flag and the task's own end; the four-bar has no fall test). That
    run's step is compiled already: the unscaled task needs no second compile of the four-bar's step."""

    class Wild(FourbarTrack):
        def _observe(self, ps, info):
            return super()._observe(ps, info) * 1e4

    limit = 50.0
    with jax.enable_x64(False):
        env = Wild(obs_limit=limit)
        s = jax.jit(env.step)(jax.jit(env.reset)(jax.random.PRNGKey(0)), jnp.zeros(1, jnp.float32))
    assert float(s.done) == 1.0 and float(s.metrics["failed"]) == 1.0
    assert not bool(s.pipeline_state.info.failed[0])  # the simulated world itself is healthy
    obs = np.abs(np.asarray(s.obs))
    assert obs.max() == limit
    for s in wrapped["states"][1:EPISODE]:
        assert np.all(np.asarray(s.done) == 0.0) and np.all(np.asarray(s.metrics["failed"]) == 0.0)
        assert not np.any(np.asarray(s.pipeline_state.info.failed))
        assert np.abs(np.asarray(s.obs)).max() < limit


@pytest.fixture(scope="module")
def fourbar_warp():
    return FourbarTrack(backend="warp")


#: per-environment factors of the randomization below: environments 0 and 1 nominal, 2 three times as heavy, 3 with
#: every other parameter changed (gains, effort limit, gravity, actuator delay; the four-bar has no geoms, armature
#: or passive damping: those factors leave zeros at zero)
_MASS = (1.0, 1.0, 3.0, 1.0)
_OTHER = (1.0, 1.0, 1.0, 1.3)


def _every_field(sys: EnvSystem):
    """A brax ``randomization_fn`` (of ``sys`` alone: brax's wrap binds nothing) changing every EnvSystem field."""
    def one(m, o):
        return sys.replace(
            body_mass=sys.body_mass * m, body_inertia=sys.body_inertia * m, geom_friction=sys.geom_friction * o,
            dof_kp=sys.dof_kp * o, dof_kd=sys.dof_kd / o, dof_armature=sys.dof_armature * o,
            dof_damping=sys.dof_damping * o, dof_effort_limit=sys.dof_effort_limit / o, gravity=sys.gravity * o,
            action_delay=(o - 1.0) * 0.05)

    batched = jax.vmap(one)(jnp.asarray(_MASS, jnp.float32), jnp.asarray(_OTHER, jnp.float32))
    return batched, jax.tree.map(lambda _: 0, batched)


@pytest.fixture(scope="module")
def randomized(fourbar, fourbar_warp):
    """Four steps of the four-bar through brax's DomainRandomizationVmapWrapper (``_every_field``), from the same
    reset and actions in every environment, on each backend: ``{backend: final brax State}``."""
    out = {}
    with jax.enable_x64(False):
        for env in (fourbar, fourbar_warp):
            w = training.wrap(env, episode_length=100, randomization_fn=_every_field)
            key = jax.random.PRNGKey(3)
            s = w.reset(jnp.stack([key] * len(_MASS)))  # the same initial configuration and target in all
            step = jax.jit(w.step)
            for _ in range(4):
                s = step(s, jnp.full((len(_MASS), 1), 0.9, jnp.float32))
            out[env.backend] = s
    return out


@pytest.mark.parametrize("backend", ["jax", "warp"])
def test_randomization_fn_changes_the_dynamics(randomized, fourbar, backend):
    """brax's DomainRandomizationVmapWrapper with a randomization_fn, on each backend: environments whose
    parameters differ follow different trajectories from the same reset and actions; equal parameters give
    identical ones."""
    q = np.asarray(randomized[backend].pipeline_state.body_q)
    np.testing.assert_array_equal(q[0], q[1])
    # three times the mass: the effort-limited crank (3 N m) accelerates a third as fast towards the same target
    assert np.max(np.abs(q[2] - q[0])) > 1e-2
    # stiffer, less damped PD with a lower effort limit, stronger gravity and a delay: another trajectory (2e-3 m
    # measured on both backends; float32 rounding is 1e-7)
    assert np.max(np.abs(q[3] - q[0])) > 5e-4
    assert fourbar.sys.body_mass.shape == (fourbar.model.num_bodies,)


def test_randomized_environments_agree_across_backends(randomized):
    """The Warp FFI step reading each environment's parameters (one call for the batch, each environment a world
    with its own masses, gains, limits and gravity) follows the JAX reference's randomized environments: 4 policy
    steps of 10 substeps in float32 on both. Poses agree to 1e-4 (2.8e-6 measured; the environments differ from
    one another by 2e-3 to 0.23). The observations hold the joint rates, which carry each solver's stopping point
    inside the environment's PADMM tolerance (1e-3): 5e-4 (1.1e-4 measured, on the heavy crank against its effort
    limit, 11 iterations a step; 9e-6 on the others)."""
    np.testing.assert_allclose(np.asarray(randomized["warp"].pipeline_state.body_q),
                               np.asarray(randomized["jax"].pipeline_state.body_q), atol=1e-4)
    np.testing.assert_allclose(np.asarray(randomized["warp"].obs), np.asarray(randomized["jax"].obs), atol=5e-4)


def test_randomize_factory_draws_per_environment(fourbar):
    fn = randomize(mass_scale=(0.5, 2.0), friction_scale=(0.5, 1.5), kp_scale=(0.8, 1.2), action_delay=(0.0, 0.02))
    sys_v, in_axes = fn(fourbar.sys, jax.random.split(jax.random.PRNGKey(0), 8))
    assert sys_v.body_mass.shape == (8, fourbar.model.num_bodies)
    assert sys_v.action_delay.shape == (8,)
    assert jax.tree.leaves(in_axes) == [0] * len(jax.tree.leaves(sys_v))
    ratio = np.asarray(sys_v.body_mass) / np.asarray(fourbar.sys.body_mass)
    assert np.all((ratio >= 0.5) & (ratio <= 2.0)) and np.ptp(ratio) > 0.1
    # the inertia follows the mass (a denser body of the same shape)
    inertia_ratio = np.asarray(sys_v.body_inertia)[:, :, 0, 0] / np.asarray(fourbar.sys.body_inertia)[:, 0, 0]
    np.testing.assert_allclose(inertia_ratio, ratio, rtol=1e-5)
    # effort limits per DoF (the unlimited DoFs stay unlimited) and one factor on the gravity vector
    sys_v, _ = randomize(effort_limit_scale=(0.5, 1.5), gravity_scale=(0.8, 1.2))(
        fourbar.sys, jax.random.split(jax.random.PRNGKey(1), 8))
    limit, nominal = np.asarray(sys_v.dof_effort_limit), np.asarray(fourbar.sys.dof_effort_limit)
    finite = np.isfinite(nominal)
    assert finite.any() and not finite.all() and np.all(np.isinf(limit[:, ~finite]))
    ratio = limit[:, finite] / nominal[finite]
    assert np.all((ratio >= 0.5) & (ratio <= 1.5)) and np.ptp(ratio) > 0.1
    g = np.asarray(sys_v.gravity)
    np.testing.assert_allclose(np.cross(g, np.asarray(fourbar.sys.gravity)), 0.0, atol=1e-5)  # along nominal gravity
    assert np.all((np.linalg.norm(g, axis=1) >= 0.8 * 9.81 - 1e-4) & (np.linalg.norm(g, axis=1) <= 1.2 * 9.81 + 1e-4))
    with pytest.raises(ValueError, match="mass_scale"):
        randomize(mass_scale=(2.0, 1.0))


def test_train_randomize_option():
    """``kamino train --randomize``: each KEY=(LOW,HIGH) is a range of ``randomize``; alone, its defaults; an unknown
    range exits naming ``--randomize`` and the ranges."""
    from kamino.envs.train import parse_args

    args = parse_args(["fourbar_track", "--randomize", "mass_scale=(0.5,1.5)",
                       "--randomize", "gravity_scale=(0.9,1.1)"])
    assert args.randomization == {"mass_scale": (0.5, 1.5), "gravity_scale": (0.9, 1.1)}
    assert parse_args(["fourbar_track", "--randomize"]).randomization == {}
    assert parse_args(["fourbar_track"]).randomization is None
    with pytest.raises(SystemExit):
        parse_args(["fourbar_track", "--randomize", "mass=(1,2)"])


def test_resets_close_the_loops(fourbar):
    """Every reset configuration satisfies every joint and the loop closure to 1e-5 m (forward kinematics solves
    to 1e-6 m; float32): the bank (default) and FK inside the traced reset (``reset_bank=None``, built through
    brax's registry), and the resets spread over the crank's range."""
    assert fourbar._bank.shape[0] >= 250  # the crank-rocker assembles at every crank angle: all 256 draws converge
    assert _violation(fourbar, jnp.asarray(fourbar._bank)).max() < 1e-5
    import brax.envs

    traced = brax.envs.get_environment("fourbar_track", reset_bank=None)
    assert isinstance(traced, FourbarTrack)
    states = jax.jit(jax.vmap(traced.reset_state))(jax.random.split(jax.random.PRNGKey(7), 16))
    assert _violation(traced, states.body_q).max() < 1e-5
    crank = np.asarray(jax.vmap(lambda s: traced.actuated_state(s)[0][0])(states))
    assert np.ptp(crank) > 2.0  # reset_noise 1: the initial crank angle is drawn over +-2.8 rad
    np.testing.assert_array_equal(np.asarray(states.body_u), 0.0)  # resets start at rest


def test_bad_arguments_raise_naming_them():
    model = kamino.models.fourbar(actuated=True)
    with pytest.raises(ValueError, match="backend"):
        FourbarTrack(backend="torch")
    with pytest.raises(ValueError, match="sim_dt"):
        FourbarTrack(sim_dt=0.0)
    with pytest.raises(ValueError, match="decimation"):
        FourbarTrack(decimation=0)
    with pytest.raises(ValueError, match="action_range"):
        FourbarTrack(action_range=4.0)
    with pytest.raises(ValueError, match="reset_bank"):
        FourbarTrack(reset_bank=0)
    with pytest.raises(ValueError, match="obs_limit"):
        FourbarTrack(obs_limit=0.0)
    with pytest.raises(ValueError, match="compile_for"):  # a batch size for the Warp step
        FourbarTrack(backend="warp", compile_for=0)
    with pytest.raises(ValueError, match="compile_for"):  # the JAX reference compiles at its first call
        FourbarTrack(backend="jax", compile_for=64)
    with pytest.raises(ValueError, match="task"):
        make("cartpole")
    from kamino.envs import KaminoEnv

    with pytest.raises(ValueError, match="action_lower and action_upper"):  # the crank hinge has no limits
        KaminoEnv(model, sim_dt=0.01, decimation=2)
    with pytest.raises(ValueError, match="no actuators"):
        KaminoEnv(kamino.models.fourbar(), sim_dt=0.01, decimation=2)
    b = kamino.ModelBuilder()
    link = b.add_body(mass=1.0, inertia=np.eye(3) * 0.01, pos=(0.0, 0.0, 0.5), name="link")
    b.add_joint_at(kamino.JointType.REVOLUTE, -1, link, anchor=(0.0, 0.0, 1.0), axis=(0.0, 1.0, 0.0), name="hinge",
                   actuation=kamino.Actuation("effort", effort_limit=5.0))
    with pytest.raises(ValueError, match="POSITION"):  # actions are PD targets
        KaminoEnv(b.finalize(), sim_dt=0.01, decimation=2, action_lower=-1, action_upper=1)
    with pytest.raises(ValueError, match="worlds"):
        KaminoEnv(kamino.replicate(model, 2), sim_dt=0.01, decimation=2, action_lower=-1, action_upper=1)


def test_step_rejects_a_wrong_action_shape(fourbar, shapes):
    s = shapes[0]
    with pytest.raises(ValueError, match="action"):
        jax.eval_shape(fourbar.step, s, jax.ShapeDtypeStruct((2,), jnp.float32))


@pytest.fixture(scope="module")
def legs():
    """dr_legs at the paper's gains; its reset bank the size of ``legs_own_gains``': the gains are not in the bank's
    forward kinematics, so one compiled program solves both banks (4 s of the second fixture's 4.6, measured)."""
    return DrLegsJoystick(kp=15.0, kd=0.6, reset_bank=8, backend="warp")


@pytest.fixture(scope="module")
def legs_own_gains():
    """``dr_legs_joystick`` as registered (the model's gains), built once: its construction solves the reset bank."""
    return make("dr_legs_joystick", reset_bank=8, backend="warp")


def test_dr_legs_actions_map_inside_the_joint_limits(legs):
    """Actions (clipped to [-1, 1]) map onto the actuated joints' limits: -1 and +1 land on them exactly."""
    m = legs.model
    lo, hi = m.dof_lower[m.actuator_dof], m.dof_upper[m.actuator_dof]
    a = jax.random.uniform(jax.random.PRNGKey(0), (256, legs.action_size), jnp.float32, -3.0, 3.0)
    t = np.asarray(jax.vmap(legs.action_to_target)(a))
    assert np.all(t >= lo - 1e-6) and np.all(t <= hi + 1e-6)
    np.testing.assert_allclose(np.asarray(legs.action_to_target(-jnp.ones(12))), lo, atol=1e-6)
    np.testing.assert_allclose(np.asarray(legs.action_to_target(jnp.ones(12))), hi, atol=1e-6)


def test_dr_legs_joystick_runs(legs):
    """Reset and step under jit + vmap on the CPU: loops closed at reset, feet on the ground, the documented
    observation, and falls end episodes (the paper's gains, kp 15 N m/rad, cannot hold the 17 kg robot at a zero
    action: it collapses in about 50 steps, 1 s; measured)."""
    assert legs.observation_size == 48 and legs.action_size == 12 and legs.dt == pytest.approx(0.02)
    assert _violation(legs, jnp.asarray(legs._bank)).max() < 1e-5
    keys = jax.random.split(jax.random.PRNGKey(0), N)
    s = jax.jit(jax.vmap(legs.reset))(keys)
    assert s.obs.shape == (N, 48)
    assert _violation(legs, s.pipeline_state.body_q).max() < 1e-5  # the heading is a rigid turn: loops stay closed
    quat = np.asarray(s.pipeline_state.body_q[:, legs._base, 3:])
    heading = 2.0 * np.arctan2(quat[:, 2], quat[:, 3])  # the pelvis starts (nearly) level: a turn about z
    assert np.ptp(heading) > 0.5  # uniform in [-pi, pi)
    pts, bodies, radii = legs._support
    q = np.asarray(s.pipeline_state.body_q)
    # lowest foot corner of every reset on the ground plane (z = 0), to float32 rounding
    from kamino.envs.geometry import place_on_ground

    for w in range(N):
        moved = place_on_ground(jnp.asarray(q[w]), jnp.asarray(pts, jnp.float32), bodies, jnp.asarray(radii,
                                                                                                      jnp.float32), 0.0)
        assert abs(float(moved[0, 2] - q[w, 0, 2])) < 1e-5
    np.testing.assert_allclose(np.asarray(s.obs[:, 3:6]), np.tile([0.0, 0.0, -1.0], (N, 1)), atol=0.25)  # upright
    cmd = np.asarray(s.info["command"])
    assert np.all(np.abs(cmd) <= np.array([0.5, 0.3, 0.8]) + 1e-6)
    np.testing.assert_array_equal(np.asarray(s.obs[:, 9:12]), cmd)  # the command is observed without noise

    step = jax.jit(jax.vmap(legs.step))
    ever_done = np.zeros(N, bool)
    for _ in range(70):
        s = step(s, jnp.zeros((N, 12), jnp.float32))
        ever_done |= np.asarray(s.done) > 0
        assert np.all(np.isfinite(np.asarray(s.obs))) and np.all(np.isfinite(np.asarray(s.reward)))
    assert ever_done.all()
    assert set(s.metrics) == {*legs.reward_terms, "failed"}


def _assert_stands_at_a_zero_action(env, seed: int, num_envs: int = 4, steps: int = 50) -> None:
    """From ``num_envs`` resets, ``steps`` policy steps of a zero action: no episode ends, and the pelvis ends within
    2 cm of its height at reset (a robot settling onto its feet moves about 1 cm; a collapse moves tens of cm)."""
    s = jax.jit(jax.vmap(env.reset))(jax.random.split(jax.random.PRNGKey(seed), num_envs))
    h0 = np.asarray(s.pipeline_state.body_q[:, env._base, 2])
    step = jax.jit(jax.vmap(env.step))
    for _ in range(steps):
        s = step(s, jnp.zeros((num_envs, env.action_size), jnp.float32))
        assert not np.any(np.asarray(s.done) > 0)
    h = np.asarray(s.pipeline_state.body_q[:, env._base, 2])
    assert np.all(np.abs(h - h0) < 0.02), (h0, h)


def test_bdx_joystick_stands_at_a_zero_action():
    """``bdx_joystick`` (a tree biped, 14 actions): resets on the ground, and with its model's leg gains (kp 400
    N m/rad) a zero action holds the reference pose. Over 1 s the pelvis stays within 2 cm of its height at
    reset and no episode ends; the robot does settle onto its feet, by about 1 cm (measured). This is the
    counterpart of dr_legs at the paper's kp 15, which collapses."""
    env = make("bdx_joystick", reset_bank=8, backend="warp")
    assert env.observation_size == 12 + 3 * 14 and env.action_size == 14
    _assert_stands_at_a_zero_action(env, seed=0)


def test_dr_legs_joystick_stands_at_a_zero_action_with_its_own_gains(legs_own_gains):
    """The default gains of ``dr_legs_joystick`` are the model's own (kp 300 N m/rad at the hips and knees, 150 at
    the ankles): a zero action holds the reference pose for 1 s. The pelvis stays within 2 cm of its height at
    reset, and no episode ends. With the paper's kp 15 the same robot collapses (test_dr_legs_joystick_runs)."""
    _assert_stands_at_a_zero_action(legs_own_gains, seed=1)
    with pytest.raises(ValueError, match="kp and kd together"):
        DrLegsJoystick(kp=15.0)


def test_with_command_sets_the_command_everywhere_the_episode_reads_it(legs):
    """``Joystick.with_command`` (the walking evaluation's fixed commands): the command lands in ``info``, in the
    memory an auto-reset restores, and in the observation's command entries (9-11); a wrong shape is refused."""
    s = legs.reset(jax.random.PRNGKey(0))
    cmd = jnp.array([0.4, 0.0, 0.0], jnp.float32)
    s2 = legs.with_command(s, cmd)
    np.testing.assert_array_equal(np.asarray(s2.info["command"]), cmd)
    np.testing.assert_array_equal(np.asarray(s2.info["reset_memory"]["command"]), cmd)
    np.testing.assert_array_equal(np.asarray(s2.obs[9:12]), cmd)
    np.testing.assert_array_equal(np.asarray(s2.obs[:9]), np.asarray(s.obs[:9]))  # the rest is untouched
    with pytest.raises(ValueError, match=r"command has shape \(2,\)"):
        legs.with_command(s, jnp.zeros(2))


def test_joystick_reward_is_the_sum_of_its_terms_clipped_at_zero(legs_own_gains):
    """The joystick reward is the sum of its weighted terms (``metrics``), clipped at 0 from below
    (``only_positive_rewards``, docs/envs.md "Training on the GPU"). A zero action from a reset earns about +1.1 per
    policy step (the standing robot: tracking, upright, alive, little torque), so the sum is positive and passes
    unchanged. A full-range action that flips every step makes the torque and action-rate penalties several units
    (measured: -2.5 to -7 per step), so the sum is negative and the reward is exactly 0."""
    env = legs_own_gains
    with jax.enable_x64(False):
        s = jax.jit(jax.vmap(env.reset))(jax.random.split(jax.random.PRNGKey(3), 2))
        step = jax.jit(jax.vmap(env.step))
        s = step(s, jnp.zeros((2, 12), jnp.float32))
        total = sum(np.asarray(v) for k, v in s.metrics.items() if k != "failed")
        assert np.all(total > 0.5)
        np.testing.assert_allclose(np.asarray(s.reward), total, rtol=1e-6)
        for sign in (1.0, -1.0, 1.0):
            s = step(s, jnp.full((2, 12), sign, jnp.float32))
        total = sum(np.asarray(v) for k, v in s.metrics.items() if k != "failed")
        assert np.all(total < -0.5)
        np.testing.assert_array_equal(np.asarray(s.reward), 0.0)


def test_warp_backend_env_matches_jax_under_jit_and_vmap(fourbar_warp, wrapped):
    """backend="warp": kamino's Warp step through its JAX FFI, batched over environments by a custom_vmap rule (one
    Warp call for all of them), on Warp's CPU device; the same trajectory as the JAX reference to float32 rounding
    (5e-6 measured over these steps), nested vmap included. A randomization_fn whose sys has per-environment
    shapes where brax vmaps none is refused, naming the field."""
    env = fourbar_warp
    with jax.enable_x64(False):
        w = training.wrap(env, episode_length=EPISODE)
        step = jax.jit(w.step)
        s = jax.jit(w.reset)(jax.random.split(jax.random.PRNGKey(0), N))
        for k in range(4):
            s = step(s, jnp.full((N, 1), 0.8 * np.sin(0.7 * k), jnp.float32))
        ref = wrapped["states"][4]
        np.testing.assert_allclose(np.asarray(s.obs), np.asarray(ref.obs), atol=1e-4)
        nested = jax.jit(jax.vmap(jax.vmap(env.step)))
        s0 = jax.vmap(jax.vmap(env.reset))(jax.random.split(jax.random.PRNGKey(1), 6).reshape(2, 3, 2))
        assert nested(s0, jnp.zeros((2, 3, 1), jnp.float32)).obs.shape == (2, 3, 7)
        with pytest.raises(ValueError, match=r"env\.sys\.body_mass has shape"):
            fn = functools.partial(randomize(), rng=jax.random.split(jax.random.PRNGKey(0), 2))
            sys_v, in_axes = fn(env.sys)
            unmapped = lambda sys: (sys_v, jax.tree.map(lambda _: None, in_axes))  # noqa: E731
            training.wrap(env, episode_length=5, randomization_fn=unmapped).reset(
                jax.random.split(jax.random.PRNGKey(0), 2))


_TWO_DEVICES = textwrap.dedent("""
    import jax
    assert jax.local_device_count() == 2, jax.devices()
    from brax.training.agents.ppo import train as ppo
    from kamino.envs import FourbarTrack, brax_compat, randomize
    from kamino.envs.configs import ppo_kwargs

    kw = ppo_kwargs("fourbar_track", num_timesteps=640, num_evals=1, num_envs=8, batch_size=8, num_minibatches=4,
                    unroll_length=5, num_updates_per_batch=1, episode_length=20, num_eval_envs=4, run_evals=False,
                    randomization_fn=randomize(effort_limit_scale=(0.8, 1.2), gravity_scale=(0.9, 1.1)))
    # brax's training state placed with the replacement for JAX releases without jax.device_put_replicated
    # (kamino/envs/brax_compat.py), under pmap
    jax.device_put_replicated = brax_compat.device_put_replicated
    make_policy, params, metrics = ppo.train(environment=FourbarTrack(reset_bank=16, backend="jax"), **kw)
    leaves = jax.tree.leaves(params)
    assert all(bool(jax.numpy.all(jax.numpy.isfinite(x))) for x in leaves)
    print("OK", "jax", jax.local_device_count(), flush=True)
""")


@pytest.mark.gpu  # 39 s of CI: a PPO compile on two devices; CI trains on two devices in test_rl_distributed.py
@pytest.mark.skipif(not jax_on_gpu(), reason="the gpu tier (JAX on the GPU)")
def test_ppo_pmaps_over_two_host_devices():
    """brax's PPO pmaps over the local devices: two forced host devices (the XLA flag must be set before jax is
    imported, hence a subprocess), 4 environments per device with domain randomization (each device's environments
    their own draws), on the JAX backend. The run places brax's training state with
    ``brax_compat.device_put_replicated``, what JAX 0.11 (the lent GPUs) needs. The Warp backend's run over two
    devices of a process (each device with its own stepper: kamino/warp_backend/jit.py; that it equals the unsharded
    step is test_sharding.py's) is tests/test_rl_distributed.py's, with randomization, two such processes."""
    env = dict(os.environ)
    env["XLA_FLAGS"] = f"{env.get('XLA_FLAGS', '')} --xla_force_host_platform_device_count=2".strip()
    env["JAX_PLATFORMS"] = "cpu"
    root = Path(__file__).resolve().parents[1]
    script = ALL_CORES + _TWO_DEVICES
    out = subprocess.run([sys.executable, "-c", script], env=env, cwd=root, capture_output=True, text=True,
                         timeout=600, check=False)
    assert out.returncode == 0, out.stdout[-2000:] + out.stderr[-4000:]
    assert "OK jax 2" in out.stdout, out.stdout[-2000:]


def _outer_loops(jaxpr) -> list[list[str]]:
    """For every loop of ``jaxpr`` that is not inside another loop (the environment's own loops; the solver's loops
    inside a step are not visited), the types of its zero-size operands (carry, closed-over arrays)."""
    from jax.extend import core as jcore

    found = []
    for eqn in jaxpr.eqns:
        if eqn.primitive.name in ("scan", "while"):
            found.append([str(v.aval) for v in eqn.invars if 0 in getattr(v.aval, "shape", (1,))])
            continue
        for param in eqn.params.values():
            for sub in param if isinstance(param, (list, tuple)) else [param]:
                if isinstance(sub, (jcore.ClosedJaxpr, jcore.Jaxpr)):
                    found += _outer_loops(getattr(sub, "jaxpr", sub))
    return found


# the JAX backend's case in the slow tier (README.md, under the test command): its trace takes 18-22 s on CI
@pytest.mark.parametrize("backend", [pytest.param("jax", marks=pytest.mark.slow), "warp"])
def test_substep_loop_holds_no_zero_size_array(backend):
    """XLA's GPU compiler (jax 0.11.2) crashes on a loop inside a per-device program (brax's pmap over several GPUs)
    that carries or closes over a zero-size array (benchmarks/results/multi_gpu_zero_size_crash_h200.txt). The
    four-bar has no couplings and no contacts, so its padded model and its State hold such arrays; the environment's
    substep scan must hold none of them (kamino.state.drop_empty), on either backend, randomized or not (on Warp a
    randomized env.sys adds its parameters, the four-bar's empty geom_friction among them, to the loop)."""
    with jax.enable_x64(False):
        env = make("fourbar_track", backend=backend)
        s = jax.eval_shape(env.reset, jax.random.PRNGKey(0))
        step = jax.make_jaxpr(env.step)(s, jnp.zeros(env.action_size, jnp.float32)).jaxpr
        reset = jax.make_jaxpr(env.reset)(jax.random.PRNGKey(0)).jaxpr
        env.sys = env.sys.replace(body_mass=env.sys.body_mass * 1.1, geom_friction=env.sys.geom_friction * 1.1)
        randomized = jax.make_jaxpr(env.step)(s, jnp.zeros(env.action_size, jnp.float32)).jaxpr
    loops = _outer_loops(step) + _outer_loops(reset) + _outer_loops(randomized)
    assert len(_outer_loops(step)) >= 1 and len(_outer_loops(randomized)) >= 1  # the substep scan is found
    assert all(empty == [] for empty in loops), loops


def test_feet_air_time_pays_a_landing_its_swing_time_past_the_target():
    """legged_gym's feet-air-time term, step by step at a 50 Hz policy: a foot in the air for 20 steps earns, as it
    lands, 20 x 0.02 s minus the 0.3 s target = 0.1 (the two-step contact filter drops its first step in the air
    and the landing step counts); a one-step lift (a graze) is filtered out and earns nothing, and its clock stays
    at zero."""
    from kamino.envs.joystick import feet_air_time

    dt, target = 0.02, 0.3
    pattern = [True] * 3 + [False] * 20 + [True] * 3  # foot 0 swings for 20 steps
    graze = [True] * 5 + [False] + [True] * 20  # foot 1 lifts for one step only
    air, was = jnp.zeros(2), jnp.ones(2, bool)
    paid = []
    for d0, d1 in zip(pattern, graze, strict=True):
        down = jnp.array([d0, d1])
        r, air = feet_air_time(air, was, down, dt, target)
        was = down
        paid.append(float(r))
    landing = pattern.index(True, 3)
    assert paid[landing] == pytest.approx(20 * dt - target, abs=1e-6)
    assert all(p == 0.0 for i, p in enumerate(paid) if i != landing)
    assert float(air[1]) == 0.0


def test_swing_heights_alternate_the_feet():
    """The gait clock's targets for two feet: foot 0 swings in the first half of the cycle (peak at phase 0.25),
    foot 1 in the second (peak at 0.75); a standing foot's target is 0; one cycle later the same."""
    from kamino.envs.joystick import swing_heights

    h = 0.05
    np.testing.assert_allclose(np.asarray(swing_heights(jnp.float32(0.25), 2, h)), [h, 0.0], atol=1e-7)
    np.testing.assert_allclose(np.asarray(swing_heights(jnp.float32(0.75), 2, h)), [0.0, h], atol=1e-7)
    np.testing.assert_allclose(np.asarray(swing_heights(jnp.float32(1.0 / 12.0), 2, h)), [0.5 * h, 0.0], atol=1e-7)
    np.testing.assert_allclose(np.asarray(swing_heights(jnp.float32(1.25), 2, h)), [h, 0.0], atol=1e-6)
    phases = jnp.linspace(0.0, 1.0, 101)
    both = np.asarray(jax.vmap(lambda p: swing_heights(p, 2, h))(phases))
    assert np.all(both >= 0.0) and np.all(np.min(both, axis=1) < 1e-7)  # never both feet in the air


def test_gait_clock_is_observed_and_its_reward_follows_the_swing(legs_own_gains):
    """``gait_frequency``: two more observations, ``(sin, cos)(2 pi phase)``, the phase starting at 0 in every
    episode (restored at auto-reset) and advancing by ``f dt`` per policy step. At the nominal pose (both feet
    standing, lift 0 to float32 rounding) ``feet_phase`` is ``exp(-sum target^2 / sigma)``: 1 for a zero command,
    and ``exp(-0.05^2 / 0.0025) = exp(-1)`` when the clock reaches a swing's peak (target 0.05 m on one foot) under a
    moving command. Without the clock its weight is refused."""
    from kamino.envs.joystick import Joystick

    model = legs_own_gains.model  # its FK programs are compiled already
    env = Joystick(model, min_height=0.45, reset_bank=8, reset_noise=1e-9, backend="warp", gait_frequency=1.25,
                   reward_weights={"feet_phase": 1.0})
    assert env.observation_size == legs_own_gains.observation_size + 2
    s = jax.jit(env.reset)(jax.random.PRNGKey(0))
    assert s.obs.shape == (env.observation_size,)
    np.testing.assert_array_equal(np.asarray(s.obs[-2:]), [0.0, 1.0])  # no noise on the clock
    assert float(s.info["phase"]) == 0.0 and float(s.info["reset_memory"]["phase"]) == 0.0
    assert float(env._phase_after(dict(s.info, phase=jnp.float32(0.99)))) == pytest.approx(0.015, abs=1e-6)
    ps = env.full_state(s.pipeline_state)
    peak = dict(s.info, phase=jnp.float32(0.25 - 1.25 * env.dt), command=jnp.array([0.4, 0.0, 0.0], jnp.float32))
    assert float(env._feet_phase(ps, peak)) == pytest.approx(np.exp(-1.0), rel=1e-4)
    assert float(env._feet_phase(ps, dict(peak, command=jnp.zeros(3, jnp.float32)))) == pytest.approx(1.0, abs=1e-4)
    with pytest.raises(ValueError, match="gait_frequency"):
        Joystick(model, min_height=0.45, reset_bank=8, backend="warp", reward_weights={"feet_phase": 1.0})


def test_feet_width_rewards_the_stance_in_the_base_heading(legs_own_gains):
    """``feet_width`` is ``exp(-(width - stance_width)^2 / stance_sigma)`` with ``width`` the feet's distance along
    the base's levelled lateral axis. dr_legs stands with its feet 0.2 m apart (CoMs at y = +-0.1 m): the default
    target (the nominal stance) scores 1, a target of 0.15 m scores ``exp(-0.05^2 / 0.0025) = exp(-1)``, on every
    heading the reset draws (the tolerance is float32 rounding of positions of order 1 m). Sliding the right foot
    5 cm outward along the base's lateral axis widens the stance to 0.25 m: ``exp(-1)`` against the default target.
    A robot without exactly two feet is refused."""
    from kamino.envs.joystick import Joystick

    model = legs_own_gains.model
    nominal = Joystick(model, min_height=0.45, reset_bank=8, reset_noise=1e-9, backend="warp",
                       reward_weights={"feet_width": 1.0})
    narrow = Joystick(model, min_height=0.45, reset_bank=8, reset_noise=1e-9, backend="warp",
                      reward_weights={"feet_width": 1.0}, stance_width=0.15)
    assert nominal._stance_width == pytest.approx(0.2, abs=1e-6)
    right = int(nominal._feet[1])
    for seed in range(3):
        s = jax.jit(nominal.reset)(jax.random.PRNGKey(seed))
        ps = nominal.full_state(s.pipeline_state)
        assert float(nominal._feet_width(ps)) == pytest.approx(1.0, abs=1e-4)
        assert float(narrow._feet_width(ps)) == pytest.approx(np.exp(-1.0), rel=1e-3)
        R = np.asarray(quat_to_matrix(ps.body_q[nominal._base, 3:]))
        left = np.array([R[0, 1], R[1, 1], 0.0]) / np.hypot(R[0, 1], R[1, 1])
        wide = ps.replace(body_q=ps.body_q.at[right, :3].add(jnp.asarray(-0.05 * left, ps.body_q.dtype)))
        assert float(nominal._feet_width(wide)) == pytest.approx(np.exp(-1.0), rel=1e-3)
    with pytest.raises(ValueError, match="exactly two feet"):
        Joystick(model, min_height=0.45, reset_bank=8, backend="warp", feet=("l_foot",),
                 reward_weights={"feet_width": 1.0})


def test_joystick_warm_start_lets_an_internal_loop_load_decay(legs_own_gains):
    """dr_legs' planar four-bars are overconstrained: some joint reactions ``lambda`` (the left null space of the joint
    Jacobian, ``J^T lambda = 0``) move no body, so PADMM's iterations never correct them and only the warm start
    carries them from substep to substep; grown over an episode, they stalled PADMM and threw the robot. The null
    directions come from the joint Jacobian of the reset pose in float64, a structural rank
    cut: singular values below 1e-12 of the largest, the eight exact redundancies (measured at most 3e-16 of it; the
    next one, genuine, 4e-9). A load of 1e5 N put along each of them at reset must, after 10 policy steps (50
    substeps) at a zero action, be at most 0.99^50 = 0.61 of itself (the walking tasks' ``WARMSTART_SCALE`` alone);
    the warm-start filter (docs/conventions.md, "Warm start") removes it on the first substep: at most 1e-3 of it
    (measured 0.5 N of 1e5; before the filter such loads grew to 0.36-3.66 times themselves). The robot must move as
    without the load: base position within 1 mm. In float32 ``J^T lambda`` of a 1e5 N self-equilibrated load is zero
    only to rounding, about 1e5 N x 1.2e-7 x a few terms = 4e-2 N on a body of 0.05 kg for the 4 ms substep before
    the filter takes the load out: 3e-3 m/s, 6e-4 m over the remaining 0.2 s; the runs end 2e-5 to 5e-4 m from the
    unloaded robot depending on how XLA orders the quaternion products. A load that grows instead throws the robot
    by metres."""
    from kamino.envs.joystick import WARMSTART_SCALE
    from kamino.jax_ref.jacobians import constraint_jacobian, joint_frames
    from kamino.jax_ref.types import layout_of
    from kamino.state import drop_empty

    env = legs_own_gains
    assert env.solver_config.warmstart_scale == WARMSTART_SCALE == 0.99
    with jax.enable_x64(False):
        s0 = jax.jit(env.reset)(jax.random.PRNGKey(3))
        ps = env.full_state(s0.pipeline_state)
    with jax.enable_x64(True):
        pm = jax.tree.map(lambda x: x[0], layout_of(env.model, jnp.float64).padded)  # the world's padded model
        q = jnp.asarray(np.asarray(ps.body_q, np.float64))
        J = np.asarray(constraint_jacobian(pm, joint_frames(pm, q), env.model.num_bodies))
    U, S, _ = np.linalg.svd(J)
    S = np.concatenate([S, np.zeros(len(U) - len(S))])
    null = U[:, S < 1e-12 * S[0]]
    assert null.shape[1] == 8  # the planar four-bars' redundant rows
    assert np.all(S[S < 1e-12 * S[0]] < 1e-14 * S[0]) and np.all(S[S >= 1e-12 * S[0]] > 1e-10 * S[0])  # the gap
    with jax.enable_x64(False):
        loaded = [s0.replace(pipeline_state=drop_empty(ps.replace(
            constraint_force=ps.constraint_force + jnp.asarray(1e5 * n, ps.constraint_force.dtype)))) for n in null.T]
        batch = jax.tree.map(lambda *x: jnp.stack(x), s0, *loaded)  # the unloaded reference first
        step = jax.jit(jax.vmap(env.step))
        zero = jnp.zeros((batch.obs.shape[0], env.action_size), jnp.float32)
        for _ in range(10):
            batch = step(batch, zero)
        f = np.asarray(jax.vmap(env.full_state)(batch.pipeline_state).constraint_force, np.float64)
        base = np.asarray(jax.vmap(env.full_state)(batch.pipeline_state).body_q[:, env._base, :3])
    left = np.einsum("ri,ir->i", null, f[1:] - f[0])
    assert np.all(np.abs(left) <= WARMSTART_SCALE ** 50 * 1e5), left
    assert np.all(np.abs(left) <= 1e-3 * 1e5), left  # the filter's doing
    np.testing.assert_allclose(base[1:], np.broadcast_to(base[0], base[1:].shape), atol=1e-3)  # float32 rounding
