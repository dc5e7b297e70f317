"""``recipes/bench_dqn.py``: DQN's speed per profile — env steps/s and updates/s of training, where
the time goes — and how soon it learns (env steps and seconds to 95 % / 99 % of the optimum), per
profile and seed, profiles alternated seed by seed in one process.

    python recipes/bench_dqn.py                                   # BENCHMARKS.md's table
    python recipes/bench_dqn.py 'seeds=[0]' 'profiles={dqn: [algo=dqn]}'
"""

from __future__ import annotations

import statistics
import time
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

from irdrc.core.checks import build, check_list, grouped
from irdrc.core.params import Params
from irdrc.runs.compose import Composed, compose_recipe
from irdrc.runs.grid import candidate_overrides, is_learner_key
from irdrc.runs.results import md_table
from irdrc.runs.sections import Eval, check_common, scenario_field
from irdrc.runs.sections import seeds as distinct_seeds

if TYPE_CHECKING:
    from irdrc.runs.scaffold import Run

NAME = "bench_dqn"
SUMMARY_KEYS = (
    "env_steps_per_second",
    "updates_per_second",
    "env_steps_to_95",
    "seconds_to_95",
    "env_steps_to_99",
    "seconds_to_99",
    "later_evals_at_99",
    "final_ratio",
)


@dataclass(frozen=True)
class Config:
    """The benchmark's keys (``irdrc/conf/bench_dqn.yaml``); ``algos``: every profile's DQN
    config, composed as ``recipes/dqn.py`` composes it, checked."""

    params: Params = scenario_field()
    profiles: dict[str, Any] = field(default_factory=lambda: {"dqn": ["algo=dqn"]})
    seeds: tuple[int, ...] = (0, 1, 2)
    overrides: tuple[str, ...] = ()
    eval: Eval = field(default_factory=Eval)
    optimum_gamma: float = 0.99
    num_threads: int = 1
    device: str = "cpu"
    csv: str = "bench_dqn.csv"
    algos: dict[str, Any] = field(default_factory=dict, metadata={"keys": ()})

    def __post_init__(self) -> None:
        check_common(self)
        seeds = distinct_seeds("seeds", self.seeds)
        object.__setattr__(self, "seeds", seeds)
        object.__setattr__(self, "overrides", check_list("overrides", self.overrides, empty=True))


def load(composed: Composed, resume: dict[str, Any] | None = None) -> Config:
    """The typed config; every profile composed (``recipes/dqn.py``'s way) and checked."""
    from dataclasses import replace

    from irdrc.recipes import dqn

    cfg = build(Config, composed.cfg)
    algos = {}
    for name, extra in candidate_overrides(cfg.profiles, "profiles").items():
        for where, o in [
            *((f"profiles.{name}", o) for o in extra),
            *(("overrides", o) for o in cfg.overrides),
        ]:
            if not is_learner_key(o):
                raise ValueError(
                    f"{where}: {o} is not read: a profile is DQN's algo.* and network.* keys; "
                    f"the scenario, seeds, eval, num_threads and device are bench_dqn's own "
                    f"(set them on its command line)"
                )
        try:
            algos[name] = dqn.load(compose_recipe(dqn, [*extra, *cfg.overrides])).algo
        except ValueError as err:
            raise ValueError(f"profiles.{name}: {str(err).strip().splitlines()[0]}") from None
    return replace(cfg, algos=algos)


def run(cfg: Config, run: Run) -> int:
    """Train every (profile, seed); ``bench_dqn.csv`` (a row per run) and ``bench_dqn.md``."""
    from irdrc.agents import dqn
    from irdrc.core.exact import Scorer, build_model
    from irdrc.runs.results import write_rows_csv, write_table_md

    start = time.perf_counter()
    run.threads(cfg.num_threads)
    scorer = Scorer(build_model(cfg.params), gamma=cfg.optimum_gamma)
    rows: list[dict[str, Any]] = []
    for seed in cfg.seeds:
        for name, algo in cfg.algos.items():
            rec = dqn.train(
                cfg.params,
                algo,
                seed=seed,
                device=cfg.device,
                eval_every_frames=cfg.eval.every_frames or dqn.DEFAULT_EVAL_EVERY_FRAMES,
                scorer=scorer,
            )
            rows.append(_speed_row(name, seed, rec))
            row = rows[-1]
            print(
                f"{name:>14} seed {seed}: {grouped(row['env_steps_per_second'])} env steps/s, "
                f"{row['updates_per_second']:.0f} updates/s of training; 99 % at "
                f"{row['env_steps_to_99']} steps / {row['seconds_to_99']} s; final "
                f"{row['final_ratio']:.4f}",
                flush=True,
            )
    write_rows_csv(run.dir / cfg.csv, rows)
    table = speed_table(rows, list(cfg.algos))
    print("\n" + table)
    write_table_md(run.dir / "bench_dqn.md", table, time.perf_counter() - start)
    run.finish(None)
    return 0


def _fmt(values: list[float]) -> str:
    hit = [v for v in values if v is not None]
    if len(hit) < len(values):
        return f"{len(hit)}/{len(values)} reached" + (
            f" (range {min(hit):.4g}–{max(hit):.4g})" if hit else ""
        )
    return f"median {statistics.median(hit):.4g} (range {min(hit):.4g}–{max(hit):.4g})"


def _speed_row(name: str, seed: int, rec: Any) -> dict[str, Any]:
    """One run of the speed benchmark: its counts, its phases' seconds, and how soon it learned."""
    info = rec.info
    train = info["seconds_collect"] + info["seconds_store"] + info["seconds_learn"]
    t99 = rec.first_reaching(0.99)
    later = [e for e in rec.history if t99 is not None and e["env_steps"] > t99]
    return {
        "profile": name,
        "seed": seed,
        "env_steps": rec.env_steps,
        "updates": rec.updates,
        "training_seconds": round(train, 3),
        "evaluation_seconds": round(info.get("seconds_evaluate", 0.0), 3),
        **{
            f"share_{k}": round(info[f"seconds_{k}"] / train, 3)
            for k in ("collect", "store", "learn")
        },
        "env_steps_per_second": rec.env_steps / train,
        "updates_per_second": rec.updates / info["seconds_learn"] if info["seconds_learn"] else 0.0,
        "env_steps_to_95": rec.first_reaching(0.95),
        "seconds_to_95": rec.first_reaching(0.95, at="wall_seconds"),
        "env_steps_to_99": t99,
        "seconds_to_99": rec.first_reaching(0.99, at="wall_seconds"),
        "later_evals_at_99": (
            sum(e["optimality_ratio"] >= 0.99 for e in later) / len(later) if later else None
        ),
        "final_ratio": rec.history[-1]["optimality_ratio"],
    }


def speed_table(rows: list[dict[str, Any]], profiles: list[str]) -> str:
    """The speed benchmark as Markdown: per profile, medians over its seeds, and its training speed
    as a ratio to the first profile's (measured in the same run, alternately)."""
    body, base = [], None
    for name in profiles:
        mine = [r for r in rows if r["profile"] == name]
        if not mine:
            continue
        rate = statistics.median(r["env_steps_per_second"] for r in mine)
        base = base or rate
        t99 = [r for r in mine if r["env_steps_to_99"] is not None]
        body.append(
            [
                name,
                len(mine),
                grouped(mine[0]["env_steps"]),
                grouped(statistics.median(r["updates"] for r in mine)),
                f"{statistics.median(r['training_seconds'] for r in mine):.2f}",
                grouped(rate),
                f"{rate / base:.3g}",
                f"{statistics.median(r['updates_per_second'] for r in mine):.0f}",
                " / ".join(
                    f"{statistics.median(r[f'share_{k}'] for r in mine):.0%}"
                    for k in ("collect", "store", "learn")
                ),
                f"{len(t99)}/{len(mine)}",
                _fmt([r["env_steps_to_99"] for r in t99]) if t99 else "—",
                _fmt([r["seconds_to_99"] for r in t99]) if t99 else "—",
                _fmt([r["final_ratio"] for r in mine]),
            ]
        )
    return md_table(
        [
            "profile",
            "seeds",
            "env steps",
            "updates",
            "training s",
            "env steps/s of training",
            "× the first profile",
            "updates/s",
            "collect / store / learn",
            "reached 99 %",
            "env steps to 99 %",
            "s to 99 %",
            "final ratio",
        ],
        body,
    ) + (
        "\n\nMedians over the seeds (ranges in brackets); one thread; training seconds leave the "
        "exact evaluations out."
    )
