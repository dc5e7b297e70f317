"""``recipes/sac.py`` — SAC from TorchRL parts on the radar share of each step (MODEL.md § D),
scored exactly against the optimum over the continuum during and after training.

    python recipes/sac.py                                   # the paper scenario, κ = 3
    python recipes/sac.py env.p1.speed=1.0 seed=3
    python recipes/sac.py env=multilevel algo.total_frames=1600000
    python recipes/sac.py resume=outputs/…/checkpoint.pt
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from irdrc.agents.configs.continuous import SACConfig
from irdrc.recipes.shares.learning import load_as, run_learner
from irdrc.runs.compose import Composed
from irdrc.runs.sections import OneVehicleLearning, algo_field

if TYPE_CHECKING:
    from irdrc.runs.scaffold import Run

NAME = "sac"
SWEEP_DEFAULTS = ("progress=false", "logger=none")
"""What a sweep gives every trial of this recipe before its own overrides (which may change it)."""
RESUMABLE = True


@dataclass(frozen=True)
class Config(OneVehicleLearning):
    """The SAC recipe's keys (``irdrc/conf/sac.yaml``)."""

    algo: SACConfig = algo_field(SACConfig)


def load(composed: Composed, resume: dict[str, Any] | None = None) -> Config:
    """The typed config, checked: a continuous action space the exact solve reaches, the
    evaluation period, what a resumed run has left."""
    return load_as(Config, composed, resume)


def run(cfg: Config, run: Run) -> dict[str, Any]:
    """Train SAC and finish the run (``run_learner``)."""
    from irdrc.agents import sac

    return run_learner(cfg, run, sac.train)
