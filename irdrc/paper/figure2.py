"""``recipes/figure2.py``: the paper's Figure 2, regenerated against the exact optimum.

``run`` plans every training run (DQN: one per seed and p^v_1; Q-learning: one vectorised
batch per profile holding every seed and p^v_1), executes them with the sweep engine
(``irdrc.sweeps.trials``), adds the exact optimum and round-robin, and writes one CSV and one PNG
per panel and the claims table. Every run is read the same way, whatever its method: its
``learners.csv`` (one row per learner, with its scenario), ``metrics.csv`` and
``episode_rewards.csv`` (one schema, rows tagged by learner).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING, Any

from irdrc.core.checks import INT, build, check_choice, check_list, check_number, check_numbers
from irdrc.core.params import Params
from irdrc.paper import claims as cl
from irdrc.paper.panels import Figure, exact_reference, panel_a, panels_bcd
from irdrc.recipes import dqn, qlearning
from irdrc.recipes.constrained.frontier import optimal_at, ref_params
from irdrc.runs.compose import Composed
from irdrc.runs.grid import format_value, parse_grid
from irdrc.runs.limits import check_dense
from irdrc.runs.results import atomic_write_text, write_rows_csv
from irdrc.runs.sections import EXECUTOR, Executor, check_common, scenario_field
from irdrc.sweeps.trials import execute, plan

if TYPE_CHECKING:
    from irdrc.runs.scaffold import Run

NAME = "figure2"
PANELS = ("a", "bcd")
LEARNER_METHODS = ("dqn", "qlearning")


@dataclass(frozen=True)
class Learner:
    """``learners.<name>``: which recipe runs it (``method``), on which ``panels``, with which
    ``overrides``."""

    method: str
    panels: tuple[str, ...]
    overrides: tuple[str, ...] = ()


@dataclass(frozen=True)
class Config:
    """The figure's keys (``irdrc/conf/figure2.yaml``); ``planned``: every training run, checked
    (``plan_figure2``)."""

    params: Params = scenario_field()
    seeds: tuple[int, ...] = (0, 1, 2, 3, 4)
    p1_speed: tuple[float, ...] = (0.1, 0.5, 1.0)
    curve_p1_speed: float = 0.1
    methods: tuple[str, ...] = ("dqn", "qlearning")
    learners: dict[str, Any] = field(default_factory=dict)
    eval: dict[str, Any] = field(default_factory=lambda: {"every_frames": None})
    optimum_gamma: float = 0.99
    smooth_episodes: int = 10
    claim3_r4: tuple[float, ...] = (5.0, 50.0, 100.0)
    executor: Executor = field(default_factory=Executor, metadata=EXECUTOR)
    planned: tuple[Any, ...] = field(default=(), metadata={"keys": ()})

    def __post_init__(self) -> None:
        check_common(self)
        seeds = self.seeds if not isinstance(self.seeds, int) else list(range(self.seeds))
        seed = lambda key, x: check_number(key, x, 0, 2**32 - 1, integer=True)  # noqa: E731
        seeds = check_list("seeds", seeds, seed)
        if len(set(seeds)) != len(seeds):
            raise ValueError(f"seeds={list(seeds)} must be distinct")
        object.__setattr__(self, "seeds", seeds)
        prob = lambda key, x: check_number(key, x, 0, 1)  # noqa: E731
        object.__setattr__(
            self, "p1_speed", tuple(sorted(set(check_list("p1_speed", self.p1_speed, prob))))
        )
        object.__setattr__(self, "curve_p1_speed", prob("curve_p1_speed", self.curve_p1_speed))
        r4 = lambda key, x: check_number(key, x, 0, 1e9, open_lo=True)  # noqa: E731
        object.__setattr__(
            self,
            "claim3_r4",
            check_list("claim3_r4", self.claim3_r4, r4, empty=True, distinct=True),
        )
        check_numbers(self, "", (("smooth_episodes", 1, 10**6, INT),))
        every = self.eval.get("every_frames")
        if every is not None:
            check_number("eval.every_frames", every, 1, 10**12, integer=True)
        learners = {}
        for name, spec in self.learners.items():
            if isinstance(spec, Learner):  # checked already (``replace``)
                learners[name] = spec
                continue
            spec = dict(spec)
            check_choice(f"learners.{name}.method", spec.get("method"), LEARNER_METHODS)
            panel = lambda key, x: check_choice(key, x, PANELS)  # noqa: E731
            panels = check_list(f"learners.{name}.panels", spec.get("panels"), panel)
            overrides = check_list(
                f"learners.{name}.overrides", spec.get("overrides", []), empty=True
            )
            learners[name] = Learner(spec["method"], panels, overrides)
        object.__setattr__(self, "learners", learners)
        pick = lambda key, m: check_choice(key, m, tuple(learners))  # noqa: E731
        object.__setattr__(
            self, "methods", check_list("methods", self.methods, pick, distinct=True)
        )


def load(composed: Composed, resume: dict[str, Any] | None = None) -> Config:
    """The typed config; every training run composed and checked before any work."""
    cfg = build(Config, composed.cfg)
    composed.refuse_overwritten(
        {
            "env.p1.speed": "set p1_speed=[…] (panels (b)–(d)) and curve_p1_speed=… (panel (a))",
            "seed": "set seeds=[…]",
        },
        [o for spec in cfg.learners.values() for o in spec.overrides],
        fixed=("optimum_gamma", "eval.mc_episodes"),
    )
    for name in cfg.learners:
        if name not in cfg.methods:
            composed.refuse_unread(
                (f"learners.{name}",), f"{name} is not among methods=[…]; add it there to run it"
            )
    check_dense(cfg.params)  # the exact references, after the training: refused before it
    return replace(cfg, planned=tuple(plan_figure2(cfg, composed.scenario_overrides)))


def plan_figure2(cfg: Config, scenario: list[str]) -> list[dict[str, Any]]:
    """Every training run of the figure, as sweep-engine plans tagged with their learner."""
    seeds, ps, curve_p = list(cfg.seeds), list(cfg.p1_speed), cfg.curve_p1_speed
    planned: list[dict[str, Any]] = []
    for name in cfg.methods:
        spec = cfg.learners[name]
        chosen: set[float] = set()
        if "a" in spec.panels:
            chosen.add(curve_p)
        if "bcd" in spec.panels:
            chosen.update(ps)
        values = sorted(chosen)
        common = [
            *scenario,
            *[str(o) for o in spec.overrides],
            "eval.mc_episodes=0",
            f"optimum_gamma={cfg.optimum_gamma}",
        ]
        if cfg.eval.get("every_frames") is not None:
            common.append(f"eval.every_frames={cfg.eval['every_frames']}")
        if spec.method == "dqn":
            points = parse_grid({"env.p1.speed": values, "seed": seeds})
            runs = plan(dqn, points, common)
        else:
            grid = "{env.p1.speed: " + format_value(values) + "}"
            base = [*common, f"num_learners={len(seeds)}", f"batch_grid={grid}"]
            runs = plan(qlearning, [{"seed": seeds[0]}], base)
        for r in runs:
            r["learner"] = name
        planned.extend(runs)
    # Longest runs first, so that no long run starts last while the other workers idle.
    planned.sort(key=_cost, reverse=True)
    return planned


def _cost(p: dict[str, Any]) -> float:
    """Relative cost of a planned run: Q-learning batches (per-step cost grows with the batch) first,
    then DQN runs by collector batches (each carries its updates and fixed overhead)."""
    algo = p["config"].algo
    if p["method"] == "qlearning":
        return 1e12 + algo.episodes
    return algo.total_frames / algo.frames_per_batch * max(1, algo.updates_per_batch)


def run(cfg: Config, run: Run) -> int:
    """Run the figure: training runs, exact references, CSVs, PNGs, claims. Returns an exit code."""
    t_start = time.perf_counter()
    out = run.dir.resolve()
    planned = list(cfg.planned)
    seeds, ps, curve_p, base = list(cfg.seeds), list(cfg.p1_speed), cfg.curve_p1_speed, cfg.params
    print(
        f"figure2: {len(planned)} training runs for {', '.join(cfg.methods)}; "
        f"{len(seeds)} seeds; p^v_1 ∈ {ps}; panel (a) at p^v_1 = {curve_p}",
        flush=True,
    )
    code = execute(cfg.executor, planned, out, run.recipe)
    t_train = time.perf_counter() - t_start
    if code != 0:
        print(
            "figure2: some runs did not finish (see summary.csv); fix and rerun with resume=true",
            flush=True,
        )
        return code
    gamma = cfg.optimum_gamma
    refs = {p: exact_reference(ref_params(base, p), gamma) for p in sorted({*ps, curve_p})}
    fig = Figure(cfg, out, planned, seeds, ps, curve_p, base, refs)
    opt_ep, rr_ep, finals, to95 = panel_a(fig)
    sweep_means = panels_bcd(fig)
    r4_miss, r4_thr = {}, {}
    for r4 in cfg.claim3_r4:
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
        "scenario": run.composed.scenario_overrides,
        "training_runs": len(planned),
        "resumed": cfg.executor.resume,  # wall times then cover only what this invocation ran
        "wall_seconds_training": t_train,
        "wall_seconds": wall,
        "optimum_episode_reward": opt_ep,
        "round_robin_episode_reward": rr_ep,
        "final_episode_reward": finals,
        "episodes_to_95": to95,
        "verdicts": counts,
    }
    print("\nclaims (MODEL.md § The paper's claims):\n")
    print(table)
    print(
        f"\n{counts[cl.HOLDS]} hold, {counts[cl.FAILS]} do not hold, {counts[cl.UNTESTED]} not tested. "
        f"Wall time {wall:.0f} s ({t_train:.0f} s of it training)."
    )
    run.finish(summary)
    return 0
