"""Heightfields (``GeomType.HFIELD``): the model's grids, the JAX reference's contact model against the grid
triangle below each candidate point (kamino/jax_ref/collision.py, "Heightfields"), MJCF import and export.

Tests run in float64 (``conftest.py``). "Rounding" tolerances of 1e-12 m allow for the frame changes and the
slope computed from normalised heights (about 1e-15 m per operation on metre-sized geometry).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import kamino
from kamino.jax_ref.collision import MAX_POINTS, HField, _hfield_surface
from kamino.jax_ref.collision import collide as _collide
from kamino.model import GeomType as G
from kamino.model import JointType, ModelBuilder, ModelError, concat, same_model, take_worlds
from kamino.viz._world import world_model

ROUNDING = 1e-12  # see module docstring


def quat(axis, angle) -> np.ndarray:
    """Unit quaternion (x, y, z, w) of a rotation by ``angle`` about ``axis``."""
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    return np.r_[np.sin(angle / 2) * axis, np.cos(angle / 2)]


def grid(nrow, ncol, size, data, adr=0) -> HField:
    """The :class:`HField` of one grid of normalised ``data`` (row-major, ``Model.hfield_data``'s order)."""
    return HField(jnp.asarray(np.ravel(data), float), jnp.asarray(adr), jnp.asarray(nrow), jnp.asarray(ncol),
                  jnp.asarray(size, float))


def ramp(nrow=4, ncol=7, rx=1.5, ry=1.0, z_top=0.6):
    """A ramp falling along +x: normalised heights 1 at ``x = -rx`` down to 0 at ``x = +rx`` (slope ``z_top / 2rx``)."""
    col = np.linspace(1.0, 0.0, ncol)
    return grid(nrow, ncol, (rx, ry, z_top, 0.2), np.tile(col, (nrow, 1))), z_top / (2 * rx)


def collide(ta, tb, pose_a, size_a, pose_b, size_b, margin, hfield=None):
    """``collide`` of numpy copies of the arguments (tuples welcome)."""
    args = (np.asarray(x, float) for x in (pose_a, size_a, pose_b, size_b))
    return _collide(ta, tb, *args, margin, hfield=hfield)


def _points(cp):
    return {k: np.asarray(getattr(cp, k)) for k in ("pos", "normal", "dist", "valid")}


# heightfield frame: turned about z and offset, so that the frame change is exercised
H_POSE = np.r_[0.3, -0.2, 0.5, quat((0, 0, 1), 0.4)]
FLAT = grid(3, 4, (1.0, 0.8, 0.25, 0.1), np.full(12, 0.4))  # all at 0.4 * 0.25 = 0.1 above the frame


def test_sphere_on_flat_heightfield_is_the_sphere_on_a_plane():
    """All heights equal: the triangle below the sphere is the plane z = 0.1 of the heightfield's frame, so the
    contact is PLANE-SPHERE's with the normal reversed (the heightfield is geom b), to rounding."""
    plane = np.r_[H_POSE[:3] + 0.1 * np.array([0, 0, 1.0]), H_POSE[3:]]
    for centre in ([0.35, -0.1, 0.62], [0.9, 0.1, 0.55], [-0.2, -0.7, 0.59]):
        sphere = np.r_[centre, 0, 0, 0, 1.0]
        h = _points(collide(G.SPHERE, G.HFIELD, sphere, (0.08, 0, 0), H_POSE, np.zeros(3), 0.1, hfield=FLAT))
        p = _points(collide(G.PLANE, G.SPHERE, plane, np.zeros(3), sphere, (0.08, 0, 0), 0.1))
        np.testing.assert_allclose(h["dist"], p["dist"], atol=ROUNDING)
        np.testing.assert_allclose(h["normal"], -p["normal"], atol=ROUNDING)
        np.testing.assert_allclose(h["pos"], p["pos"], atol=ROUNDING)
        assert h["valid"].tolist() == p["valid"].tolist()


def test_sphere_on_a_ramp_gets_the_ramp_normal():
    """Heights linear in x: every triangle lies in the ramp's plane, so the sphere's distance is its height above
    that plane along its normal ``(s, 0, 1) / sqrt(1 + s^2)`` (s the slope) less the radius, wherever it is."""
    hf, s = ramp()
    n = np.array([s, 0.0, 1.0]) / np.hypot(1.0, s)
    pose = np.r_[0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0]
    for x, y, z in ((-1.2, 0.3, 0.9), (0.1, -0.6, 0.45), (1.05, 0.95, 0.2)):
        h = _points(collide(G.SPHERE, G.HFIELD, np.r_[x, y, z, 0, 0, 0, 1.0], (0.1, 0, 0), pose, np.zeros(3), 1.0,
                            hfield=hf))
        surface = 0.6 * (1.0 - (x + 1.5) / 3.0)  # the ramp's height below the centre
        np.testing.assert_allclose(h["normal"][0], -n, atol=ROUNDING)
        np.testing.assert_allclose(h["dist"][0], (z - surface) * n[2] - 0.1, atol=ROUNDING)
        assert h["valid"][0]
    # the reference differentiates through the contact: d dist / d centre is the ramp's normal
    grad = jax.grad(lambda c: _collide(G.SPHERE, G.HFIELD, jnp.r_[c, 0, 0, 0, 1.0], jnp.array([0.1, 0, 0]),
                                       jnp.asarray(pose), jnp.zeros(3), 1.0, hfield=hf).dist[0])
    np.testing.assert_allclose(grad(jnp.array([0.1, -0.6, 0.45])), n, atol=ROUNDING)


def test_box_on_flat_heightfield_has_the_four_contacts_of_a_plane():
    """A tilted box over a flat heightfield: the 4 corners nearest it, with the distances and points of
    PLANE-BOX (as a set: the two pairs order ties alike, but the frames' rounding may differ)."""
    plane = np.r_[H_POSE[:3] + 0.1 * np.array([0, 0, 1.0]), H_POSE[3:]]
    for q in (quat((0, 0, 1), 0.2), quat((1, 1, 0), 0.3)):
        box = np.r_[0.4, -0.1, 0.69, q]
        size = np.array([0.15, 0.1, 0.05])
        h = _points(collide(G.BOX, G.HFIELD, box, size, H_POSE, np.zeros(3), 0.5, hfield=FLAT))
        p = _points(collide(G.PLANE, G.BOX, plane, np.zeros(3), box, size, 0.5))
        assert h["dist"].shape == (4,) and h["valid"].all()
        i, j = np.argsort(h["dist"]), np.argsort(p["dist"])
        np.testing.assert_allclose(h["dist"][i], p["dist"][j], atol=ROUNDING)
        np.testing.assert_allclose(h["pos"][i], p["pos"][j], atol=ROUNDING)
        np.testing.assert_allclose(h["normal"], -p["normal"], atol=ROUNDING)


def test_capsule_and_cylinder_on_a_ramp_are_their_plane_pairs():
    """On a ramp (planar terrain) CAPSULE-HFIELD and CYLINDER-HFIELD equal the PLANE pairs of the ramp's plane:
    the same candidate points (the cylinder's from the ramp's normal below its centre) with the same distances."""
    hf, s = ramp()
    th = np.arctan(s)
    plane = np.r_[0.0, 0.0, 0.3, quat((0, 1, 0), th)]  # the ramp's plane: height 0.3 at x = 0, normal tilted to +x
    pose = np.r_[0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0]
    for t in (G.CAPSULE, G.CYLINDER):
        for q in (quat((1, 0, 0), 1.2), quat((0, 1, 1), 0.5)):
            geom = np.r_[0.2, 0.1, 0.45, q]
            size = np.array([0.06, 0.12, 0.0])
            h = _points(collide(t, G.HFIELD, geom, size, pose, np.zeros(3), 0.5, hfield=hf))
            p = _points(collide(G.PLANE, t, plane, np.zeros(3), geom, size, 0.5))
            np.testing.assert_allclose(h["dist"], p["dist"], atol=ROUNDING)
            np.testing.assert_allclose(h["pos"], p["pos"], atol=ROUNDING)
            np.testing.assert_allclose(h["normal"], -p["normal"], atol=ROUNDING)


def test_heightfield_pairs_keep_the_point_count_contract():
    """Every HFIELD pair returns ``K = MAX_POINTS[pair]`` points (abstract evaluation: shapes and dtypes)."""
    p = jnp.asarray([0, 0, 0, 0, 0, 0, 1.0])
    for t in (G.SPHERE, G.CAPSULE, G.BOX, G.CYLINDER):
        cp = jax.eval_shape(lambda pa, sa, pb, t=t: _collide(t, G.HFIELD, pa, sa, pb, sa, 0.1, hfield=FLAT),
                            p, jnp.ones(3), p)
        k = MAX_POINTS[(t, G.HFIELD)]
        assert cp.pos.shape == cp.normal.shape == (k, 3) and cp.dist.shape == cp.valid.shape == (k,)


def test_points_off_the_grid_have_no_contact():
    """A sphere beyond the grid's x or y extent, however deep: no contact (and finite values)."""
    for centre in ((1.5, 0.0, 0.0), (0.0, -1.2, -0.5)):
        h = _points(collide(G.SPHERE, G.HFIELD, np.r_[centre, 0, 0, 0, 1.0], (0.1, 0, 0), np.r_[0, 0, 0, 0, 0, 0, 1.0],
                            np.zeros(3), 1.0, hfield=FLAT))
        assert not h["valid"].any()
        assert all(np.isfinite(v).all() for v in h.values())


def test_surface_is_mujocos_triangles():
    """The surface below a point is MuJoCo's: a random 4 x 5 grid exported to C MuJoCo, whose ray cast straight
    down meets the same height (to MuJoCo's float32 heights, 1e-6 m on a 0.5 m relief)."""
    mujoco = pytest.importorskip("mujoco")
    rng = np.random.default_rng(3)
    b = ModelBuilder()
    body = b.add_body(1.0, np.eye(3) * 0.01, pos=(0, 0, 2))
    b.add_joint(JointType.FREE, -1, body)
    b.add_geom(G.SPHERE, body, size=0.1)
    h = b.add_hfield(4, 5, (1.0, 0.7, 0.5, 0.1), rng.uniform(size=20), name="rough")
    b.add_geom(G.HFIELD, -1, hfield=h)
    model = b.finalize()
    mj = mujoco.MjModel.from_xml_string(kamino.save_mjcf(model))
    data = mujoco.MjData(mj)
    mujoco.mj_forward(mj, data)
    hf = grid(4, 5, model.hfield_size[0], model.hfield_data)
    gid = np.zeros(1, np.int32)
    for x, y in rng.uniform((-0.99, -0.69), (0.99, 0.69), size=(40, 2)):
        z, _, inside = _hfield_surface(hf, jnp.asarray(x), jnp.asarray(y))
        ray = mujoco.mj_ray(mj, data, np.array([x, y, 3.0]), np.array([0, 0, -1.0]), None, 1, -1, gid)
        assert bool(inside) and abs(float(z) - (3.0 - ray)) < 1e-6, (x, y)


def _hfield_scene(rows=3, cols=4, world_geom=True, elevation=None, size=(1.0, 1.0, 0.5, 0.1), **kw):
    b = ModelBuilder()
    body = b.add_body(1.0, np.eye(3) * 0.01, pos=(0, 0, 1))
    b.add_joint(JointType.FREE, -1, body)
    b.add_geom(G.SPHERE, body, size=0.1)
    e = np.arange(rows * cols, dtype=float) if elevation is None else elevation
    h = b.add_hfield(rows, cols, size, e, name="terrain")
    b.add_geom(G.HFIELD, -1 if world_geom else body, hfield=h, **kw)
    return b.finalize()


@pytest.mark.parametrize(("kwargs", "match"), [
    ({"elevation": np.zeros(5)}, r"hfield 'terrain': elevation has 5 values, expected nrow \* ncol = 3 \* 4 = 12"),
    ({"rows": 1, "elevation": np.zeros(4)}, r"hfield 'terrain': nrow must be an integer >= 2"),
    ({"size": (1.0, -1.0, 0.5, 0.1)}, r"hfield 'terrain': size \(rx, ry, z_top, z_base\) must be 4 positive"),
    ({"elevation": np.r_[np.zeros(11), np.nan]}, r"hfield 'terrain' elevation: contains NaN"),
    ({"world_geom": False}, r"geom 'geom_1' \(index 1\): a heightfield is static: attach it to the world"),
])
def test_bad_heightfields_are_model_errors_naming_the_field(kwargs, match):
    with pytest.raises(ModelError, match=match):
        _hfield_scene(**kwargs)


def test_heightfield_geom_needs_its_grid_and_only_it_takes_one():
    b = ModelBuilder()
    b.add_body(1.0, np.eye(3) * 0.01)
    b.add_geom(G.HFIELD, -1)
    with pytest.raises(ModelError, match=r"hfield -1 does not exist \(0 heightfields; add one with add_hfield"):
        b.finalize()
    b = ModelBuilder()
    body = b.add_body(1.0, np.eye(3) * 0.01)
    b.add_geom(G.SPHERE, body, size=0.1, hfield=0)
    with pytest.raises(ModelError, match=r"hfield=0 given for a SPHERE geom"):
        b.finalize()


def test_heightfields_normalise_as_mujoco_and_worlds_keep_their_own():
    """Heights normalise to [0, 1] (equal ones to 0); concat shifts grid indices and height addresses, -1 (no
    grid) stays -1; take_worlds and one world's model give each world back."""
    m = _hfield_scene(elevation=np.arange(12.0) * 2 + 5)
    np.testing.assert_allclose(m.hfield_data, np.arange(12) / 11, atol=1e-15)
    np.testing.assert_array_equal(_hfield_scene(elevation=np.full(12, 3.0)).hfield_data, np.zeros(12))
    b = ModelBuilder()
    b.add_geom(G.SPHERE, b.add_body(1.0, np.eye(3) * 0.01), size=0.1)
    plain = b.finalize()
    multi = concat([plain, m, m])
    assert multi.geom_dataid.tolist() == [-1, -1, 0, -1, 1]
    assert multi.hfield_adr.tolist() == [0, 12] and multi.world_hfield_data_start.tolist() == [0, 0, 12]
    assert same_model(take_worlds(multi, 1, 3), concat([m, m]))
    assert same_model(world_model(multi, 2), m)
    assert kamino.model.fingerprint(m) != kamino.model.fingerprint(_hfield_scene(elevation=np.arange(12.0) ** 2))


def test_mjcf_heightfield_round_trip_keeps_the_heights():
    """An MJCF ``<hfield elevation>`` scene: kamino imports MuJoCo's normalised heights, exports them (rows listed
    from +y down, as MJCF does), and C MuJoCo and kamino read the export back to the same heights; MuJoCo's are
    float32, so kamino's own float64 heights meet them to float32's rounding (6e-8 on [0, 1])."""
    mujoco = pytest.importorskip("mujoco")
    xml = """<mujoco><asset><hfield name="hills" nrow="3" ncol="4" size="2 1 0.5 0.1"
      elevation="1 2 3 4  5 6 7 8  9 10 11 13"/></asset>
      <worldbody><geom name="ground" type="hfield" hfield="hills" pos="0.1 0.2 -0.1" euler="0 0 20"/>
      <body pos="0.3 0.2 1"><freejoint/><geom type="sphere" size="0.1"/></body></worldbody></mujoco>"""
    mj = mujoco.MjModel.from_xml_string(xml)
    m = kamino.load_mjcf(xml)
    assert m.hfield_names == ("hills",) and m.geom_type[m.geom_dataid >= 0].tolist() == [G.HFIELD]
    np.testing.assert_array_equal(m.hfield_data, mj.hfield_data)
    np.testing.assert_array_equal(m.hfield_size, mj.hfield_size)
    # MJCF lists the rows from +y down: its first row (1 2 3 4) is the grid's last (y = +ry)
    np.testing.assert_allclose(m.hfield_data.reshape(3, 4)[2], np.array([0, 1, 2, 3]) / 12, atol=1e-7)
    xml2 = kamino.save_mjcf(m)
    np.testing.assert_array_equal(mujoco.MjModel.from_xml_string(xml2).hfield_data, mj.hfield_data)
    m2 = kamino.load_mjcf(xml2)
    np.testing.assert_array_equal(m2.hfield_data, m.hfield_data)
    np.testing.assert_allclose(m2.geom_pos, m.geom_pos, atol=1e-15)
    # a kamino-built grid (float64 heights): C MuJoCo reads the export to float32 rounding
    built = _hfield_scene(elevation=np.random.default_rng(0).uniform(size=12))
    mj3 = mujoco.MjModel.from_xml_string(kamino.save_mjcf(built))
    np.testing.assert_allclose(mj3.hfield_data, built.hfield_data, atol=6e-8)
    np.testing.assert_array_equal(mj3.hfield_nrow, [3])
    np.testing.assert_array_equal(mj3.hfield_ncol, [4])


def test_mjcf_heightfield_from_a_png_file(tmp_path):
    """``<hfield file="....png">``: MuJoCo's compiler reads the image (its top row at +y) and kamino takes its
    normalised heights: a 3 x 4 grey ramp 0, 20, ..., 220 gives (value / 220), rows reversed."""
    image = pytest.importorskip("PIL.Image")
    pixels = (np.arange(12).reshape(3, 4) * 20).astype(np.uint8)
    image.fromarray(pixels).save(tmp_path / "terrain.png")
    (tmp_path / "scene.xml").write_text(
        """<mujoco><asset><hfield name="t" file="terrain.png" size="2 1 0.5 0.1"/></asset><worldbody>
        <geom type="hfield" hfield="t"/><body pos="0 0 1"><freejoint/><geom type="sphere" size="0.1"/></body>
        </worldbody></mujoco>""")
    m = kamino.load_mjcf(str(tmp_path / "scene.xml"))
    np.testing.assert_allclose(m.hfield_data.reshape(3, 4), pixels[::-1] / 220.0, atol=1e-7)  # float32 heights


def test_heightfield_on_a_moving_mjcf_body_is_reported():
    xml = """<mujoco><asset><hfield name="h" nrow="2" ncol="2" size="1 1 0.5 0.1" elevation="0 1 2 3"/></asset>
      <worldbody><geom type="plane" size="1 1 1"/><body name="raft" pos="0 0 1"><freejoint/>
      <geom name="deck" type="hfield" hfield="h"/></body></worldbody></mujoco>"""
    with pytest.raises(ModelError, match=r"heightfield geom 'deck' on the moving body 'raft'"):
        kamino.load_mjcf(xml)
