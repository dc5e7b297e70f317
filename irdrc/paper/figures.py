"""Data behind the figures: means and confidence bands over seeds, learning curves, exact references.

``recipes/figure2.py`` and ``recipes/tradeoff.py`` gather their runs' files with these helpers and hand
plain rows to ``irdrc.paper.plots`` (drawing) and ``irdrc.paper.claims`` (verdicts).
"""

from __future__ import annotations

import math
import statistics
from collections.abc import Iterable, Sequence
from typing import Any

import torch

from irdrc.core.dynamics import Dynamics
from irdrc.core.params import Params

# Two-sided 95 % quantiles of Student's t for 1 … 30 degrees of freedom (beyond: the normal's).
_T975 = (
    12.706, 4.303, 3.182, 2.776, 2.571, 2.447, 2.365, 2.306, 2.262, 2.228,
    2.201, 2.179, 2.160, 2.145, 2.131, 2.120, 2.110, 2.101, 2.093, 2.086,
    2.080, 2.074, 2.069, 2.064, 2.060, 2.056, 2.052, 2.048, 2.045, 2.042,
)  # fmt: skip


def t975(dof: int) -> float:
    """The 97.5 % quantile of Student's t with ``dof`` degrees of freedom (≥ 1)."""
    if dof < 1:
        raise ValueError(f"dof={dof} must be >= 1")
    return _T975[dof - 1] if dof <= len(_T975) else 1.959964


def mean_ci(values: Iterable[float]) -> dict[str, float]:
    """Mean of independent replicates and its 95 % t-interval (``lo`` = ``hi`` = mean for one).

    NaNs (undefined values, e.g. miss detection of a policy that sees no event) are dropped.
    """
    xs = [float(v) for v in values if v is not None and not math.isnan(float(v))]
    if not xs:
        return {"mean": math.nan, "lo": math.nan, "hi": math.nan, "n": 0}
    m = statistics.fmean(xs)
    if len(xs) == 1:
        return {"mean": m, "lo": m, "hi": m, "n": 1}
    half = t975(len(xs) - 1) * statistics.stdev(xs) / math.sqrt(len(xs))
    return {"mean": m, "lo": m - half, "hi": m + half, "n": len(xs)}


def to_float(v: Any) -> float:
    """A number read from CSV or JSON; empty or None (an undefined metric) is NaN."""
    return math.nan if v in (None, "") else float(v)


def same_value(a: Any, b: Any) -> bool:
    """Whether two config values read from different places (floats, CSV strings) are equal."""
    try:
        return math.isclose(float(a), float(b), rel_tol=1e-9, abs_tol=1e-12)
    except (TypeError, ValueError):
        return str(a) == str(b)


def band_rows(
    series: str,
    xs: Sequence[float],
    per_seed: Sequence[Sequence[float]],
    bounds: tuple[float, float] | None = None,
) -> list[dict[str, Any]]:
    """Rows ``series, x, mean, lo, hi, n`` of curves given per seed on the same ``xs``.

    ``bounds``: the range every value of the metric lies in (e.g. [0, 1] for miss detection); the
    t-interval is clipped to it, since no replicate can fall outside.
    """
    rows = []
    for i, x in enumerate(xs):
        stats = mean_ci(curve[i] for curve in per_seed if i < len(curve))
        if bounds is not None and stats["n"]:
            stats["lo"] = min(max(stats["lo"], bounds[0]), bounds[1])
            stats["hi"] = max(min(stats["hi"], bounds[1]), bounds[0])
        rows.append({"series": series, "x": x, **stats})
    return rows


def moving_average(values: Sequence[float], window: int) -> list[float]:
    """Trailing moving average (shorter windows at the start)."""
    if window < 1:
        raise ValueError(f"window={window} must be >= 1")
    out, acc = [], 0.0
    for i, v in enumerate(values):
        acc += v
        if i >= window:
            acc -= values[i - window]
        out.append(acc / min(i + 1, window))
    return out


def round_robin_episodes(params: Params, seeds: Sequence[int], episodes: int) -> list[list[float]]:
    """Total reward of ``episodes`` simulated round-robin episodes for each seed.

    Round-robin communicates first after each reset and alternates every step (as
    ``irdrc.core.policies.round_robin``); each seed is its own generator.
    """
    dyn = Dynamics(params)
    out = []
    for seed in seeds:
        gen = torch.Generator().manual_seed(int(seed))
        state = dyn.reset_states(episodes, gen)
        total = torch.zeros(episodes, dtype=torch.float64)
        for t in range(params.env.horizon):
            action = torch.full((episodes,), t % 2, dtype=torch.int64)
            res = dyn.step(state, action, gen)
            total += res.reward
            state = res.state
        out.append(total.tolist())
    return out
