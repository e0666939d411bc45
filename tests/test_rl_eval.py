"""``kamino eval`` (kamino.envs.evaluate), the walking evaluation: on a policy whose action is exactly zero, and on
the walking policy that ships with kamino (``kamino.envs.load_policy("dr_legs_walk")``)."""

import json
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

pytest.importorskip("brax")

from kamino.envs import evaluate as rl_eval
from kamino.envs import load_policy, shipped_policies

ROOT = Path(__file__).resolve().parents[1]


def evaluate(run: Path | str, tmp_path: Path, *, episodes: int, seconds: float) -> dict:
    """``kamino eval RUN`` on the Warp backend (here Warp's CPU device) with a reset bank of 8, as a user runs it from
    the command line; its exit status must be 0. Returns the JSON report."""
    out = tmp_path / "eval.json"
    rc = rl_eval.main([str(run), "--backend", "warp", "--episodes", str(episodes), "--seconds", str(seconds),
                       "--env", "reset_bank=8", "--out", str(out)])
    assert rc == 0
    return json.loads(out.read_text())


@pytest.fixture(scope="module")
def zero_policy_checkpoint(tmp_path_factory):
    """A brax PPO checkpoint of dr_legs_joystick's networks (as ``kamino train`` saves them) whose policy's last
    layer is zero: the deterministic action is tanh(0) = 0 in every state, the PD targets stay at the reference
    pose."""
    from brax.training.acme import running_statistics, specs
    from brax.training.agents.ppo import checkpoint as ppo_checkpoint

    from kamino.envs.configs import ppo_kwargs

    obs_size, act_size = 48, 12
    factory = ppo_kwargs("dr_legs_joystick")["network_factory"]
    net = factory(obs_size, act_size, preprocess_observations_fn=running_statistics.normalize)
    policy = net.policy_network.init(jax.random.PRNGKey(0))
    last = sorted(policy["params"])[-1]
    policy["params"][last] = jax.tree.map(jnp.zeros_like, policy["params"][last])
    value = net.value_network.init(jax.random.PRNGKey(1))
    normalizer = running_statistics.init_state(specs.Array((obs_size,), jnp.dtype("float32")))
    config = ppo_checkpoint.network_config(obs_size, act_size, True, factory)
    folder = tmp_path_factory.mktemp("run") / "checkpoints"
    ppo_checkpoint.save(folder, 1000, (normalizer, policy, value), config)
    # the run's environment (its env.json, read by kamino eval): the defaults, whose 48 observations the
    # networks take (the task's config adds a gait clock: 50)
    (folder.parent / "env.json").write_text("{}\n")
    return folder.parent


def test_a_standing_policy_tracks_nothing_and_does_not_fall(zero_policy_checkpoint, tmp_path):
    """A zero action holds dr_legs at its reference pose (tests/test_envs.py: the pelvis moves about 1 cm while the
    feet settle), so the base does not follow the forward command: the tracking error is the command itself, here
    uniform in 0.3-0.5 m/s, up to the settling motion (a few cm/s; the bound 0.05 m/s). No episode ends: the fall
    fraction is 0, and the evaluation fails the walking bar (error <= 0.1 m/s)."""
    r = evaluate(zero_policy_checkpoint, tmp_path, episodes=4, seconds=1)
    assert r["policy_steps"] == 50 and r["episodes"] == 4
    assert r["fall_fraction"] == 0.0
    assert 0.3 <= r["command_mean"] <= 0.5
    assert abs(r["forward_speed_mean"]) < 0.05
    np.testing.assert_allclose(r["tracking_error_mean"], r["command_mean"], atol=0.05)
    # standing still, the mean velocity misses the command by the command itself, and the base hardly fluctuates
    np.testing.assert_allclose(r["mean_velocity_error"], r["command_mean"], atol=0.05)
    assert r["mean_velocity_error"] <= r["tracking_error_mean"] + 1e-6  # |mean of a vector| <= mean of its norms
    assert 0.0 <= r["fluctuation_std_x"] < 0.05 and 0.0 <= r["fluctuation_std_y"] < 0.05
    assert r["passed"] is False
    assert r["checkpoint"].endswith("checkpoints/000000001000")  # the run folder's newest (only) checkpoint


def test_an_exported_policy_reads_back_without_pickle(zero_policy_checkpoint, tmp_path):
    """``export_policy`` writes a checkpoint's normalizer and policy network as plain arrays; read back, they give
    the same actions bit for bit, and ``params.npz`` opens with ``allow_pickle=False``."""
    from kamino.envs.policy import export_policy, load_checkpoint, read_policy

    policy = load_checkpoint(zero_policy_checkpoint)
    assert policy.task == "dr_legs_joystick" and policy.step == 1000
    back = read_policy(export_policy(policy, tmp_path / "zero", description="zero action"))
    obs = np.random.default_rng(1).normal(size=(4, 48)).astype(np.float32)
    np.testing.assert_array_equal(np.asarray(back.act(obs)), np.asarray(policy.act(obs)))
    assert back.env == policy.env == {} and back.config == policy.config
    with np.load(tmp_path / "zero" / "params.npz", allow_pickle=False) as z:
        assert all(z[k].dtype != object for k in z.files)


def test_no_checkpoint_is_a_clear_error(tmp_path):
    """An empty folder, and one whose only step folder was left half-written (no commit marker), hold no
    checkpoint; an unknown name is neither a shipped policy nor a path."""
    from kamino.envs.policy import newest_checkpoint

    with pytest.raises(FileNotFoundError, match="no complete brax PPO checkpoint"):
        newest_checkpoint(tmp_path)
    (tmp_path / "checkpoints" / "000000001000").mkdir(parents=True)
    with pytest.raises(FileNotFoundError, match="no complete brax PPO checkpoint"):
        newest_checkpoint(tmp_path)
    with pytest.raises(FileNotFoundError, match="neither a shipped policy"):
        rl_eval.resolve(tmp_path / "nosuch")


def test_summary_separates_speed_deficit_from_sway():
    """``summarize`` on synthetic velocities with known answers: an episode whose forward speed averages 0.05 m/s
    below its command and sways sideways as ``0.1 sin`` over whole periods has a mean-velocity error of exactly 0.05
    m/s and a lateral fluctuation of ``0.1 / sqrt(2)``; a fall cuts the steps counted, and the steps after it do not
    count."""
    T = 200
    phase = 2 * np.pi * np.arange(T) / 50  # four whole periods
    lin = np.zeros((2, T, 3))
    lin[0, :, 0] = 0.35
    lin[0, :, 1] = 0.1 * np.sin(phase)
    lin[1, :100, 0] = 0.4  # tracks exactly until it falls at step 100, then garbage that must not count
    lin[1, 100:, 0] = 50.0
    counted = np.ones((2, T), bool)
    counted[1, 100:] = False
    r = rl_eval.summarize(np.array([0.4, 0.4]), lin, counted, np.array([False, True]))
    np.testing.assert_allclose(r["mean_velocity_error"], (0.05 + 0.0) / 2, atol=1e-12)
    np.testing.assert_allclose(r["fluctuation_std_y"], (0.1 / np.sqrt(2) + 0.0) / 2, rtol=1e-12)
    np.testing.assert_allclose(r["fluctuation_std_x"], 0.0, atol=1e-12)
    np.testing.assert_allclose(r["forward_speed_mean"], (0.35 + 0.4) / 2, rtol=1e-12)
    err0 = np.mean(np.hypot(0.05, 0.1 * np.sin(phase)))
    np.testing.assert_allclose(r["tracking_error_mean"], err0 / 2, rtol=1e-12)
    assert r["fall_fraction"] == 0.5


#: observations (standard normal, seed 0) and the original orbax checkpoint's deterministic actions for them, read
#: with Brax's own loader and the task's networks (the policy trained for 55,377,920 env steps)
OBS = np.random.default_rng(0).normal(size=(3, 50)).astype(np.float32)
ACTIONS = np.array([
    [-0.4693044, 0.9265332, -0.8856585, -0.9485745, 0.9978097, 0.4108328, 0.5994998, -0.9513769, -0.571801, 0.632248,
     -0.4054452, -0.9998206],
    [0.0482927, 0.169555, -0.6219017, -0.9916083, -0.764389, -0.2027056, 0.8249206, -0.1488281, 0.4982914, 0.7698416,
     -0.4092913, 0.9987731],
    [0.0493677, 0.1809658, 0.3039164, -0.9521802, -0.2257898, -0.9504747, 0.5311522, -0.741146, 0.1659918,
     -0.8406311, -0.6782017, -0.3637212]], np.float32)


@pytest.mark.default_xla  # against actions recorded at XLA's default optimisation level (tests/conftest.py)
def test_the_shipped_policy_acts_as_its_checkpoint():
    """The shipped arrays (``params.npz``, read without pickle) give the checkpoint's actions: the network is the
    same float32 MLP, so they agree to float32 rounding (2e-7 relative; the actions are printed to 1e-7), and the
    policy carries its task and training keywords."""
    policy = load_policy("dr_legs_walk")
    assert policy.task == "dr_legs_joystick" and policy.observation_size == 50 and policy.action_size == 12
    assert policy.env["gait_frequency"] == 2.5 and policy.env["stance_width"] == 0.13
    np.testing.assert_allclose(np.asarray(policy.act(OBS)), ACTIONS, rtol=0, atol=2e-7)


def test_an_unknown_policy_name_lists_the_shipped_ones():
    assert "dr_legs_walk" in shipped_policies()
    with pytest.raises(ValueError, match="dr_legs_walk"):
        load_policy("nosuch")


def test_the_shipped_dr_legs_policy_walks(tmp_path):
    """The shipped policy, evaluated as a user runs it (``kamino eval dr_legs_walk``: the environment of its
    training keywords, the Warp backend on the CPU device), walks: 4 episodes of 4 s at forward commands in 0.3-0.5
    m/s. None falls, and the mean tracking error stays under the walking bar of 0.1 m/s. On the GPU the same policy
    scored 0.070 m/s (p90 0.078) over 256 episodes of 10 s, and Warp's CPU device gave the same 0.070 on those
    episodes. Here it measured 0.068 m/s, with a forward speed of 0.336 m/s at a mean command of 0.349. The short
    episodes weigh the start from rest more, and the bound's margin allows for that. A policy that no longer loads,
    an environment that drifted from the one it was trained in (observation layout, gains, gait clock), or a
    simulator change that breaks the gait fails here."""
    r = evaluate("dr_legs_walk", tmp_path, episodes=4, seconds=4)
    assert r["episodes"] == 4 and r["policy_steps"] == 200
    assert r["fall_fraction"] == 0.0
    assert r["forward_speed_mean"] > 0.25
    assert r["tracking_error_mean"] < 0.1
