"""Off-policy value learning on the batched simulator: the parts every value-based learner composes
(DQN and the Lagrangian DQN), built in a fixed order.

model (``make_qnet``) → exploration (``LadderExploration``) → buffer (``make_buffer``) → loss
(``make_dqn_loss``) → target updater (``make_target_updater``) → optimiser (``make_optimizer``) →
collector (``make_collector``); then ``OffPolicyLoop`` collects from many env rows at once, stores,
and runs the gradient updates that are due.

The design is distributed DQN on one machine (Ape-X, Horgan et al. 2018): one batched env of
``num_envs`` rows, each row exploring at its own rate (an ε ladder, with random actions held for
several steps so that runs of one mode reach the long queues), a large prioritised replay, large
batches, a normalised network (LayerNorm, as PQN uses), and as many updates per env step as
``updates_per_batch`` asks. docs/DQN.md says why each default is what it is.
"""

from __future__ import annotations

import contextlib
import math
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field, fields
from typing import Any

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import TensorDictModuleBase, TensorDictSequential
from torch import nn
from torchrl.collectors import Collector
from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer
from torchrl.data.replay_buffers.samplers import RandomSampler
from torchrl.envs.transforms import MultiStepTransform
from torchrl.envs.utils import ExplorationType, exploration_type
from torchrl.modules import MLP, QValueActor
from torchrl.objectives import DQNLoss, HardUpdate, SoftUpdate

from irdrc.agents.base import Hooks, RunRecord
from irdrc.agents.replay import make_prioritized_sampler
from irdrc.core.env import DFRCEnv
from irdrc.core.params import check_bool, check_choice, check_number, reject_unknown_keys, to_plain

ACTIVATIONS = {"relu": nn.ReLU, "tanh": nn.Tanh, "elu": nn.ELU, "gelu": nn.GELU, "silu": nn.SiLU}

STORED_KEYS = (
    "observation",
    "action",
    ("next", "observation"),
    ("next", "reward"),
    ("next", "done"),
    ("next", "terminated"),
    ("next", "truncated"),
)
"""What a transition keeps in replay (learners that need more, e.g. cost signals, add theirs)."""


# -- configuration ---------------------------------------------------------------------------------


@dataclass(frozen=True)
class NetworkConfig:
    """Q-network shape (config group ``network``): hidden layer sizes, activation, and whether
    each hidden layer is normalised (LayerNorm before the activation). Observations enter scaled
    to [0, 1] (each entry divided by its largest level)."""

    hidden: tuple[int, ...] = (64, 64)
    activation: str = "relu"
    layer_norm: bool = True

    def __post_init__(self) -> None:
        hidden = self.hidden if isinstance(self.hidden, list | tuple) else None
        object.__setattr__(self, "hidden", tuple(hidden) if hidden is not None else ())
        if not self.hidden or any(
            isinstance(h, bool) or not isinstance(h, int) or not 1 <= h <= 65536
            for h in self.hidden
        ):
            raise ValueError(
                f"network.hidden={hidden if hidden is not None else self.hidden!r} must be a "
                "non-empty list of integers in [1, 65536]"
            )
        check_choice("network.activation", self.activation, tuple(ACTIVATIONS))
        check_bool("network.layer_norm", self.layer_norm)

    @classmethod
    def from_dict(cls, data: Any) -> NetworkConfig:
        """From a mapping with ``hidden``, ``activation``, ``layer_norm`` (``name`` is ignored)."""
        data = {k: v for k, v in dict(to_plain(data)).items() if k != "name"}
        reject_unknown_keys("network.", data, {f.name for f in fields(cls)})
        return cls(**data)


@dataclass(frozen=True)
class OffPolicyConfig:
    """The machinery's hyperparameters (config group ``algo``); every key names its unit.

    Attributes:
        num_envs: env rows stepped together (one batched ``DFRCEnv``), each exploring at its own
            rate (``eps_max`` … ``eps_min``).
        frames_per_batch: env steps per collection (a multiple of ``num_envs``).
        total_frames: env steps of the whole run.
        init_random_frames: env steps with uniformly random actions before the network acts.
        buffer_size: replay capacity, transitions.
        batch_size: transitions per gradient update.
        updates_per_batch: gradient updates after each collection (the replay ratio is
            ``updates_per_batch · batch_size / frames_per_batch`` samples per env step).
        lr, lr_end: Adam's learning rate, annealed linearly from ``lr`` to ``lr_end`` over
            ``total_frames`` (equal: constant).
        max_grad_norm: gradient clipping (0 = off).
        gamma: discount γ.
        n_steps: 1 (TD(0)), or the length of the n-step returns stored in replay (TorchRL's
            ``MultiStepTransform``; the loss discounts by γ^n).
        loss_function: ``l2`` (default; ``smooth_l1`` clips the rare −r3 penalty), ``l1``,
            ``smooth_l1``.
        double_dqn: the online network picks the next action (van Hasselt et al.).
        eps_max, eps_min: row i of ``num_envs`` explores with ε_i = eps_max·(eps_min/eps_max)^(i/(N−1))
            (log-uniform; one row: ``eps_max``).
        eps_duration_max: 1 (ε-greedy), or the longest hold of a random action: an exploring row
            keeps its random action for n ≤ this steps, P(n) ∝ n^−2 (εz-greedy, Dabney et al. 2021).
        target_update: ``soft`` (Polyak, rate ``tau`` per update) or ``hard`` (copy every
            ``target_update_every_updates`` updates).
        policy_network: whose greedy actions are the learner's policy — every exact evaluation
            and the final policy: ``target`` (the target network, a Polyak average of the online
            one, so one noisy update does not flip a near-tie) or ``online``. The online network
            always acts.
        reward_centering: 0 (off), or the rate per env step of an exponential average r̄ of the
            collected rewards, subtracted from every sampled reward (reward centering, Naik et al.
            2024): without terminal states this shifts every Q-value by r̄/(1 − γ) and leaves the
            greedy policy unchanged, and the network fits only the differences between states.
        prioritized: proportional prioritised replay with exponent ``alpha`` and importance
            exponent annealed from ``beta_start`` to 1 over ``total_frames``.
        sampler: ``auto`` (TorchRL's when its extension loads, else ours), ``torchrl``, ``torch``.
        network: the Q-network's shape (config group ``network``).
    """

    num_envs: int = 1000
    frames_per_batch: int = 2000
    total_frames: int = 500_000
    init_random_frames: int = 0
    buffer_size: int = 1_048_576
    batch_size: int = 1000
    updates_per_batch: int = 4
    lr: float = 3e-3
    lr_end: float = 1e-5
    max_grad_norm: float = 10.0
    gamma: float = 0.99
    n_steps: int = 1
    loss_function: str = "l2"
    double_dqn: bool = True
    eps_max: float = 1.0
    eps_min: float = 0.01
    eps_duration_max: int = 64
    target_update: str = "soft"
    tau: float = 0.02
    target_update_every_updates: int = 500
    policy_network: str = "target"
    reward_centering: float = 1e-5
    prioritized: bool = True
    alpha: float = 0.6
    beta_start: float = 1.0
    sampler: str = "auto"
    network: NetworkConfig = field(default_factory=NetworkConfig)
    name: str = field(default="dqn", compare=False)

    def __post_init__(self) -> None:
        def num(key: str, lo: float, hi: float = math.inf, **kw: Any) -> None:
            object.__setattr__(
                self, key, check_number(f"algo.{key}", getattr(self, key), lo, hi, **kw)
            )

        # Sizes are capped where a larger value could only exhaust memory or time on any machine.
        for key in ("num_envs", "frames_per_batch", "batch_size"):
            num(key, 1, 10**7, integer=True)
        num("total_frames", 1, 10**12, integer=True)
        num("buffer_size", 1, 10**9, integer=True)
        num("updates_per_batch", 1, 10**6, integer=True)  # 0 would never learn
        num("init_random_frames", 0, 10**12, integer=True)
        num("target_update_every_updates", 1, 10**12, integer=True)
        num("eps_duration_max", 1, 10**6, integer=True)
        num("n_steps", 1, 1000, integer=True)
        num("lr", 0, 1, open_lo=True, open_hi=True)
        num("lr_end", 0, 1, open_hi=True)
        num("max_grad_norm", 0)
        num("gamma", 0, 1, open_hi=True)
        for key in ("eps_max", "eps_min", "tau", "beta_start"):
            num(key, 0, 1)
        num("reward_centering", 0, 1, open_hi=True)
        num("alpha", 0, 10)
        check_choice("algo.loss_function", self.loss_function, ("l2", "l1", "smooth_l1"))
        check_choice("algo.target_update", self.target_update, ("soft", "hard"))
        check_choice("algo.sampler", self.sampler, ("auto", "torchrl", "torch"))
        check_choice("algo.policy_network", self.policy_network, ("target", "online"))
        check_bool("algo.double_dqn", self.double_dqn)
        check_bool("algo.prioritized", self.prioritized)
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
    def from_dict(cls, data: Any, network: Any = None, **extra: Any):
        """From a mapping (the ``algo`` config node) and optionally the ``network`` node; unknown
        keys are rejected, naming the closest valid one."""
        data = dict(to_plain(data))
        reject_unknown_keys("algo.", data, cls.keys())
        if network is not None:
            data["network"] = NetworkConfig.from_dict(network)
        return cls(**{**data, **extra})

    @classmethod
    def from_node(cls, cfg: Any):
        """From a recipe's config (its ``algo`` and ``network`` groups)."""
        return cls.from_dict(cfg["algo"], cfg["network"])

    def env_steps(self, horizon: int) -> int:
        """Env steps of the whole run."""
        return self.total_frames


# -- model -----------------------------------------------------------------------------------------


class Scale(nn.Module):
    """Divides observations by their upper bounds, so every input lies in [0, 1]."""

    def __init__(self, high: torch.Tensor) -> None:
        super().__init__()
        self.register_buffer("inv", 1.0 / high.clamp(min=1.0))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x * self.inv


def observation_top(env: DFRCEnv) -> torch.Tensor:
    """[n] the largest value of each observation entry (the spec's ``high`` of one row)."""
    spec = env.observation_spec["observation"]
    return spec.space.high.reshape(-1, spec.shape[-1])[0].to(torch.float32)


def make_mlp(env: DFRCEnv, net: NetworkConfig, out_features: int) -> nn.Sequential:
    """The network body sized from the env's observation spec: scaled observation in,
    ``out_features`` out, each hidden layer Linear → LayerNorm (``net.layer_norm``) → activation."""
    return make_body(observation_top(env), net, out_features, env.device)


def make_body(
    high: torch.Tensor, net: NetworkConfig, out_features: int, device: Any = "cpu"
) -> nn.Sequential:
    """``make_mlp`` for observations whose entries lie in [0, ``high``] (any leading dims)."""
    norm = (
        {"norm_class": nn.LayerNorm, "norm_kwargs": [{"normalized_shape": h} for h in net.hidden]}
        if net.layer_norm
        else {}
    )
    mlp = MLP(
        in_features=high.shape[0],
        out_features=out_features,
        num_cells=list(net.hidden),
        activation_class=ACTIVATIONS[net.activation],
        device=device,
        **norm,
    )
    return nn.Sequential(Scale(high).to(device), mlp)


def make_qnet(env: DFRCEnv, net: NetworkConfig) -> QValueActor:
    """Q-value actor: observation in, one Q-value per action out, greedy action."""
    module = make_mlp(env, net, env.action_spec_unbatched.space.n)
    return QValueActor(module=module, in_keys=["observation"], spec=env.action_spec_unbatched)


# -- exploration -----------------------------------------------------------------------------------


def eps_ladder(rows: int, eps_max: float, eps_min: float) -> torch.Tensor:
    """[rows] exploration rates, log-uniform from ``eps_max`` (row 0) to ``eps_min`` (last row)."""
    if rows == 1 or eps_max == eps_min:
        return torch.full((rows,), float(eps_max))
    if eps_min <= 0:
        # log-uniform needs eps_min > 0: linear to 0 instead
        return torch.linspace(eps_max, 0.0, rows)
    i = torch.arange(rows, dtype=torch.float64) / (rows - 1)
    return (eps_max * (eps_min / eps_max) ** i).float()


class LadderExploration(TensorDictModuleBase):
    """ε-greedy with a rate per env row and held random actions (a TorchRL exploration module).

    Row i starts an exploration with probability ε_i when it is not already exploring: a uniformly
    random action held for n steps, n drawn from P(n) ∝ n^−2 truncated at ``max_duration``
    (``max_duration`` 1: plain ε-greedy). Long holds of radar fill the queue, so the rows reach the
    long-queue states that one-step dithering almost never does. Deterministic (greedy) when the
    exploration type is not random, as TorchRL's ``EGreedyModule``.

    Args:
        eps: [rows] exploration rates (``eps_ladder``); the env's batch must have ``rows`` rows
            (a leading batch dimension of that size, or one row broadcast to every batch entry).
        max_duration: the longest hold.
        num_actions: size of the discrete action space.
        action_key: where the action is (a multi-agent env's ``("agents", "action")``: the
            agents of a row share its rate, each holding its own random actions).
    """

    def __init__(
        self,
        eps: torch.Tensor,
        max_duration: int = 1,
        num_actions: int = 2,
        action_key: Any = "action",
    ) -> None:
        super().__init__()
        self.action_key = action_key
        self.in_keys = [action_key]
        self.out_keys = [action_key]
        self.register_buffer("eps", eps.float())
        n = torch.arange(1, int(max_duration) + 1, dtype=torch.float64)
        self.register_buffer("duration_p", (n**-2.0 / (n**-2.0).sum()).float())
        self.max_duration = int(max_duration)
        self.num_actions = int(num_actions)
        self.remaining: torch.Tensor | None = None
        self.held: torch.Tensor | None = None

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        if exploration_type() not in (ExplorationType.RANDOM, None):
            return tensordict
        action = tensordict.get(self.action_key)
        eps = self.eps.view(-1, *([1] * (action.dim() - 1))) if action.dim() else self.eps[0]
        if self.max_duration <= 1:
            explore = torch.rand(action.shape, device=action.device) < eps
            random = torch.randint_like(action, self.num_actions)
            tensordict.set(self.action_key, torch.where(explore, random, action))
            return tensordict
        if self.remaining is None or self.remaining.shape != action.shape:
            self.remaining = torch.zeros(action.shape, dtype=torch.long, device=action.device)
            self.held = torch.zeros_like(action)
        start = (self.remaining == 0) & (torch.rand(action.shape, device=action.device) < eps)
        k = int(start.sum())
        if k:
            self.remaining[start] = torch.multinomial(self.duration_p, k, replacement=True) + 1
            self.held[start] = torch.randint(
                0, self.num_actions, (k,), dtype=action.dtype, device=action.device
            )
        exploring = self.remaining > 0
        tensordict.set(self.action_key, torch.where(exploring, self.held, action))
        self.remaining = (self.remaining - 1).clamp(min=0)
        return tensordict


def make_exploration(env: DFRCEnv, cfg: OffPolicyConfig) -> LadderExploration:
    """The ε ladder over the env's rows (``eps_max`` … ``eps_min``), holds up to
    ``eps_duration_max`` steps."""
    rows = env.batch_size[0] if len(env.batch_size) else 1
    return LadderExploration(
        eps_ladder(rows, cfg.eps_max, cfg.eps_min).to(env.device),
        cfg.eps_duration_max,
        env.action_spec_unbatched.space.n,
    )


# -- replay, loss, target, optimiser ---------------------------------------------------------------


def make_buffer(cfg: OffPolicyConfig) -> tuple[TensorDictReplayBuffer, Any]:
    """Replay: prioritised (``irdrc.agents.replay``) or uniform, ``batch_size`` per sample.
    Returns (buffer, sampler)."""
    if cfg.prioritized:
        sampler = make_prioritized_sampler(
            cfg.buffer_size, cfg.alpha, cfg.beta_start, prefer=cfg.sampler
        )
    else:
        sampler = RandomSampler()
    rb = TensorDictReplayBuffer(
        storage=LazyTensorStorage(cfg.buffer_size), sampler=sampler, batch_size=cfg.batch_size
    )
    return rb, sampler


def make_dqn_loss(qnet: QValueActor, env: DFRCEnv, cfg: OffPolicyConfig) -> DQNLoss:
    """TorchRL's ``DQNLoss`` with a target network, the chosen distance and γ (its TD(0)
    estimator reads ``steps_to_next_obs`` of n-step transitions and discounts by γ^n)."""
    loss = DQNLoss(
        qnet,
        loss_function=cfg.loss_function,
        delay_value=True,
        double_dqn=cfg.double_dqn,
        action_space=env.action_spec_unbatched,
    )
    loss.make_value_estimator(gamma=cfg.gamma)
    return loss


class PolyakUpdate(SoftUpdate):
    """TorchRL's ``SoftUpdate`` (θ′ ← θ′ + τ·(θ − θ′) after every update) with every target
    tensor stepped by one ``foreach`` lerp over tensor lists cached when it is built, instead of a
    walk through the loss's parameter TensorDicts per step: the same update, about a tenth of the
    cost per step (``tests/test_dqn.py`` holds it to ``SoftUpdate``)."""

    def __init__(self, loss_module: nn.Module, *, tau: float) -> None:
        super().__init__(loss_module, tau=tau)
        keys = list(self._sources.keys(True, True))
        self._source_list = [self._sources.get(k).data for k in keys]
        self._target_list = [self._targets.get(("target_" + k[0], *k[1:])).data for k in keys]
        self._weight = float(1.0 - self.eps)

    def step(self) -> None:
        """One Polyak step of every target tensor."""
        torch._foreach_lerp_(self._target_list, self._source_list, self._weight)


def make_target_updater(loss: nn.Module, cfg: OffPolicyConfig):
    """Soft (Polyak, ``tau`` per update: ``PolyakUpdate``) or hard (every
    ``target_update_every_updates``)."""
    if cfg.target_update == "soft":
        return PolyakUpdate(loss, tau=cfg.tau)
    return HardUpdate(loss, value_network_update_interval=cfg.target_update_every_updates)


def make_optimizer(loss: nn.Module, cfg: OffPolicyConfig) -> torch.optim.Adam:
    """Adam over the loss's trainable parameters (one ``foreach`` kernel per step)."""
    return torch.optim.Adam(loss.parameters(), lr=cfg.lr, foreach=True)


def make_collector(
    env: DFRCEnv, policy: TensorDictSequential, cfg: OffPolicyConfig, frames: int, seed: int
) -> Collector:
    """TorchRL's collector over the batched env: ``frames_per_batch`` env steps per batch, shaped
    [rows, steps]; the first ``init_random_frames`` (of a fresh run) with random actions."""
    collector = Collector(
        env,
        policy,
        frames_per_batch=cfg.frames_per_batch,
        total_frames=frames,
        init_random_frames=cfg.init_random_frames,
        device=env.device,
        auto_register_policy_transforms=False,
    )
    collector.set_seed(seed)
    return collector


class RewardCenter:
    """The running average r̄ of collected rewards that reward centering subtracts
    (``OffPolicyConfig.reward_centering``): the first batch's mean, then an exponential average at
    ``rate`` per env step. An n-step transition's summed reward loses r̄·(1 − γ^n)/(1 − γ)."""

    def __init__(self, rate: float, gamma: float, value: float | None = None) -> None:
        self.rate = float(rate)
        self.gamma = float(gamma)
        self.value = value

    @property
    def on(self) -> bool:
        """Whether centering is enabled (``rate`` > 0)."""
        return self.rate > 0

    def update(self, reward: torch.Tensor) -> None:
        """Fold in one collected batch of one-step rewards (any shape)."""
        if not self.on:
            return
        mean = float(reward.double().mean())
        if self.value is None:
            self.value = mean
        else:
            self.value += (1.0 - (1.0 - self.rate) ** reward.numel()) * (mean - self.value)

    def center(self, sample: TensorDictBase, key: Any = ("next", "reward")) -> TensorDictBase:
        """``sample`` with r̄ (discounted over each transition's steps) subtracted from ``key``."""
        if not self.on or self.value is None:
            return sample
        reward = sample.get(key)
        steps = sample.get("steps_to_next_obs", None)
        if steps is None:
            shift = self.value
        else:
            steps = steps.reshape(reward.shape).to(torch.float64)  # γ^n − 1 cancels in float32
            shift = (self.value * (1.0 - self.gamma**steps) / (1.0 - self.gamma)).to(reward.dtype)
        sample.set(key, reward - shift)
        return sample


def anneal(cfg: OffPolicyConfig, optimizer: torch.optim.Optimizer, sampler: Any, frames: int):
    """Learning rate (``lr`` → ``lr_end``) and PER's β (``beta_start`` → 1), linear in env steps."""
    progress = min(1.0, frames / cfg.total_frames)
    for group in optimizer.param_groups:
        group["lr"] = cfg.lr + (cfg.lr_end - cfg.lr) * progress
    if cfg.prioritized:
        sampler.beta = cfg.beta_start + (1.0 - cfg.beta_start) * progress


def clip_and_step(
    loss: nn.Module, optimizer: torch.optim.Optimizer, max_norm: float, value: torch.Tensor
) -> float:
    """One gradient step on ``value`` (gradients clipped to ``max_norm`` when > 0); returns it."""
    optimizer.zero_grad(set_to_none=True)
    value.backward()
    if max_norm > 0:
        nn.utils.clip_grad_norm_(loss.parameters(), max_norm, foreach=True)
    optimizer.step()
    return float(value.detach())


# -- the loop --------------------------------------------------------------------------------------


class EpisodeTracker:
    """Running episode returns of every env row; finished episodes go to ``record``'s
    ``episode_rewards`` (``learner``, ``episode``, ``env_steps`` at its end, ``reward``)."""

    def __init__(self, rows: int, record: RunRecord, learner: int = 0) -> None:
        self.total = torch.zeros(rows, dtype=torch.float64)
        self.record = record
        self.learner = learner

    def add(self, data: TensorDictBase, frames: int) -> None:
        """Fold in a collected batch [rows, T] that starts after ``frames`` env steps."""
        rows = self.total.shape[0]
        reward = data["next", "reward"].reshape(rows, -1).double().cpu()
        done = data["next", "done"].reshape(rows, -1).cpu()
        running = self.total[:, None] + reward.cumsum(1)
        # in time order; a row that ends several episodes in one batch subtracts, at each end,
        # its sum up to the previous one
        ends = sorted(done.nonzero().tolist(), key=lambda e: (e[1], e[0]))
        last_end = {}
        for row, t in ends:
            start_sum = running[row, last_end[row]] if row in last_end else 0.0
            self.record.episode_rewards.append(
                {
                    "learner": self.learner,
                    "episode": len(self.record.episode_rewards) + 1,
                    "env_steps": frames + (t + 1) * rows,
                    "reward": float(running[row, t] - start_sum),
                }
            )
            last_end[row] = t
        end = running[:, -1].clone()
        for row, t in last_end.items():
            end[row] = running[row, -1] - running[row, t]
        self.total = end


class OffPolicyLoop:
    """Collect from the batched env, store each batch in replay, and run the gradient updates that
    are due: the loop every value-based learner shares. The learner iterates ``batches()`` and
    calls ``learn`` with its own update, then reports, evaluates and checkpoints as it sees fit.
    ``prepare`` (optional) rewrites each collected batch before anything reads it (the fleet's
    value decomposition puts the team reward at the root there); ``keys`` are what replay keeps.

    Attributes:
        frames: env steps so far (a resumed run starts at its checkpoint's).
        updates: gradient updates so far.
        record: the run record (episodes land in it).
    """

    def __init__(
        self,
        cfg: OffPolicyConfig,
        collector: Collector,
        buffer: TensorDictReplayBuffer,
        sampler: Any,
        optimizer: torch.optim.Optimizer,
        center: RewardCenter,
        record: RunRecord,
        hooks: Hooks,
        *,
        start_frames: int = 0,
        keys: tuple = STORED_KEYS,
        center_key: Any = ("next", "reward"),
        prepare: Callable[[TensorDictBase], TensorDictBase] | None = None,
    ) -> None:
        self.cfg = cfg
        self.collector = collector
        self.buffer = buffer
        self.sampler = sampler
        self.optimizer = optimizer
        self.center = center
        self.record = record
        self.hooks = hooks
        self.frames = start_frames
        self.updates = record.updates
        self.keys = keys
        self.center_key = center_key
        self.prepare = prepare
        self.episodes = EpisodeTracker(cfg.num_envs, record)
        # a fresh run learns once its random warm-up is stored; a resumed one (its replay is not
        # checkpointed) as soon as it holds a batch
        self.learn_from = (
            cfg.batch_size if start_frames else max(cfg.batch_size, cfg.init_random_frames)
        )
        self.multistep = MultiStepTransform(cfg.n_steps, cfg.gamma) if cfg.n_steps > 1 else None
        self.last_loss = math.nan
        self.seconds = {"collect": 0.0, "store": 0.0, "learn": 0.0}
        """Wall seconds spent collecting (policy and env steps), storing (episodes, centre,
        replay), and learning (sampling, updates, priorities): where training time goes."""

    def batches(self) -> Iterator[TensorDictBase]:
        """Each collected batch [rows, steps], after it is stored in replay and counted."""
        batches = iter(self.collector)
        while True:
            t0 = time.perf_counter()
            data = next(batches, None)
            t1 = time.perf_counter()
            self.seconds["collect"] += t1 - t0
            if data is None:
                return
            n = data.numel()
            if self.prepare is not None:
                data = self.prepare(data)
            self.episodes.add(data, self.frames)
            self.center.update(data.get(self.center_key))
            stored = data.select(*self.keys)
            if self.multistep is not None:
                stored = self.multistep.inv(stored)  # the last n − 1 steps wait for the next batch
            if stored is not None:
                self.buffer.extend(stored.reshape(-1))
            self.frames += n
            anneal(self.cfg, self.optimizer, self.sampler, self.frames)
            self.seconds["store"] += time.perf_counter() - t1
            yield data

    def ready(self) -> bool:
        """Whether replay holds enough to learn from."""
        return len(self.buffer) >= self.learn_from

    def learn(self, update) -> float | None:
        """``updates_per_batch`` gradient updates, each ``update(sample) -> loss`` on a centred
        replay sample; returns the last loss (None when replay is not yet ready)."""
        if not self.ready():
            return None
        t0 = time.perf_counter()
        for _ in range(self.cfg.updates_per_batch):
            sample = self.center.center(self.buffer.sample(), self.center_key)
            self.last_loss = update(sample)
            self.updates += 1
        self.record.updates = self.updates
        self.seconds["learn"] += time.perf_counter() - t0
        return self.last_loss

    def scalars(self, **extra: Any) -> dict[str, Any]:
        """What a learner reports after each batch (``Hooks.on_batch``): env steps, episodes, the
        last loss, PER's β (NaN for uniform replay), the replay's size, and ``extra``."""
        return {
            "env_steps": self.frames,
            "episodes": len(self.record.episode_rewards),
            "loss": self.last_loss,
            "beta": getattr(self.sampler, "beta", math.nan),
            "buffer": len(self.buffer),
            **extra,
        }

    def stop_due(self) -> bool:
        """Whether the caller asked to stop (polled once per batch)."""
        return self.hooks.stop_requested()

    def shutdown(self) -> None:
        """Stop the collector and put the time spent per phase into the record's ``info``
        (``seconds_collect``, ``seconds_store``, ``seconds_learn``)."""
        self.collector.shutdown()
        for phase, seconds in self.seconds.items():
            self.record.info[f"seconds_{phase}"] = seconds


@contextlib.contextmanager
def policy_view(loss: nn.Module, cfg: OffPolicyConfig) -> Iterator[None]:
    """Inside, the loss's value network holds the parameters of ``cfg.policy_network``: the
    target network's (swapped in, and back on exit) or its own."""
    if cfg.policy_network == "target":
        with loss.target_value_network_params.to_module(loss.value_network):
            yield
    else:
        yield


def all_states(qnet: nn.Module, env: DFRCEnv) -> TensorDictBase:
    """``qnet`` (a Q-value actor) on the observation of every state, greedy."""
    with torch.no_grad():
        # an env that observes more than the state (the fleet's rows) brings its own table
        obs = getattr(env, "observation_table", None)
        obs = env.dynamics.obs if obs is None else obs
        return qnet(TensorDict({"observation": obs}, batch_size=[obs.shape[0]], device=obs.device))


def greedy_table(qnet: nn.Module, env: DFRCEnv) -> torch.Tensor:
    """The greedy action of the Q-network in every state ([S], ties → comm)."""
    return all_states(qnet, env)["action"].reshape(-1).long().cpu()


def action_values(qnet: nn.Module, env: DFRCEnv) -> torch.Tensor:
    """The Q-network's action values in every state ([S, 2], comm then radar)."""
    return all_states(qnet, env)["action_value"].reshape(-1, 2).float().cpu()
