"""Procedural models: each function returns a validated single-world :class:`kamino.Model`."""

from kamino.models.mechanisms import chain_of_loops, double_pendulum, fourbar, pendulum, slider_crank

__all__ = ["chain_of_loops", "double_pendulum", "fourbar", "pendulum", "slider_crank"]
