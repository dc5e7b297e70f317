"""``recipes/bench_timeshare.py``: every learner of the radar share (MODEL.md § D) over scenarios ×
seeds no tuning used, through the sweep engine, each run scored exactly against the optimum over
ρ ∈ [0, 1] — SAC and PPO on the continuum, DQN over G levels (also against its own G-level
optimum) — how many runs hold, how soon, and how fast they train.

    python recipes/bench_timeshare.py                                 # 3 learners × 5 scenarios × 5 seeds
    python recipes/bench_timeshare.py 'learners=[sac]' 'seeds=[5]'
    python recipes/bench_timeshare.py executor=local 'scenarios={p0.1: [env.p1.speed=0.1]}'
    python recipes/bench_timeshare.py scenarios=random 'learners=[sac]'   # 50 random draws × seed 5

With ``scenarios=random`` the scenarios are time-sharing draws of every model key, κ, the sensing
curve and the levels, kept where the optimum over ρ earns ≥ 1.02 × the binary optimum
(``irdrc.bench.random_scenarios.share_draws``).
"""

from __future__ import annotations

import json
import statistics
import sys
import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

from irdrc.bench.random_scenarios import ShareDraw, command_line
from irdrc.core.checks import INT, build, check_choice, check_list, check_numbers, grouped
from irdrc.runs.compose import Composed
from irdrc.runs.grid import candidate_overrides, parse_grid
from irdrc.runs.results import md_table
from irdrc.runs.sections import EXECUTOR, Executor, check_common, seeds

if TYPE_CHECKING:
    from irdrc.runs.scaffold import Run

NAME = "bench_timeshare"

LEARNERS = {
    "sac": ("sac", []),
    "ppo": ("ppo", []),
    "dqn_levels": ("dqn", ["algo=dqn_levels", "env.actions=levels", "eval.mc_episodes=0"]),
}
"""Each learner's recipe and the overrides that make it a learner of shares."""

SCENARIOS = {
    "paper p1=0.1": ["env.p1.speed=0.1"],
    "paper p1=0.5": ["env.p1.speed=0.5"],
    "paper p1=1.0": ["env.p1.speed=1.0"],
    "multilevel": ["env=multilevel"],
    "imperfect_radar": ["env=imperfect_radar", "reward=imperfect_radar"],
}
"""The default scenarios (``scenarios``): the paper at three p^v_1, and two extensions."""

THRESHOLDS = (0.95, 0.99)
"""Where the table reports env steps and seconds to (of the optimum over ρ)."""


@dataclass(frozen=True)
class Config:
    """The benchmark's keys (``irdrc/conf/bench_timeshare.yaml``); ``planned``: every run, checked
    (``irdrc.sweeps.trials.plan``), and ``owner``: each run's (learner, scenario)."""

    learners: tuple[str, ...] = tuple(LEARNERS)
    scenarios: dict[str, Any] | str | None = None  # or "random"
    seeds: tuple[int, ...] | None = None
    draws: int = 50
    first_draw: int = 0
    overrides: tuple[str, ...] = ()
    threshold: float = 0.99
    optimum_gamma: float = 0.99
    csv: str = "bench_timeshare.csv"
    executor: Executor = field(default_factory=Executor, metadata=EXECUTOR)
    planned: tuple[Any, ...] = field(default=(), metadata={"keys": ()})
    owner: dict[str, Any] = field(default_factory=dict, metadata={"keys": ()})
    drawn: dict[str, Any] = field(default_factory=dict, metadata={"keys": ()})

    def __post_init__(self) -> None:
        check_common(self)
        item = lambda key, v: check_choice(key, v, tuple(LEARNERS))  # noqa: E731
        object.__setattr__(
            self, "learners", check_list("learners", self.learners, item, distinct=True)
        )
        default = (5,) if self.random else (5, 6, 7, 8, 9)
        object.__setattr__(
            self, "seeds", seeds("seeds", default if self.seeds is None else self.seeds)
        )
        object.__setattr__(self, "overrides", check_list("overrides", self.overrides, empty=True))
        check_numbers(self, "", (("draws", 1, 100_000, INT), ("first_draw", 0, 10**9, INT)))
        if isinstance(self.scenarios, str) and not self.random:
            raise ValueError(
                f"scenarios={self.scenarios}: give random or a mapping {{name: [overrides]}}"
            )

    @property
    def random(self) -> bool:
        """Whether the scenarios are random time-sharing draws (``scenarios=random``)."""
        return self.scenarios == "random"

    @property
    def scenario_overrides(self) -> dict[str, list[str]]:
        """Scenario name → its overrides (``SCENARIOS`` when ``scenarios`` is unset; the draws
        found by ``load`` with ``scenarios=random``)."""
        if self.random:
            return dict(self.drawn)
        return candidate_overrides(
            SCENARIOS if self.scenarios is None else self.scenarios, "scenarios"
        )


def load(composed: Composed, resume: dict[str, Any] | None = None) -> Config:
    """The typed config; every run composed and checked before any trial."""
    from irdrc.recipes import dqn
    from irdrc.recipes.shares import ppo, sac
    from irdrc.sweeps.trials import plan

    cfg = build(Config, composed.cfg)
    composed.refuse_overwritten(
        {"seed": "set seeds=[…]"},
        cfg.overrides,
        fixed=("optimum_gamma", "checkpoint.every_frames"),
    )
    if cfg.random:  # each draw a pure function of its index: a resumed run finds the same ones
        drawn = {f"draw {d.index}": command_line(d.overrides) for d in random_draws(cfg)}
        cfg = replace(cfg, drawn=drawn)
    else:
        composed.refuse_unread(("draws", "first_draw"), "the random draws need scenarios=random")
    base = [*cfg.overrides, f"optimum_gamma={cfg.optimum_gamma}", "checkpoint.every_frames=0"]
    planned, owner = [], {}
    for learner in cfg.learners:
        method, extra = LEARNERS[learner]
        module = {"sac": sac, "ppo": ppo, "dqn": dqn}[method]
        for scenario, scen in cfg.scenario_overrides.items():
            for p in plan(module, parse_grid({"seed": list(cfg.seeds)}), [*scen, *extra, *base]):
                planned.append(p)
                owner[p["point_id"]] = (learner, scenario)
    return replace(cfg, planned=tuple(planned), owner=owner)


def random_draws(cfg: Config) -> list[ShareDraw]:
    """The ``draws`` kept time-sharing draws from ``first_draw`` up, with a line as they are found."""
    from irdrc.bench.random_scenarios import share_draws

    def say(kept: int, tried: int) -> None:
        if kept == cfg.draws or tried % 50 == 0:
            print(f"random scenarios: {kept}/{cfg.draws} kept of {tried} drawn", file=sys.stderr)

    return share_draws(cfg.first_draw, cfg.draws, cfg.optimum_gamma, say)


def run(cfg: Config, run: Run) -> int:
    """Every (learner, scenario, seed) as one run; writes ``bench_timeshare.csv`` (a row per run)
    and ``bench_timeshare.md`` (the table)."""
    from irdrc.runs.results import read_csv_rows, write_rows_csv, write_table_md
    from irdrc.sweeps.trials import execute, kept_points

    start = time.perf_counter()
    out, planned = run.dir, list(cfg.planned)
    kept = kept_points(cfg.executor, planned, out)
    code = execute(cfg.executor, planned, out, run.recipe)
    rows = []
    for p in planned:
        tdir = Path(out) / "trials" / p["point_id"]
        if (tdir / "summary.json").is_file():
            learner, scenario = cfg.owner[p["point_id"]]
            hist = read_csv_rows(tdir / "metrics.csv")
            rows.append(run_row(learner, scenario, p["point"]["seed"], tdir, hist, cfg.threshold))
    write_rows_csv(out / cfg.csv, rows)
    table = timeshare_table(rows, list(cfg.learners), list(cfg.scenario_overrides), cfg.threshold)
    if cfg.random:
        table = random_summary(rows, cfg) + "\n\n" + table
    print("\n" + table)
    write_table_md(out / "bench_timeshare.md", table, time.perf_counter() - start, kept)
    run.finish(None)
    return code


def random_summary(rows: list[dict[str, Any]], cfg: Config) -> str:
    """Per learner over the random draws: runs at or above the threshold, the worst run, and the
    median env steps to it."""
    th, lines = cfg.threshold, []
    for learner in cfg.learners:
        mine = [r for r in rows if r["learner"] == learner]
        if not mine:
            continue
        worst = min(mine, key=lambda r: r["final_ratio"])
        reached = [r[f"env_steps_to_{th:g}"] for r in mine if r.get(f"env_steps_to_{th:g}")]
        median = grouped(statistics.median(reached)) if reached else "—"
        lines.append(
            f"- **{learner}**: {sum(r['holds'] for r in mine)} of {len(mine)} runs ≥ {th:g} of the "
            f"optimum over ρ; worst {worst['final_ratio']:.4f} ({worst['scenario']}, seed "
            f"{worst['seed']}); median env steps to {th:g}: {median}"
        )
    first, last = cfg.first_draw, max(int(k.split()[-1]) for k in cfg.drawn)
    return (
        f"{len(cfg.drawn)} random time-sharing scenarios (draws {first}–{last} of "
        "`irdrc.bench.random_scenarios.share_draws`: every model key, κ, the sensing curve and the "
        "levels, kept where the optimum over ρ earns ≥ 1.02 × the binary optimum) × seeds "
        f"{', '.join(map(str, cfg.seeds or ()))}:\n\n" + "\n".join(lines)
    )


def run_row(
    learner: str, scenario: str, seed: int, tdir: Path, hist: list[dict[str, Any]], th: float
) -> dict[str, Any]:
    """One run: its final ratio to the optimum over ρ (and, over levels, to its own optimum), env
    steps and seconds to each of ``THRESHOLDS`` of the optimum over ρ, and its training speed (env
    steps per second of collecting and learning, the exact evaluations left out)."""
    s = json.loads((tdir / "summary.json").read_text())
    continuum = s.get("continuum", {}).get("optimal_avg_reward", s["optimal"]["avg_reward"])
    ratios = [float(r["avg_reward"]) / continuum for r in hist]

    def first(at: str, level: float) -> Any:
        i = next((i for i, r in enumerate(ratios) if r >= level), None)
        return None if i is None else float(hist[i][at])

    training = sum(s.get(f"seconds_{k}", 0.0) for k in ("collect", "store", "learn"))
    row = {
        "learner": learner,
        "scenario": scenario,
        "seed": int(seed),
        "final_ratio": s["metrics"]["avg_reward"] / continuum,
        "own_ratio": s["optimality_ratio"],
        "holds": s["metrics"]["avg_reward"] / continuum >= th,
        "env_steps": int(s["env_steps"]),
        "wall_seconds": float(s["wall_seconds"]),
        "env_steps_per_s": int(s["env_steps"]) / training if training > 0 else None,
    }
    for level in THRESHOLDS:
        row[f"env_steps_to_{level:g}"] = first("env_steps", level)
        row[f"seconds_to_{level:g}"] = first("wall_seconds", level)
    return row


def timeshare_table(
    rows: list[dict[str, Any]], learners: list[str], scenarios: list[str], th: float
) -> str:
    """The benchmark as Markdown: one row per (learner, scenario), medians over its seeds (steps
    and seconds to a threshold over the runs that reached it)."""

    def med(values: list[float], fmt: str = ",.0f") -> str:
        values = [v for v in values if v is not None]
        return format(statistics.median(values), fmt).replace(",", " ") if values else "—"

    body = []
    for learner in learners:
        for scenario in scenarios:
            mine = [r for r in rows if r["learner"] == learner and r["scenario"] == scenario]
            if not mine:
                continue
            mine.sort(key=lambda r: r["seed"])
            cells = [
                learner,
                scenario,
                f"{sum(r['holds'] for r in mine)}/{len(mine)}",
                ", ".join(f"{r['final_ratio']:.4f}" for r in mine),
                f"{min(r['final_ratio'] for r in mine):.4f}",
            ]
            if learner == "dqn_levels":
                own = sum(r["own_ratio"] >= th for r in mine)
                cells.append(f"{own}/{len(mine)} (worst {min(r['own_ratio'] for r in mine):.4f})")
            else:
                cells.append("—")
            for level in THRESHOLDS:
                reached = [r[f"env_steps_to_{level:g}"] for r in mine]
                cells.append(
                    f"{med(reached)} ({med([r[f'seconds_to_{level:g}'] for r in mine], '.0f')} s)"
                    f" {sum(x is not None for x in reached)}/{len(mine)}"
                )
            cells.append(med([r["env_steps_per_s"] for r in mine]))
            cells.append(med([r["wall_seconds"] for r in mine], ".0f"))
            body.append(cells)
    seeds = sorted({r["seed"] for r in rows})
    header = [
        "learner",
        "scenario",
        f"runs ≥ {th:g} of the optimum over ρ",
        f"final ratio per seed {', '.join(map(str, seeds))}",
        "worst",
        f"≥ {th:g} of its own G-level optimum",
        *(f"median env steps (s) to {t:.0%}, runs reaching it" for t in THRESHOLDS),
        "env steps/s of training (median)",
        "median s per run",
    ]
    return (
        md_table(header, body)
        + "\n\nRatios are exact long-run average rewards over the optimum over ρ ∈ [0, 1] of the "
        "same scenario (DQN over levels: its 5-level optimum is below it). Env steps/s count "
        "collecting and learning, not the exact evaluations."
    )
