"""The first hour with kamino (issue 19, item 6): every README snippet runs as written, the README's two
fresh-machine commands stay as they are, the usual first mistakes fail early with a ``TypeError`` /
``ValueError`` that names the argument, and Warp is quiet unless asked."""

from __future__ import annotations

import os
import re
import subprocess
import sys
import warnings
from pathlib import Path

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
    # skips byte-compiling every installed package (81 -> 51 s of CI's install, 2026-11-27); Python compiles what a
    # test imports, once
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
        assert met["constraint_violation"].shape == (namespace["traj"].body_q.shape[0], 1)
        # the four-bar's loop stays closed over the run (float64 here; float32 closes to a few um)
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


def test_bench_plot_without_matplotlib_names_the_extra(monkeypatch, tmp_path):
    monkeypatch.setitem(sys.modules, "matplotlib", None)  # import matplotlib now raises ImportError
    with pytest.raises(SystemExit) as done:
        cli.main(["bench", "--plot", str(tmp_path / "results.json")])
    message = str(done.value.code)
    assert "--plot needs matplotlib" in message and "pip install 'kamino[bench]'" in message


def test_bench_help_points_inside_the_repository(capsys):
    with pytest.raises(SystemExit) as done:
        cli.main(["bench", "--help"])
    assert done.value.code == 0
    out = capsys.readouterr().out
    for doc in ("docs/architecture.md", "docs/benchmark_scenes.md", "docs/settings.md"):
        assert doc in out and (ROOT / doc).is_file()


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
        cfg = kamino.SolverConfig(**{field: value})
        with pytest.warns(UserWarning, match=rf"SolverConfig\.{field}={value!r} is a Warp backend setting; "
                                             r"backend='jax' ignores it"), pytest.raises(ValueError):
            kamino.step(model, state, bad, config=cfg, backend="jax")
    # what the JAX reference computes anyway (dense, Cholesky), the defaults, and any setting on Warp: no warning
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        for cfg, backend in ((kamino.SolverConfig(jacobian="dense", linear_solver="llt"), "jax"),
                             (kamino.SolverConfig(), "jax"), (kamino.SolverConfig(linear_solver="cr"), "warp")):
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
            "kamino.api._backend('warp')\n"
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
