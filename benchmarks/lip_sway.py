"""The lateral sway that a walking gait implies, from the linear inverted pendulum (docs/envs.md, "The lateral sway").

``python benchmarks/lip_sway.py [--com-height 0.539] [--half-widths 0.1 0.055] [--frequencies 1 1.5 2 2.5 3]
[--double-support 0 0.2 0.4]``

Model (Kajita's linear inverted pendulum, lateral plane): the CoM at constant height ``z`` moves as
``y'' = omega^2 (y - p)``, ``omega = sqrt(g / z)``, about the centre of pressure ``p``. A gait clock of ``f`` Hz
makes steps of ``T = 1 / (2 f)`` s: single support on one foot, ``p = +d`` (``d``: half the lateral distance between
the feet's centres of pressure), for ``(1 - beta) T``, then a double support in which ``p`` moves linearly to ``-d``
over ``beta T``; the next step mirrors it. The periodic gait is the orbit with ``y(T) = -y(0)``, ``v(T) = -v(0)``,
found by shooting (the map is affine). Without double support it is ``y = d - c cosh(omega t)``, ``c = d /
cosh(omega T / 2)``, ``t`` from mid-step (tests/test_lip_sway.py checks the two agree). Prints the peak, root mean
square and mean absolute ``v_y`` over a step: the sway's share of the per-step velocity error that the walking test
averages (``|cmd_xy - v_xy|`` is at least ``|v_y|`` under a forward command).
"""

from __future__ import annotations

import argparse

import numpy as np

G = 9.81


def lateral_sway(frequency: float, half_width: float, com_height: float, double_support: float = 0.0,
                 samples: int = 4000) -> dict[str, float]:
    """Peak, RMS and mean ``|v_y|`` [m/s] over one step of the periodic gait above (``frequency`` [Hz], ``half_width``
    d [m], ``com_height`` z [m], ``double_support`` beta in [0, 1)); semi-implicit Euler with ``samples`` steps."""
    if not 0.0 <= double_support < 1.0:
        raise ValueError(f"lateral_sway: double_support must be in [0, 1), got {double_support}")
    w2 = G / com_height
    step = 1.0 / (2.0 * frequency)
    dt = step / samples
    t = (np.arange(samples) + 0.5) * dt
    single = (1.0 - double_support) * step
    p = np.where(t < single, half_width, half_width - 2.0 * half_width * (t - single) / max(double_support * step, dt))

    def shoot(y: float, v: float) -> tuple[float, float, np.ndarray]:
        vs = np.empty(samples)
        for k in range(samples):
            v += w2 * (y - p[k]) * dt
            y += v * dt
            vs[k] = v
        return y, v, vs

    # the end state is affine in the start state: solve (y_T, v_T) = -(y_0, v_0) from three shots
    base = np.array(shoot(0.0, 0.0)[:2])
    jac = np.column_stack([np.array(shoot(1.0, 0.0)[:2]) - base, np.array(shoot(0.0, 1.0)[:2]) - base])
    y0, v0 = np.linalg.solve(jac + np.eye(2), -base)
    v = shoot(y0, v0)[2]
    return {"peak": float(np.abs(v).max()), "rms": float(np.sqrt(np.mean(v**2))), "mean_abs": float(np.mean(np.abs(v)))}


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--com-height", type=float, default=0.539, help="CoM height [m] (dr_legs standing: 0.539)")
    p.add_argument("--half-widths", type=float, nargs="+", default=[0.1, 0.055],
                   help="half the lateral distance between the feet's centres of pressure [m] (dr_legs: 0.1 at the "
                        "feet's centres, 0.055 at their inner edges)")
    p.add_argument("--frequencies", type=float, nargs="+", default=[1.0, 1.5, 2.0, 2.5, 3.0], help="gait clock [Hz]")
    p.add_argument("--double-support", type=float, nargs="+", default=[0.0],
                   help="fractions of each step in double support (default: 0, the clock's half-cycle swings)")
    args = p.parse_args(argv)
    print("| gait clock | step | d | double support | v_y peak | v_y RMS | mean abs(v_y) |")
    print("|---|---|---|---|---|---|---|")
    for f in args.frequencies:
        for d in args.half_widths:
            for beta in args.double_support:
                r = lateral_sway(f, d, args.com_height, beta)
                sway = (f"{r[k]:.3f}" for k in ("peak", "rms", "mean_abs"))
                cells = [f"{f:g} Hz", f"{1 / (2 * f):.3f} s", f"{d:g} m", f"{beta:g}", *sway]
                print("| " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main()
