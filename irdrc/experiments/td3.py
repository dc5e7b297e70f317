"""``recipes/td3.py`` — TD3 from TorchRL parts on the radar share of each step (MODEL.md § D),
scored exactly against the optimum over the continuum during and after training (the run and its
files as ``recipes/sac.py``'s).

    python recipes/td3.py
    python recipes/td3.py env.p1.speed=1.0 seed=3
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from irdrc.agents.configs.continuous import TD3Config
from irdrc.experiments import sac
from irdrc.experiments.compose import Composed

NAME = "td3"
RESUMABLE = True

ALGO = {
    "keys": ("algo", "network"),
    "build": lambda d, p: TD3Config.from_sections(d["algo"], d["network"]),
}


@dataclass(frozen=True)
class Config(sac.Config):
    """The TD3 recipe's keys (``recipes/conf/td3.yaml``)."""

    algo: TD3Config = field(default_factory=TD3Config, metadata=ALGO)

    def __post_init__(self) -> None:
        super().__post_init__()


def load(composed: Composed, resume: dict[str, Any] | None = None) -> Config:
    """The typed config, checked as SAC's (``irdrc.experiments.sac.load_as``)."""
    return sac.load_as(Config, composed, resume)


def run(cfg: Config, run) -> dict[str, Any]:
    """Train TD3 and finish the run (``irdrc.experiments.sac.run_learner``)."""
    from irdrc.agents import td3

    return sac.run_learner(cfg, run, td3.train)
