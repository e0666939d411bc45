"""Contact detection, contact rows and contact warm start for one world (docs/formulation.md §4.2, §7.8).

``detect`` runs the narrow phase (``kamino.jax_ref.collision``) on the model's candidate pairs,
decides which points are active this step (speculative activation, restitution timing) and packs
the active ones, in pair order, into the world's fixed contact capacity. ``contact_rows`` builds
the three rows per contact ``(t1, t2, n)`` and their bias; ``warm_start`` matches the new
contacts to the previous step's by geom pair and position.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp

from kamino.config import CONTACT_BAUMGARTE, CONTACT_DEADBAND, DEPENETRATION_SPEED, RESTITUTION_THRESHOLD, SolverConfig
from kamino.jax_ref.collision import HField, collide
from kamino.jax_ref.types import PaddedModel
from kamino.model import GeomType
from kamino.spatial import quat_mul, quat_to_matrix


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Contacts:
    """Active contacts of one world, padded to the capacity ``C`` (arrays ``[C, ...]``).

    ``normal`` points from geom a (body ``body_a``, -1 the world) to geom b; ``pos`` is the
    midpoint of the witness points ``pos -/+ normal dist/2``; ``dist`` < 0 is penetration.
    """

    pair: jax.Array  # [C] world-local pair index (-1: empty slot)
    body_a: jax.Array
    body_b: jax.Array
    pos: jax.Array
    normal: jax.Array
    dist: jax.Array
    mu: jax.Array
    restitution: jax.Array
    margin: jax.Array
    mask: jax.Array
    count: jax.Array  # active contacts found (may exceed the capacity)
    overflow: jax.Array  # contacts dropped for lack of capacity


def deadband(x: jax.Array, delta) -> jax.Array:
    """``sign(x) max(0, |x| - delta)``: the dead band of docs/formulation.md §4.2, used for contact gaps
    and joint errors alike."""
    return jnp.sign(x) * jnp.maximum(jnp.abs(x) - delta, 0.0)


def geom_poses(pm: PaddedModel, body_q: jax.Array) -> jax.Array:
    """World poses ``[ng, 7]`` of the geoms: body pose composed with the geom's local pose."""
    on_body = pm.geom_body >= 0
    bq = body_q[jnp.where(on_body, pm.geom_body, 0)]
    R = quat_to_matrix(bq[:, 3:])
    p = bq[:, :3] + jnp.einsum("gij,gj->gi", R, pm.geom_pos)
    q = quat_mul(bq[:, 3:], pm.geom_quat)
    pose = jnp.concatenate([p, q], axis=-1)
    return jnp.where(on_body[:, None], pose, jnp.concatenate([pm.geom_pos, pm.geom_quat], axis=-1))


def _bounding_radius(pm: PaddedModel) -> jax.Array:
    """Distance from a body's CoM that bounds each geom (planes: their offset only; a heightfield: the box of
    half-extents ``size`` about its origin; see docstring of ``detect``)."""
    s = pm.geom_size
    r = jnp.select(
        [pm.geom_type == GeomType.SPHERE, pm.geom_type == GeomType.CAPSULE,
         (pm.geom_type == GeomType.BOX) | (pm.geom_type == GeomType.HFIELD),
         pm.geom_type == GeomType.CYLINDER, pm.geom_type == GeomType.ELLIPSOID],
        [s[:, 0], s[:, 0] + s[:, 1], jnp.linalg.norm(s, axis=-1), jnp.hypot(s[:, 0], s[:, 1]),
         jnp.max(s, axis=-1)],
        0.0,
    )
    return r + jnp.linalg.norm(pm.geom_pos, axis=-1)


def point_velocity(body_u: jax.Array, body_q: jax.Array, body: jax.Array, x: jax.Array) -> jax.Array:
    """World velocity of the material point at ``x`` of ``body`` (zero for the world, -1)."""
    b = jnp.where(body >= 0, body, 0)
    u = body_u[b]
    v = u[:, :3] + jnp.cross(u[:, 3:], x - body_q[b, :3])
    return jnp.where((body >= 0)[:, None], v, 0.0)


def _approach_velocity(body_q, body_u, body_a, body_b, pos, normal, dist):
    x_a = pos - 0.5 * dist[:, None] * normal
    x_b = pos + 0.5 * dist[:, None] * normal
    dv = point_velocity(body_u, body_q, body_b, x_b) - point_velocity(body_u, body_q, body_a, x_a)
    return jnp.sum(dv * normal, axis=-1)


def detect(pm: PaddedModel, body_q: jax.Array, body_u: jax.Array, body_u_free: jax.Array, h,
           cfg: SolverConfig) -> Contacts:
    """Active contacts of one world at pose ``body_q`` (docs/formulation.md §4.2).

    ``h`` is the horizon of the unilateral rows: one whole step ``dt`` under both integrators, up to the
    pose at which the next step reads the contacts (the midpoint rule's next ``q_m`` is ``q_m ⊕ dt u+``;
    :func:`contact_bias`). A point is active when its gap is within the pair's margin plus what the
    approach speed of the free velocity ``body_u_free`` closes over it:
    ``d <= m_a + m_b + cfg.contact_margin + h max(0, -v_n)`` (speculative contacts: fast bodies do
    not tunnel, resting ones do not sink). A speculative contact stops its bodies exactly at contact,
    which is an inelastic impact, so contacts with restitution are not speculative: they are active
    when touching (``d <= m_a + m_b + CONTACT_DEADBAND``) or, when approaching (at the
    start-of-step velocity ``body_u``) faster than ``RESTITUTION_THRESHOLD``, at the step
    boundary nearest to the impact (``d < h |v_n| / 2``; otherwise the impact happens next step, at a
    penetration below ``h |v_n| / 2``), docs/conventions.md "Contacts". The narrow phase
    is called with a margin widened by a bound of the pair's approach speed (planes attached to
    bodies contribute their body's linear speed only). A pair of bounded geoms whose bounding spheres
    (about their bodies' CoMs) are farther apart than that margin cannot have a point within it: its
    candidates are marked invalid whatever the narrow phase estimated, which is what lets the Warp
    backend skip such pairs before the narrow phase with the same result.
    """
    C = pm.max_contacts
    dtype = body_q.dtype
    gpose = geom_poses(pm, body_q)
    rad = _bounding_radius(pm)
    gb = pm.geom_body
    gsafe = jnp.where(gb >= 0, gb, 0)
    g_lin = jnp.where((gb >= 0)[:, None], body_u_free[gsafe, :3], 0.0)
    g_ang = jnp.where(gb >= 0, jnp.linalg.norm(body_u_free[gsafe, 3:], axis=-1), 0.0)
    g_centre = jnp.where((gb >= 0)[:, None], body_q[gsafe, :3], 0.0)  # the centre of each geom's bounding sphere

    fields = {k: [] for k in ("pair", "a", "b", "pos", "normal", "dist")}
    for (ta, tb), grp in zip(pm.pair_kinds, pm.pair_groups, strict=True):
        a, b = grp.geom_a, grp.geom_b
        speed = jnp.linalg.norm(g_lin[b] - g_lin[a], axis=-1) + g_ang[a] * rad[a] + g_ang[b] * rad[b]
        margin = pm.geom_margin[a] + pm.geom_margin[b] + cfg.contact_margin + h * speed
        if tb == GeomType.HFIELD:  # the heightfield is geom b (its type sorts last); its grid from the world's
            hf = jnp.maximum(pm.geom_dataid[b], 0)
            cp = jax.vmap(lambda pa, sa, pb, sb, m, adr, nr, nc, hs, ta=ta, tb=tb: collide(
                ta, tb, pa, sa, pb, sb, m, hfield=HField(pm.hfield_data, adr, nr, nc, hs)))(
                gpose[a], pm.geom_size[a], gpose[b], pm.geom_size[b], margin, pm.hfield_adr[hf], pm.hfield_nrow[hf],
                pm.hfield_ncol[hf], pm.hfield_size[hf])
        else:
            cp = jax.vmap(lambda pa, sa, pb, sb, m, ta=ta, tb=tb: collide(ta, tb, pa, sa, pb, sb, m))(
                gpose[a], pm.geom_size[a], gpose[b], pm.geom_size[b], margin)
        k = cp.dist.shape[1]
        ok = cp.valid & grp.mask[:, None]
        if ta != GeomType.PLANE:  # pairs are ordered (a plane is geom a): no point once bounding spheres are apart
            apart = jnp.linalg.norm(g_centre[b] - g_centre[a], axis=-1) > rad[a] + rad[b] + margin
            ok = ok & ~apart[:, None]
        fields["pair"].append(jnp.where(ok, grp.pair[:, None], -1).reshape(-1))
        fields["a"].append(jnp.repeat(a, k))
        fields["b"].append(jnp.repeat(b, k))
        fields["pos"].append(cp.pos.reshape(-1, 3))
        fields["normal"].append(cp.normal.reshape(-1, 3))
        fields["dist"].append(cp.dist.reshape(-1))
    if not fields["pair"]:
        z = jnp.zeros((C,), dtype)
        zi = jnp.full((C,), -1, jnp.int32)
        return Contacts(zi, zi, zi, jnp.zeros((C, 3), dtype), jnp.zeros((C, 3), dtype), z, z, z, z,
                        jnp.zeros((C,), bool), jnp.int32(0), jnp.int32(0))
    pair = jnp.concatenate(fields["pair"])
    ga, gbb = jnp.concatenate(fields["a"]), jnp.concatenate(fields["b"])
    pos, normal = jnp.concatenate(fields["pos"]), jnp.concatenate(fields["normal"])
    dist = jnp.concatenate(fields["dist"])
    body_a, body_b = pm.geom_body[ga], pm.geom_body[gbb]
    restitution = jnp.maximum(pm.geom_restitution[ga], pm.geom_restitution[gbb])
    static_margin = pm.geom_margin[ga] + pm.geom_margin[gbb] + cfg.contact_margin

    v_free = _approach_velocity(body_q, body_u_free, body_a, body_b, pos, normal, dist)
    v_n = _approach_velocity(body_q, body_u, body_a, body_b, pos, normal, dist)
    speculative = dist <= static_margin + h * jnp.maximum(-v_free, 0.0)
    impact = (restitution > 0) & (v_n < -RESTITUTION_THRESHOLD)
    touching = dist <= pm.geom_margin[ga] + pm.geom_margin[gbb] + CONTACT_DEADBAND
    elastic = jnp.where(impact, dist < 0.5 * h * jnp.abs(v_n), touching)
    active = (pair >= 0) & jnp.where(restitution > 0, elastic, speculative)

    # pack the active points, in candidate order, into the capacity (deterministic)
    count = jnp.sum(active).astype(jnp.int32)
    n_cand = pair.shape[0]
    (idx,) = jnp.nonzero(active, size=C, fill_value=n_cand)
    cap = pm.contact_capacity
    slot_ok = (jnp.arange(C) < jnp.minimum(count, cap)) & (idx < n_cand)
    safe = jnp.where(slot_ok, idx, 0)

    def take(x, fill):
        return jnp.where(slot_ok.reshape((C,) + (1,) * (x.ndim - 1)), x[safe], fill)

    return Contacts(
        pair=take(pair, -1),
        body_a=take(body_a, -1),
        body_b=take(body_b, -1),
        pos=take(pos, 0.0),
        normal=take(normal, 0.0),
        dist=take(dist, 0.0),
        mu=take(jnp.maximum(pm.geom_friction[ga], pm.geom_friction[gbb]), 0.0),
        restitution=take(restitution, 0.0),
        margin=take(static_margin, 0.0),
        mask=slot_ok,
        count=count,
        overflow=jnp.maximum(count - cap, 0).astype(jnp.int32),
    )


def contact_frames(normal: jax.Array) -> jax.Array:
    """Contact frames ``C = [t1 t2 n]`` ``[C, 3, 3]`` (columns), right-handed (docs/formulation.md §4.2)."""
    ex = jnp.zeros_like(normal).at[:, 0].set(1.0)
    ey = jnp.zeros_like(normal).at[:, 1].set(1.0)
    s = jnp.where((jnp.abs(normal[:, 0]) < jnp.cos(jnp.pi / 6))[:, None], ex, ey)

    def unit(v):
        n = jnp.linalg.norm(v, axis=-1, keepdims=True)
        return v / jnp.where(n > 0, n, 1.0)

    t2 = unit(jnp.cross(normal, s))
    t1 = unit(jnp.cross(t2, normal))
    return jnp.stack([t1, t2, normal], axis=-1)


def contact_jacobian(ct: Contacts, body_q: jax.Array, nb: int) -> jax.Array:
    """Dense contact rows ``[3C, nb*6]``: per contact ``(t1, t2, n)``, ``J_B = [c, (x_B - r_B) x c]``
    and ``J_A = -[c, (x_A - r_A) x c]`` (docs/formulation.md §4.2); the world's block is dropped."""
    C = ct.pair.shape[0]
    frames = contact_frames(ct.normal)  # [C, 3, 3]
    x_a = ct.pos - 0.5 * ct.dist[:, None] * ct.normal
    x_b = ct.pos + 0.5 * ct.dist[:, None] * ct.normal
    c = jnp.swapaxes(frames, 1, 2)  # [C, 3 rows, 3]

    def blocks(body, x, sign):
        r = body_q[jnp.where(body >= 0, body, 0), :3]
        ang = jnp.cross((x - r)[:, None, :], c)
        blk = sign * jnp.concatenate([c, ang], axis=-1)  # [C, 3, 6]
        return jnp.where(((body >= 0) & ct.mask)[:, None, None], blk, 0.0)

    J = jnp.zeros((C, 3, nb, 6), body_q.dtype)
    rows = jnp.arange(C)
    J = J.at[rows, :, jnp.where(ct.body_b >= 0, ct.body_b, 0)].add(blocks(ct.body_b, x_b, 1.0))
    J = J.at[rows, :, jnp.where(ct.body_a >= 0, ct.body_a, 0)].add(blocks(ct.body_a, x_a, -1.0))
    return J.reshape(3 * C, nb * 6)


def contact_bias(ct: Contacts, dist_start: jax.Array, v_n_minus: jax.Array, h, cfg: SolverConfig) -> jax.Array:
    """``v*`` of the contact rows ``[3C]`` (docs/formulation.md §4.2 "gap bias" and "restitution").

    Tangent rows get 0. ``h`` is one whole step ``dt`` under both integrators (:func:`detect`): the
    normal row asks the gap ``d + h v_n+`` at the pose where the next step reads it (``d``
    dead-banded, read where the dynamics are built, ``d_start`` the same reading in the pipeline) to
    be at least ``(1 - gamma) min(d_start, 0)``: a gap may close, not more, and a penetration shrinks
    by ``gamma = CONTACT_BAUMGARTE`` per step, but at most at ``DEPENETRATION_SPEED``: the penetration
    term ``gamma min(d_start, 0) / h`` is bounded below by ``-DEPENETRATION_SPEED``, so that a deep
    overlap does not launch the body (its kinetic energy stays below ``m V^2 / 2``). This is §4.2's
    ``xi = d / h`` for a gap and ``max(gamma xi, -DEPENETRATION_SPEED)`` for a penetration. Under the
    midpoint rule the end pose lies halfway between this reading and the next, so a body is stopped
    at the next midpoint instead of overshooting in the first half-step (docs/conventions.md,
    "Contacts"). An impact (restitution ``e > 0`` and approach
    faster than ``RESTITUTION_THRESHOLD``) instead asks ``v_n+ >= -e v_n-`` (Newton's law), or
    the penetration correction's speed if that is larger (``e < 1``); adding the two would inject
    energy into every bounce.
    """
    d, d0 = deadband(ct.dist, CONTACT_DEADBAND), deadband(dist_start, CONTACT_DEADBAND)
    gap_bias = (d - (1.0 - CONTACT_BAUMGARTE) * jnp.minimum(d0, 0.0)) / h
    # the bounded penetration term: the closing term ``(d - min(d_start, 0)) / h`` less the speed bound (the
    # unbounded bias is kept bit for bit where the bound does not bind)
    gap_bias = jnp.maximum(gap_bias, (d - jnp.minimum(d0, 0.0)) / h - DEPENETRATION_SPEED)
    e = ct.restitution
    impact = (e > 0) & (v_n_minus < -RESTITUTION_THRESHOLD)
    newton = jnp.minimum(e * v_n_minus, jnp.where(e < 1, jnp.minimum(gap_bias, 0.0), 0.0))
    vn = jnp.where(impact, newton, gap_bias)
    zeros = jnp.zeros_like(vn)
    return jnp.where(ct.mask[:, None], jnp.stack([zeros, zeros, vn], axis=-1), 0.0).reshape(-1)


def local_point_b(ct: Contacts, body_q: jax.Array) -> jax.Array:
    """Witness point on geom b in its body's CoM frame (world frame for the world): the warm-start
    matching key, carried rigidly with the body (docs/formulation.md §7.8 advects it instead)."""
    x_b = ct.pos + 0.5 * ct.dist[:, None] * ct.normal
    b = jnp.where(ct.body_b >= 0, ct.body_b, 0)
    R = quat_to_matrix(body_q[b, 3:])
    local = jnp.einsum("cji,cj->ci", R, x_b - body_q[b, :3])
    return jnp.where((ct.body_b >= 0)[:, None], local, x_b)


def match_previous(ct: Contacts, point_b: jax.Array, prev_pair: jax.Array, prev_point_b: jax.Array,
                   tol: float) -> tuple[jax.Array, jax.Array]:
    """Index of the previous contact each new contact continues (same geom pair, nearest point on
    geom b within ``tol``), and whether one was found (docs/formulation.md §7.8, "key and position")."""
    if ct.pair.shape[0] == 0:
        return jnp.zeros(0, jnp.int32), jnp.zeros(0, bool)
    same = (ct.pair[:, None] == prev_pair[None, :]) & (prev_pair[None, :] >= 0) & ct.mask[:, None]
    d2 = jnp.sum((point_b[:, None, :] - prev_point_b[None, :, :]) ** 2, axis=-1)
    d2 = jnp.where(same, d2, jnp.inf)
    j = jnp.argmin(d2, axis=1)
    found = jnp.min(d2, axis=1) <= tol * tol
    return j, found
