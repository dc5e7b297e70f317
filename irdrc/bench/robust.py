"""``recipes/bench_robust.py``: DQN over many unseen seeds × scenarios through the sweep engine,
every final greedy policy scored exactly against its own optimum — how many runs hold, and why the
others fail (where their policy differs from the optimum). The scenarios are the named grid
(p^v_1 × r4 of a scenario file) or, with ``scenarios=random``, contested scenarios drawn at random
from every model key (``irdrc.bench.random_scenarios``).

    python recipes/bench_robust.py                                   # 20 seeds × 6 scenarios
    python recipes/bench_robust.py env=multilevel 'p1_speed=[0.1]'
    python recipes/bench_robust.py scenarios=random                  # 100 random draws × 1 seed
    python recipes/bench_robust.py 'candidates={dqn: [], small: [network=small]}'
"""

from __future__ import annotations

import json
import statistics
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from irdrc.bench.random_scenarios import REPORTING, Draw, command_line, contested_draws
from irdrc.core.checks import (
    INT,
    build,
    check_choice,
    check_list,
    check_number,
    check_numbers,
    counted,
    grouped,
    numbers,
)
from irdrc.runs.compose import Composed
from irdrc.runs.grid import candidate_overrides, override_key, parse_grid
from irdrc.runs.results import md_table
from irdrc.runs.sections import EXECUTOR, Eval, Executor, check_common, seeds

if TYPE_CHECKING:
    from irdrc.runs.scaffold import Run

NAME = "bench_robust"

SCENARIO_SETS = ("grid", "random")
"""``scenarios``: the named grid (p^v_1 × r4), or contested draws of every model key."""


@dataclass(frozen=True)
class Config:
    """The benchmark's keys (``irdrc/conf/bench_robust.yaml``); ``planned``: every run, checked
    (``irdrc.sweeps.trials.plan``), and ``owner``: each run's candidate."""

    scenarios: str = "grid"
    seeds: tuple[int, ...] | None = None
    p1_speed: tuple[float, ...] = (0.1, 0.5, 1.0)
    r4: tuple[float, ...] = (5.0, 50.0)
    draws: int = 100
    first_draw: int = REPORTING
    candidates: dict[str, Any] | None = None
    overrides: tuple[str, ...] = ()
    eval: Eval = field(default_factory=Eval)
    threshold: float = 0.99
    optimum_gamma: float = 0.99
    csv: str = "bench_robust.csv"
    executor: Executor = field(default_factory=Executor, metadata=EXECUTOR)
    env: Any = None
    reward: Any = None
    planned: tuple[Any, ...] = field(default=(), metadata={"keys": ()})
    owner: dict[str, Any] = field(default_factory=dict, metadata={"keys": ()})

    def __post_init__(self) -> None:
        check_common(self)
        check_choice("scenarios", self.scenarios, SCENARIO_SETS)
        default = tuple(range(5, 25)) if self.scenarios == "grid" else (5,)
        object.__setattr__(
            self, "seeds", seeds("seeds", default if self.seeds is None else self.seeds)
        )
        check_numbers(self, "", (("draws", 1, 100_000, INT), ("first_draw", 0, 10**9, INT)))
        object.__setattr__(
            self, "p1_speed", check_list("p1_speed", self.p1_speed, numbers(0, 1), distinct=True)
        )
        object.__setattr__(self, "r4", check_list("r4", self.r4, numbers(0, 1e9), distinct=True))
        object.__setattr__(self, "overrides", check_list("overrides", self.overrides, empty=True))
        th = check_number("threshold", self.threshold, 0, 1, open_lo=True)
        object.__setattr__(self, "threshold", th)

    @property
    def grid(self) -> dict[str, list[Any]]:
        """The grid every candidate runs: p^v_1 × r4 × seed (with random draws: seed)."""
        if self.scenarios == "random":
            return {"seed": list(self.seeds or ())}
        return {
            "env.p1.speed": list(self.p1_speed),
            "reward.r4": list(self.r4),
            "seed": list(self.seeds or ()),
        }


def load(composed: Composed, resume: dict[str, Any] | None = None) -> Config:
    """The typed config; every run of every candidate composed and checked before any trial."""
    from dataclasses import replace

    from irdrc.recipes import dqn
    from irdrc.sweeps.trials import plan

    cfg = build(Config, composed.cfg)
    if cfg.scenarios == "random":
        composed.refuse_unread(("p1_speed", "r4"), "scenarios=random draws every model key")
    else:
        composed.refuse_unread(("draws", "first_draw"), "the random draws need scenarios=random")
    base = [
        *composed.scenario_overrides,
        *cfg.overrides,
        "eval.mc_episodes=0",
        f"eval.every_frames={cfg.eval.every_frames}",
        f"optimum_gamma={cfg.optimum_gamma}",
        "checkpoint.every_frames=0",
    ]
    planned, owner = [], {}
    draws = random_draws(cfg) if cfg.scenarios == "random" else [None]
    drawn = {override_key(o) for d in draws if d is not None for o in command_line(d.overrides)}
    grid_axes = {"seed": "set seeds=[…]"}
    if draws == [None]:
        grid_axes |= {"env.p1.speed": "set p1_speed=[…]", "reward.r4": "set r4=[…]"}
    candidates = [o for extra in candidate_overrides(cfg.candidates).values() for o in extra]
    composed.refuse_overwritten(  # a candidate's own key wins over a draw's; the grid's over both
        {**dict.fromkeys(sorted(drawn), "scenarios=random draws it"), **grid_axes},
        cfg.overrides,
        fixed=("optimum_gamma", "eval.mc_episodes", "eval.every_frames", "checkpoint.every_frames"),
    )
    composed.refuse_overwritten(grid_axes, candidates)
    for name, extra in candidate_overrides(cfg.candidates).items():
        for draw in draws:
            scenario = [] if draw is None else command_line(draw.overrides)
            for p in plan(dqn, parse_grid(cfg.grid), [*base, *scenario, *extra]):
                # what names the run in summary.csv, its progress line and its status.json
                named = {"candidate": name, **({} if draw is None else {"draw": draw.index})}
                p["point"] = {**named, **p["point"]}
                planned.append(p)
                owner[p["point_id"]] = name
    return replace(cfg, planned=tuple(planned), owner=owner)


def random_draws(cfg: Config) -> list[Draw]:
    """The ``draws`` contested draws from ``first_draw`` up, with a line as they are found."""
    import sys

    def say(kept: int, tried: int) -> None:
        if kept == cfg.draws or tried % 50 == 0:
            print(
                f"random scenarios: {kept}/{cfg.draws} contested of {tried} drawn", file=sys.stderr
            )

    return contested_draws(cfg.first_draw, cfg.draws, cfg.optimum_gamma, say)


def run(cfg: Config, run: Run) -> int:
    """Every (candidate, scenario, seed) as one DQN run through the sweep engine; per run and per
    (candidate, scenario): the final ratio, env steps and seconds to the threshold, and the share of
    evaluations after first reaching it that stay there. Writes ``bench_robust.csv`` (a row per
    run) and ``bench_robust.md`` (the table, then every run that does not hold, with the states
    where it differs from the optimum)."""
    from irdrc.core.exact import Scorer, build_model
    from irdrc.runs.results import read_csv_rows, write_rows_csv, write_table_md
    from irdrc.runs.tables import policy_differences, read_policy_csv
    from irdrc.sweeps.trials import execute, kept_points

    start = time.perf_counter()
    out, th, planned = run.dir, cfg.threshold, list(cfg.planned)
    kept = kept_points(cfg.executor, planned, out)
    code = execute(cfg.executor, planned, out, run.recipe)
    rows = []
    for p in planned:
        tdir = Path(out) / "trials" / p["point_id"]
        if (tdir / "summary.json").is_file():
            rows.append(run_row(cfg, p, tdir, read_csv_rows(tdir / "metrics.csv")))
    write_rows_csv(out / cfg.csv, rows)
    candidates = candidate_overrides(cfg.candidates)
    scenarios = (
        [{}]
        if cfg.scenarios == "random"
        else parse_grid({k: v for k, v in cfg.grid.items() if k != "seed"})
    )
    table = robust_table(rows, candidates, scenarios, th, len(cfg.seeds or ()))
    if cfg.scenarios == "random":
        last = max((r["draw"] for r in rows), default=cfg.first_draw)
        table += (
            f"\n\n{cfg.draws} contested scenarios drawn at random (draws {cfg.first_draw}–{last}"
            " of `irdrc.bench.random_scenarios`; a run's draw is in bench_robust.csv)."
        )
    print("\n" + table)
    failures = []
    for row in (r for r in rows if not r["holds"]):
        p = next(q for q in planned if q["point_id"] == row["point_id"])
        model = build_model(p["config"].params)
        learned = read_policy_csv(Path(out) / "trials" / p["point_id"] / "policy.csv")
        optimum = Scorer(model, cfg.optimum_gamma).optimal.policy
        label = " ".join(f"{k}={v}" for k, v in p["point"].items() if k != "candidate")
        text = f"{row['candidate']} {label}: final {row['final_ratio']:.4f}; "
        failures.append(text + policy_differences(model, learned, optimum))
        print("\n" + failures[-1])
    if failures:
        table += (
            "\n\nRuns that do not hold, and where their final policy differs:\n\n"
            + "\n\n".join("```\n" + f + "\n```" for f in failures)
        )
    write_table_md(out / "bench_robust.md", table, time.perf_counter() - start, kept)
    run.finish(None)
    return code


def run_row(
    cfg: Config, p: dict[str, Any], tdir: Path, hist: list[dict[str, Any]]
) -> dict[str, Any]:
    """One run of the benchmark: its final ratio, when it first reached the threshold, and how
    many later evaluations stayed there."""
    th = cfg.threshold
    summary = json.loads((tdir / "summary.json").read_text())
    ratios = [float(r["optimality_ratio"]) for r in hist]
    first = next((i for i, r in enumerate(ratios) if r >= th), None)
    later = ratios[first + 1 :] if first is not None else []
    final = float(summary["optimality_ratio"])
    return {
        "candidate": cfg.owner[p["point_id"]],
        **dict(p["point"].items()),
        "final_ratio": final,
        "holds": final >= th,
        "env_steps_to_threshold": int(hist[first]["env_steps"]) if first is not None else None,
        "seconds_to_threshold": float(hist[first]["wall_seconds"]) if first is not None else None,
        "later_evals_at_threshold": sum(r >= th for r in later) / len(later) if later else None,
        "later_evals": len(later),
        "later_evals_ok": sum(r >= th for r in later),
        "env_steps": int(summary["env_steps"]),
        "wall_seconds": float(summary["wall_seconds"]),
        "point_id": p["point_id"],
    }


def robust_table(
    rows: list[dict[str, Any]],
    candidates: dict[str, list[str]],
    scenarios: list[dict[str, Any]],
    th: float,
    seeds: int,
) -> str:
    """The benchmark as Markdown: one row per (candidate, scenario) and one per candidate over all
    its scenarios (medians over the runs; steps and seconds to the threshold over the runs that
    reached it; later evaluations pooled)."""

    def med(values: list[float]) -> str:
        values = [v for v in values if v is not None]
        return grouped(statistics.median(values)) if values else "—"

    def summary(mine: list[dict[str, Any]]) -> list[str]:
        reached = [r for r in mine if r["env_steps_to_threshold"] is not None]
        ok = sum(r["later_evals_ok"] for r in mine)
        n = sum(r["later_evals"] for r in mine)
        secs = [r["seconds_to_threshold"] for r in reached]
        return [
            f"{sum(r['holds'] for r in mine)}/{len(mine)}",
            f"{min(r['final_ratio'] for r in mine):.4f}",
            f"{statistics.median(r['final_ratio'] for r in mine):.4f}",
            f"{len(reached)}/{len(mine)}",
            med([r["env_steps_to_threshold"] for r in reached]),
            f"{statistics.median(secs):.2f}" if secs else "—",
            f"{ok}/{n} ({ok / n:.3f})" if n else "—",
            med([r["env_steps"] for r in mine]),
            f"{statistics.median(r['wall_seconds'] for r in mine):.1f}",
        ]

    body = []
    for name in candidates:
        theirs = [r for r in rows if r["candidate"] == name]
        if not theirs:
            continue
        for point in scenarios:
            mine = [r for r in theirs if all(r[k] == v for k, v in point.items())]
            if mine:
                label = ", ".join(f"{k} = {v:g}" for k, v in point.items()) or "random draws"
                body.append([name, label, *summary(mine)])
        if len(scenarios) > 1:
            body.append([f"**{name}**", "**all**", *summary(theirs)])
    th_pct = f"{th:.0%}"
    return (
        md_table(
            [
                "candidate",
                "scenario",
                f"holds ≥ {th:g} at the end",
                "worst final",
                "median final",
                f"reached {th_pct}",
                f"median env steps to {th_pct}",
                f"median s to {th_pct}",
                f"later evaluations ≥ {th:g}",
                "env steps per run",
                "median s per run",
            ],
            body,
        )
        + f"\n\n{counted(seeds, 'seed')} per scenario; each candidate's overrides: "
        + "; ".join(f"{n}: `{' '.join(o) or '(none)'}`" for n, o in candidates.items())
        + "."
    )
