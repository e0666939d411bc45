"""The first hour with kamino: every README snippet runs as written, the README's two fresh-machine commands stay
as they are, the usual first mistakes fail early with a ``TypeError`` / ``ValueError`` that names the argument, the
read-outs a task needs (a joint's coordinates by name, a body's frame, contact forces) read what they say, long
compiles are announced, and Warp is quiet unless asked (no banner, no missing-driver line on a CPU-only machine)."""

from __future__ import annotations

import dataclasses
import os
import re
import subprocess
import sys
import warnings
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import kamino
from kamino import cli

ROOT = Path(__file__).resolve().parents[1]
README = (ROOT / "README.md").read_text()
SNIPPETS = re.findall(r"```python\n(.*?)```", README, re.S)


# ---------------------------------------------------------------------------------------------
# README
# ---------------------------------------------------------------------------------------------

def test_readme_keeps_its_two_fresh_machine_commands():
    # .ci/run runs exactly the test command; the demo command is the first thing a user types. --no-compile: pip
    # skips byte-compiling every installed package (a third of CI's install time); Python compiles what a test
    # imports, once
    bash = re.findall(r"```bash\n(.*?)```", README, re.S)
    assert bash[:2] == [
        "python3 -m venv .venv && .venv/bin/pip install -e . && .venv/bin/kamino demo\n",
        'python3 -m venv .venv && .venv/bin/pip install --no-compile -e ".[test]" && .venv/bin/python -m pytest -q '
        '-n 2\n',
    ]
    assert bash[1].strip() in (ROOT / ".ci" / "run").read_text()
    assert len(SNIPPETS) >= 3


def test_documentation_links_stay_inside_the_repository():
    # every doc a user is pointed to ships with the repository: relative Markdown links resolve, every docs/*.md
    # file named in the package, the tests, the README or the docs exists, and nothing points outside
    texts = {p: p.read_text() for p in [ROOT / "README.md", *(ROOT / "docs").glob("*.md"),
                                        *(ROOT / "kamino").rglob("*.py"), *(ROOT / "tests").glob("*.py")]}
    shared = "shar" + "ed"  # the read-only folder beside the checkout (spelled so that this file does not match)
    outside = ("../" + shared, shared + "/docs", shared + "/bench", shared + "/gpu")
    for path, text in texts.items():
        where = path.relative_to(ROOT)
        assert not any(o in text for o in outside), where
        for doc in re.findall(r"docs/[\w-]+\.md", text):
            assert (ROOT / doc).is_file(), f"{where} names {doc}"
        if path.suffix == ".md":
            for link in re.findall(r"\]\(([^)#\s]+)(?:#[^)]*)?\)", text):
                assert link.startswith("http") or (path.parent / link).exists(), f"{where} links {link}"
    for doc in ("formulation.md", "architecture.md", "settings.md", "benchmark_scenes.md"):
        assert (ROOT / "docs" / doc).is_file()


@pytest.mark.parametrize("index", range(len(SNIPPETS)), ids=[f"snippet{i + 1}" for i in range(len(SNIPPETS))])
def test_readme_snippet_runs_as_written(index, monkeypatch, capsys):
    monkeypatch.chdir(ROOT)  # the snippets' paths are relative to the repository root
    namespace: dict = {"__name__": "__readme__"}
    exec(compile(SNIPPETS[index], f"README.md python snippet {index + 1}", "exec"), namespace)
    printed = capsys.readouterr().out
    assert printed.strip(), "every README snippet shows its result"
    if "traj" in namespace:  # the rollout: the metric printed is the trajectory's, [num_steps, num_worlds]
        met = kamino.metrics(namespace["model"], namespace["traj"])
        assert met["anchor_gap"].shape == (namespace["traj"].body_q.shape[0], 1)
        # the four-bar's loop stays closed over the run (float64 here; float32 closes to a few um)
        assert float(met["anchor_gap"].max()) < 1e-5
        assert float(met["constraint_violation"].max()) < 1e-5
        assert namespace["many"].num_worlds == 4096
    if "fk" in namespace:  # the batched reset: the shape the README states, every world converged
        legs, fk = namespace["legs"], namespace["fk"]
        assert fk.body_q.shape == (legs.num_bodies, 7) == (8 * 31, 7)
        assert namespace["q_act"].shape == (legs.num_actuators,) == (8 * 12,)
        assert bool(np.all(np.asarray(fk.converged)))
    if "scene" in namespace:  # two worlds: the box stack touches (20 contacts), the four-bar's crank is driven
        state = namespace["state"]
        np.testing.assert_array_equal(np.asarray(state.info.num_contacts), [20, 0])
        assert float(state.actuator_force[0]) > 0.0  # the PD pulls the crank towards +0.3 rad


# ---------------------------------------------------------------------------------------------
# Clear errors, raised before a backend runs
# ---------------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def fourbar() -> tuple[kamino.Model, kamino.State]:
    model = kamino.models.fourbar(actuated=True, kp=500.0, kd=10.0)
    return model, kamino.init_state(model)


@pytest.mark.parametrize("backend", ["jax", "warp"])
def test_config_dict_names_config(fourbar, backend):
    model, state = fourbar
    with pytest.raises(TypeError, match=r"config must be a kamino\.SolverConfig.*got dict.*SolverConfig\(\*\*"):
        kamino.step(model, state, config=dict(dt=0.01), backend=backend)
    with pytest.raises(TypeError, match=r"rollout: config must be a kamino\.SolverConfig"):
        kamino.rollout(model, state, num_steps=2, config={"dt": 0.01}, backend=backend)


@pytest.mark.parametrize("backend", ["jax", "warp"])
def test_control_with_an_extra_leading_axis_names_the_field(fourbar, backend):
    model, state = fourbar
    ctrl = kamino.Control(position_target=jnp.zeros((2, model.num_dofs)))
    with pytest.raises(ValueError, match=r"control\.position_target has shape \(2, 4\), expected \(4,\).*rollout"):
        kamino.step(model, state, ctrl, backend=backend)
    # a rollout's controls need exactly one leading (time) axis
    with pytest.raises(ValueError, match=r"controls\.position_target has shape \(4,\), expected \(num_steps, 4\)"):
        kamino.rollout(model, state, kamino.Control(position_target=jnp.zeros(model.num_dofs)), backend=backend)


@pytest.mark.parametrize("backend", ["jax", "warp"])
def test_numpy_array_as_control_names_control(fourbar, backend):
    model, state = fourbar
    with pytest.raises(TypeError, match=r"step: control must be a kamino\.Control or None, got numpy\.ndarray"):
        kamino.step(model, state, np.zeros(model.num_dofs), backend=backend)
    with pytest.raises(TypeError, match=r"rollout: controls must be a kamino\.Control or None, got numpy\.ndarray"):
        kamino.rollout(model, state, np.zeros((3, model.num_dofs)), backend=backend)


def test_concat_of_non_models_names_the_entry():
    with pytest.raises(TypeError, match=r"concat: models\[0\] is a int, expected a kamino\.Model"):
        kamino.concat([1, 2])
    with pytest.raises(TypeError, match=r"concat: models must be a sequence of kamino\.Model, got one Model"):
        kamino.concat(kamino.models.pendulum())


def test_replicate_with_a_fractional_count_names_n():
    model = kamino.models.pendulum()
    with pytest.raises(TypeError, match=r"replicate\(n=2\.7\): n, the number of copies, must be an integer"):
        kamino.replicate(model, 2.7)
    assert kamino.replicate(model, np.int64(2)).num_worlds == 2  # numpy integers are integers


def test_demo_with_no_time_names_seconds(capsys):
    with pytest.raises(SystemExit) as done:
        cli.main(["demo", "--seconds", "0"])
    assert done.value.code == 2  # argparse's usage error, before anything is compiled
    assert "--seconds must be a positive duration, got 0" in capsys.readouterr().err
    with pytest.raises(ValueError, match=r"--seconds 0\.001 is shorter than one step of --dt"):
        cli.demo(seconds=0.001)


def test_unknown_actuation_mode_fails_where_it_is_written():
    with pytest.raises(kamino.ModelError, match=r"Actuation\(mode='postion'\): unknown actuation mode.*'position'"):
        kamino.Actuation("postion", kp=1.0, kd=0.1)
    with pytest.raises(kamino.ModelError, match=r"Actuation\(mode=7\): unknown actuation mode"):
        kamino.Actuation(7)
    assert kamino.Actuation("Velocity", kd=1.0).resolved_mode() == kamino.ActuationMode.VELOCITY


def test_warp_only_solver_settings_warn_on_the_jax_backend(fourbar):
    model, state = fourbar
    bad = kamino.Control(position_target=jnp.zeros((2, model.num_dofs)))  # stops the call after the config check
    for field, value in (("linear_solver", "cr"), ("cr_iterations", 20)):
        cfg = kamino.SolverConfig(warp=kamino.WarpSettings(**{field: value}))
        with pytest.warns(UserWarning, match=rf"SolverConfig\.warp\.{field}={value!r} is a Warp backend setting; "
                                             r"backend='jax' ignores it"), pytest.raises(ValueError):
            kamino.step(model, state, bad, config=cfg, backend="jax")
    # what the JAX reference computes anyway (dense, Cholesky), the defaults, and any setting on Warp: no warning
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        dense_llt = kamino.SolverConfig(warp=kamino.WarpSettings(jacobian="dense", linear_solver="llt"))
        for cfg, backend in ((dense_llt, "jax"),
                             (kamino.SolverConfig(), "jax"),
                             (kamino.SolverConfig(warp=kamino.WarpSettings(linear_solver="cr")), "warp")):
            with pytest.raises(ValueError):
                kamino.step(model, state, bad, config=cfg, backend=backend)


# ---------------------------------------------------------------------------------------------
# MJCF habits
# ---------------------------------------------------------------------------------------------

_ARMATURE_EVERYWHERE = """<mujoco><default><joint armature="0.01" damping="0.1"/></default>
<worldbody><geom type="plane" size="5 5 .1"/>
 <body name="torso" pos="0 0 1"><freejoint name="root"/><geom type="capsule" fromto="0 0 0 0 0 .3" size=".05"/>
  <body name="upper" pos="0 0 -0.05"><joint name="hip" type="ball" {ball}/>
   <geom type="capsule" fromto="0 0 0 0 0 -.3" size=".04"/>
   <body name="lower" pos="0 0 -0.3"><joint name="knee" axis="0 1 0"/>
    <geom type="capsule" fromto="0 0 0 0 0 -.3" size=".04"/></body>
  </body>
 </body>
</worldbody></mujoco>"""


def test_default_armature_on_a_ball_joint_explains_the_refusal_and_the_fix():
    with pytest.raises(kamino.ModelError) as err:
        kamino.load_mjcf(_ARMATURE_EVERYWHERE.format(ball=""))
    message = str(err.value)
    assert "armature on ball joint 'hip' (0.01), whose parent body moves" in message
    assert "w_parent x w_rel" in message  # why: the gyroscopic term kamino's spherical armature lacks
    assert 'set armature="0" on each ball joint' in message  # and what to do
    # the fix the message gives loads, with the hinge keeping its armature
    model = kamino.load_mjcf(_ARMATURE_EVERYWHERE.format(ball='armature="0"'))
    assert model.dof_armature.max() == pytest.approx(0.01)


# ---------------------------------------------------------------------------------------------
# Forward kinematics of a floating robot in float32 (the README's reset, at JAX's default precision)
# ---------------------------------------------------------------------------------------------

def test_float32_forward_kinematics_of_a_floating_base_converges():
    # a free base without a base_pose leaves six null directions of J^T J; a shift below float32 rounding of it
    # (1e-9 relative) made every such solve stop after one iteration
    b = kamino.ModelBuilder()
    base = b.add_body(mass=2.0, inertia=[0.02, 0.02, 0.02], pos=(0, 0, 1), name="base")
    link = b.add_body(mass=0.5, inertia=[0.004, 0.004, 0.001], pos=(0, 0, 0.75), name="link")
    b.add_joint(kamino.JointType.FREE, -1, base, name="root")
    b.add_joint_at(kamino.JointType.REVOLUTE, base, link, anchor=(0, 0, 0.95), axis=(0, 1, 0), name="hinge",
                   actuation=kamino.Actuation("position", kp=10.0, kd=1.0))
    model = kamino.replicate(b.finalize(), 2)
    fk = kamino.forward_kinematics(model, actuated_positions=[0.3, -0.5], dtype=jnp.float32)
    assert fk.body_q.dtype == jnp.float32
    assert bool(np.all(np.asarray(fk.converged))), np.asarray(fk.residual)
    q = np.asarray(kamino.joint_positions(model, kamino.init_state(model, jnp.float32).replace(body_q=fk.body_q)))
    hinge = q.reshape(2, -1)[:, -1]  # per world: FREE (7 coordinates), then the hinge angle
    np.testing.assert_allclose(hinge, [0.3, -0.5], atol=1e-5)  # float32 rounding of unit-sized poses


# ---------------------------------------------------------------------------------------------
# Warp is quiet unless asked
# ---------------------------------------------------------------------------------------------

def test_warp_prints_no_banner_when_kamino_starts_it():
    code = ("import kamino, warp as wp\n"
            "kamino.Simulator(kamino.models.pendulum(), backend='warp')\n"
            "wp.init()\n"
            "print('log_level', wp.config.log_level)\n")
    env = {k: v for k, v in os.environ.items() if k != "KAMINO_WARP_VERBOSE"}
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, cwd=ROOT, timeout=120,
                         check=True)
    import warp as wp

    assert "initialized:" not in run.stdout + run.stderr  # Warp's banner
    assert f"log_level {wp.LOG_WARNING}" in run.stdout


def test_quiet_warp_leaves_a_chosen_level_and_the_verbose_switch(monkeypatch):
    import warp as wp

    from kamino import _warp

    for env, level, expected in ((None, wp.LOG_INFO, wp.LOG_WARNING), ("1", wp.LOG_INFO, wp.LOG_INFO),
                                 (None, wp.LOG_DEBUG, wp.LOG_DEBUG)):
        monkeypatch.setattr(_warp, "_configured", False)
        monkeypatch.setattr(wp.config, "log_level", level)
        if env is None:
            monkeypatch.delenv(_warp.VERBOSE_ENV, raising=False)
        else:
            monkeypatch.setenv(_warp.VERBOSE_ENV, env)
        _warp.quiet_warp()
        assert wp.config.log_level == expected
        _warp.quiet_warp()  # once per process: a later change by the user stands
        assert wp.config.log_level == expected


def test_warp_keeps_the_missing_driver_line_off_a_cpu_only_machine():
    # Warp's native library prints it while starting; without a driver kamino starts Warp with that line filtered
    from kamino import _warp

    if _warp.cuda_driver_loads():
        pytest.skip("a CUDA driver is installed: Warp has nothing to report")
    code = ("import kamino\nkamino.Simulator(kamino.models.pendulum(), backend='warp')\nimport warp as wp\n"
            "print('cuda', wp.is_cuda_available())\n")
    env = {k: v for k, v in os.environ.items() if k != _warp.VERBOSE_ENV}
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, cwd=ROOT, timeout=120,
                         check=True)
    assert "cuda False" in run.stdout
    assert _warp.NO_DRIVER_MESSAGE not in run.stderr, run.stderr
    # and the switch that keeps Warp's own output keeps the line
    verbose = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, timeout=120,
                             env={**env, _warp.VERBOSE_ENV: "1"}, check=True)
    assert _warp.NO_DRIVER_MESSAGE in verbose.stderr


def test_the_driver_filter_keeps_every_other_line(capfd):
    # native code writes to file descriptor 2; only the lines that start with the prefix are dropped
    from kamino import _warp

    def noisy() -> int:
        os.write(2, b"Warp CUDA warning: Could not find or load the NVIDIA CUDA driver. GPU execution will not be "
                    b"available.\nWarp CUDA error: something real\n")
        return 7

    assert _warp.without_lines(noisy, _warp.NO_DRIVER_MESSAGE) == 7
    err = capfd.readouterr().err
    assert err == "Warp CUDA error: something real\n"

    def fails() -> None:
        os.write(2, b"native detail\n")
        raise RuntimeError("Warp initialization failed")

    with pytest.raises(RuntimeError, match="initialization failed"):
        _warp.without_lines(fails, _warp.NO_DRIVER_MESSAGE)
    assert capfd.readouterr().err == "native detail\n"  # an error keeps what was printed before it


# ---------------------------------------------------------------------------------------------
# Long waits are announced
# ---------------------------------------------------------------------------------------------

def test_a_long_compile_is_announced_and_a_short_one_is_not(capsys, monkeypatch):
    import time

    from kamino._progress import QUIET_ENV, announce_compile

    monkeypatch.delenv(QUIET_ENV, raising=False)
    with announce_compile("the quick one", after=5.0):
        pass
    assert capsys.readouterr().err == ""
    with announce_compile("the slow one", after=0.05, note="a note"):
        time.sleep(0.3)
    out, err = capsys.readouterr()
    assert out == ""
    assert re.fullmatch(r"kamino: compiling the slow one \(a note\) \.\.\. done in 0\.\d s\n", err), err
    with pytest.raises(KeyError), announce_compile("the failing one", after=0.05, note=""):
        time.sleep(0.3)
        raise KeyError("boom")
    assert re.fullmatch(r"kamino: compiling the failing one \.\.\. failed after 0\.\d s\n", capsys.readouterr().err)
    monkeypatch.setenv(QUIET_ENV, "1")
    with announce_compile("the quiet one", after=0.0):
        time.sleep(0.1)
    assert capsys.readouterr().err == ""
    with pytest.raises(ValueError, match="what must name the work"), announce_compile(" "):
        pass


def test_progress_draws_on_stderr_unless_quiet(capsys, monkeypatch):
    from kamino._progress import QUIET_ENV, progress

    monkeypatch.delenv(QUIET_ENV, raising=False)
    assert sum(progress(range(4), desc="kamino-bar", leave=True)) == 6
    out, err = capsys.readouterr()
    assert out == "" and "kamino-bar" in err and "4/4" in err
    monkeypatch.setenv(QUIET_ENV, "yes")
    assert list(progress(range(3), desc="kamino-bar")) == [0, 1, 2]
    assert capsys.readouterr().err == ""


@pytest.mark.slow  # compiles the four-bar's rollout in a fresh process, as a user's first `kamino demo` does
def test_cold_demo_says_it_is_compiling(tmp_path):
    # a fresh JAX cache directory and the JAX reference (Warp's kernel cache is the machine's, warm after the first
    # run: that demo takes seconds): the rollout compiles, and a line on stderr says so before the numbers come
    env = {k: v for k, v in os.environ.items() if k not in ("KAMINO_QUIET", "JAX_COMPILATION_CACHE_DIR")}
    env["KAMINO_JAX_CACHE"] = str(tmp_path / "jax")
    run = subprocess.run([sys.executable, "-m", "kamino.cli", "demo", "--seconds", "0.05", "--backend", "jax"],
                         capture_output=True,
                         text=True, env=env, cwd=ROOT, timeout=600, check=True)
    assert "kamino: compiling the four-bar's rollout (the first run on a machine takes longest; later runs load " \
           "it from the cache) ... done in" in run.stderr, run.stderr
    assert "max loop-closure violation" in run.stdout
    # nothing else on stderr: no XLA log lines, no Warp line
    others = [line for line in run.stderr.splitlines() if not line.startswith("kamino: compiling")]
    assert others == [], run.stderr


# ---------------------------------------------------------------------------------------------
# The read-outs a task needs
# ---------------------------------------------------------------------------------------------

def test_joint_coordinates_by_name(fourbar):
    # a hinge about +y at the origin, its link turned by a known angle in each of two worlds
    b = kamino.ModelBuilder()
    link = b.add_body(mass=1.0, inertia=[0.02, 0.02, 0.001], pos=(0, 0, -0.5), name="link")
    b.add_joint_at(kamino.JointType.REVOLUTE, -1, link, anchor=(0, 0, 0), axis=(0, 1, 0), name="hinge")
    two = kamino.replicate(b.finalize(), 2)
    angles = np.array([0.4, -1.1])
    pos = np.stack([-0.5 * np.sin(angles), np.zeros(2), -0.5 * np.cos(angles)], axis=1)  # R_y(angle) (0, 0, -0.5)
    quat = np.stack([np.zeros(2), np.sin(angles / 2), np.zeros(2), np.cos(angles / 2)], axis=1)
    state = kamino.init_state(two).replace(body_q=jnp.asarray(np.concatenate([pos, quat], axis=1)))
    got = [float(kamino.joint_coordinates(two, state, "hinge", world=w)[0]) for w in (0, 1)]
    np.testing.assert_allclose(got, angles, atol=1e-12)
    assert float(kamino.joint_coordinates(two, state, 1)[0]) == pytest.approx(angles[1])  # a global index
    # a trajectory (a leading time axis) gives one row per step
    traj = jax.tree.map(lambda *x: jnp.stack(x), state, state, state)
    np.testing.assert_allclose(kamino.joint_coordinates(two, traj, "hinge", world=1), [[angles[1]]] * 3, atol=1e-12)
    # on the four-bar: each joint's slice of joint_positions (joint_coord_start / joint_coord_count)
    four, four_state = fourbar
    every = np.asarray(kamino.joint_positions(four, four_state))
    for j, name in enumerate(four.joint_names):
        start, count = four.joint_coord_start[j], four.joint_coord_count[j]
        np.testing.assert_array_equal(kamino.joint_coordinates(four, four_state, name), every[start:start + count])
    assert kamino.joint_coordinates(four, four_state, "fix").shape == (0,)  # a FIXED joint has no coordinate
    with pytest.raises(KeyError, match=r"joint_coordinates: no joint named 'crank' in world 0; its joints are "
                                       r"'fix', 'ground_crank', "):
        kamino.joint_coordinates(four, four_state, "crank")
    with pytest.raises(ValueError, match=r"joint_coordinates: world must be an integer in \[0, 2\)"):
        kamino.joint_coordinates(two, state, "hinge", world=2)
    with pytest.raises(ValueError, match=r"joint must be a joint name or a global joint index in \[0, 2\)"):
        kamino.joint_coordinates(two, state, 2)


def test_body_frame_reads_velocity_gravity_and_height_in_body_axes():
    b = kamino.ModelBuilder()
    quarter_turn = (0.0, 0.0, np.sin(np.pi / 4), np.cos(np.pi / 4))  # 90 deg about z: body x along world y
    upright = b.add_body(mass=1.0, inertia=[0.1, 0.1, 0.1], pos=(0, 0, 0.7), quat=quarter_turn, name="upright",
                         velocity=(1.0, 0.0, 0.5), angular_velocity=(0.0, 0.0, 2.0))
    flipped = b.add_body(mass=1.0, inertia=[0.1, 0.1, 0.1], pos=(1, 0, 0.3), quat=(1.0, 0.0, 0.0, 0.0),
                         name="flipped", angular_velocity=(0.0, 3.0, 0.0))  # 180 deg about x: upside down
    for body in (upright, flipped):
        b.add_joint(kamino.JointType.FREE, -1, body)
    model = b.finalize()
    state = kamino.init_state(model)
    up = kamino.body_frame(model, state, "upright")
    np.testing.assert_allclose(up["lin_vel"], [0.0, -1.0, 0.5], atol=1e-12)  # world x is body -y
    np.testing.assert_allclose(up["ang_vel"], [0.0, 0.0, 2.0], atol=1e-12)
    np.testing.assert_allclose(up["gravity"], [0.0, 0.0, -1.0], atol=1e-12)
    assert float(up["height"]) == pytest.approx(0.7) and float(up["up"]) == pytest.approx(1.0)
    down = kamino.body_frame(model, state, flipped)
    np.testing.assert_allclose(down["gravity"], [0.0, 0.0, 1.0], atol=1e-12)  # the world's -z is body +z
    np.testing.assert_allclose(down["ang_vel"], [0.0, -3.0, 0.0], atol=1e-12)
    assert float(down["up"]) == pytest.approx(-1.0) and float(down["height"]) == pytest.approx(0.3)
    traj = jax.tree.map(lambda *x: jnp.stack(x), state, state)
    assert kamino.body_frame(model, traj, "upright")["lin_vel"].shape == (2, 3)
    with pytest.raises(KeyError, match=r"body_frame: no body named 'base' in world 0; its bodies are 'upright'"):
        kamino.body_frame(model, state, "base")


def test_body_contact_forces_sum_each_pairs_force_on_its_two_bodies(fourbar):
    # hand-made contacts on two worlds of two stacked boxes (geoms: ground, box0, box1; pairs: ground-box0,
    # ground-box1, box0-box1): ContactState.force acts on geom b's body, its opposite on geom a's
    model = kamino.replicate(kamino.models.box_stack(2), 2)
    assert [tuple(model.geom_body[[a, b]]) for a, b in zip(model.pair_geom_a[:3], model.pair_geom_b[:3],
                                                          strict=True)] == [(-1, 0), (-1, 1), (0, 1)]
    cap = int(model.world_contact_capacity[0])
    pair = np.full(2 * cap, -1)
    force = np.full((2 * cap, 3), 100.0)  # empty slots carry garbage that must not count
    pair[[0, 1, 2]], force[[0, 1, 2]] = [0, 2, 0], [[0, 0, 5.0], [1.0, 0, 2.0], [0, 0, 1.0]]  # world 0
    pair[cap], force[cap] = 2, [0, 0.5, 3.0]  # world 1: its pairs count from world_pair_start[1]
    state = kamino.init_state(model)
    state = state.replace(contacts=dataclasses.replace(state.contacts, pair=jnp.asarray(pair),
                                                       force=jnp.asarray(force)))
    expected = [[-1.0, 0, 6.0 - 2.0], [1.0, 0, 2.0], [0, -0.5, -3.0], [0, 0.5, 3.0]]  # box0, box1 of each world
    np.testing.assert_allclose(kamino.body_contact_forces(model, state), expected, atol=1e-12)
    # a model without contacts reads zeros
    four, four_state = fourbar
    np.testing.assert_array_equal(kamino.body_contact_forces(four, four_state), np.zeros((four.num_bodies, 3)))


@pytest.mark.slow  # a 30-step rollout of two box stacks (one compile)
def test_body_contact_forces_carry_each_resting_box():
    # two worlds of two stacked boxes, 1 kg and 2 kg: at rest, each box's net contact force (the ground's or the
    # lower box's push, less the upper box's weight on it) holds up its own weight, m g upwards
    model = kamino.concat([kamino.models.box_stack(2, mass=1.0), kamino.models.box_stack(2, mass=2.0)])
    traj = kamino.rollout(model, kamino.init_state(model), num_steps=30)
    forces = np.asarray(kamino.body_contact_forces(model, traj))
    assert forces.shape == (30, 4, 3)
    weight = 9.81 * model.body_mass
    # every step, within 1 % (the first steps settle the speculative contacts of the boxes placed at rest)
    np.testing.assert_allclose(forces[:, :, 2], np.broadcast_to(weight, (30, 4)), rtol=1e-2)
    np.testing.assert_allclose(forces[-1, :, 2], weight, rtol=1e-4)  # settled
    np.testing.assert_allclose(forces[:, :, :2], 0.0, atol=1e-6 * weight.max())  # no sideways push
