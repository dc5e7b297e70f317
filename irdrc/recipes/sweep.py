"""``recipes/sweep.py``: a grid of config overrides, each point one run of a recipe (``method``), on
Ray Tune or one after another here (the engine: ``irdrc.sweeps.trials``).

    python recipes/sweep.py 'sweep.grid={env.p1.speed: [0.1,0.5,1.0], seed: [0,1,2]}'
    python recipes/sweep.py method=constrained executor=local 'sweep.grid={target_miss: [0.02,0.05]}'
    python recipes/sweep.py method=online executor=local 'sweep.grid={learner: [posterior, dqn], seed: [0,1,2]}'
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field, replace
from functools import partial
from typing import TYPE_CHECKING, Any

from irdrc.core.checks import build, check_choice, check_list
from irdrc.online import recipe as online
from irdrc.recipes import dqn, qlearning, solve
from irdrc.recipes.constrained import recipe as constrained
from irdrc.recipes.fleet import recipe as fleet
from irdrc.recipes.shares import ppo, sac
from irdrc.runs.compose import Composed, compose, compose_recipe
from irdrc.runs.grid import override_key, parse_grid
from irdrc.runs.sections import EXECUTOR, Executor
from irdrc.sweeps.trials import execute, plan

if TYPE_CHECKING:
    from irdrc.runs.scaffold import Run

NAME = "sweep"

METHODS = {m.NAME: m for m in (dqn, online, qlearning, solve, constrained, fleet, sac, ppo)}
"""The recipes a grid point may run (``method``), each handing the engine its module."""


@dataclass(frozen=True)
class Grid:
    """``sweep.*``: the ``grid`` ({key: [values]}), the ``base`` overrides of every trial, and the
    fault injection of the tests (``fail_on``: a point holding all of these raises)."""

    grid: Any = None
    base: tuple[str, ...] = ()
    fail_on: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        object.__setattr__(self, "base", check_list("sweep.base", self.base or [], empty=True))
        fail = check_list("sweep.fail_on", self.fail_on or [], empty=True)
        object.__setattr__(self, "fail_on", fail)


@dataclass(frozen=True)
class Config:
    """The sweep's keys (``irdrc/conf/sweep.yaml``); ``planned``: every grid point, checked."""

    method: str = "dqn"
    sweep: Grid = field(default_factory=Grid)
    executor: Executor = field(default_factory=Executor, metadata=EXECUTOR)
    planned: tuple[Any, ...] = field(default=(), metadata={"keys": ()})

    def __post_init__(self) -> None:
        check_choice("method", self.method, tuple(METHODS))


def misplaced_override(args: list[str]) -> str | None:
    """Where an override the sweep refused goes, when it is one of the method's recipe: into every
    trial (``sweep.base``) or over values (``sweep.grid``); None when it is not."""
    method = next((a.partition("=")[2] for a in args if override_key(a) == "method"), Config.method)
    module = METHODS.get(method)
    if module is None:
        return None
    for arg in args:
        key = override_key(arg)
        if "=" not in arg or key.startswith("hydra") or _composes(partial(compose, NAME, [arg])):
            continue
        if _composes(partial(compose_recipe, module, [arg])):
            return (
                f"{arg} is for the runs of {method} (method), not for the sweep: every trial takes "
                f"it with \"sweep.base=['{arg}']\", or over values sweep.grid='{{{key}: [...]}}'"
            )
    return None


def _composes(composing: Callable[[], Any]) -> bool:
    try:
        composing()
    except ValueError:
        return False
    return True


def load(composed: Composed, resume: dict[str, Any] | None = None) -> Config:
    """The typed config; every grid point composed and checked (``plan``) before any trial."""
    cfg = build(Config, composed.cfg)
    if cfg.executor.resume and not cfg.sweep.grid:
        raise ValueError(
            "resume=true goes on with a sweep's stored grid: name its directory with "
            "hydra.run.dir=… (the one the sweep printed)"
        )
    points = parse_grid(cfg.sweep.grid)
    composed.refuse_overwritten(
        {
            override_key(k): "sweep.grid gives its values; drop it from sweep.base"
            for k in points[0]
        },
        cfg.sweep.base,
    )
    module = METHODS[cfg.method]
    planned = plan(module, points, list(cfg.sweep.base), list(cfg.sweep.fail_on))
    return replace(cfg, planned=tuple(planned))


def run(cfg: Config, run: Run) -> int:
    """Run the planned grid (``execute``)."""
    return execute(cfg.executor, list(cfg.planned), run.dir, run.recipe)
