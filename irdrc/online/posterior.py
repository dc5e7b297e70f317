"""Posterior sampling on the model's form (``learner=posterior``; MODEL.md § E): the structure-aware
learner that the model-free ones are read against.

It is told the model's form and nothing else (``irdrc.online.form``), and plans every number it
has not seen yet optimistically. Its first step, before any data, picks each mode with probability
1/2. Before every later episode, and whenever the stream's length doubles (after 1, 2, 4, …, 256
steps in the first episode, 512 in the second, …), it draws one model from the posterior of every
number its counts allow (Dirichlet rows for the chains, Beta for the event, detection and
false-alarm probabilities, Gamma for the arrival rates) and acts by that model's optimal policy
until the next draw, planned exactly on the factored operator with value iteration at the
optimum's discount (posterior sampling for reinforcement learning, Osband, Russo and Van Roy 2013,
with the doubling draws of Ouyang et al. 2017's dynamic episodes). Its greedy policy, the one it
would deploy, is the plan of the posterior mean.

By default the vehicle waits for each plan. With ``sweeps_per_step`` k ≥ 1 it plans beside its
acting instead: k sweeps of value iteration after each step (``ValueIteration``), starting from
the last plan's values, the vehicle acting on its last plan until the new one is ready; a draw
made before then restarts the plan on the newer model from the values reached. ``observe`` says
when a plan comes into force, and the ledger scores each side with its own policy.
"""

from __future__ import annotations

import dataclasses
import random
from typing import Any

import numpy as np
import torch

from irdrc.core.exact import ValueIteration, value_iteration
from irdrc.core.params import Params
from irdrc.core.stream import Step
from irdrc.online.configs import PosteriorConfig
from irdrc.online.form import Estimate, FormCounts
from irdrc.online.loop import StreamLearner, planning_report
from irdrc.online.qlearning import tuple_state


class PosteriorSampling(StreamLearner):
    """Posterior sampling, a plan per episode and per doubling of the data (see the module
    docstring).

    Args:
        cfg: the profile (``irdrc.online.configs.POSTERIOR``).
        params: the scenario; only its observation space is read (``FormCounts``).
        seed: the posterior draws' seed.
    """

    def __init__(self, cfg: PosteriorConfig, params: Params, seed: int = 0) -> None:
        self.cfg, self.name = cfg, cfg.name
        self.counts = FormCounts(params, cfg.prior_count)
        self.rng = np.random.default_rng(seed)
        self.plan: list[int] | None = None  # None: no data yet, each mode w.p. 1/2
        self.coin = random.Random(seed)
        self.num_states = params.env.num_states
        self.updates = 0
        self._greedy: torch.Tensor | None = None
        self.values: torch.Tensor | None = None  # where the next plan made beside acting starts
        self.pending: ValueIteration | None = None  # that plan, while it is being made
        self.pending_estimate: Estimate | None = None  # the model it is made on
        self.drawn_at = 0  # the stream's steps when the pending plan's model was drawn
        self.lags: list[int] = []  # steps from each such plan's draw to its coming into force
        self.begun = 0  # plans begun beside the acting

    def _solve(self, est: Any) -> torch.Tensor:
        model = self.counts.model(est)
        return value_iteration(model, gamma=self.cfg.gamma, tol=self.cfg.tol).policy

    def _draw(self) -> None:
        """A new plan: the optimum of one model drawn from the posterior (made now, or begun)."""
        est = self.counts.estimate(self.rng)
        if not self.cfg.sweeps_per_step:
            self.plan = self._solve(est).tolist()
            self.updates += 1
            return
        if self.pending is not None:
            self.values = self.pending.values
        self.begun += 1
        self._begin(est, self.values)
        self.drawn_at = self.counts.steps

    def _begin(self, est: Estimate, values: torch.Tensor | None) -> None:
        """Begin the plan of the drawn model ``est`` from ``values``."""
        model = self.counts.model(est)
        self.pending = ValueIteration(model, self.cfg.gamma, self.cfg.tol, values)
        self.pending_estimate = est

    def begin_episode(self, episode: int) -> None:
        if self.counts.steps:
            self._draw()

    def switches(self, episode: int, horizon: int) -> tuple[int, ...]:
        lo, hi = episode * horizon, (episode + 1) * horizon
        return tuple(2**k - lo for k in range(hi.bit_length()) if lo < 2**k < hi)

    def switch(self, steps: int) -> None:
        self._draw()

    def act(self, state: int) -> int:
        if self.plan is None:
            return self.coin.randrange(2)
        return self.plan[state]

    def observe(self, state: int, action: int, step: Step) -> bool | None:
        self.counts.observe(state, action, step)
        self._greedy = None
        if self.pending is None:
            return None
        solution = self.pending.sweep(self.cfg.sweeps_per_step)
        if solution is None:
            return None
        self.plan, self.values = solution.policy.tolist(), solution.values
        self.pending = self.pending_estimate = None
        self.lags.append(self.counts.steps - self.drawn_at)
        self.updates += 1
        return True

    def behaviour(self) -> torch.Tensor:
        if self.plan is None:
            return torch.full((self.num_states, 2), 0.5, dtype=torch.float64)
        return torch.tensor(self.plan)

    def greedy(self) -> torch.Tensor:
        if self._greedy is None:
            self._greedy = self._solve(self.counts.estimate())
        return self._greedy

    def info(self) -> dict[str, Any]:
        k = self.cfg.sweeps_per_step
        if not k:
            return {}
        return planning_report(
            "sweeps_per_step", k, self.lags, self.begun, self.pending is not None
        )

    def state_dict(self) -> dict[str, Any]:
        pending = None
        if self.pending is not None and self.pending_estimate is not None:
            pending = {
                "estimate": dataclasses.asdict(self.pending_estimate),
                "values": self.pending.values,
                "iterations": self.pending.iterations,
                "drawn_at": self.drawn_at,
            }
        return {
            "counts": self.counts.state_dict(),
            "rng": self.rng.bit_generator.state,
            "coin": self.coin.getstate(),
            "plan": None if self.plan is None else list(self.plan),
            "updates": self.updates,
            "values": self.values,
            "pending": pending,
            "lags": list(self.lags),
            "begun": self.begun,
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.counts.load_state_dict(state["counts"])
        self.rng.bit_generator.state = state["rng"]
        self.coin.setstate(tuple_state(state["coin"]))
        self.plan = None if state["plan"] is None else list(state["plan"])
        self.updates = int(state["updates"])
        self._greedy = None
        self.values, self.pending = state.get("values"), None
        pending = state.get("pending")
        if pending is not None:
            self._begin(Estimate(**pending["estimate"]), pending["values"])
            assert self.pending is not None
            self.pending.iterations = int(pending["iterations"])
            self.drawn_at = int(pending["drawn_at"])
        self.lags = list(state.get("lags", []))
        self.begun = int(state.get("begun", 0))
