"""benchmarks/lip_sway.py: the pendulum's periodic gait against its closed form (docs/envs.md, "The lateral sway")."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np
import pytest

_spec = importlib.util.spec_from_file_location("lip_sway", Path(__file__).parents[1] / "benchmarks" / "lip_sway.py")
lip_sway = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(lip_sway)


@pytest.mark.parametrize("frequency", [1.5, 2.5])
def test_single_support_gait_matches_the_cosh_solution(frequency):
    """Without double support the periodic orbit is ``y = d - c cosh(omega t)``, ``c = d / cosh(omega T / 2)``, so
    ``v_y = -c omega sinh(omega t)``: peak ``d omega tanh(omega T / 2)``, RMS ``c omega sqrt((sinh(omega T) /
    (omega T) - 1) / 2)``. The shooting solve with 4000 semi-implicit Euler steps must match both to 0.1 % (its error
    is O(dt omega) = 2e-4 relative; 0.1 % keeps a margin and is far below the 2 % the docs' double-support claim
    rests on)."""
    d, z = 0.1, 0.539
    omega = np.sqrt(lip_sway.G / z)
    step = 1.0 / (2.0 * frequency)
    c = d / np.cosh(0.5 * omega * step)
    peak = d * omega * np.tanh(0.5 * omega * step)
    rms = c * omega * np.sqrt(0.5 * (np.sinh(omega * step) / (omega * step) - 1.0))
    r = lip_sway.lateral_sway(frequency, d, z)
    assert r["peak"] == pytest.approx(peak, rel=1e-3)
    assert r["rms"] == pytest.approx(rms, rel=1e-3)


def test_double_support_lowers_the_sway_a_little_and_bad_fractions_are_refused():
    """Moving the pressure across during part of each step can only shorten the single support, so the sway falls
    with the fraction (docs: 2 % at 20 %, 8 % at 40 %, 1.5 Hz, d = 0.1 m); a fraction outside [0, 1) is refused."""
    rms = [lip_sway.lateral_sway(1.5, 0.1, 0.539, beta)["rms"] for beta in (0.0, 0.2, 0.4)]
    assert rms[0] > rms[1] > rms[2] > 0.9 * rms[0]
    with pytest.raises(ValueError, match="double_support"):
        lip_sway.lateral_sway(1.5, 0.1, 0.539, 1.0)
