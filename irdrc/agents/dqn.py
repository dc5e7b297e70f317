"""DQN from TorchRL parts: builders, and the one training loop every recipe and sweep calls.

Components are built in a fixed order (model → exploration → buffer → loss → target updater →
optimiser → collector), then ``train`` runs: collect, extend, anneal ε and β, update, evaluate the
greedy network *exactly* on all states on a schedule.
"""

from __future__ import annotations

import copy
import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import TensorDictSequential
from tensordict.utils import expand_as_right
from torch import nn
from torchrl.collectors import Collector
from torchrl.data import Composite, LazyTensorStorage, TensorDictReplayBuffer
from torchrl.data.replay_buffers.samplers import RandomSampler
from torchrl.envs.utils import ExplorationType, exploration_type
from torchrl.modules import (
    MLP,
    DistributionalQValueActor,
    EGreedyModule,
    MultiAgentMLP,
    QValueActor,
)
from torchrl.objectives import DistributionalDQNLoss, DQNLoss, HardUpdate, SoftUpdate

from irdrc.agents.base import Hooks, RunRecord, make_scorers, progress_record, scenario_list
from irdrc.agents.replay import make_prioritized_sampler
from irdrc.agents.select import Snapshots, choose_final
from irdrc.core.env import DFRCEnv
from irdrc.core.params import (
    Params,
    check_bool,
    check_choice,
    check_number,
    reject_unknown_keys,
    to_plain,
)
from irdrc.core.solve import ExactScorer

NAME = "dqn"
DEFAULT_EVAL_EVERY_FRAMES = 1_000
"""Exact evaluation period when the caller gives none, env steps."""

ENCODINGS = ("scale", "onehot")
ACTIVATIONS = {"relu": nn.ReLU, "tanh": nn.Tanh, "elu": nn.ELU, "gelu": nn.GELU, "silu": nn.SiLU}


@dataclass(frozen=True)
class NetworkConfig:
    """Q-network shape (config group ``network``): hidden layer sizes, activation, and how
    observations enter the network.

    ``encoding``: ``scale`` divides each observation entry by its largest value (one input per
    entry, in [0, 1]); ``onehot`` gives each level of each entry its own input (an entry with
    levels 0..n becomes n + 1 inputs), so no level's value is extrapolated from the others.
    """

    hidden: tuple[int, ...] = (64, 64)
    activation: str = "relu"
    encoding: str = "scale"

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
        check_choice("network.encoding", self.encoding, ENCODINGS)
        if self.activation not in ACTIVATIONS:
            raise ValueError(
                f"network.activation={self.activation!r} must be one of {', '.join(ACTIVATIONS)}"
            )

    @classmethod
    def from_dict(cls, data: Any) -> NetworkConfig:
        """From a mapping with ``hidden`` and ``activation`` (``name`` is ignored)."""
        data = {k: v for k, v in dict(to_plain(data)).items() if k != "name"}
        reject_unknown_keys("network.", data, {"hidden", "activation", "encoding"})
        return cls(**data)


@dataclass(frozen=True)
class DQNConfig:
    """Hyperparameters of DQN (config group ``algo``); every key names its unit.

    Attributes:
        num_envs: envs stepped together by the collector (one batched ``DFRCEnv``).
        frames_per_batch: env steps per collected batch (a multiple of ``num_envs``).
        total_frames: env steps of the whole run.
        init_random_frames: env steps with uniformly random actions before learning starts.
        buffer_size: replay capacity, in transitions.
        batch_size: transitions per gradient update …
        batch_size_end: … 0 (default): constant; > 0: the batch grows (or shrinks) linearly in
            env steps from ``batch_size`` to this over ``total_frames`` (larger late batches: less
            gradient noise once the learning rate has annealed).
        updates_per_batch: gradient updates after each collected batch.
        lr: Adam learning rate at the start …
        lr_end: … annealed linearly to this over ``total_frames`` (equal to ``lr``: constant).
        max_grad_norm: gradient clipping (0 = off).
        gamma: discount γ.
        loss_function: ``l2`` (default; ``smooth_l1`` clips the rare −r3 penalty), ``l1``,
            ``smooth_l1``.
        double_dqn: use the online network to pick the next action (van Hasselt et al.).
        eps_start, eps_end, eps_anneal_frames: ε-greedy, annealed linearly over env steps.
        eps_duration_max: 1 (ε-greedy) or the longest hold of a random action (εz-greedy: each
            exploration holds its action for n ≤ this steps, P(n) ∝ n^−2).
        target_update: ``soft`` (Polyak, rate ``tau`` per update) or ``hard`` (copy every
            ``target_update_every_updates`` updates).
        average_tau: 0, or the rate of a Polyak average of the online network (updated after every
            gradient update) whose greedy actions are the evaluated and the final policy; acting
            stays with the online network.
        reward_centering: 0 (off), or (default 0.001) the rate per env step of an exponential
            average r̄ of the collected rewards, subtracted from every sampled reward before the loss (reward
            centering, Naik et al. 2024). Without terminal states this shifts every Q-value by
            r̄/(1 − γ) and leaves the greedy policy unchanged, but the network no longer has to
            grow its outputs to that offset — which, with γ = 0.99 and a soft target, takes far
            longer than a run — and fits only the differences between states and actions.
        reward_scale: a fixed factor on every sampled (centred) reward before the loss (1: off;
            e.g. 0.02 = 1/r3 puts the paper's −50 penalty at −1). A positive factor scales every
            Q-value and leaves the greedy policy unchanged; the learned values are in scaled units.
        popart: 0 (off), or the rate β of PopArt (van Hasselt et al. 2016: adaptive target
            normalisation that preserves outputs). The network's last layer predicts normalised
            values n, and Q = σ·n + μ, where μ and σ are running estimates of the mean and standard
            deviation of the TD targets (a plain average over the first 1/β updates, then an
            exponential average at rate β per update); each update first moves μ, σ and rescales
            the last layer of the online and target networks so that every Q-value is unchanged,
            then takes its gradient step on the loss divided by σ² (the loss in normalised units).
        select_every_frames: 0 (off), or the period, in env steps, of snapshots of the greedy
            policy taken from ``select_after_frames`` on; at the end the final policy is the
            snapshot whose mean reward, measured on the simulator by ``select_envs`` chains of
            ``select_burn_in`` + ``select_steps`` steps with common random numbers, beats the last
            network's by more than ``select_z`` standard errors of the paired difference (the
            last network's when none does; ``irdrc.agents.select``). The measurement steps are
            counted in the run's env steps.
        ensemble: 1 (one Q-network), or the number K of independently initialised Q-networks
            (heads; TorchRL's ``MultiAgentMLP`` with one unshared MLP per head) trained on the
            same replay samples, each against its own double-DQN target; acting, evaluation and
            the final policy are greedy in their mean Q. Averaging heads averages out the
            extrapolation errors in which they differ (README, "DQN across seeds").
        distributional: learn the distribution of the (centred) discounted return on a fixed
            support of ``atoms`` points (C51, Bellemare et al. 2017: TorchRL's
            ``DistributionalQValueActor`` and ``DistributionalDQNLoss``, a cross-entropy to the
            projected double-DQN target, so ``loss_function`` is unused) instead of its mean; the
            greedy action maximises the distribution's mean. The support spans
            ±``support_span`` × the largest |reward| of the env's reward table.
        atoms, support_span: the distributional support (see ``distributional``).
        ensemble_mask: with ``ensemble`` > 1, the probability that a sampled transition trains a
            given head (bootstrapped DQN, Osband et al. 2016); 1 (default): every head sees every
            sample.
        prioritized: proportional prioritised replay with exponent ``alpha`` and importance
            exponent annealed from ``beta_start`` to 1 over ``total_frames``.
        sampler: ``auto`` (TorchRL's when its extension loads, else ours), ``torchrl``, ``torch``.
        network: the Q-network's shape (config group ``network``).
    """

    num_envs: int = 8
    frames_per_batch: int = 32
    total_frames: int = 20_000
    init_random_frames: int = 512
    buffer_size: int = 20_000
    batch_size: int = 256
    batch_size_end: int = 0
    updates_per_batch: int = 4
    lr: float = 5e-4
    lr_end: float = 1e-5
    max_grad_norm: float = 10.0
    gamma: float = 0.99
    loss_function: str = "l2"
    double_dqn: bool = True
    eps_start: float = 1.0
    eps_end: float = 0.05
    eps_anneal_frames: int = 4_000
    eps_duration_max: int = 1
    target_update: str = "soft"
    tau: float = 0.01
    target_update_every_updates: int = 500
    average_tau: float = 0.0
    reward_centering: float = 0.001
    reward_scale: float = 1.0
    popart: float = 0.0
    select_every_frames: int = 0
    select_after_frames: int = 10_000
    select_envs: int = 64
    select_steps: int = 1_000
    select_burn_in: int = 200
    select_z: float = 2.58
    ensemble: int = 1
    ensemble_mask: float = 1.0
    distributional: bool = False
    atoms: int = 51
    support_span: float = 6.0
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
        num("batch_size_end", 0, 10**7, integer=True)
        num("total_frames", 1, 10**12, integer=True)
        num("buffer_size", 1, 10**9, integer=True)
        num("updates_per_batch", 1, 10**6, integer=True)  # 0 would never learn
        for key in ("init_random_frames", "eps_anneal_frames"):
            num(key, 0, 10**12, integer=True)
        num("target_update_every_updates", 1, 10**12, integer=True)
        num("eps_duration_max", 1, 10**6, integer=True)
        num("lr", 0, 1, open_lo=True, open_hi=True)
        num("lr_end", 0, 1, open_hi=True)
        num("max_grad_norm", 0)
        num("gamma", 0, 1, open_hi=True)
        for key in ("eps_start", "eps_end", "tau", "beta_start", "average_tau"):
            num(key, 0, 1)
        num("reward_centering", 0, 1, open_hi=True)
        num("reward_scale", 0, 1e6, open_lo=True)
        num("popart", 0, 1, open_hi=True)
        num("select_every_frames", 0, 10**12, integer=True)
        num("select_after_frames", 0, 10**12, integer=True)
        num("select_envs", 2, 10**7, integer=True)
        num("select_steps", 1, 10**9, integer=True)
        num("select_burn_in", 0, 10**9, integer=True)
        num("select_z", 0, 100)
        num("alpha", 0, 10)
        num("ensemble", 1, 1024, integer=True)
        num("ensemble_mask", 0, 1, open_lo=True)
        num("atoms", 2, 100_000, integer=True)
        num("support_span", 0, 1e6, open_lo=True)
        check_bool("algo.distributional", self.distributional)
        if self.distributional and self.ensemble > 1:
            raise ValueError(
                f"algo.distributional=true with algo.ensemble={self.ensemble}: the distributional "
                "loss trains one network (set algo.ensemble=1)"
            )
        if self.distributional and self.reward_scale != 1:
            raise ValueError(
                f"algo.distributional=true with algo.reward_scale={self.reward_scale}: the "
                "distributional support is already scaled to the reward table (set "
                "algo.reward_scale=1)"
            )
        if self.popart:
            for key, off in (
                ("distributional", False),
                ("ensemble", 1),
                ("average_tau", 0.0),
                ("reward_scale", 1.0),
            ):
                if getattr(self, key) != off:
                    raise ValueError(
                        f"algo.popart={self.popart} with algo.{key}={getattr(self, key)!r}: PopArt "
                        f"normalises one expected-value network's outputs (set algo.{key}={off})"
                    )
        if self.distributional and not self.double_dqn:
            raise ValueError(
                "algo.distributional=true needs algo.double_dqn=true (TorchRL's distributional "
                "loss always picks the next action with the online network)"
            )
        check_choice("algo.loss_function", self.loss_function, ("l2", "l1", "smooth_l1"))
        check_choice("algo.target_update", self.target_update, ("soft", "hard"))
        check_choice("algo.sampler", self.sampler, ("auto", "torchrl", "torch"))
        check_bool("algo.double_dqn", self.double_dqn)
        check_bool("algo.prioritized", self.prioritized)
        if not isinstance(self.network, NetworkConfig):
            raise ValueError(f"network={self.network!r} must be a NetworkConfig")
        # Combinations, named by their keys.
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
        if self.buffer_size < self.batch_size_end:
            raise ValueError(
                f"algo.buffer_size={self.buffer_size} must be >= "
                f"algo.batch_size_end={self.batch_size_end}"
            )
        if self.select_every_frames and self.select_after_frames >= self.total_frames:
            raise ValueError(
                f"algo.select_after_frames={self.select_after_frames} must be < "
                f"algo.total_frames={self.total_frames} when algo.select_every_frames > 0 (there "
                "would be nothing to choose from)"
            )
        if self.frames_per_batch > self.total_frames:
            raise ValueError(
                f"algo.frames_per_batch={self.frames_per_batch} must be <= "
                f"algo.total_frames={self.total_frames}"
            )

    @classmethod
    def from_dict(cls, data: Any, network: Any = None) -> DQNConfig:
        """From a mapping (the ``algo`` config node) and optionally the ``network`` node; unknown
        keys are rejected."""
        data = dict(to_plain(data))
        reject_unknown_keys("algo.", data, {f.name for f in fields(cls) if f.name != "network"})
        if network is not None:
            data["network"] = NetworkConfig.from_dict(network)
        return cls(**data)

    @classmethod
    def from_node(cls, cfg: Any) -> DQNConfig:
        """From a recipe's config (its ``algo`` and ``network`` groups)."""
        return cls.from_dict(cfg["algo"], cfg["network"])

    def env_steps(self, horizon: int) -> int:
        """Env steps of the whole run."""
        return self.total_frames


Config = DQNConfig
"""This learner's config class (the interface of ``irdrc.agents.base``)."""


class _Scale(nn.Module):
    """Divides observations by their upper bounds, so every input lies in [0, 1]."""

    def __init__(self, high: torch.Tensor) -> None:
        super().__init__()
        self.register_buffer("inv", 1.0 / high.clamp(min=1.0))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x * self.inv


class _OneHot(nn.Module):
    """Each entry of an integer-valued observation as a one-hot vector over its levels 0..high."""

    def __init__(self, high: torch.Tensor) -> None:
        super().__init__()
        levels = high.round().long() + 1
        self.register_buffer("offset", torch.cumsum(levels, 0) - levels)
        self.size = int(levels.sum())

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        index = x.round().long() + self.offset
        out = torch.zeros(*x.shape[:-1], self.size, dtype=x.dtype, device=x.device)
        return out.scatter_(-1, index, 1.0)


def _encoder(env: DFRCEnv, net: NetworkConfig) -> tuple[nn.Module, int]:
    """The observation encoding chosen by ``net.encoding``, on the env's device, and its width."""
    obs_spec = env.observation_spec["observation"]
    high = obs_spec.space.high.reshape(-1, obs_spec.shape[-1])[0].to(torch.float32)
    if net.encoding == "onehot":
        encode = _OneHot(high)
        return encode.to(env.device), encode.size
    return _Scale(high).to(env.device), obs_spec.shape[-1]


def make_mlp(env: DFRCEnv, net: NetworkConfig, out_features: int) -> nn.Sequential:
    """The network body sized from the env's observation spec: observation (encoded by
    ``net.encoding``) in, ``out_features`` out."""
    encode, size = _encoder(env, net)
    mlp = MLP(
        in_features=size,
        out_features=out_features,
        num_cells=list(net.hidden),
        activation_class=ACTIVATIONS[net.activation],
        device=env.device,
    )
    return nn.Sequential(encode, mlp)


class PopArt(nn.Module):
    """The output layer of PopArt (``DQNConfig.popart``): Q = σ·n + μ for the normalised values n
    of the layer before it. μ, ν (the second moment) and σ = √(ν − μ²) are buffers, so the target
    network and checkpoints carry them; ``count`` is the number of statistics updates so far."""

    def __init__(self, device: torch.device | str | None = None) -> None:
        super().__init__()
        for name, value in (("mu", 0.0), ("nu", 1.0), ("sigma", 1.0), ("count", 0.0)):
            self.register_buffer(name, torch.tensor(value, dtype=torch.float32, device=device))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x * self.sigma + self.mu


POPART_SIGMA_MIN = 1e-4
"""σ's floor: targets that are (nearly) constant would otherwise divide the last layer by zero."""


def make_qnet(env: DFRCEnv, net: NetworkConfig, popart: bool = False) -> QValueActor:
    """Q-value actor sized from the env's specs: observation (encoded by ``net.encoding``) in, one
    Q-value per action out (through a ``PopArt`` output layer when ``popart``)."""
    module = make_mlp(env, net, env.action_spec_unbatched.space.n)
    if popart:
        module = nn.Sequential(module, PopArt(env.device))
    return QValueActor(module=module, in_keys=["observation"], spec=env.action_spec_unbatched)


def _popart_keys(qnet: nn.Module) -> tuple[tuple[str, ...], tuple[str, ...]]:
    """The parameter-tree paths (as in a loss's ``value_network_params``) of ``qnet``'s last
    ``nn.Linear`` (the normalised values) and of its ``PopArt`` layer."""
    linears = [name for name, m in qnet.named_modules() if isinstance(m, nn.Linear)]
    layers = [name for name, m in qnet.named_modules() if isinstance(m, PopArt)]
    if not linears or len(layers) != 1:
        raise ValueError("the network has no PopArt output layer (algo.popart=0 when it was built)")
    return tuple(linears[-1].split(".")), tuple(layers[0].split("."))


def td_targets(loss: DQNLoss, sample: TensorDictBase, gamma: float) -> torch.Tensor:
    """The TD targets r + γ·(1 − terminated)·Q_target(s′, a′) that ``loss`` regresses on, for a
    replay ``sample`` [B] (a′ greedy in the online network with double DQN, else in the target
    network); no gradient."""
    with torch.no_grad():
        nxt = sample["next"].select("observation")
        with loss.target_value_network_params.to_module(loss.value_network):
            target_q = loss.value_network(nxt.clone(False))["action_value"]
        if loss.double_dqn:
            with loss.value_network_params.data.to_module(loss.value_network):
                action = loss.value_network(nxt.clone(False))["action_value"].argmax(-1)
        else:
            action = target_q.argmax(-1)
        value = target_q.gather(-1, action.unsqueeze(-1)).squeeze(-1)
        reward = sample["next", "reward"].reshape(value.shape)
        done = sample["next", "terminated"].reshape(value.shape).to(value.dtype)
        return reward + gamma * (1.0 - done) * value


def popart_update(
    loss: DQNLoss, targets: torch.Tensor, rate: float, weights: torch.Tensor | None = None
) -> float:
    """Fold a batch of TD ``targets`` into PopArt's μ, ν, σ (step max(rate, 1/t) at the t-th
    update; a mean weighted by ``weights``, the replay's importance weights, so that prioritised
    sampling does not bias them) and rescale the last layer of the online and the target network
    so that their outputs are unchanged (ART); returns the new σ."""
    linear, layer = _popart_keys(loss.value_network)
    online = loss.value_network_params.data
    with torch.no_grad():
        # Both networks hold the same statistics: read them from the online network.
        mu, nu = float(online[(*layer, "mu")]), float(online[(*layer, "nu")])
        count = float(online[(*layer, "count")])
        targets = targets.double().reshape(-1)
        w = torch.ones_like(targets) if weights is None else weights.double().reshape(-1)
        w = w / w.sum()
        step = max(rate, 1.0 / (count + 1.0))
        mu_new = (1.0 - step) * mu + step * float((w * targets).sum())
        nu_new = (1.0 - step) * nu + step * float((w * targets.pow(2)).sum())
        sigma_new = math.sqrt(max(nu_new - mu_new**2, POPART_SIGMA_MIN**2))
        for params in (online, loss.target_value_network_params):
            sigma, old_mu = float(params[(*layer, "sigma")]), float(params[(*layer, "mu")])
            params[(*linear, "weight")].mul_(sigma / sigma_new)
            params[(*linear, "bias")].mul_(sigma).add_(old_mu - mu_new).div_(sigma_new)
            for key, value in (("mu", mu_new), ("nu", nu_new), ("sigma", sigma_new)):
                params[(*layer, key)].fill_(value)
            params[(*layer, "count")].fill_(count + 1.0)
    return sigma_new


class _Heads(nn.Module):
    """K unshared MLPs (TorchRL's ``MultiAgentMLP``, one "agent" per head) behind the observation
    encoding. ``forward`` takes observations [..., K, n] (head k reads row k) and returns
    [..., K, actions]."""

    def __init__(self, env: DFRCEnv, net: NetworkConfig, heads: int) -> None:
        super().__init__()
        self.encode, size = _encoder(env, net)
        self.heads = heads
        self.mlp = MultiAgentMLP(
            n_agent_inputs=size,
            n_agent_outputs=env.action_spec_unbatched.space.n,
            n_agents=heads,
            centralized=False,
            share_params=False,
            num_cells=list(net.hidden),
            activation_class=ACTIVATIONS[net.activation],
            device=env.device,
        )

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.mlp(self.encode(x))


class _MeanOfHeads(nn.Module):
    """Observations [..., n] to the heads' mean Q [..., actions] (the acting and greedy values)."""

    def __init__(self, heads: _Heads) -> None:
        super().__init__()
        self.body = heads

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        shape = (*x.shape[:-1], self.body.heads, x.shape[-1])
        return self.body(x.unsqueeze(-2).expand(shape)).mean(-2)


class _Atoms(nn.Module):
    """[..., atoms · actions] to [..., atoms, actions] (the layout of TorchRL's distributional
    actor)."""

    def __init__(self, atoms: int, actions: int) -> None:
        super().__init__()
        self.shape = (atoms, actions)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x.unflatten(-1, self.shape)


def make_distributional_qnet(
    env: DFRCEnv, net: NetworkConfig, atoms: int, span: float
) -> DistributionalQValueActor:
    """C51's actor: log-probabilities [..., atoms, actions] of the return on ``atoms`` evenly
    spaced points over ±``span`` × the largest |reward| of the env's reward table; the action
    maximises the mean."""
    dyn = env.dynamics
    r_max = max(float(dyn.reward.abs().max()), float(dyn.miss_reward.abs().max()), 1e-6)
    support = torch.linspace(-span * r_max, span * r_max, atoms, device=env.device)
    n = env.action_spec_unbatched.space.n
    module = nn.Sequential(make_mlp(env, net, atoms * n), _Atoms(atoms, n))
    return DistributionalQValueActor(
        module=module, support=support, in_keys=["observation"], spec=env.action_spec_unbatched
    )


def make_qnets(
    env: DFRCEnv, net: NetworkConfig, heads: int, popart: bool = False
) -> tuple[QValueActor, QValueActor]:
    """The acting network and the network the loss trains, sharing parameters.

    With ``heads`` = 1 both are ``make_qnet``'s actor (with a ``PopArt`` output layer when
    ``popart``). With ``heads`` = K > 1 the loss's actor maps
    observations [B, K, n] to per-head values [B, K, actions] (its TD targets per head, each head
    with its own target copy), and the acting actor maps [..., n] to the heads' mean [..., actions]
    and acts greedily in it.
    """
    if heads == 1:
        qnet = make_qnet(env, net, popart)
        return qnet, qnet
    if popart:
        raise ValueError("PopArt normalises one network's outputs (algo.ensemble=1)")
    body = _Heads(env, net, heads)
    spec = env.action_spec_unbatched
    per_head = QValueActor(module=body, in_keys=["observation"], spec=spec)
    mean = QValueActor(module=_MeanOfHeads(body), in_keys=["observation"], spec=spec)
    return mean, per_head


class EZGreedyModule(EGreedyModule):
    """Temporally extended ε-greedy (εz-greedy, Dabney et al. 2021): with probability ε an env not
    already exploring starts an exploration, a uniformly random action held for n steps, n drawn
    from a zeta distribution (P(n) ∝ n^−2) truncated at ``max_duration``; ``max_duration`` 1 is
    TorchRL's ε-greedy. Held actions reach states that one-step dithering rarely does (here: long
    runs of one mode fill or empty the queue)."""

    def __init__(self, *args: Any, max_duration: int = 1, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.max_duration = int(max_duration)
        n = torch.arange(1, self.max_duration + 1, dtype=torch.float64)
        self.register_buffer("_duration_p", (n**-2.0 / (n**-2.0).sum()).float())
        self._remaining: torch.Tensor | None = None
        self._held: torch.Tensor | None = None

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        if self.max_duration <= 1 or exploration_type() not in (ExplorationType.RANDOM, None):
            return super().forward(tensordict)
        action = tensordict.get(self.action_key)
        shape = tensordict.shape
        if self._remaining is None or self._remaining.shape != shape:
            self._remaining = torch.zeros(shape, dtype=torch.long, device=action.device)
            self._held = torch.zeros_like(action)
        start = (self._remaining == 0) & (torch.rand(shape, device=action.device) < self.eps)
        if bool(start.any()):
            spec = self.spec[self.action_key] if isinstance(self.spec, Composite) else self.spec
            spec = spec.expand(action.shape) if spec.shape != action.shape else spec
            draw = torch.multinomial(self._duration_p, int(start.numel()), replacement=True) + 1
            self._remaining = torch.where(
                start, draw.view(shape).to(action.device), self._remaining
            )
            self._held = torch.where(expand_as_right(start, action), spec.rand(), self._held)
        active = self._remaining > 0
        action = torch.where(expand_as_right(active, action), self._held, action)
        self._remaining = (self._remaining - 1).clamp(min=0)
        tensordict.set(self.action_key, action)
        return tensordict


def make_exploration(env: DFRCEnv, cfg: DQNConfig) -> EGreedyModule:
    """ε-greedy, linear from ``eps_start`` to ``eps_end`` over ``eps_anneal_frames`` env steps;
    temporally extended (``EZGreedyModule``) when ``eps_duration_max`` > 1."""
    return EZGreedyModule(
        spec=env.action_spec_unbatched,
        eps_init=cfg.eps_start,
        eps_end=cfg.eps_end,
        annealing_num_steps=max(1, cfg.eps_anneal_frames),
        max_duration=cfg.eps_duration_max,
    )


class RewardCenter:
    """The running average r̄ of collected rewards that reward centering subtracts (see
    ``DQNConfig.reward_centering``): the first batch's mean, then an exponential average at
    ``rate`` per env step (so a batch of n steps moves it by 1 − (1 − rate)^n); sampled rewards
    are then multiplied by ``scale`` (``DQNConfig.reward_scale``)."""

    def __init__(self, rate: float, value: float | None = None, scale: float = 1.0) -> None:
        self.rate = float(rate)
        self.value = value
        self.scale = float(scale)

    @property
    def on(self) -> bool:
        """Whether centering is enabled (``rate`` > 0)."""
        return self.rate > 0

    def update(self, reward: torch.Tensor) -> None:
        """Fold in one collected batch of rewards (any shape)."""
        if not self.on:
            return
        mean = float(reward.double().mean())
        if self.value is None:
            self.value = mean
        else:
            self.value += (1.0 - (1.0 - self.rate) ** reward.numel()) * (mean - self.value)

    def center(self, sample: TensorDictBase) -> TensorDictBase:
        """``sample`` with r̄ subtracted from its ``("next", "reward")`` and the result multiplied
        by ``scale`` (unchanged when both are off)."""
        if self.on and self.value is not None:
            sample.set(("next", "reward"), sample["next", "reward"] - self.value)
        if self.scale != 1.0:
            sample.set(("next", "reward"), sample["next", "reward"] * self.scale)
        return sample


def make_buffer(cfg: DQNConfig):
    """Replay buffer: prioritised (see ``irdrc.agents.replay``) or uniform. Returns (buffer, sampler)."""
    if cfg.prioritized:
        sampler = make_prioritized_sampler(
            cfg.buffer_size, cfg.alpha, cfg.beta_start, prefer=cfg.sampler
        )
    else:
        sampler = RandomSampler()
    # A growing batch is passed to every sample() (TorchRL warns when both name a size).
    rb = TensorDictReplayBuffer(
        storage=LazyTensorStorage(cfg.buffer_size),
        sampler=sampler,
        batch_size=None if cfg.batch_size_end else cfg.batch_size,
    )
    return rb, sampler


def batch_size_at(cfg: DQNConfig, frames: int) -> int:
    """Transitions per update after ``frames`` env steps: ``batch_size``, or with
    ``batch_size_end`` > 0 linear from ``batch_size`` to it over ``total_frames``."""
    if not cfg.batch_size_end:
        return cfg.batch_size
    progress = min(1.0, frames / cfg.total_frames)
    return round(cfg.batch_size + (cfg.batch_size_end - cfg.batch_size) * progress)


def make_loss(qnet: QValueActor, env: DFRCEnv, cfg: DQNConfig) -> DQNLoss | DistributionalDQNLoss:
    """DQNLoss with a target network, the chosen distance and γ (``DistributionalDQNLoss`` with
    ``cfg.distributional``)."""
    if cfg.distributional:
        return DistributionalDQNLoss(qnet, gamma=cfg.gamma, delay_value=True)
    loss = DQNLoss(
        qnet,
        loss_function=cfg.loss_function,
        delay_value=True,
        double_dqn=cfg.double_dqn,
        action_space=env.action_spec_unbatched,
    )
    loss.make_value_estimator(gamma=cfg.gamma)
    return loss


def make_target_updater(loss: DQNLoss, cfg: DQNConfig):
    """Soft (Polyak, ``tau``) or hard (every ``target_update_every_updates``) target updates."""
    if cfg.target_update == "soft":
        return SoftUpdate(loss, tau=cfg.tau)
    return HardUpdate(loss, value_network_update_interval=cfg.target_update_every_updates)


def _all_states(qnet: QValueActor, env: DFRCEnv) -> TensorDictBase:
    with torch.no_grad():
        obs = env.dynamics.obs
        return qnet(TensorDict({"observation": obs}, batch_size=[obs.shape[0]], device=obs.device))


def greedy_table(qnet: QValueActor, env: DFRCEnv) -> torch.Tensor:
    """The greedy action of the Q-network in every state ([S], ties → comm)."""
    return _all_states(qnet, env)["action"].reshape(-1).long().cpu()


def action_values(qnet: QValueActor, env: DFRCEnv) -> torch.Tensor:
    """The Q-network's action values in every state ([S, 2], comm then radar); a distributional
    network's are its distributions' means."""
    values = _all_states(qnet, env)["action_value"]
    if isinstance(qnet, DistributionalQValueActor):
        values = (values.exp() * qnet.support.to(values)[:, None]).sum(-2)
    return values.reshape(-1, 2).float().cpu()


def train(
    params: Params | Sequence[Params],
    cfg: DQNConfig | None = None,
    *,
    num_learners: int = 1,
    seed: int = 0,
    device: str = "cpu",
    scorers: ExactScorer | Sequence[ExactScorer] | None = None,
    eval_every_frames: int = DEFAULT_EVAL_EVERY_FRAMES,
    hooks: Hooks | None = None,
    resume: dict[str, Any] | None = None,
) -> RunRecord:
    """Train DQN on the batched env and evaluate the greedy network exactly on a schedule.

    The interface of ``irdrc.agents.base``: one scenario and one network per run (``num_learners``
    1); ``hooks.on_batch`` gets ``env_steps``, ``episodes``, ``epsilon``, ``loss``, ``beta``,
    ``buffer`` after each collected batch; ``resume`` is an earlier run's ``RunRecord.state``; the
    returned record's ``state`` is the checkpoint (networks, optimiser, counters).
    """
    cfg = cfg or DQNConfig()
    hooks = hooks or Hooks()
    scenarios = scenario_list(params)
    if len(scenarios) != 1 or num_learners != 1:
        raise ValueError("DQN trains one network on one scenario per run (num_learners=1)")
    if eval_every_frames < 1:
        raise ValueError(f"eval.every_frames={eval_every_frames!r} must be >= 1")
    (params,) = scenarios
    (scorer,) = make_scorers(scenarios, scorers)
    torch.manual_seed(seed)
    env = DFRCEnv(params, batch_size=[cfg.num_envs], device=device, seed=seed)

    # Components in a fixed order: model → exploration → buffer → loss → target → optimiser.
    if cfg.distributional:
        qnet = trained = make_distributional_qnet(env, cfg.network, cfg.atoms, cfg.support_span)
    else:
        qnet, trained = make_qnets(env, cfg.network, cfg.ensemble, popart=cfg.popart > 0)
    exploration = make_exploration(env, cfg)
    policy = TensorDictSequential(qnet, exploration)
    rb, sampler = make_buffer(cfg)
    loss = make_loss(trained, env, cfg)
    target = make_target_updater(loss, cfg)
    optimizer = torch.optim.Adam(loss.parameters(), lr=cfg.lr)
    average = _make_average(qnet, cfg)
    greedy_net = average if average is not None else qnet
    record = RunRecord(method=cfg.name, greedy=torch.zeros(1, env.num_states, dtype=torch.int64))
    record.info["replay_sampler"] = type(sampler).__name__ + (
        " (prioritised)" if cfg.prioritized else " (uniform)"
    )
    hooks.start(dict(record.info))

    center = RewardCenter(cfg.reward_centering, scale=cfg.reward_scale)
    snapshots = Snapshots(cfg.select_every_frames, cfg.select_after_frames)
    start_frames = _restore(resume, loss, optimizer, exploration, record, average, center)
    snapshots.load(resume.get("snapshots") if resume is not None else None)
    remaining = cfg.total_frames - start_frames
    if remaining <= 0:
        raise ValueError(
            f"nothing to resume: the checkpoint is at {start_frames} ≥ algo.total_frames"
        )
    # A resumed run has no buffer: it refills with its own policy and learns from batch_size on.
    learn_from = (
        cfg.batch_size if resume is not None else max(cfg.batch_size, cfg.init_random_frames)
    )
    collector = Collector(
        env,
        policy,
        frames_per_batch=cfg.frames_per_batch,
        total_frames=remaining,
        init_random_frames=0 if resume is not None else cfg.init_random_frames,
        device=device,
        auto_register_policy_transforms=False,
    )
    collector.set_seed(seed + start_frames)

    t0 = time.perf_counter() - (float(resume["wall_seconds"]) if resume is not None else 0.0)
    frames = start_frames
    next_eval = (frames // eval_every_frames + 1) * eval_every_frames
    optimal = scorer.optimal_metrics.avg_reward

    def evaluate_now() -> None:
        m = scorer.metrics(greedy_table(greedy_net, env))
        wall = time.perf_counter() - t0
        entry = progress_record(
            0, frames, len(record.episode_rewards), wall, record.updates, m, optimal
        )
        record.history.append(entry)
        hooks.eval([entry])
        if hooks.on_values is not None:
            hooks.values(frames, action_values(greedy_net, env)[None])

    if resume is None:
        evaluate_now()
    last_loss = math.nan
    ep_total = torch.zeros(cfg.num_envs, dtype=torch.float64)
    for data in collector:
        _track_episodes(data, ep_total, frames, record.episode_rewards)
        data = data.reshape(-1)
        rb.extend(data)
        center.update(data["next", "reward"])
        frames += data.numel()
        exploration.step(data.numel())
        _anneal(cfg, optimizer, sampler, frames)
        batch = batch_size_at(cfg, frames)
        if len(rb) >= max(learn_from, batch):
            last_loss = _learn(cfg, rb, loss, optimizer, target, (average, qnet), center, batch)
            record.updates += cfg.updates_per_batch
        if snapshots.due(frames - data.numel(), frames) and frames < cfg.total_frames:
            snapshots.take(frames, greedy_table(greedy_net, env), action_values(greedy_net, env))
        hooks.batch(
            {
                "env_steps": frames,
                "episodes": len(record.episode_rewards),
                "epsilon": float(exploration.eps),
                "loss": last_loss,
                "beta": getattr(sampler, "beta", math.nan),
                "buffer": len(rb),
            }
        )
        stop = hooks.stop_requested()
        if frames >= next_eval or frames >= cfg.total_frames or stop:
            evaluate_now()
            next_eval = (frames // eval_every_frames + 1) * eval_every_frames
        if hooks.checkpoint_due(frames - data.numel(), frames) and frames < cfg.total_frames:
            wall = time.perf_counter() - t0
            state = _checkpoint(loss, optimizer, record, frames, wall, average, center)
            hooks.on_checkpoint({**state, **_snapshot_state(snapshots)})
        if stop:
            record.interrupted = True
            break
    collector.shutdown()
    record.env_steps = frames
    record.episodes = len(record.episode_rewards)
    record.greedy = greedy_table(greedy_net, env)[None]
    record.q = action_values(greedy_net, env)[None]
    record.state = _checkpoint(loss, optimizer, record, frames, 0.0, average, center)
    record.state.update(_snapshot_state(snapshots))
    if snapshots.on and not record.interrupted:
        _select_final(record, snapshots, params, cfg, seed, scorer, optimal)
    record.wall_seconds = time.perf_counter() - t0
    record.state["wall_seconds"] = record.wall_seconds
    return record


def _snapshot_state(snapshots: Snapshots) -> dict[str, Any]:
    """The snapshots' checkpoint entry (none when selection is off)."""
    return {"snapshots": snapshots.state()} if snapshots.on else {}


def _select_final(
    record: RunRecord,
    snapshots: Snapshots,
    params: Params,
    cfg: DQNConfig,
    seed: int,
    scorer: ExactScorer,
    optimal: float,
) -> None:
    """Replace the record's final greedy table by the one ``choose_final`` picks among the
    snapshots and the last table (measurement steps added to ``env_steps``); the last network's
    exact score stays in ``history``, the chosen table's is ``info["selected_ratio"]``."""
    snapshots.take(record.env_steps, record.greedy[0], record.q[0])
    index, facts = choose_final(
        params,
        snapshots,
        envs=cfg.select_envs,
        steps=cfg.select_steps,
        burn_in=cfg.select_burn_in,
        z=cfg.select_z,
        seed=seed + 104_729,
    )
    record.greedy = snapshots.tables[index].to(record.greedy.device)[None]
    record.q = snapshots.values[index].to(record.q.device)[None]
    snapshots.pop()
    record.info["training_env_steps"] = record.env_steps
    record.env_steps += int(facts["select_env_steps"])
    # Scoring only (never steering): the exact ratio of what was chosen, for benchmarks.
    record.info["selected_ratio"] = float(scorer.metrics(record.greedy[0]).avg_reward / optimal)
    record.info.update(facts)


def _make_average(qnet: QValueActor, cfg: DQNConfig) -> QValueActor | None:
    """A frozen copy of the Q-network to hold its Polyak average, or None when ``average_tau`` is 0."""
    if cfg.average_tau <= 0:
        return None
    average = copy.deepcopy(qnet)
    for p in average.parameters():
        p.requires_grad_(False)
    return average


def _update_average(average: QValueActor | None, qnet: nn.Module, tau: float) -> None:
    """average ← (1 − τ)·average + τ·online, parameter by parameter."""
    if average is None:
        return
    with torch.no_grad():
        for pa, p in zip(average.parameters(), qnet.parameters(), strict=True):
            pa.lerp_(p, tau)


def _checkpoint(
    loss: DQNLoss,
    optimizer: torch.optim.Optimizer,
    record: RunRecord,
    frames: int,
    wall: float,
    average: QValueActor | None = None,
    center: RewardCenter | None = None,
) -> dict:
    """The resumable state at ``frames`` env steps: networks (the averaged one too, when there is
    one), optimiser, counters, history so far, and the reward centre r̄ when centering is on."""
    return {
        **({"average": average.state_dict()} if average is not None else {}),
        **(
            {"reward_center": center.value}
            if center is not None and center.on and center.value is not None
            else {}
        ),
        "loss": loss.state_dict(),
        "optimizer": optimizer.state_dict(),
        "frames": frames,
        "updates": record.updates,
        "wall_seconds": wall,
        "history": list(record.history),
        "episode_rewards": list(record.episode_rewards),
    }


def _restore(
    resume: dict[str, Any] | None,
    loss: DQNLoss,
    optimizer: torch.optim.Optimizer,
    exploration: EGreedyModule,
    record: RunRecord,
    average: QValueActor | None = None,
    center: RewardCenter | None = None,
) -> int:
    """Load a checkpoint into the components and the record; returns its env steps (0 if none)."""
    if resume is None:
        return 0
    loss.load_state_dict(resume["loss"])
    if center is not None and center.on and resume.get("reward_center") is not None:
        center.value = float(resume["reward_center"])
    if average is not None:
        average.load_state_dict(resume["average"])
    optimizer.load_state_dict(resume["optimizer"])
    frames, record.updates = int(resume["frames"]), int(resume["updates"])
    exploration.step(frames)
    record.history = list(resume.get("history", []))
    record.episode_rewards = list(resume.get("episode_rewards", []))
    return frames


def _anneal(cfg: DQNConfig, optimizer: torch.optim.Optimizer, sampler, frames: int) -> None:
    """Learning rate (``lr`` → ``lr_end``) and PER's β (``beta_start`` → 1), linear in env steps."""
    progress = min(1.0, frames / cfg.total_frames)
    for group in optimizer.param_groups:
        group["lr"] = cfg.lr + (cfg.lr_end - cfg.lr) * progress
    if cfg.prioritized:
        sampler.beta = cfg.beta_start + (1.0 - cfg.beta_start) * progress


def _learn(
    cfg: DQNConfig,
    rb,
    loss: DQNLoss,
    optimizer: torch.optim.Optimizer,
    target,
    average: tuple[QValueActor | None, QValueActor] | None = None,
    center: RewardCenter | None = None,
    batch: int | None = None,
) -> float:
    """``updates_per_batch`` gradient updates from replay, of ``batch`` transitions each
    (default ``cfg.batch_size``; each update followed by the target update and, with ``average`` =
    (average, online network), the policy average's; rewards centred by ``center``; with
    ``cfg.popart`` the PopArt statistics are updated and the loss is divided by σ²); returns the
    last loss (in the values' own units)."""
    last = math.nan
    for _ in range(cfg.updates_per_batch):
        sample = rb.sample(batch or cfg.batch_size)
        if center is not None:
            sample = center.center(sample)
        if cfg.ensemble > 1:
            sample = _per_head(sample, cfg)
        scale = 1.0
        if cfg.popart:
            # Statistics and ART first (outputs unchanged), then the loss in normalised units.
            targets = td_targets(loss, sample, cfg.gamma)
            weights = sample.get("priority_weight", None) if cfg.prioritized else None
            sigma = popart_update(loss, targets, cfg.popart, weights)
            scale = 1.0 / sigma**2
        out = loss(sample)
        optimizer.zero_grad(set_to_none=True)
        (out["loss"] * scale).backward()
        if cfg.max_grad_norm > 0:
            nn.utils.clip_grad_norm_(loss.parameters(), cfg.max_grad_norm)
        optimizer.step()
        target.step()
        if average is not None:
            _update_average(*average, cfg.average_tau)
        if cfg.prioritized:
            # DQNLoss writes the squared TD error; proportional PER uses |δ| (heads: their mean);
            # the distributional loss writes its per-sample cross-entropy, used as it is.
            delta = sample["td_error"].detach()
            delta = delta if cfg.distributional else delta.sqrt()
            if cfg.ensemble > 1:
                delta, index = delta.mean(-2), sample["index"][:, 0]
            else:
                index = sample["index"]
            rb.update_priority(index, delta.reshape(-1))
        last = float(out["loss"].detach())
    return last


def _per_head(sample: TensorDictBase, cfg: DQNConfig) -> TensorDictBase:
    """A replay sample [B] as [B, K]: every head gets the same transitions, each kept for a head
    with probability ``ensemble_mask`` (a 0/1 factor on its importance weight)."""
    out = sample.unsqueeze(-1).expand(*sample.batch_size, cfg.ensemble).clone(False)
    if cfg.ensemble_mask < 1:
        keep = torch.rand(out.batch_size, device=out.device) < cfg.ensemble_mask
        weight = out.get("priority_weight", None)
        weight = torch.ones(out.batch_size, device=out.device) if weight is None else weight
        out.set("priority_weight", weight * keep.to(weight.dtype))
    return out


def _track_episodes(
    data: TensorDictBase, total: torch.Tensor, frames: int, out: list[dict[str, Any]]
) -> None:
    """Add each training episode that ends in ``data`` ([num_envs, T] from the collector) to
    ``out`` (``episode``, ``env_steps`` at its end, total ``reward``); ``total`` carries the running
    sums of unfinished episodes across batches."""
    reward = data["next", "reward"].reshape(total.shape[0], -1).double().cpu()
    done = data["next", "done"].reshape(total.shape[0], -1).cpu()
    steps = reward.shape[1]
    for t in range(steps):
        total += reward[:, t]
        for e in done[:, t].nonzero().flatten().tolist():
            out.append(
                {
                    "learner": 0,
                    "episode": len(out) + 1,
                    "env_steps": frames + (t + 1) * total.shape[0],
                    "reward": float(total[e]),
                }
            )
            total[e] = 0.0


CHECKPOINT_KEYS = ("loss", "optimizer", "frames", "updates", "wall_seconds", "history", "config")


def load_checkpoint(path) -> dict[str, Any]:
    """Load a checkpoint (``RunRecord.state`` plus the run's ``config``) written by a DQN run.

    Raises:
        ValueError: one line naming the file when it is missing, truncated, corrupt or not a DQN
            checkpoint.
    """
    path = Path(path)
    if not path.is_file():
        raise ValueError(f"resume={path}: no such checkpoint file")
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as err:  # truncated or corrupt: EOFError, RuntimeError, UnpicklingError …
        raise ValueError(
            f"resume={path}: not a readable checkpoint ({type(err).__name__}); it may be truncated "
            "or from another program"
        ) from err
    missing = [k for k in CHECKPOINT_KEYS if not isinstance(state, dict) or k not in state]
    if missing:
        raise ValueError(f"resume={path}: not an irdrc DQN checkpoint (no {', '.join(missing)})")
    return state
