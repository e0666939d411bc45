"""The planar ladder of ``K`` parallelogram loops as MJCF: ``kamino/bench/scenes/ladder8.xml`` and ``ladder32.xml``.

Each loop is closed by a ``<connect>`` equality (3 rows); a motor on the first hinge gives the benchmark drive its
actuator. ``python -m kamino.bench.ladder_mjcf K [--out DIR]`` writes ``ladderK.xml``; the shipped scenes are
``ladder_mjcf(8)`` and ``ladder_mjcf(32)`` byte for byte.
"""

from __future__ import annotations

import argparse
import pathlib

import numpy as np

#: a rail's vector from its hinge to its free end: 0.1 m at 30 degrees from the downward vertical, in the x-z plane
RAIL = 0.1 * np.array([np.sin(np.pi / 6), 0.0, -np.cos(np.pi / 6)])


def _rail(name: str, pos: str) -> str:
    """The opening tag and capsule of a 0.2 kg rail body hinged about y at ``pos`` (its ``</body>`` is the caller's)."""
    return (f'<body name="{name}" pos="{pos}"><joint name="j{name}" type="hinge" axis="0 1 0"/>'
            f'<geom type="capsule" fromto="0 0 0 {RAIL[0]:.6f} 0 {RAIL[2]:.6f}" size="0.005" mass="0.2"/>')


def _rungs(k: int, num_loops: int) -> str:
    """Loops ``k..num_loops``: rail ``A{k}`` carrying rung ``R{k}`` (which carries the next loops) and rail ``B{k}``."""
    if k > num_loops:
        return ""
    inner = _rungs(k + 1, num_loops)
    return (_rail(f"A{k}", "0 0 0")
            + f'<body name="R{k}" pos="{RAIL[0]:.6f} 0 {RAIL[2]:.6f}"><joint name="jR{k}" type="hinge" axis="0 1 0"/>'
            f'<geom type="capsule" fromto="0 0 0 0.2 0 0" size="0.005" mass="0.5"/>{inner}</body></body>'
            + _rail(f"B{k}", "0.2 0 0") + "</body>")


def ladder_mjcf(num_loops: int) -> str:
    """The MJCF text of the ladder of ``num_loops`` >= 1 loops (model name ``ladder{num_loops}``)."""
    if int(num_loops) != num_loops or num_loops < 1:
        raise ValueError(f"ladder_mjcf: the number of loops must be a positive integer, got {num_loops!r}")
    k = int(num_loops)
    eqs = "".join(f'<connect body1="B{i}" body2="R{i}" anchor="{RAIL[0]:.6f} 0 {RAIL[2]:.6f}"/>'
                  for i in range(1, k + 1))
    return (f'<mujoco model="ladder{k}"><option timestep="0.0025"/><default><geom contype="0" conaffinity="0"/>'
            f'</default><worldbody><body name="R0" pos="0 0 1"><geom type="capsule" fromto="0 0 0 0.2 0 0" '
            f'size="0.005" mass="0.5"/>{_rungs(1, k)}</body></worldbody><equality>{eqs}</equality>'
            f'<actuator><motor joint="jA1" gear="1"/></actuator></mujoco>')


def main(argv: list[str] | None = None, prog: str | None = None) -> int:
    p = argparse.ArgumentParser(prog=prog, description="Write ladderK.xml, the planar ladder of K parallelogram loops.")
    p.add_argument("loops", type=int, metavar="K", help="number of loops, >= 1")
    p.add_argument("--out", type=pathlib.Path, default=pathlib.Path("."), help="folder to write into (default: .)")
    args = p.parse_args(argv)
    if args.loops < 1:
        p.error(f"K must be >= 1, got {args.loops}")
    path = args.out / f"ladder{args.loops}.xml"
    path.write_text(ladder_mjcf(args.loops))
    print(path)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
