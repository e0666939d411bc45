"""``olaf_show``: Olaf's show targets come from its loop mechanisms' kinematics, the show reward scores a reached
target fully, and the show test's summary counts what it says."""


import jax
import jax.numpy as jnp
import numpy as np
import pytest
import warp as wp

pytest.importorskip("brax")

from kamino.envs import make
from kamino.envs.olaf_show import SHOW_JOINTS, summarize_show


@pytest.fixture(scope="module")
def env():
    return make("olaf_show", backend="warp", reset_bank=2)


def test_show_ranges_follow_the_mechanisms(env):
    """The head joints are serial, so their target range is the driver's range times ``show_fraction`` (0.9 of the
    0.6 rad half-range) to FK's tolerance; each four-bar output spans a range of its own (the crank-to-output map,
    not the identity), on both sides of its rest angle 0, within its hinge's limits."""
    lo, hi = env.show_range
    names = [j for j, _ in SHOW_JOINTS]
    for j in ("neck_yaw", "neck_pitch"):
        i = names.index(j)
        np.testing.assert_allclose([lo[i], hi[i]], [-0.54, 0.54], atol=1e-5)
    loops = [i for i, j in enumerate(names) if j.endswith("_pivot")]
    assert len(loops) == 5
    assert np.all(lo[loops] < -0.2) and np.all(hi[loops] > 0.2)
    assert not np.allclose(hi[loops] - lo[loops], 1.08, atol=0.02)  # not the crank's own range: a real map
    # left and right mechanisms mirror each other
    np.testing.assert_allclose(lo[1], lo[2], atol=1e-5)
    np.testing.assert_allclose(hi[3], hi[4], atol=1e-5)


def test_the_show_reward_is_full_at_the_target_and_targets_are_observed(env):
    """With the targets set to the joints' present angles the ``show`` term equals its weight (every per-joint kernel
    at 1); targets 0.1 rad off on every joint score ``exp(-1)`` of it (variance 0.01 rad^2). The observation ends with
    the targets, unnoised."""
    state = jax.jit(env.reset)(jax.random.PRNGKey(1))
    assert env.observation_size == 12 + 3 * env.action_size + len(SHOW_JOINTS)
    np.testing.assert_array_equal(state.obs[-len(SHOW_JOINTS):], state.info["show"])
    lo, hi = env.show_range
    assert np.all((state.info["show"] >= lo - 1e-6) & (state.info["show"] <= hi + 1e-6))
    ps = env.full_state(state.pipeline_state)
    here = env.show_angles(ps)
    action = jnp.zeros(env.action_size)
    for offset, expected in ((0.0, 1.0), (0.1, np.exp(-1.0))):
        info = dict(state.info, show=here + offset)
        _, terms = env._reward(ps, ps, action, info)
        np.testing.assert_allclose(terms["show"], 2.0 * expected, rtol=1e-5)


def test_the_show_summary_counts_settled_steps_of_upright_episodes():
    """``summarize_show`` averages the errors of the counted steps only, per episode then over episodes."""
    err = np.zeros((2, 4, len(SHOW_JOINTS)))
    err[0, :2] = 9.0          # not counted (a target's move)
    err[0, 2:] = 0.1
    err[1, 2:] = 0.3
    counted = np.array([[False, False, True, True], [False, False, True, True]])
    r = summarize_show(err, counted, np.array([False, True]))
    assert r["show_error_mean"] == pytest.approx(0.2) and r["fall_fraction"] == 0.5
    assert r["show_error_per_joint"]["jaw_pivot"] == pytest.approx(0.2)


def test_olaf_show_refuses_bad_settings():
    with pytest.raises(ValueError, match="show_fraction"):
        make("olaf_show", backend="jax", show_fraction=1.5)
    with pytest.raises(ValueError, match="show_sigma"):
        make("olaf_show", backend="jax", show_sigma=0.0)


@pytest.mark.gpu
@pytest.mark.skipif(not wp.is_cuda_available(), reason="needs a CUDA device for Warp")
def test_the_show_test_scores_a_still_policy_and_train_accepts_it(env):
    """In the gpu tier (its rollout compiles and steps Olaf for 8 s on CI's CPU). The task's test (``task_test``, what
    ``kamino eval`` and ``kamino train --walk-test`` run) on a policy of zero actions (a zero network: the PD
    targets stay at the actuators' centres): Olaf stands, so no episode falls, and the show error is the targets'
    mean distance from the outputs' rest angles, uniform draws over ranges of about 0.8-1.1 rad, so well above
    0.1 rad. ``kamino train --walk-test`` accepts the task."""
    import jax
    from brax.training.acme import running_statistics
    from brax.training.agents.ppo import checkpoint as ppo_checkpoint

    from kamino.envs import train as rl_train
    from kamino.envs.configs import ppo_kwargs
    from kamino.envs.evaluate import task_test
    from kamino.envs.policy import Policy, make_networks

    factory = ppo_kwargs("olaf_show")["network_factory"]
    factory.keywords.update(policy_hidden_layer_sizes=(8,), value_hidden_layer_sizes=(8,))
    config = ppo_checkpoint.network_config(env.observation_size, env.action_size, True, factory)
    nets = make_networks(config)
    params = nets.policy_network.init(jax.random.PRNGKey(0))
    params = jax.tree.map(lambda x: x * 0.0, params)
    normalizer = running_statistics.init_state(jax.ShapeDtypeStruct((env.observation_size,), jnp.float32))
    policy = Policy(task="olaf_show", env={"reset_bank": 2}, config=config, params=(normalizer, params),
                    source="a zero network")
    summary = task_test(env, policy.make_policy, episodes=2, seconds=2.0, seed=0)(policy.params)
    assert summary["fall_fraction"] == 0.0
    assert summary["show_error_mean"] > 0.1
    assert rl_train.parse_args(["olaf_show", "--walk-test", "4"]).walk_test == 4
