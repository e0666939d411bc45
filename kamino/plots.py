"""Plots people want from kamino runs, drawn in one place: a rollout's loop closure, energy, PADMM
iterations and residuals over time (:func:`rollout_diagnostics`); the benchmark JSONs' throughput against loop
closure (:func:`speed_against_error`), throughput against world count (:func:`throughput_against_worlds`) and the
iterations-per-step histograms (:func:`iterations_histogram`). :func:`save_figure` writes a PNG and closes it.

matplotlib is the ``bench`` extra (``pip install 'kamino[bench]'``); it is imported inside each function, never
when ``kamino.plots`` is imported, and no backend is forced: the Agg backend is chosen only when none was set and
there is no display to draw on. Every function returns the :class:`matplotlib.figure.Figure` it drew on.
"""

from __future__ import annotations

import math
import os
import sys
from collections.abc import Mapping, Sequence
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    from matplotlib.axes import Axes
    from matplotlib.figure import Figure

    from kamino.model import Model
    from kamino.state import State

__all__ = ["iterations_histogram", "rollout_diagnostics", "save_figure", "speed_against_error", "speed_at_accuracy",
           "throughput_against_worlds"]

_INSTALL = "pip install 'kamino[bench]'"


def _pyplot():
    """``matplotlib.pyplot``, or an ImportError that names the extra. Chooses Agg only when no backend was set (by
    ``MPLBACKEND``, ``matplotlib.use`` or an rc file) and, on Linux, there is no display; pyplot already imported
    keeps whatever it has."""
    try:
        import matplotlib
    except ImportError as e:
        raise ImportError(f"kamino.plots needs matplotlib, which is not installed; install the bench extra: "
                          f"{_INSTALL}") from e
    if "matplotlib.pyplot" not in sys.modules and not os.environ.get("MPLBACKEND"):
        from matplotlib import rcsetup

        unset = matplotlib.rcParams._get("backend") is rcsetup._auto_backend_sentinel
        headless = sys.platform.startswith("linux") and not (os.environ.get("DISPLAY")
                                                             or os.environ.get("WAYLAND_DISPLAY"))
        if unset and headless:
            matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _axes(ax: Axes | Sequence[Axes] | None, n: int, *, ncols: int | None = None,
          panel: tuple[float, float] = (4.5, 4.0)) -> tuple[Figure, list[Axes]]:
    """``n`` axes: the caller's (one Axes when ``n == 1``, else a sequence of at least ``n``) or a new figure's
    (``ncols`` a row, default all in one row)."""
    if ax is None:
        plt = _pyplot()
        ncols = min(ncols or n, n) or 1
        nrows = max(1, -(-n // ncols))
        fig, grid = plt.subplots(nrows, ncols, figsize=(panel[0] * ncols, panel[1] * nrows), squeeze=False)
        flat = list(grid.flat)
        for extra in flat[n:]:
            extra.axis("off")
        return fig, flat[:n]
    axes = [ax] if hasattr(ax, "figure") else list(ax)
    if len(axes) < n:
        raise ValueError(f"kamino.plots: this plot draws {n} panel(s), got {len(axes)} Axes")
    return axes[0].figure, axes[:n]


def _short_log_ticks(ax: Axes, x: Sequence[float], y: Sequence[float]) -> None:
    """Short tick labels on log axes; minor labels only where the data span less than a decade."""
    import matplotlib.ticker

    short = matplotlib.ticker.FuncFormatter(lambda v, _: f"{v:.2g}")
    for axis, data in ((ax.xaxis, x), (ax.yaxis, y)):
        data = [d for d in data if d and d > 0]
        if not data:
            continue
        axis.set_major_formatter(short)
        axis.set_minor_formatter(short if max(data) < 10 * min(data) else matplotlib.ticker.NullFormatter())
    ax.tick_params(axis="x", which="both", labelrotation=45, labelsize=7)
    ax.tick_params(axis="y", which="both", labelsize=7)


def save_figure(fig: Figure, path: str | os.PathLike, *, dpi: int = 120) -> str:
    """Write ``fig`` to ``path`` (the format from its suffix), close it (pyplot keeps no reference) and return
    the path as a string."""
    fig.savefig(path, dpi=dpi)
    if "matplotlib.pyplot" in sys.modules:
        sys.modules["matplotlib.pyplot"].close(fig)
    return str(path)


# ------------------------------------------------------------------------------------------------ rollouts


def rollout_diagnostics(model: Model, traj: State, *, world: int | None = 0, dt: float | None = None,
                        ax: Sequence[Axes] | None = None) -> Figure:
    """Four panels from a :func:`kamino.rollout` trajectory (a :class:`kamino.State` with a leading time axis):

    1. loop closure: :func:`kamino.metrics`' ``constraint_violation`` over time (log y; m for translational rows,
       rad for rotational ones);
    2. energy: ``kinetic_energy``, ``potential_energy`` and ``total_energy`` over time [J];
    3. PADMM iterations per step (``traj.info.iterations``), unconverged steps marked with red crosses;
    4. the solve's ``primal_residual`` and ``dual_residual`` per step (log y).

    Args:
        model: the model the trajectory was run on.
        traj: the trajectory; ``traj.info`` holds each step's :class:`kamino.StepInfo` (``[num_steps, num_worlds]``).
        world: the world to draw, or ``None`` for the maximum over all worlds of every quantity (an envelope;
            a step counts as unconverged when any world's solve did not converge).
        dt: the step [s], used for the time axis only when ``traj`` has no ``time`` (then ``step * dt``);
            with neither, the x axis is the step index.
        ax: four Axes to draw into (in the order above); by default a new 2 x 2 figure.

    Returns:
        The figure drawn on. Each panel's lines hold exactly the plotted arrays (``line.get_ydata()``).
    """
    from kamino.readouts import metrics

    m = {k: np.asarray(v) for k, v in metrics(model, traj).items()}
    num_steps, num_worlds = m["constraint_violation"].shape
    if world is not None and not -num_worlds <= world < num_worlds:
        raise ValueError(f"rollout_diagnostics: world {world} is out of range for {num_worlds} world(s)")

    def pick(a: Any, reduce=np.max) -> np.ndarray:
        a = np.asarray(a).reshape(num_steps, -1)
        return a[:, world] if world is not None else reduce(a, axis=1)

    time = getattr(traj, "time", None)
    if time is not None:
        t, xlabel = pick(time), "time [s]"
    elif dt is not None:
        t, xlabel = (np.arange(num_steps) + 1) * dt, "time [s]"
    else:
        t, xlabel = np.arange(num_steps) + 1, "step"
    which = f"world {world}" if world is not None else f"max over {num_worlds} worlds"
    fig, (a_close, a_energy, a_iter, a_res) = _axes(ax, 4, ncols=2, panel=(5.5, 3.5))

    a_close.plot(t, pick(m["constraint_violation"]), label="constraint violation")
    a_close.set(yscale="log", xlabel=xlabel, ylabel="max |joint residual| [m, rad]", title=f"loop closure ({which})")
    for key in ("kinetic_energy", "potential_energy", "total_energy"):
        a_energy.plot(t, pick(m[key]), label=key.replace("_", " "))
    a_energy.set(xlabel=xlabel, ylabel="energy [J]", title=f"energy ({which})")
    info = traj.info
    iters = pick(info.iterations)
    a_iter.plot(t, iters, drawstyle="steps-mid", label="iterations")
    unconverged = ~pick(info.converged, np.min).astype(bool)
    if unconverged.any():
        a_iter.plot(t[unconverged], iters[unconverged], "x", color="tab:red", label="not converged")
    a_iter.set(xlabel=xlabel, ylabel="PADMM iterations", title=f"PADMM iterations per step ({which})")
    for key in ("primal_residual", "dual_residual"):
        a_res.plot(t, pick(getattr(info, key)), label=key.replace("_", " "))
    a_res.set(yscale="log", xlabel=xlabel, ylabel="residual", title=f"PADMM residuals per step ({which})")
    for a in (a_close, a_energy, a_iter, a_res):
        a.grid(True, which="both", alpha=0.3)
        a.legend(fontsize=7)
        a.title.set_fontsize(9)
    if ax is None:
        fig.tight_layout()
    return fig


# ---------------------------------------------------------------------------------------- benchmark results


def _records(results: Mapping[str, Any] | Sequence[Mapping[str, Any]]) -> list[Mapping[str, Any]]:
    """The records of a benchmark JSON (its ``records``, or a list of them), without failed runs."""
    recs = results["records"] if isinstance(results, Mapping) else results
    return [r for r in recs if "error" not in r]


def _series(r: Mapping[str, Any]) -> str:
    """A throughput record's simulator and load: ``kamino <config>`` or ``<peer> <variant>``, followed by
    ``, <load>`` for a load other than the gentle one (``kamino.bench.loads``)."""
    load = "" if r.get("load", "gentle") == "gentle" else f", {r['load']}"
    if "config" in r and not isinstance(r["config"], Mapping):
        return f"kamino {r['config']}{load}"
    if r.get("peer"):
        return f"{r['peer']} {r.get('variant') or ''}".strip() + load
    return f"kamino {r.get('kamino') or ''}".strip() + load


def record_closure(r: Mapping[str, Any]) -> float | None:
    """A throughput record's loop closure: its timed batch's (``closure_batch_max_m``), else a one-world run's
    (``closure_max_m``; a SolverKamino run of a scene without loops has none, and its ``joint_error_max_m``, the
    largest anchor distance of any joint, is the figure that kamino's closure measures there)."""
    closure = r.get("closure_batch_max_m", r.get("closure_max_m"))
    if closure is None and r.get("peer") and r.get("peer") != "mujoco_warp":
        closure = r.get("joint_error_max_m")
    return closure


def _is_convergence(r: Mapping[str, Any]) -> bool:
    return "throughput_world_steps_per_s" in r or "run_world_steps_per_s" in r


def _distinct_runs(recs: Sequence[Mapping[str, Any]]) -> list[Mapping[str, Any]]:
    """The records with each convergence run once: ``kamino bench convergence`` records the default run, and its
    tolerance sweep repeats it at the default tolerance; the sweep's copy is kept, in record order."""
    swept = {(r["scene"], r["num_worlds"], r.get("dt"), r["tolerance"]) for r in recs
             if _is_convergence(r) and r.get("sweep")}
    return [r for r in recs if not (_is_convergence(r) and not r.get("sweep")
                                    and (r["scene"], r["num_worlds"], r.get("dt"), r["tolerance"]) in swept)]


def _labelled_series(a: Axes, series: Mapping[str, Sequence[tuple[float, float, str]]], *,
                     linestyle: str) -> tuple[list[float], list[float]]:
    """Draw each series (name -> ``(x, y, label)`` points, in drawing order) as one line of markers with every point
    annotated by its label; return every drawn x and y (for the ticks)."""
    xs: list[float] = []
    ys: list[float] = []
    for name, pts in sorted(series.items()):
        x, y, labels = zip(*pts, strict=True)
        a.plot(x, y, marker="o", linestyle=linestyle, label=name)
        for xi, yi, text in zip(x, y, labels, strict=True):
            a.annotate(text, (xi, yi), fontsize=6, textcoords="offset points", xytext=(4, 4))
        xs += x
        ys += y
    return xs, ys


def _finish_log_panel(a: Axes, xs: Sequence[float], ys: Sequence[float]) -> None:
    """Short log ticks over the drawn data, a light grid and a small legend."""
    _short_log_ticks(a, xs, ys)
    a.grid(True, which="both", alpha=0.3)
    a.legend(fontsize=6)


def speed_against_error(results: Mapping[str, Any] | Sequence[Mapping[str, Any]], *,
                        ax: Axes | Sequence[Axes] | None = None) -> Figure:
    """Throughput (y, log) against max loop closure (x, log), one panel per scene, from a benchmark JSON.

    - ``kamino.bench.throughput`` records: one series per kamino configuration (``kamino <config>``) and per
      peer (``<peer> <variant>``) under each load, one point per world count run, labelled with it. The closure is
      the timed batch's (``closure_batch_max_m``) or, for a peer, one world's run on one world count, so a record
      without a closure takes its series'; a series with no closure at all is left out.
    - ``kamino.bench.convergence`` records: one series per scene and world count over the tolerance sweep, one
      point per tolerance (labelled with it and the converged fraction; a default run at a tolerance the sweep
      also ran is drawn once), the y value its
      ``throughput_world_steps_per_s`` (or, where a point has none, e.g. on the CPU, every point's
      ``run_world_steps_per_s``, which includes host probes).

    Args:
        results: the JSON's dict (with ``records``) or the list of records; records with ``error`` are skipped.
        ax: the Axes to draw into (one per scene, scenes sorted by name); by default a new figure.

    Returns:
        The figure drawn on; each series is one line whose data are its points, in world-count order
        (throughput records) or from the loosest tolerance to the tightest (convergence records).
    """
    # scene -> series -> [(closure, throughput, label, order)]
    panels: dict[str, dict[str, list[tuple[float, float, str, float]]]] = {}
    run_rate: dict[str, bool] = {}
    recs = _distinct_runs(_records(results))
    closures: dict[tuple[str, str], float] = {}
    for r in recs:
        if not _is_convergence(r) and record_closure(r) is not None:
            closures.setdefault((r["scene"], _series(r)), record_closure(r))
    conv: dict[tuple[str, str], list[Mapping[str, Any]]] = {}
    for r in recs:
        if _is_convergence(r):
            conv.setdefault((r["scene"], f"kamino, {r['num_worlds']} worlds (tolerance sweep)"), []).append(r)
        elif r.get("throughput"):
            closure = record_closure(r) or closures.get((r["scene"], _series(r)))
            if closure is not None:
                panels.setdefault(r["scene"], {}).setdefault(_series(r), []).append(
                    (max(closure, 1e-12), r["throughput"], f"{r['num_worlds']} w", r["num_worlds"]))
    for (scene, name), rs in conv.items():
        rs = sorted((r for r in rs if r.get("closure_max_m") is not None), key=lambda r: -r["tolerance"])
        gpu = all(r.get("throughput_world_steps_per_s") for r in rs)
        run_rate[scene] = run_rate.get(scene, False) or not gpu
        pts = []
        for r in rs:
            y = r["throughput_world_steps_per_s"] if gpu else r.get("run_world_steps_per_s")
            if y:
                conv_txt = f"\n{100 * r['converged_fraction']:.1f}% conv." if r.get("converged_fraction") is not None \
                    else ""
                pts.append((max(r["closure_max_m"], 1e-12), y, f"tol {r['tolerance']:g}{conv_txt}", -r["tolerance"]))
        if pts:
            panels.setdefault(scene, {})[name] = pts
    if not panels:
        raise ValueError("speed_against_error: no record has both a throughput and a loop closure")
    scenes = sorted(panels)
    fig, axes = _axes(ax, len(scenes))
    for a, scene in zip(axes, scenes, strict=True):
        series = {name: [p[:3] for p in sorted(pts, key=lambda p: p[3])] for name, pts in panels[scene].items()}
        xs, ys = _labelled_series(a, series, linestyle="-")
        a.set(xscale="log", yscale="log", title=scene, xlabel="max loop closure [m]",
              ylabel="world-steps/s" + (" (run incl. host probes)" if run_rate.get(scene) else ""))
        _finish_log_panel(a, xs, ys)
    if ax is None:
        fig.tight_layout()
    return fig


#: the throughput benchmark's time step [s] (``kamino.bench.throughput.DT``), for records without ``sim_seconds_per_s``
_BENCH_DT = 0.0025


def solver_setting(r: Mapping[str, Any]) -> tuple[str, str]:
    """``(solver, setting)`` of a throughput record: kamino's default configuration with its solver settings
    (``tolerance=0.01``; none: ``defaults``), MuJoCo Warp with its sweep's settings (none: ``file's settings``), or a
    SolverKamino variant with its sweep's settings (``SolverKamino padmm_dense``, ``tolerance=1e-06``; none: the
    record's ``settings``). :func:`speed_at_accuracy` draws one series per solver, and
    ``kamino.bench.throughput.pareto`` reads each solver's best setting."""
    if r.get("peer") == "mujoco_warp":
        settings = " ".join(str(r.get("variant") or "").split()[1:])
        return "MuJoCo Warp", settings or "file's settings"
    if r.get("peer"):
        variant, *settings = str(r.get("variant") or "").split() or [""]
        return f"SolverKamino {variant}", " ".join(settings) or str(r.get("settings") or "")
    solver = r.get("solver") or {}
    return "kamino", " ".join(f"{k}={v}" for k, v in sorted(solver.items())) or "defaults"


def accuracy_points(results: Mapping[str, Any] | Sequence[Mapping[str, Any]]
                    ) -> dict[tuple[str, str, int], dict[str, list[tuple[float, float, str, Mapping[str, Any]]]]]:
    """``(scene, load, worlds) -> solver -> [(closure, simulated world-seconds per second, setting, record)]`` of
    the ``kamino.bench.throughput`` records with a throughput and a closure (kamino's ``default`` configuration and
    the peers; other kamino configurations and failed runs are left out), by :func:`solver_setting`. The speed is
    ``sim_seconds_per_s`` (world-steps/s x dt), else world-steps/s x the record's ``dt`` or the benchmark's 2.5 ms;
    the closure :func:`record_closure`'s, and a record without one (a peer's closure comes from one run of one world,
    made with its first world count) takes that of the same scene, load, solver and setting at another world count.
    Points keep the records' order."""
    recs = [r for r in _records(results) if not _is_convergence(r) and r.get("throughput")
            and ("peer" in r or r.get("config") == "default")]
    known: dict[tuple, float] = {}
    for r in recs:
        if record_closure(r) is not None:
            known.setdefault((r.get("scene"), r.get("load", "gentle"), *solver_setting(r)), record_closure(r))
    points: dict[tuple[str, str, int], dict[str, list]] = {}
    for r in recs:
        solver, setting = solver_setting(r)
        closure = record_closure(r)
        if closure is None:
            closure = known.get((r.get("scene"), r.get("load", "gentle"), solver, setting))
        if closure is None or not math.isfinite(closure):
            continue
        speed = r.get("sim_seconds_per_s") or r["throughput"] * (r.get("dt") or _BENCH_DT)
        key = (r["scene"], r.get("load", "gentle"), int(r["num_worlds"]))
        points.setdefault(key, {}).setdefault(solver, []).append((float(closure), float(speed), setting, r))
    return points


def speed_at_accuracy(results: Mapping[str, Any] | Sequence[Mapping[str, Any]], *,
                      ax: Axes | Sequence[Axes] | None = None) -> Figure:
    """Simulated world-seconds per second (y, log: world-steps/s x dt, comparable across time steps) against the loop
    closure (x, log), one panel per scene, load and world count (four a row), one series per solver and one point
    per solver setting, labelled with it (:func:`accuracy_points`, :func:`solver_setting`): kamino's ``default``
    configuration at each ``--kamino-sweep``, ``--tolerance`` or ``--solver`` setting, MuJoCo Warp at each
    ``--mjw-sweep`` setting, each SolverKamino variant at each ``--sk-sweep`` setting. Where one solver's curve lies
    above another's at the same closure, it is the faster at that accuracy.

    Returns:
        The figure; each series is one line of markers (no segments: settings are not ordered), its points from the
        loosest closure to the tightest.
    """
    panels = accuracy_points(results)
    if not panels:
        raise ValueError("speed_at_accuracy: no record has both a throughput and a loop closure")
    keys = sorted(panels)
    fig, axes = _axes(ax, len(keys), ncols=4)
    for a, key in zip(axes, keys, strict=True):
        series = {solver: [(max(p[0], 1e-12), p[1], p[2]) for p in sorted(pts, key=lambda p: -p[0])]
                  for solver, pts in panels[key].items()}
        xs, ys = _labelled_series(a, series, linestyle="none")
        a.set(xscale="log", yscale="log", title=f"{key[0]}, {key[1]} load, {key[2]} worlds",
              xlabel="max loop closure [m]", ylabel="simulated world-seconds per second")
        _finish_log_panel(a, xs, ys)
    if ax is None:
        fig.tight_layout()
    return fig


def throughput_against_worlds(results: Mapping[str, Any] | Sequence[Mapping[str, Any]], *,
                              ax: Axes | Sequence[Axes] | None = None) -> Figure:
    """Throughput (world-steps/s, log) against world count (log), one panel per scene (sorted), one series per
    kamino configuration and per peer, from ``kamino.bench.throughput`` records (those with a ``throughput``)."""
    panels: dict[str, dict[str, list[tuple[int, float]]]] = {}
    for r in _records(results):
        if r.get("throughput") and not _is_convergence(r):
            panels.setdefault(r["scene"], {}).setdefault(_series(r), []).append((r["num_worlds"], r["throughput"]))
    if not panels:
        raise ValueError("throughput_against_worlds: no record has a throughput")
    scenes = sorted(panels)
    fig, axes = _axes(ax, len(scenes), panel=(5.0, 4.0))
    for a, scene in zip(axes, scenes, strict=True):
        for name, pts in sorted(panels[scene].items()):
            a.plot(*zip(*sorted(pts), strict=True), marker="o", label=name)
        a.set(xscale="log", yscale="log", xlabel="worlds", ylabel="steps/s x worlds", title=scene)
        a.grid(True, which="both", alpha=0.3)
        a.legend(fontsize=7)
    if ax is None:
        fig.tight_layout()
    return fig


def iterations_histogram(results: Mapping[str, Any] | Sequence[Mapping[str, Any]], *,
                         ax: Axes | Sequence[Axes] | None = None) -> Figure:
    """The PADMM iterations-per-step histogram (log counts of (world, step) pairs) of each
    ``kamino.bench.convergence`` record that has one (its ``iterations_histogram``: ``[[iterations, count]...]``),
    one panel per run in record order (a default run that the tolerance sweep repeats is drawn once), up to four
    a row."""
    recs = [r for r in _distinct_runs(_records(results)) if r.get("iterations_histogram")]
    if not recs:
        raise ValueError("iterations_histogram: no record has an iterations_histogram")
    fig, axes = _axes(ax, len(recs), ncols=4, panel=(4.0, 3.0))
    for a, r in zip(axes, recs, strict=True):
        k, c = np.asarray(r["iterations_histogram"]).T
        a.bar(k, c, width=1.0)
        conv = r.get("converged_fraction")
        detail = ", ".join(s for s in (f"tol {r['tolerance']:g}" if r.get("tolerance") is not None else "",
                                       f"{100 * conv:.1f}% conv." if conv is not None and math.isfinite(conv) else "")
                           if s)
        a.set(yscale="log", xlabel="PADMM iterations per step", ylabel="(world, step) pairs",
              title=f"{r['scene']} ({detail})" if detail else r["scene"])
        a.title.set_fontsize(8)
    if ax is None:
        fig.tight_layout()
    return fig
