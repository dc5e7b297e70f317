"""The model's transition chains as the LP's dual (``irdrc.core.cmdp_dual``) factorises them:
every action's P_a as one dense array, or as SciPy sparse matrices past ``SPARSE_FROM_STATES``."""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

from irdrc.core.cmdp import transitions
from irdrc.core.exact import DenseModel, ExactMDP, FactoredModel

SPARSE_FROM_STATES = 3_000
"""``chain`` gives the sparse chain (SuperLU) to factored models of more states than this, the
dense one (LAPACK's LU) to the others: the faster of the two on either side (whole solves on the
paper's model with deeper queues)."""


def dense_transitions(model: ExactMDP) -> np.ndarray:
    """[A, S, S] P_a of every action as one dense array (a dense model's own; a factored model's
    written from its factors, ``FactoredModel.dense``)."""
    if isinstance(model, DenseModel):
        return np.asarray(model.P.to(torch.float64).cpu().numpy())
    if isinstance(model, FactoredModel):
        return np.stack([model.dense(a) for a in range(model.num_actions)])
    raise TypeError(
        f"dense_transitions: a DenseModel or a FactoredModel, not {type(model).__name__}"
    )


def chain(model: ExactMDP) -> np.ndarray | list[Any]:
    """The transitions ``irdrc.core.cmdp_dual.DualPlanner`` factorises fastest for ``model``: a factored model's
    sparse ones (``irdrc.core.cmdp.transitions``: only the arrivals' reach) above
    ``SPARSE_FROM_STATES`` states, and dense ones (``dense_transitions``) otherwise (a dense
    model's sparse form would hold every entry its P holds, down to 1e-300)."""
    if isinstance(model, DenseModel) or model.num_states <= SPARSE_FROM_STATES:
        return dense_transitions(model)
    return transitions(model)
