"""Environments on Brax's API (docs/envs.md): ``KaminoEnv``, the registered tasks, and trained policies.

Importing this package registers the tasks with ``brax.envs.register_environment`` (``brax.envs.get_environment``
then builds them by name). Training and evaluation: :mod:`kamino.envs.train` (``kamino train``) and
:mod:`kamino.envs.evaluate` (``kamino eval``); :func:`load_policy` loads a policy that ships with kamino. Needs the
``rl`` extra (``pip install "kamino[rl]"``: brax).
"""

from __future__ import annotations

try:
    import brax.envs as _brax_envs
except ImportError as exc:  # pragma: no cover - depends on the installation
    raise ImportError("kamino.envs needs brax: install the rl extra (pip install -e \".[rl]\")") from exc

from kamino.envs import brax_compat
from kamino.envs.base import BACKENDS, KaminoEnv
from kamino.envs.fourbar_track import FourbarTrack
from kamino.envs.joystick import BdxJoystick, DrLegsJoystick, Joystick
from kamino.envs.olaf_show import OlafShow
from kamino.envs.policy import Policy, load_policy, shipped_policies
from kamino.envs.randomization import randomize
from kamino.envs.rough import DrLegsRough
from kamino.envs.system import EnvSystem

BACKENDS: tuple[str, ...]  # the imported tuple, declared here for its docstring in the API reference
"""The simulator backends an environment runs on (``backend=``: ``"jax"`` or ``"warp"``)."""

TASKS: dict[str, type[KaminoEnv]] = {"fourbar_track": FourbarTrack, "dr_legs_joystick": DrLegsJoystick,
                                     "bdx_joystick": BdxJoystick, "olaf_show": OlafShow, "dr_legs_rough": DrLegsRough}
"""Task name -> environment class (each also registered with brax.envs)."""

brax_compat.install()
for _name, _cls in TASKS.items():
    _brax_envs.register_environment(_name, _cls)


def make(task: str, **kwargs) -> KaminoEnv:
    """The environment ``task`` (a key of :data:`TASKS`) built with ``kwargs``."""
    if task not in TASKS:
        raise ValueError(f"make: unknown task {task!r} (the task argument); choose one of {sorted(TASKS)}")
    return TASKS[task](**kwargs)


__all__ = ["BACKENDS", "TASKS", "BdxJoystick", "DrLegsJoystick", "DrLegsRough", "EnvSystem", "FourbarTrack", "Joystick",
           "KaminoEnv", "OlafShow", "Policy", "load_policy", "make", "randomize", "shipped_policies"]
