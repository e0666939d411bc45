"""A body attached to the world by a FREE joint collides with the world's geoms (docs/conventions.md,
"Contacts": a FREE joint constrains nothing, so it does not exclude its bodies' contact pairs)."""

from __future__ import annotations

import numpy as np
import pytest

import kamino
from kamino import GeomType
from kamino.models.shapes import box_inertia
from tests.helpers import BACKENDS

DT = 1.0 / 240.0
HALF = 0.1  # half edge of the box [m]
DROP = 0.02  # initial gap between the box and the plane [m]


def _free_box_over_plane(joint: kamino.JointType = kamino.JointType.FREE) -> kamino.Model:
    """A cube of edge ``2 HALF`` joined to the world by ``joint``, ``DROP`` above a world plane at z = 0."""
    b = kamino.ModelBuilder(gravity=(0.0, 0.0, -9.81))
    z0 = HALF + DROP
    box = b.add_body(mass=1.0, inertia=box_inertia(1.0, (2 * HALF,) * 3), pos=(0.0, 0.0, z0), name="box")
    b.add_geom(GeomType.BOX, box, size=(HALF, HALF, HALF), friction=0.8, name="box")
    b.add_geom(GeomType.PLANE, -1, friction=0.8, name="ground")
    # joint frame at the box's CoM (world frame for the world side), so the joint's pose is its reference
    b.add_joint(joint, parent=-1, child=box, parent_frame=((0.0, 0.0, z0), (0, 0, 0, 1)), name="free")
    return b.finalize()


def test_free_joint_keeps_the_world_pair_and_other_joints_exclude_it():
    assert _free_box_over_plane().num_pairs == 1  # the box-plane pair is a candidate
    # a joint that constrains something still excludes the pair (the rule is unchanged for non-FREE joints)
    assert _free_box_over_plane(kamino.JointType.CARTESIAN).num_pairs == 0


@pytest.mark.parametrize("variant", BACKENDS)
def test_free_box_dropped_on_a_world_plane_comes_to_rest_on_it(variant):
    model = _free_box_over_plane()
    # 2 cm fall: contact after sqrt(2 DROP / g) = 64 ms (16 steps); 0.5 s leaves ~100 steps to settle
    traj = variant.rollout(model, kamino.init_state(model), num_steps=120, config=kamino.SolverConfig(dt=DT))
    z = np.asarray(traj.body_q)[:, 0, 2]
    u = np.asarray(traj.body_u)[-20:, 0]
    # it never falls through: penetration below the documented resting penetration bound (conventions.md,
    # "Speculative contacts": ~1e-9 m at rest; 1e-4 m is the bound, also covering the impact step)
    assert (HALF - z).max() < 1e-4
    # and it lands: the last 20 steps sit at the half size and at rest (PADMM tolerance 1e-6 on the impulses
    # leaves speeds orders of magnitude below 1e-3 m/s once the inelastic impact is over)
    assert np.abs(z[-20:] - HALF).max() < 1e-4
    assert np.abs(u).max() < 1e-3
    assert np.asarray(traj.info.num_contacts)[-1, 0] == 4  # the four corners of the bottom face
