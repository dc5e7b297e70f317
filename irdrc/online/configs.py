"""The hyperparameters of the learners on one stream (``recipes/online.py learner=…``, key group
``algo``), one frozen dataclass each, with their profiles. Pure Python: the recipe checks a command
line before torch is imported.

Every profile runs ``episodes`` episodes of the vehicle's own stream (``env.horizon`` steps each,
MODEL.md § E).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any

from irdrc.agents.configs import QLearningConfig
from irdrc.agents.configs.fleet import FLEET_LEARNERS
from irdrc.agents.configs.value import NetworkConfig
from irdrc.core import checks

DEFAULT_EPISODES = 300
"""Episodes of a run on one stream: past the 170 in which the paper's DQN approaches the optimum
and the 280 its Q-learning needs (Fig. 2(a)), so that a run shows whether a learner stays there."""


@dataclass(frozen=True)
class StreamDQNConfig:
    """DQN on one stream (``learner=dqn``, ``learner=dqn_paper``).

    Attributes:
        episodes: episodes of the stream.
        eps_start, eps_end: ε-greedy exploration, ε from ``eps_start`` in the first episode to
            ``eps_end`` …
        eps_decay_episodes: … geometrically over this many episodes (0: ``eps_end`` throughout).
        buffer_size: replay capacity, transitions (uniform replay).
        warmup_steps: env steps stored before the first update.
        update_every: env steps between two bursts of updates; the policy acts with the online
            network's greedy table of the latest burst.
        updates: gradient updates per burst.
        batch_size: transitions per update (the replay ratio is
            ``updates · batch_size / update_every`` samples per env step).
        gamma: discount γ.
        double_dqn: the online network picks the next action (van Hasselt et al. 2016).
        reward_centering: 0 (off), or the rate per env step of the average r̄ of the collected
            rewards, subtracted from every sampled reward and moved after every burst by (1 − γ)
            times the mean greedy value of the states just visited, so that the values the
            network fits stay near zero (``irdrc.agents.offpolicy.RewardCenter``).
        lr, lr_end: Adam's learning rate, from ``lr`` to ``lr_end`` linearly …
        lr_decay_episodes: … over this many episodes' env steps, then ``lr_end``: counted in
            episodes, not over the run, so that a run's first episodes do not depend on how long
            it is (a vehicle on the road does not know when it will stop learning).
        max_grad_norm: gradient clipping (0: off).
        tau: the target network's Polyak rate per update.
        policy_network: whose greedy table is the learner's policy, the one scored: ``target``
            or ``online`` (the online network acts).
        hidden, activation, layer_norm: the network (``irdrc.agents.configs.NetworkConfig``).
        name: the profile's name.
    """

    episodes: int = DEFAULT_EPISODES
    eps_start: float = 1.0
    eps_end: float = 0.01
    eps_decay_episodes: int = 10
    buffer_size: int = 200_000
    warmup_steps: int = 400
    update_every: int = 8
    updates: int = 1
    batch_size: int = 2048
    gamma: float = 0.99
    double_dqn: bool = True
    reward_centering: float = 1e-3
    lr: float = 1e-3
    lr_end: float = 1e-5
    lr_decay_episodes: int = 200
    max_grad_norm: float = 0.0
    tau: float = 0.01
    policy_network: str = "target"
    hidden: tuple[int, ...] = (32, 32)
    activation: str = "relu"
    layer_norm: bool = False
    name: str = field(default="dqn", compare=False)

    def __post_init__(self) -> None:
        checks.check_numbers(
            self,
            "algo.",
            (
                ("episodes", 1, 10**7, checks.INT),
                ("eps_start", 0, 1, {}),
                ("eps_end", 0, 1, {}),
                ("eps_decay_episodes", 0, 10**7, checks.INT),
                ("buffer_size", 1, 10**9, checks.INT),
                ("warmup_steps", 0, 10**9, checks.INT),
                ("update_every", 1, 10**6, checks.INT),
                ("updates", 1, 10**4, checks.INT),
                ("batch_size", 1, 10**6, checks.INT),
                ("gamma", 0, 1, checks.OPEN_HI),
                ("lr", 0, 1, {"open_lo": True, "open_hi": True}),
                ("lr_end", 0, 1, checks.OPEN_HI),
                ("lr_decay_episodes", 1, 10**7, checks.INT),
                ("max_grad_norm", 0, 1e12, {}),
                ("tau", 0, 1, {}),
                ("reward_centering", 0, 1, checks.OPEN_HI),
            ),
        )
        checks.check_bool("algo.double_dqn", self.double_dqn)
        checks.check_choice("algo.policy_network", self.policy_network, ("target", "online"))
        self.network  # noqa: B018 - checks hidden, activation and layer_norm
        if self.buffer_size < self.batch_size:
            raise ValueError(
                f"algo.buffer_size={self.buffer_size} must be >= algo.batch_size={self.batch_size}"
            )

    @property
    def network(self) -> NetworkConfig:
        """The network's shape."""
        hidden = self.hidden
        if isinstance(hidden, list):
            hidden = tuple(hidden)
        try:
            return NetworkConfig(hidden, self.activation, self.layer_norm)
        except ValueError as err:
            raise ValueError(str(err).replace("network.", "algo.")) from None

    def epsilon(self, episode: int) -> float:
        """ε during ``episode`` (0-based)."""
        k = self.eps_decay_episodes
        if k == 0 or episode >= k or self.eps_start == 0:
            return self.eps_end
        return self.eps_start * (self.eps_end / self.eps_start) ** (episode / k)


DQN = StreamDQNConfig()
"""Our DQN on one stream (docs/ONLINE.md)."""

DQN_PAPER = StreamDQNConfig(
    eps_start=0.1,
    eps_end=0.1,
    eps_decay_episodes=0,
    buffer_size=50_000,
    warmup_steps=100,
    update_every=1,
    updates=1,
    batch_size=32,
    double_dqn=False,
    reward_centering=0.0,
    lr=1e-3,
    lr_end=1e-3,
    max_grad_norm=0.0,
    tau=1e-3,
    policy_network="online",
    hidden=(32, 32),
    layer_norm=False,
    name="dqn_paper",
)
"""The reference profile (MODEL.md § Learning setup, the authors' Keras DQN) on one stream:
32-32 ReLU, ε = 0.1, replay 50 000, 100 warm-up steps, one update of 32 per step, Adam 1e-3,
τ = 1e-3."""


@dataclass(frozen=True)
class PosteriorConfig:
    """Posterior sampling on the model's form (``learner=posterior``; MODEL.md § E).

    Attributes:
        episodes: episodes of the stream.
        prior_count: pseudo-count of each outcome in the Dirichlet and Beta priors (chains,
            events, detection, false alarms).
        gamma: the discount each sampled model is planned with (the optimum's, 0.99).
        tol: value iteration's tolerance on the sampled models.
        sweeps_per_step: 0: each plan is made between two steps, the vehicle waiting for it;
            k ≥ 1: beside the acting, k sweeps of value iteration after each step, the vehicle
            acting on its last plan until the new one is ready (a draw made meanwhile restarts
            the plan from where it stood).
        name: the profile's name.
    """

    episodes: int = DEFAULT_EPISODES
    prior_count: float = 1.0
    gamma: float = 0.99
    tol: float = 1e-6
    sweeps_per_step: int = 0
    name: str = field(default="posterior", compare=False)

    def __post_init__(self) -> None:
        checks.check_numbers(
            self,
            "algo.",
            (
                ("episodes", 1, 10**7, checks.INT),
                ("prior_count", 0, 1e6, {"open_lo": True}),
                ("gamma", 0, 1, checks.OPEN_HI),
                ("tol", 0, 1, {"open_lo": True}),
                ("sweeps_per_step", 0, 10**6, checks.INT),
            ),
        )


POSTERIOR = PosteriorConfig()

POSTERIOR_ANYTIME = PosteriorConfig(sweeps_per_step=1, name="posterior_anytime")
"""Posterior sampling planning beside its acting, one sweep of value iteration a step: the vehicle
never waits for a plan, only for a draw and a sweep."""


@dataclass(frozen=True)
class SafeConfig:
    """The safe learner (``learner=safe``; MODEL.md § E, safe learning).

    Attributes:
        episodes: episodes of the stream.
        target_miss: m*: the vehicle's cumulative miss detection is kept at or under it, and its
            plans aim at it.
        prior_count: as ``PosteriorConfig``'s.
        evaluations_per_step: each plan is the LP's optimum, found on the LP's Lagrangian dual
            (``irdrc.core.cmdp_dual``). 0: solved between two steps, the vehicle waiting for it;
            k ≥ 1: beside the acting, k units of planning work after each step (a batch of the
            noisy-or sampler's sweeps, the model, or one policy evaluation), the vehicle acting on
            its last plan until the new one is ready.
        name: the profile's name.
    """

    episodes: int = DEFAULT_EPISODES
    target_miss: float = 0.05
    prior_count: float = 1.0
    evaluations_per_step: int = 0
    name: str = field(default="safe", compare=False)

    def __post_init__(self) -> None:
        checks.check_numbers(
            self,
            "algo.",
            (
                ("episodes", 1, 10**7, checks.INT),
                ("target_miss", 0, 1, {"open_lo": True, "open_hi": True}),
                ("prior_count", 0, 1e6, {"open_lo": True}),
                ("evaluations_per_step", 0, 10**6, checks.INT),
            ),
        )


SAFE = SafeConfig()

SAFE_ANYTIME = SafeConfig(evaluations_per_step=1, name="safe_anytime")
"""The safe learner planning beside its acting, one unit of planning work a step: its plans are
the LP's optimum found on the LP's dual, and the vehicle never waits for one."""

QLEARNING = dataclasses.replace(QLearningConfig(), episodes=DEFAULT_EPISODES)
"""Our tabular Q-learning (``recipes/qlearning.py``'s profile: step sizes 1/k, uniform exploration)
on one stream."""

QLEARNING_PAPER = QLearningConfig(
    episodes=DEFAULT_EPISODES,
    alpha=0.01,
    alpha_schedule="constant",
    epsilon_end=0.1,
    name="qlearning_paper",
)
"""The reference profile (α = 0.01, ε = 0.1, γ = 0.99) on one stream."""

PROFILES: dict[str, Any] = {
    "dqn": DQN,
    "dqn_paper": DQN_PAPER,
    "posterior": POSTERIOR,
    "posterior_anytime": POSTERIOR_ANYTIME,
    "qlearning": QLEARNING,
    "qlearning_paper": QLEARNING_PAPER,
    "safe": SAFE,
    "safe_anytime": SAFE_ANYTIME,
}
"""Each learner's profile (``learner=…``), its ``algo.*`` defaults."""

LEARNERS = tuple(PROFILES)

SAFE_LEARNERS = ("safe", "safe_anytime")
"""The profiles of the safe learner, read against the LP at their ``target_miss``."""


ELSEWHERE = {
    "dqn_lagrangian": "python recipes/constrained.py learner=dqn_lagrangian",
    "sac": "python recipes/sac.py",
    "ppo": "python recipes/ppo.py",
    **{n: f"python recipes/fleet.py learner={n}" for n in FLEET_LEARNERS},
}
"""Learners of other recipes, by the name a user may try here: where each runs."""


def learner_config(learner: str, algo: Any) -> Any:
    """The profile of ``learner`` with the ``algo`` mapping's keys over it; unknown keys are
    refused, naming the closest of that learner's keys (a learner of another recipe, that
    recipe). A learner of one's own (``PATH.py:Class``) is ``irdrc.online.own``'s."""
    if learner in ELSEWHERE:
        raise ValueError(
            f"learner={learner} is not a learner on one vehicle's stream: use {ELSEWHERE[learner]}"
        )
    if learner not in LEARNERS:
        raise ValueError(
            f"learner={learner!r} must be one of {', '.join(LEARNERS)}, or one of your own: "
            "learner=PATH.py:Class"
        )
    base = PROFILES[learner]
    data = dict(algo or {})
    names = _keys(learner)
    for key in sorted(set(data) - names):
        readers = [n for n in LEARNERS if key in _keys(n)]
        if readers:
            raise ValueError(
                f"algo.{key} is read by learner={'|'.join(readers)}, not by learner={learner} "
                f"(which reads algo." + ", algo.".join(sorted(names)) + ")"
            )
    checks.reject_unknown_keys("algo.", data, names)
    if "hidden" in data and isinstance(data["hidden"], list):
        data["hidden"] = tuple(data["hidden"])
    return dataclasses.replace(base, **data)


def recorded_algo(algo: Any) -> dict[str, Any]:
    """A learner's config (``learner_config``'s) as a run records it under ``algo`` in
    ``config.yaml`` and its checkpoint: every key, plain containers. A resumed run and a
    checkpoint's evaluation then read the profile the run learned with, not this version's."""
    return {
        f.name: list(value) if isinstance(value := getattr(algo, f.name), tuple) else value
        for f in dataclasses.fields(algo)
        if f.name != "name"
    }


def _keys(learner: str) -> set[str]:
    """The ``algo.*`` keys of ``learner``'s profile."""
    return {f.name for f in dataclasses.fields(PROFILES[learner]) if f.name != "name"}
