"""Sim-to-sim (kamino.envs.sim2sim): the shipped dr_legs policy in C MuJoCo on ``kamino.save_mjcf``'s export, with
kamino's observation and action pipeline. The state maps both ways between the simulators, the observation read
off MuJoCo equals one built from MuJoCo's own joint and free-joint coordinates, and the policy walks there."""

import json

import jax
import numpy as np
import pytest

pytest.importorskip("brax")
mujoco = pytest.importorskip("mujoco")

from kamino.envs import evaluate as rl_eval  # noqa: E402
from kamino.envs import load_policy, make, sim2sim  # noqa: E402


@pytest.fixture(scope="module")
def walker():
    """The shipped policy's environment (JAX backend, a reset bank of 8), its MuJoCo model and layout."""
    policy = load_policy("dr_legs_walk")
    env = make(policy.task, backend="jax", reset_bank=8, **policy.env)
    mj = sim2sim.mujoco_model(env)
    return env, mj, sim2sim.Layout(env.model, mj)


def test_a_kamino_reset_is_the_same_pose_in_mujoco(walker):
    """A reset configuration written into MuJoCo (free joint and tree hinges, then MuJoCo's own forward kinematics)
    puts every body where kamino has it: positions to 1e-5 m and orientations to 1e-6 (``1 - |q_mj . q_kamino|``).
    kamino's state is float32 and its FK closes the loops to 1e-6, and MuJoCo rebuilds each body through up to 12
    hinges from the pelvis, so the feet land within a few 1e-6 m (2.8e-6 measured); a hinge whose MuJoCo coordinate
    had the wrong sign or offset moves its subtree by centimetres. The loop closures, which MuJoCo does not see in
    the tree, hold within the FK tolerance too: every ``<connect>`` violation is under 1e-5 m."""
    env, mj, layout = walker
    for seed in range(3):
        ps = env.full_state(env.reset(jax.random.PRNGKey(seed)).pipeline_state)
        d = mujoco.MjData(mj)
        sim2sim.set_mujoco_state(env, layout, mj, d, ps)
        body_q, body_u = sim2sim.kamino_body_state(layout, d)
        ref = np.asarray(ps.body_q, float)
        assert np.abs(body_q[:, :3] - ref[:, :3]).max() < 1e-5
        assert (1 - np.abs(np.sum(body_q[:, 3:] * ref[:, 3:], 1))).max() < 1e-6
        assert np.abs(body_u).max() == 0.0
        eq = d.efc_type[:d.nefc] == int(mujoco.mjtConstraint.mjCNSTR_EQUALITY)
        assert eq.sum() == 3 * mj.neq and np.abs(d.efc_pos[:d.nefc][eq]).max() < 1e-5


def test_the_mujoco_actuators_are_kamino_s(walker):
    """The export's ``<position>`` actuators are kamino's implicit PD, parameter for parameter: MuJoCo's force
    ``kp (ctrl - q) - kv qd`` (``gainprm[0] = kp``, ``biasprm[1:3] = (-kp, -kv)``), clamped to ``forcerange`` =
    the effort limit, on a joint with kamino's armature and damping; and the controls are unclamped (``ctrlrange``
    off), since the environment maps an action into the joint range itself. Exact: the export writes the float64
    values."""
    env, mj, _ = walker
    m = env.model
    dof = np.asarray(m.actuator_dof)
    kp, kd = m.dof_kp[dof], m.dof_kd[dof]
    np.testing.assert_array_equal(mj.actuator_gainprm[:, 0], kp)
    np.testing.assert_array_equal(mj.actuator_biasprm[:, 1], -kp)
    np.testing.assert_array_equal(mj.actuator_biasprm[:, 2], -kd)
    assert mj.actuator_forcelimited.all()
    np.testing.assert_array_equal(mj.actuator_forcerange, np.stack([-m.dof_effort_limit[dof],
                                                                    m.dof_effort_limit[dof]], 1))
    joints = mj.actuator_trnid[:, 0]
    np.testing.assert_array_equal(mj.dof_armature[mj.jnt_dofadr[joints]], m.dof_armature[dof])
    np.testing.assert_array_equal(mj.dof_damping[mj.jnt_dofadr[joints]], m.dof_damping[dof])
    assert not mj.actuator_ctrllimited.any()


def test_the_observation_read_off_mujoco_is_kamino_s(walker):
    """A moving MuJoCo state (a reset pose, then random ``qvel`` of 1 rad/s or m/s per DoF and a tilt of the base)
    read through the kamino state (:func:`sim2sim.kamino_body_state`, then the environment's own ``_observe``)
    gives the observation written directly from MuJoCo's coordinates: the base's angular velocity (the free joint's
    ``qvel[3:6]``, in its frame) times 0.25, gravity ``-R^T e_z``, the base's linear velocity ``R^T qvel[0:3]``, the
    command, the actuated hinges' ``qpos`` about the range's centre and 0.05 ``qvel``, the last action and the gait
    clock. They agree to 2e-5 (float32 rounding of entries of order 1). A body velocity taken at the wrong point (the
    subtree CoM instead of the body's), a quaternion in the other order or a hinge mapped to another DoF differs by
    0.1-1."""
    env, mj, layout = walker
    rng = np.random.default_rng(0)
    ps = env.full_state(env.reset(jax.random.PRNGKey(0)).pipeline_state)
    d = mujoco.MjData(mj)
    sim2sim.set_mujoco_state(env, layout, mj, d, ps)
    d.qpos[3:7] = [np.cos(0.15), np.sin(0.15), 0.0, 0.0]  # the base tilted by 0.3 rad about x
    d.qvel[:] = rng.normal(size=mj.nv)
    mujoco.mj_forward(mj, d)
    command = np.array([0.4, -0.1, 0.2], np.float32)
    last = rng.uniform(-1, 1, env.action_size).astype(np.float32)
    phase = 0.3
    obs = np.asarray(sim2sim._observer(env)(*(x[None] for x in (
        *sim2sim.kamino_body_state(layout, d), command, last, np.float32(phase))))[0][0])
    base = mujoco.mj_name2id(mj, mujoco.mjtObj.mjOBJ_BODY, "pelvis")
    R = d.xmat[base].reshape(3, 3)
    joints = [mujoco.mj_name2id(mj, mujoco.mjtObj.mjOBJ_JOINT, mj.actuator(a).name) for a in range(mj.nu)]
    assert min(joints) >= 0  # dr_legs' actuators are named after their joints
    q = d.qpos[mj.jnt_qposadr[joints]]
    qd = d.qvel[mj.jnt_dofadr[joints]]
    centre = 0.5 * (env.action_lower + env.action_upper)
    expected = np.concatenate([0.25 * d.qvel[3:6], -R[2], R.T @ d.qvel[0:3], command, q - centre, 0.05 * qd, last,
                               [np.sin(2 * np.pi * phase), np.cos(2 * np.pi * phase)]])
    assert obs.shape == expected.shape == (env.observation_size,)
    np.testing.assert_allclose(obs, expected, rtol=0, atol=2e-5)


def test_the_shipped_policy_walks_in_mujoco(tmp_path):
    """``kamino eval dr_legs_walk --sim mujoco``: 2 episodes of 2 s at forward commands in 0.3-0.5 m/s in MuJoCo with
    the export's settings (2 ms, implicitfast, 4 ms ``<connect>`` time constant). Neither episode falls, the robot
    moves forward at more than 0.25 m/s and the tracking error stays under 0.15 m/s; a robot that stood still would
    score the command itself (0.3-0.5 m/s). Measured: 0.076 m/s at a forward speed of 0.307 m/s (mean command
    0.303); over 64 episodes of 10 s 0.068 m/s, kamino's own 0.069 on the same episodes (docs/envs.md, "Sim-to-sim
    in MuJoCo"). Short episodes weigh the start from rest more, which the bound allows for. The soft loop closures
    open by at most 1.7 mm over those 64 episodes; at twice the time constant (the 4 ms step, where MuJoCo keeps a
    time constant at two steps or more) they open by 5 mm and the error rises to 0.086 m/s, and at MuJoCo's default
    20 ms every episode falls: the bound of 3 mm catches loop closures softer than the export's."""
    out = tmp_path / "mujoco.json"
    rc = rl_eval.main(["dr_legs_walk", "--sim", "mujoco", "--episodes", "2", "--seconds", "2", "--env",
                       "reset_bank=8", "--out", str(out)])
    assert rc == 0
    r = json.loads(out.read_text())
    assert r["sim"] == "mujoco" and r["episodes"] == 2 and r["policy_steps"] == 100
    assert r["mujoco"]["timestep"] == 0.002 and r["mujoco"]["integrator"] == "implicitfast"
    assert r["fall_fraction"] == 0.0
    assert r["forward_speed_mean"] > 0.25
    assert r["tracking_error_mean"] < 0.15
    assert r["loop_gap_max"] < 3e-3
