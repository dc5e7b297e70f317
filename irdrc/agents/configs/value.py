"""The value learners' hyperparameters: a network's shape, DQN's (the off-policy machinery every
value learner shares) and tabular Q-learning's."""

from __future__ import annotations

import math
from dataclasses import dataclass, field, fields
from typing import Any, ClassVar, Self

from irdrc.core import checks

ACTIVATIONS = ("relu", "tanh", "elu", "gelu", "silu")
"""Hidden-layer activations (``network.activation``)."""
CENTER_ON = ("rewards", "values")
"""What reward centering's r̄ follows (``OffPolicyConfig.center_on``)."""


@dataclass(frozen=True)
class NetworkConfig:
    """A network's shape (config group ``network``): hidden layer sizes, activation, and whether each
    hidden layer is normalised (LayerNorm before the activation). Observations enter scaled to
    [0, 1] (each entry divided by its largest level)."""

    hidden: tuple[int, ...] = (64, 64)
    activation: str = "relu"
    layer_norm: bool = True

    def __post_init__(self) -> None:
        item = lambda key, h: checks.check_number(key, h, 1, 65536, integer=True)  # noqa: E731
        object.__setattr__(self, "hidden", checks.check_list("network.hidden", self.hidden, item))
        checks.check_choice("network.activation", self.activation, ACTIVATIONS)
        checks.check_bool("network.layer_norm", self.layer_norm)

    @classmethod
    def from_dict(cls, data: Any, prefix: str = "network.") -> NetworkConfig:
        """From the ``network`` mapping (``name`` is ignored); unknown keys are refused."""
        return checks.build(cls, {k: v for k, v in dict(data).items() if k != "name"}, prefix)


LARGE = NetworkConfig(hidden=(256, 256))
"""``network=large``: DQN's network (docs/DQN.md)."""

DEFAULT_NETWORK = NetworkConfig()
"""``network=default`` (64-64): the Lagrangian DQN's and the fleet's value learners' network."""


@dataclass(frozen=True)
class OffPolicyConfig:
    """DQN's hyperparameters (config group ``algo``), which every value learner shares; each key
    names its unit. Grouped as the learner builds its parts:

    Attributes:
        num_envs: env rows stepped together (one batched env), each exploring at its own rate.
        frames_per_batch: env steps per collection (a multiple of ``num_envs``).
        total_frames: env steps of the whole run.
        init_random_frames: env steps with uniformly random actions before the network acts.
        eps_max, eps_min: row i of ``num_envs`` explores with ε_i = eps_max·(eps_min/eps_max)^(i/(N−1))
            (log-uniform; one row: ``eps_max``).
        eps_duration_max: 1 (ε-greedy), or the longest hold of a random action: an exploring row
            keeps its random action for n ≤ this steps, P(n) ∝ n^−2 (εz-greedy, Dabney et al. 2021).
        buffer_size: replay capacity, transitions.
        prioritized: proportional prioritised replay with exponent ``alpha``, every sample
            weighted by its full importance correction (β = 1).
        gamma: discount γ.
        double_dqn: the online network picks the next action (van Hasselt et al.).
        reward_centering: 0 (off), or the rate per env step of an exponential average r̄ of the
            collected rewards, subtracted from every sampled reward (Naik et al. 2024): without
            terminal states this shifts every Q-value by r̄/(1 − γ) and leaves the greedy policy
            unchanged, and the network fits only the differences between states.
        center_on: what r̄ follows — ``values`` (DQN's default): the collected rewards' average,
            moved after every collected batch by (1 − γ) times the mean greedy value the network
            gives the collected states, so that the values the network fits stay near zero (the
            collected rewards average the exploring rows' too, far below what the greedy policy
            earns where exploring is costly); ``rewards``: the collected rewards' average alone
            (the fleet's learners, DQN over levels).
        reward_means: each sampled reward replaced by the mean reward of every step collected at
            its (observation, action) (the reward table, ``irdrc.agents.reward_table``): the target's expected
            reward from all the run's data, without the one sample's noise (docs/DQN.md).
        batch_size: transitions per gradient update.
        updates_per_batch: gradient updates after each collection (the replay ratio is
            ``updates_per_batch · batch_size / frames_per_batch`` samples per env step).
        lr, lr_end: Adam's learning rate, annealed linearly from ``lr`` to ``lr_end``.
        max_grad_norm: gradient clipping (0 = off).
        tau: the target network's Polyak rate per update.
        policy_network: whose greedy actions are the learner's policy — every evaluation and the
            final policy: ``target`` (a Polyak average, so one noisy update does not flip a
            near-tie) or ``online``. The online network always acts.
        network: the network's shape (config group ``network``; DQN's: ``large``, 256-256).
        name: the profile's name (runs are labelled with it).
    """

    num_envs: int = 8000
    frames_per_batch: int = 16_000
    total_frames: int = 4_000_000
    init_random_frames: int = 0
    eps_max: float = 1.0
    eps_min: float = 0.01
    eps_duration_max: int = 64
    buffer_size: int = 1_048_576
    prioritized: bool = True
    alpha: float = 0.6
    gamma: float = 0.99
    double_dqn: bool = True
    reward_centering: float = 1e-5
    center_on: str = "values"
    reward_means: bool = True
    batch_size: int = 4000
    updates_per_batch: int = 2
    lr: float = 6e-3
    lr_end: float = 1e-5
    max_grad_norm: float = 10.0
    tau: float = 0.02
    policy_network: str = "target"
    network: NetworkConfig = field(default_factory=lambda: LARGE, metadata={"keys": ()})
    name: str = field(default="dqn", compare=False)

    NUMBERS: ClassVar[tuple[checks.NumberSpec, ...]] = (
        # Sizes are capped where a larger value could only exhaust memory or time on any machine.
        ("num_envs", 1, 10**7, checks.INT),
        ("frames_per_batch", 1, 10**7, checks.INT),
        ("batch_size", 1, 10**7, checks.INT),
        ("total_frames", 1, 10**12, checks.INT),
        ("buffer_size", 1, 10**9, checks.INT),
        ("updates_per_batch", 1, 10**6, checks.INT),  # 0 would never learn
        ("init_random_frames", 0, 10**12, checks.INT),
        ("eps_duration_max", 1, 10**6, checks.INT),
        ("lr", 0, 1, {"open_lo": True, "open_hi": True}),
        ("lr_end", 0, 1, checks.OPEN_HI),
        ("max_grad_norm", 0, math.inf, {}),
        ("gamma", 0, 1, checks.OPEN_HI),
        ("eps_max", 0, 1, {}),
        ("eps_min", 0, 1, {}),
        ("tau", 0, 1, {}),
        ("reward_centering", 0, 1, checks.OPEN_HI),
        ("alpha", 0, 10, {}),
    )

    def __post_init__(self) -> None:
        checks.check_numbers(self, "algo.", self.NUMBERS)
        checks.check_choice("algo.policy_network", self.policy_network, ("target", "online"))
        checks.check_choice("algo.center_on", self.center_on, CENTER_ON)
        checks.check_bool("algo.double_dqn", self.double_dqn)
        checks.check_bool("algo.prioritized", self.prioritized)
        checks.check_bool("algo.reward_means", self.reward_means)
        if not isinstance(self.network, NetworkConfig):
            raise ValueError(f"network={self.network!r} must be a NetworkConfig")
        # Combinations, named by their keys.
        if self.eps_min > self.eps_max:
            raise ValueError(
                f"algo.eps_min={self.eps_min} must be <= algo.eps_max={self.eps_max} (the ladder "
                "runs from eps_max on the first row to eps_min on the last)"
            )
        if self.frames_per_batch % self.num_envs:
            raise ValueError(
                f"algo.frames_per_batch={self.frames_per_batch} must be a multiple of "
                f"algo.num_envs={self.num_envs}"
            )
        if self.init_random_frames >= self.total_frames:
            raise ValueError(
                f"algo.init_random_frames={self.init_random_frames} must be < "
                f"algo.total_frames={self.total_frames} (no learning would happen)"
            )
        if self.buffer_size < self.batch_size:
            raise ValueError(
                f"algo.buffer_size={self.buffer_size} must be >= algo.batch_size={self.batch_size}"
            )
        if self.frames_per_batch > self.total_frames:
            raise ValueError(
                f"algo.frames_per_batch={self.frames_per_batch} must be <= "
                f"algo.total_frames={self.total_frames}"
            )

    @classmethod
    def keys(cls) -> set[str]:
        """The ``algo.*`` keys this config reads."""
        return {f.name for f in fields(cls) if f.name != "network"}

    @classmethod
    def from_sections(
        cls, algo: Any, network: Any = None, *, base: Any = None, **extra: Any
    ) -> Self:
        """From the ``algo`` mapping and the ``network`` mapping; unknown keys are refused, naming
        the closest valid one. A key the mappings leave out takes ``base``'s value (a learner's own
        default, e.g. the Lagrangian's), or this class's default without one."""
        data = dict(algo)
        if base is not None:
            data = {
                **{f.name: getattr(base, f.name) for f in fields(cls) if f.name != "network"},
                **data,
            }
        built = checks.build(cls, {k: v for k, v in data.items() if k != "network"}, "algo.")
        if network is not None:
            net = NetworkConfig.from_dict(network)
        elif base is not None:
            net = base.network
        elif not extra:
            return built
        else:
            net = built.network
        return _replace(built, network=net, **extra)


def _replace(obj: Any, **changes: Any) -> Any:
    """``dataclasses.replace`` (the checks run again)."""
    import dataclasses

    return dataclasses.replace(obj, **changes)


DQNConfig = OffPolicyConfig
"""DQN's config: the off-policy machinery's, nothing more."""


@dataclass(frozen=True)
class QLearningConfig:
    """Tabular Q-learning (config group ``algo`` of ``recipes/qlearning.py``).

    Attributes:
        episodes: training episodes per learner (each ``env.horizon`` steps).
        gamma: discount γ.
        alpha: step size; with ``alpha_schedule="count"`` the step size of the k-th update of a
            (state, action) pair is ``max(alpha_min, alpha / k**alpha_power)``.
        alpha_schedule: ``constant`` or ``count``.
        alpha_power: ω of the count schedule (1/2 < ω ≤ 1 keeps the Robbins–Monro conditions).
        alpha_min: floor of the count schedule.
        epsilon_start: exploration rate at the first episode.
        epsilon_end: exploration rate after ``epsilon_decay_episodes`` (linear in between).
        epsilon_decay_episodes: episodes over which ε decays; 0 keeps ``epsilon_end`` throughout.
        init_q: initial value of every Q entry.
        name: the profile's name.
    """

    episodes: int = 600
    gamma: float = 0.99
    alpha: float = 1.0
    alpha_schedule: str = "count"
    alpha_power: float = 1.0
    alpha_min: float = 0.0
    epsilon_start: float = 1.0
    epsilon_end: float = 1.0
    epsilon_decay_episodes: int = 0
    init_q: float = 0.0
    name: str = field(default="qlearning", compare=False)

    def __post_init__(self) -> None:
        checks.check_numbers(
            self,
            "algo.",
            (
                ("episodes", 1, 10**9, checks.INT),
                ("gamma", 0, 1, checks.OPEN_HI),
                ("alpha", 0, 1, {"open_lo": True}),
                ("alpha_power", 0, 1, {}),
                ("alpha_min", 0, 1, {}),
                ("epsilon_start", 0, 1, {}),
                ("epsilon_end", 0, 1, {}),
                ("epsilon_decay_episodes", 0, 10**9, checks.INT),
                ("init_q", -1e12, 1e12, {}),
            ),
        )
        checks.check_choice("algo.alpha_schedule", self.alpha_schedule, ("constant", "count"))

    @classmethod
    def from_dict(cls, data: Any, prefix: str = "algo.") -> QLearningConfig:
        """From the ``algo`` mapping; unknown keys are refused."""
        return checks.build(cls, data, prefix)

    def epsilon(self, episode: int) -> float:
        """ε during ``episode`` (0-based)."""
        if self.epsilon_decay_episodes == 0 or episode >= self.epsilon_decay_episodes:
            return self.epsilon_end
        frac = episode / self.epsilon_decay_episodes
        return self.epsilon_start + frac * (self.epsilon_end - self.epsilon_start)
