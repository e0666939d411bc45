"""ONNX export of a trained policy (kamino/envs/onnx_export.py, examples/onnx_policy.py): the model's action agrees
with the JAX policy's deterministic action, observation normalization included; the standalone example runs it
without kamino or JAX; a wrong observation size is an error that names the sizes."""

from __future__ import annotations

import dataclasses
import importlib.util
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("brax")
pytest.importorskip("onnx")
pytest.importorskip("onnxruntime")
import jax

from kamino.envs import onnx_export
from kamino.envs.policy import Policy, load_policy, make_networks

ROOT = Path(__file__).resolve().parents[1]
EXAMPLE = ROOT / "examples" / "onnx_policy.py"
#: float32 agreement of onnxruntime and JAX on the same network: rounding of the dot products and of sigmoid/tanh
#: (kamino.envs.onnx_export.check_onnx derives its size, about 1e-6 measured for the shipped policy)
TOL = onnx_export.TOLERANCE


def _jax_actions(policy: Policy, obs: np.ndarray) -> np.ndarray:
    with jax.enable_x64(False):
        return np.asarray(jax.jit(lambda o: policy.act(o))(obs))


@pytest.fixture(scope="module")
def shipped(tmp_path_factory):
    """The shipped dr_legs policy, its model, 1000 observations and the JAX actions for them."""
    policy = load_policy("dr_legs_walk")
    path = onnx_export.export_onnx(policy, tmp_path_factory.mktemp("onnx") / "dr_legs_walk.onnx")
    obs = onnx_export.sample_observations(policy, 1000, seed=0)
    return policy, path, obs, _jax_actions(policy, obs)


def test_the_model_matches_the_jax_policy_on_1000_observations(shipped):
    """The ONNX action is the JAX deterministic action to 1e-5 on 1000 observations around the training data, and
    the comparison is sharp: the same network exported without its normalizer misses by far more."""
    policy, path, obs, reference = shipped
    actions = onnx_export.onnx_actions(path, obs)
    assert actions.shape == (1000, policy.action_size) and actions.dtype == np.float32
    diff = np.abs(actions - reference).max()
    assert diff <= TOL, diff
    assert np.abs(reference).max() > 0.9  # the observations reach the actions' range, not only its middle
    bare = dataclasses.replace(policy, config={**policy.config, "normalize_observations": False})
    bare_path = onnx_export.export_onnx(bare, path.with_name("bare.onnx"))
    assert np.abs(onnx_export.onnx_actions(bare_path, obs) - reference).max() > 0.1


def test_the_model_carries_what_it_was_trained_on(shipped):
    import onnx

    policy, path, _, _ = shipped
    model = onnx.load(path)
    meta = {p.key: p.value for p in model.metadata_props}
    assert meta["task"] == "dr_legs_joystick" and meta["observation_size"] == "50" and meta["action_size"] == "12"
    assert meta["activation"] == "silu" and meta["normalized_observations"] == "true"
    assert meta["step"] == str(policy.step)
    assert model.opset_import[0].version == onnx_export.OPSET
    assert [i.name for i in model.graph.input] == ["observation"] and [o.name for o in model.graph.output] == ["action"]


def test_the_example_runs_without_kamino_or_jax(shipped, tmp_path):
    """``python -X importtime examples/onnx_policy.py`` imports no kamino, JAX, Brax or Flax module, and writes the
    actions onnxruntime gives in this process."""
    _, path, obs, reference = shipped
    np.save(tmp_path / "obs.npy", obs[:64])
    out = tmp_path / "actions.npy"
    run = subprocess.run([sys.executable, "-X", "importtime", str(EXAMPLE), str(path), "--obs",
                          str(tmp_path / "obs.npy"), "--out", str(out)], capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, run.stderr[-2000:]
    imported = {line.rsplit("|", 1)[-1].strip().split(".")[0] for line in run.stderr.splitlines()
                if line.startswith("import time:")}
    assert "onnxruntime" in imported and "numpy" in imported  # the import log is read right
    forbidden = {"kamino", "jax", "jaxlib", "brax", "flax"}
    assert not imported & forbidden, f"the example imports {sorted(imported & forbidden)}"
    assert "task dr_legs_joystick, observation 50, action 12" in run.stdout
    actions = np.load(out)
    assert np.array_equal(actions, onnx_export.onnx_actions(path, obs[:64]))
    assert np.abs(actions - reference[:64]).max() <= TOL


def _example():
    spec = importlib.util.spec_from_file_location("onnx_policy_example", EXAMPLE)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_a_wrong_observation_size_is_named(shipped, tmp_path):
    policy, path, obs, reference = shipped
    example = _example().OnnxPolicy(str(path))
    assert np.array_equal(example(obs[0]), example(obs[:1])[0])  # one observation or a batch
    assert np.abs(example(obs[0]) - reference[0]).max() <= TOL
    with pytest.raises(ValueError, match=r"shape \(49,\); the policy of task 'dr_legs_joystick' expects 50 values"):
        example(obs[0, :49])
    with pytest.raises(ValueError, match=r"shape \(3, 51\).*takes \[batch, 50\]"):
        onnx_export.onnx_actions(path, np.zeros((3, 51), np.float32))
    np.save(tmp_path / "short.npy", obs[:2, :49])
    run = subprocess.run([sys.executable, str(EXAMPLE), str(path), "--obs", str(tmp_path / "short.npy")],
                         capture_output=True, text=True, timeout=120)
    assert run.returncode == 2 and "expects 50 values" in run.stderr, run.stderr[-2000:]
    broken = dataclasses.replace(policy, config={**policy.config, "observation_size": 49})
    with pytest.raises(ValueError, match=r"layer hidden_0 has kernel \(50, 128\).*observation_size 49"):
        onnx_export.export_onnx(broken, tmp_path / "broken.onnx")


def _random_policy(activation: str, seed: int = 0) -> Policy:
    """A small tanh-normal policy of fresh Brax parameters, its normalizer fed with data far from zero mean and unit
    spread, so that a wrong or missing normalization shows."""
    from brax.training.acme import running_statistics, specs

    config = {"observation_size": 7, "action_size": 3, "normalize_observations": True,
              "network_factory_kwargs": {"activation": activation, "policy_hidden_layer_sizes": [16, 16],
                                         "value_hidden_layer_sizes": [8]}}
    with jax.enable_x64(False):  # float32 throughout, as in training (Brax's normalizer follows the x64 flag)
        key = jax.random.PRNGKey(seed)
        params = make_networks(config).policy_network.init(key)
        params = jax.tree_util.tree_map(lambda w: 2.0 * w, params)  # wider pre-activations: the nonlinearities show
        data = 5.0 + 3.0 * jax.random.normal(jax.random.fold_in(key, 1), (256, 7))
        normalizer = running_statistics.update(
            running_statistics.init_state(specs.Array((7,), np.dtype("float32"))), data)
    return Policy(task="fourbar_track", env={}, config=config, params=(normalizer, params), source="random")


@pytest.mark.parametrize("activation", onnx_export.ACTIVATIONS)
def test_every_supported_activation_matches_brax(activation, tmp_path):
    policy = _random_policy(activation)
    path = onnx_export.export_onnx(policy, tmp_path / "p.onnx")
    assert onnx_export.check_onnx(policy, path, onnx_export.sample_observations(policy, 200)) <= TOL


def test_a_network_it_cannot_export_is_named(tmp_path):
    policy = _random_policy("silu")
    gelu = dataclasses.replace(policy, config={**policy.config, "network_factory_kwargs": {"activation": "gelu"}})
    with pytest.raises(ValueError, match="activation 'gelu' has no ONNX form"):
        onnx_export.export_onnx(gelu, tmp_path / "p.onnx")
    normal = dataclasses.replace(policy, config={**policy.config,
                                                 "network_factory_kwargs": {"distribution_type": "normal"}})
    with pytest.raises(ValueError, match="distribution_type is 'normal'"):
        onnx_export.export_onnx(normal, tmp_path / "p.onnx")


def test_kamino_export_writes_and_checks_the_model(tmp_path, capsys):
    from kamino import cli

    with pytest.raises(SystemExit) as exit_:
        cli.main(["export", "--help"])
    assert exit_.value.code == 0 and "usage: kamino export" in capsys.readouterr().out
    assert cli.main(["export", "dr_legs_walk", str(tmp_path / "walk.onnx"), "--check", "100"]) == 0
    out = capsys.readouterr().out
    assert (tmp_path / "walk.onnx").is_file() and "on 100 observations" in out and "within 1e-05" in out
    with pytest.raises(SystemExit) as exit_:
        cli.main(["export", "no_such_policy", str(tmp_path / "x.onnx")])
    assert exit_.value.code == 2 and "dr_legs_walk" in capsys.readouterr().err


def test_kamino_export_takes_a_training_checkpoint(tmp_path, capsys):
    """A ``kamino train`` checkpoint (Brax's own format, its network config naming the activation) exports and
    passes the check, as a shipped policy does (Brax stores linen.swish by its function name, silu)."""
    import functools

    from brax.training.acme import running_statistics, specs
    from brax.training.agents.ppo import checkpoint as ppo_checkpoint
    from brax.training.agents.ppo import networks as ppo_networks
    from flax import linen

    from kamino import cli

    factory = functools.partial(ppo_networks.make_ppo_networks, policy_hidden_layer_sizes=(16, 16),
                                value_hidden_layer_sizes=(8,), activation=linen.swish)
    with jax.enable_x64(False):
        net = factory(7, 3, preprocess_observations_fn=running_statistics.normalize)
        key = jax.random.PRNGKey(2)
        policy = net.policy_network.init(key)
        normalizer = running_statistics.update(
            running_statistics.init_state(specs.Array((7,), np.dtype("float32"))),
            1.0 + 2.0 * jax.random.normal(jax.random.fold_in(key, 1), (64, 7)))
        config = ppo_checkpoint.network_config(7, 3, True, factory)
        ppo_checkpoint.save(tmp_path / "run" / "checkpoints", 500, (normalizer, policy,
                                                                    net.value_network.init(key)), config)
    out = tmp_path / "run.onnx"
    assert cli.main(["export", str(tmp_path / "run"), str(out), "--task", "fourbar_track", "--check", "200"]) == 0
    printed = capsys.readouterr().out
    assert "fourbar_track policy" in printed and "within 1e-05" in printed
    import onnx

    meta = {p.key: p.value for p in onnx.load(out).metadata_props}
    assert meta["step"] == "500" and meta["activation"] == "silu" and meta["observation_size"] == "7"
