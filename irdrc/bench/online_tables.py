"""The tables of ``recipes/bench_online.py``: one row per run (convergence, the ledger at the
window, the speed), then medians per learner and scenario, and the safe learner beside the
Lagrangian DQN's training."""

from __future__ import annotations

import math
import statistics
from typing import Any

from irdrc.core.checks import counted
from irdrc.online.configs import SAFE_LEARNERS
from irdrc.runs.results import md_table

THRESHOLD = 0.99


def run_row(job: Any, result: dict[str, Any], window: int) -> dict[str, Any]:
    """One run's figures: convergence, the ledger at ``window`` episodes, the speed."""
    from irdrc.online.recipe import convergence

    hist = result["history"]
    at = next((r for r in hist if r["episodes"] >= window), hist[-1])
    conv = convergence(hist)
    steps = hist[-1]["env_steps"]
    row = {
        "learner": job.learner,
        "scenario": job.scenario,
        "seed": job.seed,
        "target_miss": job.target,
        **conv,
        "within_window": conv["episodes_to_99"] is not None and conv["episodes_to_99"] <= window,
        "final_ratio": hist[-1]["optimality_ratio"],
        "regret": at["regret"],
        "expected_missed": at["expected_missed"],
        "floor_missed": at["floor_missed"],
        "realised_regret": at["realised_regret"],
        "realised_missed": at["realised_missed"],
        "steps_per_second": steps / result["seconds_learning"]
        if result.get("seconds_learning")
        else None,
        "slowest_decision": result.get("slowest_decision"),
        "wall_seconds": result["wall_seconds"],
    }
    if job.learner in SAFE_LEARNERS:
        cum = [
            r["cumulative_miss_detection"]
            for r in hist
            if r.get("cumulative_miss_detection") is not None
            and not _nan(r["cumulative_miss_detection"])
        ]
        conf = result.get("plan_confidence") or {}
        cost = result.get("lp_cost")  # (g* − g_LP) per step: the target's own
        row.update(
            {
                "worst_cumulative_miss": max(cum, default=0.0),
                "violations": sum(c > job.target + 1e-12 for c in cum),
                "expected_holds": all(
                    r["expected_missed"] <= job.target * r["expected_events"] + 1e-9 for r in hist
                ),
                "lp_ratio": at.get("lp_ratio"),
                "learning_regret": None if cost is None else at["regret"] - cost * at["env_steps"],
                "meets_target": bool(at.get("meets_target")),
                "greedy_miss": at["miss_detection"],
                "plan_miss_mean": conf.get("miss_mean"),
                "plan_miss_sd": conf.get("miss_sd"),
                "plan_p_within_target": conf.get("p_within_target"),
            }
        )
    return row


def _nan(x: Any) -> bool:
    return x is None or (isinstance(x, float) and math.isnan(x))


def _med(values: list[float]) -> str:
    values = [v for v in values if v is not None]
    return f"{statistics.median(values):.4g}" if values else "—"


def _slowest(rows: list[dict[str, Any]]) -> str:
    """The runs' slowest decisions in milliseconds: median (worst); "—" where none was timed."""
    ms = [1e3 * r["slowest_decision"] for r in rows if r.get("slowest_decision") is not None]
    return f"{statistics.median(ms):.3g} ({max(ms):.3g})" if ms else "—"


def learner_table(rows: list[dict[str, Any]], window: int) -> str:
    """One row per (learner, scenario set): medians (worst) over its runs."""
    body = []
    groups: dict[tuple[str, str], list[dict[str, Any]]] = {}
    for r in rows:
        where = "random draws" if r["scenario"].startswith("draw") else r["scenario"]
        groups.setdefault((r["learner"], where), []).append(r)
    for (learner, where), mine in groups.items():
        ep99 = [r["episodes_to_99"] for r in mine]
        reached = [e for e in ep99 if e is not None]
        later = [r["stay_99"] for r in mine if r["stay_99"] is not None]
        body.append(
            [
                learner,
                where,
                f"{sum(r['within_window'] for r in mine)}/{len(mine)}",
                _med(reached) + (f" ({max(reached)})" if reached else ""),
                _med([r["episodes_to_95"] for r in mine]),
                _med(later),
                f"{_med([r['regret'] for r in mine])} ({max(r['regret'] for r in mine):.4g})",
                f"{_med([r['expected_missed'] for r in mine])} ({max(r['expected_missed'] for r in mine):.4g})",
                _med([r["floor_missed"] for r in mine]),
                _med([r["steps_per_second"] for r in mine]),
                _slowest(mine),
                _med([r["wall_seconds"] for r in mine]),
            ]
        )
    return md_table(
        [
            "learner",
            "scenario",
            f"≥ {THRESHOLD} within {window} episodes",
            "episodes to 0.99, median (worst)",
            "episodes to 0.95",
            "later evaluations ≥ 0.99",
            f"regret over {window} episodes, median (worst)",
            f"missed events over {window} episodes, median (worst)",
            "the optimum's (floor)",
            "env steps/s of training",
            "slowest decision, ms, median (worst)",
            "wall time per run, s (median)",
        ],
        body,
    )


def safe_table(rows: list[dict[str, Any]], lag: list[dict[str, Any]], window: int) -> str:
    """The safe learner per (target, scenario), with the Lagrangian DQN's training beside it; per
    profile too, in a first column, where the rows hold more than one."""
    body = []
    groups: dict[tuple[str, float, str], list[dict[str, Any]]] = {}
    for r in rows:
        groups.setdefault((r["learner"], r["target_miss"], r["scenario"]), []).append(r)
    several = len({learner for learner, _, _ in groups}) > 1
    for (learner, target, scenario), mine in groups.items():
        theirs = [r for r in lag if r["target_miss"] == target and r["scenario"] == scenario]
        ratios = [r["lp_ratio"] for r in mine if r["lp_ratio"] is not None]
        beyond = [r["learning_regret"] for r in mine if r.get("learning_regret") is not None]
        body.append(
            [learner] * several
            + [
                f"{target:g}",
                scenario,
                f"{sum(r['violations'] == 0 for r in mine)}/{len(mine)}",
                f"{max(r['worst_cumulative_miss'] for r in mine):.4f}",
                f"{sum(r['expected_holds'] for r in mine)}/{len(mine)}",
                f"{_med(ratios)} ({min(ratios):.4f})" if ratios else "—",
                f"{_med(beyond)} ({max(beyond):.4g})" if beyond else "—",
                f"{sum(r['meets_target'] for r in mine)}/{len(mine)}",
                _confidence(mine, target),
                _slowest(mine),
                _med([r["wall_seconds"] for r in mine]),
                (
                    f"{sum(r['violations'] == 0 for r in theirs)}/{len(theirs)}, worst "
                    f"{max(r['worst_cumulative_miss'] for r in theirs):.4f}, at the end "
                    f"{_med([r['final_cumulative_miss'] for r in theirs])}"
                )
                if theirs
                else "—",
            ]
        )
    return md_table(
        ["learner"] * several
        + [
            "target_miss",
            "scenario",
            "runs within the target at every evaluation",
            "worst cumulative miss detection",
            "expected missed ≤ target × expected events, every evaluation",
            f"greedy plan's packets / the LP's at {window} episodes, median (worst)",
            f"regret over {window} episodes beyond the LP's own, median (worst)",
            "greedy plan's long-run miss ≤ target",
            "its posterior: P(plan's miss ≤ target), mean; the sd of its miss over the target, median",
            "slowest decision, ms, median (worst)",
            "wall time per run, s (median)",
            "Lagrangian DQN's training: runs within the target throughout, worst, at the end "
            "(median)",
        ],
        body,
    )


def _confidence(rows: list[dict[str, Any]], target: float) -> str:
    """The safe plans' stated confidence (``SafeLearner.plan_confidence``) over a cell's runs: the
    mean probability of meeting the target, and the median spread as a share of the target."""
    rows = [r for r in rows if r.get("plan_miss_sd") is not None]
    if not rows:
        return "—"
    p = statistics.mean(r["plan_p_within_target"] for r in rows)
    sd = statistics.median(r["plan_miss_sd"] for r in rows) / target
    return f"{p:.2f}; {100 * sd:.1f} %"


def calibration_note(rows: list[dict[str, Any]]) -> str:
    """The safe plans' stated confidence held against the truth, over every safe run that states
    one: how often the plan's exact long-run miss detection lies within one and two posterior sds
    of the posterior mean (about 68 % and 95 % if the posterior is calibrated), on which side of it
    (below: the posterior expects more misses than the plan makes, and its stated probability errs
    low), beside the mean stated probability of meeting the target and the plans that do ("" where
    no run states one)."""
    rows = [r for r in rows if r.get("plan_miss_sd") is not None]
    if not rows:
        return ""
    z = []
    for r in rows:
        gap = abs(r["greedy_miss"] - r["plan_miss_mean"])
        z.append(
            gap / r["plan_miss_sd"] if r["plan_miss_sd"] > 0 else (0.0 if gap < 1e-12 else math.inf)
        )
    n = len(z)
    one, two = sum(x <= 1 for x in z), sum(x <= 2 for x in z)
    p = statistics.mean(r["plan_p_within_target"] for r in rows)
    meets = sum(bool(r["meets_target"]) for r in rows)
    below = sum(r["greedy_miss"] < r["plan_miss_mean"] for r in rows)
    return (
        f"The stated confidence against the truth, over the {counted(n, 'safe run')}: each plan's exact "
        f"long-run miss detection lies within one posterior sd of the posterior mean in {one} "
        f"({100 * one / n:.0f} %; about 68 % if the posterior is calibrated) and within two in "
        f"{two} ({100 * two / n:.0f} %; about 95 %), and below the posterior mean (fewer misses "
        f"than the posterior expects) in {below} of the {n}. The stated probabilities of meeting the "
        f"target average {p:.2f}; {meets} of the {n} plans meet it."
    )


def lagrangian_row(job: Any, result: dict[str, Any], horizon: int) -> dict[str, Any]:
    """The Lagrangian DQN's training: its cumulative miss detection (every row's steps) at the
    first batch past each multiple of ``horizon`` env steps, as the safe learner's is read after
    each episode: how often it was over the target."""
    cum, mark = [], horizon
    for p in result["trace"]:
        if p["env_steps"] >= mark:
            cum.append(p["cumulative_miss"])
            mark = (p["env_steps"] // horizon + 1) * horizon
    return {
        "learner": job.learner,
        "scenario": job.scenario,
        "seed": job.seed,
        "target_miss": job.target,
        "worst_cumulative_miss": max(cum, default=0.0),
        "final_cumulative_miss": result["trace"][-1]["cumulative_miss"]
        if result["trace"]
        else None,
        "violations": sum(c > job.target + 1e-12 for c in cum),
        "points": len(cum),
    }
