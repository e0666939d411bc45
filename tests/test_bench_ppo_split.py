"""``kamino.bench.ppo_split`` on the CPU at tiny PPO sizes: the split of brax's PPO epoch into collection and
learning, checked against an environment of known cost, and the command's record end to end."""

import json

import pytest

pytest.importorskip("brax")

import jax
import jax.numpy as jnp

from kamino.bench import ppo_split

#: fourbar_track's networks at 8 environments: 2 unrolls of 5 env steps per training step, 2 minibatches
TINY = {"batch_size": 8, "num_minibatches": 2, "unroll_length": 5}


def _cuda() -> bool:
    """Whether Warp sees a CUDA device."""
    import warp as wp

    return wp.is_cuda_available()


class MatvecEnv(ppo_split.NullEnv):
    """The null environment plus ``matvecs`` chained 256 x 256 matrix-vector products in every step: an environment
    whose step costs a fixed amount of arithmetic, on which the learner's cost does not depend."""

    def __init__(self, observation_size: int, action_size: int, matvecs: int):
        super().__init__(observation_size, action_size)
        self.matvecs = matvecs

    def step(self, state, action):
        s = super().step(state, action)
        w = 0.5 * jnp.eye(256) + 0.01
        x = jnp.resize(s.obs, (256,))
        x = jax.lax.fori_loop(0, self.matvecs, lambda i, x: jnp.tanh(w @ x), x)
        return s.replace(obs=s.obs + 1e-3 * x[: s.obs.shape[0]])


def test_null_env_steps_follow_the_actions():
    """The null environment's observation moves halfway to the tiled, clipped action each step, so that the policy's
    actions feed its next observation; it never ends an episode itself."""
    env = ppo_split.NullEnv(5, 2)
    s = env.reset(jax.random.PRNGKey(0))
    assert s.obs.shape == (5,) and float(s.obs[0]) == -1.0 and float(s.obs[-1]) == 1.0
    s = env.step(s, jnp.array([3.0, -0.5]))
    expected = 0.5 * (jnp.linspace(-1.0, 1.0, 5) + jnp.array([1.0, -0.5, 1.0, -0.5, 1.0]))
    assert jnp.allclose(s.obs, expected) and float(s.done) == 0.0
    assert float(s.reward) == pytest.approx(-(1.0 + 0.25) / 2)  # the clipped action's mean square


def test_bad_sizes_and_options_are_named():
    with pytest.raises(ValueError, match="trajectories"):
        ppo_split.training_config("fourbar_track", 3, TINY)  # 16 trajectories are not whole unrolls of 3 envs
    with pytest.raises(SystemExit):
        ppo_split.parse_args(["--set", "num_evals=3"])
    with pytest.raises(SystemExit):
        ppo_split.parse_args(["--epochs", "0"])
    with pytest.raises(SystemExit):
        ppo_split.parse_args(["--solver", "nosuch=1"])


def test_split_predicts_the_epoch_of_an_environment_of_known_cost():
    """PPO on the null environment and on :class:`MatvecEnv` (40 matrix-vector products per step), same sizes.
    The learner sees neither environment's arithmetic, so the matvec environment's PPO epoch is its collection alone
    plus the null environment's learning. The epochs compared are the fastest of 9 of each (other work on the
    shared 2-core CPU only adds time; the medians swing by 2x under load). The prediction came within 8 % in six of
    seven trials on the loaded 2-core CPU and within 16 % in the seventh (load 3.4); the bound is 25 %. The
    collection is about 80 % of the matvec environment's epoch here, so a collection loop that ran one unroll per
    training step instead of brax's two would miss by 40 %. The matvec steps cost the collection alone: the matvec
    environment's fastest epoch is 3.5-4.6x the null environment's (bound 2x), and its collection's share is the
    larger."""
    kwargs = ppo_split.training_config("fourbar_track", 8, TINY)
    null = ppo_split.measure(ppo_split.NullEnv(7, 1), kwargs, 4, 9)
    costly = ppo_split.measure(MatvecEnv(7, 1, 40), kwargs, 4, 9)
    for r in (null, costly):
        assert r["collect_share"] + r["learn_share"] == pytest.approx(1.0)
        assert len(r["train"]["epochs_s"]) == len(r["collect"]["epochs_s"]) == 9
        assert r["train"]["env_steps_per_s"] == pytest.approx(4 * 80 / r["train"]["epoch_s"])
    null_learn = null["train"]["epoch_min_s"] - null["collect"]["epoch_min_s"]
    predicted = costly["collect"]["epoch_min_s"] + null_learn
    assert predicted == pytest.approx(costly["train"]["epoch_min_s"], rel=0.25)
    assert costly["train"]["epoch_min_s"] > 2 * null["train"]["epoch_min_s"]
    assert costly["collect_share"] > null["collect_share"]


# the gpu tier, where the command is run: about a minute on the 2-core CPU (the four-bar's Warp step compiles in PPO
# and in the collection); the split itself is checked on the CPU above
@pytest.mark.gpu
@pytest.mark.skipif(not _cuda(), reason="the gpu tier: needs a CUDA device for Warp")
def test_command_writes_the_record_of_both_environments(tmp_path):
    """``kamino bench ppo_split fourbar_track`` at tiny sizes appends one record with both environments' PPO env
    steps/s, the task's split, and the configuration and host it ran with; the four-bar's physics makes its PPO
    slower than the null environment's."""
    pytest.importorskip("warp")
    out = tmp_path / "split.jsonl"
    argv = ["fourbar_track", "--num-envs", "8", *(f"--set={k}={v}" for k, v in TINY.items()),
            "--steps-per-epoch", "2", "--epochs", "2", "--out", str(out)]
    assert ppo_split.main(argv) == 0
    (rec,) = (json.loads(line) for line in out.read_text().splitlines())
    assert rec["task"] == "fourbar_track" and rec["ppo"]["num_envs"] == 8 and rec["ppo"]["batch_size"] == 8
    assert rec["network"]["policy_hidden_layer_sizes"] == [32, 32]
    assert rec["observation_size"] == 7 and rec["action_size"] == 1
    assert rec["env_steps_per_training_step"] == 80 and rec["timed_env_steps"] == 2 * 2 * 80
    assert rec["ppo_env_steps_per_s"] == rec["task_run"]["ppo_env_steps_per_s"] > 0
    assert rec["ceiling_env_steps_per_s"] == rec["null"]["ppo_env_steps_per_s"] > rec["ppo_env_steps_per_s"]
    assert rec["collect_share"] + rec["learn_share"] == pytest.approx(1.0)
    assert {"jax", "warp", "python", "brax", "command", "device"} <= set(rec)
