"""Figures of learning on one stream, against episodes: the greedy policy's exact share of the
optimum, the cumulative regret, and the cumulative missed events beside the optimum's floor — for one
run (``learning_curve.<format>``; a safe learner's against its own goal: its plan's packets over the
LP's, and its cumulative miss detection under the target) and for several learners over seeds (the
benchmark's figure, the paper's Fig. 2(a) on one vehicle)."""

from __future__ import annotations

import statistics
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt

from irdrc.agents.base import RunRecord
from irdrc.runs.results import atomic_savefig

COLORS = {
    "posterior": "tab:green",
    "posterior_anytime": "tab:olive",
    "dqn": "tab:blue",
    "dqn_paper": "tab:cyan",
    "qlearning": "tab:orange",
    "qlearning_paper": "tab:red",
    "safe": "tab:purple",
    "safe_anytime": "tab:pink",
}


def _axes(
    title: str,
    first: str = "greedy policy / optimum (exact)",
    lines: tuple[float, float] = (1.0, 0.99),
) -> tuple[Any, Any]:
    """Three panels against episodes; the first labelled ``first``, with lines at ``lines``."""
    fig, axes = plt.subplots(1, 3, figsize=(13.5, 3.8))
    axes[0].set_ylabel(first)
    axes[1].set_ylabel("cumulative regret (reward)")
    axes[2].set_ylabel("cumulative missed events")
    for ax in axes:
        ax.set_xlabel("episodes")
        ax.grid(alpha=0.3)
    axes[0].axhline(lines[0], color="black", linestyle="--", linewidth=1)
    axes[0].axhline(lines[1], color="black", linestyle=":", linewidth=1)
    fig.suptitle(title, fontsize=11)
    return fig, axes


def plot_run(
    record: RunRecord,
    path: Path,
    title: str,
    target_miss: float | None = None,
    lp_threshold: float = 0.95,
    lp_regret_per_step: float | None = None,
) -> None:
    """One run: the greedy and behaviour policies' ratios, the exact and realised regret, the
    expected and realised missed events and the optimum's floor, against episodes.

    With ``target_miss`` (a safe learner), the first panel is its greedy plan's packets over the
    LP's at that target (lines at 1 and ``lp_threshold``, the share its run is held to) and the
    last its cumulative miss detection on the stream, with the target it stays under;
    ``lp_regret_per_step`` (the optimum's reward per step less the LP's) draws what the target
    itself costs in the regret panel, the part of the regret no learner under it avoids."""
    h = record.history
    x = [r["episodes"] for r in h]
    if target_miss is None:
        fig, axes = _axes(title)
        axes[0].plot(x, [r["optimality_ratio"] for r in h], marker=".", label="greedy")
        axes[0].plot(x[1:], [r["behaviour_ratio"] for r in h[1:]], alpha=0.6, label="behaviour")
        axes[0].set_ylim(bottom=max(-0.5, min([r["optimality_ratio"] for r in h] + [0.0])))
    else:
        first = f"greedy plan's packets / the LP's at {target_miss:g}"
        fig, axes = _axes(title, first, (1.0, lp_threshold))
        axes[0].plot(x, [r["lp_ratio"] for r in h], marker=".", label="greedy plan")
        axes[0].set_ylim(bottom=min([r["lp_ratio"] for r in h] + [0.0]))
    axes[1].plot(x, [r["regret"] for r in h], label="exact (behaviour policies)")
    axes[1].plot(x, [r["realised_regret"] for r in h], alpha=0.6, label="realised")
    if lp_regret_per_step is not None:
        lp_line = [lp_regret_per_step * r["env_steps"] for r in h]
        axes[1].plot(x, lp_line, "k--", linewidth=1, label="the LP's (the target's own cost)")
    if target_miss is None:
        axes[2].plot(x, [r["expected_missed"] for r in h], label="expected")
        axes[2].plot(x, [r["realised_missed"] for r in h], alpha=0.6, label="realised")
        axes[2].plot(x, [r["floor_missed"] for r in h], "k--", linewidth=1, label="optimum (floor)")
    else:
        axes[2].set_ylabel("cumulative miss detection (stream)")
        miss = [r["cumulative_miss_detection"] for r in h]
        axes[2].plot(x, miss, color="tab:purple", label="missed / events so far")
        axes[2].axhline(target_miss, color="black", linestyle="--", linewidth=1, label="target")
        axes[2].set_ylim(0.0, 2 * target_miss)
    for ax in axes:
        ax.legend(fontsize=8)
    fig.tight_layout()
    atomic_savefig(fig, path, dpi=150)


def _band(ax: Any, x: Sequence[int], runs: list[list[float]], color: str, label: str) -> None:
    cols = list(zip(*runs, strict=False))
    ax.plot(x[: len(cols)], [statistics.median(c) for c in cols], color=color, label=label)
    if len(runs) > 1:
        ax.fill_between(
            x[: len(cols)], [min(c) for c in cols], [max(c) for c in cols], color=color, alpha=0.15
        )


def plot_learners(
    histories: Mapping[str, list[list[dict[str, Any]]]], path: Path, title: str
) -> None:
    """Several learners, each over several runs (``histories[learner]``: one ``metrics.csv``'s
    rows per run, evaluated every episode): the median and the min–max band of each panel."""
    fig, axes = _axes(title)
    floor = None
    for i, (name, runs) in enumerate(histories.items()):
        if not runs:
            continue
        color = COLORS.get(name, f"C{i}")
        x = [r["episodes"] for r in runs[0]]
        n = len(runs)
        _band(axes[0], x, [[r["optimality_ratio"] for r in h] for h in runs], color, name)
        _band(axes[1], x, [[r["regret"] for r in h] for h in runs], color, name)
        _band(axes[2], x, [[r["expected_missed"] for r in h] for h in runs], color, name)
        if floor is None:
            floor = (
                x,
                [
                    statistics.median(c)
                    for c in zip(*[[r["floor_missed"] for r in h] for h in runs], strict=False)
                ],
            )
        axes[0].set_title(f"median and range of {n} runs each", fontsize=9)
    if floor is not None:
        axes[2].plot(
            floor[0][: len(floor[1])], floor[1], "k--", linewidth=1, label="optimum (floor)"
        )
    axes[0].set_ylim(0.0, 1.02)
    for ax in axes:
        ax.legend(fontsize=8)
    fig.tight_layout()
    atomic_savefig(fig, path, dpi=150)
