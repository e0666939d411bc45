"""``describe(model)``: a readable inventory of a model, one block per distinct kind of world."""

from __future__ import annotations

import numpy as np

from kamino.model import JOINT_CONSTRAINT_ROWS, ActuationMode, GeomType, JointType, Model, count_loops


def _world_lines(model: Model, w: int) -> list[str]:
    bs, nb = int(model.world_body_start[w]), int(model.world_body_count[w])
    js, nj = int(model.world_joint_start[w]), int(model.world_joint_count[w])
    ds, nd = int(model.world_dof_start[w]), int(model.world_dof_count[w])
    types = model.joint_type[js:js + nj]
    modes = model.dof_act_mode[ds:ds + nd]
    owner = np.repeat(np.arange(js, js + nj), model.joint_dof_count[js:js + nj])
    actuated = set(owner[modes != int(ActuationMode.PASSIVE)].tolist())
    n_free_base = int(np.count_nonzero((types == int(JointType.FREE)) & (model.joint_parent[js:js + nj] < 0)))
    by_type = ", ".join(f"{int(np.count_nonzero(types == int(t)))} {t.name.lower()}" for t in JointType
                        if np.any(types == int(t)))
    n_kin = int(sum(len(JOINT_CONSTRAINT_ROWS[JointType(int(t))]) for t in types))
    n_cpl = int(model.world_coupling_count[w])
    is_pd = np.isin(modes, (int(ActuationMode.POSITION), int(ActuationMode.VELOCITY)))
    dd = slice(ds, ds + nd)
    passive_rows = (model.dof_armature[dd] > 0) | (model.dof_damping[dd] > 0) | (model.dof_stiffness[dd] > 0)
    n_dyn = int(np.count_nonzero(is_pd)) + int(np.count_nonzero(passive_rows))
    n_lim = int(np.count_nonzero(np.isfinite(model.dof_lower[dd]) | np.isfinite(model.dof_upper[dd])))
    cap = int(model.world_contact_capacity[w])
    gs, ng = int(model.world_geom_start[w]), int(model.world_geom_count[w])
    geoms = ", ".join(f"{int(np.count_nonzero(model.geom_type[gs:gs + ng] == int(t)))} {t.name.lower()}"
                      for t in GeomType if np.any(model.geom_type[gs:gs + ng] == int(t)))
    mass = float(model.body_mass[bs:bs + nb].sum())
    return [
        f"  bodies: {nb} ({mass:.4g} kg)",
        f"  joints: {nj} ({by_type or 'none'})",
        f"  actuated joints: {len(actuated)} ({int(np.count_nonzero(modes != 0))} actuated DoFs, "
        f"{int(model.world_actuator_count[w])} actuators); passive joints: {nj - len(actuated) - n_free_base}"
        + (" + 1 free base" if n_free_base else ""),
        f"  DoFs: {nd}; independent loops: {count_loops(model, w)}; couplings: {n_cpl}",
        f"  constraint rows: {n_kin} joint + {n_cpl} coupling (bilateral), {n_dyn} joint-dynamics, up to {n_lim} "
        f"limit and {3 * cap} contact: at most {n_kin + n_cpl + n_dyn + n_lim + 3 * cap}",
        f"  geoms: {ng} ({geoms or 'none'}); contact pairs: {int(model.world_pair_count[w])}; "
        f"contact capacity: {cap}",
    ]


def describe(model: Model) -> str:
    """Bodies, joints by type, actuated/passive joints, loops, constraint rows and contact capacity of
    every distinct kind of world (identical worlds are listed once, with their indices)."""
    blocks: dict[tuple[str, ...], list[int]] = {}
    for w in range(model.num_worlds):
        blocks.setdefault(tuple(_world_lines(model, w)), []).append(w)
    out = [f"kamino.Model: {model.num_worlds} world(s), {model.num_bodies} bodies, {model.num_joints} joints in all"]
    for lines, worlds in blocks.items():
        label = f"world {worlds[0]}" if len(worlds) == 1 else f"worlds {worlds[0]}..{worlds[-1]} ({len(worlds)})"
        if len(worlds) > 1 and worlds != list(range(worlds[0], worlds[-1] + 1)):
            label = f"{len(worlds)} worlds ({worlds[:4]}...)"
        out.append(label + ":")
        out.extend(lines)
    return "\n".join(out)
