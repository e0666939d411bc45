"""Float32 accuracy of the hub-body factorisation against today's Cholesky of the fixed rows (issue 17's memory
lead for the animatronic): ``python benchmarks/hub_factor_accuracy.py --scenes animatronic --hub-rows 48``.

Today the Warp backend factorises ``A = P (J M^-1 J^T + R) P + s I`` on a world's always-active rows (joint
dynamics, joints, couplings; ``P`` the Jacobi scaling, ``s = eta + rho_free``; docs/formulation.md §7.1-7.2) as
``L L^T`` with the rows in minimum-degree order (``sparse_llt.symbolic``). The rows on one body form a clique of
``A`` (the animatronic: 201 rows on one body), which no order of rows avoids.

The lead (docs/warp_backend.md, "Open problems"): bodies carrying more than ``--hub-rows`` rows (hubs) keep their 6
velocity unknowns, and the quasi-definite system

    K = [[A0, Jh], [Jh^T, -Mh]],   A0 = P (sum_{b not a hub} J_b M_b^-1 J_b^T + R) P + s I,   Jh = P J_hub,

whose Schur complement on the rows is ``A``, is factorised as ``L D L^T`` with ``D`` of both signs (any symmetric
order factorises a quasi-definite matrix). This script builds both for one world at its initial pose in float64,
factorises them densely in float32 in their minimum-degree orders (no pivoting, as the kernels), solves four random
right-hand sides, and reports the relative error against a float64 solve, the smallest pivot, the count of negative
pivots (6 per hub expected) and the factor's entries (structural, from the symbolic count). The hub system is
factorised twice: in the free minimum-degree order (``hub_ldlt``) and with the hubs' unknowns held back until every
row is eliminated (``hub_ldlt_hubs_last``: the rows' block is then a plain Cholesky factor and the hubs' unknowns
act as the first tail rows, docs/warp_backend.md "Open problems").
"""

from __future__ import annotations

import argparse
import json
import pathlib
import sys

import numpy as np

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent))


def fixed_row_system(scene: str) -> dict:
    """Scaled Jacobian blocks ``Js [n, nb, 6]``, per-body ``Minv``/``M`` ``[nb, 6, 6]``, the scaled ``R``, the shift
    ``s``, ``A`` and the rows' moving bodies (``sparse_llt.fixed_row_bodies``) of world 0 of ``scene``."""
    import jax

    jax.config.update("jax_enable_x64", True)
    import jax.numpy as jnp
    import throughput as tb  # the benchmark scenes

    import kamino
    from kamino.config import SolverConfig
    from kamino.jax_ref.couplings import coupling_jacobian
    from kamino.jax_ref.dynamics import body_dynamics
    from kamino.jax_ref.joints import constraint_jacobian, dof_jacobian, dof_positions, joint_frames
    from kamino.jax_ref.layout import layout_of
    from kamino.jax_ref.step import WorldControl, dynamics_rows
    from kamino.warp_backend.sparse_llt import fixed_row_bodies

    model, _ = tb.load_scene(scene)
    lay = layout_of(model, np.float64)
    pm = jax.tree.map(lambda x: x[0] if getattr(x, "ndim", 0) and x.shape[0] == lay.num_worlds else x, lay.padded)
    q = jnp.asarray(np.asarray(kamino.init_state(model, np.float64).body_q)[lay.body_gather[0]])
    nb = q.shape[0]
    cfg = SolverConfig(dt=0.002)
    jf, bd = joint_frames(pm, q), body_dynamics(pm, q)
    J_dofs = dof_jacobian(pm, jf, nb)
    q_dof = dof_positions(pm, jf)
    zeros = jnp.zeros(pm.dof_mask.shape)
    ctrl = WorldControl(effort=zeros, wrench=jnp.zeros((nb, 6)), position_target=zeros, velocity_target=zeros)
    R_dyn = dynamics_rows(pm, q_dof, zeros, ctrl, cfg.dt, cfg)[0]
    J_dyn = jnp.where(pm.dyn_mask[:, None], J_dofs[pm.dyn_dof], 0.0)
    J_kin, J_cpl = constraint_jacobian(pm, jf, nb), coupling_jacobian(pm, q_dof, J_dofs)
    mask = np.concatenate([np.asarray(pm.dyn_mask), np.asarray(pm.row_mask), np.asarray(pm.cpl_mask)])
    J = np.asarray(jnp.concatenate([J_dyn, J_kin, J_cpl]))[mask]
    R = np.concatenate([np.asarray(R_dyn), np.zeros(J_kin.shape[0] + J_cpl.shape[0])])[mask]
    n = len(J)
    inv_mass, inv_inertia, inertia = (np.asarray(a) for a in (bd.inv_mass, bd.inv_inertia, bd.inertia))
    Minv, M = np.zeros((nb, 6, 6)), np.zeros((nb, 6, 6))
    for b in np.flatnonzero(inv_mass > 0):
        Minv[b, :3, :3], Minv[b, 3:, 3:] = inv_mass[b] * np.eye(3), inv_inertia[b]
        M[b, :3, :3], M[b, 3:, 3:] = np.eye(3) / inv_mass[b], inertia[b]
    Jb = J.reshape(n, nb, 6)
    D = np.einsum("rbi,bij,sbj->rs", Jb, Minv, Jb) + np.diag(R)
    P = 1.0 / np.sqrt(np.diag(D))
    s = cfg.eta + cfg.rho_free
    bodies = fixed_row_bodies(model)[0]
    if len(bodies) != n:
        raise SystemExit(f"hub_factor_accuracy: {scene}: {len(bodies)} rows in the factor's table, {n} assembled")
    return {"Js": P[:, None, None] * Jb, "Minv": Minv, "M": M, "R": P * R * P, "s": s,
            "A": P[:, None] * D * P[None, :] + s * np.eye(n), "bodies": bodies}


def ldl(K: np.ndarray, dtype) -> tuple[np.ndarray, np.ndarray]:
    """Dense ``K = L diag(d) L^T`` without pivoting, computed in ``dtype`` (column by column, as the kernels)."""
    K = K.astype(dtype)
    m = len(K)
    L, d = np.eye(m, dtype=dtype), np.zeros(m, dtype)
    for j in range(m):
        d[j] = K[j, j] - np.dot(L[j, :j] * d[:j], L[j, :j])
        L[j + 1:, j] = (K[j + 1:, j] - (L[j + 1:, :j] * d[:j]) @ L[j, :j]) / d[j]
    return L, d


def ldl_solve(L: np.ndarray, d: np.ndarray, b: np.ndarray) -> np.ndarray:
    from scipy.linalg import solve_triangular

    y = solve_triangular(L, b.astype(L.dtype), lower=True, unit_diagonal=True)
    return solve_triangular(L.T, y / d[:, None], lower=False, unit_diagonal=True)


def measure(scene: str, hub_rows: int, rhs: int = 4, seed: int = 0) -> dict:
    """Both factorisations of ``scene``'s fixed rows in float32 (see the module docstring)."""
    from memory_breakdown import hub_graph, min_degree_order

    from kamino.warp_backend.sparse_llt import symbolic

    sysm = fixed_row_system(scene)
    A, bodies, Js = sysm["A"], sysm["bodies"], sysm["Js"]
    n = len(A)
    B = np.random.default_rng(seed).standard_normal((n, rhs))
    X = np.linalg.solve(A, B)
    err = lambda Y: float(np.linalg.norm(Y - X) / np.linalg.norm(X))  # noqa: E731

    sym = symbolic(bodies)
    order = np.asarray(sym.perm)
    L, d = ldl(A[np.ix_(order, order)], np.float32)
    Y = np.empty_like(X)
    Y[order] = ldl_solve(L, d, B[order])
    out = {"scene": scene, "rows": n, "cond_A": float(np.linalg.cond(A)),
           "llt": {"rel_error": err(Y), "min_pivot": float(d.min()), "factor_entries": int(sym.nnz)}}

    adj, node, on_body = hub_graph(bodies, hub_rows)
    hubs = sorted(node)
    keep = np.ones(len(sysm["Minv"]), bool)
    keep[hubs] = False
    N = n + 6 * len(hubs)
    K = np.zeros((N, N))
    K[:n, :n] = (np.einsum("rbi,bij,sbj->rs", Js[:, keep], sysm["Minv"][keep], Js[:, keep])
                 + np.diag(sysm["R"]) + sysm["s"] * np.eye(n))  # A0: the hubs' terms left out, not subtracted
    for h, v in node.items():
        c = slice(n + 6 * (v - n), n + 6 * (v - n) + 6)
        K[:n, c], K[c, :n], K[c, c] = Js[:, h], Js[:, h].T, -sysm["M"][h]
    weight = [1] * n + [6] * len(hubs)
    hub_only = sum({int(x) for x in bodies[a] if x >= 0} <= set(hubs) for a in range(n))
    Baug = np.concatenate([B, np.zeros((N - n, rhs))])
    for name, last in (("hub_ldlt", frozenset()), ("hub_ldlt_hubs_last", frozenset(node.values()))):
        nodes, entries = min_degree_order(adj, weight, last)
        o = np.concatenate([[v] if v < n else np.arange(n + 6 * (v - n), n + 6 * (v - n) + 6)
                            for v in nodes]).astype(np.int64)
        L, d = ldl(K[np.ix_(o, o)], np.float32)
        Z = np.zeros_like(Baug)
        Z[o] = ldl_solve(L, d, Baug[o])
        out[name] = {"hub_rows_over": hub_rows, "hubs": len(hubs), "rows_on_hubs": [len(on_body[h]) for h in hubs],
                     "rows_on_hubs_only": int(hub_only), "rel_error": err(Z[:n]),
                     "min_abs_pivot": float(np.abs(d).min()), "negative_pivots": int((d < 0).sum()),
                     "factor_entries": int(entries)}
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--scenes", nargs="+", default=["animatronic"])
    p.add_argument("--hub-rows", type=int, default=48, help="a body with more rows than this is a hub")
    p.add_argument("--out", type=pathlib.Path)
    args = p.parse_args(argv)
    results = []
    for scene in args.scenes:
        r = measure(scene, args.hub_rows)
        results.append(r)
        llt = r["llt"]
        print(f"{scene}: {r['rows']} fixed rows, cond(A) {r['cond_A']:.2e}; LLT (float32): error "
              f"{llt['rel_error']:.2e}, min pivot {llt['min_pivot']:.2e}, {llt['factor_entries']} entries", flush=True)
        for name in ("hub_ldlt", "hub_ldlt_hubs_last"):
            h = r[name]
            print(f"  {name}: {h['hubs']} hubs {h['rows_on_hubs']} ({h['rows_on_hubs_only']} rows on hubs only): "
                  f"error {h['rel_error']:.2e}, min |pivot| {h['min_abs_pivot']:.2e}, {h['negative_pivots']} "
                  f"negative, {h['factor_entries']} entries", flush=True)
    if args.out:
        args.out.write_text(json.dumps(results, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
