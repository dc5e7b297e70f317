"""One scorer family: a model's optimum, and the exact long-run metrics of any policy table against
it, cached (learners revisit the same greedy table often)."""

from __future__ import annotations

from typing import Any

import torch

from irdrc.core.exact.mdp import ExactMDP
from irdrc.core.exact.solve import (
    DEFAULT_OPTIMUM_GAMMA,
    metrics_from_sums,
    stationary_occupancy,
    value_iteration,
)
from irdrc.core.metrics import Metrics
from irdrc.core.params import Params
from irdrc.core.sizes import fits_dense

CacheKey = tuple[str, tuple[int, ...], bytes]
"""A policy table's cache key: its dtype, shape and bytes."""


class Scorer:
    """Exact stationary metrics of policy tables on one exact model, and its optimum.

    Attributes:
        model: the exact model (dense, factored, or a fleet's).
        optimal: value iteration's ``Solution`` at ``gamma``.
        optimal_metrics: the optimum's exact long-run metrics.
        optimal_sums: the optimum's long-run expectations per step (``sums``).
    """

    def __init__(self, model: ExactMDP, gamma: float = DEFAULT_OPTIMUM_GAMMA, tol: float = 1e-9):
        self.model = model
        self.optimal = value_iteration(model, gamma=gamma, tol=tol)
        self._cache: dict[CacheKey, Metrics] = {}
        self._sums: dict[CacheKey, dict[str, float]] = {}
        self.optimal_sums = model.sums(stationary_occupancy(model, self.optimal.policy))
        self.optimal_metrics = metrics_from_sums(model, self.optimal_sums)

    def policy(self, table: torch.Tensor) -> Any:
        """The model's policy for a learner's ``table`` (here the table itself; the fleet's scorer
        turns each vehicle's own table into the joint policy)."""
        return table

    def metrics(self, table: torch.Tensor) -> Metrics:
        """Exact stationary ``Metrics`` of the policy ``table`` ([S] actions or [S, A])."""
        return self._cache[self._score(table)]

    def sums(self, table: torch.Tensor) -> dict[str, float]:
        """The policy ``table``'s long-run expectations per step (``ExactMDP.sums``: ``reward``,
        ``event``, ``missed``, ``sent``, ``dropped`` …), the rates its metrics are made of."""
        return self._sums[self._score(table)]

    def _score(self, table: torch.Tensor) -> CacheKey:
        """The cache key of ``table``, its stationary occupancy scored once."""
        t = torch.as_tensor(table).cpu()
        key = (str(t.dtype), tuple(t.shape), t.numpy().tobytes())
        if key not in self._cache:
            sums = self.model.sums(stationary_occupancy(self.model, self.policy(t)))
            self._cache[key] = metrics_from_sums(self.model, sums)
            self._sums[key] = sums
        return key

    def ratio(self, table: torch.Tensor) -> float:
        """Average reward of ``table`` over the optimal average reward (both stationary)."""
        return self.metrics(table).avg_reward / self.optimal_metrics.avg_reward


def require_ratio(scorer: Any) -> None:
    """Refuse to score learners against an optimum that earns ≤ 0 per step.

    A learner is read as its long-run reward over the optimum's (MODEL.md); that ratio ranks
    policies only when the optimum earns more than 0 (with a negative optimum a worse policy would
    score above 1). ``scorer``: any scorer with ``optimal_metrics``.

    Raises:
        ValueError: naming the optimum's reward and what to change.
    """
    best = scorer.optimal_metrics.avg_reward
    if not best > 0:
        raise ValueError(
            f"the exact optimum earns {best:.4g} per step: learners are scored by their ratio to "
            "it, which needs an optimum that earns more than 0; raise a reward (reward.r1, "
            "reward.r2, reward.r4) or lower a penalty (reward.r3, reward.r5), or solve it "
            "exactly with recipes/solve.py"
        )


def exact_model(params: Params, device: str | torch.device = "cpu") -> ExactMDP:
    """The exact model of ``params``: dense while its transition tensor fits
    ``irdrc.core.sizes.DENSE_LIMIT_BYTES``, else factored."""
    from irdrc.core.exact.dense import build_model
    from irdrc.core.exact.factored import build_factored

    return build_model(params) if fits_dense(params) else build_factored(params, device)


def exact_scorer(params: Params, gamma: float = DEFAULT_OPTIMUM_GAMMA) -> Scorer:
    """The scorer of ``params`` on its exact model (``exact_model``); value iteration to 1e-9 on a
    dense model, to McQueen's 1e-6 on a factored one (values of order 10²–10³)."""
    return Scorer(exact_model(params), gamma, tol=1e-9 if fits_dense(params) else 1e-6)


def score_summary(scorer: Any, table: torch.Tensor) -> dict[str, float]:
    """A policy table's exact long-run figures against ``scorer``'s optimum (any scorer with
    ``metrics`` and ``optimal_metrics``: ``Scorer``, the fleet's, the continuum's): ``ratio``
    (average reward over the optimum's), ``avg_reward``, ``optimum``, ``throughput``,
    ``miss_detection``, ``radar_fraction``."""
    m, best = scorer.metrics(table), scorer.optimal_metrics
    return {
        "ratio": m.avg_reward / best.avg_reward,
        "avg_reward": m.avg_reward,
        "optimum": best.avg_reward,
        "throughput": m.throughput,
        "miss_detection": m.miss_detection,
        "radar_fraction": m.radar_fraction,
    }
