"""Everything exact, on one interface (``mdp.ExactMDP``): a model over S states and A actions that
takes expectations and steps distributions.

- ``dense``: ``build_model`` — P[a, s, s′] in memory (small S; the cross-check);
- ``factored``: ``build_factored`` — no S × S matrix, for S in the millions (MODEL.md § B.4);
- ``stationary``: the factored model's fast stationary solvers;
- ``krylov``: linear solves on operators never built as matrices (GMRES), and a stationary
  distribution as one such solve (the fleet's);
- ``solve``: one value iteration (to the end, or a few sweeps at a time), one occupancy → metrics
  routine, stationary and episodic metrics of any policy (stationary, randomised, periodic);
- ``scorer``: a model's optimum and the exact metrics of any policy table against it.

The fleet's model (``irdrc.fleet.model``) is one more ``ExactMDP``, with 2^N joint actions.
"""

from irdrc.core.exact.dense import DenseModel, build_model, stationary_distribution
from irdrc.core.exact.factored import FactoredModel, build_factored
from irdrc.core.exact.mdp import ExactMDP, as_probs, as_schedule
from irdrc.core.exact.scorer import Scorer, exact_model, exact_scorer, require_ratio
from irdrc.core.exact.solve import (
    DEFAULT_OPTIMUM_GAMMA,
    Solution,
    ValueIteration,
    episodic_metrics,
    metrics_from_occupancy,
    one_step_spread,
    policy_evaluation,
    stationary_metrics,
    stationary_occupancy,
    value_iteration,
)
from irdrc.core.exact.stationary import stationary_distribution_factored
from irdrc.core.sizes import fits_dense

__all__ = [
    "DEFAULT_OPTIMUM_GAMMA",
    "DenseModel",
    "ExactMDP",
    "FactoredModel",
    "Scorer",
    "Solution",
    "ValueIteration",
    "as_probs",
    "as_schedule",
    "build_factored",
    "build_model",
    "episodic_metrics",
    "exact_model",
    "exact_scorer",
    "fits_dense",
    "metrics_from_occupancy",
    "one_step_spread",
    "policy_evaluation",
    "require_ratio",
    "stationary_distribution",
    "stationary_distribution_factored",
    "stationary_metrics",
    "stationary_occupancy",
    "value_iteration",
]
