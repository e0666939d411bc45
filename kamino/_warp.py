"""Warp's console output under kamino: quiet by default.

Warp prints a banner when it initialises and a "Module ... load on device ..." line for every kernel module it
loads (about 25 per process for kamino's Warp backend). kamino turns these off the first time it imports Warp
(``kamino.step(..., backend="warp")``, ``kamino bench``), unless the user already chose a level:

- ``KAMINO_WARP_VERBOSE=1`` in the environment keeps Warp's own default (banner and module loads);
- or set ``warp.config.log_level = warp.LOG_INFO`` (Warp 1.19+; ``warp.config.quiet = False`` before) after the
  first kamino call that uses Warp: kamino sets the level only once per process, and a level other than
  Warp's default is left as the user set it.

Warnings and errors are still printed (``warp.LOG_WARNING``), except one that a machine without an NVIDIA GPU cannot
act on: Warp's native library prints "Warp CUDA warning: Could not find or load the NVIDIA CUDA driver. GPU execution
will not be available." when it starts without a CUDA driver (a CPU-only machine, where kamino's Warp backend runs
on the CPU). When no driver library loads (``libcuda.so`` / ``libcuda.so.1``; ``nvcuda.dll`` on Windows),
:func:`quiet_warp` starts Warp (``warp.init()``) with the process's stderr read into a temporary file and writes back
every line but that one. ``KAMINO_WARP_VERBOSE=1`` keeps it too.
"""

from __future__ import annotations

import contextlib
import ctypes
import os
import sys
import tempfile
from collections.abc import Callable

#: environment variable that keeps Warp's own console output (banner, module loads): "1", "true" or "yes"
VERBOSE_ENV = "KAMINO_WARP_VERBOSE"

#: how Warp's native library starts its message about a missing CUDA driver (one line on stderr)
NO_DRIVER_MESSAGE = "Warp CUDA warning: Could not find or load the NVIDIA CUDA driver"

#: the driver libraries Warp looks for, in its order, per platform (macOS: Warp has no CUDA and prints nothing)
DRIVER_LIBRARIES = {"linux": ("libcuda.so", "libcuda.so.1"), "win32": ("nvcuda.dll",)}

_configured = False


def quiet_warp() -> None:
    """Import Warp and silence its banner and module-load lines, once per process (module docstring)."""
    global _configured
    if _configured:
        return
    _configured = True
    if os.environ.get(VERBOSE_ENV, "").strip().lower() in ("1", "true", "yes", "on"):
        return
    import warp as wp

    config = wp.config
    if hasattr(config, "log_level"):  # Warp 1.19+: the banner and module loads are LOG_INFO messages
        info, warning = getattr(wp, "LOG_INFO", 20), getattr(wp, "LOG_WARNING", 30)
        if config.log_level == info:  # Warp's default: the user has not chosen a level
            config.log_level = warning
    elif not getattr(config, "quiet", False):  # older Warp
        config.quiet = True
    if not cuda_driver_loads():
        without_lines(wp.init, NO_DRIVER_MESSAGE)


def cuda_driver_loads(platform: str | None = None) -> bool:
    """Whether a CUDA driver library that Warp would load is there (``platform``: ``sys.platform`` by default; one
    with no entry in :data:`DRIVER_LIBRARIES` counts as having nothing to report)."""
    names = DRIVER_LIBRARIES.get(sys.platform if platform is None else platform)
    if names is None:
        return True
    for name in names:
        try:
            ctypes.CDLL(name)
        except OSError:
            continue
        return True
    return False


def without_lines(call: Callable[[], object], prefix: str) -> object:
    """``call()`` with the process's stderr (file descriptor 2, where native code writes) read into a temporary file;
    afterwards every line that does not start with ``prefix`` is written to stderr again, in order. Returns what
    ``call`` returns; an exception from it propagates after the lines are written. A process whose descriptor 2
    cannot be duplicated runs ``call`` as it is."""
    sys.stderr.flush()
    try:
        saved = os.dup(2)
    except OSError:
        return call()
    with tempfile.TemporaryFile() as held, contextlib.ExitStack() as restore:
        restore.callback(os.close, saved)
        os.dup2(held.fileno(), 2)
        try:
            return call()
        finally:
            sys.stderr.flush()
            os.dup2(saved, 2)
            held.seek(0)
            kept = [line for line in held.read().decode(errors="replace").splitlines(keepends=True)
                    if not line.startswith(prefix)]
            if kept:
                sys.stderr.write("".join(kept))
                sys.stderr.flush()
