"""brax's PPO learns the small loop task (issue 18, tests): ``fourbar_track`` on the CPU in about a minute.

Measured on the 2-core CPU machine (JAX backend, float32, this config, 61 440 environment steps; the eval is the mean
return of 64 deterministic episodes of 100 steps, brax's ``eval/episode_reward``):

- the initial policy (brax's eval at step 0), seeds 0-3: 12.7, 14.4, 12.8, 22.3, with a spread of the 64 episode
  returns of 17-23, so each eval mean has a standard error of at most 23 / 8 = 2.9;
- a uniformly random policy: 11.6 (episode spread 5.4);
- after training, seeds 0-3: 90.5, 81.7, 89.4, 90.0 (100 is the most a policy can score: exact tracking at every
  step; the crank needs about 20 steps to swing to a new target, twice per episode).

The test asks for an improvement of 40 over the initial eval and a final eval above 60: 40 is over ten standard
errors of the two evals and two thirds of the smallest improvement measured (59.4, seed 1); 60 is four times the
best untrained score. The run took 40-50 s alone on the machine when this was written (half of it compiling); on
2026-11-26 it took 84 s alone and 152 s pinned to one core, as CI's workers are, and so did session 25's commit (the
machine slowed, not the code). Issue 18 allows 2 minutes, which is not asserted (a timing under CI's parallel
workers would make the test flaky).
"""

from __future__ import annotations

import time

import jax
import pytest

pytest.importorskip("brax")

from brax.training.agents.ppo import train as ppo

from kamino.envs import FourbarTrack
from kamino.envs.configs import ppo_kwargs

STEPS = 61_440  # 12 PPO iterations of 5 120 environment steps (batch 64 x unroll 10 x 8 minibatches)
MIN_IMPROVEMENT = 40.0
MIN_FINAL = 60.0


def test_ppo_improves_the_fourbar_tracking_return():
    env = FourbarTrack()
    evals: list[tuple[int, float]] = []
    start = time.perf_counter()
    with jax.enable_x64(False):  # brax's wrappers need the default float32 (tests/test_envs.py)
        ppo.train(environment=env, progress_fn=lambda step, m: evals.append((step, float(m["eval/episode_reward"]))),
                  **ppo_kwargs("fourbar_track", num_timesteps=STEPS, num_evals=2, seed=0))
    print(f"fourbar_track PPO: {evals} in {time.perf_counter() - start:.1f} s")
    (step0, initial), (step1, final) = evals[0], evals[-1]
    assert step0 == 0 and step1 >= STEPS
    assert final - initial > MIN_IMPROVEMENT, evals
    assert final > MIN_FINAL, evals
