"""The parts of a learner of the radar share ρ ∈ [0, 1] (MODEL.md § D), apart from its loss: a critic
Q(observation, ρ), exploration of shares over the env rows, a Beta distribution of shares, and the
policy's table of shares."""

from __future__ import annotations

from typing import Any

import torch
from tensordict import TensorDict
from torch import nn
from torchrl.envs.utils import ExplorationType, set_exploration_type

from irdrc.agents.configs.value import NetworkConfig
from irdrc.agents.loop import start_frames
from irdrc.agents.offpolicy import eps_ladder, make_body
from irdrc.core.env import DFRCEnv
from irdrc.core.params import Params


class Critic(nn.Module):
    """Q(observation, ρ): the scaled observation and the share, clipped to [0, 1] (what the env
    steps with, wherever the actor's samples lie), into one MLP."""

    def __init__(self, high: torch.Tensor, network: NetworkConfig) -> None:
        super().__init__()
        self.body = make_body(torch.cat([high, torch.ones(1)]), network, 1)

    def forward(self, observation: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        return self.body(torch.cat([observation, action.clamp(0.0, 1.0)], -1))


class ShareBeta(torch.distributions.Beta):
    """A Beta distribution of shares for a ``ProbabilisticActor`` (Chou et al. 2017: bounded, no
    mass lost at the ends): samples kept within ``EPS`` of [0, 1]'s ends (a float32 sample of
    exactly 0 or 1 has an infinite log-density), and the mode as the deterministic share — it
    reaches 1 (β = 1), which the mean never does. The actor's concentrations are > 1
    (``BetaConcentrations``), so the mode exists."""

    EPS = 1e-6

    def sample(self, sample_shape: Any = ()) -> torch.Tensor:
        return super().sample(sample_shape).clamp(self.EPS, 1.0 - self.EPS)

    def rsample(self, sample_shape: Any = ()) -> torch.Tensor:
        return super().rsample(sample_shape).clamp(self.EPS, 1.0 - self.EPS)

    @property
    def deterministic_sample(self) -> torch.Tensor:
        """The mode (α − 1)/(α + β − 2); the mean where α = β = 1."""
        a, b = self.concentration1, self.concentration0
        mode = (a - 1.0) / (a + b - 2.0).clamp(min=1e-6)
        return torch.where(a + b > 2.0 + 1e-6, mode, self.mean)


class BetaConcentrations(nn.Module):
    """Two network outputs → the Beta's concentrations α, β = 1 + softplus(·) > 1 (unimodal)."""

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        c = nn.functional.softplus(x) + 1.0
        return c[..., :1], c[..., 1:]


class ShareLadder(nn.Module):
    """Exploration of a share beside the actor's own: the actor's share clipped to [0, 1], and row
    i of the batch takes a uniformly random share with probability ε_i (``eps_ladder``:
    log-uniform across rows, DQN's ladder)."""

    eps: torch.Tensor

    def __init__(self, rows: int, eps_max: float, eps_min: float) -> None:
        super().__init__()
        self.register_buffer("eps", eps_ladder(rows, eps_max, eps_min)[:, None])

    def forward(self, action: torch.Tensor) -> torch.Tensor:
        action = action.clamp(0.0, 1.0)
        if action.shape[0] != self.eps.shape[0]:  # not the collector's batch: as the actor says
            return action
        explore = torch.rand_like(action) < self.eps
        return torch.where(explore, torch.rand_like(action), action)


def share_table(actor: nn.Module, env: DFRCEnv) -> torch.Tensor:
    """The actor's deterministic share in every state ([S] float64)."""
    obs = env.dynamics.obs
    with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
        out = actor(TensorDict({"observation": obs}, batch_size=[obs.shape[0]]))
    return out["action"].reshape(-1).double().clamp(0.0, 1.0).cpu()


def share_run(
    params: Params, cfg: Any, *, seed: int, device: str, scorer: Any, resume: Any
) -> tuple[DFRCEnv, Any, int]:
    """What every learner of the radar share starts with: the check that the scenario's actions
    are shares, torch seeded, ``cfg.num_envs`` env rows, the exact scorer (the continuum's
    optimum unless ``scorer`` is given) and the env steps a resumed run starts at.

    Raises:
        ValueError: a discrete action space, or a checkpoint with nothing left to train.
    """
    name = cfg.name.upper()
    if params.env.actions != "continuous":
        raise ValueError(
            f"{name} acts on radar shares: env.actions=continuous (got {params.env.actions})"
        )
    torch.manual_seed(seed)
    env = DFRCEnv(params, batch_size=[cfg.num_envs], device=device, seed=seed)
    if scorer is None:
        from irdrc.core.exact.continuum import ContinuumScorer

        scorer = ContinuumScorer(params)
    start = start_frames(resume)
    return env, scorer, start
