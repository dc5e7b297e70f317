"""``recipes/dqn.py`` — the main job: DQN from TorchRL parts, evaluated exactly during training,
by Monte-Carlo at the end, beside the optimum and the baselines.

    python recipes/dqn.py                                   # our profile, paper scenario
    python recipes/dqn.py reward.r4=50 network=large env=ref_impl
    python recipes/dqn.py algo=dqn_paper                    # the reference profile (1 M steps)
    python recipes/dqn.py resume=outputs/…/checkpoint.pt algo.total_frames=8000000
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from irdrc.agents.configs import DQNConfig
from irdrc.core.checks import build
from irdrc.runs.compose import Composed
from irdrc.runs.limits import check_exact, check_memory
from irdrc.runs.resume import refuse_finished
from irdrc.runs.sections import OneVehicleLearning, algo_field, check_eval_period

if TYPE_CHECKING:
    from irdrc.runs.scaffold import Run

NAME = "dqn"
ALGO_KEYS = DQNConfig.keys()
"""Every ``algo.*`` key DQN reads (a profile's file lists those that act in its run)."""
SWEEP_DEFAULTS = ("progress=false", "logger=none")
"""What a sweep gives every trial of this recipe before its own overrides (which may change it)."""
RESUMABLE = True
ELSEWHERE = {
    "algo=qlearning": "python recipes/qlearning.py",
    "algo=qlearning_paper": "python recipes/qlearning.py algo=qlearning_paper",
    "algo=dqn_lagrangian": "python recipes/constrained.py learner=dqn_lagrangian",
    "algo=posterior": "python recipes/online.py learner=posterior",
    "algo=safe": "python recipes/online.py learner=safe",
}


@dataclass(frozen=True)
class Config(OneVehicleLearning):
    """The main job's keys (``irdrc/conf/dqn.yaml``)."""

    algo: DQNConfig = algo_field(DQNConfig)


def load(composed: Composed, resume: dict[str, Any] | None = None) -> Config:
    """The typed config, checked: values, what the exact model and the final evaluation cost, and
    what a resumed run has left to train."""
    cfg = build(Config, composed.cfg)
    check_exact(cfg.params)
    if cfg.params.env.actions != "binary":
        from irdrc.recipes.solve import check_shares_fit

        if cfg.params.env.actions == "continuous":
            raise ValueError(
                "env.actions=continuous: DQN picks one of finitely many actions; use "
                "env.actions=levels (G radar shares) or recipes/sac.py for ρ ∈ [0, 1]"
            )
        check_shares_fit(cfg.params)
    cfg.eval.check_cost(cfg.params)
    check_memory(cfg.algo)
    explicit = "eval.every_frames" in composed.explicit
    check_eval_period(cfg.eval.every_frames, cfg.algo.total_frames, explicit)
    if resume is not None:
        total = cfg.algo.total_frames
        refuse_finished(cfg.resume, int(resume["frames"]), total, "algo.total_frames", total)
    return cfg


def run(cfg: Config, run: Run) -> dict[str, Any]:
    """Train, evaluate, finish the run directory (``irdrc.runs.report``)."""
    from irdrc.agents import dqn
    from irdrc.core.exact import exact_scorer, require_ratio
    from irdrc.core.exact.continuum import continuum_optimum
    from irdrc.runs.report import LearnerRun, finish_learner
    from irdrc.runs.tracking import log_scalars

    run.threads(cfg.num_threads)
    logger = run.make_logger(cfg.logger, cfg.algo.name)
    scorer = exact_scorer(cfg.params, cfg.optimum_gamma)  # dense, or factored beyond its reach
    require_ratio(scorer)
    record = run.train(cfg, dqn.train, scorer)
    best = continuum_optimum(cfg.params, cfg.optimum_gamma)  # with G levels, else None
    final = record.history[-1]["optimality_ratio"]  # the final policy's, exact
    log_scalars(logger, {"final/optimality_ratio": final}, record.env_steps)
    summary = finish_learner(run, LearnerRun.single(cfg, record, scorer))
    if best is not None:  # G levels read against the optimum over ρ ∈ [0, 1] (MODEL.md § D)
        learned, levels = summary["metrics"]["avg_reward"], summary["optimal"]["avg_reward"]
        summary["continuum"] = {
            "optimal_avg_reward": best,
            "levels_ratio": levels / best,
            "optimality_ratio": learned / best,
        }
        print(
            f"over ρ ∈ [0, 1] the optimum earns {best:.4f} per step: the {cfg.params.env.levels}-"
            f"level optimum is {levels / best:.4f} of it, dqn {learned / best:.4f}"
        )
    run.finish(summary, interrupted_at=record.env_steps if record.interrupted else None)
    return summary
