"""Builder-level couplings and named actuators: validation, ctrl mapping, multi-world index shifts."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
import pytest

import kamino
from kamino import JointType as JT
from kamino.models.shapes import box_inertia


def _two_hinges(actuation=None, **actuator):
    b = kamino.ModelBuilder()
    la = b.add_body(1.0, box_inertia(1.0, (0.1, 0.1, 1.0)), pos=(0, 0, 0.5), name="a")
    lb = b.add_body(1.0, box_inertia(1.0, (0.1, 0.1, 1.0)), pos=(1, 0, 0.5), name="b")
    ja = b.add_joint_at(JT.REVOLUTE, -1, la, anchor=(0, 0, 1), axis=(0, 1, 0), name="ja")
    jb = b.add_joint_at(JT.REVOLUTE, -1, lb, anchor=(1, 0, 1), axis=(0, 1, 0), name="jb", actuation=actuation)
    if actuator:
        b.add_actuator(jb, **actuator)
    return b, ja, jb


def test_coupling_validation_names_the_problem():
    b, ja, jb = _two_hinges()
    b.add_coupling(ja, ja, (0, 1), name="self")
    with pytest.raises(kamino.ModelError, match="'self': couples joint 'ja' to itself"):
        b.finalize()
    b, ja, jb = _two_hinges()
    b.add_coupling(ja, 7, (0, 1), name="c")
    with pytest.raises(kamino.ModelError, match="'c': joint_b 7 is not a joint"):
        b.finalize()
    b, ja, jb = _two_hinges()
    with pytest.raises(kamino.ModelError, match="polycoef needs 1 to 5"):
        b.add_coupling(ja, jb, (0, 1, 2, 3, 4, 5))
    with pytest.raises(kamino.ModelError, match="NaN or inf"):
        b.add_coupling(ja, jb, (0, np.nan))
    b2 = kamino.ModelBuilder()
    body = b2.add_body(1.0, np.eye(3), pos=(0, 0, 0))
    other = b2.add_body(1.0, np.eye(3), pos=(1, 0, 0))
    js = b2.add_joint_at(JT.SPHERICAL, -1, body, anchor=(0, 0, 0))
    jr = b2.add_joint_at(JT.REVOLUTE, -1, other, anchor=(1, 0, 0))
    b2.add_coupling(js, jr, (0, 1), name="ball")
    with pytest.raises(kamino.ModelError, match=r"'ball': joint_a .* is a SPHERICAL joint"):
        b2.finalize()


def test_actuator_validation_and_automatic_names():
    pos = kamino.Actuation("position", kp=10.0, kd=1.0)
    model = _two_hinges(pos)[0].finalize()
    assert model.actuator_names == ("jb",) and model.actuator_index("jb") == 0
    b = _two_hinges(pos, name="servo", gear=2.0)[0]
    with pytest.raises(kamino.ModelError, match="'servo': position actuators take gear 1"):
        b.finalize()
    b = _two_hinges(None, name="m")[0]
    with pytest.raises(kamino.ModelError, match="'m': joint 'jb' is passive"):
        b.finalize()
    b, _, jb = _two_hinges(kamino.Actuation("effort"), name="m1")
    b.add_actuator(jb, name="m2")
    with pytest.raises(kamino.ModelError, match="'m2': DoF 0 of joint 'jb' already has actuator 'm1'"):
        b.finalize()
    b = _two_hinges(kamino.Actuation("effort"), name="m", ctrl_range=(1.0, -1.0))[0]
    with pytest.raises(kamino.ModelError, match="ctrl_range"):
        b.finalize()


def test_from_ctrl_clips_and_applies_gear_per_mode():
    b = kamino.ModelBuilder()
    bodies = [b.add_body(1.0, np.eye(3) * 0.1, pos=(k, 0, 0), name=f"b{k}") for k in range(3)]
    modes = [kamino.Actuation("effort", effort_limit=100.0), kamino.Actuation("position", kp=5.0, kd=1.0),
             kamino.Actuation("velocity", kd=2.0)]
    joints = [b.add_joint_at(JT.REVOLUTE, -1, bodies[k], anchor=(k, 0, 0), axis=(0, 1, 0), actuation=modes[k],
                             name=f"j{k}") for k in range(3)]
    b.add_actuator(joints[2], name="vel", ctrl_range=(-1.0, 1.0))  # listed first: explicit ones come first
    b.add_actuator(joints[0], name="motor", gear=3.0, ctrl_range=(-2.0, 2.0))
    model = kamino.replicate(b.finalize(), 2)
    assert model.actuator_names == ("vel", "motor", "j1") * 2
    np.testing.assert_array_equal(model.actuator_dof, [2, 0, 1, 5, 3, 4])
    ctrl = kamino.Control.from_ctrl(model, jnp.asarray([[5.0, 1.5, 0.3, -0.5, -9.0, 0.1]]))
    np.testing.assert_allclose(ctrl.dof_effort, [[4.5, 0, 0, -6.0, 0, 0]])  # gear 3, clipped to +-2
    np.testing.assert_allclose(ctrl.position_target, [[0, 0.3, 0, 0, 0.1, 0]])
    np.testing.assert_allclose(ctrl.velocity_target, [[0, 0, 1.0, 0, 0, -0.5]])  # clipped to +-1
    with pytest.raises(ValueError, match="one entry per actuator"):
        kamino.Control.from_ctrl(model, jnp.zeros(5))


def test_concat_shifts_coupling_and_actuator_indices():
    pos = kamino.Actuation("position", kp=10.0, kd=1.0)
    b, ja, jb = _two_hinges(pos)
    b.add_coupling(ja, jb, (0.0, 2.0), name="m")
    single = b.finalize()
    b0 = kamino.ModelBuilder()
    b0.add_body(1.0, np.eye(3), name="lonely")
    mixed = kamino.concat([b0.finalize(), single, single])
    np.testing.assert_array_equal(mixed.coupling_joint_a, [0, 2])
    np.testing.assert_array_equal(mixed.coupling_joint_b, [1, 3])
    np.testing.assert_array_equal(mixed.actuator_dof, [1, 3])
    np.testing.assert_array_equal(mixed.world_coupling_count, [0, 1, 1])
    # each world's coupling is enforced on its own joints
    state = kamino.init_state(mixed, actuated_positions=[0.2, -0.3])
    q = np.asarray(kamino.joint_positions(mixed, state))
    np.testing.assert_allclose(q, [0.4, 0.2, -0.6, -0.3], atol=1e-9)


def test_ellipsoid_pairs_other_than_plane_are_rejected():
    b = kamino.ModelBuilder()
    e = b.add_body(1.0, np.eye(3) * 0.01, pos=(0, 0, 1), name="egg")
    s = b.add_body(1.0, np.eye(3) * 0.01, pos=(0, 0, 2), name="ball")
    b.add_geom(kamino.GeomType.PLANE, -1, name="floor")
    b.add_geom(kamino.GeomType.ELLIPSOID, e, size=(0.1, 0.2, 0.3), name="egg_geom")
    b.add_geom(kamino.GeomType.SPHERE, s, size=0.1, name="ball_geom")
    with pytest.raises(kamino.ModelError, match=r"'egg_geom' and 'ball_geom'.*not supported"):
        b.finalize()
    b.set_collision(1, 2, False)
    model = b.finalize()
    assert model.num_pairs == 2  # floor-egg, floor-ball
