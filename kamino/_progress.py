"""Words for long waits: an announced compile and a progress bar, both on stderr.

The helpers that kamino's command-line entry points use so that no wait of more than a few seconds passes in
silence (``kamino demo`` announces the compiles of its rollout and of its diagnostics):

- :func:`announce_compile` wraps work that may compile (the first call of a jitted function, a Warp module load).
  If the work is still running after ``after`` seconds (:data:`ANNOUNCE_AFTER`, 2 s), one line on stderr says what
  is being compiled, and the same line ends with the time it took. A call answered from JAX's persistent
  compilation cache (kamino/_jax_cache.py) or Warp's kernel cache usually ends before that and prints nothing.
- :func:`progress` is a tqdm bar on stderr for host-side loops (rollouts stepped from Python, episodes, runs), drawn
  at most twice a second and cleared when done.

``KAMINO_QUIET=1`` in the environment turns both off (for logs parsed by other programs). Library functions
(``kamino.step``, ``kamino.rollout``) print nothing: only entry points call these.
"""

from __future__ import annotations

import contextlib
import os
import sys
import threading
import time
from collections.abc import Iterable, Iterator
from typing import IO, TypeVar

from tqdm import tqdm

#: seconds of silence before :func:`announce_compile` speaks
ANNOUNCE_AFTER = 2.0

#: least seconds between two redraws of a :func:`progress` bar
PROGRESS_INTERVAL = 0.5

#: environment variable that turns announcements and bars off: "1", "true", "yes" or "on"
QUIET_ENV = "KAMINO_QUIET"

T = TypeVar("T")


def quiet() -> bool:
    """Whether ``KAMINO_QUIET`` asks for no announcements and no bars."""
    return os.environ.get(QUIET_ENV, "").strip().lower() in ("1", "true", "yes", "on")


def cache_note() -> str:
    """What the next run gains: "the first run on a machine takes longest; later runs load it from the cache" when
    JAX's persistent compilation cache is on (kamino/_jax_cache.py), "JAX's compilation cache is off" when it is
    off, and nothing before JAX is imported."""
    jax = sys.modules.get("jax")
    if jax is None:
        return ""
    try:
        on = bool(jax.config.jax_enable_compilation_cache) and bool(jax.config.jax_compilation_cache_dir)
    except AttributeError:
        on = False
    if on:
        return "the first run on a machine takes longest; later runs load it from the cache"
    return "JAX's compilation cache is off"


def _elapsed(seconds: float) -> str:
    return f"{seconds:.1f} s" if seconds < 60 else f"{int(seconds // 60)} min {seconds % 60:.0f} s"


@contextlib.contextmanager
def announce_compile(what: str, *, after: float = ANNOUNCE_AFTER, note: str | None = None,
                     stream: IO[str] | None = None) -> Iterator[None]:
    """Announce on ``stream`` (stderr by default) that ``what`` is compiling, if the block takes over ``after``
    seconds.

    The line reads ``kamino: compiling WHAT (NOTE) ...`` and, when the block ends, ``done in 41.3 s`` (or
    ``failed after ...`` when it raises; the exception propagates). A block that ends within ``after`` seconds
    prints nothing. ``what`` names the work in a few words (``"the four-bar's rollout"``); ``note`` defaults to
    :func:`cache_note` (``""``: none; a Warp module load passes its own, e.g. "Warp keeps the kernels for the next
    run")::

        from kamino._progress import announce_compile

        with announce_compile("the policy's training step"):
            jitted(state).block_until_ready()  # the first call compiles

    The announcement comes from a timer thread (JAX and Warp release Python's lock while compiling, so it is on
    time); ``KAMINO_QUIET=1`` turns it off."""
    if not isinstance(what, str) or not what.strip():
        raise ValueError(f"announce_compile: what must name the work being compiled, got {what!r}")
    if not (isinstance(after, (int, float)) and after >= 0):
        raise ValueError(f"announce_compile: after must be a number of seconds >= 0, got {after!r}")
    if quiet():
        yield
        return
    out = sys.stderr if stream is None else stream
    note = cache_note() if note is None else note
    line = f"kamino: compiling {what}" + (f" ({note})" if note else "") + " ..."
    start = time.perf_counter()
    lock = threading.Lock()
    state = {"spoke": False, "over": False}

    def speak() -> None:
        with lock:
            if state["over"]:
                return
            state["spoke"] = True
            out.write(line)
            out.flush()

    timer = threading.Timer(after, speak)
    timer.daemon = True
    timer.start()
    outcome = "failed after"
    try:
        yield
        outcome = "done in"
    finally:
        timer.cancel()
        with lock:
            state["over"] = True
            if state["spoke"]:
                out.write(f" {outcome} {_elapsed(time.perf_counter() - start)}\n")
                out.flush()


def progress(iterable: Iterable[T] | None = None, *, desc: str | None = None, total: int | None = None,
             disable: bool = False, **options) -> tqdm:
    """A tqdm bar on stderr over ``iterable`` (or ``total`` manual updates), redrawn at most every
    :data:`PROGRESS_INTERVAL` seconds and cleared at the end; ``disable`` (or ``KAMINO_QUIET=1``) turns it off.
    ``options`` go to tqdm (``unit="step"``, ``leave=True``, ...)::

        for episode in progress(range(n), desc="kamino eval", unit="episode"):
            ...
    """
    options.setdefault("leave", False)
    options.setdefault("mininterval", PROGRESS_INTERVAL)
    options.setdefault("dynamic_ncols", True)
    return tqdm(iterable, desc=desc, total=total, disable=disable or quiet(), file=sys.stderr, **options)


__all__ = ["ANNOUNCE_AFTER", "PROGRESS_INTERVAL", "QUIET_ENV", "announce_compile", "cache_note", "progress", "quiet"]
