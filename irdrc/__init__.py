"""irdrc: the iRDRC radar/communication mode-selection model — simulator, exact optimum, learners.

The package's layers, each importing only the layers below it (``tests/test_layers.py`` checks
this):

- ``irdrc.core``: the model and everything exact (params, env, the exact core ``core.exact``,
  the constrained LP, metrics, policies, Monte-Carlo evaluation, gym);
- ``irdrc.fleet``: several vehicles (MODEL.md § C) on the exact core and the single-vehicle
  simulator;
- ``irdrc.agents``: the learners, one loop;
- ``irdrc.runs``: the run machinery every recipe uses (composing a command line, the run
  directory, checkpoints, results files, tracking, the ``irdrc`` command);
- ``irdrc.sweeps``: the sweep engine (grids of runs on Ray Tune or here);
- ``irdrc.recipes`` and ``irdrc.online``: the recipes' modules; ``online`` is one vehicle on the
  road, its learners and the price of their learning;
- ``irdrc.bench``: the benchmarks;
- ``irdrc.paper``: the paper's figures, claims, trade-off and the reproduction report.

``import irdrc`` registers the gymnasium id ``irdrc/DFRC-v0`` and imports nothing heavy: the
names below (``DFRCEnv`` …) and the layers (``irdrc.fleet.parallel_env`` …) load on first use.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:  # the lazy names below, as a type checker reads them
    from irdrc import agents as agents
    from irdrc import bench as bench
    from irdrc import core as core
    from irdrc import fleet as fleet
    from irdrc import online as online
    from irdrc import paper as paper
    from irdrc import recipes as recipes
    from irdrc import runs as runs
    from irdrc import sweeps as sweeps
    from irdrc.core.dynamics import Dynamics as Dynamics
    from irdrc.core.env import DFRCEnv as DFRCEnv
    from irdrc.core.params import EnvParams as EnvParams
    from irdrc.core.params import Params as Params
    from irdrc.core.params import RewardParams as RewardParams
    from irdrc.core.states import decode_state as decode_state
    from irdrc.core.states import state_index as state_index
    from irdrc.runs.scenarios import scenario as scenario

__version__ = "0.1.0"

_LAZY = {
    "DFRCEnv": "irdrc.core.env",
    "Dynamics": "irdrc.core.dynamics",
    "decode_state": "irdrc.core.states",
    "state_index": "irdrc.core.states",
    "EnvParams": "irdrc.core.params",
    "Params": "irdrc.core.params",
    "RewardParams": "irdrc.core.params",
    "scenario": "irdrc.runs.scenarios",
}

_SUBPACKAGES = ("agents", "bench", "core", "fleet", "online", "paper", "recipes", "runs", "sweeps")
"""The layers, reachable as ``irdrc.fleet`` … after a bare ``import irdrc`` (each loads on first
use)."""

__all__ = sorted(_LAZY)


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        return getattr(importlib.import_module(_LAZY[name]), name)
    if name in _SUBPACKAGES:
        return importlib.import_module(f"irdrc.{name}")
    raise AttributeError(f"module 'irdrc' has no attribute {name!r}")


def _register_gym() -> None:
    """Register ``irdrc/DFRC-v0`` (single and vector) with gymnasium (idempotent), by name: the
    env's module loads when an env is made."""
    import gymnasium

    if "irdrc/DFRC-v0" not in gymnasium.registry:
        gymnasium.register(
            id="irdrc/DFRC-v0",
            entry_point="irdrc.core.gym:DFRCGymEnv",
            vector_entry_point="irdrc.core.gym:DFRCVectorEnv",
        )


_register_gym()
