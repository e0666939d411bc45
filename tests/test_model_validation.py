"""Model validation (ModelError messages), multi-world layout (replicate/concat), loop counts,
backend/config argument checks and model immutability. No physics is run here."""

from __future__ import annotations

import dataclasses
import re

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import kamino
from kamino import JointType, ModelBuilder, ModelError
from kamino.model import count_loops
from kamino.models import chain_of_loops, double_pendulum, fourbar, pendulum, slider_crank

I3 = np.eye(3) * 0.01  # a valid (isotropic) inertia


def _one_body(**body_kwargs) -> ModelBuilder:
    """A builder holding one body named ``body_kwargs['name']`` (valid unless overridden)."""
    kw = {"mass": 1.0, "inertia": I3, "pos": (0.0, 0.0, 1.0)}
    kw.update(body_kwargs)
    b = ModelBuilder()
    b.add_body(**kw)
    return b


def _two_bodies() -> ModelBuilder:
    b = ModelBuilder()
    b.add_body(1.0, I3, pos=(0.0, 0.0, 1.0), name="upper_arm")
    b.add_body(1.0, I3, pos=(0.0, 0.0, 0.5), name="forearm")
    return b


# ---------------------------------------------------------------------------------------------
# Bodies. All of these are accepted by add_body and rejected by finalize().
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("mass", [0.0, -2.5])
def test_nonpositive_mass(mass):
    b = _one_body(mass=mass, name="weightless_widget")
    with pytest.raises(ModelError, match=r"body 'weightless_widget'.*mass must be > 0"):
        b.finalize()


def test_nonfinite_mass():
    b = _one_body(mass=float("nan"), name="nan_mass_block")
    with pytest.raises(ModelError, match=r"body 'nan_mass_block'.*mass is nan"):
        b.finalize()


def test_inertia_not_symmetric():
    I = np.array([[1.0, 0.1, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
    b = _one_body(inertia=I, name="lopsided_gear")
    with pytest.raises(ModelError, match=r"body 'lopsided_gear'.*inertia is not symmetric"):
        b.finalize()


@pytest.mark.parametrize("moments", [(1.0, 1.0, -0.5), (1.0, 1.0, 0.0)])
def test_inertia_not_positive_definite(moments):
    b = _one_body(inertia=np.diag(moments), name="negative_spinner")
    with pytest.raises(ModelError, match=r"body 'negative_spinner'.*inertia is not positive definite"):
        b.finalize()


def test_inertia_triangle_inequality():
    b = _one_body(inertia=np.diag([1.0, 1.0, 3.0]), name="impossible_disk")
    with pytest.raises(ModelError, match=r"body 'impossible_disk'.*inertia violates the triangle inequality"):
        b.finalize()


def test_inertia_triangle_equality_is_accepted():
    # a thin plate: Izz = Ixx + Iyy exactly is physical (the limit case)
    model = _one_body(inertia=np.diag([1.0, 2.0, 3.0]), name="thin_plate").finalize()
    assert model.body_names == ("thin_plate",)


def test_zero_body_quaternion():
    b = _one_body(quat=(0.0, 0.0, 0.0, 0.0), name="unoriented_puck")
    with pytest.raises(ModelError, match=r"body 'unoriented_puck'.*zero quaternion"):
        b.finalize()


def test_non_unit_body_quaternion():
    b = _one_body(quat=(0.0, 0.0, 0.0, 1.01), name="stretched_rotor")
    with pytest.raises(ModelError, match=r"body 'stretched_rotor'.*quaternion norm is 1\.01, not 1"):
        b.finalize()


def test_nearly_unit_quaternion_is_accepted_and_normalised():
    q = np.array([0.0, 0.0, 0.0, 1.0 + 1e-8])  # inside the 1e-6 unit-norm tolerance
    model = _one_body(quat=q, name="almost_unit").finalize()
    # stored normalised: float64 round-off only
    assert np.linalg.norm(model.body_q0[0, 3:]) == pytest.approx(1.0, abs=1e-15)


def test_nan_body_position():
    b = _one_body(pos=(0.0, float("nan"), 1.0), name="lost_marble")
    with pytest.raises(ModelError, match=r"body 'lost_marble'.*pos: contains NaN or inf"):
        b.finalize()


def test_nan_inertia():
    I = np.eye(3) * 0.01
    I[1, 1] = np.nan
    b = _one_body(inertia=I, name="fuzzy_flywheel")
    with pytest.raises(ModelError, match=r"body 'fuzzy_flywheel'.*inertia: contains NaN or inf"):
        b.finalize()


def test_inf_body_velocity():
    b = _one_body(velocity=(np.inf, 0.0, 0.0), name="warp_drive")
    with pytest.raises(ModelError, match=r"body 'warp_drive'.*velocity: contains NaN or inf"):
        b.finalize()


def test_body_shape_errors_raise_at_add_time():
    b = ModelBuilder()
    with pytest.raises(ModelError, match=r"body 'flat_thing' pos: expected 3 numbers"):
        b.add_body(1.0, I3, pos=(0.0, 1.0), name="flat_thing")
    with pytest.raises(ModelError, match=r"body 'quat_short' quat: expected 4 numbers"):
        b.add_body(1.0, I3, quat=(0.0, 0.0, 1.0), name="quat_short")


def test_inertia_wrong_shape():
    b = _one_body(inertia=np.eye(2), name="two_d_body")
    with pytest.raises(ModelError, match=r"body 'two_d_body'.*inertia must be 3x3"):
        b.finalize()


def test_empty_model_and_duplicate_names():
    with pytest.raises(ModelError, match="model has no bodies"):
        ModelBuilder().finalize()
    b = _two_bodies()
    b.add_body(1.0, I3, name="forearm")
    with pytest.raises(ModelError, match=r"body name 'forearm' is used twice"):
        b.finalize()
    b = _two_bodies()
    b.add_joint(JointType.REVOLUTE, -1, 0, axis=(0, 1, 0), name="elbow")
    b.add_joint(JointType.REVOLUTE, 0, 1, axis=(0, 1, 0), name="elbow")
    with pytest.raises(ModelError, match=r"joint name 'elbow' is used twice"):
        b.finalize()


def test_nonfinite_gravity():
    b = ModelBuilder(gravity=(0.0, 0.0, np.nan))
    b.add_body(1.0, I3, name="floater")
    with pytest.raises(ModelError, match=r"gravity: contains NaN or inf"):
        b.finalize()


# ---------------------------------------------------------------------------------------------
# Joints. add_joint stores the joint; the checks below fire in finalize().
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("parent", [2, 17, -2])
def test_joint_parent_does_not_exist(parent):
    b = _two_bodies()
    b.add_joint(JointType.REVOLUTE, parent, 1, axis=(0, 1, 0), name="orphan_elbow")
    with pytest.raises(ModelError, match=rf"joint 'orphan_elbow'.*parent body {parent} does not exist"):
        b.finalize()


@pytest.mark.parametrize("child", [2, 9, -1])
def test_joint_child_does_not_exist(child):
    b = _two_bodies()
    b.add_joint(JointType.REVOLUTE, 0, child, axis=(0, 1, 0), name="dangling_wrist")
    with pytest.raises(ModelError, match=rf"joint 'dangling_wrist'.*child body {child} does not exist"):
        b.finalize()


def test_joint_body_to_itself():
    b = _two_bodies()
    b.add_joint(JointType.REVOLUTE, 1, 1, axis=(0, 1, 0), name="ouroboros")
    with pytest.raises(ModelError, match=r"joint 'ouroboros'.*connects body 1 to itself"):
        b.finalize()


def test_joint_zero_length_axis():
    b = _two_bodies()
    b.add_joint(JointType.REVOLUTE, 0, 1, axis=(0.0, 0.0, 0.0), name="axisless_knee")
    with pytest.raises(ModelError, match=r"joint 'axisless_knee'.*zero-length axis"):
        b.finalize()


def test_joint_axis2_problems():
    b = _two_bodies()
    b.add_joint(JointType.UNIVERSAL, 0, 1, axis=(1, 0, 0), axis2=(0, 0, 0), name="cardan_nil")
    with pytest.raises(ModelError, match=r"joint 'cardan_nil'.*zero-length axis2"):
        b.finalize()
    b = _two_bodies()
    b.add_joint(JointType.UNIVERSAL, 0, 1, axis=(1, 0, 0), axis2=(-2, 0, 0), name="cardan_flat")
    with pytest.raises(ModelError, match=r"joint 'cardan_flat'.*axis2 is parallel to axis"):
        b.finalize()


@pytest.mark.parametrize("which", ["parent_frame position", "child_frame position"])
def test_joint_frame_inf(which):
    b = _two_bodies()
    bad = ((0.0, np.inf, 0.0), (0, 0, 0, 1))
    good = ((0.0, 0.0, 0.0), (0, 0, 0, 1))
    frames = {"parent_frame": bad, "child_frame": good} if which.startswith("parent") else \
        {"parent_frame": good, "child_frame": bad}
    b.add_joint(JointType.REVOLUTE, 0, 1, axis=(0, 1, 0), name="infinite_hinge", **frames)
    with pytest.raises(ModelError, match=rf"joint 'infinite_hinge'.*{which}: contains NaN or inf"):
        b.finalize()


def test_joint_frame_quaternions():
    b = _two_bodies()
    b.add_joint(JointType.REVOLUTE, 0, 1, parent_frame=((0, 0, 0), (0, 0, 0, 0)), name="blank_pivot")
    with pytest.raises(ModelError, match=r"joint 'blank_pivot'.*parent_frame quaternion: zero quaternion"):
        b.finalize()
    b = _two_bodies()
    b.add_joint(JointType.REVOLUTE, 0, 1, child_frame=((0, 0, 0), (0, 0, 0, 1.01)), name="bloated_pivot")
    with pytest.raises(ModelError, match=r"joint 'bloated_pivot'.*child_frame quaternion: quaternion norm"):
        b.finalize()


def test_joint_lower_limit_above_upper():
    b = _two_bodies()
    b.add_joint(JointType.REVOLUTE, 0, 1, axis=(0, 1, 0), limits=(1.0, -1.0), name="inverted_stop")
    with pytest.raises(ModelError, match=r"joint 'inverted_stop'.*lower limit 1\.0 > upper limit -1\.0"):
        b.finalize()


def test_joint_limit_nan():
    b = _two_bodies()
    b.add_joint(JointType.REVOLUTE, 0, 1, axis=(0, 1, 0), limits=(np.nan, 1.0), name="vague_stop")
    with pytest.raises(ModelError, match=r"joint 'vague_stop'.*limits contain NaN"):
        b.finalize()


def test_equal_limits_are_accepted():
    b = _two_bodies()
    b.add_joint(JointType.REVOLUTE, 0, 1, axis=(0, 1, 0), limits=(0.3, 0.3), name="locked")
    model = b.finalize()
    assert model.dof_lower.tolist() == [0.3] and model.dof_upper.tolist() == [0.3]


def test_joint_errors_raised_at_add_time():
    b = _two_bodies()
    with pytest.raises(ModelError, match=r"joint 'mystery_joint': unknown joint type 42"):
        b.add_joint(42, 0, 1, name="mystery_joint")
    with pytest.raises(ModelError, match=r"joint 'bad_limits': limits must be \(lower, upper\)"):
        b.add_joint(JointType.REVOLUTE, 0, 1, limits=1.0, name="bad_limits")
    with pytest.raises(ModelError, match=r"joint 'short_axis' axis: expected 3 numbers"):
        b.add_joint(JointType.REVOLUTE, 0, 1, axis=(0, 1), name="short_axis")
    with pytest.raises(ModelError, match=r"joint 'far_anchor': parent 0 or child 5 is not a body"):
        b.add_joint_at(JointType.REVOLUTE, 0, 5, anchor=(0, 0, 0), name="far_anchor")
    with pytest.raises(ModelError, match=r"joint 'motorised': actuation must be a kamino.Actuation"):
        b.add_joint(JointType.REVOLUTE, 0, 1, actuation="pd", name="motorised")
    assert b._joints == []  # nothing was stored by the failed calls


def test_first_error_reported_names_the_bad_joint_not_a_good_one():
    b = _two_bodies()
    b.add_joint(JointType.REVOLUTE, -1, 0, axis=(0, 1, 0), name="good_shoulder")
    b.add_joint(JointType.REVOLUTE, 0, 1, axis=(0, 0, 0), name="bad_elbow")
    with pytest.raises(ModelError, match=r"joint 'bad_elbow' \(index 1\)"):
        b.finalize()


# ---------------------------------------------------------------------------------------------
# replicate / concat layout
# ---------------------------------------------------------------------------------------------

_PER_BODY = ("body_mass", "body_inertia", "body_q0", "body_u0")
_PER_JOINT = ("joint_type", "joint_anchor_B", "joint_anchor_F", "joint_frame_B", "joint_frame_F",
              "joint_dof_count", "joint_coord_count", "joint_cts_count")
_PER_DOF = ("dof_lower", "dof_upper")
_ENTITIES = ("body", "joint", "dof", "coord", "cts")


def _prefix(counts) -> list[int]:
    return np.concatenate([[0], np.cumsum(counts)[:-1]]).astype(int).tolist()


def _world_sizes(m: kamino.Model) -> dict[str, int]:
    """Sizes of a single-world model, per entity."""
    return {"body": m.num_bodies, "joint": m.num_joints, "dof": m.num_dofs, "coord": m.num_coords,
            "cts": m.num_constraints}


def _check_world_equals(multi: kamino.Model, w: int, single: kamino.Model) -> None:
    """World ``w`` of ``multi`` equals the single-world ``single`` up to index shifts (exact)."""
    assert single.num_worlds == 1
    bs, nb = int(multi.world_body_start[w]), int(multi.world_body_count[w])
    js, nj = int(multi.world_joint_start[w]), int(multi.world_joint_count[w])
    ds, nd = int(multi.world_dof_start[w]), int(multi.world_dof_count[w])
    cs, nc = int(multi.world_coord_start[w]), int(multi.world_coord_count[w])
    rs, nr = int(multi.world_cts_start[w]), int(multi.world_cts_count[w])
    sizes = _world_sizes(single)
    assert (nb, nj, nd, nc, nr) == tuple(sizes[e] for e in _ENTITIES)
    for f in _PER_BODY:
        np.testing.assert_array_equal(getattr(multi, f)[bs:bs + nb], getattr(single, f), err_msg=f)
    for f in _PER_JOINT:
        np.testing.assert_array_equal(getattr(multi, f)[js:js + nj], getattr(single, f), err_msg=f)
    for f in _PER_DOF:
        np.testing.assert_array_equal(getattr(multi, f)[ds:ds + nd], getattr(single, f), err_msg=f)
    np.testing.assert_array_equal(multi.gravity[w], single.gravity[0])
    assert multi.body_names[bs:bs + nb] == single.body_names
    assert multi.joint_names[js:js + nj] == single.joint_names
    assert np.all(multi.body_world[bs:bs + nb] == w)
    assert np.all(multi.joint_world[js:js + nj] == w)
    # index fields: body indices shift by the world's body start; the world (-1) stays -1
    p = single.joint_parent
    np.testing.assert_array_equal(multi.joint_parent[js:js + nj], np.where(p >= 0, p + bs, -1))
    np.testing.assert_array_equal(multi.joint_child[js:js + nj], single.joint_child + bs)
    np.testing.assert_array_equal(multi.joint_dof_start[js:js + nj], single.joint_dof_start + ds)
    np.testing.assert_array_equal(multi.joint_coord_start[js:js + nj], single.joint_coord_start + cs)
    np.testing.assert_array_equal(multi.joint_cts_start[js:js + nj], single.joint_cts_start + rs)
    # name lookups resolve inside the world
    for name in single.body_names:
        assert multi.body_index(name, w) == single.body_index(name) + bs
    for name in single.joint_names:
        assert multi.joint_index(name, w) == single.joint_index(name) + js


def _check_consistent(m: kamino.Model) -> None:
    """Per-world starts are prefix sums of the counts, and the world counts agree with the per-joint
    counts (every joint's DoFs / coordinates / rows lie inside its world's segment)."""
    W = m.num_worlds
    totals = {"body": m.num_bodies, "joint": m.num_joints, "dof": m.num_dofs, "coord": m.num_coords,
              "cts": m.num_constraints}
    for e in _ENTITIES:
        start, count = getattr(m, f"world_{e}_start"), getattr(m, f"world_{e}_count")
        assert start.shape == count.shape == (W,)
        assert start.tolist() == _prefix(count), e
        assert int(count.sum()) == totals[e], e
    for e in ("dof", "coord", "cts"):
        jcount, jstart = getattr(m, f"joint_{e}_count"), getattr(m, f"joint_{e}_start")
        assert jstart.tolist() == _prefix(jcount), e
        for w in range(W):
            js, nj = int(m.world_joint_start[w]), int(m.world_joint_count[w])
            assert int(jcount[js:js + nj].sum()) == int(getattr(m, f"world_{e}_count")[w]), (e, w)
            if nj:
                assert int(jstart[js]) == int(getattr(m, f"world_{e}_start")[w]), (e, w)
    assert m.body_world.tolist() == np.repeat(np.arange(W), m.world_body_count).tolist()
    assert m.joint_world.tolist() == np.repeat(np.arange(W), m.world_joint_count).tolist()
    # every joint connects bodies of its own world (or the world)
    for j in range(m.num_joints):
        w = int(m.joint_world[j])
        lo, hi = int(m.world_body_start[w]), int(m.world_body_start[w] + m.world_body_count[w])
        assert lo <= m.joint_child[j] < hi
        assert m.joint_parent[j] == -1 or lo <= m.joint_parent[j] < hi


def test_replicate_fourbar_layout():
    base = fourbar()
    n = 3
    rep = kamino.replicate(base, n)
    nb, nj = base.num_bodies, base.num_joints
    assert rep.num_worlds == n
    for e, size in _world_sizes(base).items():
        assert int(getattr(rep, f"world_{e}_count").sum()) == n * size, e
        assert getattr(rep, f"world_{e}_count").tolist() == [size] * n, e
        assert getattr(rep, f"world_{e}_start").tolist() == [k * size for k in range(n)], e
    assert (rep.num_bodies, rep.num_joints) == (n * nb, n * nj)
    assert (rep.num_dofs, rep.num_coords, rep.num_constraints) == \
        (n * base.num_dofs, n * base.num_coords, n * base.num_constraints)
    for f in _PER_BODY + _PER_JOINT + _PER_DOF:
        assert getattr(rep, f).shape[0] == n * getattr(base, f).shape[0], f
    assert rep.world_body_start.tolist() == [0, nb, 2 * nb]
    assert rep.body_world.tolist() == [0] * nb + [1] * nb + [2] * nb
    assert rep.joint_world.tolist() == [0] * nj + [1] * nj + [2] * nj
    assert rep.gravity.shape == (n, 3)
    # fourbar's "fix" joint hangs from the world: -1 must survive the shift in every copy
    assert base.joint_parent[0] == -1
    parent = rep.joint_parent.reshape(n, nj)
    shift = nb * np.arange(n)[:, None]
    assert parent[:, 0].tolist() == [-1] * n
    np.testing.assert_array_equal(parent[:, 1:], base.joint_parent[1:] + shift)
    np.testing.assert_array_equal(rep.joint_child.reshape(n, nj), base.joint_child + shift)
    for w in range(n):
        _check_world_equals(rep, w, base)
        assert count_loops(rep, w) == 1
    _check_consistent(rep)


def test_concat_heterogeneous_layout():
    singles = [pendulum(), fourbar(), slider_crank()]
    cat = kamino.concat(singles)
    assert cat.num_worlds == 3
    for e in _ENTITIES:
        counts = [_world_sizes(s)[e] for s in singles]
        assert getattr(cat, f"world_{e}_count").tolist() == counts, e
        assert getattr(cat, f"world_{e}_start").tolist() == _prefix(counts), e
    # world_cts_* agree with the per-joint row counts
    for w in range(3):
        js, nj = int(cat.world_joint_start[w]), int(cat.world_joint_count[w])
        rows = cat.joint_cts_count[js:js + nj]
        assert int(rows.sum()) == int(cat.world_cts_count[w])
        assert int(cat.joint_cts_start[js]) == int(cat.world_cts_start[w])
        assert int(cat.world_cts_start[w]) == int(cat.joint_cts_count[:js].sum())
    for w, s in enumerate(singles):
        _check_world_equals(cat, w, s)
    assert [count_loops(cat, w) for w in range(3)] == [0, 1, 1]
    _check_consistent(cat)


def test_concat_of_multi_world_models():
    """concat accepts multi-world inputs: worlds keep their order, world ids and body indices shift."""
    a = kamino.replicate(pendulum(), 2)
    b = kamino.concat([fourbar(), double_pendulum()])
    cat = kamino.concat([a, b, slider_crank()])
    singles = [pendulum(), pendulum(), fourbar(), double_pendulum(), slider_crank()]
    assert cat.num_worlds == 5
    for w, s in enumerate(singles):
        _check_world_equals(cat, w, s)
    _check_consistent(cat)
    # replicate of a multi-world model repeats the whole block of worlds
    rep = kamino.replicate(b, 2)
    for w, s in enumerate([fourbar(), double_pendulum()] * 2):
        _check_world_equals(rep, w, s)
    _check_consistent(rep)


def test_replicate_and_concat_argument_errors():
    with pytest.raises(ModelError, match="number of copies must be >= 1"):
        kamino.replicate(pendulum(), 0)
    with pytest.raises(ModelError, match="no models given"):
        kamino.concat([])


def test_replicate_joint_free_world():
    b = ModelBuilder()
    b.add_body(1.0, I3, name="free_floater")
    rep = kamino.replicate(b.finalize(), 2)
    assert rep.num_joints == 0
    assert rep.joint_dof_start.shape == rep.joint_cts_start.shape == rep.joint_coord_start.shape == (0,)


# ---------------------------------------------------------------------------------------------
# Loops and constraint rows
# ---------------------------------------------------------------------------------------------


def test_loop_counts():
    assert count_loops(pendulum()) == 0
    assert count_loops(double_pendulum()) == 0
    assert count_loops(fourbar()) == 1
    assert count_loops(slider_crank()) == 1
    assert count_loops(chain_of_loops(8)) == 8
    assert count_loops(chain_of_loops(8, closure="spherical")) == 8


@pytest.mark.parametrize("n", [1, 2, 3, 5, 8])
def test_chain_of_loops_rows_grow_linearly(n):
    m = chain_of_loops(n)
    # FIXED (6 rows) + per loop 4 revolutes x 5 rows
    assert m.num_constraints == 6 + 20 * n
    assert int(m.world_cts_count[0]) == 6 + 20 * n
    assert m.num_bodies == 1 + 3 * n and m.num_joints == 1 + 4 * n
    assert count_loops(m) == n
    # spherical closures: 3 rows instead of 5 per loop
    assert chain_of_loops(n, closure="spherical").num_constraints == 6 + 18 * n


# ---------------------------------------------------------------------------------------------
# Backends, solver configuration, immutability
# ---------------------------------------------------------------------------------------------


def test_warp_backend_rejects_bad_input_like_the_reference():
    m = pendulum()
    s = kamino.init_state(m)
    with pytest.raises(ValueError, match="body_q"):
        kamino.step(m, s.replace(body_q=s.body_q[:0]), backend="warp")
    half = jax.tree_util.tree_map(lambda x: x.astype(jnp.float16) if jnp.issubdtype(x.dtype, jnp.floating) else x, s)
    with pytest.raises(ValueError, match="float32 and float64"):
        kamino.step(m, half, backend="warp")
    with pytest.raises(ValueError, match="linear_solver='cr'"):
        kamino.step(m, s, config=kamino.SolverConfig(warp=kamino.WarpSettings(jacobian="dense", linear_solver="cr")),
                    backend="warp")


def test_unknown_backend():
    m = pendulum()
    s = kamino.init_state(m)
    with pytest.raises(ValueError, match=r"unknown backend 'nope'"):
        kamino.step(m, s, backend="nope")
    with pytest.raises(ValueError, match=r"unknown backend 'nope'"):
        kamino.rollout(m, s, num_steps=2, backend="nope")


@pytest.mark.parametrize("dt", [-1, 0.0, float("nan"), float("inf")])
def test_solver_config_bad_dt(dt):
    with pytest.raises(ValueError, match=r"SolverConfig\.dt"):
        kamino.SolverConfig(dt=dt)


def test_solver_config_bad_integrator():
    with pytest.raises(ValueError, match=r"SolverConfig\.integrator.*'rk4'"):
        kamino.SolverConfig(integrator="rk4")


@pytest.mark.parametrize(
    ("field", "value"),
    [("stabilisation.baumgarte", 1.5), ("max_iterations", 0), ("tolerance", 0.0), ("penalty.rho", -1.0),
     ("penalty.eta", -1e-3), ("penalty.rho_free", 0.0), ("penalty.mode", "balanced"), ("warmstart_scale", 2.0),
     ("warp.jacobian", "csr"), ("warp.linear_solver", "qr"), ("warp.cr_iterations", 0),
     ("stabilisation.projection_shift", 0.0), ("contact_margin", -1.0), ("max_unconverged_steps", -1)],
)
def test_solver_config_other_fields(field, value):
    """A bad value is refused naming its path (a nested setting: ``SolverConfig.warp.linear_solver``)."""
    with pytest.raises(ValueError, match=rf"SolverConfig\.{re.escape(field)}: .*\(got {re.escape(repr(value))}\)"):
        kamino.SolverConfig().replace(**{field: value})


def test_solver_config_nests_its_settings():
    """15 top-level fields; the nested settings go by their dotted names, a wrong kind or name is refused."""
    assert len(dataclasses.fields(kamino.SolverConfig)) <= 15
    cfg = kamino.SolverConfig().replace(tolerance=1e-4, **{"warp.linear_solver": "cr", "penalty.rho": 0.05})
    assert cfg.warp == kamino.WarpSettings(linear_solver="cr") and cfg.penalty == kamino.Penalty(rho=0.05)
    assert cfg.tolerance == 1e-4 and cfg.stabilisation == kamino.Stabilisation()
    assert cfg.replace(penalty=kamino.Penalty(mode="fixed")).penalty.mode == "fixed"
    with pytest.raises(TypeError, match=r"SolverConfig has no setting 'linear_solver'.*warp\.linear_solver"):
        cfg.replace(linear_solver="cr")
    with pytest.raises(TypeError, match=r"no setting 'warp\.rho'"):
        cfg.replace(**{"warp.rho": 1.0})
    with pytest.raises(ValueError, match=r"SolverConfig\.warp: must be a kamino\.WarpSettings \(got 'cr'\)"):
        kamino.SolverConfig(warp="cr")


def test_solver_config_is_frozen_and_hashable():
    cfg = kamino.SolverConfig(dt=1e-3, integrator="midpoint")
    with pytest.raises(dataclasses.FrozenInstanceError):
        cfg.dt = 1.0
    assert hash(cfg) == hash(kamino.SolverConfig(dt=1e-3, integrator="midpoint"))


@pytest.mark.parametrize("make", [pendulum, lambda: kamino.replicate(fourbar(), 2),
                                  lambda: kamino.concat([pendulum(), slider_crank()])])
def test_model_is_immutable(make):
    model = make()
    before = float(model.body_mass[0])
    with pytest.raises(ValueError, match="read-only"):
        model.body_mass[0] = 123.0
    assert float(model.body_mass[0]) == before
    # every array field is read-only, not just body_mass
    for f in dataclasses.fields(model):
        v = getattr(model, f.name)
        if isinstance(v, np.ndarray):
            assert not v.flags.writeable, f.name
    with pytest.raises(dataclasses.FrozenInstanceError):
        model.body_mass = np.zeros(model.num_bodies)


def test_derived_models_do_not_alias_the_source():
    base = fourbar()
    rep = kamino.replicate(base, 2)
    cat = kamino.concat([base, base])
    for f in _PER_BODY + _PER_JOINT + _PER_DOF + ("joint_parent", "joint_child"):
        assert not np.shares_memory(getattr(rep, f), getattr(base, f)), f
        assert not np.shares_memory(getattr(cat, f), getattr(base, f)), f


# ---- geoms and actuation ------------------------------------------------------------


def test_geom_errors_name_the_geom():
    def builder():
        b = kamino.ModelBuilder()
        b.add_body(mass=1.0, inertia=(0.01,) * 3)
        return b

    cases = [
        (dict(type=kamino.GeomType.SPHERE, body=0, size=0.0, name="dot"), r"geom 'dot' \(index 0\): a SPHERE needs 1"),
        (dict(type=kamino.GeomType.BOX, body=0, size=(0.1, 0.1), name="flat"), r"geom 'flat'.*BOX needs 3"),
        (dict(type=kamino.GeomType.SPHERE, body=3, size=0.1, name="lost"), r"geom 'lost'.*body 3 does not exist"),
        (dict(type=kamino.GeomType.SPHERE, body=0, size=0.1, friction=-1, name="grippy"), r"geom 'grippy'.*friction"),
        (dict(type=kamino.GeomType.SPHERE, body=0, size=0.1, restitution=1.5, name="bouncy"),
         r"geom 'bouncy'.*restitution must lie in \[0, 1\]"),
        (dict(type=kamino.GeomType.SPHERE, body=0, size=0.1, quat=(0, 0, 0, 2), name="twisted"),
         r"geom 'twisted'.*quaternion norm"),
        (dict(type=kamino.GeomType.SPHERE, body=0, size=float("nan"), name="nan"), r"geom 'nan'.*NaN"),
    ]
    for kwargs, pattern in cases:
        b = builder()
        b.add_geom(**kwargs)
        with pytest.raises(ModelError, match=pattern):
            b.finalize()
    b = builder()
    with pytest.raises(ModelError, match=r"geom 'odd': unknown geom type 9"):
        b.add_geom(9, 0, name="odd")
    b = builder()
    g0 = b.add_geom(kamino.GeomType.SPHERE, 0, size=0.1)
    g1 = b.add_geom(kamino.GeomType.BOX, 0, size=(0.1, 0.1, 0.1))
    b.set_collision(g0, g1, True)
    with pytest.raises(ModelError, match="same body"):
        b.finalize()


def test_actuation_errors_name_the_joint():
    b = _two_bodies()
    Act = kamino.Actuation
    with pytest.raises(ModelError, match=r"joint 'ball': position actuation needs a scalar-coordinate joint"):
        b.add_joint(JointType.SPHERICAL, 0, 1, actuation=Act("position", kp=1.0), name="ball")
    with pytest.raises(ModelError, match=r"joint 'lazy': position actuation needs positive gains"):
        b.add_joint(JointType.REVOLUTE, 0, 1, actuation=Act("position"), name="lazy")
    with pytest.raises(ModelError, match=r"joint 'ff': effort actuation takes no gains"):
        b.add_joint(JointType.REVOLUTE, 0, 1, actuation=Act("effort", kp=3.0), name="ff")
    with pytest.raises(ModelError, match=r"joint 'weak': effort_limit must be > 0"):
        b.add_joint(JointType.REVOLUTE, 0, 1, actuation=Act("position", kp=1.0, effort_limit=0.0), name="weak")
    with pytest.raises(ModelError, match=r"joint 'neg': armature must be >= 0"):
        b.add_joint(JointType.REVOLUTE, 0, 1, armature=-0.1, name="neg")
    with pytest.raises(ModelError, match=r"unknown actuation mode 'servo'"):
        b.add_joint(JointType.REVOLUTE, 0, 1, actuation=Act("servo"), name="servo")
    with pytest.raises(ModelError, match=r"joint 'weld': a FIXED joint has no DoF to actuate"):
        b.add_joint(JointType.FIXED, 0, 1, actuation=Act("effort"), name="weld")
    with pytest.raises(ModelError, match=r"joint 'many' damping: expected a number or 1 numbers"):
        b.add_joint(JointType.REVOLUTE, 0, 1, damping=(1.0, 2.0), name="many")
    assert b._joints == []


def test_replicate_and_concat_shift_geom_and_pair_indices():
    single = kamino.models.box_stack(2)
    mixed = kamino.concat([kamino.models.fourbar(), single, single])
    assert mixed.num_geoms == 2 * single.num_geoms
    assert mixed.num_pairs == 2 * single.num_pairs
    w2 = mixed.pair_world == 2
    assert np.all(mixed.geom_world[mixed.pair_geom_a[w2]] == 2)
    bodies = mixed.geom_body[mixed.geom_world == 2]
    assert np.all((bodies == -1) | (mixed.body_world[np.maximum(bodies, 0)] == 2))
    assert mixed.world_contact_capacity.tolist() == [0, 16, 16]
