"""Learning curves: a run's greedy policy, evaluated exactly, as a fraction of the optimum against
env steps (several learners: their median and bands)."""

from __future__ import annotations

import statistics
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt

from irdrc.agents.base import RunRecord
from irdrc.core.checks import counted
from irdrc.runs.results import atomic_savefig


def plot_learning_curve(
    record: RunRecord, path: Path, *, title: str, unit: str = "env steps"
) -> None:
    """The learning curve (``learning_curve.<format>``): the greedy policy, evaluated exactly, as a
    fraction of the optimum's average reward against env steps. With several learners: their
    median, a band over the middle half (quartiles) and one over all of them (min–max)."""
    fig, ax = plt.subplots(figsize=(6.4, 4.0))
    curves = [[r for r in record.history if r["learner"] == n] for n in range(record.num_learners)]
    xs = [r["env_steps"] for r in curves[0]] if curves and curves[0] else []
    if len(curves) > 1 and xs:
        cols = [sorted(c[i]["optimality_ratio"] for c in curves) for i in range(len(xs))]
        q = [statistics.quantiles(col, n=4, method="inclusive") for col in cols]
        ax.fill_between(
            xs,
            [c[0] for c in cols],
            [c[-1] for c in cols],
            color="tab:blue",
            alpha=0.15,
            linewidth=0,
            label=f"min–max of {counted(len(curves), 'learner')}",
        )
        ax.fill_between(
            xs,
            [v[0] for v in q],
            [v[2] for v in q],
            color="tab:blue",
            alpha=0.3,
            linewidth=0,
            label="interquartile range",
        )
        ax.plot(
            xs,
            [statistics.median(col) for col in cols],
            color="tab:blue",
            linewidth=2,
            label="median",
        )
    elif xs:
        ax.plot(
            xs,
            [r["optimality_ratio"] for r in curves[0]],
            color="tab:blue",
            linewidth=1.8,
            marker=".",
            label="greedy policy",
        )
    ax.axhline(1.0, color="black", linestyle="--", linewidth=1, label="exact optimum")
    ax.axhline(0.99, color="black", linestyle=":", linewidth=1, label="99 % of the optimum")
    ax.set_xlabel(f"{unit} per learner", fontsize=11)
    ax.set_ylabel("average reward / optimum's (exact)", fontsize=11)
    ax.tick_params(labelsize=10)
    ax.set_title(title, fontsize=11)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=9, loc="lower right")
    fig.tight_layout()
    atomic_savefig(fig, path, dpi=200)
