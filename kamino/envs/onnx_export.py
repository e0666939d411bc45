"""A trained policy as an ONNX model: ``kamino export RUN_OR_POLICY OUT.onnx`` or :func:`export_onnx`.

The model is the policy's deterministic action, what ``kamino eval`` runs: for observations ``x``
(``[batch, observation_size]``, float32) it computes

    z_0 = (x - mean) / std                      Brax's observation normalizer (running_statistics.normalize)
    z_k = act(z_(k-1) W_k + b_k),  k = 1..L-1   the hidden Dense layers and the network's activation
    a   = tanh(z_(L-1) W_L[:, :A] + b_L[:A])    the mode of the tanh-normal: tanh of the mean half of the last layer

with ``A = action_size`` (the last layer's other ``A`` outputs parameterize the spread, which the mode does not use).
Each line is the same float32 operation Brax's inference function applies (``brax.training.agents.ppo.networks.
make_inference_fn`` with ``deterministic=True``), built with the ``onnx`` package's helper API at opset
:data:`OPSET`. The input is named ``observation``, the output ``action``; the batch dimension is free. The model's
metadata (``metadata_props``) holds the task, the observation and action sizes, the environment keywords and where
the policy came from.

:func:`check_onnx` runs the model with onnxruntime against the JAX policy on observations from
:func:`sample_observations` and returns the largest absolute difference. Needs the ``export`` extra
(``pip install "kamino[export]"``: onnx and onnxruntime).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from kamino.envs.policy import Policy

#: the ONNX operator set the exported models use (every operator in them is unchanged since opset 13)
OPSET = 17
#: the names of the model's input and output
INPUT, OUTPUT = "observation", "action"
#: what the check of ``kamino export`` allows between the ONNX and the JAX action (absolute, float32; see
#: :func:`check_onnx`)
TOLERANCE = 1e-5

#: Flax's SELU constants (``jax.nn.selu``)
_SELU_ALPHA, _SELU_SCALE = 1.6732632423543772848170429916717, 1.0507009873554804934193349852946
#: the activations an exported network may use (Brax's ``networks.ACTIVATION`` names) and Flax's negative slope of
#: ``leaky_relu``
ACTIVATIONS = ("elu", "leaky_relu", "linear", "relu", "selu", "sigmoid", "silu", "soft_sign", "softplus", "swish",
               "tanh")
_LEAKY_SLOPE = 0.01


def _needs(module: str):
    import importlib

    try:
        return importlib.import_module(module)
    except ImportError as exc:
        raise ImportError(f"exporting a policy to ONNX needs {module}: install the export extra "
                          "(pip install \"kamino[export]\")") from exc


def policy_layers(policy: Policy) -> tuple[tuple[np.ndarray, np.ndarray] | None, list[tuple[np.ndarray, np.ndarray]],
                                           str]:
    """What the model computes, as float32 arrays: ``(normalizer, layers, activation)``. ``normalizer`` is
    ``(mean, std)`` (``None`` for a network trained without observation normalization), ``layers`` the ``(kernel
    [in, out], bias [out])`` of each Dense layer in order, the last one cut to the mean half (its first
    ``action_size`` outputs). Raises a ``ValueError`` naming what does not fit: a network other than Brax's
    tanh-normal MLP, an activation outside :data:`ACTIVATIONS`, or arrays whose sizes do not chain from
    ``observation_size`` to ``2 * action_size``."""
    config = policy.config
    kwargs = dict(config.get("network_factory_kwargs") or {})
    if not isinstance(config.get("observation_size"), int):
        raise ValueError(f"export_onnx: the policy's observation_size is {config.get('observation_size')!r}; only a "
                         "flat observation (an int size) is exported")
    distribution = kwargs.get("distribution_type") or "tanh_normal"
    if distribution != "tanh_normal":
        raise ValueError(f"export_onnx: the policy's distribution_type is {distribution!r}; only Brax's tanh_normal "
                         "policy is exported")
    activation = kwargs.get("activation") or "swish"  # Brax's make_ppo_networks default
    if not isinstance(activation, str):
        activation = getattr(activation, "__name__", repr(activation))
    if activation not in ACTIVATIONS:
        raise ValueError(f"export_onnx: the policy's activation {activation!r} has no ONNX form here; supported: "
                         f"{', '.join(ACTIVATIONS)}")
    obs_size, action_size = policy.observation_size, policy.action_size
    normalizer_state, params = policy.params
    dense = dict(params.get("params", params))
    names = sorted((k for k in dense if k.startswith("hidden_")), key=lambda k: int(k.split("_")[1]))
    if not names or len(names) != len(dense):
        raise ValueError(f"export_onnx: the policy parameters hold {sorted(dense)}; expected Brax's MLP layers "
                         "hidden_0, hidden_1, ...")
    layers = [(np.asarray(dense[k]["kernel"], np.float32), np.asarray(dense[k]["bias"], np.float32)) for k in names]
    width = obs_size
    for name, (kernel, bias) in zip(names, layers, strict=True):
        if kernel.ndim != 2 or kernel.shape[0] != width or bias.shape != (kernel.shape[1],):
            raise ValueError(f"export_onnx: layer {name} has kernel {kernel.shape} and bias {bias.shape}; expected a "
                             f"kernel ({width}, n) and a bias (n,) after the observation_size {obs_size}")
        width = kernel.shape[1]
    if width != 2 * action_size:
        raise ValueError(f"export_onnx: the last layer has {width} outputs; a tanh-normal policy of action_size "
                         f"{action_size} has {2 * action_size} (mean and spread)")
    kernel, bias = layers[-1]
    layers[-1] = (kernel[:, :action_size], bias[:action_size])
    normalizer = None
    if config.get("normalize_observations"):
        mean = np.asarray(normalizer_state.mean, np.float32)
        std = np.asarray(normalizer_state.std, np.float32)
        if mean.shape != (obs_size,) or std.shape != (obs_size,):
            raise ValueError(f"export_onnx: the normalizer's mean {mean.shape} and std {std.shape} do not match the "
                             f"observation_size {obs_size}")
        normalizer = (mean, std)
    return normalizer, layers, activation


def _activation_nodes(helper, name: str, x: str, out: str) -> list:
    """The ONNX nodes of the activation ``name`` from ``x`` to ``out``."""
    if name in ("silu", "swish"):  # x * sigmoid(x)
        return [helper.make_node("Sigmoid", [x], [f"{out}_sigmoid"]),
                helper.make_node("Mul", [x, f"{out}_sigmoid"], [out])]
    single = {"relu": ("Relu", {}), "tanh": ("Tanh", {}), "sigmoid": ("Sigmoid", {}), "elu": ("Elu", {"alpha": 1.0}),
              "softplus": ("Softplus", {}), "soft_sign": ("Softsign", {}), "linear": ("Identity", {}),
              "leaky_relu": ("LeakyRelu", {"alpha": _LEAKY_SLOPE}),
              "selu": ("Selu", {"alpha": _SELU_ALPHA, "gamma": _SELU_SCALE})}
    op, attrs = single[name]
    return [helper.make_node(op, [x], [out], **attrs)]


def build_onnx(policy: Policy, opset: int = OPSET):
    """The policy's deterministic action as an ``onnx.ModelProto`` (the module doc), checked by
    ``onnx.checker``."""
    onnx = _needs("onnx")
    from onnx import TensorProto, helper, numpy_helper

    normalizer, layers, activation = policy_layers(policy)
    inits, nodes = [], []
    x = INPUT
    if normalizer is not None:
        mean, std = normalizer
        inits += [numpy_helper.from_array(mean, "obs_mean"), numpy_helper.from_array(std, "obs_std")]
        nodes += [helper.make_node("Sub", [x, "obs_mean"], ["obs_centered"]),
                  helper.make_node("Div", ["obs_centered", "obs_std"], ["obs_normalized"])]
        x = "obs_normalized"
    for i, (kernel, bias) in enumerate(layers):
        last = i == len(layers) - 1
        inits += [numpy_helper.from_array(kernel, f"hidden_{i}_kernel"),
                  numpy_helper.from_array(bias, f"hidden_{i}_bias")]
        dense = "action_mean" if last else f"hidden_{i}_dense"
        nodes.append(helper.make_node("Gemm", [x, f"hidden_{i}_kernel", f"hidden_{i}_bias"], [dense]))
        if last:
            nodes.append(helper.make_node("Tanh", [dense], [OUTPUT]))
        else:
            x = f"hidden_{i}"
            nodes += _activation_nodes(helper, activation, dense, x)
    graph = helper.make_graph(
        nodes, "policy",
        [helper.make_tensor_value_info(INPUT, TensorProto.FLOAT, ["batch", policy.observation_size])],
        [helper.make_tensor_value_info(OUTPUT, TensorProto.FLOAT, ["batch", policy.action_size])],
        initializer=inits)
    model = helper.make_model(graph, producer_name="kamino", opset_imports=[helper.make_opsetid("", opset)],
                              doc_string=f"{policy.task}: the deterministic action tanh(mean) of a Brax PPO policy, "
                                         "observation normalization included")
    model.ir_version = min(model.ir_version, 8)  # what opset 17 needs: readable by older onnxruntime releases too
    meta = {"task": policy.task, "observation_size": str(policy.observation_size),
            "action_size": str(policy.action_size), "env": json.dumps(policy.env, sort_keys=True),
            "source": policy.source, "step": "" if policy.step is None else str(policy.step),
            "activation": activation, "normalized_observations": str(normalizer is not None).lower()}
    helper.set_model_props(model, meta)
    onnx.checker.check_model(model, full_check=True)
    return model


def export_onnx(policy: Policy, path: str | Path, opset: int = OPSET) -> Path:
    """Write ``policy``'s deterministic action as the ONNX model ``path`` (:func:`build_onnx`); returns the path."""
    onnx = _needs("onnx")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    onnx.save_model(build_onnx(policy, opset), path)
    return path


def sample_observations(policy: Policy, n: int = 1000, seed: int = 0, spread: float = 3.0) -> np.ndarray:
    """``n`` float32 observations ``[n, observation_size]`` around those the policy was trained on: ``mean + spread
    * std * z`` with ``z`` standard normal and the normalizer's ``mean``/``std`` (for a network without
    normalization, ``spread * z``). A spread of 3 covers the observations of training and reaches into the tails,
    where the last tanh saturates."""
    rng = np.random.default_rng(seed)
    z = rng.standard_normal((n, policy.observation_size))
    normalizer, _, _ = policy_layers(policy)
    if normalizer is None:
        return (spread * z).astype(np.float32)
    mean, std = normalizer
    return (mean + spread * std * z).astype(np.float32)


def onnx_actions(path: str | Path, observations: np.ndarray) -> np.ndarray:
    """The actions of the ONNX model ``path`` for ``observations`` (``[n, observation_size]``), run on
    onnxruntime's CPU provider."""
    ort = _needs("onnxruntime")
    session = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    size = session.get_inputs()[0].shape[-1]
    observations = np.asarray(observations, np.float32)
    if observations.ndim != 2 or observations.shape[1] != size:
        raise ValueError(f"onnx_actions: observations of shape {observations.shape}; the model {path} takes "
                         f"[batch, {size}] (its observation_size is {size})")
    return session.run([OUTPUT], {INPUT: observations})[0]


def check_onnx(policy: Policy, path: str | Path, observations: np.ndarray | None = None) -> float:
    """The largest absolute difference between the ONNX model ``path`` (onnxruntime) and ``policy``'s JAX
    deterministic action over ``observations`` (default: 1000 of :func:`sample_observations`).

    Both evaluate the same float32 operations, layer by layer; they differ only in the rounding inside each: the
    summation order of the dot products and each library's sigmoid and tanh (a few ulp). Rounding a dot product
    ``sum w_i h_i`` of ``n`` terms in float32 errs by about ``sqrt(n) u sum|w_i h_i|`` (``u = 2**-24``, rounding
    errors of random sign; ``n u sum|w_i h_i|`` at worst). For the shipped policy on the observations of
    :func:`sample_observations` (spread 3), the last layer's ``sum|w_i h_i|`` stays below about 11, so each float32
    evaluation is within about ``sqrt(128) u 11 = 7.5e-6`` of the exact mean (the JAX one measures 2.4e-6 from a
    float64 evaluation), and the final tanh (slope at most 1) does not enlarge it. The two actions measure 1.6e-6
    apart on 1000 such observations, inside :data:`TOLERANCE` with a margin of six (3.3e-7 on 1000 observations of
    the policy's own rollouts, which lie closer to the training data). The difference grows with the
    observation's distance from the training data, as ``sum|w_i h_i|`` does."""

    import jax

    observations = sample_observations(policy) if observations is None else np.asarray(observations, np.float32)
    with jax.enable_x64(False):
        reference = np.asarray(jax.jit(lambda obs: policy.act(obs))(observations))
    return float(np.max(np.abs(onnx_actions(path, observations) - reference)))


def main(argv: list[str] | None = None) -> int:
    """``kamino export ARGS``: returns the exit status."""
    from kamino.envs import evaluate, runs
    from kamino.envs.policy import shipped_policies

    p = argparse.ArgumentParser(prog="kamino export",
                                description="Write a trained policy's deterministic action (observation normalization "
                                "included) as an ONNX model, and check it against the JAX policy.",
                                epilog=f"Shipped policies: {', '.join(shipped_policies())}. Needs the export extra "
                                "(onnx, onnxruntime).")
    p.add_argument("policy", metavar="RUN_OR_POLICY", help="a shipped policy's name, a run folder or a checkpoint")
    p.add_argument("out", metavar="OUT.onnx", type=Path, help="the model file to write")
    p.add_argument("--task", help="the task (default: the run's, else dr_legs_joystick)")
    p.add_argument("--check", type=int, default=1000, metavar="N",
                   help="observations to compare the model on with the JAX policy (default 1000; 0 skips)")
    p.add_argument("--tolerance", type=float, default=TOLERANCE,
                   help=f"the largest absolute action difference the check allows (default {TOLERANCE:g})")
    args = p.parse_args(sys.argv[1:] if argv is None else argv)
    if args.check < 0:
        p.error("--check must be >= 0")
    try:
        policy = evaluate.resolve(args.policy, args.task)
        path = export_onnx(policy, args.out)
    except (runs.OptionError, FileNotFoundError, ValueError, ImportError) as e:
        p.error(str(e))
    print(f"kamino export: {policy.task} policy from {policy.source} -> {path} (observation {policy.observation_size}, "
          f"action {policy.action_size}, opset {OPSET})", flush=True)
    if args.check:
        try:
            diff = check_onnx(policy, path, sample_observations(policy, args.check))
        except ImportError as e:
            p.error(f"{e}; --check 0 writes the model without the check")
        ok = diff <= args.tolerance
        print(f"  onnxruntime vs JAX on {args.check} observations: max |action difference| {diff:.2e} "
              f"({'within' if ok else 'OVER'} {args.tolerance:g})", flush=True)
        if not ok:
            return 1
    return 0


__all__ = ["ACTIVATIONS", "INPUT", "OPSET", "OUTPUT", "TOLERANCE", "build_onnx", "check_onnx", "export_onnx",
           "onnx_actions", "policy_layers", "sample_observations"]


if __name__ == "__main__":
    raise SystemExit(main())
