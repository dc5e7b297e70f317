"""``frontier_grid.*`` of ``recipes/constrained.py frontier=true``: the speeds, the targets and the
r4 route the frontier is drawn on (``irdrc.recipes.constrained.frontier``)."""

from __future__ import annotations

from dataclasses import dataclass, field

from irdrc.core import checks


@dataclass(frozen=True)
class R4Grid:
    """``frontier_grid.r4``: the r4 route's detection rewards ``lo``, ``lo + step``, …, ≤ ``hi``."""

    lo: float = 0.0
    hi: float = 100.0
    step: float = 1.0

    def __post_init__(self) -> None:
        checks.check_numbers(self, "frontier_grid.r4.", (("lo", 0, 1e9, {}),))
        checks.check_numbers(self, "frontier_grid.r4.", (("hi", self.lo, 1e9, {}),))
        checks.check_numbers(self, "frontier_grid.r4.", (("step", 0, 1e9, {"open_lo": True}),))
        if (self.hi - self.lo) / self.step > 5000:
            raise ValueError(
                f"frontier_grid.r4: {int((self.hi - self.lo) / self.step) + 1} exact solves per "
                "p1.speed (> 5 000); raise frontier_grid.r4.step"
            )

    def values(self) -> list[float]:
        """The r4 values of the route."""
        n = int((self.hi - self.lo) / self.step + 1e-9) + 1
        return [round(self.lo + i * self.step, 10) for i in range(n)]


@dataclass(frozen=True)
class FrontierGrid:
    """``frontier_grid.*``: one frontier per ``p1_speed``, ``points`` targets from 0 to the
    reward-optimal policy's miss detection, the r4 route, and the table's ``targets``."""

    p1_speed: tuple[float, ...] = (0.1, 1.0)
    points: int = 41
    r4: R4Grid = field(default_factory=R4Grid)
    targets: tuple[float, ...] = (0.05, 0.1, 0.15, 0.2)

    def __post_init__(self) -> None:
        item = checks.numbers(0, 1)
        object.__setattr__(
            self,
            "p1_speed",
            checks.check_list("frontier_grid.p1_speed", self.p1_speed, item, distinct=True),
        )
        object.__setattr__(
            self,
            "targets",
            checks.check_list(
                "frontier_grid.targets", self.targets, item, empty=True, distinct=True
            ),
        )
        checks.check_numbers(self, "frontier_grid.", (("points", 2, 10_000, checks.INT),))
