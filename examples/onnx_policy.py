"""Run a policy exported by ``kamino export`` with onnxruntime alone: no kamino, JAX or Brax.

    kamino export dr_legs_walk dr_legs_walk.onnx            # once, where kamino is installed
    python examples/onnx_policy.py dr_legs_walk.onnx         # anywhere with numpy and onnxruntime

The model maps observations ``[batch, observation_size]`` (float32, the environment's raw observation: the model
normalizes it) to actions ``[batch, action_size]`` in [-1, 1], the policy's deterministic action. With ``--obs
FILE.npy`` it acts on those observations, else on a few random ones; ``--out FILE.npy`` saves the actions.
"""

from __future__ import annotations

import argparse
import sys

import numpy as np
import onnxruntime as ort


class OnnxPolicy:
    """An exported policy: ``OnnxPolicy(path)(obs)`` is the action for ``obs`` (one observation or a batch)."""

    def __init__(self, path: str):
        self.session = ort.InferenceSession(path, providers=["CPUExecutionProvider"])
        self.meta = self.session.get_modelmeta().custom_metadata_map
        self.input = self.session.get_inputs()[0]
        self.observation_size = int(self.input.shape[-1])
        self.action_size = int(self.session.get_outputs()[0].shape[-1])

    def __call__(self, obs) -> np.ndarray:
        obs = np.asarray(obs, np.float32)
        if obs.ndim not in (1, 2) or obs.shape[-1] != self.observation_size:
            raise ValueError(f"the observation has shape {obs.shape}; the policy of task {self.meta.get('task')!r} "
                             f"expects {self.observation_size} values ([{self.observation_size}] or "
                             f"[batch, {self.observation_size}])")
        action = self.session.run(None, {self.input.name: np.atleast_2d(obs)})[0]
        return action[0] if obs.ndim == 1 else action


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("model", help="the .onnx file kamino export wrote")
    p.add_argument("--obs", help="observations [batch, observation_size] as a .npy file (default: 4 random ones)")
    p.add_argument("--out", help="write the actions here (.npy)")
    args = p.parse_args(argv)
    policy = OnnxPolicy(args.model)
    print(f"{args.model}: task {policy.meta.get('task')}, observation {policy.observation_size}, "
          f"action {policy.action_size}, trained for {policy.meta.get('step') or '?'} steps")
    if args.obs:
        obs = np.load(args.obs)
    else:
        obs = np.random.default_rng(0).standard_normal((4, policy.observation_size))
    try:
        actions = policy(obs)
    except ValueError as e:
        p.error(str(e))
    np.set_printoptions(precision=4, suppress=True, linewidth=120)
    print(f"actions for {len(np.atleast_2d(obs))} observations:\n{np.atleast_2d(actions)[:4]}")
    if args.out:
        np.save(args.out, actions)
    return 0


if __name__ == "__main__":
    sys.exit(main())
