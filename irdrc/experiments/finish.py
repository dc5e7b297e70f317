"""How every learner's run finishes: the run files, the printout, the learning-curve figure.

``finish_run`` writes ``metrics.csv`` (one schema: ``irdrc.agents.base.progress_fields``),
``episode_rewards.csv``, ``learners.csv``, ``policy.csv``, ``summary.json`` (every row of the
printed table), ``learning_curve.png`` and ``checkpoint.pt`` for learners that checkpoint, then
prints the table, the final ratio and the states where the policy differs from the optimum.
"""

from __future__ import annotations

import statistics
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
from omegaconf import DictConfig, OmegaConf

from irdrc.agents.base import EPISODE_FIELDS, RunRecord, progress_fields
from irdrc.core.env import DFRCEnv
from irdrc.core.evaluate import evaluate
from irdrc.core.metrics import Metrics, format_table
from irdrc.core.model import ExactModel
from irdrc.core.params import Params
from irdrc.core.policies import table_policy
from irdrc.core.solve import ExactScorer, episodic_metrics, stationary_metrics
from irdrc.experiments.grid import is_scenario_key, point_overrides
from irdrc.experiments.guard import save_checkpoint
from irdrc.experiments.results import (
    atomic_savefig,
    clean_number,
    policy_differences,
    summary_dict,
    write_policy_csv,
    write_rows_csv,
    write_summary,
)


def finish_run(
    name: str,
    cfg: DictConfig,
    out: Path,
    scenario: str,
    record: RunRecord,
    scenarios: list[Params],
    scorers: list[ExactScorer],
    points: list[dict[str, Any]],
    num_learners: int,
    comparisons: dict[str, Metrics],
) -> dict[str, Any]:
    """Write the run files of every learner the same way, print the table, return the summary."""
    learners = learner_rows(record, scorers, points, num_learners)
    if record.state is not None:
        state = {**record.state, "scenario": scenario}  # a resumed run keeps the scenario's name
        save_checkpoint(out, state, OmegaConf.to_container(cfg, resolve=True))
    write_rows_csv(out / "metrics.csv", record.history, progress_fields(record.history))
    write_rows_csv(out / "episode_rewards.csv", record.episode_rewards, EPISODE_FIELDS)
    write_rows_csv(out / "learners.csv", learners)
    greedy = record.greedy[0].cpu()
    write_policy_csv(out / "policy.csv", greedy, scenarios[0].env.levels)
    plot_learning_curve(record, out / curve_file(cfg), title=f"{name} on {scenario}")

    model, opt = scorers[0].model, scorers[0].optimal_metrics
    learned = scorers[0].metrics(greedy)
    rows: dict[str, Metrics] = {f"{name} (exact, long run)": learned}
    errs: dict[str, dict[str, float]] = {}
    episodic = int(cfg.eval.mc_episodes) > 0 and isinstance(model, ExactModel)
    if int(cfg.eval.mc_episodes):
        env = DFRCEnv(scenarios[0], batch_size=[int(cfg.eval.mc_num_envs)], seed=int(cfg.seed) + 1)
        ev = evaluate(table_policy(greedy), env, episodes=int(cfg.eval.mc_episodes))
        if episodic:  # what the Monte-Carlo row estimates, exactly
            rows[f"{name} (exact, episodic)"] = episodic_metrics(model, greedy)
        label = f"{name} (Monte-Carlo, episodic)"
        rows[label], errs[label] = ev.metrics, ev.ci95
    rows["optimal (exact, long run)"] = opt
    if episodic:
        rows["optimal (exact, episodic)"] = episodic_metrics(model, scorers[0].optimal.policy)
    rows["round_robin (exact, long run)"] = stationary_metrics(model, "round_robin")
    for label, m in comparisons.items():
        rows[f"{label} (exact, long run)"] = m

    first99 = record.first_reaching(0.99)
    extra: dict[str, Any] = {
        "training_env_steps": record.training_env_steps,
        "measurement_env_steps": record.measurement_env_steps,
        "updates": record.updates,
        "env_steps_to_95": record.first_reaching(0.95),
        "env_steps_to_99": first99,
        "num_learners": num_learners,
        "interrupted": record.interrupted,
        "states_differing_from_optimum": int((greedy != scorers[0].optimal.policy).sum()),
        "learners": [_summary_row(r) for r in learners],
        "table": table_dict(rows, errs),
        **record.info,
    }
    if len(scenarios) > 1:
        extra["batch_grid"] = [
            {
                "overrides": point_overrides(point),
                "optimal": {
                    k: clean_number(v) for k, v in scorers[g].optimal_metrics.as_dict().items()
                },
            }
            for g, point in enumerate(points)
        ]
    summary = summary_dict(
        method=name,
        scenario=scenario,
        seed=int(cfg.seed),
        env_steps=record.env_steps,
        wall_seconds=record.wall_seconds,
        metrics=learned,
        optimal=opt,
        **extra,
    )
    write_summary(out / "summary.json", summary)

    _print_run(name, cfg, out, scenario, record, scenarios, scorers, points, learners, rows, errs)
    return summary


def _print_run(
    name: str,
    cfg: DictConfig,
    out: Path,
    scenario: str,
    record: RunRecord,
    scenarios: list[Params],
    scorers: list[ExactScorer],
    points: list[dict[str, Any]],
    learners: list[dict[str, Any]],
    rows: dict[str, Metrics],
    errs: dict[str, dict[str, float]],
) -> None:
    """The run's printout: the table (or one line per batched scenario), learners, files."""
    num_learners = int(cfg.get("num_learners", 1))
    print(
        f"\nscenario={scenario} method={name} seed={cfg.seed} learners={num_learners}"
        + (f" × {len(scenarios)} scenarios (batch_grid)" if len(scenarios) > 1 else "")
    )
    print(
        f"{record.env_steps} env steps per learner, {record.updates} updates in "
        f"{record.wall_seconds:.1f} s; exact evaluation every {cfg.eval.every_frames} env steps\n"
    )
    if len(scenarios) == 1:
        print(format_table(rows, errors=errs))
        print(
            "long run: the policy's stationary average (it runs forever); episodic: episodes of "
            f"{scenarios[0].env.horizon} steps from a uniform reset, as the Monte-Carlo row samples"
        )
        if note := degenerate_note(scorers[0].optimal_metrics):
            print(note)
    else:
        print("scenario                        optimum avg reward  final ratio (median, min)")
        for g, point in enumerate(points):
            mine = [r["final_ratio"] for r in learners if record.group[r["learner"]] == g]
            label = " ".join(point_overrides(point))
            print(
                f"{label:<32}{scorers[g].optimal_metrics.avg_reward:>18.4f}  "
                f"{statistics.median(mine):.4f}, {min(mine):.4f}"
            )
    if record.num_learners > 1:
        print("\nlearner  final ratio  env steps to 95 %  to 99 %")
        for row in learners:
            print(
                f"{row['learner']:>7}  {row['final_ratio']:>11.4f}  {row['env_steps_to_95']!s:>17}  "
                f"{row['env_steps_to_99']!s:>7}"
            )
    for th in ("95", "99") if record.num_learners > 1 else ():
        got = [r[f"env_steps_to_{th}"] for r in learners]
        hit = sorted(g for g in got if g is not None)
        med = statistics.median(hit) if len(hit) == len(got) else None
        print(f"to {th} %: {len(hit)}/{len(got)} learners; median env steps {med}")
    final = learners[0]["final_ratio"]
    first99 = learners[0]["env_steps_to_99"]
    print(
        f"\nfinal greedy policy: {final:.4f} of the optimum's average reward (exact); "
        + (
            f"first ≥ 99 % at {first99} env steps"
            if first99 is not None
            else f"not ≥ 99 % at any evaluation of its {record.env_steps} env steps"
        )
    )
    model = scorers[0].model
    print(policy_differences(model, record.greedy[0].cpu(), scorers[0].optimal.policy))
    files = [
        "summary.json",
        "policy.csv",
        "metrics.csv",
        "learners.csv",
        "episode_rewards.csv",
        curve_file(cfg),
    ]
    if record.state is not None:
        files += ["config.yaml", "checkpoint.pt"]
    print(f"\nwrote {', '.join(files)} to {out}")


def learner_rows(
    record: RunRecord,
    scorers: list[ExactScorer],
    points: list[dict[str, Any]],
    num_learners: int,
) -> list[dict[str, Any]]:
    """``learners.csv``: one row per learner — its scenario point, ``learner`` (the index used in
    ``metrics.csv`` and ``episode_rewards.csv``), ``replicate`` (its index within its scenario),
    final ratio, steps to 95 / 99 % and final exact metrics."""
    rows = []
    for n in range(record.num_learners):
        g = record.group[n]
        final = scorers[g].metrics(record.greedy[n].cpu())
        curve = record.curve(n)
        rows.append(
            {
                **points[g],
                "learner": n,
                "replicate": n % num_learners,
                "final_ratio": curve[-1]["optimality_ratio"],
                "training_env_steps": record.training_env_steps,
                "measurement_env_steps": record.measurement_env_steps,
                "env_steps": record.env_steps,
                "env_steps_to_95": record.first_reaching(0.95, n),
                "env_steps_to_99": record.first_reaching(0.99, n),
                **{k: clean_number(v) for k, v in final.as_dict().items()},
            }
        )
    return rows


def _summary_row(row: dict[str, Any]) -> dict[str, Any]:
    keys = ("learner", "replicate", "final_ratio", "env_steps_to_95", "env_steps_to_99")
    return {k: row[k] for k in keys} | {k: v for k, v in row.items() if is_scenario_key(k)}


def table_dict(
    rows: dict[str, Metrics], errs: dict[str, dict[str, float]]
) -> dict[str, dict[str, Any]]:
    """The printed table as JSON: row → metrics (and ``ci95`` where the row has intervals)."""
    out = {}
    for label, m in rows.items():
        entry: dict[str, Any] = {k: clean_number(v) for k, v in m.as_dict().items()}
        if label in errs:
            entry["ci95"] = {k: clean_number(v) for k, v in errs[label].items()}
        out[label] = entry
    return out


PLOT_FORMATS = ("png", "pdf", "svg")
"""Formats of ``learning_curve.<format>`` (``plot.format``)."""


def curve_file(cfg: DictConfig) -> str:
    """The learning curve's file name for ``plot.format`` (``learning_curve.png`` by default)."""
    return f"learning_curve.{cfg.get('plot', {}).get('format', 'png')}"


def plot_learning_curve(record: RunRecord, path: Path, *, title: str) -> None:
    """The learning curve (``learning_curve.<format>``): the greedy policy, evaluated exactly, as a
    fraction of the optimum's average reward against env steps. With several learners: their
    median, a band over the middle half (quartiles) and one over all of them (min–max)."""
    fig, ax = plt.subplots(figsize=(6.4, 4.0))
    curves = [record.curve(n) for n in range(record.num_learners)]
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
            label=f"min–max of {len(curves)} learners",
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
    ax.set_xlabel("env steps per learner", fontsize=11)
    ax.set_ylabel("average reward / optimum's (exact)", fontsize=11)
    ax.tick_params(labelsize=10)
    ax.set_title(title, fontsize=11)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=9, loc="lower right")
    fig.tight_layout()
    atomic_savefig(fig, path, dpi=200)


def degenerate_note(optimal: Metrics) -> str | None:
    """A line explaining an optimum that never communicates (throughput 0, every packet dropped),
    or None: with a large detection reward r4 (e.g. 50 at p^v_1 = 0.1) radar earns more in every
    state — the paper's degenerate case (docs/REPRODUCTION.md, claim 3)."""
    if optimal.radar_fraction < 1.0 - 1e-9:
        return None
    return (
        "note: at these weights the optimum never communicates (radar always: throughput 0, "
        "every packet dropped); a large detection reward r4 makes radar worth more in every "
        "state, the paper's degenerate case (docs/REPRODUCTION.md, claim 3)"
    )


END_THRESHOLD = 0.99
"""A run whose final greedy policy is below this share of the optimum ends with a warning."""

END_SLACK = 0.01
"""… as does one whose final policy is more than this below its own best evaluation."""


def end_warning(history: list[dict[str, Any]]) -> str | None:
    """One warning line when a learner's final greedy policy is below ``END_THRESHOLD`` of the
    optimum, or more than ``END_SLACK`` below its own best evaluation, saying where that best
    evaluation was; ``None`` when every learner ends well. The exact model only scores: the
    warning does not change which network the run returns."""
    runs: dict[int, list[dict[str, Any]]] = {}
    for e in history:
        runs.setdefault(int(e.get("learner", 0)), []).append(e)
    bad = []
    for learner, hist in sorted(runs.items()):
        final = float(hist[-1]["optimality_ratio"])
        best = max(hist, key=lambda e: float(e["optimality_ratio"]))
        gap = float(best["optimality_ratio"]) - final
        if final < END_THRESHOLD or gap > END_SLACK:
            why = [f"below {END_THRESHOLD}"] if final < END_THRESHOLD else []
            if gap > END_SLACK:
                why.append(f"{gap:.4f} below its best")
            bad.append(
                (
                    learner,
                    f"{final:.4f} of the optimum ({', '.join(why)}); its best evaluation "
                    f"was {float(best['optimality_ratio']):.4f} at {int(best['env_steps'])} env steps",
                )
            )
    if not bad:
        return None
    if len(runs) == 1:
        return f"warning: the final greedy policy is {bad[0][1]} (metrics.csv)"
    each = "; ".join(f"learner {i}: {text}" for i, text in bad)
    return f"warning: {len(bad)} of {len(runs)} learners end badly — {each} (metrics.csv)"
