"""The figures, drawn from the rows the recipes also write as CSV (``irdrc.paper.figures.band_rows`` format:
``series, x, mean, lo, hi, n``). Matplotlib with the Agg backend: no display needed."""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
from matplotlib.lines import Line2D

from irdrc.runs.results import atomic_savefig

STYLE = {
    "dqn": {"color": "tab:blue", "label": "DQN (ours)"},
    "dqn_paper": {"color": "tab:cyan", "label": "DQN (paper profile)"},
    "qlearning": {"color": "tab:orange", "label": "Q-learning (ours)"},
    "qlearning_paper": {"color": "tab:brown", "label": "Q-learning (paper profile)"},
    "round_robin": {"color": "tab:gray", "label": "round-robin"},
    "optimal": {"color": "black", "label": "exact optimum", "linestyle": "--"},
}
DPI = 80


def _style(series: str) -> dict[str, Any]:
    return STYLE.get(series, {"label": series})


def _series(rows: Sequence[Mapping[str, Any]]) -> dict[str, list[Mapping[str, Any]]]:
    out: dict[str, list[Mapping[str, Any]]] = {}
    for r in rows:
        out.setdefault(str(r["series"]), []).append(r)
    return out


def _draw_bands(ax: Any, rows: Sequence[Mapping[str, Any]], marker: str | None = None) -> None:
    for name, rs in _series(rows).items():
        st = _style(name)
        xs = [float(r["x"]) for r in rs]
        ax.plot(
            xs,
            [float(r["mean"]) for r in rs],
            color=st.get("color"),
            linestyle=st.get("linestyle", "-"),
            marker=marker,
            markersize=4,
            label=st["label"],
        )
        lo = [float(r["lo"]) for r in rs]
        hi = [float(r["hi"]) for r in rs]
        if any(not math.isclose(a, b) for a, b in zip(lo, hi, strict=True)):
            ax.fill_between(xs, lo, hi, color=st.get("color"), alpha=0.2, linewidth=0)


def _hline(ax: Any, y: float, series: str, label: str | None = None) -> None:
    st = _style(series)
    ax.axhline(
        y,
        color=st.get("color"),
        linestyle=st.get("linestyle", ":"),
        linewidth=1.2,
        label=label or st["label"],
    )


def plot_panel_a(
    greedy: Sequence[Mapping[str, Any]],
    training: Sequence[Mapping[str, Any]],
    optimum: float,
    optimum_training: float,
    round_robin: float,
    marks: Mapping[str, float | None],
    path: Path,
    *,
    p1_speed: float,
    seeds: int,
    window: int,
    horizon: int = 400,
) -> None:
    """Panel (a): total reward per episode vs training episode, two views side by side.

    Left: the greedy policy after each training episode, evaluated exactly (horizon × its long-run
    reward per step), with markers where the mean first reaches 95 % of the optimum. Right: the
    training episodes themselves (behaviour policy, exploration included — what the paper plots),
    smoothed, with simulated round-robin episodes.
    """
    fig, axes = plt.subplots(1, 2, figsize=(12, 4.6), sharey=False)
    ax = axes[0]
    _draw_bands(ax, greedy)
    _hline(ax, optimum, "optimal")
    _hline(ax, round_robin, "round_robin", "round-robin (exact)")
    ax.axhline(0.95 * optimum, color="black", linewidth=0.6, alpha=0.4)
    for name, x in marks.items():
        if x is not None:
            ax.plot([x], [0.95 * optimum], marker="v", color=_style(name).get("color"), ms=9)
    ax.set_title(f"(a) greedy policy, exact — p$^v_1$ = {p1_speed:g}, {seeds} seeds, 95 % band")
    ax.set_xlabel(f"training episode ({horizon} steps)")
    ax.set_ylabel("total reward per episode")
    ax.legend(fontsize=8, loc="lower right")
    ax.grid(alpha=0.3)

    ax = axes[1]
    _draw_bands(ax, training)
    _hline(ax, optimum_training, "optimal", "exact optimum (episode from uniform reset)")
    ax.set_title(f"(a′) training episodes as the paper plots them (mean of {window})")
    ax.set_xlabel(f"training episode ({horizon} steps)")
    ax.set_ylabel("total reward per episode")
    ax.legend(fontsize=8, loc="lower right")
    ax.grid(alpha=0.3)
    ymin = min(round_robin, min((float(r["lo"]) for r in training), default=round_robin))
    for a in axes:
        a.set_ylim(bottom=max(a.get_ylim()[0], ymin - 0.1 * abs(optimum)))
        # Runs differ in length by 50× (DQN vs Q-learning's paper profile): log-scaled episodes,
        # linear below 10 so that episode 0 (the untrained policy) stays on the axis.
        a.set_xscale("symlog", linthresh=10)
        a.set_xlim(left=0)
    fig.tight_layout()
    atomic_savefig(fig, path, dpi=DPI)


def plot_p_sweep(
    panels: Sequence[tuple[str, str, Sequence[Mapping[str, Any]]]],
    path: Path,
    *,
    seeds: int,
    title: str,
) -> None:
    """One panel per (title, y label, rows) against p^v_1 (rows' ``x``), side by side."""
    fig, axes = plt.subplots(
        1, len(panels), figsize=(max(8.0, 6 * len(panels)), 4.6), squeeze=False
    )
    for ax, (sub, ylabel, rows) in zip(axes[0], panels, strict=True):
        _draw_bands(ax, rows, marker="o")
        ax.set_title(sub)
        ax.set_xlabel("p$^v_1$: event probability at high speed")
        ax.set_ylabel(ylabel)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    fig.suptitle(
        f"{title} — learned: final greedy policies, exact\nmean and 95 % band over {seeds} "
        "seeds (clipped to the metric's range)",
        fontsize=10,
    )
    fig.tight_layout()
    atomic_savefig(fig, path, dpi=DPI)


def plot_tradeoff(
    rows: Sequence[Mapping[str, Any]],
    learned: Sequence[Mapping[str, Any]],
    path: Path,
    *,
    target: float | None,
    scan: Sequence[Mapping[str, Any]] = (),
) -> None:
    """The optimal policy's miss detection against r4, throughput and link capacity.

    ``rows``: ``series`` (one curve per scenario), ``r4``, ``miss_detection``, ``throughput``,
    ``link_capacity``; ``learned``: the same keys plus ``lo``/``hi`` bounds of miss detection;
    ``scan``: extra (denser) exact points drawn in the r4 panel.
    """
    fig, axes = plt.subplots(1, 3, figsize=(18, 5.6))
    colors = {}
    ax = axes[0]
    for name, rs in _series(rows).items():
        pts = sorted([*rs, *[r for r in scan if r["series"] == name]], key=lambda r: float(r["r4"]))
        (line,) = ax.plot(
            [float(r["r4"]) for r in pts],
            [float(r["miss_detection"]) for r in pts],
            marker=".",
            label=f"optimum, {name}",
        )
        colors[name] = line.get_color()
    for r in learned:
        _learned_point(ax, r, "r4")
    ax.set_xscale("log")
    ax.set_xlabel("r4: detection reward (× (b + 1))")
    for ax, metric, xlabel in (
        (axes[1], "throughput", "throughput (packets sent per step)"),
        (axes[2], "link_capacity", "link capacity used (packets per step)"),
    ):
        for name, rs in _series(rows).items():
            xs = [float(r[metric]) for r in rs]
            ys = [float(r["miss_detection"]) for r in rs]
            ax.plot(xs, ys, marker="o", color=colors[name], label=f"optimum, {name}")
            # one label per distinct point: several r4 values often share the same policy
            labels: dict[tuple[float, float], list[str]] = {}
            for r, x, y in zip(rs, xs, ys, strict=True):
                labels.setdefault((round(x, 4), round(y, 4)), []).append(f"{float(r['r4']):g}")
            for (x, y), names in labels.items():
                ax.annotate(
                    "r4=" + ", ".join(names),
                    (x, y),
                    fontsize=8,
                    xytext=(-6, 6),
                    textcoords="offset points",
                    ha="right",
                    color=colors[name],
                    bbox={"boxstyle": "round,pad=0.15", "fc": "white", "ec": "none", "alpha": 0.8},
                )
        for r in learned:
            _learned_point(ax, r, metric)
        ax.set_xlabel(xlabel)
    for ax in axes:
        if target is not None:
            ax.axhline(target, color="tab:red", linestyle=":", label=f"target miss = {target:g}")
        ax.set_ylabel("miss detection probability")
        ax.grid(alpha=0.3)
        handles, texts = ax.get_legend_handles_labels()
        if learned:
            handles.append(Line2D([], [], marker="s", color="tab:blue", linestyle=""))
            texts.append("DQN (ours), final greedy, 95 % band")
        ax.legend(handles, texts, fontsize=8)
    fig.suptitle("Radar vs communication: the exact optimum as the detection reward r4 varies")
    fig.tight_layout()
    atomic_savefig(fig, path, dpi=DPI)


def _learned_point(ax: Any, r: Mapping[str, Any], xkey: str) -> None:
    y = float(r["miss_detection"])
    ax.errorbar(
        [float(r[xkey])],
        [y],
        yerr=[[y - float(r["lo"])], [float(r["hi"]) - y]],
        fmt="s",
        color="tab:blue",
        capsize=3,
    )
    ax.annotate(
        f"DQN r4={float(r['r4']):g}",
        (float(r[xkey]), y),
        fontsize=8,
        xytext=(-6, -14),
        textcoords="offset points",
        ha="right",
        color="tab:blue",
        bbox={"boxstyle": "round,pad=0.15", "fc": "white", "ec": "none", "alpha": 0.8},
    )
