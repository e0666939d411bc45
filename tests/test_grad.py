"""Differentiating through ``step`` in fixed-iteration mode."""

from __future__ import annotations

import jax
import jax.numpy as jnp

import kamino


def test_grad_of_pendulum_angle_matches_finite_differences():
    """The reverse-mode derivative of a pendulum's angle after 50 steps with respect to its initial rate, against
    a central difference of the same function. The two function values of the difference come from the program
    that ``jax.value_and_grad`` compiles (its forward pass computes the rollout itself): compiling the plain
    rollout as a third program would add its compile to the test's time and check nothing more."""
    model = kamino.models.pendulum(angle=0.3)
    state0 = kamino.init_state(model)
    # without curvature refinement, whose second solve doubles the unrolled iterations (this checks the gradient's
    # machinery, not the step's physics)
    cfg = kamino.SolverConfig(dt=1.0 / 240.0, fixed_iterations=True, max_iterations=30).replace(
        **{"stabilisation.curvature_refinement": False})

    lever = state0.body_q[0, :3] - jnp.array([0.0, 0.0, 1.0])  # CoM relative to the pivot

    def final_angle(w0):
        omega = jnp.array([0.0, 1.0, 0.0]) * w0
        twist = jnp.concatenate([jnp.cross(omega, lever), omega])  # rigid rotation about the pivot
        s = state0.replace(body_u=twist[None, :])
        traj = kamino.rollout(model, s, num_steps=50, config=cfg, backend="jax")  # the differentiable one
        return kamino.joint_positions(model, jax.tree.map(lambda x: x[-1], traj))[0]

    angle_and_grad = jax.value_and_grad(final_angle)
    w0 = 0.7
    g = float(angle_and_grad(jnp.asarray(w0))[1])
    h = 1e-5
    fd = (float(angle_and_grad(jnp.asarray(w0 + h))[0]) - float(angle_and_grad(jnp.asarray(w0 - h))[0])) / (2 * h)
    # central difference error O(h^2) ~ 1e-10 relative; the bound is 1e-4 relative
    assert abs(g - fd) <= 1e-4 * abs(fd), (g, fd)
    assert abs(fd) > 0.05  # the angle really depends on the initial speed
