"""Device memory per world of the default Warp stepper, array by array: ``kamino bench memory_breakdown``.

Builds ``kamino.SolverConfig(dt)``'s stepper for each scene (:mod:`kamino.bench.throughput`'s scenes) with
``--worlds`` identical worlds, walks every Warp array it holds (the work buffers, the factor's pattern and values,
the model), and prints the total and the largest arrays per world. On a CUDA device the total is checked against
the memory pool's count (``wp.get_mempool_used_mem_current``); patterns shared by all worlds of a type shrink per
world as the worlds grow, so measure at the batch size of interest. ``--out`` writes every scene's record as JSON.

``--tail-fill`` counts the tail's ``L_tf`` entries per world: dense (``n_tail x n_fixed``), as stored (every tail row
sized for the widest pattern a slot can hold; a row's entries of ``L_tf = D~_tf L_f^-T`` can be nonzero only on the
fixed rows its bodies' rows reach up the elimination tree of ``L_f``, ``linear_solve_pattern.tail_patterns``), and
sized per
source (each limited DoF's row its own pattern), a layout the backend does not use. ``--hub-fill`` counts the
fixed rows' factor entries if bodies carrying many rows kept their 6 velocity unknowns in the factorised system
(:func:`hub_fill`), a lead for the animatronic.
"""

from __future__ import annotations

import argparse
import json
import pathlib

import numpy as np

from kamino.bench import throughput as tb  # the benchmark scenes


def arrays_of(obj, path: str, seen: dict, depth: int = 0) -> None:
    """Every ``wp.array`` reachable from ``obj`` (attributes, Warp struct fields, lists, dicts), by pointer."""
    import warp as wp

    if depth > 4 or obj is None:
        return
    if isinstance(obj, wp.array):
        if obj.ptr is not None and obj.ptr not in seen:
            seen[obj.ptr] = (path, obj.capacity)
        return
    for name in list(getattr(type(obj), "vars", {}) or {}):
        arrays_of(getattr(obj, name, None), f"{path}.{name}", seen, depth + 1)
    for name, value in (getattr(obj, "__dict__", None) or {}).items():
        items = enumerate(value) if isinstance(value, (list, tuple)) else (
            value.items() if isinstance(value, dict) else [(None, value)])
        for key, item in items:
            arrays_of(item, f"{path}.{name}" + ("" if key is None else f"[{key}]"), seen, depth + 1)


def breakdown(scene: str, num_worlds: int, device: str, padmm: str | None = None) -> dict:
    import warp as wp

    import kamino
    from kamino.warp_backend.pipeline import Stepper

    base, _ = tb.load_scene(scene)
    model = kamino.replicate(base, num_worlds) if num_worlds > 1 else base
    cfg = kamino.SolverConfig(dt=tb.DT, **tb.SOLVER)
    dev = wp.get_device(device)
    wp.synchronize_device(dev)
    pool0 = wp.get_mempool_used_mem_current(dev) if dev.is_cuda else 0
    st = Stepper(model, cfg, np.float32, dev, padmm=padmm)
    wp.synchronize_device(dev)
    pool = (wp.get_mempool_used_mem_current(dev) - pool0) / num_worlds if dev.is_cuda else None
    seen: dict = {}
    arrays_of(st, "stepper", seen)
    per_world = sorted(((p, b / num_worlds) for p, b in seen.values()), key=lambda x: -x[1])
    return {"scene": scene, "num_worlds": num_worlds, "device": str(dev), "padmm": st.padmm,
            "linear_solver": st.linear_solver, "rows_max": st.wm.max_rows, "mempool_per_world": pool,
            "arrays_per_world": sum(b for _, b in per_world), "largest": per_world[:40]}


def tail_fill(scene: str) -> dict:
    """The tail's ``L_tf`` entries for one world of ``scene``: dense (``n_tail x n_fixed``), as
    stored (every row sized for the widest pattern ``K``, ``linear_solve_pattern.tail_patterns``), and sized per
    source (each
    limit row its own pattern, each contact slot the widest pair's); ``L_t`` (``n_tail^2``) is dense either way."""
    from kamino.tables import row_tables
    from kamino.warp_backend.linear_solve_pattern import fixed_row_bodies, symbolic, tail_patterns, tail_row_bodies

    model, _ = tb.load_scene(scene)
    bodies = fixed_row_bodies(model)[0]
    sym = symbolic(bodies)
    n = len(sym.perm)
    lim, pairs = tail_row_bodies(model, row_tables(model), 0)
    contact_rows = 3 * int(model.world_contact_capacity[0])
    sizes = [len(p) for p in tail_patterns(bodies, sym, lim, pairs if contact_rows else None)]
    lim_sizes, pair_sizes = sizes[:len(lim)], sizes[len(lim):]
    n_tail = len(lim) + contact_rows
    widest = max(sizes, default=0)
    on_body: dict[int, set[int]] = {}  # the fixed rows on each moving body: a clique of D~_ff
    for a in range(n):
        for b in bodies[a][bodies[a] >= 0]:
            on_body.setdefault(int(b), set()).add(a)
    coupled = [set().union(*(on_body[int(b)] for b in bodies[a][bodies[a] >= 0])) for a in range(n)]
    return {"scene": scene, "fixed_rows": n, "D_ff_lower": sum(len(c) + 1 for c in coupled) // 2, "L_f": sym.nnz,
            "busiest_body_rows": max((len(r) for r in on_body.values()), default=0), "tail_rows": n_tail,
            "limit_rows": len(lim),
            "contact_rows": contact_rows, "dense_L_tf": n_tail * n,
            "sparse_L_tf": sum(lim_sizes) + contact_rows * max(pair_sizes, default=0),
            "widest_pattern": widest, "uniform_L_tf": n_tail * widest, "L_t": n_tail * n_tail}


def min_degree_order(adj: list[set[int]], weight: list[int], last: frozenset = frozenset()) -> tuple[list[int], int]:
    """Greedy minimum degree on a symmetric matrix's graph ``adj`` (the order of ``linear_solve_pattern.symbolic``; a
    node of
    weight ``w`` stands for ``w`` scalar unknowns), the nodes in ``last`` held back until the others are eliminated.
    Returns ``(order, scalar entries of the Cholesky / LDL^T factor)``."""
    adj = [set(a) for a in adj]
    alive, order, nnz = set(range(len(adj))), [], 0
    while alive:
        pool = (alive - last) or alive
        v = min(pool, key=lambda a: (sum(weight[b] for b in adj[a]), a))
        nb, w = adj[v], weight[v]
        order.append(v)
        nnz += w * (w + 1) // 2 + w * sum(weight[b] for b in nb)  # the diagonal block and the columns below it
        for a in nb:
            adj[a] |= nb
            adj[a].discard(a)
            adj[a].discard(v)
        alive.discard(v)
    return order, nnz


def min_degree_fill(adj: list[set[int]], weight: list[int]) -> int:
    """Scalar entries of the factor under greedy minimum degree (:func:`min_degree_order`)."""
    return min_degree_order(adj, weight)[1]


def hub_graph(bodies: np.ndarray, threshold: int | None) -> tuple[list[set[int]], dict[int, int], dict[int, set[int]]]:
    """The graph of the fixed rows' system when every body with more than ``threshold`` rows (a hub; ``None``: no
    hubs) keeps its 6 velocity unknowns as a node of its own (``bodies``: the rows' moving bodies,
    ``linear_solve_pattern.fixed_row_bodies``): rows on a hub couple to its node, rows on another body to each other.
    Returns ``(adjacency over rows then hub nodes, hub body -> node, body -> its rows)``."""
    n = len(bodies)
    on_body: dict[int, set[int]] = {}
    for a in range(n):
        for b in bodies[a][bodies[a] >= 0]:
            on_body.setdefault(int(b), set()).add(a)
    hubs = sorted(b for b, rows in on_body.items() if threshold is not None and len(rows) > threshold)
    node = {b: n + i for i, b in enumerate(hubs)}
    adj: list[set[int]] = [set() for _ in range(n + len(hubs))]
    for b, rows in on_body.items():
        for a in rows:
            if b in node:
                adj[a].add(node[b])
                adj[node[b]].add(a)
            else:
                adj[a] |= rows
    for a, nb in enumerate(adj):
        nb.discard(a)
    return adj, node, on_body


def hub_fill(scene: str, thresholds=(None, 48, 24, 12)) -> list[dict]:
    """The fixed rows' factor entries if every body with more than ``threshold`` rows on it (a hub) kept its 6
    velocity unknowns in the system instead of being eliminated first (the quasi-definite augmented system
    ``[[R + sum_other J_b M_b^-1 J_b^T, J_h], [J_h^T, -M_h]]``, ``J_h`` the rows' blocks on the hub, rows x 6, whose
    Schur complement on the rows is ``D``): the
    rows on a hub then couple to its 6 unknowns, not to each other. ``None``: no hubs (the factor as built)."""
    from kamino.warp_backend.linear_solve_pattern import fixed_row_bodies

    model, _ = tb.load_scene(scene)
    bodies = fixed_row_bodies(model)[0]
    out = []
    for threshold in thresholds:
        adj, node, _ = hub_graph(bodies, threshold)
        out.append({"scene": scene, "hub_rows_over": threshold, "hubs": len(node),
                    "factor_entries": min_degree_fill(adj, [1] * len(bodies) + [6] * len(node))})
    return out


def main(argv: list[str] | None = None, prog: str | None = None) -> int:
    """``kamino bench memory_breakdown ARGS`` (``prog`` names the command in the help and errors); 0 when done."""
    p = argparse.ArgumentParser(prog=prog, description=__doc__.splitlines()[0])
    p.add_argument("--scenes", nargs="+", default=["fourbar", "ladder8", "ladder32", "dr_legs", "bdx", "olaf",
                                                   "animatronic"], choices=sorted({*tb.SCENES, *tb.ROBOTS}))
    p.add_argument("--worlds", type=int, default=4096)
    p.add_argument("--device", default=None, help="Warp device (default: Warp's default device)")
    p.add_argument("--top", type=int, default=8, help="arrays printed per scene")
    p.add_argument("--padmm", choices=("thread", "warp"), default=None,
                   help="the PADMM schedule (default: the automatic choice on the device; 'warp' on the CPU counts "
                        "what the GPU's 32-thread schedule allocates)")
    p.add_argument("--out", type=pathlib.Path, default=None)
    p.add_argument("--hub-fill", action="store_true",
                   help="print the fixed rows' factor entries with hub bodies kept as unknowns (hub_fill) and exit")
    p.add_argument("--tail-fill", action="store_true",
                   help="print the tail's L_tf entries (dense, as stored, per source) and exit")
    args = p.parse_args(argv)
    if args.worlds < 1:
        p.error(f"--worlds must be >= 1, got {args.worlds}")
    if args.hub_fill:
        for scene in args.scenes:
            for r in hub_fill(scene):
                print(f"{scene}: hubs (bodies with more than {r['hub_rows_over']} rows) {r['hubs']}: "
                      f"{r['factor_entries']} factor entries")
        return 0
    if args.tail_fill:
        for scene in args.scenes:
            r = tail_fill(scene)
            print(f"{scene}: {r['fixed_rows']} fixed rows, {r['tail_rows']} tail rows ({r['limit_rows']} limit, "
                  f"{r['contact_rows']} contact); L_tf dense {r['dense_L_tf']} entries, "
                  f"{r['uniform_L_tf']} as stored, every row sized for the widest pattern ({r['widest_pattern']}: "
                  f"{100 * r['uniform_L_tf'] / max(r['dense_L_tf'], 1):.0f} %), {r['sparse_L_tf']} sized per source "
                  f"({100 * r['sparse_L_tf'] / max(r['dense_L_tf'], 1):.0f} %); L_t {r['L_t']}; fixed rows: D~_ff "
                  f"{r['D_ff_lower']} entries in its lower triangle, L_f {r['L_f']}, {r['busiest_body_rows']} rows on "
                  "the busiest body")
        return 0
    import warp as wp

    wp.config.quiet = True
    records = []
    for scene in args.scenes:
        rec = breakdown(scene, args.worlds, args.device or str(wp.get_device()), args.padmm)
        records.append(rec)
        pool = "" if rec["mempool_per_world"] is None else f", memory pool {rec['mempool_per_world']:.0f}"
        print(f"{scene} ({rec['rows_max']} rows, {rec['padmm']}, {rec['linear_solver']}): "
              f"{rec['arrays_per_world']:.0f} B per world{pool}")
        for path, size in rec["largest"][:args.top]:
            print(f"    {path:<45s} {size:10.0f}")
    if args.out:
        args.out.write_text(json.dumps(records, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
