"""irdrc: the iRDRC radar/communication mode-selection model — simulator, exact optimum, learners."""

from irdrc.env import DFRCEnv, Dynamics, decode_state, state_index
from irdrc.params import EnvParams, Params, RewardParams

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

from irdrc.gym import register as _register_gym

_register_gym()
