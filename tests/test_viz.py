"""``kamino.viz``: the HTML page embeds exactly the trajectory's world, the GIFs have the frames they claim.

The page is checked here through its text: its embedded JSON (body poses per frame, geoms, loop-closing joints,
contacts) and the libraries it carries inline (tests/test_viewer_browser.py opens it in a headless browser, where
one is installed); the GIFs through Pillow (frame count, size). The MuJoCo renderer
runs in a subprocess with ``MUJOCO_GL=egl`` (the variable is read when ``mujoco`` is imported) and the test is
skipped where no OpenGL context can be made. One short four-bar rollout; the other trajectories are built by hand.
"""

from __future__ import annotations

import dataclasses
import html as html_lib
import importlib.resources
import json
import os
import re
import subprocess
import sys
import textwrap

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import kamino
from kamino import viz
from kamino.model import count_loops
from kamino.viz._scene import frame_steps

jax.config.update("jax_enable_x64", True)

DT = 1.0 / 240.0


# ------------------------------------------------------------------------------------------------ helpers


def _page_data(text: str) -> dict:
    """The JSON the page embeds."""
    match = re.search(r'<script type="application/json" id="kamino-data">(.*?)</script>', text, re.S)
    assert match, "no embedded data"
    return json.loads(match.group(1))


def _segment(model: kamino.Model, entity: str, world: int) -> slice:
    start = int(getattr(model, f"world_{entity}_start")[world])
    return slice(start, start + int(getattr(model, f"world_{entity}_count")[world]))


def _synthetic(model: kamino.Model, num_steps: int, seed: int = 0) -> kamino.State:
    """A hand-made trajectory (no compilation): every body moves and turns each step, and every world's first
    contact slots hold points (the others are empty), as a rollout's State with a leading time axis."""
    rng = np.random.default_rng(seed)
    state = kamino.init_state(model)
    traj = jax.tree.map(lambda x: jnp.stack([x] * num_steps), state)
    q = np.repeat(np.asarray(model.body_q0)[None], num_steps, axis=0)
    q[..., 0] += 0.05 * np.arange(num_steps)[:, None]
    quat = rng.normal(size=(num_steps, model.num_bodies, 4))
    q[..., 3:] = quat / np.linalg.norm(quat, axis=-1, keepdims=True)
    time = DT * (1 + np.arange(num_steps))[:, None] * np.ones(model.num_worlds)
    pair = np.full((num_steps, model.num_contacts), -1, np.int32)
    pos = np.zeros((num_steps, model.num_contacts, 3))
    for w in range(model.num_worlds):
        start = int(np.sum(model.world_contact_capacity[:w]))
        for k in range(num_steps):
            n = min(k % 3 + 1, int(model.world_contact_capacity[w]))
            pair[k, start:start + n] = 0
            pos[k, start:start + n] = rng.normal(size=(n, 3))
    contacts = dataclasses.replace(traj.contacts, pair=jnp.asarray(pair), pos=jnp.asarray(pos))
    return traj.replace(body_q=jnp.asarray(q), time=jnp.asarray(time), contacts=contacts)


@pytest.fixture(scope="module")
def fourbar_run():
    """Three four-bar worlds, the middle one released from another crank angle (a batch whose worlds differ)."""
    model = kamino.replicate(kamino.models.fourbar(), 3)
    state = kamino.init_state(model)
    other = kamino.init_state(kamino.models.fourbar(crank_angle=-0.6))
    seg = _segment(model, "body", 1)
    state = state.replace(body_q=state.body_q.at[seg].set(other.body_q))
    traj = kamino.rollout(model, state, num_steps=24, config=kamino.SolverConfig(dt=DT), backend="warp")
    return model, traj


@pytest.fixture(scope="module")
def mixed():
    """A heterogeneous batch: a four-bar (no geoms) and a box stack (geoms, a plane, contacts)."""
    model = kamino.concat([kamino.models.fourbar(), kamino.models.box_stack(2)])
    return model, _synthetic(model, 5)


# ------------------------------------------------------------------------------------------------ HTML


@pytest.mark.parametrize("world", [1, -1])
def test_html_embeds_the_worlds_trajectory_and_loop_joints(fourbar_run, world, tmp_path):
    model, traj = fourbar_run
    w = world % model.num_worlds
    path = tmp_path / "fourbar.html"
    text = viz.html(model, traj, path, world=world)
    assert path.read_text(encoding="utf-8") == text
    data = _page_data(text)
    seg = _segment(model, "body", w)
    frames = data["frames"]
    np.testing.assert_array_equal(np.asarray(frames["body_q"]), np.asarray(traj.body_q)[:, seg])
    np.testing.assert_array_equal(frames["time"], np.asarray(traj.time)[:, w])
    assert frames["step"] == list(range(24))
    assert data["world"] == w and data["num_worlds"] == 3
    assert [b["name"] for b in data["bodies"]] == list(model.body_names[seg])
    # the four-bar has no geoms: every body is drawn by its stand-in, with rods to its joints' anchors
    assert data["geoms"] == [] and not any(b["has_geom"] for b in data["bodies"])
    assert sum(len(b["links"]) for b in data["bodies"]) == 2 * 5 - 1  # five joints, one of them to the world
    # loop-closing joints: exactly the one the MJCF export's spanning tree cuts
    assert data["loop_joints"] == ["rocker_ground"]
    assert [j["name"] for j in data["joints"] if j["loop"]] == ["rocker_ground"]
    assert sum(j["loop"] for j in data["joints"]) == count_loops(model, w) == 1
    js = _segment(model, "joint", w)
    np.testing.assert_array_equal([j["anchor_parent"] for j in data["joints"]], model.joint_anchor_B[js])
    np.testing.assert_array_equal([j["anchor_child"] for j in data["joints"]], model.joint_anchor_F[js])
    assert [j["parent"] for j in data["joints"]] == [-1, 0, 1, 2, 3]
    assert [j["child"] for j in data["joints"]] == [0, 1, 2, 3, 0]


def test_html_worlds_differ_in_a_batch(fourbar_run):
    model, traj = fourbar_run
    first, second = (np.asarray(_page_data(viz.html(model, traj, world=w))["frames"]["body_q"]) for w in (0, 1))
    assert not np.allclose(first, second)  # world 1 starts from another crank angle


def _inline_script(text: str, element_id: str) -> str:
    """The text of the page's ``<script type="text/plain">`` element ``element_id`` (a library it carries)."""
    match = re.search(rf'<script type="text/plain" id="{element_id}">(.*?)</script>', text, re.S)
    assert match, f"no {element_id} element"
    return match.group(1)


def test_html_carries_three_inline_and_needs_no_network(fourbar_run):
    model, traj = fourbar_run
    text = viz.html(model, traj, title="four-bar <&> test")
    vendor = importlib.resources.files("kamino.viz").joinpath("vendor")
    # the libraries, byte for byte as vendored: three.js r170's minified module build and its OrbitControls
    three = _inline_script(text, "kamino-three")
    assert three == vendor.joinpath("three.module.min.js").read_text(encoding="utf-8")
    assert 'const t="170"' in three[:400] and "SPDX-License-Identifier: MIT" in three[:400]  # three.REVISION
    controls = _inline_script(text, "kamino-orbit-controls")
    assert controls == vendor.joinpath("OrbitControls.js").read_text(encoding="utf-8")
    assert "export { OrbitControls };" in controls and "} from 'three';" in controls
    # each becomes a module at a blob: URL, named by the import map the page builds before its module runs
    classic = re.search(r"<script>(.*?)</script>", text, re.S).group(1)
    assert 'map.type = "importmap"' in classic
    for specifier, element in (("three", "kamino-three"),
                               ("three/addons/controls/OrbitControls.js", "kamino-orbit-controls")):
        assert f'"{specifier}": moduleUrl("{element}")' in classic
    assert text.index("<script>") < text.index('<script type="module">')
    module = re.search(r'<script type="module">(.*?)</script>', text, re.S).group(1)
    assert 'from "three"' in module and 'from "three/addons/controls/OrbitControls.js"' in module
    # self-contained: no script src, stylesheet, fetch or dynamic import, and no URL outside the libraries' text
    page = text.replace(three, "").replace(controls, "")
    assert not re.search(r"<script[^>]*\ssrc=|<link|fetch\(|import\(|https?://", page)
    # the size: the libraries, 0.72 MB, and the data; the rest is the viewer's 10 kB
    assert len(three) + len(controls) < 750_000
    data = re.search(r'<script type="application/json" id="kamino-data">(.*?)</script>', text, re.S).group(1)
    assert len(page) - len(data) < 15_000
    assert f"<title>{html_lib.escape('four-bar <&> test')}</title>" in text
    assert _page_data(text)["title"] == "four-bar <&> test"
    for element in ("slider", "play", "speed"):
        assert f'id="{element}"' in text
    assert "__KAMINO_" not in text  # every placeholder filled


def test_html_refuses_a_library_that_would_end_its_element(fourbar_run, monkeypatch):
    from kamino.viz import _html

    model, traj = fourbar_run
    real = _html._package_text
    monkeypatch.setattr(_html, "_package_text",
                        lambda name: 'x = "</script>";' if name == _html.VENDOR["__KAMINO_THREE__"] else real(name))
    _html._vendor_scripts.cache_clear()
    try:
        with pytest.raises(RuntimeError, match=r"three\.module\.min\.js contains '</script' or '<!--'"):
            viz.html(model, traj)
    finally:
        _html._vendor_scripts.cache_clear()


def test_html_geoms_contacts_of_a_heterogeneous_batch(mixed):
    model, traj = mixed
    data = _page_data(viz.html(model, traj, world=1))
    gs = _segment(model, "geom", 1)
    geoms = data["geoms"]
    assert [g["name"] for g in geoms] == list(model.geom_names[gs])
    assert [g["type"] for g in geoms] == ["plane", "box", "box"]
    assert [g["body"] for g in geoms] == [-1, 0, 1]  # world-local body indices
    for key, field in (("size", "geom_size"), ("pos", "geom_pos"), ("quat", "geom_quat")):
        np.testing.assert_array_equal([g[key] for g in geoms], getattr(model, field)[gs])
    assert all(b["has_geom"] for b in data["bodies"]) and data["joints"] == [] and data["loop_joints"] == []
    np.testing.assert_array_equal(data["frames"]["body_q"], np.asarray(traj.body_q)[:, _segment(model, "body", 1)])
    # contacts: the world's slots that hold a contact (pair >= 0), per frame
    start, cap = int(model.world_contact_capacity[0]), int(model.world_contact_capacity[1])
    pair, pos = np.asarray(traj.contacts.pair), np.asarray(traj.contacts.pos)
    for k, points in enumerate(data["frames"]["contacts"]):
        active = pair[k, start:start + cap] >= 0
        np.testing.assert_array_equal(np.asarray(points).reshape(-1, 3), pos[k, start:start + cap][active])
    assert [len(c) for c in data["frames"]["contacts"]] == [1, 2, 3, 1, 2]
    quiet = _page_data(viz.html(model, traj, world=1, show_contacts=False, show_joints=False))
    assert "contacts" not in quiet["frames"] and not quiet["show_joints"]


def test_html_fps_keeps_one_frame_per_period(fourbar_run):
    model, traj = fourbar_run
    data = _page_data(viz.html(model, traj, world=2, fps=60))
    time = np.asarray(traj.time)[:, 2]
    steps = data["frames"]["step"]
    # the last step at or before each 1/60 s from the first frame: every 4th step at dt = 1/240
    assert steps == list(range(0, 24, 4))
    np.testing.assert_array_equal(data["frames"]["time"], time[steps])
    body_q = np.asarray(traj.body_q)[steps][:, _segment(model, "body", 2)]
    np.testing.assert_array_equal(data["frames"]["body_q"], body_q)


def test_html_escapes_what_would_end_its_script():
    b = kamino.ModelBuilder()
    body = b.add_body(1.0, np.eye(3) * 1e-2, pos=(0, 0, 1), name="</script><!--x")
    b.add_joint_at(kamino.JointType.REVOLUTE, -1, body, anchor=(0, 0, 1.2), axis=(0, 1, 0), name="pin")
    model = b.finalize()
    text = viz.html(model, _synthetic(model, 2))
    assert "</script><!--x" not in text
    assert _page_data(text)["bodies"][0]["name"] == "</script><!--x"


def test_clear_errors(fourbar_run, mixed, tmp_path):
    model, traj = fourbar_run
    for world in (3, -4):
        with pytest.raises(ValueError, match=r"world -?\d is out of range for a model of 3 world\(s\)"):
            viz.html(model, traj, world=world)
    with pytest.raises(TypeError, match="world must be an integer"):
        viz.html(model, traj, world=1.0)
    one = jax.tree.map(lambda x: x[0], traj)
    with pytest.raises(ValueError, match="no time axis"):
        viz.html(model, one)
    with pytest.raises(ValueError, match="does not match the model"):
        viz.html(kamino.models.fourbar(), traj)  # a 3-world trajectory, a 1-world model
    with pytest.raises(ValueError, match="does not match the model"):
        viz.gif(mixed[0], traj, tmp_path / "x.gif")
    with pytest.raises(TypeError, match=r"traj must be a kamino\.State"):
        viz.html(model, np.asarray(traj.body_q))
    with pytest.raises(TypeError, match=r"model must be a kamino\.Model"):
        viz.html("fourbar", traj)
    with pytest.raises(ValueError, match="fps must be a positive"):
        viz.html(model, traj, fps=0)
    with pytest.raises(ValueError, match=r"\.gif or \.mp4"):
        viz.gif(model, traj, tmp_path / "x.png")
    with pytest.raises(ValueError, match="renderer must be one of"):
        viz.gif(model, traj, tmp_path / "x.gif", renderer="vulkan")
    with pytest.raises(ValueError, match="world 5 is out of range"):
        viz.gif(model, traj, tmp_path / "x.gif", world=5)
    assert not (tmp_path / "x.gif").exists()


# ------------------------------------------------------------------------------------------------ GIF


def _gif_frames(path) -> tuple[int, tuple[int, int], list[np.ndarray]]:
    from PIL import Image, ImageSequence

    with Image.open(path) as im:
        frames = [np.asarray(f.convert("RGB")) for f in ImageSequence.Iterator(im)]
        return im.n_frames, im.size, frames


def test_gif_matplotlib_has_a_frame_per_period(fourbar_run, tmp_path):
    pytest.importorskip("matplotlib")
    model, traj = fourbar_run
    path = tmp_path / "fourbar.gif"
    assert viz.gif(model, traj, path, world=1, fps=60, renderer="matplotlib", width=200, height=150) == "matplotlib"
    n, size, frames = _gif_frames(path)
    time = np.asarray(traj.time)[:, 1]
    expected = int(np.floor((time[-1] - time[0]) * 60 + 1e-3)) + 1  # 23 steps of 1/240 s: 0, 1/60, ..., 5/60
    assert n == expected == len(frame_steps(time, 60, unique=False)) == 6
    assert size == (200, 150)
    assert all(f.shape == (150, 200, 3) for f in frames)
    assert not np.array_equal(frames[0], frames[-1])


def test_gif_auto_draws_with_what_is_there(mixed, tmp_path):
    pytest.importorskip("matplotlib")
    import warnings

    model, traj = mixed
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        used = viz.gif(model, traj, tmp_path / "boxes.gif", world=-1, fps=1 / DT, width=96, height=64)
    assert used in ("mujoco", "matplotlib")
    if used == "matplotlib":  # no OpenGL context in this process: said so
        assert any("drawing with matplotlib" in str(w.message) for w in caught)
    n, size, _ = _gif_frames(tmp_path / "boxes.gif")
    assert (n, size) == (5, (96, 64))


def test_mp4_needs_imageio_ffmpeg(fourbar_run, tmp_path):
    try:
        import imageio_ffmpeg  # noqa: F401
    except ImportError:
        with pytest.raises(ImportError, match="imageio-ffmpeg"):
            viz.gif(*fourbar_run, tmp_path / "x.mp4")
    else:
        pytest.skip("imageio-ffmpeg is installed: the MP4 path is not an error here")


def test_mujoco_drawing_model_puts_bodies_at_kamino_poses(mixed):
    """The flattened export (no OpenGL needed): after qpos is set, MuJoCo's body frames are kamino's poses."""
    mujoco = pytest.importorskip("mujoco")
    from kamino.viz._mujoco import qpos_addresses, set_poses, visual_mjcf
    from kamino.viz._scene import make_scene

    model, traj = mixed
    for world in (0, 1):
        scene = make_scene(model, traj, world=world, fps=None, fn="test")
        mj_model = mujoco.MjModel.from_xml_string(visual_mjcf(scene, width=64, height=48, show_joints=True))
        data = mujoco.MjData(mj_model)
        adr = qpos_addresses(scene, mj_model)
        ids = [mujoco.mj_name2id(mj_model, mujoco.mjtObj.mjOBJ_BODY, n) for n in scene.model.body_names]
        assert mj_model.neq == 0 and mj_model.nu == 0 and mj_model.njnt == scene.model.num_bodies
        for k in range(scene.num_frames):
            q = scene.body_q[k]
            set_poses(mj_model, data, adr, q)
            np.testing.assert_allclose(data.xpos[ids], q[:, :3], atol=1e-12)
            np.testing.assert_allclose(data.xquat[ids], q[:, [6, 3, 4, 5]] * np.sign(q[:, [6]] * data.xquat[ids, :1]),
                                       atol=1e-12)


def test_mujoco_renderer_needs_an_mjcf_export(tmp_path):
    """A world MJCF cannot describe (a loop closed by a prismatic joint) is an error for renderer="mujoco" (before
    any OpenGL context is asked for) and falls back to matplotlib for "auto"."""
    pytest.importorskip("matplotlib")
    b = kamino.ModelBuilder()
    body = b.add_body(1.0, np.eye(3) * 1e-2, pos=(0, 0, 1), name="slider")
    b.add_geom(kamino.GeomType.BOX, body, size=(0.05, 0.05, 0.05))
    b.add_joint_at(kamino.JointType.PRISMATIC, -1, body, anchor=(0, 0, 1), axis=(1, 0, 0), name="x")
    b.add_joint_at(kamino.JointType.PRISMATIC, -1, body, anchor=(0, 0, 1), axis=(1, 0, 0), name="x_again")
    model = b.finalize()
    traj = _synthetic(model, 3)
    with pytest.raises(RuntimeError, match="save_mjcf cannot export world 0"):
        viz.gif(model, traj, tmp_path / "x.gif", renderer="mujoco")
    with pytest.warns(RuntimeWarning, match="drawing with matplotlib: kamino.save_mjcf cannot export"):
        assert viz.gif(model, traj, tmp_path / "x.gif", width=64, height=48) == "matplotlib"
    assert _page_data(viz.html(model, traj))["loop_joints"] == ["x_again"]


_MUJOCO_SCRIPT = textwrap.dedent("""
    import json, sys
    import jax
    jax.config.update("jax_enable_x64", True)
    import kamino
    from kamino import viz
    from kamino.viz._mujoco import RendererUnavailable, _open_renderer
    import mujoco
    try:
        _open_renderer(mujoco.MjModel.from_xml_string("<mujoco><worldbody/></mujoco>"), 32, 32).close()
    except RendererUnavailable as e:
        print("SKIP " + str(e).splitlines()[0]); sys.exit(0)
    model = kamino.concat([kamino.models.box_stack(2), kamino.models.fourbar()])
    traj = jax.tree.map(lambda x: jax.numpy.stack([x] * 4), kamino.init_state(model))
    steps = jax.numpy.arange(4.0)
    traj = traj.replace(body_q=traj.body_q.at[:, :, 0].add(0.05 * steps[:, None]),  # every body moves each step
                        time=(steps[:, None] + 1) / 240 * jax.numpy.ones(2))
    out = {}
    for world in (0, 1):
        path = f"{sys.argv[1]}/w{world}.gif"
        out[world] = viz.gif(model, traj, path, world=world, fps=240, renderer="mujoco", width=120, height=90)
    print("RESULT " + json.dumps(out))
""")


def test_gif_mujoco_renderer(tmp_path):
    """MuJoCo's renderer where an OpenGL context can be made (``MUJOCO_GL=egl`` unless set otherwise)."""
    pytest.importorskip("mujoco")
    env = {**os.environ, "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl"), "JAX_PLATFORMS": "cpu"}
    proc = subprocess.run([sys.executable, "-c", _MUJOCO_SCRIPT, str(tmp_path)], env=env,
                          capture_output=True, text=True, timeout=300, check=False)
    assert proc.returncode == 0, proc.stderr[-3000:]
    lines = proc.stdout.splitlines()
    skip = [line for line in lines if line.startswith("SKIP ")]
    if skip:
        pytest.skip(f"no OpenGL context for MuJoCo (MUJOCO_GL={env['MUJOCO_GL']}): {skip[0][5:]}")
    result = json.loads(next(line for line in lines if line.startswith("RESULT "))[7:])
    assert result == {"0": "mujoco", "1": "mujoco"}
    for world in (0, 1):
        n, size, frames = _gif_frames(tmp_path / f"w{world}.gif")
        assert (n, size) == (4, (120, 90))  # one frame per step at fps = 1/dt; the bodies move every step
        assert not np.array_equal(frames[0], frames[1])


# ------------------------------------------------------------------------------------------------ helpers of viz


def test_world_model_is_concats_inverse():
    model = kamino.concat([kamino.models.fourbar(actuated=True), kamino.models.box_stack(2),
                           kamino.models.slider_crank(), kamino.models.fourbar()])
    back = kamino.concat([viz.world_model(model, w) for w in range(model.num_worlds)])
    for f in dataclasses.fields(model):
        a, b = getattr(model, f.name), getattr(back, f.name)
        if isinstance(a, np.ndarray):
            assert a.dtype == b.dtype and np.array_equal(a, b), f.name
        else:
            assert a == b, f.name
    single = viz.world_model(model, 2)
    assert single.num_worlds == 1 and single.body_names == ("crank", "rod", "slider")


def test_loop_joints_are_the_export_cuts():
    assert [kamino.models.fourbar().joint_names[j] for j in viz.loop_joints(kamino.models.fourbar())] == \
        ["rocker_ground"]
    ladder = kamino.models.chain_of_loops(3)
    assert len(viz.loop_joints(ladder)) == count_loops(ladder) == 3
    assert viz.loop_joints(kamino.models.box_stack(2)) == []


def test_viewer_template_and_libraries_are_package_data():
    package = importlib.resources.files("kamino.viz")
    template = package.joinpath("viewer.html")
    assert template.is_file()
    text = template.read_text(encoding="utf-8")
    assert all(placeholder in text for placeholder in
               ("__KAMINO_DATA__", "__KAMINO_TITLE__", "__KAMINO_THREE__", "__KAMINO_ORBIT_CONTROLS__"))
    for name in ("vendor/three.module.min.js", "vendor/OrbitControls.js", "vendor/LICENSE"):
        assert package.joinpath(name).is_file(), name
    assert package.joinpath("vendor/LICENSE").read_text(encoding="utf-8").startswith("The MIT License")


def test_html_plays_a_robot_with_loops():
    # the viewer opens a robot (dr_legs: 31 bodies, its leg linkages closed by loop joints) and plays it:
    # every frame's poses are the trajectory's, every body is drawn, the loop joints are the export's cuts.
    robot = kamino.models.dr_legs()
    traj = _synthetic(robot, 4)
    data = _page_data(viz.html(robot, traj))
    np.testing.assert_array_equal(np.asarray(data["frames"]["body_q"]), np.asarray(traj.body_q))
    assert data["frames"]["step"] == [0, 1, 2, 3]
    assert [b["name"] for b in data["bodies"]] == list(robot.body_names)
    cuts = [robot.joint_names[j] for j in viz.loop_joints(robot)]
    assert sorted(data["loop_joints"]) == sorted(cuts) and len(cuts) == count_loops(robot, 0) > 0
    assert sorted(j["name"] for j in data["joints"] if j["loop"]) == sorted(cuts)
