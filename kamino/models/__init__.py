"""Procedural models: each function returns a validated single-world :class:`kamino.Model`."""

from kamino.models.describe import describe
from kamino.models.mechanisms import (
    chain_of_loops,
    double_pendulum,
    fourbar,
    jansen_walker,
    pendulum,
    slider_crank,
    stewart_platform,
)
from kamino.models.robots import animatronic, bdx, dr_legs, olaf
from kamino.models.scenes import box_on_plane, box_stack, incline, newtons_cradle, sphere_drop

__all__ = ["animatronic", "bdx", "box_on_plane", "box_stack", "chain_of_loops", "describe", "double_pendulum",
           "dr_legs", "fourbar", "incline", "jansen_walker", "newtons_cradle", "olaf", "pendulum", "slider_crank",
           "sphere_drop", "stewart_platform"]
