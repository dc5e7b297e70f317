"""The price of learning (MODEL.md § E), exact: what a vehicle pays while it learns, counted from the
behaviour policy in force in each period (exploration included) on the exact model, beside what the
stream itself recorded.

With g* the optimum's long-run reward per step and g(π) a policy's, over periods k of n_k steps with
behaviour policy π_k:

- regret R = Σ_k n_k·(g* − g(π_k)), in reward units: the long-run approximation of the expected
  regret, exact for each period's policy;
- expected missed events Σ_k n_k·e(π_k), e(π) the long-run missed events per step, beside the
  **floor** Σ_k n_k·e(π*), what the optimum itself misses in the same steps; expected events,
  packets sent and dropped likewise;
- the realised counts (rewards, events, events missed, packets sent and dropped) and the realised
  regret g*·n − Σ rewards: noisy, model-free, a check on the exact figures.

A period is one episode, or a part of one where the learner announces a change of its behaviour
policy (posterior sampling draws a new model whenever its data doubles) or reports one as it
happens (a plan made beside the acting comes ready); a change it does neither for (a gradient
step of DQN) is scored with the policy of the period's start. Every learner's
run reports the same ``Ledger``: it reads only the behaviour policy the learner exposes.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields
from typing import Any

import torch

LEDGER_FIELDS = (
    "behaviour_ratio",
    "regret",
    "expected_missed",
    "floor_missed",
    "expected_events",
    "expected_sent",
    "expected_dropped",
    "realised_regret",
    "realised_reward",
    "realised_events",
    "realised_missed",
    "realised_sent",
    "realised_dropped",
    "cumulative_miss_detection",
)
"""The ledger's columns in ``metrics.csv`` (cumulative from the run's first step):
``behaviour_ratio`` is g(π)/g* of the behaviour policy of the latest period;
``cumulative_miss_detection`` the realised missed events over the realised events (NaN before
the first event)."""


@dataclass
class Tally:
    """Realised counts of the stream (sums over its steps)."""

    steps: int = 0
    reward: float = 0.0
    events: int = 0
    missed: int = 0
    sent: int = 0
    dropped: int = 0

    def __iadd__(self, other: Tally) -> Tally:
        for f in fields(self):
            setattr(self, f.name, getattr(self, f.name) + getattr(other, f.name))
        return self


@dataclass
class Expected:
    """Exact expected sums over the periods scored so far."""

    steps: int = 0
    reward: float = 0.0
    regret: float = 0.0
    missed: float = 0.0
    floor_missed: float = 0.0
    events: float = 0.0
    sent: float = 0.0
    dropped: float = 0.0


class Ledger:
    """The price of learning of one stream (see the module docstring).

    Args:
        scorer: the scenario's exact scorer (``irdrc.core.exact.Scorer``): the optimum's expected
            sums and any policy's.
    """

    def __init__(self, scorer: Any) -> None:
        self.scorer = scorer
        self.optimum = scorer.optimal_sums
        self.expected = Expected()
        self.realised = Tally()
        self.behaviour_ratio = math.nan

    @property
    def g_star(self) -> float:
        """The optimum's long-run reward per step."""
        return float(self.optimum["reward"])

    def add(self, behaviour: torch.Tensor, realised: Tally) -> None:
        """One period: ``realised.steps`` steps with the ``behaviour`` policy ([S] actions or
        [S, A] probabilities) in force, and what the stream recorded in them."""
        n = realised.steps
        s = self.scorer.sums(behaviour)
        e, opt = self.expected, self.optimum
        e.steps += n
        e.reward += n * s["reward"]
        e.regret += n * (opt["reward"] - s["reward"])
        e.missed += n * s["missed"]
        e.floor_missed += n * opt["missed"]
        e.events += n * s["event"]
        e.sent += n * s["sent"]
        e.dropped += n * s["dropped"]
        self.realised += realised
        g = self.g_star
        self.behaviour_ratio = s["reward"] / g if g != 0 else math.nan

    def row(self) -> dict[str, float]:
        """The ledger so far, as ``LEDGER_FIELDS``."""
        e, r = self.expected, self.realised
        return {
            "behaviour_ratio": self.behaviour_ratio,
            "regret": e.regret,
            "expected_missed": e.missed,
            "floor_missed": e.floor_missed,
            "expected_events": e.events,
            "expected_sent": e.sent,
            "expected_dropped": e.dropped,
            "realised_regret": self.g_star * r.steps - r.reward,
            "realised_reward": r.reward,
            "realised_events": float(r.events),
            "realised_missed": float(r.missed),
            "realised_sent": float(r.sent),
            "realised_dropped": float(r.dropped),
            "cumulative_miss_detection": r.missed / r.events if r.events else math.nan,
        }

    def state_dict(self) -> dict[str, Any]:
        """The sums so far (a checkpoint's entry)."""
        return {
            "expected": dict(vars(self.expected)),
            "realised": dict(vars(self.realised)),
            "behaviour_ratio": self.behaviour_ratio,
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore ``state_dict``'s sums."""
        self.expected = Expected(**state["expected"])
        self.realised = Tally(**state["realised"])
        self.behaviour_ratio = float(state["behaviour_ratio"])
