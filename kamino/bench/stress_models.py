"""float32 stress models for :mod:`kamino.bench.convergence`, built with :class:`kamino.ModelBuilder`.

Each function returns a validated single-world :class:`kamino.Model` that is hard for PADMM in float32 for
one named reason (the docstrings say which):

- :func:`mass_ratio_pendulum`: a 1e4 mass ratio across a joint (ill-conditioned Delassus matrix);
- :func:`serial_chain`: a long serial chain released horizontal (a 20-link chain: long load path, fast tip);
- :func:`tilted_fourbar`: a four-bar whose last hinge axis is tilted out of the plane (a rigid spatial loop
  whose constraint Jacobian is nearly rank deficient for a small tilt);
- :func:`spinning_body`: a torque-free body spinning about its intermediate axis (Dzhanibekov; no constraints:
  the invariants measure the integrator, docs/conventions.md "Gyroscopic term");
- the shipped scene ``biped_connect.xml`` (:func:`biped_connect`): a MuJoCo-Menagerie-style biped on a free
  joint, with parallel four-bar knees closed by ``<connect>`` equalities, stiff joint springs, position
  actuators and box feet on a ground plane, loaded with :func:`kamino.load_mjcf`.
"""

from __future__ import annotations

import numpy as np

import kamino
from kamino.bench import scene_path
from kamino.model import Actuation, JointType
from kamino.models.shapes import add_link, box_inertia

Y = (0.0, 1.0, 0.0)
#: the free body of :func:`spinning_body`: principal inertia, body-frame angular velocity (30 rad/s about the
#: intermediate axis, perturbed by 0.05 rad/s as in tests/test_gyroscopic.py) and a generic orientation
SPIN_INERTIA = np.array([0.01, 0.02, 0.03])
SPIN_OMEGA_BODY = np.array([0.05, 30.0, 0.05])
SPIN_QUAT = np.array([0.1, 0.2, 0.3, 0.9]) / np.linalg.norm([0.1, 0.2, 0.3, 0.9])


def _rot(q: np.ndarray) -> np.ndarray:
    """Rotation matrix of a unit quaternion ``(x, y, z, w)``."""
    x, y, z, w = q
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def _about_y(angle: float) -> np.ndarray:
    return np.array([0.0, np.sin(angle / 2), 0.0, np.cos(angle / 2)])


def mass_ratio_pendulum(light: float = 0.01, heavy: float = 100.0, length: float = 0.5, width: float = 0.02,
                        angles: tuple[float, float] = (0.5, 0.3)) -> kamino.Model:
    """Two slender boxes hinged in series about world y from a pivot at z = 1 m: a ``light`` [kg] link at the
    pivot, a ``heavy`` [kg] link at the tip (mass ratio 1e4 by default), released from rest at the absolute
    ``angles`` [rad] from the vertical. The light link carries the heavy link's whole load: its rows' effective
    masses differ by the mass ratio, which puts a float32 rounding floor on PADMM's residuals."""
    b = kamino.ModelBuilder()
    p0 = np.array([0.0, 0.0, 1.0])
    down = [length * np.array([-np.sin(a), 0.0, -np.cos(a)]) for a in angles]
    p1 = p0 + down[0]
    links = [b.add_body(mass=m, inertia=box_inertia(m, (width, width, length)), pos=p + 0.5 * d, quat=_about_y(a),
                        name=name)
             for m, p, d, a, name in zip((light, heavy), (p0, p1), down, angles, ("light", "heavy"), strict=True)]
    b.add_joint_at(JointType.REVOLUTE, -1, links[0], anchor=p0, axis=Y, name="pivot")
    b.add_joint_at(JointType.REVOLUTE, links[0], links[1], anchor=p1, axis=Y, name="elbow")
    return b.finalize()


def serial_chain(n: int = 20, length: float = 0.1, mass: float = 0.1, radius: float = 0.01,
                 height: float = 1.0) -> kamino.Model:
    """``n`` capsule links (``length`` [m], ``mass`` [kg] each) hinged end to end about world y, the first to
    the world at ``(0, 0, height)``, released at rest lying horizontal along +x. The tip falls at up to
    ~sqrt(2 g n length) (6 m/s for 20 links) and the load path is ``n`` joints long. No geoms (no contacts)."""
    b = kamino.ModelBuilder()
    start = np.array([0.0, 0.0, height])
    step = np.array([length, 0.0, 0.0])
    prev = -1
    for k in range(n):
        link = add_link(b, start + k * step, start + (k + 1) * step, mass, radius, f"link{k}")
        b.add_joint_at(JointType.REVOLUTE, prev, link, anchor=start + k * step, axis=Y, name=f"hinge{k}")
        prev = link
    return b.finalize()


def _circle_intersection_upper(c0: np.ndarray, r0: float, c1: np.ndarray, r1: float) -> np.ndarray:
    """The upper (larger z) intersection of two circles in the xz plane."""
    d = np.linalg.norm(c1 - c0)
    a = (r0 * r0 - r1 * r1 + d * d) / (2 * d)
    h = np.sqrt(max(r0 * r0 - a * a, 0.0))
    mid = c0 + a * (c1 - c0) / d
    perp = np.array([-(c1 - c0)[2], 0.0, (c1 - c0)[0]]) / d
    p1, p2 = mid + h * perp, mid - h * perp
    return p1 if p1[2] >= p2[2] else p2


def tilted_fourbar(tilt_deg: float, ground: float = 0.3, crank: float = 0.18, coupler: float = 0.26,
                   rocker: float = 0.24, crank_angle: float = -1.2, linear_density: float = 2.0,
                   radius: float = 0.01, height: float = 1.0) -> kamino.Model:
    """The four-bar of :func:`kamino.models.fourbar` (same dimensions, pivots hinged to the world) with the
    coupler-rocker hinge axis tilted out of the plane by ``tilt_deg`` (world y rotated about world x).

    With a tilted axis the loop is a spatial RRRR that is not a Bennett linkage: it is rigid (mobility 0),
    and for a small tilt its constraint Jacobian has a singular value of order ``sin(tilt)`` (near the planar
    mechanism's one-DoF motion). The crank hinge ``drive`` is an EFFORT actuator (driven by
    :mod:`kamino.bench.convergence` like the MJCF four-bar): the drive loads the nearly singular direction.
    The loop closes exactly at the builder pose (every anchor coincides; only the axis is tilted)."""
    b = kamino.ModelBuilder()
    A = np.array([0.0, 0.0, height])
    D = A + np.array([ground, 0.0, 0.0])
    B = A + crank * np.array([np.cos(crank_angle), 0.0, np.sin(crank_angle)])
    C = _circle_intersection_upper(B, coupler, D, rocker)
    cr = add_link(b, A, B, linear_density * crank, radius, "crank")
    co = add_link(b, B, C, linear_density * coupler, radius, "coupler")
    ro = add_link(b, D, C, linear_density * rocker, radius, "rocker")
    t = np.deg2rad(tilt_deg)
    b.add_joint_at(JointType.REVOLUTE, -1, cr, anchor=A, axis=Y, name="drive", actuation=Actuation("effort"))
    b.add_joint_at(JointType.REVOLUTE, cr, co, anchor=B, axis=Y, name="crank_coupler")
    b.add_joint_at(JointType.REVOLUTE, co, ro, anchor=C, axis=(0.0, np.cos(t), np.sin(t)), name="coupler_rocker")
    b.add_joint_at(JointType.REVOLUTE, -1, ro, anchor=D, axis=Y, name="rocker_ground")
    return b.finalize()


def spinning_body() -> kamino.Model:
    """A free 1 kg body with principal inertia ``diag(0.01, 0.02, 0.03)`` kg m^2 spinning at 30 rad/s about its
    intermediate axis (plus 0.05 rad/s about the others, so that it flips), gravity off, no joints, no geoms.
    Kinetic energy and ``|L|`` are invariants of the motion (and of kamino's implicit gyroscopic rule)."""
    b = kamino.ModelBuilder(gravity=(0.0, 0.0, 0.0))
    b.add_body(mass=1.0, inertia=SPIN_INERTIA, quat=SPIN_QUAT, angular_velocity=_rot(SPIN_QUAT) @ SPIN_OMEGA_BODY,
               name="plate")
    return b.finalize()


def biped_connect() -> kamino.Model:
    """The shipped scene ``biped_connect.xml`` (:func:`kamino.bench.scene_path`) through :func:`kamino.load_mjcf`
    (see the file's comment)."""
    return kamino.load_mjcf(scene_path("biped_connect"))
