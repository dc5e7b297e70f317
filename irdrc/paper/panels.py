"""Figure 2's panels from its training runs' files: the exact references, the learning curves of
panel (a) and the p^v_1 sweep of panels (b)–(d), each written as a CSV and a PNG
(``irdrc.paper.figure2`` runs them)."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from irdrc.core.exact import Scorer, build_model, episodic_metrics, stationary_metrics
from irdrc.core.metrics import Metrics, first_reaching
from irdrc.core.params import Params
from irdrc.paper import plots
from irdrc.paper.figures import (
    band_rows,
    moving_average,
    round_robin_episodes,
    same_value,
    to_float,
)
from irdrc.recipes.constrained.frontier import ref_params
from irdrc.runs.results import read_csv_rows as read_csv
from irdrc.runs.results import write_rows_csv


@dataclass
class Reference:
    """Exact values of the optimum and of round-robin in one scenario."""

    optimal: Metrics
    optimal_episodic: Metrics
    round_robin: Metrics


def exact_reference(params: Params, gamma: float) -> Reference:
    """Optimal (value iteration at discount ``gamma``) and round-robin metrics, exactly."""
    model = build_model(params)
    scorer = Scorer(model, gamma)
    return Reference(
        optimal=scorer.optimal_metrics,
        optimal_episodic=episodic_metrics(model, scorer.optimal.policy),
        round_robin=stationary_metrics(model, "round_robin"),
    )


def _runs_of(
    planned: list[dict[str, Any]], trials: Path, learner: str
) -> list[tuple[dict[str, Any], Path]]:
    return [(p, trials / p["point_id"]) for p in planned if p["learner"] == learner]


def _learners_at(
    runs: list[tuple[dict[str, Any], Path]], p: float
) -> list[tuple[Path, dict[str, str]]]:
    """Every learner (run directory, its ``learners.csv`` row) whose scenario has p^v_1 = ``p``: the
    row's own ``env.p1.speed`` (batched scenarios) or else its run's."""
    out = []
    for planned, tdir in runs:
        run_p = planned["config"].params.env.p1.speed
        for row in read_csv(tdir / "learners.csv"):
            if same_value(row.get("env.p1.speed", run_p), p):
                out.append((tdir, row))
    return out


def _curves(
    runs: list[tuple[dict[str, Any], Path]], p: float, horizon: int, window: int
) -> tuple[list[float], list[list[float]], list[float], list[list[float]]]:
    """(episodes evaluated, greedy curves per learner, training episodes, smoothed training curves)
    of every learner at p^v_1 = ``p``; x in episodes of ``horizon`` steps."""
    greedy, training = [], []
    xs: list[float] = []
    txs: list[float] = []
    files: dict[Path, tuple[list[dict[str, Any]], list[dict[str, Any]]]] = {}
    for tdir, row in _learners_at(runs, p):
        if tdir not in files:
            files[tdir] = (read_csv(tdir / "metrics.csv"), read_csv(tdir / "episode_rewards.csv"))
        hist = [r for r in files[tdir][0] if r["learner"] == row["learner"]]
        eps = [r for r in files[tdir][1] if r["learner"] == row["learner"]]
        xs = [int(r["env_steps"]) / horizon for r in hist]
        greedy.append([float(r["avg_reward"]) * horizon for r in hist])
        txs = [float(r["episode"]) for r in eps]
        training.append(moving_average([float(r["reward"]) for r in eps], window))
    return xs, greedy, txs, training


def _finals(runs: list[tuple[dict[str, Any], Path]], p: float) -> list[dict[str, float]]:
    """Final greedy policies' exact metrics, one dict per learner, at p^v_1 = p."""
    return [
        {k: to_float(row.get(k)) for k in Metrics.__dataclass_fields__}
        for _, row in _learners_at(runs, p)
    ]


def _exact_rows(
    series: str | Sequence[str], xs: Sequence[float], values: Sequence[float]
) -> list[dict[str, Any]]:
    """Band rows of exact values (no replicates: ``lo`` = ``hi`` = ``mean``, ``n`` = 0)."""
    names = [series] * len(xs) if isinstance(series, str) else list(series)
    return [
        {"series": name, "x": x, "mean": v, "lo": v, "hi": v, "n": 0}
        for name, x, v in zip(names, xs, values, strict=True)
    ]


@dataclass
class Figure:
    """What every panel of one figure run needs."""

    cfg: Any  # the figure's Config (irdrc.paper.figure2)
    out: Path
    planned: list[dict[str, Any]]
    seeds: list[int]
    ps: list[float]
    curve_p: float
    base: Params
    refs: dict[float, Reference]

    @property
    def horizon(self) -> int:
        """Steps per episode of the figure's scenario."""
        return self.base.env.horizon

    @property
    def methods(self) -> list[str]:
        """The learners the figure shows, in order."""
        return list(self.cfg.methods)

    def runs(self, learner: str) -> list[tuple[dict[str, Any], Path]]:
        """Each finished run of ``learner``: its planned point and its trial directory."""
        return _runs_of(self.planned, self.out / "trials", learner)


def panel_a(fig: Figure) -> tuple[float, float, dict[str, float], dict[str, float | None]]:
    """Panel (a): learning curves. Returns (optimum and round-robin per episode, each learner's
    final mean, each learner's first episode at 95 % of the optimum)."""
    horizon, window = fig.horizon, int(fig.cfg.smooth_episodes)
    ref_a = fig.refs[fig.curve_p]
    opt_ep = ref_a.optimal.avg_reward * horizon
    rr_ep = ref_a.round_robin.avg_reward * horizon
    greedy_rows, training_rows, finals, to95 = [], [], {}, {}
    max_episode = 0.0
    for name in fig.methods:
        if "a" not in fig.cfg.learners[name].panels:
            continue
        xs, greedy, txs, training = _curves(fig.runs(name), fig.curve_p, horizon, window)
        rows = band_rows(name, xs, greedy)
        greedy_rows += rows
        training_rows += band_rows(name, txs, training)
        to95[name] = first_reaching(rows, 0.95 * opt_ep, value="mean", at="x")
        finals[name] = rows[-1]["mean"]
        max_episode = max(max_episode, xs[-1] if xs else 0.0, txs[-1] if txs else 0.0)
    n_rr = max(int(max_episode), window)
    rr_sim = [
        moving_average(c, window)
        for c in round_robin_episodes(ref_params(fig.base, fig.curve_p), fig.seeds, n_rr)
    ]
    training_rows += band_rows("round_robin", list(range(1, n_rr + 1)), rr_sim)
    panel_a = [{"view": "greedy_exact", **r} for r in greedy_rows]
    panel_a += [{"view": "training_smoothed", **r} for r in training_rows]
    panel_a += [
        {"view": "reference", **row}
        for row in _exact_rows(
            ["optimal", "optimal_episodic", "round_robin"],
            [math.nan] * 3,
            [opt_ep, ref_a.optimal_episodic.episode_reward, rr_ep],
        )
    ]
    write_rows_csv(fig.out / "panel_a.csv", panel_a)
    plots.plot_panel_a(
        greedy_rows,
        training_rows,
        opt_ep,
        ref_a.optimal_episodic.episode_reward,
        rr_ep,
        dict(to95),
        fig.out / "panel_a.png",
        p1_speed=fig.curve_p,
        seeds=len(fig.seeds),
        window=window,
        horizon=horizon,
    )
    return opt_ep, rr_ep, finals, to95


PANEL_METRICS = ("avg_reward", "throughput", "link_capacity", "miss_detection")


def value_bounds(env: Any) -> dict[str, tuple[float, float] | None]:
    """The ranges the final policies' exact long-run values lie in, per panel metric (bands are
    clipped to them): throughput up to the arrival rate (with bursty arrivals, its largest
    phase's), link capacity up to the larger packets per comm step."""
    rate = env.arrival_rate if env.arrival_rate is not None else max(env.bursty.rates)
    return {
        "avg_reward": None,
        "throughput": (0.0, float(rate)),
        "link_capacity": (0.0, float(max(env.packets_good, env.packets_bad))),
        "miss_detection": (0.0, 1.0),
    }


def panels_bcd(fig: Figure) -> dict[str, dict[str, list[float]]]:
    """Panels (b)–(d): final policies against p^v_1. Returns subject → metric → mean per p^v_1."""
    ps, bounds = fig.ps, value_bounds(fig.base.env)
    metric_rows: dict[str, list[dict[str, Any]]] = {m: [] for m in PANEL_METRICS}
    sweep_means: dict[str, dict[str, list[float]]] = {}
    for name in [m for m in fig.methods if "bcd" in fig.cfg.learners[m].panels]:
        per_p = [_finals(fig.runs(name), p) for p in ps]
        sweep_means[name] = {}
        for metric, rows in metric_rows.items():
            band = band_rows(
                name,
                ps,
                [[f[metric] for f in fin] for fin in zip(*per_p, strict=True)],
                bounds[metric],
            )
            rows += band
            sweep_means[name][metric] = [r["mean"] for r in band]
    for series in ("optimal", "round_robin"):
        sweep_means[series] = {}
        for metric, rows in metric_rows.items():
            values = [getattr(getattr(fig.refs[p], series), metric) for p in ps]
            rows += _exact_rows(series, ps, values)
            sweep_means[series][metric] = values
    out, n = fig.out, len(fig.seeds)
    write_rows_csv(out / "panel_b.csv", metric_rows["avg_reward"])
    write_rows_csv(
        out / "panel_c.csv",
        [{"metric": m, **r} for m in ("throughput", "link_capacity") for r in metric_rows[m]],
    )
    write_rows_csv(out / "panel_d.csv", metric_rows["miss_detection"])
    plots.plot_p_sweep(
        [("(b) average reward", "average reward per step", metric_rows["avg_reward"])],
        out / "panel_b.png",
        seeds=n,
        title="Fig. 2(b)",
    )
    plots.plot_p_sweep(
        [
            (
                "(c) throughput: packets sent (paper's definition, ≤ λ = 1)",
                "packets per step",
                metric_rows["throughput"],
            ),
            (
                "(c′) link capacity used (what the reference code plotted)",
                "packets per step",
                metric_rows["link_capacity"],
            ),
        ],
        out / "panel_c.png",
        seeds=n,
        title="Fig. 2(c)",
    )
    plots.plot_p_sweep(
        [
            (
                "(d) miss detection probability",
                "missed events / events",
                metric_rows["miss_detection"],
            )
        ],
        out / "panel_d.png",
        seeds=n,
        title="Fig. 2(d)",
    )
    return sweep_means
