"""Forward kinematics on the procedural robots with loops: random actuated configurations within the joint limits
converge to max |C| <= 1e-6; a world that does not is flagged and finite. The full 1000-configuration run of
``animatronic`` is ``kamino bench fk_convergence`` (GPU) — here it gets a CPU-sized sample."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
import pytest

import kamino
from kamino.bench import fk_convergence
from tests.helpers import JAX_GPU_TIER


# dr_legs: 250 configurations on the CPU (the solve of 1000 takes 14.5 s of one core at XLA's level 0, of 250 3.5 s;
# 0.99 lets 2 of 250 fail, and a failure rate of 2 % fails the test 88 times in 100); the 1000 in the gpu tier,
# where the 250 are its CPU check. The animatronic's case is in the slow tier: its FK also assembles in the default
# tier's test_robots.py::test_mechanism_assembles_over_the_box_of_actuated_limits[animatronic]
@pytest.mark.parametrize("name, num", [("dr_legs", 250),
                                       pytest.param("dr_legs", 1000, marks=JAX_GPU_TIER, id="dr_legs-1000"),
                                       pytest.param("animatronic", 8, marks=pytest.mark.slow, id="animatronic-8")])
def test_random_actuated_configurations_converge(name, num):
    robot = getattr(kamino.models, name)()
    samples = fk_convergence.random_actuated(robot, num, seed=1)
    model = kamino.replicate(robot, num)
    fk = kamino.forward_kinematics(model, actuated_positions=jnp.asarray(samples.reshape(-1)))
    converged = np.asarray(fk.converged)
    assert np.all(np.isfinite(np.asarray(fk.body_q))) and np.all(np.isfinite(np.asarray(fk.residual)))
    assert converged.mean() >= 0.99, f"{name}: {converged.mean():.3f} converged"
    assert np.all(np.asarray(fk.residual)[converged] <= 1e-6)
    # the converged poses are what they claim: loops closed, actuated joints at their targets
    state = kamino.init_state(model).replace(body_q=fk.body_q)
    viol = np.asarray(kamino.metrics(model, state)["constraint_violation"])
    assert np.all(viol[converged] <= 1e-6)
    q = np.asarray(kamino.joint_positions(model, state))
    dof_to_coord = _actuated_coordinate_index(robot)
    per_world = q.reshape(num, -1)[:, dof_to_coord]
    np.testing.assert_allclose(per_world[converged], samples[converged], atol=1e-6)


def _actuated_coordinate_index(model: kamino.Model) -> np.ndarray:
    """Coordinate index of each actuator's DoF (scalar-coordinate joints: DoF k is coordinate k)."""
    owner = np.repeat(np.arange(model.num_joints), model.joint_dof_count)
    joint = owner[model.actuator_dof]
    return model.joint_coord_start[joint] + (model.actuator_dof - model.joint_dof_start[joint])
