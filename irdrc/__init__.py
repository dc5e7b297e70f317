"""irdrc: the iRDRC radar/communication mode-selection model — simulator, exact optimum, learners.

The package is four layers, each importing only the layers below it (``tests/test_layers.py``
checks this):

- ``irdrc.core``: the model and everything exact (params, env, model, solve, metrics, policies,
  evaluate, gym);
- ``irdrc.agents``: the learners (Q-learning, DQN, replay), one interface;
- ``irdrc.experiments``: configs to run directories (run functions, grids, sweeps, results files,
  tracking, the ``irdrc`` command);
- ``irdrc.paper``: the paper's figures, claims, trade-off and the reproduction report.

``import irdrc`` registers the gymnasium id ``irdrc/DFRC-v0``.
"""

import sys as _sys

from irdrc.core import env as _env
from irdrc.core import evaluate as _evaluate
from irdrc.core import gym as _gym
from irdrc.core import metrics as _metrics
from irdrc.core import model as _model
from irdrc.core import params as _params
from irdrc.core import policies as _policies
from irdrc.core import solve as _solve
from irdrc.core.env import DFRCEnv, Dynamics, decode_state, state_index
from irdrc.core.params import EnvParams, Params, RewardParams

__version__ = "0.1.0"

__all__ = [
    "DFRCEnv",
    "Dynamics",
    "EnvParams",
    "Params",
    "RewardParams",
    "decode_state",
    "state_index",
]

# Deprecated import paths from before the layers (``irdrc.model``, ``irdrc.solve`` …) keep working
# as aliases of the ``irdrc.core`` modules; new code imports ``irdrc.core.<module>``.
for _name, _module in {
    "env": _env,
    "evaluate": _evaluate,
    "gym": _gym,
    "metrics": _metrics,
    "model": _model,
    "params": _params,
    "policies": _policies,
    "solve": _solve,
}.items():
    _sys.modules.setdefault(f"{__name__}.{_name}", _module)
    globals()[_name] = _module

_gym.register()
