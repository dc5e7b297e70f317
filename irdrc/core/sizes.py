"""How large a model the dense exact side takes, in pure Python (the command-line checks read it
without importing torch).

The dense model (``irdrc.core.exact.dense``) holds its transition tensor P[a, s, s′] for two
actions in float64: 16·S² bytes. Recipes build it while that fits ``DENSE_LIMIT_BYTES``; above it
they switch to the factored operator (``irdrc.core.exact.factored``) or refuse.
"""

from __future__ import annotations

import math

from irdrc.core.params import Params

DENSE_LIMIT_BYTES = 2**29
"""The largest dense transition tensor (2·S² float64) recipes build: 512 MiB, S = 5 792."""


def dense_fit_states() -> int:
    """The largest S whose dense transition tensor (2·S² float64) fits ``DENSE_LIMIT_BYTES``
    (read at call time, so that lowering the limit moves it)."""
    return math.isqrt(DENSE_LIMIT_BYTES // 16)


def fits_dense(params: Params) -> bool:
    """Whether the dense transition tensor of ``params`` fits ``DENSE_LIMIT_BYTES`` (above it the
    exact model is the factored one)."""
    return params.env.num_states <= dense_fit_states()
