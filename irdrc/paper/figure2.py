"""The paper's Figure 2, regenerated against the exact optimum.

``run_figure2`` plans every training run (DQN: one per seed and p^v_1; Q-learning: one vectorised
batch per profile holding every seed and p^v_1), executes them with the sweep engine
(``irdrc.experiments.sweep``), adds the exact optimum and round-robin, and writes one CSV and one PNG
per panel and the claims table. Every run is read the same way, whatever its method: its
``learners.csv`` (one row per learner, with its scenario), ``metrics.csv`` and
``episode_rewards.csv`` (one schema, rows tagged by learner).
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from omegaconf import DictConfig

from irdrc.core.metrics import Metrics, first_reaching
from irdrc.core.model import build_model
from irdrc.core.params import Params, check_number, to_plain
from irdrc.core.solve import ExactScorer, episodic_metrics, stationary_metrics
from irdrc.experiments.grid import format_value, parse_grid
from irdrc.experiments.results import atomic_write_text, write_rows_csv
from irdrc.experiments.sweep import execute, plan
from irdrc.experiments.validate import check_common, check_executor
from irdrc.paper import claims as cl
from irdrc.paper import plots
from irdrc.paper.figures import (
    band_rows,
    moving_average,
    read_csv,
    round_robin_episodes,
    same_value,
    to_float,
)
from irdrc.paper.tradeoff import optimal_at, ref_params

PANELS = ("a", "bcd")
LEARNER_METHODS = ("dqn", "qlearning")


def _check_figure2(cfg: DictConfig) -> tuple[list[int], list[float], float, list[str]]:
    seeds = to_plain(cfg.seeds)
    if isinstance(seeds, int):
        seeds = list(range(seeds))
    if (
        not isinstance(seeds, list)
        or not seeds
        or not all(isinstance(s, int) and s >= 0 for s in seeds)
        or len(set(seeds)) != len(seeds)
    ):
        raise ValueError(f"seeds={seeds!r} must be a non-empty list of distinct integers >= 0")
    ps = to_plain(cfg.p1_speed)
    if not isinstance(ps, list) or not ps:
        raise ValueError(f"p1_speed={ps!r} must be a non-empty list of probabilities")
    for p in [*ps, cfg.curve_p1_speed]:
        if not isinstance(p, int | float) or not 0.0 <= float(p) <= 1.0:
            raise ValueError(f"p1_speed value {p!r} must be a probability in [0, 1]")
    ps = sorted({float(p) for p in ps})
    methods = [str(m) for m in to_plain(cfg.methods)]
    if not methods:
        raise ValueError("methods is empty: name at least one of the learners")
    for m in methods:
        if m not in cfg.learners:
            raise ValueError(f"methods: {m!r} is not in learners ({', '.join(cfg.learners)})")
        spec = cfg.learners[m]
        if spec.method not in LEARNER_METHODS:
            raise ValueError(f"learners.{m}.method={spec.method!r} must be dqn or qlearning")
        bad = [p for p in spec.panels if p not in PANELS]
        if bad or not spec.panels:
            raise ValueError(f"learners.{m}.panels={list(spec.panels)} must be a subset of a, bcd")
    if int(cfg.smooth_episodes) < 1:
        raise ValueError(f"smooth_episodes={cfg.smooth_episodes} must be >= 1")
    every = cfg.eval.every_frames
    if every is not None and (not isinstance(every, int) or every < 1):
        raise ValueError(f"eval.every_frames={every!r} must be an integer >= 1 (or null)")
    return seeds, ps, float(cfg.curve_p1_speed), methods


def plan_figure2(
    cfg: DictConfig, scenario: list[str]
) -> tuple[list[dict[str, Any]], list[int], list[float], float]:
    """Every training run of the figure, as sweep-engine plans tagged with their learner."""
    seeds, ps, curve_p, methods = _check_figure2(cfg)
    planned: list[dict[str, Any]] = []
    for name in methods:
        spec = cfg.learners[name]
        values = set()
        if "a" in spec.panels:
            values.add(curve_p)
        if "bcd" in spec.panels:
            values.update(ps)
        values = sorted(values)
        common = [
            *scenario,
            *[str(o) for o in spec.overrides],
            "eval.mc_episodes=0",
            f"optimum_gamma={float(cfg.optimum_gamma)}",
        ]
        if cfg.eval.every_frames is not None:
            common.append(f"eval.every_frames={int(cfg.eval.every_frames)}")
        if spec.method == "dqn":
            points = parse_grid({"env.p1.speed": values, "seed": seeds})
            runs = plan("dqn", points, common)
        else:
            grid = "{env.p1.speed: " + format_value(values) + "}"
            base = [*common, f"num_learners={len(seeds)}", f"batch_grid={grid}"]
            runs = plan("qlearning", [{"seed": seeds[0]}], base)
        for r in runs:
            r["learner"] = name
        planned.extend(runs)
    # Longest runs first, so that no long run starts last while the other workers idle.
    planned.sort(key=_cost, reverse=True)
    return planned, seeds, ps, curve_p


def _cost(p: dict[str, Any]) -> float:
    """Relative cost of a planned run: Q-learning batches (per-step cost grows with the batch) first,
    then DQN runs by collector batches (each carries its updates and fixed overhead)."""
    algo = p["cfg"]["algo"]
    if p["method"] == "qlearning":
        return 1e12 + algo["episodes"]
    return algo["total_frames"] / algo["frames_per_batch"] * max(1, algo["updates_per_batch"])


@dataclass
class Reference:
    """Exact values of the optimum and of round-robin in one scenario."""

    optimal: Metrics
    optimal_episodic: Metrics
    round_robin: Metrics


def exact_reference(params: Params, gamma: float) -> Reference:
    """Optimal (value iteration at discount ``gamma``) and round-robin metrics, exactly."""
    model = build_model(params)
    scorer = ExactScorer(model, gamma)
    return Reference(
        optimal=scorer.optimal_metrics,
        optimal_episodic=episodic_metrics(model, scorer.optimal.policy),
        round_robin=stationary_metrics(model, "round_robin"),
    )


def _runs_of(planned: list[dict], trials: Path, learner: str) -> list[tuple[dict, Path]]:
    return [(p, trials / p["point_id"]) for p in planned if p["learner"] == learner]


def _learners_at(runs: list[tuple[dict, Path]], p: float) -> list[tuple[Path, dict[str, str]]]:
    """Every learner (run directory, its ``learners.csv`` row) whose scenario has p^v_1 = ``p``: the
    row's own ``env.p1.speed`` (batched scenarios) or else its run's."""
    out = []
    for planned, tdir in runs:
        run_p = planned["cfg"]["env"]["p1"]["speed"]
        for row in read_csv(tdir / "learners.csv"):
            if same_value(row.get("env.p1.speed", run_p), p):
                out.append((tdir, row))
    return out


def _curves(
    runs: list[tuple[dict, Path]], p: float, horizon: int, window: int
) -> tuple[list[float], list[list[float]], list[float], list[list[float]]]:
    """(episodes evaluated, greedy curves per learner, training episodes, smoothed training curves)
    of every learner at p^v_1 = ``p``; x in episodes of ``horizon`` steps."""
    greedy, training = [], []
    xs: list[float] = []
    txs: list[float] = []
    files: dict[Path, tuple[list[dict], list[dict]]] = {}
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


def _finals(runs: list[tuple[dict, Path]], p: float) -> list[dict[str, float]]:
    """Final greedy policies' exact metrics, one dict per learner, at p^v_1 = p."""
    return [
        {k: to_float(row.get(k)) for k in Metrics.__dataclass_fields__}
        for _, row in _learners_at(runs, p)
    ]


def _exact_rows(
    series: str | Sequence[str], xs: Sequence[float], values: Sequence[float]
) -> list[dict]:
    """Band rows of exact values (no replicates: ``lo`` = ``hi`` = ``mean``, ``n`` = 0)."""
    names = [series] * len(xs) if isinstance(series, str) else list(series)
    return [
        {"series": name, "x": x, "mean": v, "lo": v, "hi": v, "n": 0}
        for name, x, v in zip(names, xs, values, strict=True)
    ]


@dataclass
class _Figure:
    """What every panel of one figure run needs."""

    cfg: DictConfig
    out: Path
    planned: list[dict[str, Any]]
    seeds: list[int]
    ps: list[float]
    curve_p: float
    base: Params
    refs: dict[float, Reference]

    @property
    def horizon(self) -> int:
        return self.base.env.horizon

    @property
    def methods(self) -> list[str]:
        return [str(m) for m in to_plain(self.cfg.methods)]

    def runs(self, learner: str) -> list[tuple[dict, Path]]:
        return _runs_of(self.planned, self.out / "trials", learner)


def run_figure2(cfg: DictConfig, out: Path, scenario: list[str] | None = None) -> int:
    """Run the figure: training runs, exact references, CSVs, PNGs, claims. Returns an exit code.

    Args:
        cfg: ``recipes/conf/figure2.yaml`` composed.
        out: the run directory.
        scenario: overrides naming the scenario (``env=…``, ``env.*``, ``reward.*``) given to
            every training run; the figure's own env/reward config must describe the same scenario.
    """
    t_start = time.perf_counter()
    out = Path(out).resolve()
    out.mkdir(parents=True, exist_ok=True)
    scenario = list(scenario or [])
    planned, seeds, ps, curve_p = plan_figure2(cfg, scenario)
    base = Params.from_config(cfg)
    print(
        f"figure2: {len(planned)} training runs for {', '.join(to_plain(cfg.methods))}; "
        f"{len(seeds)} seeds; p^v_1 ∈ {ps}; panel (a) at p^v_1 = {curve_p}",
        flush=True,
    )
    code = execute(cfg, planned, out)
    t_train = time.perf_counter() - t_start
    if code != 0:
        print(
            "figure2: some runs did not finish (see summary.csv); fix and rerun with resume=true",
            flush=True,
        )
        return code
    gamma = float(cfg.optimum_gamma)
    refs = {p: exact_reference(ref_params(base, p), gamma) for p in sorted({*ps, curve_p})}
    fig = _Figure(cfg, out, planned, seeds, ps, curve_p, base, refs)
    opt_ep, rr_ep, finals, to95 = _panel_a(fig)
    sweep_means = _panels_bcd(fig)
    r4_miss, r4_thr = {}, {}
    for r4 in to_plain(cfg.claim3_r4):
        _, m = optimal_at(ref_params(base, curve_p), float(r4), gamma)
        r4_miss[float(r4)], r4_thr[float(r4)] = m.miss_detection, m.throughput
    numbers = cl.FigureNumbers(
        optimum_episode=opt_ep,
        round_robin_episode=rr_ep,
        final_episode=finals,
        episodes_to_95=to95,
        p1_speed=ps,
        sweep=sweep_means,
        r4_miss=r4_miss,
        r4_throughput=r4_thr,
    )
    verdicts = cl.check_claims(numbers)
    table = cl.format_claims(verdicts)
    write_rows_csv(out / "claims.csv", [v.as_dict() for v in verdicts])
    atomic_write_text(out / "claims.md", table + "\n")
    wall = time.perf_counter() - t_start
    counts = cl.summarize(verdicts)
    summary = {
        "seeds": seeds,
        "p1_speed": ps,
        "curve_p1_speed": curve_p,
        "methods": fig.methods,
        "scenario": scenario,
        "training_runs": len(planned),
        "resumed": bool(cfg.resume),  # wall times then cover only what this invocation ran
        "wall_seconds_training": t_train,
        "wall_seconds": wall,
        "optimum_episode_reward": opt_ep,
        "round_robin_episode_reward": rr_ep,
        "final_episode_reward": finals,
        "episodes_to_95": to95,
        "verdicts": counts,
    }
    atomic_write_text(out / "summary.json", json.dumps(summary, indent=2) + "\n")
    print("\nclaims (MODEL.md § The paper's claims):\n")
    print(table)
    print(
        f"\n{counts[cl.HOLDS]} hold, {counts[cl.FAILS]} do not hold, {counts[cl.UNTESTED]} not tested. "
        f"Wall time {wall:.0f} s ({t_train:.0f} s of it training). Wrote panel_[abcd].png/.csv, "
        f"claims.md/.csv, summary.json to {out}"
    )
    return 0


def _panel_a(fig: _Figure) -> tuple[float, float, dict[str, float], dict[str, float | None]]:
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


def _panels_bcd(fig: _Figure) -> dict[str, dict[str, list[float]]]:
    """Panels (b)–(d): final policies against p^v_1. Returns subject → metric → mean per p^v_1."""
    ps, env = fig.ps, fig.base.env
    # The ranges the final policies' exact long-run values lie in: bands are clipped to them.
    bounds = {
        "avg_reward": None,
        "throughput": (0.0, env.arrival_rate),
        "link_capacity": (0.0, float(max(env.packets_good, env.packets_bad))),
        "miss_detection": (0.0, 1.0),
    }
    metric_rows: dict[str, list[dict]] = {m: [] for m in PANEL_METRICS}
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


def validate_figure2(cfg: DictConfig) -> None:
    """Every key of ``recipes/conf/figure2.yaml`` and every planned training run, before any work."""
    check_common(cfg)
    check_executor(cfg)
    r4 = to_plain(cfg.claim3_r4)
    if not isinstance(r4, list):
        raise ValueError(f"claim3_r4={r4!r} must be a list of detection rewards")
    for i, v in enumerate(r4):
        check_number(f"claim3_r4[{i}]", v, 0, 1e9, open_lo=True)
    plan_figure2(cfg, [])  # composes and validates every training run
