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

from kamino.model import GeomType
from kamino.warp_backend.collision import collide_pair_func
from kamino.warp_backend.cone import cone_funcs
from kamino.warp_backend.indexing import index_funcs
from kamino.warp_backend.rows import ROW_CONTACT, row_kernels
from kamino.warp_backend.spatial import spatial_funcs
from kamino.warp_backend.workspace import builder_types

PLANE = int(GeomType.PLANE)


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
    """``narrow_phase(m, w, h, contact_margin)``: the candidate points of every geom pair (§4.2, activation
    margin), one thread per pair, by :func:`kamino.warp_backend.collision.collide_pair_func`."""
    scalar, vec3, M, Work = builder_types(np_dtype).take("scalar", "vec3", "M", "Work")
    sp = spatial_funcs(np_dtype)
    lin, ang = sp.lin, sp.ang
    collide_pair = collide_pair_func(np_dtype)
    geom_pose = point_funcs(np_dtype).geom_pose

    @wp.kernel(module="unique", enable_backward=False)
    def narrow_phase(m: M, w: Work, h: scalar, contact_margin: scalar):
        """Candidate points of each geom pair, with the margin widened by a bound of the pair's approach
        speed over the pose update (``detect`` of the JAX reference); a pair whose bounding spheres are
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
            va = lin(w.u_f[ba])
            wa = wp.length(ang(w.u_f[ba]))
        if bb >= 0:
            vb = lin(w.u_f[bb])
            wb = wp.length(ang(w.u_f[bb]))
        speed = wp.length(vb - va) + wa * m.geom_radius[ga] + wb * m.geom_radius[gb]
        margin = m.geom_margin[ga] + m.geom_margin[gb] + contact_margin + h * speed
        if m.geom_type[ga] != PLANE:  # pairs are ordered: a plane is always geom a
            ca = vec3()
            cb = vec3()
            if ba >= 0:
                ca = wp.transform_get_translation(w.q_eval[ba])
            if bb >= 0:
                cb = wp.transform_get_translation(w.q_eval[bb])
            if wp.length(cb - ca) > m.geom_radius[ga] + m.geom_radius[gb] + margin:  # bounding spheres apart
                for k in range(m.pair_points[p]):
                    w.cand_valid[m.pair_cand[p] + k] = 0
                return
        collide_pair(m.geom_type[ga], m.geom_type[gb], geom_pose(m, w.q_eval, ga), m.geom_size[ga],
                     geom_pose(m, w.q_eval, gb), m.geom_size[gb], margin, m.pair_cand[p], w.cand_pos,
                     w.cand_normal, w.cand_dist, w.cand_valid)

    return narrow_phase


@functools.cache
def pack_kernel(np_dtype) -> wp.Kernel:
    """``pack(m, w, h, contact_margin, deadband_c, restitution_threshold)``: activation (speculative, or
    restitution timing) and packing into the world's capacity, one thread per world (§4.2)."""
    scalar, M, Work = builder_types(np_dtype).take("scalar", "M", "Work")
    approach_velocity = point_funcs(np_dtype).approach_velocity

    @wp.kernel(module="unique", enable_backward=False)
    def pack(m: M, w: Work, h: scalar, contact_margin: scalar, deadband_c: scalar, restitution_threshold: scalar):
        """Active points (speculative, or restitution timing) packed in detection order into the capacity."""
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
                if w.cand_valid[c] == 0:
                    continue
                pos = w.cand_pos[c]
                nrm = w.cand_normal[c]
                dist = w.cand_dist[c]
                active = False
                if rest > scalar(0.0):
                    v_n = approach_velocity(w.q_eval, w.u, ba, bb, pos, nrm, dist)
                    if v_n < -restitution_threshold:
                        active = dist < scalar(0.5) * h * wp.abs(v_n)
                    else:
                        active = dist <= mg + deadband_c
                else:
                    v_free = approach_velocity(w.q_eval, w.u_f, ba, bb, pos, nrm, dist)
                    active = dist <= mg + contact_margin + h * wp.max(-v_free, scalar(0.0))
                if active:
                    if count < cap:
                        s = s0 + count
                        w.ct_pair[s] = m.pair_key[p]
                        w.ct_body_a[s] = ba
                        w.ct_body_b[s] = bb
                        w.ct_pos[s] = pos
                        w.ct_normal[s] = nrm
                        w.ct_dist[s] = dist
                        w.ct_mu[s] = wp.max(m.geom_friction[ga], m.geom_friction[gb])
                        w.ct_restitution[s] = rest
                    count += 1
        w.ct_found[wid] = count
        w.n_con[wid] = wp.min(count, cap)

    return pack


@functools.cache
def frame_funcs(np_dtype) -> SimpleNamespace:
    """The contact frame, the warm-start key point and the Jacobian blocks of a contact row (§4.2, §7.8)."""
    scalar, vec3, vec6, Work = builder_types(np_dtype).take("scalar", "vec3", "vec6", "Work")
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
    def local_point_b(w: Work, s: int):
        """Witness point on geom b in its body's CoM frame (world frame for the world): the warm-start key."""
        x_b = w.ct_pos[s] + scalar(0.5) * w.ct_dist[s] * w.ct_normal[s]
        b = w.ct_body_b[s]
        if b < 0:
            return x_b
        x = w.q_eval[b]
        return wp.quat_rotate_inv(wp.transform_get_rotation(x), x_b - wp.transform_get_translation(x))

    @wp.func
    def contact_blocks(w: Work, s: int, dirn: vec3):
        """Blocks on bodies b and a of the row along ``dirn``: ``[c, (x - r) x c]``, negative on a (§4.2)."""
        nrm = w.ct_normal[s]
        d = w.ct_dist[s]
        x_a = w.ct_pos[s] - scalar(0.5) * d * nrm
        x_b = w.ct_pos[s] + scalar(0.5) * d * nrm
        ba = w.ct_body_a[s]
        bb = w.ct_body_b[s]
        JB = vec6()
        JA = vec6()
        if bb >= 0:
            JB = twist(dirn, wp.cross(x_b - wp.transform_get_translation(w.q_eval[bb]), dirn))
        if ba >= 0:
            JA = -twist(dirn, wp.cross(x_a - wp.transform_get_translation(w.q_eval[ba]), dirn))
        return JB, JA

    return SimpleNamespace(contact_frame=contact_frame, local_point_b=local_point_b, contact_blocks=contact_blocks)


@functools.cache
def contact_rows_kernel(np_dtype) -> wp.Kernel:
    """``contact_rows(m, w, nblk, h, gamma, deadband_c, restitution_threshold, match_distance)``: three rows
    per active contact with the gap or restitution bias (§4.2) and the warm start (§7.8)."""
    scalar, vec3, M, Work = builder_types(np_dtype).take("scalar", "vec3", "M", "Work")
    deadband = spatial_funcs(np_dtype).deadband
    cf = cone_funcs(np_dtype)
    rk = row_kernels(np_dtype)
    ix = index_funcs(np_dtype)
    ridx, row_info = ix.ridx, ix.row_info
    ff = frame_funcs(np_dtype)
    contact_frame, local_point_b, contact_blocks = ff.contact_frame, ff.local_point_b, ff.contact_blocks

    @wp.kernel(module="unique", enable_backward=False)
    def contact_rows(m: M, w: Work, nblk: int, h: scalar, gamma: scalar, deadband_c: scalar,
                     restitution_threshold: scalar, match_distance: scalar):
        """Three rows per contact with their bias (``contact_bias``) and warm start (``match_previous``)."""
        wid, i = wp.tid()
        if i >= w.n_con[wid]:
            return
        s = m.con_start[wid] + i
        a0 = w.n_box[wid] + 3 * i
        C = contact_frame(w.ct_normal[s])
        ba = w.ct_body_a[s]
        bb = w.ct_body_b[s]
        mu = w.ct_mu[s]
        for t in range(3):
            JB, JA = contact_blocks(w, s, vec3(C[0, t], C[1, t], C[2, t]))
            rt = ridx(m, w.row_stride, wid, a0 + t)
            rk.set_blocks(w.row_body, w.row_J, rt, nblk, bb, JB, ba, JA)
            w.reg[rt] = scalar(0.0)
            w.lo[rt] = scalar(0.0)
            w.hi[rt] = scalar(0.0)
            w.row_info[rt] = row_info(ROW_CONTACT, s, scalar(1.0))  # row_mu reads the slot's friction
            w.vstar[rt] = scalar(0.0)
        # bias of the normal row: gap closes at most, penetration shrinks by gamma; or Newton's restitution
        d = deadband(w.ct_dist[s], deadband_c)
        gap_bias = (d - (scalar(1.0) - gamma) * wp.min(d, scalar(0.0))) / h
        vn_minus = rk.row_dot(w.row_body, w.row_J, ridx(m, w.row_stride, wid, a0 + 2), nblk, w.u)
        e = w.ct_restitution[s]
        vn = gap_bias
        if e > scalar(0.0) and vn_minus < -restitution_threshold:
            corr = scalar(0.0)
            if e < scalar(1.0):
                corr = wp.min(gap_bias, scalar(0.0))
            vn = wp.min(e * vn_minus, corr)
        w.vstar[ridx(m, w.row_stride, wid, a0 + 2)] = vn
        # warm start: previous contact of the same pair nearest on geom b (first on ties), within the distance
        pb = local_point_b(w, s)
        best = int(-1)
        best_d2 = scalar(wp.inf)
        for k in range(m.con_capacity[wid]):
            c = m.con_start[wid] + k
            if w.con_pair[c] == w.ct_pair[s] and w.con_pair[c] >= 0:
                d2 = wp.length_sq(pb - w.con_point_b[c])
                if d2 < best_d2:
                    best_d2 = d2
                    best = c
        f = vec3()
        v = vec3()
        if best >= 0 and best_d2 <= match_distance * match_distance:
            f = wp.transpose(C) * w.con_force[best]
            f = cf.cone_project(f[0], f[1], f[2], mu)
            v = wp.transpose(C) * w.con_velocity[best]
        v[2] = v[2] + cf.de_saxce(v[0], v[1], mu)
        for t in range(3):
            w.f0[ridx(m, w.row_stride, wid, a0 + t)] = f[t]
            w.v0[ridx(m, w.row_stride, wid, a0 + t)] = v[t]

    return contact_rows


@functools.cache
def commit_contacts_kernel(np_dtype) -> wp.Kernel:
    """``commit_contacts(m, w, inv_dt)``: the step's contacts into the State, world-frame force on geom b's body
    and relative velocity (§4.2), kept for the next step's warm start (§7.8)."""
    scalar, vec3, M, Work = builder_types(np_dtype).take("scalar", "vec3", "M", "Work")
    ridx = index_funcs(np_dtype).ridx
    ff = frame_funcs(np_dtype)
    contact_frame, local_point_b = ff.contact_frame, ff.local_point_b

    @wp.kernel(module="unique", enable_backward=False)
    def commit_contacts(m: M, w: Work, inv_dt: scalar):
        """The step's contacts into the State (world-frame force on geom b's body and relative velocity)."""
        wid, i = wp.tid()
        if i >= m.con_capacity[wid] or w.failed[wid] != 0:
            return
        s = m.con_start[wid] + i
        if i < w.n_con[wid]:
            r = ridx(m, w.row_stride, wid, w.n_box[wid] + 3 * i)
            r1 = r + w.row_stride
            r2 = r + 2 * w.row_stride
            C = contact_frame(w.ct_normal[s])
            w.con_pair[s] = w.ct_pair[s]
            w.con_pos[s] = w.ct_pos[s]
            w.con_normal[s] = w.ct_normal[s]
            w.con_dist[s] = w.ct_dist[s]
            w.con_force[s] = C * vec3(w.impulse[r], w.impulse[r1], w.impulse[r2]) * inv_dt
            w.con_velocity[s] = C * vec3(w.velocity[r], w.velocity[r1], w.velocity[r2])
            w.con_point_b[s] = local_point_b(w, s)
        else:
            w.con_pair[s] = -1
            w.con_pos[s] = vec3()
            w.con_normal[s] = vec3()
            w.con_dist[s] = scalar(0.0)
            w.con_force[s] = vec3()
            w.con_velocity[s] = vec3()
            w.con_point_b[s] = vec3()

    return commit_contacts
