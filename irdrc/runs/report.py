"""How a single-vehicle learner's run finishes, whatever the learner: its files, its table, its last
lines.

``finish_learner`` writes ``metrics.csv`` (one schema: ``irdrc.agents.base.PROGRESS_FIELDS``),
``episode_rewards.csv``, ``learners.csv``, ``policy.csv``, ``learning_curve.<format>``,
``summary.json`` (every row of the printed table) and the final checkpoint, then prints the table,
the final ratio, the states where the policy differs from the optimum, and a warning when the run
ends below the optimum.
"""

from __future__ import annotations

import dataclasses
import statistics
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

from irdrc.agents.base import EPISODE_FIELDS, RunRecord
from irdrc.core.env import DFRCEnv
from irdrc.core.evaluate import evaluate
from irdrc.core.exact import DenseModel, Scorer, episodic_metrics, stationary_metrics
from irdrc.core.metrics import Metrics, format_table
from irdrc.core.params import Params
from irdrc.core.policies import table_policy
from irdrc.runs.curves import plot_learning_curve
from irdrc.runs.grid import is_scenario_key, point_overrides
from irdrc.runs.results import clean_number, summary_dict, write_metrics_csv, write_rows_csv
from irdrc.runs.scaffold import Run
from irdrc.runs.sections import Eval
from irdrc.runs.signals import Signalled
from irdrc.runs.tables import policy_differences, write_policy_csv

if TYPE_CHECKING:
    import torch


@dataclass
class LearnerRun:
    """What a single-vehicle learner's run produced, and how it is reported.

    Attributes:
        name: the learner's profile (``dqn``, ``qlearning_paper`` …).
        record: the learner's record.
        scenarios: the scenario of each batched point (one for most runs).
        scorers: the exact scorer of each scenario.
        points: each scenario's overrides (``batch_grid``; ``[{}]`` for one scenario).
        num_learners: learners per scenario.
        eval: the evaluation keys (``eval.every_frames``; the Monte-Carlo rows at the end).
        seed: the run's seed.
        plot_format: the learning curve's format.
        advice: the override a run that ends below the optimum is told to try (default: the
            profile's ``ADVICE``).
        plot: draws the learning curve, ``plot(record, path, title)`` (default
            ``plot_learning_curve``: against env steps).
        end_check: the warning a finished run ends with, from its history, or None (default
            ``end_warning`` with ``advice``: the final greedy policy against the optimum; a
            learner held to a constraint passes ``end_warning`` read against its own target).
        reference: what the final greedy policy's states are set against in the printout, as
            (the sentence's words, the column's name, its actions [S]), or None: the optimum. A
            learner held to a constraint passes the constrained optimum's.
        labels: each scenario's overrides as command-line words (from ``points``).
    """

    name: str
    record: RunRecord
    scenarios: list[Params]
    scorers: list[Scorer]
    points: list[dict[str, Any]]
    num_learners: int
    eval: Eval
    seed: int
    plot_format: str = "png"
    advice: str | None = None
    plot: Callable[..., None] | None = None
    end_check: Callable[[list[dict[str, Any]]], str | None] | None = None
    reference: tuple[str, str, Any] | None = None
    labels: list[list[str]] = field(init=False)

    def __post_init__(self) -> None:
        self.labels = [point_overrides(point) for point in self.points]
        if self.advice is None and self.name in ADVICE:  # fitted to this run
            self.advice = ADVICE[self.name].format(twice=2 * int(self.record.env_steps))

    @classmethod
    def single(cls, cfg: Any, record: RunRecord, scorer: Scorer, **rest: Any) -> LearnerRun:
        """One learner on one scenario, from a recipe's config (``algo.name``, ``params``,
        ``eval``, ``seed``, ``plot.format``); ``rest`` sets the optional attributes."""
        return cls(
            name=cfg.algo.name,
            record=record,
            scenarios=[cfg.params],
            scorers=[scorer],
            points=[{}],
            num_learners=1,
            eval=cfg.eval,
            seed=cfg.seed,
            plot_format=cfg.plot.format,
            **rest,
        )

    @property
    def final_policy(self) -> torch.Tensor:
        """Learner 0's final policy: its randomised [S, A] probabilities where it has them, else
        its greedy table [S]."""
        if self.record.policy is not None:
            return self.record.policy[0].cpu()
        return self.record.greedy[0].cpu()


def finish_learner(run: Run, lr: LearnerRun) -> dict[str, Any]:
    """Write the run's files, print its table, return its summary (see the module docstring)."""
    record, scorer = lr.record, lr.scorers[0]
    learners = learner_rows(lr)
    if record.state is not None:
        run.checkpoint(record.state)
    write_metrics_csv(run.dir / "metrics.csv", record.history)
    write_rows_csv(run.dir / "episode_rewards.csv", record.episode_rewards, EPISODE_FIELDS)
    write_rows_csv(run.dir / "learners.csv", learners)
    greedy = record.greedy[0].cpu()
    curve = run.dir / f"learning_curve.{lr.plot_format}"
    (lr.plot or plot_learning_curve)(record, curve, title=f"{lr.name} on {run.scenario}")
    try:
        rows, errs = final_rows(lr, lr.final_policy)
    except Signalled as sig:  # the Monte-Carlo evaluation cut short: the files without it
        print(
            f"\n{sig}: the Monte-Carlo evaluation is left out; writing the run's files", flush=True
        )
        no_mc = dataclasses.replace(lr, eval=dataclasses.replace(lr.eval, mc_episodes=0))
        rows, errs = final_rows(no_mc, lr.final_policy)
    summary = summary_dict(
        method=lr.name,
        scenario=run.scenario,
        seed=lr.seed,
        env_steps=record.env_steps,
        wall_seconds=record.wall_seconds,
        metrics=rows[f"{lr.name} (exact, long run)"],
        optimal=scorer.optimal_metrics,
        training_env_steps=record.training_env_steps,
        measurement_env_steps=record.measurement_env_steps,
        updates=record.updates,
        env_steps_to_95=record.first_reaching(0.95),
        env_steps_to_99=record.first_reaching(0.99),
        num_learners=lr.num_learners,
        interrupted=record.interrupted,
        states_differing_from_optimum=int((greedy != scorer.optimal.policy).sum()),
        learners=[_summary_row(r) for r in learners],
        table=table_dict(rows, errs),
        **_batch_grid(lr),
        **record.info,
    )
    print_learner(run, lr, learners, rows, errs)
    env = lr.scenarios[0].env
    shares = env.shares if env.actions == "levels" else None
    write_policy_csv(run.dir / "policy.csv", lr.final_policy, env.factor_levels, shares)
    return summary


def final_rows(
    lr: LearnerRun, greedy: torch.Tensor
) -> tuple[dict[str, Metrics], dict[str, dict[str, float]]]:
    """The final table: the learned policy ``greedy`` ([S] actions or [S, A] probabilities)
    exactly (long run, and episodic beside the Monte-Carlo row), the optimum and round-robin;
    Monte-Carlo ± 95 % CI."""
    scorer, name = lr.scorers[0], lr.name
    model = scorer.model
    rows: dict[str, Metrics] = {f"{name} (exact, long run)": scorer.metrics(greedy)}
    errs: dict[str, dict[str, float]] = {}
    mc = int(lr.eval.mc_episodes or 0)
    episodic = mc > 0 and isinstance(model, DenseModel)
    if mc:
        env = DFRCEnv(lr.scenarios[0], batch_size=[lr.eval.mc_batch], seed=lr.seed + 1)
        ev = evaluate(
            table_policy(greedy, seed=lr.seed + 2, num_actions=model.num_actions), env, episodes=mc
        )
        if episodic:  # what the Monte-Carlo row estimates, exactly
            rows[f"{name} (exact, episodic)"] = episodic_metrics(model, greedy)
        label = f"{name} (Monte-Carlo, episodic)"
        rows[label], errs[label] = ev.metrics, ev.ci95
    rows["optimal (exact, long run)"] = scorer.optimal_metrics
    if episodic:
        rows["optimal (exact, episodic)"] = episodic_metrics(model, scorer.optimal.policy)
    rows["round_robin (exact, long run)"] = stationary_metrics(model, "round_robin")
    return rows, errs


def _batch_grid(lr: LearnerRun) -> dict[str, Any]:
    if len(lr.scenarios) == 1:
        return {}
    return {
        "batch_grid": [
            {
                "overrides": lr.labels[g],
                "optimal": {
                    k: clean_number(v) for k, v in lr.scorers[g].optimal_metrics.as_dict().items()
                },
            }
            for g in range(len(lr.points))
        ]
    }


def _steps(value: Any) -> str:
    """Env steps to a threshold, or "never" (None: no evaluation reached it)."""
    return "never" if value is None else str(value)


def print_learner(
    run: Run,
    lr: LearnerRun,
    learners: list[dict[str, Any]],
    rows: dict[str, Metrics],
    errs: dict[str, dict[str, float]],
) -> None:
    """The run's printout: the table (or one line per batched scenario), learners, the end."""
    record, scorers = lr.record, lr.scorers
    print(
        f"\nscenario={run.scenario} method={lr.name} seed={lr.seed} learners={lr.num_learners}"
        + (f" × {len(lr.scenarios)} scenarios (batch_grid)" if len(lr.scenarios) > 1 else "")
    )
    print(
        f"{record.env_steps} env steps per learner, {record.updates} updates in "
        f"{record.wall_seconds:.1f} s; exact evaluation every {lr.eval.every_frames} env steps\n"
    )
    if len(lr.scenarios) == 1:
        print(format_table(rows, errors=errs))
        print(
            "long run: the policy's stationary average (it runs forever); episodic: episodes of "
            f"{lr.scenarios[0].env.horizon} steps from a uniform reset, as the Monte-Carlo row "
            "samples"
        )
        if note := degenerate_note(scorers[0].optimal_metrics):
            print(note)
    else:
        print("scenario                        optimum avg reward  final ratio (median, min)")
        for g in range(len(lr.points)):
            mine = [r["final_ratio"] for r in learners if record.group[r["learner"]] == g]
            label = " ".join(lr.labels[g])
            print(
                f"{label:<32}{scorers[g].optimal_metrics.avg_reward:>18.4f}  "
                f"{statistics.median(mine):.4f}, {min(mine):.4f}"
            )
    if record.num_learners > 1:
        print("\nlearner  final ratio  env steps to 95 %  to 99 %")
        for row in learners:
            to95, to99 = (_steps(row[f"env_steps_to_{th}"]) for th in ("95", "99"))
            print(f"{row['learner']:>7}  {row['final_ratio']:>11.4f}  {to95:>17}  {to99:>7}")
        for th in ("95", "99"):
            got = [r[f"env_steps_to_{th}"] for r in learners]
            hit = sorted(g for g in got if g is not None)
            med = (
                f"median env steps {statistics.median(hit):g}"
                if len(hit) == len(got)
                else "no median: not every learner reached it"
            )
            print(f"to {th} %: {len(hit)}/{len(got)} learners; {med}")
    final, first99 = learners[0]["final_ratio"], learners[0]["env_steps_to_99"]
    reached = (
        f"first ≥ 99 % at {first99} env steps"
        if first99 is not None
        else f"not ≥ 99 % at any evaluation of its {record.env_steps} env steps"
    )
    optimum = "the unconstrained optimum's" if lr.reference else "the optimum's"
    print(f"\nfinal greedy policy: {final:.4f} of {optimum} average reward (exact); {reached}")
    against = lr.reference or ("the optimum", "optimum", scorers[0].optimal.policy)
    print(policy_differences(scorers[0].model, record.greedy[0].cpu(), against[2], *against[:2]))
    check = lr.end_check or (lambda history: end_warning(history, lr.advice))
    if not record.interrupted and (warning := check(record.history)):
        print(warning, flush=True)


def learner_rows(lr: LearnerRun) -> list[dict[str, Any]]:
    """``learners.csv``: one row per learner — its scenario point, ``learner`` (the index used in
    ``metrics.csv`` and ``episode_rewards.csv``), ``replicate`` (its index within its scenario),
    final ratio, steps to 95 / 99 % and final exact metrics."""
    record, rows = lr.record, []
    for n in range(record.num_learners):
        g = record.group[n]
        final = lr.scorers[g].metrics(
            record.policy[n].cpu() if record.policy is not None else record.greedy[n].cpu()
        )
        rows.append(
            {
                **lr.points[g],
                "learner": n,
                "replicate": n % lr.num_learners,
                "final_ratio": record.curve(n)[-1]["optimality_ratio"],
                "training_env_steps": record.training_env_steps,
                "measurement_env_steps": record.measurement_env_steps,
                "env_steps": record.env_steps,
                "env_steps_to_95": record.first_reaching(0.95, n),
                "env_steps_to_99": record.first_reaching(0.99, n),
                **{k: clean_number(v) for k, v in final.as_dict().items()},
            }
        )
    return rows


def _summary_row(row: dict[str, Any]) -> dict[str, Any]:
    keys = ("learner", "replicate", "final_ratio", "env_steps_to_95", "env_steps_to_99")
    return {k: row[k] for k in keys} | {k: v for k, v in row.items() if is_scenario_key(k)}


def table_dict(
    rows: dict[str, Metrics], errs: dict[str, dict[str, float]]
) -> dict[str, dict[str, Any]]:
    """The printed table as JSON: row → metrics (and ``ci95`` where the row has intervals)."""
    out = {}
    for label, m in rows.items():
        entry: dict[str, Any] = {k: clean_number(v) for k, v in m.as_dict().items()}
        if label in errs:
            entry["ci95"] = {k: clean_number(v) for k, v in errs[label].items()}
        out[label] = entry
    return out


def degenerate_note(optimal: Metrics) -> str | None:
    """A line explaining an optimum that never communicates (throughput 0, every packet dropped),
    or None: with a large detection reward r4 (e.g. 50 at p^v_1 = 0.1) radar earns more in every
    state — the paper's degenerate case (docs/REPRODUCTION.md, claim 3)."""
    if optimal.radar_fraction < 1.0 - 1e-9:
        return None
    return (
        "note: at these weights the optimum never communicates (radar always: throughput 0, "
        "every packet dropped); a large detection reward r4 makes radar worth more in every "
        "state, the paper's degenerate case (docs/REPRODUCTION.md, claim 3)"
    )


END_THRESHOLD = 0.99
"""A run whose final greedy policy is below this share of the optimum ends with a warning."""

WARNING_LEARNERS = 5
"""A warning about many learners names this many, one per line, and counts the rest."""

END_SLACK = 0.01
"""… as does one whose final policy is more than this below its own best evaluation."""


ADVICE = {
    "dqn": "algo.total_frames={twice} (twice this run's env steps and about twice its wall time: "
    "it held on all 3 random-scenario runs where the default is known to fall short; docs/DQN.md)",
    "dqn_plain": "algo=dqn (DQN with a reward table, the default: docs/DQN.md)",
    "dqn_paper": "algo=dqn (our profile, the default: 120 of 120 runs ≥ 0.99 on the named grid, "
    "about 18 s each here; docs/DQN.md)",
    "dqn_levels": "algo.total_frames={twice} (twice this run's env steps: on env=imperfect_radar "
    "seeds 6 and 8, at 0.9802 and 0.9742 of the G-level optimum after 10⁶, ended at 0.9958 and "
    "0.9938, network=large at 0.9934 and 0.9973; docs/TIMESHARING.md)",
    "qlearning": "algo.episodes=2400 (four times the default's 600 episodes and wall time: on "
    "env=multilevel three learners at 0.971–0.978 after 600 were at 0.992–0.996; "
    "docs/BENCHMARKS.md) — or, on a state space the size of env=large (100 800 states), "
    "recipes/dqn.py",
    "qlearning_paper": "algo=qlearning (our profile: on the paper scenario 5 of 5 seeds ≥ 0.99, "
    "where this profile reached 0 of 5; docs/BENCHMARKS.md)",
}
"""The one override most likely to help a learner that ends below the threshold, by profile (every
profile the main job's and Q-learning's recipes run, ``irdrc/conf/algo``)."""


def end_warning(
    history: list[dict[str, Any]],
    advice: str | None = None,
    *,
    key: str = "optimality_ratio",
    threshold: float | None = None,
    of: str = "the optimum",
    best_among: str | None = None,
) -> str | None:
    """One warning line when a learner's final greedy policy is below ``threshold`` (default
    ``END_THRESHOLD``) of the optimum, or more than ``END_SLACK`` below its own best evaluation,
    saying where that best evaluation was and, with ``advice``, the override to try; ``None`` when
    every learner ends well. ``key`` is the history's column read and ``of`` what it is a share of
    (a learner held to a constraint: ``lp_ratio``, "the LP's packets"). With ``best_among`` (a
    history column, ``meets_target``), only the evaluations where it is true count as a best: a
    plan that breaks its target is not a best to fall from. The exact model only scores: the
    warning does not change which network the run returns."""
    threshold = END_THRESHOLD if threshold is None else threshold
    runs: dict[int, list[dict[str, Any]]] = {}
    for e in history:
        runs.setdefault(int(e.get("learner", 0)), []).append(e)
    bad = []
    for learner, hist in sorted(runs.items()):
        final = float(hist[-1][key])
        eligible = [e for e in hist if best_among is None or float(e[best_among]) > 0]
        best = max(eligible, key=lambda e: float(e[key])) if eligible else None
        gap = float(best[key]) - final if best is not None else 0.0
        if final < threshold or gap > END_SLACK:
            why = [f"below {threshold}"] if final < threshold else []
            if gap > END_SLACK:
                why.append(f"{gap:.4f} below its best")
            where = (
                f"its best evaluation was {float(best[key]):.4f} at {int(best['env_steps'])} "
                "env steps"
                if best is not None
                else f"none of its evaluations had {best_among}"
            )
            bad.append((learner, f"{final:.4f} of {of} ({', '.join(why)}); {where}"))
    if not bad:
        return None
    tail = f"; try {advice}" if advice else ""
    if len(runs) == 1:
        return f"warning: the final greedy policy is {bad[0][1]} (metrics.csv){tail}"
    shown = [f"  learner {i}: {text}" for i, text in bad[:WARNING_LEARNERS]]
    if len(bad) > WARNING_LEARNERS:
        shown.append(f"  … and {len(bad) - WARNING_LEARNERS} more (learners.csv, metrics.csv)")
    return "\n".join(
        [f"warning: {len(bad)} of {len(runs)} learners end badly (metrics.csv){tail}", *shown]
    )
