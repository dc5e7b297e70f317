"""The learners on one stream by name (``learner=…``): each profile's learner, built for a scenario."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from irdrc.core.checks import check_choice
from irdrc.core.params import Params
from irdrc.online.configs import LEARNERS, PROFILES, learner_config
from irdrc.online.loop import StreamLearner
from irdrc.online.own import OwnLearnerConfig, is_own, make_own_learner, own_learner_config


def make_learner(name: str, cfg: Any, params: Params, seed: int = 0) -> StreamLearner:
    """The learner ``name`` (``irdrc.online.configs.LEARNERS``, or one's own: ``PATH.py:Class``,
    ``irdrc.online.own``) with hyperparameters ``cfg``: its profile's type (``learner_config(name,
    {…})``), a mapping of keys over its profile, or None (the profile as it is).

    Raises:
        ValueError: an unknown learner, a key its profile does not have, or a config of another
            learner's type.
    """
    if is_own(name):
        if cfg is None or isinstance(cfg, Mapping):
            cfg = own_learner_config(name, cfg)
        elif not isinstance(cfg, OwnLearnerConfig):
            raise ValueError(
                f"learner={name} takes its constructor's keys (a mapping), not a "
                f"{type(cfg).__name__}"
            )
        return make_own_learner(cfg, params, seed)
    check_choice("learner", name, LEARNERS)
    if cfg is None or isinstance(cfg, Mapping):
        cfg = learner_config(name, cfg)
    elif type(cfg) is not type(PROFILES[name]):
        raise ValueError(
            f"learner={name} takes a {type(PROFILES[name]).__name__} "
            f"(irdrc.online.configs.learner_config({name!r}, {{…}})), not a {type(cfg).__name__}"
        )
    if name in ("dqn", "dqn_paper"):
        from irdrc.online.dqn import StreamDQN

        return StreamDQN(cfg, params, seed)
    if name in ("qlearning", "qlearning_paper"):
        from irdrc.online.qlearning import StreamQLearning

        return StreamQLearning(cfg, params.env.num_states, seed)
    if name in ("posterior", "posterior_anytime"):
        from irdrc.online.posterior import PosteriorSampling

        return PosteriorSampling(cfg, params, seed)
    from irdrc.online.safe import SafeLearner

    return SafeLearner(cfg, params, seed)
