"""Plot the walking tests and training returns of one or more ``rl_train.py`` runs side by side (issue 18):
``python benchmarks/plot_walk_tests.py RUN [RUN ...] --out walk_tests.png``.

Each ``RUN`` is a folder written by ``rl_train.py --walk-test`` (``walk_tests.json``, ``train_curve.json``); its
name labels it. Four panels against environment steps: the walking test's mean tracking error and fall fraction,
with issue 18's bars (0.1 m/s, 5 %) drawn, the training episodes' mean return per policy step (the return divided
by the episode length, comparable across runs whose episodes differ in length), and the learning rate PPO used in
each training window (brax's ``learning_rate`` metric, log scale: with ``ADAPTIVE_KL`` it is what the KL rule left
of the configured rate; docs/envs.md, "The eleventh run").
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

#: issue 18's walking bars: mean tracking error [m/s] and fraction of fallen episodes
ERROR_BAR, FALL_BAR = 0.1, 0.05


def load(run: Path) -> tuple[list[dict], list[dict]]:
    """``(walk tests, training windows)`` of ``run``; a missing file reads as no entries."""
    def read(name: str) -> list[dict]:
        path = run / name
        return json.loads(path.read_text()) if path.exists() else []

    return read("walk_tests.json"), read("train_curve.json")


def figure(runs: list[Path]):
    """The four panels of ``runs`` (a matplotlib Figure; the caller closes it)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 4, figsize=(18, 4))
    for run in runs:
        walks, train = load(run)
        if not walks and not train:
            raise SystemExit(f"plot_walk_tests: {run} has neither walk_tests.json nor train_curve.json")
        steps = [w["step"] / 1e6 for w in walks]
        axes[0].plot(steps, [w["tracking_error_mean"] for w in walks], marker="o", label=run.name)
        axes[1].plot(steps, [100 * w["fall_fraction"] for w in walks], marker="o", label=run.name)
        axes[2].plot([t["step"] / 1e6 for t in train], [t["reward"] / max(t["length"], 1.0) for t in train],
                     label=run.name)
        lr = [(t["step"] / 1e6, t["episode"]["learning_rate"]) for t in train
              if "learning_rate" in t.get("episode", {})]
        if lr:
            axes[3].plot(*zip(*lr, strict=True), label=run.name)
    axes[3].set_yscale("log")
    axes[0].axhline(ERROR_BAR, color="k", ls="--", lw=1, label="issue 18's bar")
    axes[1].axhline(100 * FALL_BAR, color="k", ls="--", lw=1, label="issue 18's bar")
    for ax, ylabel in zip(axes, ("walking test: mean tracking error [m/s]", "walking test: episodes fallen [%]",
                                 "training: return per policy step", "training: PPO learning rate"),
                              strict=True):
        ax.set_xlabel("environment steps [M]")
        ax.set_ylabel(ylabel)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    fig.tight_layout()
    return fig


def plot(runs: list[Path], out: Path) -> None:
    """Write :func:`figure` of ``runs`` to ``out`` (PNG)."""
    import matplotlib.pyplot as plt

    fig = figure(runs)
    fig.savefig(out, dpi=110)
    plt.close(fig)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("runs", nargs="+", type=Path, help="rl_train.py output folders")
    p.add_argument("--out", type=Path, default=Path("walk_tests.png"))
    args = p.parse_args(argv)
    plot(args.runs, args.out)
    print(args.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
