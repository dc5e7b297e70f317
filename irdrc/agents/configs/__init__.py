"""Every learner's hyperparameters, as frozen dataclasses checked on construction, one module per
learner family.

Pure Python (no torch): a recipe builds and checks its whole config — learner included — before
anything heavy is imported, so a bad value is refused in well under a second. Each key is named as
on the command line (``algo.lr``, ``network.hidden``); docs/DQN.md says why each default is what
it is, and ``irdrc/conf/algo/*.yaml`` holds the same values (a test holds the two together).
"""

from irdrc.agents.configs.fleet import (
    FLEET_LEARNERS,
    FLEET_OBSERVES,
    MIXERS,
    POLICY_GRADIENT,
    FleetLearnerConfig,
    FleetPPOConfig,
    check_fleet_learner,
)
from irdrc.agents.configs.lagrangian import (
    LAGRANGIAN_KEYS,
    OBJECTIVES,
    LagrangianConfig,
    SearchConfig,
)
from irdrc.agents.configs.value import (
    ACTIVATIONS,
    DQNConfig,
    NetworkConfig,
    OffPolicyConfig,
    QLearningConfig,
)

__all__ = [
    "ACTIVATIONS",
    "FLEET_LEARNERS",
    "FLEET_OBSERVES",
    "LAGRANGIAN_KEYS",
    "MIXERS",
    "OBJECTIVES",
    "POLICY_GRADIENT",
    "DQNConfig",
    "FleetLearnerConfig",
    "FleetPPOConfig",
    "LagrangianConfig",
    "NetworkConfig",
    "OffPolicyConfig",
    "QLearningConfig",
    "SearchConfig",
    "check_fleet_learner",
]
