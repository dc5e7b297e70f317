"""The parts every value learner composes (DQN, the Lagrangian DQN, the fleet's learners), in the
order a learner builds them: model → exploration → collector → buffer → target → optimiser; the
loop that drives them is ``irdrc.agents.loop``.

The design is distributed DQN on one machine (Ape-X, Horgan et al. 2018): one batched env of
``num_envs`` rows, each row exploring at its own rate (an ε ladder, with random actions held for
several steps so that runs of one mode reach the long queues), a large prioritised replay, large
batches, a normalised network (LayerNorm, as PQN uses), and as many updates per env step as
``updates_per_batch`` asks. docs/DQN.md says why each default is what it is.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator, Sequence
from typing import Any

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import TensorDictModuleBase, TensorDictSequential
from torch import nn
from torchrl.collectors import Collector
from torchrl.data import TensorDictReplayBuffer
from torchrl.data.replay_buffers.samplers import RandomSampler
from torchrl.envs.transforms import Compose, Transform
from torchrl.envs.utils import ExplorationType, exploration_type
from torchrl.modules import MLP, QValueActor
from torchrl.objectives import LossModule, SoftUpdate

from irdrc.agents.base import BatchSchedule, ReplayConfig, RunRecord
from irdrc.agents.configs.value import NetworkConfig, OffPolicyConfig
from irdrc.agents.levels import DistinctRows
from irdrc.agents.replay import PackedStorage, make_prioritized_sampler

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


# -- model -----------------------------------------------------------------------------------------


class Scale(nn.Module):
    """Divides observations by their upper bounds, so every input lies in [0, 1]."""

    inv: torch.Tensor

    def __init__(self, high: torch.Tensor) -> None:
        super().__init__()
        self.register_buffer("inv", 1.0 / high.clamp(min=1.0))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x * self.inv


def observation_top(env: Any) -> torch.Tensor:
    """[n] the largest value of each observation entry (the spec's ``high`` of one row)."""
    spec = env.observation_spec["observation"]
    return spec.space.high.reshape(-1, spec.shape[-1])[0].to(torch.float32)


def make_mlp(env: Any, net: NetworkConfig, out_features: int) -> nn.Sequential:
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


def make_qnet(env: Any, net: NetworkConfig) -> QValueActor:
    """Q-value actor: observation in, one Q-value per action out, greedy action (the body a
    ``DistinctRows``: in every pass, one evaluation per distinct observation)."""
    return q_actor(observation_top(env), net, env.action_spec_unbatched, env.device)


def q_actor(high: torch.Tensor, net: NetworkConfig, spec: Any, device: Any = "cpu") -> QValueActor:
    """``make_qnet`` for observations whose entries are integer levels in [0, ``high``] and the
    discrete action spec ``spec``."""
    body = make_body(high, net, spec.space.n, device)
    # the collector's thousands of rows, and a loss's samples, hold a few hundred distinct
    # observations: one evaluation each
    module = DistinctRows(*body, high=high.to(device))
    return QValueActor(module=module, in_keys=["observation"], spec=spec)


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
        remaining, held = self.remaining, self.held
        if remaining is None or held is None or remaining.shape != action.shape:
            remaining = torch.zeros(action.shape, dtype=torch.long, device=action.device)
            held = torch.zeros_like(action)
        start = (remaining == 0) & (torch.rand(action.shape, device=action.device) < eps)
        k = int(start.sum())
        if k:
            remaining[start] = torch.multinomial(self.duration_p, k, replacement=True) + 1
            held[start] = torch.randint(
                0, self.num_actions, (k,), dtype=action.dtype, device=action.device
            )
        tensordict.set(self.action_key, torch.where(remaining > 0, held, action))
        self.remaining, self.held = (remaining - 1).clamp(min=0), held
        return tensordict


def make_exploration(env: Any, cfg: OffPolicyConfig) -> LadderExploration:
    """The ε ladder over the env's rows (``eps_max`` … ``eps_min``), holds up to
    ``eps_duration_max`` steps."""
    rows = env.batch_size[0] if len(env.batch_size) else 1
    return LadderExploration(
        eps_ladder(rows, cfg.eps_max, cfg.eps_min).to(env.device),
        cfg.eps_duration_max,
        env.action_spec_unbatched.space.n,
    )


# -- collector -------------------------------------------------------------------------------------


def make_collector(
    env: Any, policy: TensorDictSequential, cfg: BatchSchedule, seed: int, start: int = 0
) -> Collector:
    """TorchRL's collector over the batched env: ``frames_per_batch`` env steps per batch, shaped
    [rows, steps], to ``total_frames``; the first ``init_random_frames`` with random actions. A run
    resumed at ``start`` env steps collects the rest on a stream of its own (seed + start), acting
    with its network from the first step."""
    collector = Collector(
        env,
        policy,
        frames_per_batch=cfg.frames_per_batch,
        total_frames=max(cfg.total_frames - start, cfg.frames_per_batch),  # none left: never run
        init_random_frames=cfg.init_random_frames,
        device=env.device,
        auto_register_policy_transforms=False,
    )
    collector.set_seed(seed + start)
    if start:
        collector.init_random_frames = 0
    return collector


# -- buffer, target, optimiser ---------------------------------------------------------------------


def make_buffer(
    cfg: ReplayConfig, transforms: Sequence[Transform] = ()
) -> tuple[TensorDictReplayBuffer, Any]:
    """Replay: prioritised (``irdrc.agents.replay``: TorchRL's sampler where its extension loads,
    else ours) or uniform, ``batch_size`` per sample, each transition one row of a
    ``PackedStorage``; ``transforms`` rewrite every sample as it is drawn, in order (TorchRL replay
    transforms: the reward table, the centering). Returns (buffer, sampler)."""
    if cfg.prioritized:
        sampler = make_prioritized_sampler(cfg.buffer_size, cfg.alpha, 1.0)
    else:
        sampler = RandomSampler()
    rb = TensorDictReplayBuffer(
        storage=PackedStorage(cfg.buffer_size),
        sampler=sampler,
        batch_size=cfg.batch_size,
        transform=Compose(*transforms) if transforms else None,
    )
    return rb, sampler


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


def make_optimizer(loss: nn.Module, cfg: BatchSchedule) -> torch.optim.Adam:
    """Adam over the loss's trainable parameters (one ``foreach`` kernel per step)."""
    return torch.optim.Adam(loss.parameters(), lr=cfg.lr, foreach=True)


class RewardCenter:
    """What the loss sees of the collected rewards: centred by their running average r̄
    (``OffPolicyConfig.reward_centering``: the first batch's mean, then an exponential average at
    ``rate`` per env step; ``rate`` 0: off)."""

    def __init__(self, rate: float, value: float | None = None) -> None:
        self.rate = float(rate)
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

    def follow(self, level: float, gamma: float) -> None:
        """Move r̄ by (1 − γ)·``level``, the mean greedy value the network gives a collected
        batch (``OffPolicyConfig.center_on=values``): values that sit at a level L above zero
        mean rewards centred too low by about (1 − γ)·L."""
        if self.on and self.value is not None:
            self.value += (1.0 - gamma) * float(level)

    def center(self, sample: TensorDictBase, key: Any = ("next", "reward")) -> TensorDictBase:
        """``sample`` with its rewards under ``key`` ``centred``."""
        r = sample.get(key)
        out = self.centred(r)
        if out is not r:
            sample.set(key, out)
        return sample

    def centred(self, reward: torch.Tensor) -> torch.Tensor:
        """``reward`` with r̄ subtracted (where on; else itself)."""
        if self.on and self.value is not None:
            reward = reward - self.value
        return reward

    def state(self) -> dict[str, float]:
        """The checkpoint's entry: the average, where set."""
        return {"reward_center": self.value} if self.value is not None else {}

    def load(self, state: dict[str, Any]) -> None:
        """Restore ``state``'s entry (a checkpoint without it leaves r̄ to the first batch)."""
        if self.on and state.get("reward_center") is not None:
            self.value = float(state["reward_center"])


class CenteredRewards(Transform):
    """A replay buffer's transform: every sample's rewards under ``key`` centred by ``center``
    (``RewardCenter.center``) as it is drawn; stored as collected."""

    def __init__(self, center: RewardCenter, key: Any = ("next", "reward")) -> None:
        super().__init__()
        self.center, self.key = center, key

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        return self.center.center(tensordict, self.key)

    def _inv_call(self, tensordict: TensorDictBase) -> TensorDictBase:
        return tensordict


def anneal(cfg: BatchSchedule, optimizer: torch.optim.Optimizer, frames: int) -> None:
    """The learning rate, ``lr`` → ``lr_end`` linearly in env steps."""
    progress = min(1.0, frames / cfg.total_frames)
    for group in optimizer.param_groups:
        group["lr"] = cfg.lr + (cfg.lr_end - cfg.lr) * progress


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


# -- running the parts ------------------------------------------------------------------------------


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
        last_end: dict[int, int] = {}
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


@contextlib.contextmanager
def policy_view(loss: LossModule, cfg: OffPolicyConfig) -> Iterator[None]:
    """Inside, the loss's value network holds the parameters of ``cfg.policy_network``: the
    target network's (swapped in, and back on exit) or its own."""
    if cfg.policy_network == "target":
        with loss.target_value_network_params.to_module(loss.value_network):
            yield
    else:
        yield


def all_states(qnet: nn.Module, env: Any) -> TensorDictBase:
    """``qnet`` (a Q-value actor) on the observation of every state, greedy."""
    with torch.no_grad():
        # an env that observes more than the state (the fleet's rows) brings its own table
        obs = getattr(env, "observation_table", None)
        obs = env.dynamics.obs if obs is None else obs
        return qnet(TensorDict({"observation": obs}, batch_size=[obs.shape[0]], device=obs.device))


def greedy_table(qnet: nn.Module, env: Any) -> torch.Tensor:
    """The greedy action of the Q-network in every state ([S], ties → comm)."""
    return all_states(qnet, env)["action"].reshape(-1).long().cpu()


def action_values(qnet: nn.Module, env: Any) -> torch.Tensor:
    """The Q-network's action values in every state ([S, A]: comm then radar; G levels)."""
    values = all_states(qnet, env)["action_value"]
    return values.reshape(-1, values.shape[-1]).float().cpu()
