"""Scenarios a user might type, drawn at random (``recipes/bench_robust.py scenarios=random``, and
with the radar share's keys ``recipes/bench_timeshare.py scenarios=random``):
every model key of MODEL.md v1/§ B — queue size, arrival rate (or bursty arrivals), packets per
channel level, every factor's chain and event probabilities, the event model, the radar reaction,
reward weights from 0.1 to 100, three-level factors, an imperfect radar — kept to the *contested*
ones: neither always-radar nor always-comm within ``CONTESTED`` of the exact optimum's long-run
average reward (which must be positive, so that a ratio to it means something).

Draw ``i`` is a pure function of ``i`` (``draw_overrides``): the benchmark's draws are reproducible
and named by index. The learners' defaults were chosen on draws ``TUNING`` and are reported on draws
from ``REPORTING`` up, which no choice looked at.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, TypeVar

import numpy as np

from irdrc.runs.grid import format_value

CONTESTED = 0.9
"""A draw is kept when both always-radar and always-comm earn less than this of the optimum."""

REPORTING = 8200
"""The first draw index of the reported benchmark (``first_draw``): none of them was looked at
before it reported."""

TUNING = range(REPORTING)
"""Draw indices the defaults may be chosen on: every draw below ``REPORTING`` has been looked at
while a default was chosen or measured (docs/lab/ says which draws served which choice)."""

OPTIONAL = ("env.factors", "env.bursty", "env.detection_prob", "env.false_alarm_prob", "reward.r5")
"""Keys absent from the base scenario (a command line adds them with ``+``)."""


def _sig(x: float, digits: int = 3) -> float:
    """``x`` to ``digits`` significant digits: numbers a user would type."""
    return 0.0 if x == 0 else float(f"{x:.{digits}g}")


def _log_uniform(rng: np.random.Generator, lo: float, hi: float) -> float:
    return _sig(math.exp(rng.uniform(math.log(lo), math.log(hi))))


def _three_levels(rng: np.random.Generator, top: float) -> dict[str, Any]:
    """A random three-level factor: a sticky chain, event probabilities rising with the level."""
    rows = []
    for i in range(3):
        w = rng.uniform(0.0, 1.0, 3)
        w[i] += rng.uniform(1.0, 6.0)
        row = [_sig(x) for x in w / w.sum()]
        row[i] = round(1.0 - sum(x for j, x in enumerate(row) if j != i), 12)
        rows.append(row)
    events = sorted(_log_uniform(rng, 1e-4, top) for _ in range(3))
    return {"levels": ["low", "medium", "high"], "transition": rows, "event": events}


def draw_overrides(index: int) -> dict[str, Any]:
    """Draw ``index``: model keys as on the command line (dotted) → values."""
    if not isinstance(index, int) or index < 0:
        raise ValueError(f"a draw index is a whole number ≥ 0; got {index!r}")
    rng = np.random.default_rng([0x1DC, index])
    out: dict[str, Any] = {"env.queue_capacity": round(_log_uniform(rng, 2, 20))}
    if rng.random() < 0.2:
        out["env.arrival_rate"] = None
        x, y = _sig(rng.uniform(0.02, 0.3)), _sig(rng.uniform(0.05, 0.5))
        out["env.bursty"] = {
            "rates": sorted([_sig(rng.uniform(0.1, 1.0)), _sig(rng.uniform(1.0, 4.0))]),
            "transition": [[round(1 - x, 12), x], [y, round(1 - y, 12)]],
        }
    else:
        out["env.arrival_rate"] = _sig(rng.uniform(0.2, 3.0))
    good = int(rng.integers(1, 9))
    out["env.packets_good"], out["env.packets_bad"] = good, int(rng.integers(0, good + 1))
    factors = {}
    for name, top in (("speed", 0.5), ("object", 0.3)):
        if rng.random() < 0.25:
            factors[name] = _three_levels(rng, top)
    for name in ("road", "weather", "speed", "object"):
        if name in factors:
            continue
        p0 = _log_uniform(rng, 1e-4, 2e-2)
        out[f"env.p0.{name}"], out[f"env.p1.{name}"] = p0, _log_uniform(rng, p0, 0.5)
    for name in ("channel", "road", "weather", "speed", "object"):
        if name in factors:
            continue
        out[f"env.stay_good.{name}"] = _sig(rng.uniform(0.5, 0.99))
        out[f"env.stay_bad.{name}"] = _sig(rng.uniform(0.05, 0.95))
    if factors:
        out["env.factors"] = factors
    out["env.event_model"] = str(rng.choice(["noisy_or", "sum"]))
    out["env.radar_reaction"] = bool(rng.random() < 0.8)
    out["env.reaction_clear"] = _sig(rng.uniform(0.3, 1.0))
    r1 = _log_uniform(rng, 0.1, 100)
    out["reward.r1"], out["reward.r2"] = r1, _sig(r1 * rng.uniform(0.05, 1.0))
    out["reward.r3"], out["reward.r4"] = _log_uniform(rng, 0.1, 100), _log_uniform(rng, 0.1, 100)
    if rng.random() < 0.25:
        out["env.detection_prob"] = _sig(rng.uniform(0.7, 0.99))
        out["env.false_alarm_prob"] = _sig(rng.uniform(0.0, 0.1))
        out["reward.r5"] = _log_uniform(rng, 0.1, 100)
    return out


def command_line(overrides: dict[str, Any]) -> list[str]:
    """The overrides as a command line types them (``+`` before keys the base config lacks)."""
    out = []
    for key, value in overrides.items():
        plus = "+" if key.startswith(OPTIONAL) else ""
        if isinstance(value, dict):
            for sub, v in _flatten(value, key).items():
                out.append(f"{plus}{sub}={format_value(v)}")
        else:
            out.append(f"{plus}{key}={format_value(value)}")
    return out


def _flatten(value: dict[str, Any], prefix: str) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for k, v in value.items():
        if isinstance(v, dict):
            out.update(_flatten(v, f"{prefix}.{k}"))
        else:
            out[f"{prefix}.{k}"] = v
    return out


@dataclass(frozen=True)
class Draw:
    """One kept draw: its index, overrides, and what made it contested.

    Attributes:
        index: the draw's index.
        overrides: ``draw_overrides(index)``.
        optimum: the exact optimum's long-run average reward per step.
        always_radar, always_comm: the baselines' long-run average rewards, over the optimum's.
        states: S.
    """

    index: int
    overrides: dict[str, Any]
    optimum: float
    always_radar: float
    always_comm: float
    states: int


def contested(index: int, gamma: float = 0.99) -> Draw | None:
    """Draw ``index`` with its exact optimum and baselines, or None when it is not contested (or
    its optimum earns ≤ 0 per step)."""
    from irdrc.core.exact import build_model, stationary_metrics, value_iteration
    from irdrc.core.params import Params

    overrides = draw_overrides(index)
    params = Params.from_overrides(overrides)
    model = build_model(params)
    best = stationary_metrics(model, value_iteration(model, gamma=gamma).policy).avg_reward
    if best <= 0:
        return None
    radar, comm = (
        stationary_metrics(model, p).avg_reward / best for p in ("always_radar", "always_comm")
    )
    if max(radar, comm) >= CONTESTED:
        return None
    return Draw(index, overrides, best, radar, comm, params.env.num_states)


def contested_draws(
    first: int, count: int, gamma: float = 0.99, progress: Callable[[int, int], None] | None = None
) -> list[Draw]:
    """The first ``count`` contested draws from index ``first`` up; ``progress(kept, tried)``
    after each draw."""
    return kept_draws(lambda i: contested(i, gamma), first, count, progress)


Kept = TypeVar("Kept")


def kept_draws(
    keep: Callable[[int], Kept | None],
    first: int,
    count: int,
    progress: Callable[[int, int], None] | None = None,
) -> list[Kept]:
    """The first ``count`` draws from index ``first`` up that ``keep`` returns (not None);
    ``progress(kept, tried)`` after each draw."""
    out: list[Kept] = []
    index = first
    while len(out) < count:
        draw = keep(index)
        if draw is not None:
            out.append(draw)
        index += 1
        if progress is not None:
            progress(len(out), index - first)
    return out


SHARE_GAIN = 1.02
"""A time-sharing draw is kept when the optimum over ρ ∈ [0, 1] earns at least this many times the
binary optimum: where sharing each step's time matters."""


def share_overrides(index: int) -> dict[str, Any]:
    """Time-sharing draw ``index`` (``recipes/bench_timeshare.py scenarios=random``): every model key
    of ``draw_overrides(index)``, then the sensing curve, its κ and the number of levels."""
    out = draw_overrides(index)
    rng = np.random.default_rng([0x75A, index])
    out["env.sensing"] = str(rng.choice(["dwell", "linear"]))
    out["env.dwell_gain"] = _log_uniform(rng, 0.5, 10.0)
    out["env.levels"] = int(rng.choice([3, 5, 9]))
    return out


@dataclass(frozen=True)
class ShareDraw:
    """One kept time-sharing draw: its index, overrides, the optimum over ρ and the binary optimum
    (long-run average rewards per step), and S."""

    index: int
    overrides: dict[str, Any]
    optimum: float
    binary: float
    states: int


def share_draw(index: int, gamma: float = 0.99) -> ShareDraw | None:
    """Time-sharing draw ``index`` with both optima, or None when the binary optimum earns ≤ 0 per
    step or the optimum over ρ earns less than ``SHARE_GAIN`` times it."""
    from irdrc.core.exact import exact_scorer
    from irdrc.core.exact.continuum import ContinuumScorer
    from irdrc.core.params import Params

    overrides = share_overrides(index)
    params = Params.from_overrides(overrides)
    binary = exact_scorer(params, gamma).optimal_metrics.avg_reward
    if binary <= 0:
        return None
    cont = Params.from_overrides({**overrides, "env.actions": "continuous"})
    best = ContinuumScorer(cont, gamma).optimal_metrics.avg_reward
    if best < SHARE_GAIN * binary:
        return None
    return ShareDraw(index, overrides, best, binary, params.env.num_states)


def share_draws(
    first: int, count: int, gamma: float = 0.99, progress: Callable[[int, int], None] | None = None
) -> list[ShareDraw]:
    """The first ``count`` kept time-sharing draws from index ``first`` up; ``progress(kept,
    tried)`` after each draw."""
    return kept_draws(lambda i: share_draw(i, gamma), first, count, progress)
