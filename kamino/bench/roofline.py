"""Roofline note per scene: the achieved fraction of the GPU's FLOP rate and memory bandwidth, from the
throughput records of :mod:`kamino.bench.throughput` and a cost per world-step counted on the code's own structures.

    kamino bench roofline RESULTS.json [RESULTS.json ...] [--worlds 4096] [--details]
                          [--peak-flops 67e12] [--peak-bandwidth 3.35e12] [--world-bytes-only]

Reads the kamino records (``"config": "default"``, no ``"peer"`` key) of each file, builds each scene's model as the
throughput benchmark does (:func:`kamino.bench.throughput.load_scene`) and its Warp stepper on the CPU under the
32-thread schedule (``Stepper(padmm="warp")``: ``linear_solve.build(per_world=True)`` with the hub threshold of the
run),
reads one world's factor pattern back from the device structures (``linear_solve.Pattern``: ``nnz``, the fan-out triples
``fan_*``, the ``L_tf`` patterns ``pat_*`` and their forward-substitution pairs ``pat_upd_*``), and prints a markdown
table. Identical worlds: one world's count is every world's.

Cost model (docs/warp_backend.md, "Robot-sized worlds: 32 threads per world on the sparse factor"; the kernels of
``kamino/warp_backend/solver_lanes.py``; docs/formulation.md §7.3-§7.5 and §8.1):

- FLOP per world-step = the factorisation (once per step, ``solver_lanes.factor``) + the mean PADMM iterations x one
  iteration (``solver_lanes.padmm_iterate``). Factorisation: ``L_f`` by fan-out (a square root per column, a division
  per entry below the diagonal, 2 FLOP per update triple), the tail's ``L_tf`` (a forward substitution per tail row
  over its pattern: 2 per pair, 1 division per entry), its Schur complement (2 per position shared by the two
  rows' patterns) and the dense Cholesky of the ``n_t`` tail rows (:func:`factor_flops`). One iteration: the solve
  (forward and backward sweeps over ``L_f``, a reciprocal and a product per diagonal, 2 per entry below it; the
  tail's ``L_tf`` twice and ``L_t`` twice: ``4 nnz + 4 sum |P_t| + 2 n_t^2``, :func:`solve_flops`) and the
  rule-by-rule arithmetic of the three row passes and the world's reductions (:func:`row_pass_flops`).
- Bytes per world-step = the mean iterations x the bytes one iteration moves + one pass over the world's device
  memory (the record's ``memory_per_world_bytes``, else counted: :func:`world_memory_bytes`). One iteration: each
  4-byte word a pass of the iteration reads or writes, counted once per pass (the solve's two sweeps each read the
  factor; 32 threads reading one word count once): the factor's values and the tail (per world), its index arrays
  (``perm``, ``row_ptr``, ``cptr``, ``cent``, ``crow``, ``colrow``, ``pat_*``: shared by the worlds of a type, so
  mostly L2 hits; ``--world-bytes-only`` leaves them out) and the row vectors the passes read and write
  (:func:`solve_words`, :func:`row_pass_words`). The solve's two vectors live in shared memory and are not counted.
- The tail at capacity: every limit row active and every contact slot's three rows on the contact pair with the
  widest ``L_tf`` pattern (as ``kamino bench memory_breakdown --tail-fill`` sizes it). The active tail is usually
  smaller, so a scene with a tail (limits or contact slots) gets ``<=``: its figures are upper bounds.

Not counted: the assembly of ``D~`` (``linear_solve.assemble_fixed`` / ``assemble_tail``: the Delassus entries) and
the other kernels of the step (kinematics, rows, collision, integration: their traffic is in the one pass over the
world's memory, their arithmetic is not), post-stabilisation's solve with ``L_f`` (``--details`` prints it), the
refactorisations inside PADMM (the tail's on a new penalty, the whole factor on a saturation switch: data dependent,
not in the records), and the factorisation's index traffic (the fan-out triples, shared by the worlds of a type).
Counts are of the arithmetic and the words in the source, not of compiled instructions; min, max and abs count as
one FLOP, comparisons as none.

A count of "factor multiply-adds" as ``n_upd + n_t nnz + n_t (n_t + 1) / 2 n_f + n_t^3 / 6`` is that of the factor
without hubs and with a dense ``L_tf`` (``linear_solve_pattern.symbolic`` with ``hubs=None``; e.g. dr_legs with a
36-row tail:
30,428 + 36 x 3,473 + 666 x 204 + 7,776 = 3.0e5), an upper bound of the counts here.
"""

import argparse
import dataclasses
import json
import math
import pathlib
import sys
from collections.abc import Callable, Iterable, Sequence

import numpy as np

from kamino.bench import throughput as tb  # the benchmark scenes

#: bytes of a float32 or int32 word
WORD = 4
#: H100 SXM: float32 FLOP/s without the tensor cores, and HBM3 bandwidth [B/s]
PEAK_FLOPS = 67e12
PEAK_BANDWIDTH = 3.35e12
#: threads per world of the 32-thread schedule (solver_lanes.LANES; a tile reduction of 32 values is 31 FLOP)
LANES = 32
#: the tile reductions of one iteration (solver_lanes.padmm_iterate: r_p, r_d, r_c, c_sum, r_tail, de, dx, hit)
REDUCTIONS = 8


# --- the structures a world's cost depends on -----------------------------------------------------------

@dataclasses.dataclass(frozen=True, eq=False)
class FactorShape:
    """One world's factor (``linear_solve_pattern.Symbolic`` / ``Pattern``), with its tail at capacity."""

    n_fixed: int  # fixed rows (joint-dynamics, joint, coupling)
    n_pos: int  # positions of L_f: the fixed rows, then 6 per hub
    nnz: int  # entries of L_f, diagonal included
    n_upd: int  # fan-out update triples (Symbolic.fan_*): L_f's multiply-adds
    tail: tuple[np.ndarray, ...] = ()  # the L_tf pattern (fixed positions) of each tail row
    tail_upd: tuple[int, ...] = ()  # each tail row's L_tf forward-substitution pairs (Pattern.pat_upd_*)
    tail_pid: tuple[int, ...] = ()  # each tail row's pattern id (rows of one pattern share its index arrays)

    @property
    def n_tail(self) -> int:
        return len(self.tail)


@dataclasses.dataclass(frozen=True)
class RowShape:
    """One world's rows at capacity, by the arithmetic ``padmm_iterate`` does on them."""

    fixed_bounded: int  # effort-limited actuator rows (finite box: lo = -bound, hi = bound)
    fixed_free: int  # the other fixed rows (joint, coupling, passive, unlimited actuator: the null-direction test)
    limits: int  # limit rows (lo = 0, hi = inf)
    contacts: int  # contact slots (three rows each)

    @property
    def n_box(self) -> int:
        return self.fixed_bounded + self.fixed_free + self.limits

    @property
    def n_rows(self) -> int:
        return self.n_box + 3 * self.contacts


@dataclasses.dataclass(frozen=True)
class SceneShape:
    """What :func:`step_cost` needs of a scene: its factor and rows, and post-stabilisation's solves per step."""

    factor: FactorShape
    rows: RowShape
    post_solves: int = 0


@dataclasses.dataclass(frozen=True)
class Cost:
    """FLOP and bytes (per world and in index arrays shared by the worlds of a type)."""

    flops: float
    world_bytes: float
    shared_bytes: float = 0.0

    def bytes(self, shared: bool = True) -> float:
        return self.world_bytes + (self.shared_bytes if shared else 0.0)


# --- factorisation and solve --------------------------------------------------------------------------------

def fixed_factor_flops(f: FactorShape) -> int:
    """``L_f`` by fan-out (``solver_lanes.factor``): a square root per position, a division per entry below the
    diagonal, and 2 per update triple: ``nnz + 2 n_upd``."""
    return f.nnz + 2 * f.n_upd


def dense_cholesky_flops(n: int) -> int:
    """The tail's ``L_t = chol(S_t + shift I)`` by columns (``solver_lanes.factor_tail``): column ``j`` adds the
    shift, subtracts ``j`` products and takes a root (``2 j + 2``), and each of the ``n - 1 - j`` rows below it
    subtracts ``j`` products and divides (``2 j + 1``)."""
    return sum(2 * j + 2 + (n - 1 - j) * (2 * j + 1) for j in range(n))


def tail_factor_flops(f: FactorShape) -> int:
    """The tail rows' share of the factorisation: ``L_tf`` (per tail row, its pattern's forward-substitution pairs at
    2 FLOP and a division per entry), the Schur complement ``S_t = D~_t - L_tf L_tf^T`` (pair ``(t, j <= t)``: 2 per
    position in both rows' patterns, ``linear_solve.schur_entry``) and :func:`dense_cholesky_flops`."""
    ltf = sum(len(p) + 2 * u for p, u in zip(f.tail, f.tail_upd, strict=True))
    schur = sum(2 * len(np.intersect1d(f.tail[t], f.tail[j], assume_unique=True))
                for t in range(f.n_tail) for j in range(t + 1))
    return ltf + schur + dense_cholesky_flops(f.n_tail)


def factor_flops(f: FactorShape) -> int:
    """FLOP of one factorisation of the world (once per step)."""
    return fixed_factor_flops(f) + tail_factor_flops(f)


def solve_flops(f: FactorShape, tail: bool = True) -> int:
    """FLOP of one solve ``x <- L^-T L^-1 x`` (``solver_lanes.solve``): each sweep over ``L_f`` a reciprocal and a
    product per position and 2 per entry below the diagonal (``4 nnz`` for both); the tail's fixed part twice
    (forward over ``L_tf``, backward its share of the fixed rows: ``4 sum |P_t|``); ``L_t`` forward and backward, a
    division per row and 2 per entry below the diagonal (``2 n_t^2``). ``tail=False``: the fixed rows only
    (post-stabilisation's solve)."""
    n = f.n_tail if tail else 0
    return 4 * f.nnz + (4 * sum(len(p) for p in f.tail) + 2 * n * n if n else 0)


def solve_words(f: FactorShape, tail: bool = True) -> tuple[int, int]:
    """Words one solve reads, counted once per sweep: ``(per world, shared)``. Per world: ``L_f``'s values in each
    sweep (``2 nnz``); the tail's ``L_tf`` entries in each of its two passes, ``L_t``'s lower triangle in each of
    its two sweeps, and each tail row's pattern id (``Pattern.tail_pat``) in the two passes that look it up. Shared
    by the worlds of a type: forward ``perm``, the diagonal's ``row_ptr``, ``cptr``, ``cent`` and ``crow`` (``n_pos``
    + ``n_pos`` + ``n_pos + 1`` + 2 per entry below the diagonal); backward ``perm``, ``row_ptr`` and ``colrow``;
    the hubs' positions' ``perm`` twice (right-hand side, sign); per pattern in use ``pat_ptr`` (2) and ``pat_row``
    (forward), and the backward pass's ``perm`` and each pattern's lookup ``pat_lut`` (``n_pos`` each)."""
    below = f.nnz - f.n_pos
    shared = (3 * f.n_pos + 1 + 2 * below) + (2 * f.n_pos + 1 + below) + 2 * (f.n_pos - f.n_fixed)
    world = 2 * f.nnz
    n = f.n_tail if tail else 0
    if n:
        world += 2 * sum(len(p) for p in f.tail) + n * (n + 1) + 2 * n
        used = {pid: len(p) for pid, p in zip(f.tail_pid, f.tail, strict=True)}
        shared += f.n_pos + sum(2 + size + f.n_pos for size in used.values())
    return world, shared


# --- the PADMM row passes -------------------------------------------------------------------------------------

#: FLOP per row (per contact slot for ``contact``) of one ``padmm_iterate`` iteration, pass by pass:
#: right-hand side ``-vt + eta x_p + rho y_hat + z_hat`` (5; a contact's normal row also ``- mu |z_t|``, De Saxcé: 7);
#: projection and dual update (a box row: ``x - z_hat / rho`` 2, the clamp 2, ``dual_update`` 25, the maxima of r_p
#: and r_d and the sum c 3, then the complementarity with its maximum, 8 on a two-sided box, 5 on a limit's, 1
#: without bounds, and r_tail 1 or the null-direction test's ``e``, ``|e - e_p|``, ``|x - x_p|`` 11 on a fixed row
#: without bounds; a contact: the three arguments 6, ``cone_project`` 14 on its costliest branch, per row
#: ``dual_update`` 25 + 3 maxima + the sum + ``y z`` 2, the slot's ``|y.z|`` 2); momentum (``y_hat``, ``z_hat``
#: extrapolated, 3 each).
ROW_FLOPS = {
    "fixed_bounded": 5 + (2 + 2 + 25 + 3 + 8 + 1) + 6,
    "fixed_free": 5 + (2 + 2 + 25 + 3 + 1 + 11) + 6,
    "limits": 5 + (2 + 2 + 25 + 3 + 5 + 1) + 6,
    "contacts": 3 * 5 + 7 + (6 + 14 + 3 * (25 + 3 + 1 + 2) + 2) + 3 * 6,
}
#: words per row (per contact slot) of one iteration, counted once per pass: right-hand side (``vt``, ``x_p``,
#: ``y_hat``, ``z_hat``; a fixed row's ``row_info`` for its penalty; a contact's ``row_info`` and ``ct_mu`` for its
#: friction), projection and dual update (reads ``z_hat``, ``lo``, ``hi``, ``x_p``, ``y_hat``, ``P``, a fixed row's
#: ``row_info``; writes ``x``, ``y``, ``z``; a fixed row without bounds reads and writes ``e_p``; a contact reads
#: ``z_hat``, ``x_p``, ``y_hat``, ``P`` of its rows, ``row_info``, ``ct_mu`` and writes ``x``, ``y``, ``z``), momentum
#: (reads ``y``, ``z``, ``y_p``, ``z_p``; writes ``y_hat``, ``z_hat``, ``x_p``, ``y_p``, ``z_p``).
ROW_WORDS = {
    "fixed_bounded": 5 + (7 + 3) + 9,
    "fixed_free": 5 + (7 + 3 + 2) + 9,
    "limits": 4 + (6 + 3) + 9,
    "contacts": (3 * 4 + 2) + (14 + 9) + 3 * 9,
}
#: per world and iteration: the tile reductions, the momentum (§7.4), the stopping and penalty tests
WORLD_FLOPS = REDUCTIONS * (LANES - 1) + 20
#: per world and iteration: iters, it_cap, a_p, c_p, k_rho read; a_p, c_p, iters, r_p, r_d, r_c written
WORLD_WORDS = 11


def row_pass_flops(r: RowShape) -> int:
    """FLOP of one iteration's row passes and world reductions (:data:`ROW_FLOPS`, :data:`WORLD_FLOPS`)."""
    return sum(getattr(r, k) * v for k, v in ROW_FLOPS.items()) + WORLD_FLOPS


def row_pass_words(r: RowShape) -> int:
    """Words one iteration's row passes move, per world (:data:`ROW_WORDS`, :data:`WORLD_WORDS`)."""
    return sum(getattr(r, k) * v for k, v in ROW_WORDS.items()) + WORLD_WORDS


# --- per iteration, per world-step ----------------------------------------------------------------------------

def iteration_cost(s: SceneShape) -> Cost:
    """One PADMM iteration of one world: the solve and the row passes."""
    world, shared = solve_words(s.factor)
    return Cost(flops=solve_flops(s.factor) + row_pass_flops(s.rows),
                world_bytes=WORD * (world + row_pass_words(s.rows)), shared_bytes=WORD * shared)


def step_cost(s: SceneShape, iterations: float, memory_bytes: float) -> Cost:
    """One world-step: the factorisation, ``iterations`` x :func:`iteration_cost`, and one pass over the world's
    ``memory_bytes`` of device memory."""
    it = iteration_cost(s)
    return Cost(flops=factor_flops(s.factor) + iterations * it.flops,
                world_bytes=iterations * it.world_bytes + memory_bytes, shared_bytes=iterations * it.shared_bytes)


def is_upper_bound(s: SceneShape) -> bool:
    """A tail sized at capacity (limit rows, contact slots): fewer rows are usually active."""
    return s.factor.n_tail > 0


# --- a scene's shapes, read from the Warp backend's structures -------------------------------------------------

def stepper_of(model):
    """The default configuration's Warp stepper of ``model`` on the CPU under the 32-thread schedule (as
    ``throughput.bench_warp`` builds it on the GPU at these world counts)."""
    import warp as wp

    import kamino
    from kamino.warp_backend.pipeline import Stepper

    cfg = kamino.SolverConfig(dt=tb.DT, **tb.SOLVER, **tb.CONFIGS["default"])
    return Stepper(model, cfg, np.float32, wp.get_device("cpu"), padmm="warp")


def factor_shape(sp, lim_dofs: np.ndarray, contact_slots: int, pairs: int) -> FactorShape:
    """World 0's :class:`FactorShape` from a ``linear_solve.Pattern`` (``sp``), its limited DoFs (global indices, in
    the order the limit rows are packed), contact slots and contact pairs: each limit row has its DoF's ``L_tf``
    pattern, and every contact row the widest of the pairs' patterns (the most updates among equals)."""
    a = {name: getattr(sp, name).numpy() for name in ("n_fixed", "n_pos", "nnz", "ptr_start", "fan_ptr", "pat_ptr",
                                                      "pat_pos", "pat_upd_ptr", "dof_pat", "con_pat")}
    nf, npos, nnz, p0 = (int(a[k][0]) for k in ("n_fixed", "n_pos", "nnz", "ptr_start"))
    n_upd = int(a["fan_ptr"][p0 + npos] - a["fan_ptr"][p0])
    pat_ptr, pat_upd_ptr = a["pat_ptr"], a["pat_upd_ptr"]

    def pattern(pid: int) -> np.ndarray:
        return a["pat_pos"][pat_ptr[pid]:pat_ptr[pid + 1]].astype(np.int64)

    def updates(pid: int) -> int:
        return int(pat_upd_ptr[pat_ptr[pid + 1]] - pat_upd_ptr[pat_ptr[pid]])

    ids = [int(p) for p in a["dof_pat"][lim_dofs]] if len(lim_dofs) else []
    if contact_slots:
        con0 = int(a["con_pat"][0])
        widest = max(range(con0, con0 + pairs), key=lambda p: (len(pattern(p)), updates(p)))
        ids += [widest] * (3 * contact_slots)
    return FactorShape(n_fixed=nf, n_pos=npos, nnz=nnz, n_upd=n_upd, tail=tuple(pattern(p) for p in ids),
                       tail_upd=tuple(updates(p) for p in ids), tail_pid=tuple(ids))


def row_shape(model, n_fixed: int) -> RowShape:
    """World 0's :class:`RowShape` at capacity: its effort-limited actuator rows have a two-sided box, its other
    fixed rows none (``rows.dyn_rows``, ``joint_rows``, ``coupling_rows``)."""
    from kamino.tables import DYN_ACTUATOR, row_tables

    tab = row_tables(model)
    d = int(tab.world_dyn_count[0])  # world 0's joint-dynamics rows come first
    act = tab.dyn_dof[:d][tab.dyn_kind[:d] == DYN_ACTUATOR]
    bounded = int(np.isfinite(np.asarray(model.dof_effort_limit)[act]).sum())
    return RowShape(fixed_bounded=bounded, fixed_free=n_fixed - bounded, limits=int(tab.world_lim_count[0]),
                    contacts=int(model.world_contact_capacity[0]))


def scene_shape(name: str) -> SceneShape:
    """:class:`SceneShape` of a benchmark scene (one world of ``throughput.load_scene(name)``), from the stepper's
    ``linear_solve.Pattern``. Checks that the tail it counts is the capacity the stepper allocated."""
    from kamino.tables import prefix, row_tables

    model, _ = tb.load_scene(name)
    st = stepper_of(model)
    tab = row_tables(model)
    l0 = int(prefix(tab.world_lim_count)[0])
    lim_dofs = np.asarray(tab.lim_dof)[l0:l0 + int(tab.world_lim_count[0])]
    f = factor_shape(st.sf.arrays, lim_dofs, int(model.world_contact_capacity[0]), int(model.world_pair_count[0]))
    rows = row_shape(model, f.n_fixed)
    capacity = int(st.wm.arrays.row_maxdim.numpy()[0])
    if f.n_fixed + f.n_tail != capacity or rows.n_rows != capacity:
        raise RuntimeError(f"{name}: counted {f.n_fixed} fixed + {f.n_tail} tail rows ({rows.n_rows} by kind), the "
                           f"stepper allocates {capacity}")
    posts = int(st.cfg.stabilisation.post_stabilisation) if st.post_shares_factor else 0
    return SceneShape(factor=f, rows=rows, post_solves=posts)


def world_memory_bytes(name: str, group: int = 32) -> float:
    """The device memory one more world takes (``memory_breakdown.breakdown``'s arrays at ``2 group`` worlds less
    those at ``group``, per world: the patterns shared by a type drop out), for records without a measured value."""
    import memory_breakdown as mb

    small, large = (mb.breakdown(name, n, "cpu", padmm="warp")["arrays_per_world"] * n for n in (group, 2 * group))
    return (large - small) / group


# --- records and the table ------------------------------------------------------------------------------------

def kamino_records(results: Iterable[dict], worlds: Sequence[int] | None = None) -> list[dict]:
    """The kamino records at the default configuration (no peers), at ``worlds`` (all if ``None``); of several of
    the same scene and size, the later one (``throughput.latest_records``, the rule of ``--table`` and ``--plot``)."""
    out = [r for r in tb.latest_records(r for res in results for r in res.get("records", []))
           if "peer" not in r and r.get("config") == "default" and r.get("throughput") is not None
           and (worlds is None or int(r["num_worlds"]) in worlds)]
    order = {s: i for i, s in enumerate((*tb.SCENES, *tb.ROBOTS))}
    return sorted(out, key=lambda r: (order.get(r["scene"], len(order)), r["scene"], int(r["num_worlds"])))


def sig(x: float, digits: int = 2) -> str:
    """``x`` to ``digits`` significant digits without an exponent: ``sig(150.3) == "150"``, ``sig(0.2234) ==
    "0.22"``."""
    if x == 0 or not math.isfinite(x):
        return f"{x:g}"
    return f"{x:.{max(digits - 1 - math.floor(math.log10(abs(x))), 0)}f}"


def sci(x: float, digits: int = 2) -> str:
    """``x`` in scientific notation, as the benchmark tables write it: ``sci(3.06e5) == "3.1e5"``."""
    mantissa, exponent = f"{x:.{digits - 1}e}".split("e")
    return f"{mantissa}e{int(exponent)}"


def si(x: float, unit: str, digits: int = 2) -> str:
    """``x`` with an SI prefix: ``si(3.06e5, "B") == "310 kB"``."""
    for scale, prefix in ((1e12, "T"), (1e9, "G"), (1e6, "M"), (1e3, "k")):
        if abs(x) >= scale:
            return f"{sig(x / scale, digits)} {prefix}{unit}"
    return f"{sig(x, digits)} {unit}"


def roofline_rows(records: Sequence[dict], shape_of: Callable[[str], SceneShape],
                  memory_of: Callable[[str], float], peak_flops: float = PEAK_FLOPS,
                  peak_bandwidth: float = PEAK_BANDWIDTH, shared: bool = True) -> list[dict]:
    """Per record: the cost per world-step (:func:`step_cost`) and what its throughput achieves against the peaks.
    ``shape_of(scene)``: the scene's :class:`SceneShape`; ``memory_of(scene)``: its memory per world where the
    record has none; ``shared``: count the index arrays shared by the worlds of a type."""
    rows = []
    for r in records:
        s = shape_of(r["scene"])
        memory = float(r.get("memory_per_world_bytes") or 0.0) or memory_of(r["scene"])
        cost = step_cost(s, float(r["iterations_mean"]), memory)
        flops, nbytes = cost.flops, cost.bytes(shared)
        rate = float(r["throughput"])
        rows.append({"scene": r["scene"], "worlds": int(r["num_worlds"]), "throughput": rate,
                     "iterations": float(r["iterations_mean"]), "flop": flops, "bytes": nbytes,
                     "flops": rate * flops, "bandwidth": rate * nbytes, "flops_fraction": rate * flops / peak_flops,
                     "bandwidth_fraction": rate * nbytes / peak_bandwidth, "upper_bound": is_upper_bound(s),
                     "memory": memory, "padmm": r.get("padmm")})
    return rows


def markdown(rows: Sequence[dict]) -> str:
    """The table: scene | worlds | world-steps/s | mean iterations | FLOP and bytes per world-step | achieved. A run
    under one thread per world (``"padmm": "thread"``, large world counts) is marked: the same arithmetic and factor
    reads, but its solve's vectors live in device memory, which the count leaves out."""
    head = ("| scene | worlds | world-steps/s | mean iterations | FLOP per world-step | bytes per world-step | "
            "achieved FLOP/s (% of peak) | achieved bandwidth (% of peak) |\n|---|---|---|---|---|---|---|---|")
    lines = [head]
    for r in rows:
        le = "<= " if r["upper_bound"] else ""
        worlds = f"{r['worlds']}" + (" (thread)" if r["padmm"] == "thread" else "")
        lines.append(f"| {r['scene']} | {worlds} | {sci(r['throughput'], 3)} | {r['iterations']:.2f} | "
                     f"{le}{sci(r['flop'])} | {le}{si(r['bytes'], 'B')} | "
                     f"{le}{si(r['flops'], 'FLOP/s')} ({sig(100 * r['flops_fraction'])} %) | "
                     f"{le}{si(r['bandwidth'], 'B/s')} ({sig(100 * r['bandwidth_fraction'])} %) |")
    return "\n".join(lines)


def details(scenes: Iterable[str], shape_of: Callable[[str], SceneShape]) -> str:
    """Per scene, the counts behind the table (per world) and post-stabilisation's solves, which it leaves out."""
    lines = ["| scene | fixed rows / positions / tail rows | nnz(L_f) | update triples | factorisation FLOP | "
             "solve FLOP | row-pass FLOP | iteration bytes: per world / shared | post-stabilisation FLOP (not "
             "counted) |", "|---|---|---|---|---|---|---|---|---|"]
    for name in scenes:
        s = shape_of(name)
        f, it = s.factor, iteration_cost(s)
        lines.append(f"| {name} | {f.n_fixed} / {f.n_pos} / {f.n_tail} | {f.nnz} | {f.n_upd} | "
                     f"{sci(factor_flops(f))} | {sci(solve_flops(f))} | {sci(row_pass_flops(s.rows))} | "
                     f"{si(it.world_bytes, 'B')} / {si(it.shared_bytes, 'B')} | "
                     f"{sci(s.post_solves * solve_flops(f, tail=False))} |")
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None, prog: str | None = None) -> int:
    """``kamino bench roofline ARGS`` (``prog`` names the command in the help and errors); 0 when done."""
    ap = argparse.ArgumentParser(prog=prog, description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawTextHelpFormatter,
                                 epilog="The cost model: help(kamino.bench.roofline).")
    ap.add_argument("results", nargs="+", type=pathlib.Path, help="JSON files of kamino bench (throughput) runs")
    ap.add_argument("--worlds", nargs="+", type=int, default=[4096], help="world counts to report (default 4096)")
    ap.add_argument("--peak-flops", type=float, default=PEAK_FLOPS, help="FLOP/s (default: H100 SXM float32)")
    ap.add_argument("--peak-bandwidth", type=float, default=PEAK_BANDWIDTH, help="B/s (default: H100 SXM HBM3)")
    ap.add_argument("--world-bytes-only", action="store_true",
                    help="leave out the index arrays shared by the worlds of a type (mostly L2 hits)")
    ap.add_argument("--details", action="store_true", help="also print the per-world counts behind the table")
    args = ap.parse_args(argv)
    import warp as wp

    wp.config.quiet = True
    records = kamino_records((json.loads(p.read_text()) for p in args.results), args.worlds)
    shapes: dict[str, SceneShape] = {}
    memories: dict[str, float] = {}

    def shape_of(name: str) -> SceneShape:
        if name not in shapes:
            shapes[name] = scene_shape(name)
        return shapes[name]

    def memory_of(name: str) -> float:
        if name not in memories:
            memories[name] = world_memory_bytes(name)
        return memories[name]

    rows = roofline_rows(records, shape_of, memory_of, args.peak_flops, args.peak_bandwidth,
                         shared=not args.world_bytes_only)
    print(markdown(rows))
    print(f"\nPeaks: {si(args.peak_flops, 'FLOP/s', 3)}, {si(args.peak_bandwidth, 'B/s', 3)}. `<=`: the tail (limit "
          "rows, contact slots) counted at capacity, an upper bound. (thread): a run with one thread per world, "
          "counted as the 32-thread schedule. Bytes " + ("without" if args.world_bytes_only else "with")
          + " the index arrays shared by the worlds of a type. Cost model: kamino.bench.roofline's docstring.")
    if args.details:
        print()
        print(details(dict.fromkeys(r["scene"] for r in rows), shape_of))
    return 0


if __name__ == "__main__":
    sys.exit(main())
