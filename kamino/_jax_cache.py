"""JAX's persistent compilation cache, on by default for kamino, and quiet when it loads an entry.

JAX compiles ``kamino.step``, ``kamino.rollout`` and every ``jax.jit`` around them anew in each process: seconds to
minutes on the CPU for a robot (docs/first_step.md). With the persistent cache, XLA's executables are written to disk
and the next process loads them instead of compiling. ``import kamino`` calls :func:`enable` once, which chooses the
directory in this order:

1. ``KAMINO_JAX_CACHE=0`` (or ``off``, ``false``, ``no``, ``none``): kamino leaves JAX's cache settings alone.
2. JAX's cache already configured: ``jax_enable_compilation_cache`` switched off, or ``jax_compilation_cache_dir``
   set (``jax.config.update`` before ``import kamino``, or the ``JAX_COMPILATION_CACHE_DIR`` variable): respected,
   nothing changes (a different ``KAMINO_JAX_CACHE=/path`` is then reported in a warning).
3. ``KAMINO_JAX_CACHE=/path``: there (``~`` expanded).
4. Otherwise the user's cache directory: ``platformdirs.user_cache_dir("kamino")/jax`` when ``platformdirs`` is
   installed, else ``$XDG_CACHE_HOME/kamino/jax``, else ``~/.cache/kamino/jax``.

When kamino chooses the directory (3 or 4) it creates it and caps ``jax_persistent_cache_min_compile_time_secs`` at
:data:`MIN_COMPILE_TIME_SECS` (1 s, JAX's own default today; a lower value of the user's stays). Every kamino step or
rollout compiles for 3 s or more on a CPU, so each is written; the small eager ops (padded layout, initial state) stay
out, and compiling them again costs about 0.1 s per process (docs/first_step.md).
``jax_persistent_cache_min_entry_size_bytes`` is left at JAX's default (0: no size floor), which keeps every entry.
The cache is unbounded (JAX's ``jax_compilation_cache_max_size`` = -1; an entry is 0.3-0.7 MB): delete the directory
to reclaim the space. Entries are keyed by the program, the jax/jaxlib version, the XLA flags and the device (on the
CPU: the target triple, CPU model and feature list), so a directory shared between machines never serves an
executable built for another CPU.

Failures never pass in silence: a directory that cannot be created or written, or a JAX whose config lacks one of the
names above, gives a ``RuntimeWarning`` naming what failed and the way out (``KAMINO_JAX_CACHE=/writable/path`` or
``KAMINO_JAX_CACHE=0``); the import then goes on without the cache. :data:`choice` holds what happened.

Loading an entry makes XLA log lines the user cannot act on: ``pjrt_executable.cc ... Assume version compatibility.
PjRt-IFRT does not track XLA executable versions.`` (a warning) and, on some CPUs, ``cpu_aot_loader.cc ... Target
machine feature +prefer-no-gather is not supported on the host machine`` (logged as an error, but the feature is an
LLVM tuning hint, not an instruction set, and the entry's key already holds the CPU's features).
:func:`quiet_cache_loads` (called by ``import kamino``) raises XLA's C++ log threshold to fatal while JAX reads one
entry, and puts jaxlib's default (warnings and errors) back right after; every other compile, run and log line is
untouched. A load that fails still raises inside JAX, which warns in Python ("Error reading persistent compilation
cache entry"). A user who chose XLA's log level (``TF_CPP_MIN_LOG_LEVEL=0`` to see everything, or 2, 3; or JAX's
``jax_logging_level`` / ``JAX_LOGGING_LEVEL``) sees every line at that level: kamino then leaves the threshold alone.
"""

from __future__ import annotations

import dataclasses
import functools
import os
import threading
import warnings
from collections.abc import Mapping
from pathlib import Path

ENV = "KAMINO_JAX_CACHE"
"""The environment variable: ``0`` (off) or a directory."""

MIN_COMPILE_TIME_SECS = 1.0
"""``jax_persistent_cache_min_compile_time_secs`` when kamino chooses the directory: compiles shorter than this are not
written (a step or rollout of any kamino model compiles for longer; docs/first_step.md)."""

_OFF = {"0", "off", "false", "no", "none"}


@dataclasses.dataclass(frozen=True)
class CacheChoice:
    """What :func:`choose` decided: ``directory`` (None: kamino sets no directory), and why (``source``)."""

    directory: str | None
    source: str  # "off" (KAMINO_JAX_CACHE=0), "jax" (JAX already configured), "env" (KAMINO_JAX_CACHE=/path),
    #              "default" (the user's cache directory), "failed" (see the warning)
    detail: str = ""


choice: CacheChoice | None = None
"""The last :func:`enable`'s decision (``kamino._jax_cache.choice``), for a user asking where the cache is."""


def default_dir(environ: Mapping[str, str] | None = None) -> Path:
    """The user's cache directory for kamino's JAX cache: platformdirs, else ``$XDG_CACHE_HOME``, else ``~/.cache``
    (each + ``kamino/jax``). ``environ`` (default ``os.environ``) is read only when platformdirs is missing."""
    try:
        import platformdirs
    except ImportError:
        platformdirs = None
    if platformdirs is not None:
        return Path(platformdirs.user_cache_dir("kamino")) / "jax"
    env = os.environ if environ is None else environ
    xdg = env.get("XDG_CACHE_HOME", "")
    base = Path(xdg).expanduser() if xdg and Path(xdg).expanduser().is_absolute() else Path("~/.cache").expanduser()
    return base / "kamino" / "jax"


def _jax_value(name: str):
    import jax

    return getattr(jax.config, name)


def choose(environ: Mapping[str, str] | None = None, *, jax_dir: str | None = None,
           jax_enabled: bool = True) -> CacheChoice:
    """The cache directory kamino would use, from the environment (``environ``, default ``os.environ``) and JAX's
    current settings (``jax_dir``: ``jax_compilation_cache_dir``; ``jax_enabled``: ``jax_enable_compilation_cache``).
    Pure: reads no config and writes nothing (:func:`enable` does)."""
    env = os.environ if environ is None else environ
    raw = env.get(ENV, "").strip()
    if raw.lower() in _OFF:
        return CacheChoice(None, "off", f"{ENV}={raw}")
    if not jax_enabled:
        return CacheChoice(None, "jax", "jax_enable_compilation_cache is False")
    if jax_dir:
        return CacheChoice(str(jax_dir), "jax", "jax_compilation_cache_dir was already set")
    if raw:
        return CacheChoice(str(Path(raw).expanduser()), "env", f"{ENV}={raw}")
    return CacheChoice(str(default_dir(env)), "default", "the user's cache directory")


def _warn(message: str, stacklevel: int = 3) -> None:
    warnings.warn(f"kamino: {message}", RuntimeWarning, stacklevel=stacklevel)


def _left_off(message: str, detail: str) -> CacheChoice:
    """Warn that the cache stays off (``message``), record why (``detail``) in :data:`choice` and return it."""
    global choice
    _warn(f"JAX's persistent compilation cache left off: {message}", stacklevel=4)
    choice = CacheChoice(None, "failed", detail)
    return choice


def enable(environ: Mapping[str, str] | None = None) -> CacheChoice:
    """Choose the directory (:func:`choose`, with JAX's current settings) and, where kamino chooses it, create it and
    point JAX there. Returns the choice and stores it in :data:`choice`. Never raises for a cache problem: it
    warns (``RuntimeWarning``) and leaves JAX's cache as it was."""
    global choice
    env = os.environ if environ is None else environ
    try:
        jax_dir = _jax_value("jax_compilation_cache_dir")
        jax_enabled = bool(_jax_value("jax_enable_compilation_cache"))
    except Exception as exc:  # a JAX whose config names differ
        return _left_off(f"reading jax.config.jax_compilation_cache_dir / jax_enable_compilation_cache failed "
                         f"({type(exc).__name__}: {exc}). Configure the cache with JAX yourself, or set {ENV}=0 to "
                         "silence this.", f"reading JAX's config: {exc}")
    choice = choose(env, jax_dir=jax_dir, jax_enabled=jax_enabled)
    raw = env.get(ENV, "").strip()
    if choice.source == "jax" and raw and raw.lower() not in _OFF and jax_dir and \
            Path(raw).expanduser().resolve() != Path(jax_dir).expanduser().resolve():
        _warn(f"{ENV}={raw} ignored: jax_compilation_cache_dir is already set to {jax_dir!r} (JAX's own setting "
              "wins; unset it or JAX_COMPILATION_CACHE_DIR to use kamino's)")
    if choice.source not in ("env", "default"):
        return choice

    path = Path(choice.directory)
    try:
        path.mkdir(parents=True, exist_ok=True)
        if not os.access(path, os.W_OK | os.X_OK):
            raise PermissionError(f"{str(path)!r} is not writable")
    except OSError as exc:
        return _left_off(f"cannot use {str(path)!r} ({type(exc).__name__}: {exc}). Set {ENV}=/a/writable/directory, "
                         f"or {ENV}=0 to run without it.", f"{path}: {exc}")

    import jax

    try:
        jax.config.update("jax_compilation_cache_dir", str(path))
    except Exception as exc:
        return _left_off(f"jax.config.update('jax_compilation_cache_dir', ...) failed ({type(exc).__name__}: {exc}). "
                         f"Set {ENV}=0 to silence this.", f"jax_compilation_cache_dir: {exc}")
    try:
        if float(_jax_value("jax_persistent_cache_min_compile_time_secs")) > MIN_COMPILE_TIME_SECS:
            jax.config.update("jax_persistent_cache_min_compile_time_secs", MIN_COMPILE_TIME_SECS)
    except Exception as exc:
        _warn(f"JAX's persistent compilation cache is in {str(path)!r}, but setting "
              f"jax_persistent_cache_min_compile_time_secs failed ({type(exc).__name__}: {exc}): JAX's own threshold "
              "decides which compiles are kept.")
    return choice


#: XLA's C++ log thresholds (absl): 0 info, 1 warning, 2 error, 3 fatal. jaxlib's default is 1.
XLA_DEFAULT_MIN_LOG_LEVEL = 1
_XLA_FATAL = 3

_loads_lock = threading.Lock()
_loads_in_flight = 0


def user_chose_xla_logging(environ: Mapping[str, str] | None = None) -> bool:
    """Whether the user set XLA's C++ log level: ``TF_CPP_MIN_LOG_LEVEL`` in ``environ`` (default ``os.environ``) to
    a level other than 1 (``import jax`` sets 1 when the variable is unset), or JAX's ``jax_logging_level``
    (``JAX_LOGGING_LEVEL``) to a level other than ``NOTSET``."""
    env = os.environ if environ is None else environ
    if env.get("TF_CPP_MIN_LOG_LEVEL", "").strip() not in ("", str(XLA_DEFAULT_MIN_LOG_LEVEL)):
        return True
    try:
        level = _jax_value("jax_logging_level")
    except Exception:  # a JAX without this option
        return False
    return level not in (None, "", "NOTSET")


def _set_xla_min_log_level(level: int) -> None:
    from jax._src.lib import utils

    utils.absl_set_min_log_level(level)


@functools.lru_cache(maxsize=1)
def _can_set_xla_log_level() -> bool:
    try:
        from jax._src.lib import utils
    except ImportError:
        return False
    return hasattr(utils, "absl_set_min_log_level")


class _XlaLogsOff:
    """XLA's C++ log threshold at fatal while inside (re-entrant and thread-safe: the threshold is process-wide, and
    jaxlib's default comes back when the last one leaves)."""

    def __enter__(self) -> None:
        global _loads_in_flight
        with _loads_lock:
            _loads_in_flight += 1
            if _loads_in_flight == 1:
                _set_xla_min_log_level(_XLA_FATAL)

    def __exit__(self, *exc) -> None:
        global _loads_in_flight
        with _loads_lock:
            _loads_in_flight -= 1
            if _loads_in_flight == 0:
                _set_xla_min_log_level(XLA_DEFAULT_MIN_LOG_LEVEL)


def _quiet_loader(load):
    """``load`` (JAX's ``compilation_cache.get_executable_and_time``) run with XLA's C++ log lines off, unless the
    user chose XLA's log level (:func:`user_chose_xla_logging`)."""

    @functools.wraps(load)
    def quiet_load(*args, **kwargs):
        if user_chose_xla_logging():
            return load(*args, **kwargs)
        with _XlaLogsOff():
            return load(*args, **kwargs)

    quiet_load.kamino_quiet = True
    return quiet_load


def quiet_cache_loads() -> bool:
    """Keep XLA's log lines about a loaded cache entry off stderr (module docstring). Idempotent; returns whether
    the loads are quiet. A JAX whose internals differ (no ``jax._src.compilation_cache.get_executable_and_time``,
    or no way to set the C++ log threshold) is left as it is, and its lines stay."""
    try:
        from jax._src import compilation_cache
    except ImportError:
        return False
    load = getattr(compilation_cache, "get_executable_and_time", None)
    if load is None or not _can_set_xla_log_level():
        return False
    if not getattr(load, "kamino_quiet", False):
        compilation_cache.get_executable_and_time = _quiet_loader(load)
    return True
