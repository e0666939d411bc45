"""The README's picture, ``docs/images/kamino_robot.gif``: ``kamino.models.dr_legs()`` squatting.

    python docs/images/make_readme_gif.py [--out docs/images/kamino_robot.gif] [--seconds 2.5]

How the GIF was made (all of it in this script, nothing edited by hand):

- the robot: ``kamino.models.dr_legs()``, the biped with parallel legs (31 bodies, 12 actuators, 6 loops: a
  four-bar at each knee and ankle pitch, a spatial eight-revolute loop at each ankle roll; docs/robots.md), standing
  on the ground in its reference pose under its implicit PD actuators (zero position targets hold that pose, as in
  tests/test_robots.py);
- the motion: a squat. For a pelvis lowered by ``d``, :func:`kamino.forward_kinematics` (the pelvis held at its
  reference pose) and a few Newton steps give the hip pitch, knee drive and ankle pitch drive targets that keep
  each foot flat and under the hip (:func:`squat_targets`, on a table of depths); the targets follow
  ``d(t) = DEPTH (1 - cos 2 pi f t) / 2`` on both legs, and the hips yaw by ``YAW sin 2 pi f t`` so the pelvis
  turns on its planted feet and the view is not flat. The other actuators hold zero. Every loop closes through the
  simulation (the targets are on the actuated joints only);
- the simulation: the JAX backend (``kamino.rollout``), float32, ``SolverConfig(dt=0.005, tolerance=1e-4)`` (the
  standing tests' tolerance), ``--seconds`` of simulated time (2.5 s: two squats, so that the GIF loops smoothly;
  about 10-30 s on a CPU, jit compilation included);
- the picture: ``kamino.viz.gif(..., renderer="mujoco")``, MuJoCo's renderer through Mesa's EGL (``MUJOCO_GL=egl``,
  set here before ``mujoco`` is imported), 480 x 360 at 25 frames per second; loop-closing joints are the red
  markers, other joints dark ones (the dark dot that the pelvis leaves behind is the world side of its FREE
  joint). Where MuJoCo cannot open an OpenGL context the script falls back to ``renderer="matplotlib"`` with a
  warning. The frames are drawn at 600 x 450 and cropped to 480 x 360 about the robot (a closer view than
  ``kamino.viz``'s framing of the whole motion), then Pillow re-saves the GIF with one palette for all frames
  (:func:`finish`), which keeps it well under 1.5 MB.
"""

from __future__ import annotations

import argparse
import os
import pathlib
import sys
import time
import warnings

os.environ.setdefault("MUJOCO_GL", "egl")  # before mujoco is first imported (kamino.viz imports it lazily)

import jax
import jax.numpy as jnp
import numpy as np

HERE = pathlib.Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parents[1]))

import kamino  # noqa: E402
from kamino import viz  # noqa: E402
from kamino.hostmath import quat_to_matrix  # noqa: E402

DT = 0.005
#: squat depth [m] (how far the pelvis goes down), frequency [Hz], hip yaw amplitude [rad]
DEPTH, FREQUENCY, YAW = 0.05, 0.8, 0.25
WIDTH, HEIGHT, FPS = 480, 360, 25
#: rendered ZOOM times larger, then cropped to WIDTH x HEIGHT about the robot: kamino.viz frames a sphere holding the
#: whole motion, which leaves room around a tall robot
ZOOM = 1.25
#: the view from the front right, 40 degrees off the side view (the knee and ankle four-bars are in the sagittal plane)
AZIMUTH, ELEVATION = 140.0, -8.0
MAX_BYTES = 1_500_000


def _pitch(R: np.ndarray) -> float:
    """The rotation angle about y of a rotation ``R`` that is (close to) one about y."""
    return float(np.arctan2(R[0, 2], R[0, 0]))


def squat_targets(model: kamino.Model, depths: np.ndarray) -> np.ndarray:
    """``[len(depths), 3]``: (hip pitch, knee drive, ankle pitch drive) [rad] that lower the pelvis by each depth
    [m] with the foot flat and right under its reference place (forward kinematics, the pelvis held; Newton on
    finite differences; the legs are mirror images, so the left leg's solution is both legs')."""
    names = list(model.actuator_names)
    cols = [names.index(f"l_{j}") for j in ("hip_pitch", "knee_drive", "ankle_pitch_drive")]
    foot = list(model.body_names).index("l_foot")
    ref = np.asarray(kamino.forward_kinematics(model).body_q)
    base = ref[list(model.body_names).index("pelvis")]
    R0 = quat_to_matrix(ref[foot, 3:])

    def foot_error(x: np.ndarray, depth: float) -> np.ndarray:
        q = np.zeros(model.num_actuators)
        q[cols] = x
        bq = np.asarray(kamino.forward_kinematics(model, actuated_positions=q, base_pose=base).body_q)
        d = bq[foot, :3] - ref[foot, :3]
        return np.array([_pitch(quat_to_matrix(bq[foot, 3:]) @ R0.T), d[0], d[2] - depth])

    out, x = [], np.zeros(3)
    for depth in depths:
        for _ in range(8):
            e = foot_error(x, depth)
            if np.max(np.abs(e)) < 1e-5:
                break
            J = np.stack([(foot_error(x + h, depth) - e) / 1e-3 for h in 1e-3 * np.eye(3)], axis=1)
            x = x - np.linalg.solve(J, e)
        out.append(x.copy())
    return np.array(out)


def controls(model: kamino.Model, seconds: float) -> kamino.Control:
    """Position targets ``[steps, num_dofs]`` after each step: the squat on both legs and the hip yaw."""
    steps = round(seconds / DT)
    t = DT * np.arange(1, steps + 1)
    table_depths = np.linspace(0.0, DEPTH, 11)
    table = squat_targets(model, table_depths)
    depth = DEPTH * 0.5 * (1.0 - np.cos(2 * np.pi * FREQUENCY * t))
    legs = np.stack([np.interp(depth, table_depths, table[:, k]) for k in range(3)], axis=1)
    yaw = YAW * np.sin(2 * np.pi * FREQUENCY * t)
    targets = np.zeros((steps, model.num_dofs), np.float32)
    names = list(model.actuator_names)
    for side in "lr":
        for k, joint in enumerate(("hip_pitch", "knee_drive", "ankle_pitch_drive")):
            targets[:, model.actuator_dof[names.index(f"{side}_{joint}")]] = legs[:, k]
        targets[:, model.actuator_dof[names.index(f"{side}_hip_yaw")]] = yaw
    return kamino.Control(position_target=jnp.asarray(targets))


def finish(path: pathlib.Path, fps: float) -> None:
    """Crop the GIF's frames to ``WIDTH x HEIGHT`` about the robot (the box of the coloured pixels of every frame:
    the sky and the floor are grey) and re-save them with one adaptive palette for every frame (fewer bytes than
    one per frame)."""
    from PIL import Image, ImageSequence

    with Image.open(path) as im:
        frames = [f.convert("RGB") for f in ImageSequence.Iterator(im)]
    rgb = np.stack([np.asarray(f, np.int16) for f in frames])
    ys, xs = np.nonzero(np.any(rgb.max(-1) - rgb.min(-1) > 60, axis=0))
    w, h = frames[0].size
    cx, cy = ((xs.min() + xs.max()) // 2, (ys.min() + ys.max()) // 2) if len(xs) else (w // 2, h // 2)
    left = int(np.clip(cx - WIDTH // 2, 0, w - WIDTH))
    top = int(np.clip(cy - HEIGHT // 2, 0, h - HEIGHT))
    frames = [f.crop((left, top, left + WIDTH, top + HEIGHT)) for f in frames]
    strip = Image.new("RGB", (frames[0].width, frames[0].height * len(frames[::4])))
    for i, f in enumerate(frames[::4]):  # the palette from every fourth frame
        strip.paste(f, (0, i * f.height))
    palette = strip.quantize(colors=128, method=Image.Quantize.MEDIANCUT)
    out = [f.quantize(palette=palette, dither=Image.Dither.NONE) for f in frames]
    out[0].save(path, save_all=True, append_images=out[1:], duration=round(1000.0 / fps), loop=0, optimize=True)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", type=pathlib.Path, default=HERE / "kamino_robot.gif")
    p.add_argument("--seconds", type=float, default=2.5, help="simulated time [s]")
    args = p.parse_args(argv)

    model = kamino.models.dr_legs()
    state = kamino.init_state(model, np.float32)
    cfg = kamino.SolverConfig(dt=DT, tolerance=1e-4)
    ctrl = controls(model, args.seconds)
    t0 = time.perf_counter()
    traj = jax.block_until_ready(kamino.rollout(model, state, ctrl, config=cfg))
    closure = float(np.max(np.asarray(kamino.metrics(model, traj)["constraint_violation"])))
    pelvis_z = np.asarray(traj.body_q)[:, list(model.body_names).index("pelvis"), 2]
    print(f"simulated {args.seconds:g} s of dr_legs in {time.perf_counter() - t0:.1f} s: worst loop closure "
          f"{closure:.2e}, pelvis height {pelvis_z.min():.3f}..{pelvis_z.max():.3f} m")

    options = dict(fps=FPS, width=round(ZOOM * WIDTH), height=round(ZOOM * HEIGHT), azimuth=AZIMUTH,
                   elevation=ELEVATION, show_contacts=False)
    try:
        used = viz.gif(model, traj, args.out, renderer="mujoco", **options)
    except Exception as e:  # no OpenGL context here (RuntimeError; a GL platform that fails at import: others)
        warnings.warn(f"MuJoCo cannot draw here ({e}); drawing with matplotlib", RuntimeWarning, stacklevel=1)
        used = viz.gif(model, traj, args.out, renderer="matplotlib", **options)
    finish(args.out, FPS)
    size = args.out.stat().st_size
    print(f"wrote {args.out} ({used}, {WIDTH}x{HEIGHT}, {size / 1e6:.2f} MB)")
    if size > MAX_BYTES:
        print(f"warning: larger than {MAX_BYTES / 1e6:g} MB", file=sys.stderr)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
