"""The continuous-action learners' hyperparameters (MODEL.md § D: the radar share ρ ∈ [0, 1])."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any, ClassVar

from irdrc.agents.configs.value import NetworkConfig
from irdrc.core import checks


@dataclass(frozen=True)
class ShareConfig:
    """What every learner of the radar share has (section ``algo``), on the off-policy loop every
    learner shares (``irdrc.agents.loop``): many env rows at once, the ε ladder, prioritised replay.

    Attributes:
        num_envs: env rows stepped together.
        frames_per_batch: env steps per collection (a multiple of ``num_envs``).
        total_frames: env steps of the whole run.
        init_random_frames: env steps with uniformly random shares before the actor acts.
        eps_max, eps_min: beside the actor's own sampling, row i of ``num_envs`` takes a uniformly
            random share with probability ε_i, log-uniform from eps_max to eps_min across rows
            (DQN's ladder): the critics see every share in every state the rows reach.
        buffer_size: replay capacity, transitions.
        prioritized: proportional prioritised replay (priority: the critics' TD error) with
            exponent ``alpha``, every sample weighted by its full importance correction (β = 1).
        gamma: discount γ.
        reward_centering: rate per env step of the average reward subtracted from sampled rewards
            (0: off); see ``OffPolicyConfig``.
        batch_size: transitions per gradient update.
        updates_per_batch: gradient updates per collection.
        lr, lr_end: Adam's learning rate, annealed linearly.
        max_grad_norm: gradient clipping (0: off).
        tau: the target actor's and critics' Polyak rate per update.
        network: the actor's and each critic's shape.
    """

    num_envs: int = 1000
    frames_per_batch: int = 2000
    total_frames: int = 800_000
    init_random_frames: int = 6_000
    eps_max: float = 1.0
    eps_min: float = 0.01
    buffer_size: int = 1_048_576
    prioritized: bool = True
    alpha: float = 0.6
    gamma: float = 0.99
    reward_centering: float = 1e-5
    batch_size: int = 1000
    updates_per_batch: int = 8
    lr: float = 1e-3
    lr_end: float = 1e-5
    max_grad_norm: float = 10.0
    tau: float = 0.01
    network: NetworkConfig = field(default_factory=NetworkConfig, metadata={"keys": ()})
    name: str = field(default="share", compare=False)

    NUMBERS: ClassVar[tuple[checks.NumberSpec, ...]] = (
        ("num_envs", 1, 10**7, checks.INT),
        ("frames_per_batch", 1, 10**7, checks.INT),
        ("total_frames", 1, 10**12, checks.INT),
        ("init_random_frames", 0, 10**12, checks.INT),
        ("eps_max", 0, 1, {}),
        ("eps_min", 0, 1, {}),
        ("buffer_size", 1, 10**9, checks.INT),
        ("alpha", 0, 10, {}),
        ("gamma", 0, 1, checks.OPEN_HI),
        ("reward_centering", 0, 1, checks.OPEN_HI),
        ("batch_size", 1, 10**7, checks.INT),
        ("updates_per_batch", 1, 10**6, checks.INT),
        ("lr", 0, 1, {"open_lo": True, "open_hi": True}),
        ("lr_end", 0, 1, checks.OPEN_HI),
        ("max_grad_norm", 0, 1e9, {}),
        ("tau", 0, 1, {}),
    )

    def __post_init__(self) -> None:
        checks.check_numbers(self, "algo.", self.NUMBERS)
        checks.check_bool("algo.prioritized", self.prioritized)
        if self.frames_per_batch % self.num_envs:
            raise ValueError(
                f"algo.frames_per_batch={self.frames_per_batch} must be a multiple of "
                f"algo.num_envs={self.num_envs}"
            )

    @classmethod
    def from_sections(cls, algo: Any, network: Any) -> Any:
        """From the ``algo`` and ``network`` sections; unknown keys are refused."""
        built = checks.build(cls, {k: v for k, v in dict(algo).items() if k != "network"}, "algo.")
        return dataclasses.replace(built, network=NetworkConfig.from_dict(network))


@dataclass(frozen=True)
class SACConfig(ShareConfig):
    """SAC's hyperparameters (``recipes/sac.py``): the machinery's and SAC's temperature.

    Attributes:
        temperature_init: the entropy temperature at the start, then tuned towards the target
            entropy at the optimiser's (annealed) learning rate: over a default run it about
            halves.
        target_entropy: the entropy the temperature is tuned towards, nats (TorchRL's "auto" is
            −1 for one action dimension, a spread of a third of [0, 1]).

    Half the machinery's updates, each on twice its batch (the same replay ratio): SAC's update
    costs mostly its fixed overhead at these sizes; and 720 000 env steps (about 50 s of training
    here on one thread).
    """

    total_frames: int = 720_000
    batch_size: int = 2000
    updates_per_batch: int = 4
    temperature_init: float = 0.1
    target_entropy: float = -5.0
    name: str = field(default="sac", compare=False)

    def __post_init__(self) -> None:
        super().__post_init__()
        checks.check_numbers(
            self,
            "algo.",
            (("temperature_init", 0, 1e3, {"open_lo": True}), ("target_entropy", -100, 100, {})),
        )


@dataclass(frozen=True)
class PPOConfig:
    """PPO's hyperparameters (``recipes/ppo.py``, section ``algo``): on-policy, so no replay, no
    exploration schedule and no target networks — the actor's own sampling explores.

    Attributes:
        num_envs: env rows stepped together.
        frames_per_batch: env steps per collection (a multiple of ``num_envs``): ``num_envs``
            rows × frames_per_batch / num_envs steps of each, one rollout to learn from.
        total_frames: env steps of the whole run (whole rollouts).
        gamma: discount γ.
        gae_lambda: GAE's λ (the advantage's bias–variance trade-off).
        reward_centering: rate per env step of the average reward subtracted from the collected
            rewards before the advantages (0: off); see ``OffPolicyConfig``.
        epochs: passes over each rollout.
        batch_size: transitions per gradient update (a rollout is split into minibatches of this).
        clip_epsilon: PPO's clip of the probability ratio.
        entropy_coeff: weight of the entropy bonus.
        critic_coeff: weight of the critic's loss.
        lr, lr_end: Adam's learning rate, annealed linearly.
        max_grad_norm: gradient clipping (0: off).
        network: the actor's and the critic's shape.
    """

    num_envs: int = 1000
    frames_per_batch: int = 32_000
    total_frames: int = 1_920_000
    gamma: float = 0.99
    gae_lambda: float = 0.95
    reward_centering: float = 1e-5
    epochs: int = 4
    batch_size: int = 4000
    clip_epsilon: float = 0.1
    entropy_coeff: float = 1e-3
    critic_coeff: float = 0.5
    lr: float = 3e-3
    lr_end: float = 1e-5
    max_grad_norm: float = 1.0
    network: NetworkConfig = field(default_factory=NetworkConfig, metadata={"keys": ()})
    name: str = field(default="ppo", compare=False)
    _section: str = field(default="algo", compare=False, repr=False)

    NUMBERS: ClassVar[tuple[checks.NumberSpec, ...]] = (
        ("num_envs", 1, 10**7, checks.INT),
        ("frames_per_batch", 1, 10**8, checks.INT),
        ("total_frames", 1, 10**12, checks.INT),
        ("gamma", 0, 1, checks.OPEN_HI),
        ("gae_lambda", 0, 1, {}),
        ("reward_centering", 0, 1, checks.OPEN_HI),
        ("epochs", 1, 1000, checks.INT),
        ("batch_size", 1, 10**8, checks.INT),
        ("clip_epsilon", 0, 10, {"open_lo": True}),
        ("entropy_coeff", 0, 100, {}),
        ("critic_coeff", 0, 100, {}),
        ("lr", 0, 1, {"open_lo": True, "open_hi": True}),
        ("lr_end", 0, 1, checks.OPEN_HI),
        ("max_grad_norm", 0, 1e9, {}),
    )

    init_random_frames: ClassVar[int] = 0
    """The actor acts from the first step (the loop's warm-up, for off-policy learners)."""
    prioritized: ClassVar[bool] = False
    """No replay."""

    def __post_init__(self) -> None:
        p = f"{self._section}."
        checks.check_numbers(self, p, self.NUMBERS)
        if self.frames_per_batch % self.num_envs:
            raise ValueError(
                f"{p}frames_per_batch={self.frames_per_batch} must be a multiple of "
                f"{p}num_envs={self.num_envs}"
            )
        if self.total_frames % self.frames_per_batch:
            raise ValueError(
                f"{p}total_frames={self.total_frames} must be a multiple of "
                f"{p}frames_per_batch={self.frames_per_batch} (whole rollouts)"
            )
        if self.batch_size > self.frames_per_batch:
            raise ValueError(
                f"{p}batch_size={self.batch_size} is larger than a rollout "
                f"({p}frames_per_batch={self.frames_per_batch})"
            )

    @property
    def updates_per_batch(self) -> int:
        """Gradient updates per rollout: ``epochs`` passes of ⌈frames_per_batch / batch_size⌉."""
        return self.epochs * -(-self.frames_per_batch // self.batch_size)

    @classmethod
    def from_sections(cls, algo: Any, network: Any) -> Any:
        """From its section (``algo``; the fleet's: ``ppo``) and ``network``; unknown keys are
        refused."""
        data = {k: v for k, v in dict(algo).items() if k != "network"}
        built = checks.build(cls, data, f"{cls._section}.")
        return dataclasses.replace(built, network=NetworkConfig.from_dict(network))
