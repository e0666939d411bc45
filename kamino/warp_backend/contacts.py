"""Contacts in Warp: narrow phase, activation and packing, contact rows, warm start, State output.

The same rules as ``kamino/jax_ref/contacts.py`` (docs/formulation.md §4.2, §7.8): speculative
activation with the free velocity, restitution timing, packing in detection order into the world's
capacity (deterministic: one thread per world walks its candidates), rows ``(t1, t2, n)`` with the
gap / Newton-restitution bias, and the warm start by geom pair and nearest point on geom b.

Each kernel comes from its own builder cached per precision (``narrow_phase_kernel``, ``pack_kernel``,
``contact_rows_kernel``, ``commit_contacts_kernel``); :func:`contact_kernels` gathers the four for the
stepper.
"""

import functools
from types import SimpleNamespace

import warp as wp

from kamino.config import DEPENETRATION_SPEED
from kamino.model import GeomType
from kamino.warp_backend.collision import collide_hfield_func, collide_pair_func
from kamino.warp_backend.cone import cone_funcs
from kamino.warp_backend.indexing import index_funcs
from kamino.warp_backend.rows import ROW_CONTACT, row_kernels
from kamino.warp_backend.spatial import spatial_funcs
from kamino.warp_backend.workspace import builder_types

PLANE = int(GeomType.PLANE)
HFIELD = int(GeomType.HFIELD)


@functools.cache
def contact_kernels(np_dtype) -> SimpleNamespace:
    """The contact kernels of one precision, in launch order: ``narrow_phase``, ``pack``, ``contact_rows``,
    ``commit_contacts``."""
    return SimpleNamespace(narrow_phase=narrow_phase_kernel(np_dtype), pack=pack_kernel(np_dtype),
                           contact_rows=contact_rows_kernel(np_dtype),
                           commit_contacts=commit_contacts_kernel(np_dtype))


@functools.cache
def point_funcs(np_dtype) -> SimpleNamespace:
    """Geom poses and point velocities of the candidate points (§4.2: ``x_A``, ``x_B`` and their velocities)."""
    scalar, vec3, vec6, transform, M = builder_types(np_dtype).take("scalar", "vec3", "vec6", "transform", "M")
    sp = spatial_funcs(np_dtype)
    lin, ang = sp.lin, sp.ang

    @wp.func
    def geom_pose(m: M, body_q: wp.array(dtype=transform), g: int):
        """World pose of geom ``g``: its body's pose composed with the geom's local pose."""
        b = m.geom_body[g]
        if b < 0:
            return transform(m.geom_pos[g], m.geom_quat[g])
        x = body_q[b]
        q = wp.transform_get_rotation(x)
        return transform(wp.transform_get_translation(x) + wp.quat_rotate(q, m.geom_pos[g]), q * m.geom_quat[g])

    @wp.func
    def point_velocity(body_q: wp.array(dtype=transform), u: wp.array(dtype=vec6), b: int, x: vec3):
        """Velocity of the world point ``x`` moving with body ``b`` (zero for the world, ``b < 0``)."""
        if b < 0:
            return vec3()
        return lin(u[b]) + wp.cross(ang(u[b]), x - wp.transform_get_translation(body_q[b]))

    @wp.func
    def approach_velocity(body_q: wp.array(dtype=transform), u: wp.array(dtype=vec6), ba: int, bb: int, pos: vec3,
                          normal: vec3, dist: scalar):
        """Normal velocity of geom b's witness point relative to geom a's (negative: approaching)."""
        x_a = pos - scalar(0.5) * dist * normal
        x_b = pos + scalar(0.5) * dist * normal
        return wp.dot(point_velocity(body_q, u, bb, x_b) - point_velocity(body_q, u, ba, x_a), normal)

    return SimpleNamespace(geom_pose=geom_pose, point_velocity=point_velocity, approach_velocity=approach_velocity)


@functools.cache
def narrow_phase_kernel(np_dtype) -> wp.Kernel:
    """``narrow_phase``: the candidate points ``cand_*`` of every geom pair (§4.2, activation margin), one thread
    per pair, by :func:`kamino.warp_backend.collision.collide_pair_func` (a heightfield geom b: by
    :func:`~kamino.warp_backend.collision.collide_hfield_func`, with its grid from the model)."""
    scalar, vec3, vec6, transform, M = builder_types(np_dtype).take("scalar", "vec3", "vec6", "transform", "M")
    sp = spatial_funcs(np_dtype)
    lin, ang = sp.lin, sp.ang
    collide_pair = collide_pair_func(np_dtype)
    collide_hfield = collide_hfield_func(np_dtype)
    geom_pose = point_funcs(np_dtype).geom_pose

    @wp.kernel(module="unique", enable_backward=False)
    def narrow_phase(
        # model (read only)
        m: M,
        # in
        dt: scalar, contact_margin: scalar,
        u_f: wp.array(dtype=vec6),
        q_eval: wp.array(dtype=transform),
        # out
        cand_pos: wp.array(dtype=vec3),
        cand_normal: wp.array(dtype=vec3),
        cand_dist: wp.array(dtype=scalar),
        cand_valid: wp.array(dtype=wp.int32),
    ):
        """Candidate points of each geom pair, with the margin widened by a bound of the pair's approach
        speed over one step ``dt`` (``detect`` of the JAX reference); a pair whose bounding spheres are
        farther apart than that margin is skipped (no valid candidate, as in the reference)."""
        wid, i = wp.tid()
        if i >= m.pair_count[wid]:
            return
        p = m.pair_start[wid] + i
        ga = m.pair_geom_a[p]
        gb = m.pair_geom_b[p]
        ba = m.geom_body[ga]
        bb = m.geom_body[gb]
        va = vec3()
        vb = vec3()
        wa = scalar(0.0)
        wb = scalar(0.0)
        if ba >= 0:
            va = lin(u_f[ba])
            wa = wp.length(ang(u_f[ba]))
        if bb >= 0:
            vb = lin(u_f[bb])
            wb = wp.length(ang(u_f[bb]))
        speed = wp.length(vb - va) + wa * m.geom_radius[ga] + wb * m.geom_radius[gb]
        margin = m.geom_margin[ga] + m.geom_margin[gb] + contact_margin + dt * speed
        if m.geom_type[ga] != PLANE:  # pairs are ordered: a plane is always geom a
            ca = vec3()
            cb = vec3()
            if ba >= 0:
                ca = wp.transform_get_translation(q_eval[ba])
            if bb >= 0:
                cb = wp.transform_get_translation(q_eval[bb])
            if wp.length(cb - ca) > m.geom_radius[ga] + m.geom_radius[gb] + margin:  # bounding spheres apart
                for k in range(m.pair_points[p]):
                    cand_valid[m.pair_cand[p] + k] = 0
                return
        if m.geom_type[gb] == HFIELD:  # the heightfield is geom b (its type sorts last)
            h = m.geom_dataid[gb]
            collide_hfield(m.geom_type[ga], geom_pose(m, q_eval, ga), m.geom_size[ga], geom_pose(m, q_eval, gb),
                           m.hfield_data, m.hfield_adr[h], m.hfield_nrow[h], m.hfield_ncol[h], m.hfield_size[h],
                           margin, m.pair_cand[p], cand_pos, cand_normal, cand_dist, cand_valid)
        else:
            collide_pair(m.geom_type[ga], m.geom_type[gb], geom_pose(m, q_eval, ga), m.geom_size[ga],
                         geom_pose(m, q_eval, gb), m.geom_size[gb], margin, m.pair_cand[p], cand_pos,
                         cand_normal, cand_dist, cand_valid)

    return narrow_phase


@functools.cache
def pack_kernel(np_dtype) -> wp.Kernel:
    """``pack``: activation (speculative, or restitution timing) of the candidates ``cand_*`` and packing into the
    world's capacity (``ct_*``, ``ct_found``, ``n_con``), one thread per world (§4.2)."""
    scalar, vec3, vec6, transform, M = builder_types(np_dtype).take("scalar", "vec3", "vec6", "transform", "M")
    approach_velocity = point_funcs(np_dtype).approach_velocity

    @wp.kernel(module="unique", enable_backward=False)
    def pack(
        # model (read only)
        m: M,
        # in
        dt: scalar, contact_margin: scalar, deadband_c: scalar, restitution_threshold: scalar,
        q_eval: wp.array(dtype=transform),
        u: wp.array(dtype=vec6),
        u_f: wp.array(dtype=vec6),
        cand_pos: wp.array(dtype=vec3),
        cand_normal: wp.array(dtype=vec3),
        cand_dist: wp.array(dtype=scalar),
        cand_valid: wp.array(dtype=wp.int32),
        # out
        ct_pair: wp.array(dtype=wp.int32),
        ct_body_a: wp.array(dtype=wp.int32),
        ct_body_b: wp.array(dtype=wp.int32),
        ct_pos: wp.array(dtype=vec3),
        ct_normal: wp.array(dtype=vec3),
        ct_dist: wp.array(dtype=scalar),
        ct_mu: wp.array(dtype=scalar),
        ct_restitution: wp.array(dtype=scalar),
        ct_found: wp.array(dtype=wp.int32),
        n_con: wp.array(dtype=wp.int32),
    ):
        """Active points (speculative, or restitution timing, over one step ``dt``: ``detect`` of the JAX reference)
        packed in detection order into the capacity."""
        wid = wp.tid()
        count = int(0)
        cap = m.con_capacity[wid]
        s0 = m.con_start[wid]
        for i in range(m.pair_count[wid]):
            p = m.pair_start[wid] + i
            ga = m.pair_geom_a[p]
            gb = m.pair_geom_b[p]
            ba = m.geom_body[ga]
            bb = m.geom_body[gb]
            rest = wp.max(m.geom_restitution[ga], m.geom_restitution[gb])
            mg = m.geom_margin[ga] + m.geom_margin[gb]
            for k in range(m.pair_points[p]):
                c = m.pair_cand[p] + k
                if cand_valid[c] == 0:
                    continue
                pos = cand_pos[c]
                nrm = cand_normal[c]
                dist = cand_dist[c]
                active = False
                if rest > scalar(0.0):
                    v_n = approach_velocity(q_eval, u, ba, bb, pos, nrm, dist)
                    if v_n < -restitution_threshold:
                        active = dist < scalar(0.5) * dt * wp.abs(v_n)
                    else:
                        active = dist <= mg + deadband_c
                else:
                    v_free = approach_velocity(q_eval, u_f, ba, bb, pos, nrm, dist)
                    active = dist <= mg + contact_margin + dt * wp.max(-v_free, scalar(0.0))
                if active:
                    if count < cap:
                        s = s0 + count
                        ct_pair[s] = m.pair_key[p]
                        ct_body_a[s] = ba
                        ct_body_b[s] = bb
                        ct_pos[s] = pos
                        ct_normal[s] = nrm
                        ct_dist[s] = dist
                        ct_mu[s] = wp.max(m.geom_friction[ga], m.geom_friction[gb])
                        ct_restitution[s] = rest
                    count += 1
        ct_found[wid] = count
        n_con[wid] = wp.min(count, cap)

    return pack


@functools.cache
def frame_funcs(np_dtype) -> SimpleNamespace:
    """The contact frame, the warm-start key point and the Jacobian blocks of a contact row (§4.2, §7.8)."""
    scalar, vec3, vec6, transform = builder_types(np_dtype).take("scalar", "vec3", "vec6", "transform")
    twist = spatial_funcs(np_dtype).twist

    @wp.func
    def contact_frame(nrm: vec3):
        """``C = [t1 t2 n]`` (columns), right-handed (``contact_frames`` of the JAX reference)."""
        s = vec3(scalar(0.0), scalar(1.0), scalar(0.0))
        if wp.abs(nrm[0]) < scalar(0.8660254037844387):
            s = vec3(scalar(1.0), scalar(0.0), scalar(0.0))
        t2 = wp.cross(nrm, s)
        l2 = wp.length(t2)
        if l2 > scalar(0.0):
            t2 = t2 / l2
        t1 = wp.cross(t2, nrm)
        l1 = wp.length(t1)
        if l1 > scalar(0.0):
            t1 = t1 / l1
        return wp.matrix_from_cols(t1, t2, nrm)

    @wp.func
    def local_point_b(ct_pos: wp.array(dtype=vec3), ct_dist: wp.array(dtype=scalar), ct_normal: wp.array(dtype=vec3),
                      ct_body_b: wp.array(dtype=wp.int32), q_eval: wp.array(dtype=transform), s: int):
        """Witness point on geom b in its body's CoM frame (world frame for the world): the warm-start key."""
        x_b = ct_pos[s] + scalar(0.5) * ct_dist[s] * ct_normal[s]
        b = ct_body_b[s]
        if b < 0:
            return x_b
        x = q_eval[b]
        return wp.quat_rotate_inv(wp.transform_get_rotation(x), x_b - wp.transform_get_translation(x))

    @wp.func
    def contact_blocks(ct_pos: wp.array(dtype=vec3), ct_dist: wp.array(dtype=scalar), ct_normal: wp.array(dtype=vec3),
                       ct_body_a: wp.array(dtype=wp.int32), ct_body_b: wp.array(dtype=wp.int32),
                       q_eval: wp.array(dtype=transform), s: int, dirn: vec3):
        """Blocks on bodies b and a of the row along ``dirn``: ``[c, (x - r) x c]``, negative on a (§4.2)."""
        nrm = ct_normal[s]
        d = ct_dist[s]
        x_a = ct_pos[s] - scalar(0.5) * d * nrm
        x_b = ct_pos[s] + scalar(0.5) * d * nrm
        ba = ct_body_a[s]
        bb = ct_body_b[s]
        JB = vec6()
        JA = vec6()
        if bb >= 0:
            JB = twist(dirn, wp.cross(x_b - wp.transform_get_translation(q_eval[bb]), dirn))
        if ba >= 0:
            JA = -twist(dirn, wp.cross(x_a - wp.transform_get_translation(q_eval[ba]), dirn))
        return JB, JA

    return SimpleNamespace(contact_frame=contact_frame, local_point_b=local_point_b, contact_blocks=contact_blocks)


@functools.cache
def contact_rows_kernel(np_dtype) -> wp.Kernel:
    """``contact_rows``: three rows per active contact with the gap or restitution bias (§4.2) and the warm start
    (§7.8)."""
    scalar, vec3, vec6, transform, M = builder_types(np_dtype).take("scalar", "vec3", "vec6", "transform", "M")
    deadband = spatial_funcs(np_dtype).deadband
    cf = cone_funcs(np_dtype)
    rk = row_kernels(np_dtype)
    ix = index_funcs(np_dtype)
    ridx, make_row_info = ix.ridx, ix.row_info
    ff = frame_funcs(np_dtype)
    contact_frame, local_point_b, contact_blocks = ff.contact_frame, ff.local_point_b, ff.contact_blocks
    depenetration_speed = scalar(DEPENETRATION_SPEED)

    @wp.kernel(module="unique", enable_backward=False)
    def contact_rows(
        # model (read only)
        m: M,
        # in
        nblk: int, dt: scalar, gamma: scalar, deadband_c: scalar, restitution_threshold: scalar,
        match_distance: scalar, row_stride: int,
        n_con: wp.array(dtype=wp.int32),
        n_box: wp.array(dtype=wp.int32),
        ct_pair: wp.array(dtype=wp.int32),
        ct_body_a: wp.array(dtype=wp.int32),
        ct_body_b: wp.array(dtype=wp.int32),
        ct_pos: wp.array(dtype=vec3),
        ct_normal: wp.array(dtype=vec3),
        ct_dist: wp.array(dtype=scalar),
        ct_mu: wp.array(dtype=scalar),
        ct_restitution: wp.array(dtype=scalar),
        q_eval: wp.array(dtype=transform),
        u: wp.array(dtype=vec6),
        con_pair: wp.array(dtype=wp.int32),
        con_force: wp.array(dtype=vec3),
        con_velocity: wp.array(dtype=vec3),
        con_point_b: wp.array(dtype=vec3),
        # out
        row_body: wp.array(dtype=wp.int32),  # also read
        row_J: wp.array(dtype=vec6),  # also read
        reg: wp.array(dtype=scalar),
        lo: wp.array(dtype=scalar),
        hi: wp.array(dtype=scalar),
        row_info: wp.array(dtype=wp.int32),
        vstar: wp.array(dtype=scalar),
        f0: wp.array(dtype=scalar),
        v0: wp.array(dtype=scalar),
    ):
        """Three rows per contact with their bias (``contact_bias``) and warm start (``match_previous``)."""
        wid, i = wp.tid()
        if i >= n_con[wid]:
            return
        s = m.con_start[wid] + i
        a0 = n_box[wid] + 3 * i
        C = contact_frame(ct_normal[s])
        ba = ct_body_a[s]
        bb = ct_body_b[s]
        mu = ct_mu[s]
        for t in range(3):
            JB, JA = contact_blocks(ct_pos, ct_dist, ct_normal, ct_body_a, ct_body_b, q_eval, s,
                                    vec3(C[0, t], C[1, t], C[2, t]))
            rt = ridx(m, row_stride, wid, a0 + t)
            rk.set_blocks(row_body, row_J, rt, nblk, bb, JB, ba, JA)
            reg[rt] = scalar(0.0)
            lo[rt] = scalar(0.0)
            hi[rt] = scalar(0.0)
            row_info[rt] = make_row_info(ROW_CONTACT, s, scalar(1.0))  # row_mu reads the slot's friction
            vstar[rt] = scalar(0.0)
        # bias of the normal row, aimed one step dt ahead (the pose the next step reads the contact at, under both
        # integrators): gap closes at most, penetration shrinks by gamma but at most at the depenetration speed;
        # or Newton's restitution
        d = deadband(ct_dist[s], deadband_c)
        gap_bias = (d - (scalar(1.0) - gamma) * wp.min(d, scalar(0.0))) / dt
        gap_bias = wp.max(gap_bias, (d - wp.min(d, scalar(0.0))) / dt - depenetration_speed)
        vn_minus = rk.row_dot(row_body, row_J, ridx(m, row_stride, wid, a0 + 2), nblk, u)
        e = ct_restitution[s]
        vn = gap_bias
        if e > scalar(0.0) and vn_minus < -restitution_threshold:
            corr = scalar(0.0)
            if e < scalar(1.0):
                corr = wp.min(gap_bias, scalar(0.0))
            vn = wp.min(e * vn_minus, corr)
        vstar[ridx(m, row_stride, wid, a0 + 2)] = vn
        # warm start: previous contact of the same pair nearest on geom b (first on ties), within the distance
        pb = local_point_b(ct_pos, ct_dist, ct_normal, ct_body_b, q_eval, s)
        best = int(-1)
        best_d2 = scalar(wp.inf)
        for k in range(m.con_capacity[wid]):
            c = m.con_start[wid] + k
            if con_pair[c] == ct_pair[s] and con_pair[c] >= 0:
                d2 = wp.length_sq(pb - con_point_b[c])
                if d2 < best_d2:
                    best_d2 = d2
                    best = c
        f = vec3()
        v = vec3()
        if best >= 0 and best_d2 <= match_distance * match_distance:
            f = wp.transpose(C) * con_force[best]
            f = cf.cone_project(f[0], f[1], f[2], mu)
            v = wp.transpose(C) * con_velocity[best]
        v[2] = v[2] + cf.de_saxce(v[0], v[1], mu)
        for t in range(3):
            f0[ridx(m, row_stride, wid, a0 + t)] = f[t]
            v0[ridx(m, row_stride, wid, a0 + t)] = v[t]

    return contact_rows


@functools.cache
def commit_contacts_kernel(np_dtype) -> wp.Kernel:
    """``commit_contacts``: the step's contacts into the State (``con_*``), world-frame force on geom b's body and
    relative velocity (§4.2), kept for the next step's warm start (§7.8)."""
    scalar, vec3, transform, M = builder_types(np_dtype).take("scalar", "vec3", "transform", "M")
    ridx = index_funcs(np_dtype).ridx
    ff = frame_funcs(np_dtype)
    contact_frame, local_point_b = ff.contact_frame, ff.local_point_b

    @wp.kernel(module="unique", enable_backward=False)
    def commit_contacts(
        # model (read only)
        m: M,
        # in
        inv_dt: scalar, row_stride: int,
        failed: wp.array(dtype=wp.int32),
        n_con: wp.array(dtype=wp.int32),
        n_box: wp.array(dtype=wp.int32),
        ct_pair: wp.array(dtype=wp.int32),
        ct_body_b: wp.array(dtype=wp.int32),
        ct_pos: wp.array(dtype=vec3),
        ct_normal: wp.array(dtype=vec3),
        ct_dist: wp.array(dtype=scalar),
        q_eval: wp.array(dtype=transform),
        impulse: wp.array(dtype=scalar),
        velocity: wp.array(dtype=scalar),
        # out
        con_pair: wp.array(dtype=wp.int32),
        con_pos: wp.array(dtype=vec3),
        con_normal: wp.array(dtype=vec3),
        con_dist: wp.array(dtype=scalar),
        con_force: wp.array(dtype=vec3),
        con_velocity: wp.array(dtype=vec3),
        con_point_b: wp.array(dtype=vec3),
    ):
        """The step's contacts into the State (world-frame force on geom b's body and relative velocity)."""
        wid, i = wp.tid()
        if i >= m.con_capacity[wid] or failed[wid] != 0:
            return
        s = m.con_start[wid] + i
        if i < n_con[wid]:
            r = ridx(m, row_stride, wid, n_box[wid] + 3 * i)
            r1 = r + row_stride
            r2 = r + 2 * row_stride
            C = contact_frame(ct_normal[s])
            con_pair[s] = ct_pair[s]
            con_pos[s] = ct_pos[s]
            con_normal[s] = ct_normal[s]
            con_dist[s] = ct_dist[s]
            con_force[s] = C * vec3(impulse[r], impulse[r1], impulse[r2]) * inv_dt
            con_velocity[s] = C * vec3(velocity[r], velocity[r1], velocity[r2])
            con_point_b[s] = local_point_b(ct_pos, ct_dist, ct_normal, ct_body_b, q_eval, s)
        else:
            con_pair[s] = -1
            con_pos[s] = vec3()
            con_normal[s] = vec3()
            con_dist[s] = scalar(0.0)
            con_force[s] = vec3()
            con_velocity[s] = vec3()
            con_point_b[s] = vec3()

    return commit_contacts
