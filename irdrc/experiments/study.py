"""The paper's claim, tested (``python recipes/study.py``): "Q-learning suffers the large state space
problem", so DQN. Each learner in ``learners`` (its own default profile, as ``recipes/<learner>.py``
runs it) trains on each scenario in ``scenarios`` with each seed; its greedy policy is scored
exactly against the scenario's optimum ``evals`` times over its budget (the dense model where it
fits, the factored one beyond: ``irdrc.core.factored.exact_scorer``).

Reported per run: the env steps and training seconds to 95 % and 99 % of the optimal average
reward (the first evaluation at or above), the final and best ratios. Training seconds leave out
the exact scoring, which on a 10⁵-state scenario costs far more than the training it scores;
scoring seconds are reported beside them.
"""

from __future__ import annotations

import json
import logging
import statistics
import time
import warnings
from pathlib import Path
from typing import Any

import torch
from omegaconf import DictConfig

from irdrc.agents.base import Hooks
from irdrc.core.factored import exact_scorer
from irdrc.core.metrics import Metrics, first_reaching
from irdrc.core.params import Params
from irdrc.core.solve import ExactScorer
from irdrc.experiments.config import compose, list_scenarios
from irdrc.experiments.results import atomic_write_text, write_rows_csv, write_table_md
from irdrc.experiments.runs import LEARNERS

THRESHOLDS = (0.95, 0.99)
"""Fractions of the optimal average reward whose first crossing is reported."""


class TimedScorer:
    """An ``ExactScorer`` that keeps the cumulative seconds spent scoring after each call, so
    that a learner's wall time (evaluations included) can be told apart from its training."""

    def __init__(self, inner: ExactScorer) -> None:
        self.inner = inner
        self.seconds = 0.0
        self.after: list[float] = []

    @property
    def optimal_metrics(self) -> Metrics:
        """The optimum's exact metrics."""
        return self.inner.optimal_metrics

    @property
    def optimal(self):
        """The optimum (its ``policy``)."""
        return self.inner.optimal

    @property
    def model(self):
        """The exact model scored on."""
        return self.inner.model

    def metrics(self, table: torch.Tensor) -> Metrics:
        """The inner scorer's metrics, timed."""
        t0 = time.perf_counter()
        m = self.inner.metrics(table)
        self.seconds += time.perf_counter() - t0
        self.after.append(self.seconds)
        return m


def check_study(cfg: DictConfig) -> None:
    """Refuse a bad study before any work."""
    unknown = [str(x) for x in cfg.learners if str(x) not in LEARNERS]
    if unknown or not cfg.learners:
        raise ValueError(
            f"learners={list(cfg.learners)} must be a non-empty list of {', '.join(LEARNERS)}"
        )
    if not cfg.scenarios or not cfg.seeds:
        raise ValueError("scenarios and seeds must be non-empty lists")
    known = list_scenarios()
    bad = [str(s) for s in cfg.scenarios if str(s) not in known]
    if bad:
        raise ValueError(f"scenarios {bad} are not named scenarios ({', '.join(known)})")
    stray = [str(k) for k in cfg.evals if str(k) != "default" and str(k) not in known]
    if stray:
        raise ValueError(f"evals.{stray[0]}: not a named scenario ({', '.join(known)}) or default")
    for s in cfg.scenarios:
        if int(_evals(cfg, str(s))) < 1:
            raise ValueError(f"evals for {s} must be >= 1")
    for learner in cfg.get("overrides", {}) or {}:
        if learner not in LEARNERS:
            raise ValueError(f"overrides.{learner}: not a learner ({', '.join(LEARNERS)})")


def _evals(cfg: DictConfig, scenario: str) -> int:
    evals = cfg.evals
    return int(evals.get(scenario, evals.get("default", 20)))


BATCHED = ("qlearning",)
"""Learners that train several independent learners in one batched run: the study's seeds become
learners 0 … n − 1 of one run seeded with the first seed (their seconds are the batch's)."""


def run_seeds(
    learner: str,
    scenario: str,
    seeds: list[int],
    scorer: ExactScorer,
    evals: int,
    overrides: list[str],
    device: str = "cpu",
) -> list[dict[str, Any]]:
    """Train ``learner`` on ``scenario`` for each seed (one batched run for ``BATCHED`` learners);
    one row of ``study.csv`` per seed."""
    agent = LEARNERS[learner]
    node = compose(learner, [f"env={scenario}", *overrides])
    params = Params.from_config(node)
    config = agent.Config.from_node(node)
    budget = config.env_steps(params.env.horizon)
    runs = [(seeds[0], len(seeds))] if learner in BATCHED else [(s, 1) for s in seeds]
    rows = []
    for seed, n in runs:
        timed = TimedScorer(scorer)
        rec = agent.train(
            params,
            config,
            num_learners=n,
            seed=seed,
            device=device,
            scorers=[timed],
            eval_every_frames=max(1, budget // evals),
            hooks=Hooks(),
        )
        # every evaluation scores the n learners, then reads the clock
        done = timed.after[n - 1 :: n]
        for i in range(n):
            curve = rec.curve(i)
            if len(curve) != len(done):
                raise RuntimeError(f"{len(curve)} evaluations but {len(done)} scorings")
            for e, scored in zip(curve, done, strict=True):
                e["train_seconds"] = e["wall_seconds"] - scored
            row: dict[str, Any] = {
                "scenario": scenario,
                "states": params.env.num_states,
                "learner": learner,
                "seed": seed if n == 1 else seeds[i],
                "run_seed": seed,
                "learners_in_run": n,
                "budget_env_steps": curve[-1]["env_steps"],
                "evaluations": len(curve),
            }
            for th in THRESHOLDS:
                pct = round(th * 100)
                row[f"env_steps_to_{pct}"] = first_reaching(curve, th)
                secs = first_reaching(curve, th, at="train_seconds")
                row[f"train_seconds_to_{pct}"] = None if secs is None else round(secs, 2)
            row["final_ratio"] = curve[-1]["optimality_ratio"]
            row["best_ratio"] = max(e["optimality_ratio"] for e in curve)
            row["train_seconds"] = round(curve[-1]["train_seconds"], 2)
            row["scoring_seconds"] = round(timed.seconds / n, 2)
            rows.append(row)
    return rows


def _median(values: list[Any]) -> Any:
    got = [v for v in values if v is not None]
    return statistics.median(got) if got else None


def _n(x: Any, digits: int = 0) -> str:
    if x is None:
        return "—"
    return f"{x:,.{digits}f}".replace(",", " ")


def study_table(rows: list[dict[str, Any]]) -> str:
    """The markdown table of ``study.md``: per scenario and learner, medians over the seeds."""
    header = [
        "scenario (S)",
        "learner",
        "env steps (budget)",
        "reached 95 %",
        "median env steps / training s to 95 %",
        "reached 99 %",
        "median env steps / training s to 99 %",
        "final ratio: median (worst)",
        "scoring s (all seeds)",
    ]
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    keys = list(dict.fromkeys((r["scenario"], r["learner"]) for r in rows))
    for scenario, learner in keys:
        rs = [r for r in rows if r["scenario"] == scenario and r["learner"] == learner]
        cells = [
            f"{scenario} ({_n(rs[0]['states'])})",
            learner,
            _n(rs[0]["budget_env_steps"]),
        ]
        for pct in (95, 99):
            steps = [r[f"env_steps_to_{pct}"] for r in rs]
            secs = [r[f"train_seconds_to_{pct}"] for r in rs]
            reached = sum(s is not None for s in steps)
            cells.append(f"{reached}/{len(rs)}")
            cells.append("—" if not reached else f"{_n(_median(steps))} / {_n(_median(secs), 1)}")
        finals = [r["final_ratio"] for r in rs]
        cells.append(f"{statistics.median(finals):.3f} ({min(finals):.3f})")
        cells.append(_n(sum(r["scoring_seconds"] for r in rs), 0))  # per-learner shares
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def run_study(cfg: DictConfig, out: Path) -> int:
    """Every (scenario, learner, seed); ``study.csv``, ``study.md`` and ``summary.json`` in ``out``."""
    check_study(cfg)
    torch.set_num_threads(int(cfg.num_threads))
    logging.getLogger("torchrl").setLevel(logging.WARNING)
    warnings.filterwarnings("ignore", message="total_frames .* is not exactly divisible")
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    overrides = cfg.get("overrides", {}) or {}
    gamma = float(cfg.optimum_gamma)
    t_start = time.perf_counter()
    rows: list[dict[str, Any]] = []
    optima: dict[str, dict[str, Any]] = {}
    for scenario in map(str, cfg.scenarios):
        params = Params.from_config(compose("solve", [f"env={scenario}"]))
        t0 = time.perf_counter()
        scorer = exact_scorer(params, gamma)
        solve_s = time.perf_counter() - t0
        opt = scorer.optimal_metrics
        optima[scenario] = {
            "states": params.env.num_states,
            "solver": type(scorer).__name__,
            "solve_seconds": round(solve_s, 2),
            "avg_reward": opt.avg_reward,
            "radar_fraction": opt.radar_fraction,
        }
        print(
            f"{scenario}: S = {params.env.num_states}, optimum {opt.avg_reward:.4f} reward/step "
            f"({type(scorer).__name__}, {solve_s:.1f} s)",
            flush=True,
        )
        for learner in map(str, cfg.learners):
            got = run_seeds(
                learner,
                scenario,
                [int(x) for x in cfg.seeds],
                scorer,
                _evals(cfg, scenario),
                [str(o) for o in overrides.get(learner, [])],
                str(cfg.device),
            )
            rows += got
            for row in got:
                print(
                    f"  {learner:>9} seed {row['seed']}: 95 % at {row['env_steps_to_95']} steps, "
                    f"99 % at {row['env_steps_to_99']} steps; final {row['final_ratio']:.4f} "
                    f"(best {row['best_ratio']:.4f}); {row['train_seconds']:.1f} s training + "
                    f"{row['scoring_seconds']:.1f} s scoring",
                    flush=True,
                )
    table = study_table(rows)
    write_rows_csv(out / str(cfg.csv), rows)
    write_table_md(out / "study.md", table, time.perf_counter() - t_start)
    summary = {
        "scenarios": optima,
        "learners": [str(x) for x in cfg.learners],
        "seeds": [int(s) for s in cfg.seeds],
        "wall_seconds": round(time.perf_counter() - t_start, 1),
    }
    atomic_write_text(out / "summary.json", json.dumps(summary, indent=2) + "\n")
    print("\n" + table)
    print(f"\nwrote {out / str(cfg.csv)}, study.md, summary.json ({summary['wall_seconds']:.0f} s)")
    return 0
