"""The paper's Figure 2 and the r4 trade-off, regenerated against the exact optimum.

``run_figure2`` plans every training run (DQN: one per seed and p^v_1; Q-learning: one vectorised
batch per profile holding every seed and p^v_1), executes them with the sweep engine
(``irdrc.sweep``), adds the exact optimum and round-robin, and writes one CSV and one PNG per panel and
the claims table. ``run_tradeoff`` maps the exact optimum over r4 and finds, by bisection, the
smallest r4 whose optimal policy meets a miss-detection target.
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from omegaconf import DictConfig

from irdrc import claims as cl
from irdrc import plots
from irdrc.figures import (
    band_rows,
    first_reaching,
    mean_ci,
    moving_average,
    read_csv,
    round_robin_episodes,
    same_value,
)
from irdrc.metrics import Metrics
from irdrc.model import build_model
from irdrc.params import Params, to_plain
from irdrc.results import atomic_write_text, write_rows_csv
from irdrc.solve import ExactScorer, episodic_metrics, stationary_metrics, value_iteration
from irdrc.sweep import execute, format_value, parse_grid, plan

GAMMA = 0.99
"""The discount that defines the optimum every result is read against (MODEL.md)."""
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
    if int(cfg.smooth_episodes) < 1 or int(cfg.dqn_eval_every_frames) < 1:
        raise ValueError("smooth_episodes and dqn_eval_every_frames must be >= 1")
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
        overrides = [str(o) for o in spec.overrides]
        if spec.method == "dqn":
            base = [
                *scenario,
                *overrides,
                "eval.mc_episodes=0",
                f"eval.every_frames={int(cfg.dqn_eval_every_frames)}",
            ]
            points = parse_grid({"env.p1.speed": values, "seed": seeds})
            runs = plan("dqn", points, base)
        else:
            grid = "{env.p1.speed: " + format_value(values) + "}"
            base = [
                *scenario,
                *overrides,
                f"num_learners={len(seeds)}",
                "mc_episodes=0",
                f"batch_grid={grid}",
            ]
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


def exact_reference(params: Params) -> Reference:
    """Optimal (value iteration at γ = 0.99) and round-robin metrics, exactly."""
    model = build_model(params)
    scorer = ExactScorer(model, GAMMA)
    return Reference(
        optimal=scorer.optimal_metrics,
        optimal_episodic=episodic_metrics(model, scorer.optimal.policy),
        round_robin=stationary_metrics(model, "round_robin"),
    )


def _runs_of(planned: list[dict], trials: Path, learner: str) -> list[tuple[dict, Path]]:
    return [(p, trials / p["point_id"]) for p in planned if p["learner"] == learner]


def _curves(
    spec_method: str, runs: list[tuple[dict, Path]], p: float, horizon: int, window: int
) -> tuple[list[float], list[list[float]], list[float], list[list[float]]]:
    """(eval episodes, greedy curves per seed, training episodes, smoothed training curves)."""
    greedy, training = [], []
    xs: list[float] = []
    txs: list[float] = []
    if spec_method == "dqn":
        for point, tdir in runs:
            if not same_value(point["point"]["env.p1.speed"], p):
                continue
            hist = read_csv(tdir / "metrics.csv")
            xs = [int(r["env_steps"]) / horizon for r in hist]
            greedy.append([float(r["avg_reward"]) * horizon for r in hist])
            eps = read_csv(tdir / "episode_rewards.csv")
            txs = [float(r["episode"]) for r in eps]
            training.append(moving_average([float(r["reward"]) for r in eps], window))
    else:
        ((_, tdir),) = runs
        rows = [r for r in read_csv(tdir / "learners.csv") if same_value(r["env.p1.speed"], p)]
        hist = read_csv(tdir / "metrics.csv")
        eps = read_csv(tdir / "episode_rewards.csv")
        xs = [float(r["episode"]) for r in hist]
        txs = [float(r["episode"]) for r in eps]
        for r in rows:
            n = r["row"]
            greedy.append([float(h[f"avg_reward_{n}"]) * horizon for h in hist])
            training.append(moving_average([float(e[f"reward_{n}"]) for e in eps], window))
    return xs, greedy, txs, training


def _finals(spec_method: str, runs: list[tuple[dict, Path]], p: float) -> list[dict[str, float]]:
    """Final greedy policies' exact metrics, one dict per seed, at p^v_1 = p."""
    out = []
    if spec_method == "dqn":
        for point, tdir in runs:
            if same_value(point["point"]["env.p1.speed"], p):
                s = json.loads((tdir / "summary.json").read_text())
                out.append({k: _num(v) for k, v in s["metrics"].items()})
    else:
        ((_, tdir),) = runs
        for r in read_csv(tdir / "learners.csv"):
            if same_value(r["env.p1.speed"], p):
                out.append({k: _num(r.get(k)) for k in Metrics.__dataclass_fields__})
    return out


def _num(v: Any) -> float:
    return math.nan if v in (None, "") else float(v)


def _exact_rows(
    series: str | Sequence[str], xs: Sequence[float], values: Sequence[float]
) -> list[dict]:
    """Band rows of exact values (no replicates: ``lo`` = ``hi`` = ``mean``, ``n`` = 0)."""
    names = [series] * len(xs) if isinstance(series, str) else list(series)
    return [
        {"series": name, "x": x, "mean": v, "lo": v, "hi": v, "n": 0}
        for name, x, v in zip(names, xs, values, strict=True)
    ]


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
    base_params = Params.from_config(cfg)
    horizon = base_params.env.horizon
    window = int(cfg.smooth_episodes)
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
    trials = out / "trials"

    refs = {p: exact_reference(ref_params(base_params, p)) for p in sorted({*ps, curve_p})}
    ref_a = refs[curve_p]
    opt_ep = ref_a.optimal.avg_reward * horizon
    rr_ep = ref_a.round_robin.avg_reward * horizon

    # Panel (a).
    greedy_rows, training_rows, marks, finals, to95 = [], [], {}, {}, {}
    max_episode = 0.0
    methods = [str(m) for m in to_plain(cfg.methods)]
    for name in methods:
        spec = cfg.learners[name]
        if "a" not in spec.panels:
            continue
        runs = _runs_of(planned, trials, name)
        xs, greedy, txs, training = _curves(spec.method, runs, curve_p, horizon, window)
        rows = band_rows(name, xs, greedy)
        greedy_rows += rows
        training_rows += band_rows(name, txs, training)
        marks[name] = to95[name] = first_reaching(rows, 0.95 * opt_ep)
        finals[name] = rows[-1]["mean"]
        max_episode = max(max_episode, xs[-1] if xs else 0.0, txs[-1] if txs else 0.0)
    n_rr = max(int(max_episode), window)
    rr_sim = [
        moving_average(c, window)
        for c in round_robin_episodes(ref_params(base_params, curve_p), seeds, n_rr)
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
    write_rows_csv(out / "panel_a.csv", panel_a)
    plots.plot_panel_a(
        greedy_rows,
        training_rows,
        opt_ep,
        ref_a.optimal_episodic.episode_reward,
        rr_ep,
        marks,
        out / "panel_a.png",
        p1_speed=curve_p,
        seeds=len(seeds),
        window=window,
        horizon=horizon,
    )

    # Panels (b)–(d).
    sweep_learners = [m for m in methods if "bcd" in cfg.learners[m].panels]
    metric_rows: dict[str, list[dict]] = {
        m: [] for m in ("avg_reward", "throughput", "link_capacity", "miss_detection")
    }
    sweep_means: dict[str, dict[str, list[float]]] = {}
    for name in sweep_learners:
        spec = cfg.learners[name]
        runs = _runs_of(planned, trials, name)
        per_p = [_finals(spec.method, runs, p) for p in ps]
        sweep_means[name] = {}
        for metric, rows in metric_rows.items():
            band = band_rows(
                name, ps, [[f[metric] for f in fin] for fin in zip(*per_p, strict=True)]
            )
            rows += band
            sweep_means[name][metric] = [r["mean"] for r in band]
    for series, attr in (("optimal", "optimal"), ("round_robin", "round_robin")):
        sweep_means[series] = {}
        for metric, rows in metric_rows.items():
            values = [getattr(getattr(refs[p], attr), metric) for p in ps]
            rows += _exact_rows(series, ps, values)
            sweep_means[series][metric] = values
    write_rows_csv(out / "panel_b.csv", metric_rows["avg_reward"])
    write_rows_csv(
        out / "panel_c.csv",
        [{"metric": m, **r} for m in ("throughput", "link_capacity") for r in metric_rows[m]],
    )
    write_rows_csv(out / "panel_d.csv", metric_rows["miss_detection"])
    n = len(seeds)
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

    # Claims.
    r4_miss, r4_thr = {}, {}
    for r4 in to_plain(cfg.claim3_r4):
        _, m = optimal_at(ref_params(base_params, curve_p), float(r4))
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
        "methods": methods,
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


def ref_params(base: Params, p1_speed: float) -> Params:
    """The scenario at ``p1_speed``."""
    return base.with_overrides({"env.p1.speed": p1_speed})


# --------------------------------------------------------------------------------------------------
# The r4 trade-off (claim 3 and beyond).


def optimal_at(params: Params, r4: float) -> tuple[torch.Tensor, Metrics]:
    """The optimal policy and its exact long-run metrics at detection reward ``r4``."""
    p = params.with_overrides({"reward.r4": r4})
    model = build_model(p)
    policy = value_iteration(model, gamma=GAMMA).policy
    return policy, stationary_metrics(model, policy)


def smallest_r4(
    miss_of: Callable[[float], float],
    target: float,
    lo: float,
    hi: float,
    resolution: float,
) -> tuple[float | None, int]:
    """The smallest r4 on the grid ``lo + k·resolution`` (≤ ``hi``) with ``miss_of(r4) ≤ target``.

    Bisection: assumes miss detection does not increase with r4 (a larger detection reward never
    makes the optimum watch less), and checks both ends first.

    Returns:
        (r4 or None if even ``hi`` misses the target, number of ``miss_of`` calls).
    """
    if resolution <= 0 or hi < lo:
        raise ValueError("need resolution > 0 and hi >= lo")
    calls = 0

    def ok(k: int) -> bool:
        nonlocal calls
        calls += 1
        return miss_of(lo + k * resolution) <= target

    k_hi = math.floor((hi - lo) / resolution + 1e-9)
    if ok(0):
        return lo, calls
    if not ok(k_hi):
        return None, calls
    a, b = 0, k_hi  # ok(a) is False, ok(b) is True
    while b - a > 1:
        mid = (a + b) // 2
        if ok(mid):
            b = mid
        else:
            a = mid
    return round(lo + b * resolution, 10), calls


def run_tradeoff(cfg: DictConfig, out: Path, scenario: list[str] | None = None) -> int:
    """Exact trade-off curves over r4, the bisection for ``target_miss``, DQN at a few points."""
    t0 = time.perf_counter()
    out = Path(out).resolve()
    out.mkdir(parents=True, exist_ok=True)
    r4s = sorted({float(r) for r in to_plain(cfg.r4)})
    ps = [float(p) for p in to_plain(cfg.p1_speed)]
    if not r4s or any(r <= 0 for r in r4s) or not ps:
        raise ValueError("r4 must be a non-empty list of positive values; p1_speed non-empty")
    target = cfg.target_miss
    if target is not None and not 0.0 <= float(target) <= 1.0:
        raise ValueError(f"target_miss={target!r} must be in [0, 1] (or null)")
    base = Params.from_config(cfg)
    rows = []
    for p in ps:
        params = ref_params(base, p)
        for r4 in r4s:
            policy, m = optimal_at(params, r4)
            rows.append(
                {
                    "series": f"p1.speed={p:g}",
                    "p1_speed": p,
                    "r4": r4,
                    "radar_states": int(policy.sum()),
                    **m.as_dict(),
                }
            )
    write_rows_csv(out / "tradeoff.csv", rows)
    print(f"the optimal policy as r4 varies (exact, γ = {GAMMA}):\n")
    print("p1.speed      r4  radar states  miss detection  throughput  link capacity  avg reward")
    for r in rows:
        print(
            f"{r['p1_speed']:>8g}  {r['r4']:>6g}  {r['radar_states']:>12}  {r['miss_detection']:>14.4f}  "
            f"{r['throughput']:>10.4f}  {r['link_capacity']:>13.4f}  {r['avg_reward']:>10.4f}"
        )

    found: dict[str, Any] = {}
    scan_rows: list[dict] = []
    if target is not None:
        lo, hi, res = float(cfg.search.lo), float(cfg.search.hi), float(cfg.search.resolution)
        for p in ps:
            params = ref_params(base, p)
            metrics_at: dict[float, Metrics] = {}

            def miss_of(r: float, params: Params = params, memo: dict = metrics_at) -> float:
                if r not in memo:
                    memo[r] = optimal_at(params, r)[1]
                return memo[r].miss_detection

            r4, calls = smallest_r4(miss_of, float(target), lo, hi, res)
            entry: dict[str, Any] = {"r4": r4, "bisection_r4": r4, "solver_calls": calls}
            if r4 is not None and cfg.search.verify:
                # Bisection assumes miss detection never rises with r4; it can (see
                # docs/REPRODUCTION.md), so every grid point below the answer is solved too.
                grid = [round(lo + k * res, 10) for k in range(round((r4 - lo) / res))]
                below = [r for r in grid if miss_of(r) <= float(target)]
                entry["verified"] = not below
                if below:
                    entry["r4"] = r4 = below[0]
                scan_rows += [
                    {"series": f"p1.speed={p:g}", "p1_speed": p, "r4": r, **metrics_at[r].as_dict()}
                    for r in sorted(metrics_at)
                ]
            if r4 is not None:
                entry["metrics"] = (
                    metrics_at[r4].as_dict()
                    if r4 in metrics_at
                    else optimal_at(params, r4)[1].as_dict()
                )
                if r4 - res >= lo - 1e-9:
                    entry["miss_at_lower_neighbour"] = miss_of(round(r4 - res, 10))
            found[f"{p:g}"] = entry
            if r4 is None:
                print(
                    f"\np1.speed={p:g}: no r4 in [{lo:g}, {hi:g}] meets miss detection ≤ {target}"
                )
                continue
            print(
                f"\np1.speed={p:g}: smallest r4 meeting miss detection ≤ {target}: {r4:g} "
                f"(grid step {res:g}; bisection: {calls} exact solves"
                + (
                    ", confirmed by solving every grid point below it)"
                    if entry.get("verified")
                    else f"; it answered {entry['bisection_r4']:g}, but miss detection is not "
                    "monotone in r4 here and the scan below it found this one)"
                    if "verified" in entry
                    else ")"
                )
                + f"; there miss {entry['metrics']['miss_detection']:.4f}, "
                f"throughput {entry['metrics']['throughput']:.4f}, "
                f"link capacity {entry['metrics']['link_capacity']:.4f}"
                + (
                    f"; at r4 = {r4 - res:g} miss {entry['miss_at_lower_neighbour']:.4f}"
                    if "miss_at_lower_neighbour" in entry
                    else ""
                )
            )
        if scan_rows:
            write_rows_csv(out / "r4_scan.csv", scan_rows)

    learned_rows: list[dict] = []
    dqn_r4 = [float(r) for r in (to_plain(cfg.dqn.r4) or [])]
    code = 0
    if dqn_r4:
        seeds = [int(s) for s in to_plain(cfg.dqn.seeds)]
        p = ps[0]
        base_ov = [
            *(scenario or []),
            *[str(o) for o in cfg.dqn.overrides],
            "eval.mc_episodes=0",
            f"env.p1.speed={p}",
        ]
        planned = plan("dqn", parse_grid({"reward.r4": dqn_r4, "seed": seeds}), base_ov)
        code = execute(cfg, planned, out)
        if code == 0:
            for r4 in dqn_r4:
                fin = [
                    json.loads((out / "trials" / pl["point_id"] / "summary.json").read_text())[
                        "metrics"
                    ]
                    for pl in planned
                    if same_value(pl["point"]["reward.r4"], r4)
                ]
                miss = mean_ci(_num(f["miss_detection"]) for f in fin)
                learned_rows.append(
                    {
                        "series": f"dqn, p1.speed={p:g}",
                        "r4": r4,
                        "miss_detection": miss["mean"],
                        "lo": miss["lo"],
                        "hi": miss["hi"],
                        "n": miss["n"],
                        "throughput": mean_ci(_num(f["throughput"]) for f in fin)["mean"],
                        "link_capacity": mean_ci(_num(f["link_capacity"]) for f in fin)["mean"],
                    }
                )
            write_rows_csv(out / "tradeoff_dqn.csv", learned_rows)
            print("\nDQN (ours), final greedy policies, exact, mean over seeds:")
            for r in learned_rows:
                print(
                    f"  r4={r['r4']:g}: miss {r['miss_detection']:.4f} [{r['lo']:.4f}, {r['hi']:.4f}], "
                    f"throughput {r['throughput']:.4f}, link capacity {r['link_capacity']:.4f}"
                )
    plots.plot_tradeoff(
        rows,
        learned_rows,
        out / "tradeoff.png",
        target=None if target is None else float(target),
        scan=scan_rows,
    )
    summary = {
        "r4": r4s,
        "p1_speed": ps,
        "target_miss": target,
        "smallest_r4": found,
        "wall_seconds": time.perf_counter() - t0,
    }
    atomic_write_text(out / "summary.json", json.dumps(summary, indent=2) + "\n")
    print(
        f"\nwrote tradeoff.csv, tradeoff.png, summary.json to {out} ({summary['wall_seconds']:.0f} s)"
    )
    return code


# --------------------------------------------------------------------------------------------------
# docs/REPRODUCTION.md: the generated blocks and the committed figures.

FIGURES = ("panel_a.png", "panel_b.png", "panel_c.png", "panel_d.png")


def _block(text: str, name: str, body: str) -> str:
    """Replace the body between ``<!-- generated:NAME -->`` and ``<!-- /generated:NAME -->``."""
    start, end = f"<!-- generated:{name} -->", f"<!-- /generated:{name} -->"
    i, j = text.find(start), text.find(end)
    if i < 0 or j < i:
        raise ValueError(f"the report has no block {start} … {end}")
    return text[: i + len(start)] + "\n" + body.rstrip() + "\n" + text[j:]


def _md_table(header: Sequence[str], rows: Sequence[Sequence[Any]]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(str(c) for c in r) + " |" for r in rows]
    return "\n".join(lines)


def _fmt(x: Any, digits: int = 4) -> str:
    try:
        v = float(x)
    except (TypeError, ValueError):
        return str(x)
    return "n/a" if math.isnan(v) else f"{v:.{digits}g}"


def write_report(figure_dir: Path, tradeoff_dir: Path, docs_dir: Path, command: str) -> None:
    """Copy the figures into ``docs_dir/figures`` and fill the generated blocks of
    ``docs_dir/REPRODUCTION.md`` from a figure2 run and a tradeoff run."""
    import shutil

    figure_dir, tradeoff_dir, docs_dir = Path(figure_dir), Path(tradeoff_dir), Path(docs_dir)
    fig_out = docs_dir / "figures"
    fig_out.mkdir(parents=True, exist_ok=True)
    for name in FIGURES:
        shutil.copyfile(figure_dir / name, fig_out / name)
    shutil.copyfile(tradeoff_dir / "tradeoff.png", fig_out / "tradeoff.png")
    summary = json.loads((figure_dir / "summary.json").read_text())
    trade = json.loads((tradeoff_dir / "summary.json").read_text())
    if summary.get("resumed"):
        raise ValueError(f"{figure_dir} was resumed: its wall time is not the whole run's")

    report = (docs_dir / "REPRODUCTION.md").read_text()
    report = _block(report, "command", f"```bash\n{command}\n```")
    report = _block(
        report,
        "timing",
        f"Measured on this 2-core machine: **{summary['wall_seconds'] / 60:.1f} min** "
        f"({summary['wall_seconds']:.0f} s) for the figure: {summary['training_runs']} training "
        f"runs ({len(summary['seeds'])} seeds; p^v_1 ∈ {{{', '.join(f'{p:g}' for p in summary['p1_speed'])}}}) "
        f"took {summary['wall_seconds_training']:.0f} s of it; then {trade['wall_seconds']:.0f} s "
        "for the trade-off.",
    )
    # Panel (a) numbers.
    rows = []
    for name, final in summary["final_episode_reward"].items():
        ep = summary["episodes_to_95"].get(name)
        rows.append([name, "never" if ep is None else f"{ep:g}", f"{final:.1f}"])
    rows.append(["optimal (exact)", "—", f"{summary['optimum_episode_reward']:.1f}"])
    rows.append(["round-robin (exact)", "—", f"{summary['round_robin_episode_reward']:.1f}"])
    report = _block(
        report,
        "panel_a",
        _md_table(
            [
                "method",
                "first training episode with mean ≥ 95 % of the optimum",
                "final total reward per episode (mean over seeds)",
            ],
            rows,
        ),
    )
    # Panels (b)–(d) at the ends of the sweep.
    p_lo, p_hi = summary["p1_speed"][0], summary["p1_speed"][-1]
    table: dict[str, dict[str, str]] = {}
    for panel, metric_key in (("b", None), ("c", "metric"), ("d", None)):
        for r in read_csv(figure_dir / f"panel_{panel}.csv"):
            metric = (
                r[metric_key] if metric_key else {"b": "avg_reward", "d": "miss_detection"}[panel]
            )
            for p, tag in ((p_lo, "lo"), (p_hi, "hi")):
                if same_value(r["x"], p):
                    band = "" if r["n"] == "0" else f" [{_fmt(r['lo'])}, {_fmt(r['hi'])}]"
                    table.setdefault(r["series"], {})[f"{metric}_{tag}"] = _fmt(r["mean"]) + band
    metrics = ("avg_reward", "throughput", "link_capacity", "miss_detection")
    header = ["method"] + [f"{m} at {p:g}" for m in metrics for p in (p_lo, p_hi)]
    rows = [
        [s] + [vals.get(f"{m}_{t}", "") for m in metrics for t in ("lo", "hi")]
        for s, vals in table.items()
    ]
    report = _block(report, "panels_bcd", _md_table(header, rows))
    report = _block(report, "claims", (figure_dir / "claims.md").read_text())
    # Trade-off.
    rows = [
        [
            _fmt(r["p1_speed"], 3),
            _fmt(r["r4"], 4),
            r["radar_states"],
            _fmt(r["miss_detection"]),
            _fmt(r["throughput"]),
            _fmt(r["link_capacity"]),
        ]
        for r in read_csv(tradeoff_dir / "tradeoff.csv")
    ]
    body = _md_table(
        ["p^v_1", "r4", "radar states (of 352)", "miss detection", "throughput", "link capacity"],
        rows,
    )
    lines = []
    for p, entry in (trade.get("smallest_r4") or {}).items():
        if entry.get("r4") is None:
            lines.append(f"- p^v_1 = {p}: no r4 on the search grid meets the target.")
            continue
        m = entry["metrics"]
        lines.append(
            f"- p^v_1 = {p}: smallest r4 with miss detection ≤ {trade['target_miss']}: "
            f"**{entry['r4']:g}** (miss {m['miss_detection']:.4f}, throughput {m['throughput']:.4f}, "
            f"link capacity {m['link_capacity']:.4f}); one grid step lower, miss "
            f"{entry.get('miss_at_lower_neighbour', float('nan')):.4f}"
            + ("; checked against every grid point below it" if entry.get("verified") else "")
            + "."
        )
    dqn_csv = tradeoff_dir / "tradeoff_dqn.csv"
    if dqn_csv.is_file() and dqn_csv.stat().st_size:
        for r in read_csv(dqn_csv):
            lines.append(
                f"- DQN (ours), {r['series']}, r4 = {_fmt(r['r4'])}: miss detection "
                f"{_fmt(r['miss_detection'])} [{_fmt(r['lo'])}, {_fmt(r['hi'])}] over {r['n']} seeds, "
                f"throughput {_fmt(r['throughput'])}, link capacity {_fmt(r['link_capacity'])}."
            )
    report = _block(report, "tradeoff", body + "\n\n" + "\n".join(lines))
    atomic_write_text(docs_dir / "REPRODUCTION.md", report)
