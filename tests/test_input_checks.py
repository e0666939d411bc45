"""Inputs a user can get wrong fail with an error that names what is wrong: the builder's range checks (MuJoCo's
compiler's rules, with float32's range), MJCF files kamino cannot simulate, states of another model, state dtypes,
unreachable kinematic targets and time steps too large for a model."""

from __future__ import annotations

import pickle
import warnings

import jax
import numpy as np
import pytest

import kamino
from kamino import JointType, ModelBuilder, ModelError
from kamino.model import MAX_PARAMETER


def _pendulum(mass: float = 1.0, inertia=(0.02, 0.02, 0.01), axis=(0.0, 1.0, 0.0), length: float = 0.5,
              kp: float = 0.0, name: str = "link") -> ModelBuilder:
    """A one-link pendulum's builder, with the value under test put in."""
    b = ModelBuilder()
    link = b.add_body(mass=mass, inertia=inertia, pos=(0.0, 0.0, 1.0 - length), name=name)
    actuation = kamino.Actuation(mode="position", kp=kp, kd=1.0) if kp else None
    b.add_joint(JointType.REVOLUTE, -1, link, parent_frame=((0.0, 0.0, 1.0), (0, 0, 0, 1)),
                child_frame=((0.0, 0.0, length), (0, 0, 0, 1)), axis=axis, name="hinge", actuation=actuation)
    return b


@pytest.mark.parametrize(("kwargs", "pattern"), [
    ({"mass": 1e-20}, r"body 'link'.*mass 1e-20 is below 1e-15"),
    ({"mass": 1e39}, r"body 'link'.*mass.*1e\+39.*float32"),
    ({"mass": 2e30}, r"body 'link'.*mass.*2e\+30.*float32"),
    ({"inertia": (1e-18, 1e-18, 1e-18)}, r"body 'link'.*principal moment of inertia 1e-18"),
    ({"inertia": (1e31, 1e31, 1e31)}, r"body 'link'.*inertia.*float32"),
    ({"inertia": (0.01, 0.01, 0.03)}, r"body 'link'.*triangle inequality"),
    ({"axis": (1e-11, 0.0, 0.0)}, r"joint 'hinge'.*zero-length axis"),
    ({"length": 1e35}, r"body 'link'.*pos.*-1e\+35"),
    ({"kp": 1e33}, r"joint 'hinge'.*kp.*1e\+33"),
])
def test_builder_rejects_values_mujoco_rejects_or_float32_cannot_step(kwargs, pattern):
    with pytest.raises(ModelError, match=pattern):
        _pendulum(**kwargs).finalize()


def test_builder_accepts_the_edges_of_the_ranges():
    """The bounds themselves are accepted: the smallest mass, an axis of any length above the bound (normalised),
    a parameter of exactly MAX_PARAMETER, infinite limits."""
    model = _pendulum(mass=1e-15, inertia=(2e-15, 2e-15, 1e-15), axis=(0.0, 1e-9, 0.0)).finalize()
    assert model.body_mass[0] == 1e-15
    b = _pendulum()
    b.add_body(mass=MAX_PARAMETER, inertia=(1.0, 1.0, 1.0), pos=(5.0, 0.0, 0.0), name="heavy")
    b.add_joint(JointType.PRISMATIC, -1, 1, axis=(3.0, 0.0, 0.0), limits=(-np.inf, np.inf), name="slide")
    model = b.finalize()
    assert model.body_mass[1] == MAX_PARAMETER


def test_builder_names_are_unique_per_kind():
    b = _pendulum()
    b.add_body(mass=1.0, inertia=(1.0, 1.0, 1.0), name="link")
    with pytest.raises(ModelError, match="body name 'link' is used twice"):
        b.finalize()


MJCF_BODY = '<body name="{name}" pos="0 0 1"><joint name="j" axis="0 1 0"/><geom size="0.1" mass="1"/></body>'


@pytest.mark.parametrize(("source", "pattern"), [
    ("<mujoco/>", "has no bodies"),
    ('<mujoco><worldbody><geom type="plane" size="1 1 1"/></worldbody></mujoco>', "has no bodies"),
    ('<mujoco><worldbody><body><geom size="0.1"/></body></worldbody></mujoco>', "has no joints: its 1 body is welded"),
    (("<mujoco><worldbody>" + MJCF_BODY.format(name="a\xff\xfeb") + "</worldbody></mujoco>").encode("latin-1"),
     "not UTF-8"),
])
def test_load_mjcf_rejects_what_it_cannot_simulate(source, pattern):
    with pytest.raises(ModelError, match=pattern):
        kamino.load_mjcf(source)


def test_load_mjcf_rejects_a_file_with_a_name_that_is_not_utf8(tmp_path):
    path = tmp_path / "latin1.xml"
    path.write_bytes(("<mujoco><worldbody>" + MJCF_BODY.format(name="b\xe9ton") + "</worldbody></mujoco>")
                     .encode("latin-1"))
    with pytest.raises(ModelError, match=r"the name b'b\\xe9ton' is not UTF-8"):
        kamino.load_mjcf(path)


def test_a_state_of_another_mechanism_is_rejected_before_a_backend_runs():
    """Two pendulums of different lengths have states of the same shapes; a state of one stepped with the other
    would jump 0.2 m in one step. The fingerprint stops it in step, rollout, Simulator.step and metrics, under
    jax.jit too (the fingerprint is static data: the check runs at trace time), on both backends."""
    short, long = kamino.models.pendulum(), kamino.models.pendulum(length=1.2)
    state = kamino.init_state(short)
    assert state.model_fingerprint == kamino.init_state(kamino.models.pendulum(mass=3.0)).model_fingerprint
    assert state.model_fingerprint != kamino.init_state(long).model_fingerprint
    for backend in ("jax", "warp"):
        with pytest.raises(ValueError, match="step: the state belongs to another model"):
            kamino.step(long, state, backend=backend)
        with pytest.raises(ValueError, match="rollout: the state belongs to another model"):
            kamino.rollout(long, state, num_steps=2, backend=backend)
        with pytest.raises(ValueError, match="the state belongs to another model"):
            jax.jit(lambda s, b=backend: kamino.step(long, s, backend=b))(state)
    with pytest.raises(ValueError, match="metrics: the state belongs to another model"):
        kamino.metrics(long, state)


def test_the_fingerprint_travels_with_the_state():
    """replace, tree maps, pickling and a step keep it; an unbound state (built field by field) is not checked."""
    model = kamino.models.pendulum()
    state = kamino.init_state(model)
    key = state.model_fingerprint
    assert state.replace(body_u=state.body_u + 1.0).model_fingerprint == key
    assert jax.tree.map(lambda x: x, state).model_fingerprint == key
    assert pickle.loads(pickle.dumps(state)).model_fingerprint == key
    assert kamino.state.drop_empty(state).model_fingerprint == key
    stepped = kamino.step(model, state, backend="warp")
    assert stepped.model_fingerprint == key
    assert jax.tree.structure(stepped) == jax.tree.structure(state)
    unbound = kamino.state.bind(state, None)
    assert unbound.model_fingerprint is None
    kamino.metrics(kamino.models.pendulum(length=1.2), unbound)  # not known, not checked


@pytest.mark.parametrize("dtype", [np.int32, np.float16, "bfloat16", "complex64"])
def test_init_state_takes_float32_or_float64_only(dtype):
    with pytest.raises(ValueError, match="init_state: dtype must be float32 or float64"):
        kamino.init_state(kamino.models.pendulum(), dtype=dtype)


def test_step_rejects_an_integer_state():
    model = kamino.models.pendulum()
    state = kamino.init_state(model)
    bad = state.replace(body_q=state.body_q.astype(np.int32))
    with pytest.raises(ValueError, match=r"step: state\.body_q has dtype int32"):
        kamino.step(model, bad, backend="jax")


def test_a_time_step_beyond_the_quiet_bound_warns_naming_dt():
    model = kamino.models.pendulum()
    with pytest.warns(UserWarning, match=r"config.dt=0.5 s is longer than 0.05 s"):
        kamino.Simulator(model, kamino.SolverConfig(dt=0.5), backend="jax")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        kamino.Simulator(model, kamino.SolverConfig(dt=0.05), backend="jax")


def _limited_hinges() -> kamino.Model:
    """Two worlds of a pendulum whose actuated hinge is limited to [-1, 1] rad."""
    b = ModelBuilder()
    link = b.add_body(mass=1.0, inertia=(0.02, 0.02, 0.01), pos=(0.0, 0.0, 0.5))
    b.add_joint(JointType.REVOLUTE, -1, link, parent_frame=((0.0, 0.0, 1.0), (0, 0, 0, 1)),
                child_frame=((0.0, 0.0, 0.5), (0, 0, 0, 1)), axis=(0, 1, 0), limits=(-1.0, 1.0),
                actuation=kamino.Actuation(mode="position", kp=10.0, kd=1.0), name="hinge")
    return kamino.replicate(b.finalize(), 2)


def test_forward_kinematics_reports_a_target_beyond_the_limits_as_unreachable():
    """The solver can put the link at 4 rad (the pendulum has no loop, the residual is zero), but that configuration
    is not one the joint can reach: converged is False there. One program answers both worlds."""
    model = _limited_hinges()
    fk = kamino.forward_kinematics(model, joint_positions=[0.5, 4.0])
    assert fk.within_limits.tolist() == [True, False]
    assert fk.converged.tolist() == [True, False]
    assert float(fk.residual.max()) < 1e-6  # the poses themselves satisfy the joints
    with pytest.raises(ValueError, match=r"worlds \[1\] lie beyond the joint limits"):
        kamino.init_state(model, joint_positions=[0.5, 4.0])


def test_actuated_targets_are_checked_against_their_dofs_limits():
    """The actuated targets map to their DoFs' limits world by world (what forward_kinematics ANDs into converged
    for actuated_positions), to the solver's tolerance."""
    model = _limited_hinges()
    inside = kamino.kinematics._targets_within_limits(model, jax.numpy.asarray([-1.0 - 1e-7, 1.0 + 1e-5]),
                                                      "actuated", 1e-6)
    assert inside.tolist() == [True, False]


KEYFRAME_MJCF = """<mujoco><option timestep="0.005"/><worldbody>
<body name="link" pos="0 0 1"><joint name="hinge" axis="0 1 0"/>
<geom type="capsule" fromto="0 0 0 0 0 -0.5" size="0.02" mass="1"/></body>
</worldbody><actuator><motor joint="hinge" name="m"/></actuator>
<keyframe><key name="home" qpos="0.3" qvel="1.0" ctrl="0.5" time="2"/><key qpos="-0.2"/></keyframe></mujoco>"""


def test_mjcf_keyframes_become_initial_states():
    """A hinge at height 1 about y, its link's CoM 0.25 m below: at the key's angle 0.3 rad and rate 1 rad/s the
    CoM sits at 0.25 (-sin 0.3, 0, -cos 0.3) from the hinge and moves at w x r."""
    model = kamino.load_mjcf(KEYFRAME_MJCF)
    assert model.suggested_dt == 0.005
    assert [k.name for k in model.keyframes] == ["home", "key1"]
    assert model.keyframe("home").ctrl.tolist() == [0.5]
    state = kamino.init_state(model, keyframe="home", dtype=np.float64)
    r = 0.25 * np.array([-np.sin(0.3), 0.0, -np.cos(0.3)])
    np.testing.assert_allclose(np.asarray(state.body_q)[0, :3], np.array([0.0, 0.0, 1.0]) + r, atol=1e-12)
    np.testing.assert_allclose(np.asarray(state.body_q)[0, 3:], [0.0, np.sin(0.15), 0.0, np.cos(0.15)], atol=1e-12)
    np.testing.assert_allclose(np.asarray(state.body_u)[0], [*np.cross([0.0, 1.0, 0.0], r), 0.0, 1.0, 0.0],
                               atol=1e-12)
    assert float(state.time[0]) == 2.0
    unnamed = kamino.init_state(kamino.replicate(model, 3), keyframe=1, dtype=np.float64)
    np.testing.assert_allclose(np.asarray(unnamed.body_q)[:, 0], -0.25 * np.sin(-0.2), atol=1e-12)
    assert kamino.replicate(model, 3).suggested_dt == 0.005
    assert pickle.loads(pickle.dumps(model)).keyframe(0).name == "home"
    assert kamino.load_mjcf(kamino.save_mjcf(model)).suggested_dt == 0.005
    with pytest.raises(ValueError, match=r"keyframe 'away': .*known: \['home', 'key1'\]"):
        kamino.init_state(model, keyframe="away")
    with pytest.raises(ValueError, match="keyframe 2"):
        kamino.init_state(model, keyframe=2)


def test_a_model_without_timestep_or_keyframes_suggests_nothing():
    model = kamino.load_mjcf(KEYFRAME_MJCF.replace('<option timestep="0.005"/>', "").split("<keyframe>")[0]
                             + "</mujoco>")
    assert model.suggested_dt is None and model.keyframes == ()
    assert kamino.models.pendulum().suggested_dt is None


def test_the_fingerprint_follows_each_worlds_mechanism():
    """Copies of a model share its fingerprint (a sharded step's group model is such a block); the order of
    different worlds and any world's geometry change it."""
    fourbar, boxes = kamino.models.fourbar(), kamino.models.box_stack()
    key = kamino.model.fingerprint
    assert key(kamino.replicate(fourbar, 3)) == key(fourbar)
    pair = kamino.concat([fourbar, boxes])
    assert key(kamino.concat([pair, pair])) == key(pair) != key(kamino.concat([boxes, fourbar]))
    assert key(kamino.concat([fourbar, kamino.models.fourbar(crank=0.2)])) != key(kamino.replicate(fourbar, 2))
