"""The paper's claim, tested (``python recipes/study.py``): "Q-learning suffers the large state space
problem", so DQN. Each learner in ``learners`` (its own default profile, as ``recipes/<learner>.py``
runs it) trains on each scenario in ``scenarios`` with each seed; its greedy policy is scored
exactly against the scenario's optimum ``evals`` times over its budget (the dense model where it
fits, the factored one beyond: ``irdrc.core.exact.exact_scorer``).

Reported per run: the env steps and training seconds to 95 % and 99 % of the optimal average
reward (the first evaluation at or above), the final and best ratios. Training seconds leave out
the exact scoring, which on a 10⁵-state scenario costs far more than the training it scores;
scoring seconds are reported beside them.
"""

from __future__ import annotations

import statistics
import time
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING, Any

from irdrc.core.checks import (
    build,
    check_choice,
    check_list,
    check_number,
    grouped,
    reject_unknown_keys,
)
from irdrc.core.metrics import Metrics, first_reaching
from irdrc.recipes import solve
from irdrc.runs.compose import Composed, compose, compose_recipe
from irdrc.runs.grid import is_learner_key, is_scenario_key, override_key
from irdrc.runs.scenarios import list_scenarios
from irdrc.runs.sections import check_common, one_vehicle_scenarios
from irdrc.runs.sections import seeds as distinct_seeds

if TYPE_CHECKING:
    from irdrc.agents.base import RunRecord
    from irdrc.runs.scaffold import Run

NAME = "study"
LEARNERS = {
    "dqn": ("dqn", []),
    "dqn_plain": ("dqn", ["algo=dqn_plain"]),
    "qlearning": ("qlearning", []),
}
"""The learners the study compares: each one's recipe and profile (DQN with its reward table, the
default; plain DQN, without the table and the centering, DQN's update as the paper means it; and
tabular Q-learning's default)."""
THRESHOLDS = (0.95, 0.99)
"""Fractions of the optimal average reward whose first crossing is reported."""


@dataclass(frozen=True)
class Config:
    """The study's keys (``irdrc/conf/study.yaml``); ``planned``: each (learner, scenario)'s
    typed config, composed and checked at load."""

    scenarios: tuple[str, ...] = ("paper", "multilevel", "large")
    learners: tuple[str, ...] = tuple(LEARNERS)
    seeds: tuple[int, ...] = (100, 101, 102)
    evals: dict[str, Any] = field(default_factory=lambda: {"default": 40, "large": 10})
    overrides: dict[str, Any] = field(default_factory=dict)
    optimum_gamma: float = 0.99
    num_threads: int = 1
    device: str = "cpu"
    csv: str = "study.csv"
    planned: dict[tuple[str, str], Any] = field(default_factory=dict, metadata={"keys": ()})

    def __post_init__(self) -> None:
        check_common(self)
        known = list_scenarios()
        pick = lambda choices: lambda key, x: check_choice(key, x, choices)  # noqa: E731
        object.__setattr__(self, "scenarios", one_vehicle_scenarios("scenarios", self.scenarios))
        object.__setattr__(
            self, "learners", check_list("learners", self.learners, pick(LEARNERS), distinct=True)
        )
        seeds = distinct_seeds("seeds", self.seeds)
        object.__setattr__(self, "seeds", seeds)
        reject_unknown_keys("evals.", self.evals, ("default", *known))
        for key, n in self.evals.items():
            check_number(f"evals.{key}", n, 1, 10**6, integer=True)
        reject_unknown_keys("overrides.", self.overrides or {}, LEARNERS)
        for learner, extra in (self.overrides or {}).items():
            check_list(f"overrides.{learner}", extra or [], empty=True)

    def evals_of(self, scenario: str) -> int:
        """Exact evaluations per run on ``scenario``."""
        return int(self.evals.get(scenario, self.evals.get("default", 20)))


def load(composed: Composed, resume: dict[str, Any] | None = None) -> Config:
    """The typed config, checked; each learner's overrides composed on each scenario, so that a
    bad one is refused before any run (one that sets the scenario too: each learner runs each of
    ``scenarios`` as it is, and is scored against that scenario's optimum)."""
    cfg = build(Config, composed.cfg)
    for learner in cfg.overrides or {}:
        if learner not in cfg.learners:
            composed.refuse_unread(
                (f"overrides.{learner}",), f"{learner} is not among learners=[…]; add it there"
            )
    for scenario in cfg.evals:
        if scenario != "default" and scenario not in cfg.scenarios:
            composed.refuse_unread(
                (f"evals.{scenario}",), f"{scenario} is not among scenarios=[…]; add it there"
            )
    planned = {}
    for learner in cfg.learners:
        extra = [str(o) for o in (cfg.overrides or {}).get(learner) or []]
        for o in extra:
            if is_scenario_key(o) or override_key(o) == "env":
                raise ValueError(
                    f"overrides.{learner}: {o!r} sets the scenario; the study runs every learner "
                    f"on each of scenarios={list(cfg.scenarios)} as it is"
                )
            if not is_learner_key(o):
                raise ValueError(
                    f"overrides.{learner}: {o!r} is not read: a learner's overrides are its "
                    "algo.* and network.* keys; seeds, evals, num_threads and device are the "
                    "study's own"
                )
        for scenario in cfg.scenarios:
            planned[learner, scenario] = learner_config(learner, scenario, extra)
    return replace(cfg, planned=planned)


def learner_config(learner: str, scenario: str, overrides: list[str]) -> Any:
    """The typed config of ``learner``'s recipe on ``scenario`` with ``overrides``."""
    from irdrc.recipes import dqn, qlearning

    recipe, profile = LEARNERS[learner]
    module = {"dqn": dqn, "qlearning": qlearning}[recipe]
    return module.load(compose_recipe(module, [*profile, f"env={scenario}", *overrides]))


class TimedScorer:
    """A scorer that keeps the cumulative seconds spent scoring after each call, so that a
    learner's wall time (evaluations included) can be told apart from its training."""

    def __init__(self, inner: Any) -> None:
        self.inner = inner
        self.seconds = 0.0
        self.after: list[float] = []
        self.optimal_metrics = inner.optimal_metrics
        self.optimal = inner.optimal
        self.model = inner.model

    def metrics(self, table: Any) -> Metrics:
        """The inner scorer's metrics, timed."""
        t0 = time.perf_counter()
        m = self.inner.metrics(table)
        self.seconds += time.perf_counter() - t0
        self.after.append(self.seconds)
        return m


def train(
    learner: str, cfg: Any, n: int, seed: int, device: str, scorer: Any, evals: int
) -> RunRecord:
    """One run of ``learner`` (its recipe's typed config ``cfg``), ``evals`` exact evaluations
    evenly over its budget."""
    from irdrc.agents import dqn, qlearning

    if learner == "qlearning":
        budget = cfg.algo.episodes * cfg.params.env.horizon
        every = max(1, budget // evals)
        return qlearning.train(
            cfg.params,
            cfg.algo,
            num_learners=n,
            seed=seed,
            device=device,
            scorers=[scorer],
            eval_every_frames=every,
        )
    every = max(1, cfg.algo.total_frames // evals)
    return dqn.train(
        cfg.params, cfg.algo, seed=seed, device=device, scorer=scorer, eval_every_frames=every
    )


BATCHED = ("qlearning",)
"""Learners that train several independent learners in one batched run: the study's seeds become
learners 0 … n − 1 of one run seeded with the first seed (their seconds are the batch's)."""


def run_seeds(
    learner: str,
    scenario: str,
    seeds: list[int],
    scorer: Any,
    evals: int,
    cfg: Any,
    device: str = "cpu",
) -> list[dict[str, Any]]:
    """Train ``learner`` (its recipe's typed config ``cfg``) on ``scenario`` for each seed (one
    batched run for ``BATCHED`` learners); one row of ``study.csv`` per seed."""
    params = cfg.params
    runs = [(seeds[0], len(seeds))] if learner in BATCHED else [(s, 1) for s in seeds]
    rows = []
    for seed, n in runs:
        timed = TimedScorer(scorer)
        rec = train(learner, cfg, n, seed, device, timed, evals)
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
    return grouped(x, digits)


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


def run(cfg: Config, run: Run) -> int:
    """Every (scenario, learner, seed); ``study.csv``, ``study.md`` and ``summary.json``."""

    from irdrc.core.exact import exact_scorer
    from irdrc.runs.results import write_rows_csv, write_table_md

    run.threads(cfg.num_threads)
    t_start = time.perf_counter()
    rows: list[dict[str, Any]] = []
    optima: dict[str, dict[str, Any]] = {}
    for scenario in cfg.scenarios:
        params = solve.load(compose("solve", [f"env={scenario}"])).model
        t0 = time.perf_counter()
        scorer = exact_scorer(params, cfg.optimum_gamma)
        solve_s = time.perf_counter() - t0
        opt = scorer.optimal_metrics
        solver = type(scorer.model).__name__
        optima[scenario] = {
            "states": params.env.num_states,
            "solver": solver,
            "solve_seconds": round(solve_s, 2),
            "avg_reward": opt.avg_reward,
            "radar_fraction": opt.radar_fraction,
        }
        print(
            f"{scenario}: S = {params.env.num_states}, optimum {opt.avg_reward:.4f} reward/step "
            f"({solver}, {solve_s:.1f} s)",
            flush=True,
        )
        for learner in cfg.learners:
            got = run_seeds(
                learner,
                scenario,
                list(cfg.seeds),
                scorer,
                cfg.evals_of(scenario),
                cfg.planned[learner, scenario],
                cfg.device,
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
    write_rows_csv(run.dir / cfg.csv, rows)
    write_table_md(run.dir / "study.md", table, time.perf_counter() - t_start)
    summary = {
        "scenarios": optima,
        "learners": list(cfg.learners),
        "seeds": list(cfg.seeds),
        "wall_seconds": round(time.perf_counter() - t_start, 1),
    }
    print("\n" + table)
    run.finish(summary)
    return 0
