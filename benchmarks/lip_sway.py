"""The lateral sway that a walking gait implies, from the linear inverted pendulum (docs/envs.md, "The lateral sway").

``python benchmarks/lip_sway.py [--com-height 0.539] [--half-widths 0.1 0.055] [--frequencies 1 1.5 2 2.5 3]``

Model (Kajita's linear inverted pendulum, lateral plane): the CoM at constant height ``z`` moves as
``y'' = omega^2 (y - p)``, ``omega = sqrt(g / z)``, about the centre of pressure ``p`` of the stance foot. A gait
clock of ``f`` Hz with alternating single support (each foot swings half the cycle: ``swing_heights``) makes steps
of ``T = 1 / (2 f)`` s with ``p = +-d`` (``d``: half the lateral distance between the feet's centres of pressure).
The periodic solution in a step, time ``t`` from its middle, is ``y = d - c cosh(omega t)`` with ``c = d /
cosh(omega T / 2)`` (the CoM crosses the midline at each change of support), so ``v_y = -c omega sinh(omega t)``.
Prints, per frequency and half-width, the peak, root mean square and mean absolute ``v_y`` over a step: the sway's
share of the per-step velocity error that the walking test averages (``|cmd_xy - v_xy|`` is at least ``|v_y|``
under a forward command).
"""

from __future__ import annotations

import argparse

import numpy as np

G = 9.81


def lateral_sway(frequency: float, half_width: float, com_height: float, samples: int = 4001) -> dict[str, float]:
    """Peak, RMS and mean ``|v_y|`` [m/s] of the periodic LIP gait above (``frequency`` [Hz], ``half_width`` d [m],
    ``com_height`` z [m])."""
    omega = np.sqrt(G / com_height)
    step = 1.0 / (2.0 * frequency)
    c = half_width / np.cosh(0.5 * omega * step)
    t = np.linspace(-0.5 * step, 0.5 * step, samples)
    v = -c * omega * np.sinh(omega * t)
    return {"peak": float(np.abs(v).max()), "rms": float(np.sqrt(np.mean(v**2))), "mean_abs": float(np.mean(np.abs(v)))}


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--com-height", type=float, default=0.539, help="CoM height [m] (dr_legs standing: 0.539)")
    p.add_argument("--half-widths", type=float, nargs="+", default=[0.1, 0.055],
                   help="half the lateral distance between the feet's centres of pressure [m] (dr_legs: 0.1 at the "
                        "feet's centres, 0.055 at their inner edges)")
    p.add_argument("--frequencies", type=float, nargs="+", default=[1.0, 1.5, 2.0, 2.5, 3.0], help="gait clock [Hz]")
    args = p.parse_args(argv)
    print("| gait clock | step | d | v_y peak | v_y RMS | mean abs(v_y) |")
    print("|---|---|---|---|---|---|")
    for f in args.frequencies:
        for d in args.half_widths:
            r = lateral_sway(f, d, args.com_height)
            sway = (f"{r[k]:.3f}" for k in ("peak", "rms", "mean_abs"))
            cells = [f"{f:g} Hz", f"{1 / (2 * f):.3f} s", f"{d:g} m", *sway]
            print("| " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main()
