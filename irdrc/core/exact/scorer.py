"""One scorer family: a model's optimum, and the exact long-run metrics of any policy table against
it, cached (learners revisit the same greedy table often)."""

from __future__ import annotations

from typing import Any

import torch

from irdrc.core.exact.mdp import ExactMDP
from irdrc.core.exact.solve import DEFAULT_OPTIMUM_GAMMA, stationary_metrics, value_iteration
from irdrc.core.metrics import Metrics
from irdrc.core.params import Params


class Scorer:
    """Exact stationary metrics of policy tables on one exact model, and its optimum.

    Attributes:
        model: the exact model (dense, factored, or a fleet's).
        optimal: value iteration's ``Solution`` at ``gamma``.
        optimal_metrics: the optimum's exact long-run metrics.
    """

    def __init__(self, model: ExactMDP, gamma: float = DEFAULT_OPTIMUM_GAMMA, tol: float = 1e-9):
        self.model = model
        self.optimal = value_iteration(model, gamma=gamma, tol=tol)
        self.optimal_metrics = stationary_metrics(model, self.optimal.policy)
        self._cache: dict[tuple, Metrics] = {}

    def policy(self, table: torch.Tensor) -> Any:
        """The model's policy for a learner's ``table`` (here the table itself; the fleet's scorer
        turns each vehicle's own table into the joint policy)."""
        return table

    def metrics(self, table: torch.Tensor) -> Metrics:
        """Exact stationary ``Metrics`` of the policy ``table`` ([S] actions or [S, A])."""
        t = torch.as_tensor(table).cpu()
        key = (str(t.dtype), tuple(t.shape), t.numpy().tobytes())
        if key not in self._cache:
            self._cache[key] = stationary_metrics(self.model, self.policy(t))
        return self._cache[key]

    def ratio(self, table: torch.Tensor) -> float:
        """Average reward of ``table`` over the optimal average reward (both stationary)."""
        return self.metrics(table).avg_reward / self.optimal_metrics.avg_reward


def exact_model(params: Params, device: str | torch.device = "cpu") -> ExactMDP:
    """The exact model of ``params``: dense while its transition tensor fits
    ``DENSE_MODEL_LIMIT_BYTES``, else factored."""
    from irdrc.core.exact.dense import build_model, fits_dense
    from irdrc.core.exact.factored import build_factored

    return build_model(params) if fits_dense(params) else build_factored(params, device)


def exact_scorer(params: Params, gamma: float = DEFAULT_OPTIMUM_GAMMA) -> Scorer:
    """The scorer of ``params`` on its exact model (``exact_model``); value iteration to 1e-9 on a
    dense model, to McQueen's 1e-6 on a factored one (values of order 10²–10³)."""
    from irdrc.core.exact.dense import fits_dense

    return Scorer(exact_model(params), gamma, tol=1e-9 if fits_dense(params) else 1e-6)
