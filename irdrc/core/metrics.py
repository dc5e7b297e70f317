"""The Metrics record and its names (MODEL.md § Metrics), shared by logs, CSVs, tables and plots.

Every metric is a ratio of sums over the steps evaluated — never a mean of per-episode ratios — so
miss detection stays defined when an episode has no event.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from dataclasses import asdict, dataclass, fields
from typing import Any

METRIC_NAMES = (
    "avg_reward",
    "episode_reward",
    "throughput",
    "link_capacity",
    "miss_detection",
    "radar_fraction",
    "drop_rate",
    "mean_queue",
)
"""The metrics every table, log and CSV reports. ``Metrics.false_alarm_rate`` (false alarms per
radar step without an event) joins them where the scenario has false alarms (P_fa > 0)."""


@dataclass(frozen=True)
class Metrics:
    """Long-run or sampled performance of a policy; NaN where undefined (no event seen)."""

    avg_reward: float
    episode_reward: float
    throughput: float
    link_capacity: float
    miss_detection: float
    radar_fraction: float
    drop_rate: float
    mean_queue: float
    false_alarm_rate: float = math.nan

    def as_dict(self) -> dict[str, float]:
        """Plain dict keyed by ``METRIC_NAMES``, plus ``false_alarm_rate`` where it is defined
        (a scenario with radar false alarms, MODEL.md § B.3)."""
        out = asdict(self)
        if math.isnan(out["false_alarm_rate"]):
            del out["false_alarm_rate"]
        return out

    @classmethod
    def from_dict(cls, data: dict[str, float]) -> Metrics:
        """Inverse of ``as_dict`` (extra keys are ignored; None, an undefined metric, is NaN)."""
        return cls(
            **{
                f.name: math.nan if data.get(f.name) is None else float(data[f.name])
                for f in fields(cls)
                if f.name in data or f.name in METRIC_NAMES
            }
        )


def long_run_rates(s: Mapping[str, float]) -> dict[str, float]:
    """Rates from per-step sums (expected or counted) of ``reward``, ``missed``, ``event``,
    ``sent``, ``dropped``, ``radar`` (time in radar mode), ``queue``, and where known ``capacity``,
    ``false_alarms`` with ``quiet_radar`` (radar time without an event), ``denied`` with ``comm``:
    each an expectation per step, except miss detection (missed / events), the false-alarm rate
    (false alarms / quiet radar time) and the denial rate (denied / comm steps), ratios of sums;
    NaN where a ratio is undefined. The one definition of every metric, exact or simulated."""

    def ratio(a: str, b: str) -> float:
        return s[a] / s[b] if s.get(b, 0.0) > 0 else math.nan

    out = {
        "avg_reward": s["reward"],
        "throughput": s["sent"],
        "miss_detection": ratio("missed", "event"),
        "radar_fraction": s["radar"],
        "drop_rate": s["dropped"],
        "mean_queue": s["queue"],
    }
    if "capacity" in s:
        out["link_capacity"] = s["capacity"]
    if "false_alarms" in s:
        out["false_alarm_rate"] = ratio("false_alarms", "quiet_radar")
    if "denied" in s:
        out["denial_rate"] = ratio("denied", "comm")
    return out


RESOLUTION = 1e-12
"""The smallest magnitude a table shows as a number: the exact solves are accurate to about this
(``GMRES_RTOL``), so a long-run value below it is printed ``<1e-12`` rather than as float noise."""


def _fmt(x: float) -> str:
    if x is None or (isinstance(x, float) and math.isnan(x)):
        return "n/a"
    if x != 0 and abs(x) < RESOLUTION:
        return f"<{RESOLUTION:.0e}"
    return f"{x:.4g}" if abs(x) >= 1e-3 or x == 0 else f"{x:.2e}"


def format_table(
    rows: Mapping[str, Metrics | dict[str, float]],
    names: tuple[str, ...] | None = None,
    errors: Mapping[str, dict[str, float]] | None = None,
) -> str:
    """Side-by-side table: one row per method, one column per metric.

    Args:
        rows: method name → its metrics.
        names: metric columns, in order; default ``METRIC_NAMES``, and ``false_alarm_rate`` when
            a row has it.
        errors: method name → metric → half-width of a confidence interval, shown as ``± x``.
    """
    if names is None:
        names = METRIC_NAMES
        if any(
            not math.isnan(
                (m.as_dict() if isinstance(m, Metrics) else m).get("false_alarm_rate", math.nan)
                or math.nan
            )
            for m in rows.values()
        ):
            names = (*METRIC_NAMES, "false_alarm_rate")
    header = ["method", *names]
    body = []
    for method, m in rows.items():
        values = m.as_dict() if isinstance(m, Metrics) else m
        cells = [method]
        for n in names:
            cell = _fmt(values.get(n, float("nan")))
            err = (errors or {}).get(method, {}).get(n)
            if err is not None and not math.isnan(err):
                cell += f" ±{_fmt(err)}"
            cells.append(cell)
        body.append(cells)
    widths = [max(len(r[i]) for r in [header, *body]) for i in range(len(header))]

    def line(r: list[str]) -> str:
        return "  ".join(
            c.ljust(w) if i == 0 else c.rjust(w)
            for i, (c, w) in enumerate(zip(r, widths, strict=True))
        )

    sep = "  ".join("-" * w for w in widths)
    return "\n".join([line(header), sep, *(line(r) for r in body)])


def first_reaching(
    rows: Iterable[Mapping[str, Any]],
    threshold: float,
    *,
    value: str = "optimality_ratio",
    at: str = "env_steps",
) -> Any:
    """``row[at]`` of the first row (in order) whose ``row[value]`` is ≥ ``threshold``; None if none.

    The one definition of "first reached" for learning curves (env steps to 99 % of the optimum)
    and for bands over seeds (``value="mean", at="x"``).
    """
    return next((r[at] for r in rows if r[value] is not None and r[value] >= threshold), None)
