"""Training across processes (``kamino train --distributed``, kamino.envs.distributed): two CPU processes on one
machine, coordinated on localhost, each with two forced host devices, train one tiny PPO run of ``fourbar_track``
(Warp backend, domain randomization; the PPO config of tests/test_rl_resume.py: three evaluations 240 environment
steps apart, 8 environments, 2 on each of the 4 devices).

Each process steps its own environments (Brax folds the process index into their keys) and Brax's ``pmap`` averages
the gradients and the observation statistics over the devices of both processes. The test asserts what follows:

- both processes end with the same parameters, bit for bit (each applies the same averaged update to the same
  parameters), and these are not the initial ones (the run trained);
- the observation normaliser counts every observation of both processes: 720, the run's environment steps, where
  one process's own environments give 360;
- process 0 alone writes the run folder: a checkpoint after each evaluation (240, 480, 720), each with its row of
  ``curve.json``, the last one holding the parameters both processes end with.

The processes capture the parameters Brax returns (and those it hands over before the first epoch) by wrapping
``ppo.train`` in the subprocess script. Two devices per process also make this the test of Brax's PPO on the Warp
backend over two devices of one process, with randomization (each device with its own Warp stepper,
kamino/warp_backend/jit.py); tests/test_envs.py's two-device run covers the JAX backend.
"""

from __future__ import annotations

import os
import socket
import subprocess
import sys
import time
from pathlib import Path

import jax
import numpy as np
import pytest

pytest.importorskip("brax")

from brax.training.agents.ppo import checkpoint as ppo_checkpoint

from kamino.envs import runs
from tests.helpers import ALL_CORES

STEPS, EVERY, PROCESSES = 720, 240, 2
ARGS = ["fourbar_track", "--backend", "warp", "--steps", str(STEPS), "--num-envs", "8", "--evals", "4",
        "--set", "batch_size=8", "--set", "num_minibatches=2", "--set", "unroll_length=5",
        "--set", "num_eval_envs=4", "--set", "episode_length=20", "--set", "run_evals=False", "--env", "reset_bank=8",
        "--randomize", "effort_limit_scale=(0.8,1.2)", "--randomize", "gravity_scale=(0.9,1.1)"]

#: one process of the run: ``kamino train ARGS`` with ppo.train wrapped to save, as ``NAME.<process>.npz``, the
#: parameters Brax hands over before the first epoch (``initial``) and those it returns (``final``)
PROCESS = ALL_CORES + """
import functools
import sys
from pathlib import Path
import numpy as np
import jax
from brax.training.agents.ppo import train as ppo_train
from kamino.envs import train
saved, argv = Path(sys.argv[1]), sys.argv[2:]
train.plot_curve = lambda *args, **kwargs: None  # not part of what is checked; its first drawing costs seconds
brax_train, captured = ppo_train.train, {}
@functools.wraps(brax_train)  # kamino train reads ppo.train's defaults from its signature
def capturing(**kwargs):
    handed = kwargs["policy_params_fn"]
    def on_params(step, make_policy, params):
        captured.setdefault("initial", params)
        handed(step, make_policy, params)
    result = brax_train(**{**kwargs, "policy_params_fn": on_params})
    captured["final"] = result[1]
    return result
ppo_train.train = capturing
status = train.main(argv)
assert (jax.local_device_count(), jax.device_count()) == (2, 4), jax.devices()
for name, params in captured.items():
    np.savez(saved / f"{name}.{jax.process_index()}.npz", *[np.asarray(x) for x in jax.tree.leaves(params)])
sys.exit(status)
"""


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _leaves(path: Path) -> list[np.ndarray]:
    with np.load(path) as data:
        return [data[f"arr_{i}"] for i in range(len(data.files))]


def test_two_processes_train_one_policy(tmp_path):
    out = tmp_path / "run"
    coordinator = f"127.0.0.1:{_free_port()}"
    logs = [tmp_path / f"process{i}.log" for i in range(PROCESSES)]
    env = dict(os.environ, JAX_PLATFORMS="cpu")
    env["XLA_FLAGS"] = f"{env.get('XLA_FLAGS', '')} --xla_force_host_platform_device_count=2".strip()
    procs = []
    for i, log in enumerate(logs):
        with log.open("w") as sink:
            procs.append(subprocess.Popen(
                [sys.executable, "-c", PROCESS, str(tmp_path), *ARGS, "--out", str(out), "--distributed",
                 "--coordinator", coordinator, "--num-processes", str(PROCESSES), "--process-id", str(i)],
                stdout=sink, stderr=subprocess.STDOUT, env=env))
    deadline = time.monotonic() + 300
    while any(p.poll() is None for p in procs) and time.monotonic() < deadline:
        time.sleep(0.2)
    for p in procs:
        if p.poll() is None:
            p.kill()
            p.wait()
    report = "\n".join(f"--- process {i} (exit {p.returncode}):\n{log.read_text()[-3000:]}"
                       for i, (p, log) in enumerate(zip(procs, logs, strict=True)))
    assert all(p.returncode == 0 for p in procs), report

    final = [_leaves(tmp_path / f"final.{i}.npz") for i in range(PROCESSES)]
    initial = [_leaves(tmp_path / f"initial.{i}.npz") for i in range(PROCESSES)]
    # bit for bit: one averaged update, applied alike on both processes, every epoch
    for a, b in zip(*final, strict=True):
        np.testing.assert_array_equal(a, b)
    for a, b in zip(*initial, strict=True):  # the networks start from the same (global) key
        np.testing.assert_array_equal(a, b)
    moved = max(float(np.max(np.abs(a - b))) for a, b in zip(final[0], initial[0], strict=True) if a.dtype.kind == "f")
    assert moved > 1e-4, f"the parameters moved by at most {moved:g}: the run did not train"

    # the observation normaliser (the first parameters: Brax's RunningStatisticsState; its count a (hi, lo) pair of
    # uint32) counts the observations of both processes: the run's environment steps, twice one process's
    ckpts = runs.committed_checkpoints(out / "checkpoints")
    assert [step for step, _ in ckpts] == [EVERY, 2 * EVERY, 3 * EVERY]
    saved = ppo_checkpoint.load(ckpts[-1][1])
    count = saved[0].count
    assert (int(count.hi), int(count.lo)) == (0, STEPS)
    # process 0's last checkpoint: the parameters both processes hold
    for a, b in zip(jax.tree.leaves(saved), final[0], strict=True):
        np.testing.assert_array_equal(np.asarray(a), b)
    curve = runs.read_json(out / "curve.json")
    assert [row["step"] for row in curve] == [EVERY, 2 * EVERY, 3 * EVERY]
    for step, path in ckpts:
        assert [row["step"] for row in runs.checkpoint_record(path)["curve"]] == [step]


def test_the_checkpoint_written_alone_is_brax_s(tmp_path):
    """Across processes process 0 writes each checkpoint without Brax's writer (whose orbax save waits for every
    process): the same network config, byte for byte, and parameters that Brax's loader reads back equal to those
    Brax's own writer saves (a normaliser with its step count, the policy and value networks)."""
    import functools

    from brax.training.acme import running_statistics, specs
    from brax.training.agents.ppo import networks as ppo_networks

    factory = functools.partial(ppo_networks.make_ppo_networks, policy_hidden_layer_sizes=(4,),
                                value_hidden_layer_sizes=(3,))
    net = factory(5, 2, preprocess_observations_fn=running_statistics.normalize)
    policy_key, value_key = jax.random.split(jax.random.PRNGKey(0))
    normaliser = running_statistics.update(running_statistics.init_state(specs.Array((5,), np.dtype("float32"))),
                                           jax.random.normal(policy_key, (7, 5), "float32"))
    params = (normaliser, net.policy_network.init(policy_key), net.value_network.init(value_key))
    config = ppo_checkpoint.network_config(5, 2, True, factory)
    ppo_checkpoint.save(tmp_path / "brax", 80, params, config)
    alone = runs.write_checkpoint_alone(tmp_path / "alone", 80, params, config)
    theirs = tmp_path / "brax" / f"{80:012d}"
    assert runs.is_checkpoint(alone)
    assert (alone / runs.NETWORK_CONFIG).read_text() == (theirs / runs.NETWORK_CONFIG).read_text()
    ours, reference = ppo_checkpoint.load(alone), ppo_checkpoint.load(theirs)
    assert jax.tree.structure(ours) == jax.tree.structure(reference)
    assert int(ours[0].count.lo) == 7
    for a, b in zip(jax.tree.leaves(ours), jax.tree.leaves(reference), strict=True):
        np.testing.assert_array_equal(a, b)
