"""``recipes/bench_online.py``: the learners on one stream over named scenarios × seeds no tuning used
and random contested scenarios nobody tuned them for, each run scored by the ledger; the safe
learner at each miss target beside the Lagrangian DQN's own training.

    python recipes/bench_online.py                                    # the whole benchmark
    python recipes/bench_online.py 'scenarios=[paper]' random_draws=0 'safe_targets=[]'
    python recipes/bench_online.py 'learners=[posterior]' 'seeds=[10,11]'

Per learner and scenario: the runs whose greedy policy reaches 0.99 of the optimum within
``window`` episodes, episodes to 0.95 / 0.99, the share of later evaluations at or above 0.99, the
regret and the expected missed events over the first ``window`` episodes beside the optimum's own
(the floor), and the speed. Every run is a process of its own (``workers`` at a time); a run's
result is kept in ``runs/`` as it finishes, and ``resume=true`` into the same directory runs only
the rest.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from irdrc.bench.online_jobs import Job, execute, scenario_params
from irdrc.bench.online_tables import (
    calibration_note,
    lagrangian_row,
    learner_table,
    run_row,
    safe_table,
)
from irdrc.bench.random_scenarios import REPORTING, Draw, contested_draws
from irdrc.core.checks import (
    INT,
    build,
    check_bool,
    check_list,
    check_numbers,
    counted,
    numbers,
)
from irdrc.online.configs import LEARNERS, PROFILES, SAFE_LEARNERS
from irdrc.runs.compose import Composed
from irdrc.runs.grid import require_runs
from irdrc.runs.sections import one_vehicle_scenarios, seeds

if TYPE_CHECKING:
    from irdrc.runs.scaffold import Run

NAME = "bench_online"


def _names(key: str, value: Any, allowed: list[str], empty: bool = False) -> tuple[str, ...]:
    out = check_list(key, value, empty=empty, distinct=True)
    for name in out:
        if name not in allowed:
            own = (
                "; a learner of your own runs beside them in a sweep: recipes/sweep.py "
                "method=online 'sweep.grid={learner: [posterior, PATH.py:Class], seed: [0,1,2]}'"
                if ":" in str(name)
                else ""
            )
            raise ValueError(f"{key}: {name!r} must be one of {', '.join(allowed)}{own}")
    return out


@dataclass(frozen=True)
class Config:
    """The benchmark's keys (``irdrc/conf/bench_online.yaml``)."""

    scenarios: tuple[str, ...] = ("paper", "multilevel", "imperfect_radar")
    seeds: tuple[int, ...] = tuple(range(10, 20))
    learners: tuple[str, ...] = ("posterior", "dqn")
    paper_learners: tuple[str, ...] = ("qlearning", "qlearning_paper")
    paper_seeds: tuple[int, ...] = tuple(range(10, 20))
    random_draws: int = 10
    first_draw: int = REPORTING
    random_seed: int = 10
    random_learners: tuple[str, ...] = ("posterior", "dqn")
    episodes: int = 200
    window: int = 170
    safe_targets: tuple[float, ...] = (0.05, 0.1)
    safe_learners: tuple[str, ...] = ("safe",)
    safe_scenarios: tuple[str, ...] = ("paper", "multilevel", "persistent")
    safe_seeds: tuple[int, ...] = (10, 11, 12)
    lagrangian_seeds: tuple[int, ...] = (10,)
    workers: int = 2
    resume: bool = False
    optimum_gamma: float = 0.99

    def __post_init__(self) -> None:
        learners = [n for n in LEARNERS if n not in SAFE_LEARNERS]
        scenarios = one_vehicle_scenarios("scenarios", self.scenarios, empty=True)
        object.__setattr__(self, "scenarios", scenarios)
        object.__setattr__(self, "seeds", seeds("seeds", self.seeds))
        object.__setattr__(self, "paper_seeds", seeds("paper_seeds", self.paper_seeds))
        object.__setattr__(self, "safe_seeds", seeds("safe_seeds", self.safe_seeds))
        for key in ("learners", "paper_learners", "random_learners"):
            object.__setattr__(self, key, _names(key, getattr(self, key), learners, True))
        safe = _names("safe_learners", self.safe_learners, list(SAFE_LEARNERS))
        object.__setattr__(self, "safe_learners", safe)
        object.__setattr__(
            self,
            "safe_scenarios",
            one_vehicle_scenarios("safe_scenarios", self.safe_scenarios, True),
        )
        targets = check_list(
            "safe_targets",
            self.safe_targets,
            numbers(0, 1, open_lo=True, open_hi=True),
            empty=True,
            distinct=True,
        )
        object.__setattr__(self, "safe_targets", targets)
        check_numbers(
            self,
            "",
            (
                ("random_draws", 0, 10_000, INT),
                ("first_draw", 0, 10**9, INT),
                ("random_seed", 0, 2**32 - 1, INT),
                ("episodes", 1, 10**6, INT),
                ("window", 1, 10**6, INT),
                ("workers", 1, 1024, INT),
                ("optimum_gamma", 0, 1, {"open_hi": True}),
            ),
        )
        object.__setattr__(
            self,
            "lagrangian_seeds",
            seeds("lagrangian_seeds", self.lagrangian_seeds, empty=True),
        )
        check_bool("resume", self.resume)
        if self.window > self.episodes:
            raise ValueError(f"window={self.window} must be <= episodes={self.episodes}")
        random = self.random_draws if self.random_learners else 0
        require_runs(
            len(plan(self, [])) + random,
            "scenarios × learners × seeds; paper_learners × paper_seeds with paper among the "
            "scenarios; random_draws × random_learners; safe_targets × safe_scenarios × "
            "(safe_seeds, lagrangian_seeds)",
        )


def load(composed: Composed, resume: dict[str, Any] | None = None) -> Config:
    """The typed config, checked; a key of a part of the benchmark that does not run is refused."""
    cfg = build(Config, composed.cfg)
    if "paper" not in cfg.scenarios:
        composed.refuse_unread(
            ("paper_learners", "paper_seeds"), "their runs are on paper, which scenarios leaves out"
        )
    if not cfg.random_draws or not cfg.random_learners:
        off = "random_draws=0" if not cfg.random_draws else "random_learners=[]"
        composed.refuse_unread(
            [k for k in ("random_draws", "random_learners") if not off.startswith(k)]
            + ["first_draw", "random_seed"],
            f"no random draw runs ({off})",
        )
    if not cfg.safe_targets:
        composed.refuse_unread(
            ("safe_learners", "safe_scenarios", "safe_seeds", "lagrangian_seeds"),
            "no safe learner runs (safe_targets=[])",
        )
    return cfg


def plan(cfg: Config, draws: list[Draw]) -> list[Job]:
    """Every run of the benchmark."""
    jobs = []
    for scenario in cfg.scenarios:
        jobs += [Job(n, scenario, s, cfg.episodes) for n in cfg.learners for s in cfg.seeds]
        if scenario == "paper":
            jobs += [
                Job(n, scenario, s, cfg.episodes)
                for n in cfg.paper_learners
                for s in cfg.paper_seeds
            ]
    for d in draws:
        jobs += [
            Job(n, f"draw {d.index}", cfg.random_seed, cfg.episodes, overrides=d.overrides)
            for n in cfg.random_learners
        ]
    # the safe learner's runs stop at the window (its figures are read there)
    for target in cfg.safe_targets:
        for scenario in cfg.safe_scenarios:
            jobs += [
                Job(n, scenario, s, cfg.window, target)
                for n in cfg.safe_learners
                for s in cfg.safe_seeds
            ]
            jobs += [
                Job("dqn_lagrangian", scenario, s, cfg.window, target) for s in cfg.lagrangian_seeds
            ]
    return jobs


def run(cfg: Config, run: Run) -> int:
    """Every run, then ``bench_online.csv`` (a row per run), ``bench_online.md`` (the tables) and
    ``bench_online.png`` (each named scenario's learners against episodes)."""
    from irdrc.online.figures import plot_learners
    from irdrc.runs.results import write_rows_csv, write_table_md

    start = time.perf_counter()
    draws = (
        contested_draws(cfg.first_draw, cfg.random_draws, cfg.optimum_gamma)
        if cfg.random_draws
        else []
    )
    jobs = plan(cfg, draws)
    print(
        f"bench_online: {counted(len(jobs), 'run')}, {cfg.workers} at a time, into {run.dir}",
        flush=True,
    )
    results, kept = execute(
        jobs, Path(run.dir), workers=cfg.workers, resume=cfg.resume, gamma=cfg.optimum_gamma
    )
    rows, safe, lag = [], [], []
    for job in jobs:
        result = results[job.name]
        if job.learner == "dqn_lagrangian":
            lag.append(lagrangian_row(job, result, scenario_params(job).env.horizon))
        elif job.learner in SAFE_LEARNERS:
            safe.append(run_row(job, result, cfg.window))
        else:
            rows.append(run_row(job, result, cfg.window))
    every = rows + safe + lag
    fields = list(dict.fromkeys(k for r in every for k in r))
    write_rows_csv(run.dir / "bench_online.csv", every, fields)
    parts = []
    if rows:
        parts.append(learner_table(rows, cfg.window))
        parts.append(
            f"{counted(len(cfg.seeds), 'seed')} per named scenario ({', '.join(map(str, cfg.seeds))}"
            + (
                f"; {', '.join(cfg.paper_learners)}: {', '.join(map(str, cfg.paper_seeds))}"
                if cfg.paper_learners and "paper" in cfg.scenarios
                else ""
            )
            + "); "
            + (
                f"{len(draws)} contested random draws ({draws[0].index}–{draws[-1].index}), seed "
                f"{cfg.random_seed}; "
                if draws
                else ""
            )
            + f"{counted(cfg.episodes, 'episode')} per run; medians over runs, worst in brackets. Regret and "
            "missed events are the exact ledger's (the behaviour policy of each episode)."
        )
    if safe:
        parts.append(safe_table(safe, lag, cfg.window))
        if note := calibration_note(safe):
            parts.append(note)
    table = "\n\n".join(parts)
    print("\n" + table)
    write_table_md(run.dir / "bench_online.md", table, time.perf_counter() - start, kept)
    for scenario in cfg.scenarios:
        histories = {
            n: [
                results[j.name]["history"]
                for j in jobs
                if j.learner == n and j.scenario == scenario
            ]
            for n in dict.fromkeys(
                j.learner
                for j in jobs
                if j.scenario == scenario
                and j.learner in PROFILES
                and j.learner not in SAFE_LEARNERS
            )
        }
        plot_learners(
            histories, run.dir / f"bench_online_{scenario}.png", f"one stream, {scenario}"
        )
    run.finish(None)
    return 0
