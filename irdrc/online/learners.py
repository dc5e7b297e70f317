"""The learners on one stream by name (``learner=…``): each profile's learner, built for a scenario."""

from __future__ import annotations

from typing import Any

from irdrc.core.params import Params
from irdrc.online.loop import StreamLearner


def make_learner(name: str, cfg: Any, params: Params, seed: int = 0) -> StreamLearner:
    """The learner ``name`` (``irdrc.online.configs.LEARNERS``) with hyperparameters ``cfg``."""
    if name in ("dqn", "dqn_paper"):
        from irdrc.online.dqn import StreamDQN

        return StreamDQN(cfg, params, seed)
    if name in ("qlearning", "qlearning_paper"):
        from irdrc.online.qlearning import StreamQLearning

        return StreamQLearning(cfg, params.env.num_states, seed)
    if name in ("posterior", "posterior_anytime"):
        from irdrc.online.posterior import PosteriorSampling

        return PosteriorSampling(cfg, params, seed)
    if name in ("safe", "safe_anytime"):
        from irdrc.online.safe import SafeLearner

        return SafeLearner(cfg, params, seed)
    raise ValueError(f"learner={name!r} is not a learner on one stream")
