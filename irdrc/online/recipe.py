"""``recipes/online.py`` — one vehicle learning on the road from its own stream (MODEL.md § E), scored
exactly while it learns: the greedy policy against the optimum, and the price of learning (the
regret and the missed events of the policy it behaved by) every episode.

    python recipes/online.py                                 # posterior sampling on the model's form
    python recipes/online.py learner=dqn env=multilevel      # DQN on one stream, told nothing
    python recipes/online.py learner=posterior_anytime       # it plans beside its acting
    python recipes/online.py learner=safe algo.target_miss=0.1
    python recipes/online.py learner=qlearning_paper algo.episodes=600
    python recipes/online.py learner=watchful.py:Watchful   # your own (docs/ONLINE.md)
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, fields, replace
from functools import partial
from typing import TYPE_CHECKING, Any

from irdrc.core.checks import build, counted
from irdrc.core.params import Params
from irdrc.online.configs import (
    PROFILES,
    SAFE_LEARNERS,
    learner_config,
    recorded_algo,
)
from irdrc.online.own import DOC, is_own, own_learner_config, recorded_keys, resumable
from irdrc.runs.compose import Composed
from irdrc.runs.grid import override_key
from irdrc.runs.limits import check_exact
from irdrc.runs.resume import refuse_finished
from irdrc.runs.sections import Learning, Plot, check_eval_period, scenario_field

if TYPE_CHECKING:
    from irdrc.runs.scaffold import Run

NAME = "online"
RESUMABLE = True
SWEEP_DEFAULTS = ("progress=false", "logger=none")
ALGO_KEYS = frozenset(
    f.name for profile in PROFILES.values() for f in fields(profile) if f.name != "name"
)
"""Every ``algo.*`` key a learner on one stream reads (each learner checks its own)."""

ADVICE = {
    "dqn": "learner=posterior (told the model's form, it needs far fewer episodes: docs/ONLINE.md)",
    "dqn_paper": "learner=dqn (our profile on one stream: docs/ONLINE.md)",
    "qlearning": "learner=posterior (docs/ONLINE.md) or algo.episodes=1200",
    "qlearning_paper": "learner=qlearning (step sizes 1/k: docs/ONLINE.md)",
    "posterior": "algo.episodes={twice}",
    "posterior_anytime": "algo.episodes={twice}",
    "safe": "algo.episodes={twice}",
    "safe_anytime": "algo.episodes={twice}",
}
"""What a run that ends below the optimum is told to try, per learner (``{twice}``: twice its
episodes; a learner of one's own is told that too)."""

SAFE_END_THRESHOLD = 0.95
"""A ``learner=safe`` run whose final plan sends less than this share of the LP's packets ends with
a warning (it is read against the LP at its ``target_miss``, not the unconstrained optimum)."""

DEFAULT_LEARNER = "posterior"
"""``learner=`` when none is given (``irdrc/conf/online.yaml`` says the same)."""


def algo_keys(args: list[str]) -> frozenset[str]:
    """The ``algo.*`` keys of the command line ``args`` beyond ``ALGO_KEYS``, with a learner of
    one's own (``learner=PATH.py:Class``): its constructor's keywords, checked against it when the
    config is built."""
    learners = [a.split("=", 1)[1] for a in args if override_key(a) == "learner" and "=" in a]
    if not learners or not is_own(learners[-1]):
        return frozenset()
    return frozenset(override_key(a)[5:] for a in args if override_key(a).startswith("algo."))


def misplaced_override(args: list[str]) -> str | None:
    """What to say of ``device=…``, which online refused: one vehicle's stream runs on the CPU."""
    for arg in args:
        if override_key(arg) == "device":
            return (
                f"{arg}: online runs one vehicle's stream on the CPU, one step at a time "
                "(num_threads=… sets its threads); device is a key of the recipes that simulate "
                "many vehicles at once (recipes/dqn.py device=cuda)"
            )
    return None


def _algo(data: Any, prefix: str) -> Any:
    learner = data.get("learner", DEFAULT_LEARNER)
    if is_own(learner):
        return own_learner_config(learner, data.get("algo"))
    return learner_config(learner, data.get("algo") or {})


@dataclass(frozen=True)
class Config(Learning):
    """The keys of ``irdrc/conf/online.yaml``."""

    params: Params = scenario_field()
    learner: str = DEFAULT_LEARNER
    algo: Any = field(default=None, metadata={"keys": ("algo",), "build": _algo})
    plot: Plot = field(default_factory=Plot)

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.algo is None:  # the learner's profile (an unknown learner refused there)
            object.__setattr__(self, "algo", _algo({"learner": self.learner}, "algo."))
        if is_own(self.learner):  # its spec as the run records it (a file's path absolute)
            object.__setattr__(self, "learner", self.algo.learner)

    @property
    def total_frames(self) -> int:
        """Env steps of the whole stream."""
        return self.algo.episodes * self.params.env.horizon


def load(composed: Composed, resume: dict[str, Any] | None = None) -> Config:
    """The typed config, checked: values, the exact model's size, the evaluation period, what a
    resumed run has left."""
    cfg = build(Config, composed.cfg)
    check_exact(cfg.params)
    if cfg.params.env.actions != "binary":
        raise ValueError(
            f"env.actions={cfg.params.env.actions}: a vehicle on one stream chooses comm or radar "
            "each step (env.actions=binary); the radar share is learned by recipes/sac.py "
            "(continuous), recipes/ppo.py, or recipes/dqn.py algo=dqn_levels (levels)"
        )
    if cfg.eval.every_frames is None:  # every episode, whatever its length
        cfg = replace(cfg, eval=replace(cfg.eval, every_frames=cfg.params.env.horizon))
    explicit = "eval.every_frames" in composed.explicit
    check_eval_period(cfg.eval.every_frames, cfg.total_frames, explicit)
    if resume is not None and is_own(cfg.learner) and not resumable(cfg.algo):
        raise ValueError(
            f"resume={cfg.resume}: learner={cfg.learner} defines no state_dict(), so a resumed "
            "run could not go on from where it stopped; give it state_dict() and "
            f"load_state_dict() ({DOC})"
        )
    if resume is not None:
        episodes = cfg.algo.episodes
        done = int(resume.get("episode", 0))
        refuse_finished(cfg.resume, done, episodes, "algo.episodes", episodes, unit="episodes")
    return cfg


def recorded(config: Config, cfg: dict[str, Any]) -> dict[str, Any]:
    """The composed config ``cfg`` as the run records it: ``algo`` holds the learner's whole
    profile, the command line's keys over it (``config.algo``), and a learner of one's own is
    named with its file's absolute path."""
    own = is_own(config.learner)
    algo = recorded_keys(config.algo) if own else recorded_algo(config.algo)
    return {**cfg, "learner": config.learner, "algo": algo}


def convergence(history: list[dict[str, Any]]) -> dict[str, Any]:
    """Episodes until the greedy policy first reaches 0.95 and 0.99 of the optimum, and the share
    of the later evaluations that stay at or above 0.99 (None where it never reached it)."""
    first = {
        t: next((r["episodes"] for r in history if r["optimality_ratio"] >= t), None)
        for t in (0.95, 0.99)
    }
    later = [r for r in history if first[0.99] is not None and r["episodes"] > first[0.99]]
    stay = sum(r["optimality_ratio"] >= 0.99 for r in later) / len(later) if later else None
    return {"episodes_to_95": first[0.95], "episodes_to_99": first[0.99], "stay_99": stay}


def run(cfg: Config, run: Run) -> dict[str, Any]:
    """Learn on the stream, then finish the run directory as every learner's (``finish_learner``)
    with the ledger beside it."""
    from irdrc.core.exact import exact_scorer, require_ratio
    from irdrc.online.figures import plot_run
    from irdrc.online.learners import make_learner
    from irdrc.online.loop import learn_on_stream
    from irdrc.online.safe import SafeLearner
    from irdrc.runs.report import LearnerRun, end_warning, finish_learner

    run.threads(cfg.num_threads)
    run.make_logger(cfg.logger, cfg.algo.name)
    scorer = exact_scorer(cfg.params, cfg.optimum_gamma)
    require_ratio(scorer)
    greedy_scorer = None
    if cfg.learner in SAFE_LEARNERS:
        from irdrc.online.safe import ConstrainedScorer

        greedy_scorer = ConstrainedScorer(scorer, cfg.algo.target_miss)
    learner = make_learner(cfg.learner, cfg.algo, cfg.params, cfg.seed)
    with run.training(
        cfg.total_frames, cfg.algo.name, checkpoint=cfg.checkpoint, verbatim=True
    ) as hooks:
        record = learn_on_stream(
            learner,
            cfg.params,
            scorer,
            episodes=cfg.algo.episodes,
            seed=cfg.seed,
            eval_every_frames=cfg.eval.every_frames,
            hooks=hooks,
            resume=run.resume_state,
            greedy_scorer=greedy_scorer,
        )
    twice = 2 * cfg.algo.episodes  # what a run that ends short is told to try
    summary = finish_learner(
        run,
        LearnerRun.single(
            cfg,
            record,
            scorer,
            advice=ADVICE.get(cfg.learner, ADVICE["posterior"]).format(twice=twice),
            plot=(
                partial(
                    plot_run,
                    target_miss=cfg.algo.target_miss,
                    lp_threshold=SAFE_END_THRESHOLD,
                    lp_regret_per_step=lp_cost(scorer, greedy_scorer),
                )
                if greedy_scorer is not None
                else plot_run
            ),
            end_check=(
                partial(
                    end_warning,
                    advice=ADVICE["safe"].format(twice=twice),
                    key="lp_ratio",
                    threshold=SAFE_END_THRESHOLD,
                    of="the LP's packets",
                    best_among="meets_target",
                )
                if greedy_scorer is not None
                else None
            ),
            reference=lp_reference(greedy_scorer.lp, cfg.algo.target_miss)
            if greedy_scorer is not None
            else None,
        ),
    )
    ledger = record.history[-1]
    summary["learner"] = cfg.learner
    summary["episodes"] = record.episodes
    summary.update(convergence(record.history))
    summary["ledger"] = {k: v for k, v in record.info.pop("ledger").items()}
    summary.update({k: v for k, v in record.info.items() if k.startswith("seconds_")})
    summary["decisions_over_1ms"] = record.info["decisions_over_1ms"]
    summary["env_steps_per_second"] = record.env_steps / max(record.wall_seconds, 1e-9)
    if greedy_scorer is not None:
        summary["target_miss"] = cfg.algo.target_miss
        summary["lp"] = {
            "throughput": greedy_scorer.lp.value,
            "miss_detection": greedy_scorer.lp.metrics.miss_detection,
            "regret": lp_cost(scorer, greedy_scorer) * record.env_steps,
        }
        summary["lp_ratio"] = ledger["lp_ratio"]
        if isinstance(learner, SafeLearner):
            summary["plan_confidence"] = learner.plan_confidence()
    print_ledger(ledger, summary, cfg)
    run.finish(summary, interrupted_at=record.env_steps if record.interrupted else None)
    return summary


def lp_cost(scorer: Any, constrained: Any) -> float:
    """What the target itself costs per step: the optimum's long-run reward less the LP's. Over a
    run's steps, the part of a safe learner's regret that no learner held to the target avoids."""
    return float(scorer.optimal_metrics.avg_reward - constrained.lp.metrics.avg_reward)


def lp_reference(lp: Any, target_miss: float) -> tuple[str, str, Any]:
    """What a safe learner's plan is set against in the printout: the LP's likelier mode per state
    (``LearnerRun.reference``), named with the states where it randomises."""
    n = len(lp.randomised)
    where = f" (its likelier mode in the {n} state{'s' if n != 1 else ''} where it randomises)"
    return f"the LP at target_miss={target_miss}" + (where if n else ""), "LP", lp.policy.argmax(-1)


def _miss_text(x: float) -> str:
    return "n/a (no event yet)" if math.isnan(x) else f"{x:.4f}"


def print_ledger(row: dict[str, Any], summary: dict[str, Any], cfg: Config) -> None:
    """The price of learning, in a few lines."""
    first, stay = summary["episodes_to_99"], summary["stay_99"]
    if first is None:
        conv = "never ≥ 0.99"
    else:
        conv = f"first ≥ 0.99 after {first} episode{'' if first == 1 else 's'}"
        conv += (
            " (the last evaluation)"
            if stay is None
            else f", ≥ 0.99 at {stay:.0%} of the evaluations since"
        )
    print(
        f"\nthe price of learning over {counted(summary['episodes'], 'episode')} (exact, from the behaviour "
        f"policy of each episode; realised on the stream in brackets):\n"
        f"  regret {row['regret']:.1f} ({row['realised_regret']:.1f}) in reward units; "
        f"missed events {row['expected_missed']:.1f} ({row['realised_missed']:.0f}) where the "
        f"optimum misses {row['floor_missed']:.1f}; packets sent {row['expected_sent']:.0f} "
        f"({row['realised_sent']:.0f})\n"
        f"  cumulative miss detection {_miss_text(row['cumulative_miss_detection'])}; greedy policy: "
        f"{conv}"
    )
    if cfg.learner in SAFE_LEARNERS:
        print(
            f"  target_miss={cfg.algo.target_miss}: the greedy plan sends {row['lp_ratio']:.4f} of "
            f"the LP's packets, its long-run miss detection {row['miss_detection']:.4f}"
        )
        lp_regret = summary["lp"]["regret"]
        print(
            f"  the LP itself pays {lp_regret:.1f} of that regret over these steps (the target's "
            f"own cost): learning under the target cost {row['regret'] - lp_regret:.1f}"
        )
        conf = summary["plan_confidence"]
        print(
            f"  what its data say of that miss detection: {conf['miss_mean']:.4f} ± "
            f"{conf['miss_sd']:.4f} (posterior mean ± sd), at or under the target with "
            f"probability {conf['p_within_target']:.2f}"
        )
    print(
        f"  {summary['env_steps_per_second']:.0f} env steps/s of training (evaluations included); "
        f"its slowest decision took {1e3 * summary['seconds_slowest_decision']:.1f} ms, "
        f"{summary['decisions_over_1ms']} of {summary['env_steps']} over 1 ms"
    )
    plans = summary.get("planning")
    if plans is not None:
        made, sweeps = plans["plans_made_beside_acting"], "sweeps_per_step" in plans
        k = plans["sweeps_per_step" if sweeps else "evaluations_per_step"]
        work = (
            f"{k} sweep{'' if k == 1 else 's'} of value iteration"
            if sweeps
            else f"{k} unit{'' if k == 1 else 's'} of work (a batch of sweeps, the model, or "
            "one policy evaluation of the LP's dual)"
        )
        since, newer = ("their draw", "a newer draw") if sweeps else ("their data", "newer data")
        when = (
            f"{made} plans, in force a median of {plans['plan_lag_steps_median']} steps after "
            f"{since} (at most {plans['plan_lag_steps_max']})"
            if made
            else "no plan in force yet"
        )
        print(
            f"  it planned beside its acting, {work} a step: {when}; "
            f"{plans['plans_superseded']} replaced by {newer} before they were ready"
        )
