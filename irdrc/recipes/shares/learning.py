"""What every recipe of a learner of the radar share (MODEL.md § D) does beside its learner: its
checks before any work, and its run — trained, scored exactly beside the optimum over ρ and
binary's, and written like every learner's run (``recipes/sac.py``, ``recipes/ppo.py``)."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from irdrc.core.checks import build, grouped
from irdrc.runs.compose import Composed
from irdrc.runs.limits import check_memory
from irdrc.runs.resume import refuse_finished
from irdrc.runs.sections import check_eval_period

if TYPE_CHECKING:
    from irdrc.runs.scaffold import Run


def load_as(config: type, composed: Composed, resume: dict[str, Any] | None) -> Any:
    """``load`` of a learner of shares whose recipe's keys are ``config``."""
    from irdrc.recipes.solve import check_shares_fit

    cfg = build(config, composed.cfg)
    if cfg.params.env.actions != "continuous":
        raise ValueError(
            f"env.actions={cfg.params.env.actions}: {cfg.algo.name.upper()} acts on the radar share ρ ∈ [0, 1] "
            "(env.actions=continuous); a discrete action space is DQN's (recipes/dqn.py)"
        )
    check_shares_fit(cfg.params)
    check_memory(cfg.algo)
    explicit = "eval.every_frames" in composed.explicit
    check_eval_period(cfg.eval.every_frames, cfg.algo.total_frames, explicit)
    if resume is not None:
        total = cfg.algo.total_frames
        refuse_finished(cfg.resume, int(resume["frames"]), total, "algo.total_frames", total)
    return cfg


def run_learner(cfg: Any, run: Run, train: Any) -> dict[str, Any]:
    """Train with ``train`` (``irdrc.agents.sac.train``, ``ppo.train``), score the final shares
    exactly beside the optimum over ρ and binary's, and write ``checkpoint.pt``, ``metrics.csv``,
    ``episode_rewards.csv``, ``policy.csv`` (``rho``), ``learning_curve.<format>`` and
    ``summary.json``."""
    from irdrc.agents.base import EPISODE_FIELDS
    from irdrc.core.exact import build_model, require_ratio, stationary_metrics, value_iteration
    from irdrc.core.exact.continuum import ContinuumScorer
    from irdrc.core.metrics import format_table
    from irdrc.runs.curves import plot_learning_curve
    from irdrc.runs.report import table_dict
    from irdrc.runs.results import summary_dict, write_metrics_csv, write_rows_csv
    from irdrc.runs.tables import write_policy_csv
    from irdrc.runs.tracking import log_scalars

    run.threads(cfg.num_threads)
    logger = run.make_logger(cfg.logger, cfg.algo.name)
    scorer = ContinuumScorer(cfg.params, cfg.optimum_gamma)
    require_ratio(scorer)
    print(
        f"scenario={run.scenario}: optimum over ρ ∈ [0, 1] {scorer.optimal_metrics.avg_reward:.4f} "
        f"per step (exact, within {scorer.optimal.value_bound:.0e} in value)",
        flush=True,
    )
    record = run.train(cfg, train, scorer)
    run.checkpoint(record.state)
    rho = record.greedy[0]
    write_metrics_csv(run.dir / "metrics.csv", record.history)
    write_rows_csv(run.dir / "episode_rewards.csv", record.episode_rewards, EPISODE_FIELDS)
    write_policy_csv(run.dir / "policy.csv", rho, cfg.params.env.factor_levels, shares=())
    plot_learning_curve(
        record,
        run.dir / f"learning_curve.{cfg.plot.format}",
        title=f"{cfg.algo.name} on {run.scenario}",
    )
    binary = build_model(cfg.params, shares=(0.0, 1.0))
    best = value_iteration(binary, gamma=cfg.optimum_gamma, tol=1e-9).policy
    name = cfg.algo.name
    rows = {
        f"{name} (exact, long run)": scorer.metrics(rho),
        "optimal over ρ (exact)": scorer.optimal_metrics,
        "binary optimum (exact)": stationary_metrics(binary, best),
    }
    print("\nexact long-run metrics:\n")
    print(format_table(rows))
    ratio = scorer.ratio(rho)
    to99 = record.first_reaching(0.99)
    print(
        f"\n{name}: {ratio:.4f} of the optimum over ρ after {grouped(record.env_steps)} env steps "
        f"({record.wall_seconds:.0f} s); first ≥ 0.99 at "
        f"{'—' if to99 is None else f'{grouped(to99)} env steps'}"
    )
    if ratio < 0.99:
        print(
            "warning: below 0.99 of the optimum; a longer run (algo.total_frames) usually closes it"
        )
    log_scalars(logger, {"final/optimality_ratio": ratio}, record.env_steps)
    summary = summary_dict(
        method=cfg.algo.name,
        scenario=run.scenario,
        seed=cfg.seed,
        env_steps=record.env_steps,
        wall_seconds=record.wall_seconds,
        metrics=rows[f"{name} (exact, long run)"],
        optimal=scorer.optimal_metrics,
        updates=record.updates,
        env_steps_to_95=record.first_reaching(0.95),
        env_steps_to_99=to99,
        interrupted=record.interrupted,
        binary_optimum=rows["binary optimum (exact)"].as_dict(),
        table=table_dict(rows, {}),
        **record.info,
    )
    run.finish(summary, interrupted_at=record.env_steps if record.interrupted else None)
    return summary
