"""Warp's console output under kamino: quiet by default.

Warp prints a banner when it initialises and a "Module ... load on device ..." line for every kernel module it
loads (about 25 per process for kamino's Warp backend). kamino turns these off the first time it imports Warp
(``kamino.step(..., backend="warp")``, ``kamino bench``), unless the user already chose a level:

- ``KAMINO_WARP_VERBOSE=1`` in the environment keeps Warp's own default (banner and module loads);
- or set ``warp.config.log_level = warp.LOG_INFO`` (Warp 1.19+; ``warp.config.quiet = False`` before) after the
  first kamino call that uses Warp: kamino sets the level only once per process, and a level other than
  Warp's default is left as the user set it.

Warnings and errors are still printed (``warp.LOG_WARNING``).
"""

from __future__ import annotations

import os

#: environment variable that keeps Warp's own console output (banner, module loads): "1", "true" or "yes"
VERBOSE_ENV = "KAMINO_WARP_VERBOSE"

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
