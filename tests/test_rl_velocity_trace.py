"""benchmarks/rl_velocity_trace.py splits the walking test's error into the gait's sway and the speed error."""

import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))

import rl_velocity_trace


def test_split_error_of_a_swaying_walk_matches_its_closed_form():
    """A base that walks at 0.35 m/s under a 0.4 m/s command and sways sideways as 0.1 sin(2 pi 1.5 t), yaw rate 0.2:
    the sway's mean magnitude is 2 A / pi (a sine's mean absolute value over whole periods), the mean-velocity
    error is the 0.05 m/s lag, the per-step error is the mean of sqrt(0.05^2 + (A sin)^2), and the spectrum's peak
    sits at 1.5 Hz (10 s at 50 Hz: 15 whole periods after 2 s settle, so no leakage moves it)."""
    dt, amp = 0.02, 0.1
    t = np.arange(500) * dt
    lin = np.stack([np.full_like(t, 0.35), amp * np.sin(2 * np.pi * 1.5 * t), np.zeros_like(t)], -1)
    ang = np.tile([0.0, 0.0, 0.2], (500, 1))
    row = rl_velocity_trace.split_error(0.4, lin, ang, np.ones(500, bool), dt, settle=2.0)
    sway = amp * np.sin(2 * np.pi * 1.5 * t[100:])
    assert row["oscillation"] == pytest.approx(2 * amp / np.pi, rel=1e-3)  # sampled sine: 1e-3 of the integral
    assert row["mean_velocity_error"] == pytest.approx(0.05, abs=1e-9)
    assert row["per_step_error"] == pytest.approx(np.mean(np.hypot(0.05, sway)), rel=1e-12)
    assert row["sway_hz"] == pytest.approx(1.5)
    assert row["yaw_rate_mean"] == pytest.approx(0.2)
    assert row["lateral_std"] == pytest.approx(amp / np.sqrt(2), rel=1e-3)


def test_a_fallen_episode_is_reported_as_fallen_only():
    upright = np.ones(500, bool)
    upright[300:] = False
    row = rl_velocity_trace.split_error(0.4, np.zeros((500, 3)), np.zeros((500, 3)), upright, 0.02, settle=2.0)
    assert row == {"command": pytest.approx(0.4), "fell": True, "steps_up": 300}
