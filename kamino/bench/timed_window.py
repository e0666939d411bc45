"""The one timing rule of the throughput benchmark (:mod:`kamino.bench.throughput`: kamino Warp and JAX;
:mod:`kamino.bench.peers`: MuJoCo Warp and Newton's SolverKamino): every timed figure covers the same simulated window.

Each of ``repeats`` trials

1. resets the simulation to its initial state (``reset``: state, time, controls and whatever warm start the solver
   carries from step to step, as far as that solver lets it be reset; each caller documents what its reset covers),
2. runs ``warmup`` blocks of ``graph_steps`` steps untimed (``block``: one CUDA-graph replay, or a Python loop of
   steps where nothing is captured),
3. synchronises (``sync``), reads the clock, runs ``replays`` blocks, synchronises and reads the clock again.

The figure is the median trial over ``replays * graph_steps`` steps. So every trial, and every solver, times steps
``[warmup * graph_steps, (warmup + replays) * graph_steps)`` of the same driven motion from the same start, whatever
``repeats`` is, and a different ``replays`` lengthens the window without moving its start.

Why: the PADMM loop runs until every world converges, so a step costs in proportion to the iterations it needs, and
those follow the driven motion. On the four-bar (the 1 Hz sine drive) the iterations per block of 10 steps from
reset are 21, 20, 20, 27, 22, 38, 56, 160, 54, 36, 164. Trials that continue the simulation from one to the next
give the median trial of ``--replays 2`` about 30 iterations per block and that of ``--replays 3`` about 85: the
same H100 and code then measure the four-bar at 6.06e6 world-steps/s at 16384 worlds with ``--replays 2`` and 3.95e6
with ``--replays 3``. Scenes with flat iteration counts (ladder8: 20 per block throughout) give the same figure
either way; trials sized by wall time (a replay count calibrated to last a set time) would time yet another window.
"""

from __future__ import annotations

import statistics
import time
from collections.abc import Callable
from typing import Any

#: untimed blocks of every trial after its reset (the benchmark's ``--warmup``)
WARMUP_BLOCKS = 2


def window(graph_steps: int, warmup: int, replays: int, dt: float) -> dict[str, list]:
    """The timed window in steps from the reset, ``[start, end)``, and in simulated seconds ``[start dt, end dt)``."""
    start, end = warmup * graph_steps, (warmup + replays) * graph_steps
    return {"window_steps": [start, end], "window_s": [start * dt, end * dt]}


def time_window(
    reset: Callable[[], None],
    block: Callable[[], None],
    sync: Callable[[], None],
    *,
    graph_steps: int,
    replays: int,
    repeats: int,
    dt: float,
    warmup: int = WARMUP_BLOCKS,
    before_timing: Callable[[int], None] | None = None,
    after_trial: Callable[[int], None] | None = None,
) -> dict[str, Any]:
    """Time ``repeats`` trials of the window (module docstring) and return the median.

    Args:
        reset: put the simulation back to its initial state (untimed).
        block: advance ``graph_steps`` steps (enqueue them; ``sync`` waits).
        sync: wait until everything enqueued has run (``wp.synchronize_device``, ``jax.block_until_ready``).
        graph_steps: steps per block.
        replays: timed blocks per trial (at least 1).
        repeats: trials (at least 1); the median trial is reported.
        dt: time step [s], for ``window_s``.
        warmup: untimed blocks after each reset.
        before_timing: called with the trial's index after its warm-up has run and synchronised, just before the
            clock starts (untimed), e.g. to zero statistics that the timed blocks fold.
        after_trial: called with the trial's index after it has been timed and synchronised (untimed), e.g. to
            read the state a trial ends in.

    Returns:
        ``step_time_s`` (median trial / steps per trial), ``trials_s`` (every trial [s]), ``graph_steps``,
        ``warmup_blocks``, ``replays_per_trial``, ``repeats``, ``window_steps`` and ``window_s``.
    """
    replays, repeats, warmup = max(1, int(replays)), max(1, int(repeats)), max(0, int(warmup))
    trials = []
    for trial in range(repeats):
        reset()
        for _ in range(warmup):
            block()
        sync()
        if before_timing is not None:
            before_timing(trial)
            sync()
        t0 = time.perf_counter()
        for _ in range(replays):
            block()
        sync()
        trials.append(time.perf_counter() - t0)
        if after_trial is not None:
            after_trial(trial)
    return {
        "step_time_s": statistics.median(trials) / (replays * graph_steps),
        "trials_s": trials,
        "graph_steps": graph_steps,
        "warmup_blocks": warmup,
        "replays_per_trial": replays,
        "repeats": repeats,
        **window(graph_steps, warmup, replays, dt),
    }
