"""The safe learner (``learner=safe``; MODEL.md § E, safe learning): the vehicle's cumulative miss
detection — events missed so far over events so far, on its own stream — stays at or under the
target m* at every step, while it climbs toward the constrained optimum (the LP of MODEL.md § A).

Two parts:

- **The budget.** With E events so far and M of them missed, M ≤ m*·E must hold after every step.
  A comm step can miss one event, so the vehicle may send only while the slack m*·E − M is at
  least 1 − m*: then even a miss leaves M + 1 ≤ m*·(E + 1). Otherwise it senses. A radar that
  detects every event (P_d = 1) never misses in radar mode, so with it the bound holds at every
  step of every run, with probability 1; it starts in radar mode (no slack yet) and earns its
  first comm step after (1 − m*)/m* detected events (19 at m* = 0.05). A radar that misses events
  (P_d < 1) can break it in radar mode, which no choice of mode prevents: the budget then holds
  only as far as the radar's own misses allow.
- **The plan.** Before the first episode and whenever its data has doubled since the last plan
  (before episodes 1, 2, 4, 8, …) it finds the LP's optimum — the most packets at miss target m* —
  on the posterior-mean model of what it has counted (``irdrc.online.form``: told the model's
  form, not its numbers), the noisy-or sampler run ``GIBBS_SWEEPS`` sweeps on before it (the mean
  is drawn from where it stands); an infeasible plan is radar everywhere. It solves the LP's
  Lagrangian dual (``irdrc.core.cmdp_dual``: policy iteration, one LU of the chain per
  evaluation), which reaches the LP's optimum in a fraction of the LP's time at every size, past
  the dense limit included. It acts by the plan wherever the budget allows. A level of the
  channel whose capacity has not shown yet is planned as carrying every packet (optimism), so the
  plan tries it. Its greedy policy, the one it would deploy, is the plan.

By default the vehicle waits for each plan. With ``evaluations_per_step`` k ≥ 1 it plans beside its
acting instead (``learner=safe_anytime``): k units of work after each step — ``GIBBS_BATCH`` of the
sampler's sweeps, then the posterior-mean model, then one policy evaluation at a time of the LP's
Lagrangian dual (``irdrc.core.cmdp_dual``, the LP's optimum) — the vehicle acting on its last plan,
under the budget, until the new one is ready. Data that doubles meanwhile restarts the plan on the
newer counts. ``observe`` says when a plan comes into force.

Its behaviour policy in the ledger is the plan, or radar everywhere while the budget forbids
sending at the episode's start: the budget's interventions within an episode are not in the exact
ledger (the realised counts have them).

Its **stated confidence** in the plan (``plan_confidence``): the budget holds the vehicle's count,
but the plan deployed alone is only as good as the data behind it. Over models drawn from the
posterior of the counts, it gives the plan's long-run miss detection (mean and standard deviation)
and the share of draws in which it is at or under m*.
"""

from __future__ import annotations

import dataclasses
import random
from typing import TYPE_CHECKING, Any

import numpy as np
import torch

from irdrc.core.chains import chain
from irdrc.core.cmdp import (
    InfeasibleTarget,
    SolverFailed,
    build_constraints,
    lp_standing,
    objective_table,
    solve_cmdp,
)
from irdrc.core.cmdp_dual import DualPlanner, solve_cmdp_dual
from irdrc.core.params import Params
from irdrc.core.sizes import dense_fit_states
from irdrc.core.stream import Step
from irdrc.online.configs import SafeConfig
from irdrc.online.form import Estimate, FormCounts
from irdrc.online.loop import StreamLearner, planning_report
from irdrc.online.qlearning import tuple_state

if TYPE_CHECKING:
    from irdrc.core.metrics import Metrics

GIBBS_SWEEPS = 200
"""Sweeps of the noisy-or sampler before each plan (``FormCounts.advance``): from its cold start the
posterior mean overstates the event probabilities, and the plan sends less than the data allow."""


GIBBS_BATCH = 25
"""Sweeps of the noisy-or sampler in one unit of planning work beside the acting (about as long as
one policy evaluation on ``multilevel``)."""


CONFIDENCE_DRAWS = 50
"""Posterior models drawn for ``SafeLearner.plan_confidence``: its probability then has a standard
error of at most 0.07 (√(0.25/50))."""


class SafeLearner(StreamLearner):
    """A miss budget and a plan at the LP's optimum (see the module docstring).

    Args:
        cfg: the profile (``irdrc.online.configs.SAFE``).
        params: the scenario; only its observation space is read (``FormCounts``).
        seed: the seed of its draws between a randomised plan's modes.
    """

    def __init__(self, cfg: SafeConfig, params: Params, seed: int = 0) -> None:
        self.cfg, self.name = cfg, cfg.name
        self.counts = FormCounts(params, cfg.prior_count)
        self.num_states = params.env.num_states
        self.rng = random.Random(seed)
        self.gibbs = np.random.default_rng(seed)
        self.events = 0
        self.missed = 0
        self.radar = torch.ones(self.num_states, dtype=torch.int64)
        self.plan = torch.nn.functional.one_hot(self.radar, 2).to(torch.float64)
        self.comm = [0.0] * self.num_states  # P(comm | s) of the plan
        self.updates = 0
        self.forced = 0  # radar steps the budget imposed on the plan
        self.planned_at = -1  # the stream's steps at the last plan
        # beside the acting: the plan being made (sweeps left; its model, its planner), each
        # plan's steps from its data to its coming into force, plans begun
        self.planning = False
        self.sweeps_left = 0
        self.pending_estimate: Estimate | None = None
        self.planner: DualPlanner | None = None
        self.begun_at = 0
        self.lags: list[int] = []
        self.begun = 0

    @property
    def slack(self) -> float:
        """m*·events − missed: how far the cumulative miss detection is under the target."""
        return self.cfg.target_miss * self.events - self.missed

    def _may_send(self) -> bool:
        return self.slack >= 1.0 - self.cfg.target_miss

    def _solve(self) -> torch.Tensor:
        """The plan the waiting profile adopts: the planner (``_begin_planner``) on the
        posterior-mean model of the counts so far, run to the end."""
        self._begin_planner(self.counts.estimate())
        plan = None
        while plan is None:
            plan = self._plan_step()
        self.planner = self.pending_estimate = None
        return plan

    def begin_episode(self, episode: int) -> None:
        steps = self.counts.steps
        if self.planned_at >= 0 and steps < 2 * max(self.planned_at, 1):
            return
        self.planned_at = steps
        if self.cfg.evaluations_per_step:
            self.begun += 1
            self.planning, self.begun_at, self.sweeps_left = True, steps, GIBBS_SWEEPS
            self.pending_estimate = self.planner = None
            return
        self.counts.advance(self.gibbs, GIBBS_SWEEPS)
        self._adopt(self._solve())

    def _adopt(self, plan: torch.Tensor) -> None:
        self.plan = plan
        self.comm = self.plan[:, 0].tolist()
        self.updates += 1

    def _begin_planner(self, est: Estimate) -> None:
        model = self.counts.model(est)
        self.pending_estimate = est
        self.planner = DualPlanner(
            chain(model),
            objective_table(model, "throughput"),
            build_constraints(model, self.cfg.target_miss)[0],
        )

    def _work(self) -> torch.Tensor | None:
        """One unit of the plan being made; the plan when it is ready."""
        if self.sweeps_left:
            batch = min(GIBBS_BATCH, self.sweeps_left) if self.counts.noisy_or else self.sweeps_left
            self.counts.advance(self.gibbs, batch)
            self.sweeps_left -= batch
            return None
        if self.planner is None:
            self._begin_planner(self.counts.estimate())
            return None
        return self._plan_step()

    def _plan_step(self) -> torch.Tensor | None:
        """One policy evaluation of the planner; the plan when it is ready: the LP's optimal
        policy [S, 2] on the planner's model, radar everywhere where no policy meets the target,
        the plan so far where the planner cannot settle it."""
        assert self.planner is not None
        try:
            result = self.planner.step()
        except InfeasibleTarget:
            return torch.nn.functional.one_hot(self.radar, 2).to(torch.float64)
        except SolverFailed:
            return self.plan
        return None if result is None else result.policy

    def act(self, state: int) -> int:
        p = self.comm[state]
        if p <= 0.0:
            return 1
        if not self._may_send():
            self.forced += 1
            return 1
        return 0 if p >= 1.0 or self.rng.random() < p else 1

    def observe(self, state: int, action: int, step: Step) -> bool | None:
        self.counts.observe(state, action, step)
        self.events += step.event
        self.missed += step.missed
        for _ in range(self.cfg.evaluations_per_step if self.planning else 0):
            plan = self._work()
            if plan is not None:
                self.planning, self.pending_estimate, self.planner = False, None, None
                self.lags.append(self.counts.steps - self.begun_at)
                self._adopt(plan)
                return True
        return None

    def end_episode(self, episode: int) -> dict[str, float]:
        return {"slack": self.slack, "forced_radar": self.forced}

    def behaviour(self) -> torch.Tensor:
        if self._may_send():
            return self.plan
        return torch.nn.functional.one_hot(self.radar, 2).to(torch.float64)

    def greedy(self) -> torch.Tensor:
        return self.plan

    def info(self) -> dict[str, Any]:
        k = self.cfg.evaluations_per_step
        if not k:
            return {}
        return planning_report("evaluations_per_step", k, self.lags, self.begun, self.planning)

    def plan_confidence(self, draws: int = CONFIDENCE_DRAWS) -> dict[str, float]:
        """The plan's long-run miss detection under ``draws`` models drawn from the posterior of
        the counts so far: ``miss_mean``, ``miss_sd`` and ``p_within_target``, the share of draws
        in which it is at or under m* (the stated confidence that the plan meets the target
        without the budget). Drawn on a generator fixed by the data; the learner's own sampler
        state is left as it was."""
        from irdrc.core.exact.solve import metrics_from_occupancy, stationary_occupancy

        if draws < 2:
            raise ValueError(f"plan_confidence: draws={draws}, at least 2 are needed for a spread")
        rng = np.random.default_rng([self.counts.steps, self.events, self.missed])
        fire = [f.copy() for f in self.counts.fire]
        miss = []
        try:
            for _ in range(draws):
                model = self.counts.model(self.counts.estimate(rng))
                occ = stationary_occupancy(model, self.plan)
                miss.append(metrics_from_occupancy(model, occ).miss_detection)
        finally:
            self.counts.fire = fire
        values = np.asarray(miss)
        return {
            "miss_mean": float(values.mean()),
            "miss_sd": float(values.std(ddof=1)),
            "p_within_target": float(np.mean(values <= self.cfg.target_miss + 1e-12)),
            "draws": draws,
        }

    def state_dict(self) -> dict[str, Any]:
        return {
            "counts": self.counts.state_dict(),
            "rng": self.rng.getstate(),
            "events": self.events,
            "missed": self.missed,
            "plan": self.plan,
            "updates": self.updates,
            "forced": self.forced,
            "planned_at": self.planned_at,
            "gibbs": self.gibbs.bit_generator.state,
            "pending": self._pending_state(),
            "lags": list(self.lags),
            "begun": self.begun,
        }

    def _pending_state(self) -> dict[str, Any] | None:
        if not self.planning:
            return None
        est = self.pending_estimate
        return {
            "sweeps_left": self.sweeps_left,
            "begun_at": self.begun_at,
            "estimate": None if est is None else dataclasses.asdict(est),
            "planner": None if self.planner is None else self.planner.state_dict(),
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.counts.load_state_dict(state["counts"])
        self.rng.setstate(tuple_state(state["rng"]))
        self.events, self.missed = int(state["events"]), int(state["missed"])
        self.plan = state["plan"]
        self.comm = self.plan[:, 0].tolist()
        self.updates, self.forced = int(state["updates"]), int(state["forced"])
        self.planned_at = int(state["planned_at"])
        self.gibbs.bit_generator.state = state["gibbs"]
        self.lags, self.begun = list(state.get("lags", [])), int(state.get("begun", 0))
        self.sweeps_left, self.pending_estimate, self.planner = 0, None, None
        pending = state.get("pending")
        self.planning = pending is not None
        if pending is not None:
            self.sweeps_left, self.begun_at = int(pending["sweeps_left"]), int(pending["begun_at"])
            if pending["estimate"] is not None:
                self._begin_planner(Estimate(**pending["estimate"]))
                if pending["planner"] is not None:
                    assert self.planner is not None
                    self.planner.load_state_dict(pending["planner"])


class ConstrainedScorer:
    """Scores a safe learner's greedy policy against the constrained optimum (the LP at m*; past the
    dense limit, the LP's optimum on its dual, ``solve_cmdp_dual``): its exact metrics, and
    ``extra`` columns — ``lp_ratio`` (its packets per step over the LP's) and ``meets_target``
    (its long-run miss detection ≤ m*).

    Args:
        scorer: the scenario's exact scorer.
        target_miss: m*.
    """

    def __init__(self, scorer: Any, target_miss: float) -> None:
        self.scorer = scorer
        self.target_miss = float(target_miss)
        if scorer.model.num_states <= dense_fit_states():
            self.lp = solve_cmdp(scorer.model, target_miss)
        else:
            self.lp = solve_cmdp_dual(scorer.model, target_miss)
        self.optimal_metrics = scorer.optimal_metrics

    def metrics(self, table: torch.Tensor) -> Metrics:
        """The exact metrics of ``table`` (``Scorer.metrics``)."""
        return self.scorer.metrics(table)

    def extra(self, table: torch.Tensor) -> dict[str, float]:
        """``lp_ratio`` and ``meets_target`` of ``table``."""
        ratio, meets = lp_standing(self.scorer.metrics(table), self.lp.value, self.target_miss)
        return {"lp_ratio": ratio, "meets_target": float(meets)}
