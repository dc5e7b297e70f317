"""``recipes/qlearning.py``: vectorised tabular Q-learning — several learners, several scenarios in
one batch — evaluated exactly, beside the optimum.

    python recipes/qlearning.py                                 # our profile
    python recipes/qlearning.py algo=qlearning_paper            # the reference profile
    python recipes/qlearning.py num_learners=5 'batch_grid={env.p1.speed: [0.1,0.5,1.0]}'
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields
from typing import TYPE_CHECKING, Any

from irdrc.agents.configs import QLearningConfig
from irdrc.core.checks import INT, build, check_numbers
from irdrc.core.params import Params
from irdrc.runs.compose import Composed
from irdrc.runs.grid import is_scenario_key, parse_grid
from irdrc.runs.resume import refuse_finished
from irdrc.runs.sections import Learning, Plot, check_eval_period, scenario_field

if TYPE_CHECKING:
    from irdrc.runs.scaffold import Run

NAME = "qlearning"
ALGO_KEYS = frozenset(f.name for f in fields(QLearningConfig))
"""Every ``algo.*`` key Q-learning reads (a profile's file lists those that act in its run)."""
SWEEP_DEFAULTS = ("progress=false", "logger=none")
"""What a sweep gives every trial of this recipe before its own overrides (which may change it)."""
RESUMABLE = True

TABLES_LIMIT_BYTES = 4 * 2**30
"""The Q-tables and visit counts of every learner together (float32) are refused above this."""


@dataclass(frozen=True)
class Config(Learning):
    """Q-learning's keys (``irdrc/conf/qlearning.yaml``)."""

    params: Params = scenario_field()
    algo: QLearningConfig = field(default_factory=QLearningConfig)
    plot: Plot = field(default_factory=Plot)
    num_learners: int = 1
    device: str = "cpu"
    batch_grid: Any = None

    def __post_init__(self) -> None:
        super().__post_init__()
        check_numbers(self, "", (("num_learners", 1, 10**6, INT),))
        object.__setattr__(self, "batch_grid", batch_points(self.batch_grid))

    @property
    def scenarios(self) -> list[Params]:
        """The scenario of every batched point."""
        return [self.params.with_overrides(p) for p in self.batch_grid]


def batch_points(grid: Any) -> list[dict[str, Any]]:
    """The scenario points of ``batch_grid`` (one point, no overrides, when it is unset)."""
    if grid is None:
        return [{}]
    if isinstance(grid, list) and all(isinstance(p, dict) for p in grid):  # its points already
        return grid or [{}]
    points = parse_grid(grid, "batch_grid")
    for key in points[0]:
        if not is_scenario_key(key):
            raise ValueError(
                f"batch_grid key {key!r} must be an env. or reward. key (one batch varies "
                "the scenario; vary algo settings with a sweep)"
            )
    return points


def load(composed: Composed, resume: dict[str, Any] | None = None) -> Config:
    """The typed config, checked: values, every batched scenario, what the tables cost."""
    cfg = build(Config, composed.cfg)
    for key in cfg.batch_grid[0]:
        composed.refuse_unread(
            (key,), f"batch_grid sets {key} in every scenario of the batch; drop one of the two"
        )
    scenarios = cfg.scenarios
    rows = cfg.num_learners * len(scenarios)
    table_bytes = rows * cfg.params.env.num_states * 2 * 4 * 2  # Q-values and visit counts
    if table_bytes > TABLES_LIMIT_BYTES:
        raise ValueError(
            f"num_learners={cfg.num_learners} × {len(scenarios)} scenarios: the Q-tables would "
            f"take {table_bytes / 2**30:.1f} GiB (limit 4 GiB); use fewer learners"
        )
    from irdrc.runs.limits import check_exact

    check_exact(cfg.params)
    cfg.eval.check_cost(cfg.params)
    total = cfg.algo.episodes * cfg.params.env.horizon
    check_eval_period(cfg.eval.every_frames, total, "eval.every_frames" in composed.explicit)
    if resume is not None:
        refuse_finished(
            cfg.resume, int(resume["frames"]), total, "algo.episodes", cfg.algo.episodes
        )
    return cfg


def run(cfg: Config, run: Run) -> dict[str, Any]:
    """Train every learner, evaluate, finish the run directory (``irdrc.runs.report``)."""
    from irdrc.agents import qlearning
    from irdrc.core.exact import exact_scorer, require_ratio
    from irdrc.runs.report import LearnerRun, finish_learner
    from irdrc.runs.tracking import log_scalars

    run.threads(cfg.num_threads)
    logger = run.make_logger(cfg.logger, cfg.algo.name)
    scenarios = cfg.scenarios
    scorers = [exact_scorer(p, cfg.optimum_gamma) for p in scenarios]  # dense, or factored
    for scorer in scorers:
        require_ratio(scorer)
    total = cfg.algo.episodes * cfg.params.env.horizon
    with run.training(total, cfg.algo.name, checkpoint=cfg.checkpoint, verbatim=True) as hooks:
        record = qlearning.train(
            scenarios,
            cfg.algo,
            num_learners=cfg.num_learners,
            seed=cfg.seed,
            device=cfg.device,
            scorers=scorers,
            eval_every_frames=cfg.eval.every_frames or qlearning.DEFAULT_EVAL_EVERY_FRAMES,
            hooks=hooks,
            resume=run.resume_state,
        )
    summary = finish_learner(
        run,
        LearnerRun(
            name=cfg.algo.name,
            record=record,
            scenarios=scenarios,
            scorers=scorers,
            points=cfg.batch_grid,
            num_learners=cfg.num_learners,
            eval=cfg.eval,
            seed=cfg.seed,
            plot_format=cfg.plot.format,
        ),
    )
    log_scalars(logger, {"final/optimality_ratio": summary["optimality_ratio"]}, record.env_steps)
    run.finish(summary, interrupted_at=record.env_steps if record.interrupted else None)
    return summary
