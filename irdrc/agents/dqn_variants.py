"""DQN's variants, each off by default: distributional values (C51) and the choice of the final
policy among late snapshots by measured returns. ``irdrc.agents.dqn`` calls them through the few
functions below, so the default learner reads the same whether they are on or off."""

from __future__ import annotations

from typing import Any

import torch
from tensordict import TensorDictBase
from torch import nn
from torchrl.modules import DistributionalQValueActor
from torchrl.objectives import DistributionalDQNLoss

from irdrc.agents.base import RunRecord
from irdrc.agents.offpolicy import OffPolicyConfig, action_values, all_states, make_mlp
from irdrc.agents.select import Snapshots, choose_final
from irdrc.core.env import DFRCEnv
from irdrc.core.params import Params
from irdrc.core.solve import ExactScorer

SELECT_SEED_OFFSET = 104_729
"""The selection's measurements use the run's seed plus this (their own random numbers)."""


# -- distributional values (C51) -------------------------------------------------------------------


class _Atoms(nn.Module):
    """[..., atoms · actions] to [..., atoms, actions] (TorchRL's distributional layout)."""

    def __init__(self, atoms: int, actions: int) -> None:
        super().__init__()
        self.shape = (atoms, actions)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x.unflatten(-1, self.shape)


def make_distributional(
    env: DFRCEnv, cfg: OffPolicyConfig
) -> tuple[DistributionalQValueActor, DistributionalDQNLoss]:
    """C51's actor — log-probabilities [..., atoms, actions] of the return on ``atoms`` evenly
    spaced points over ±``support_span`` × the largest |reward| of the env's reward table, greedy in
    the mean — and TorchRL's ``DistributionalDQNLoss`` (a cross-entropy to the projected
    double-DQN target)."""
    dyn = env.dynamics
    r_max = max(float(dyn.reward.abs().max()), float(dyn.miss_reward.abs().max()), 1e-6)
    support = torch.linspace(
        -cfg.support_span * r_max, cfg.support_span * r_max, cfg.atoms, device=env.device
    )
    n = env.action_spec_unbatched.space.n
    module = nn.Sequential(make_mlp(env, cfg.network, cfg.atoms * n), _Atoms(cfg.atoms, n))
    qnet = DistributionalQValueActor(
        module=module, support=support, in_keys=["observation"], spec=env.action_spec_unbatched
    )
    return qnet, DistributionalDQNLoss(qnet, gamma=cfg.gamma, delay_value=True)


def priority(sample: TensorDictBase, cfg: Any) -> torch.Tensor:
    """The new priority of each sampled transition: |δ| (``DQNLoss`` writes δ²), or the
    distributional loss's per-sample cross-entropy as it is."""
    delta = sample["td_error"].detach()
    return (delta if getattr(cfg, "distributional", False) else delta.sqrt()).reshape(-1)


def values(qnet: nn.Module, env: DFRCEnv) -> torch.Tensor:
    """[S, 2] action values of every state: a distributional network's are its means."""
    if not isinstance(qnet, DistributionalQValueActor):
        return action_values(qnet, env)
    logp = all_states(qnet, env)["action_value"]
    return (logp.exp() * qnet.support.to(logp)[:, None]).sum(-2).reshape(-1, 2).float().cpu()


# -- final-policy selection ------------------------------------------------------------------------


class Selection:
    """Snapshots of the greedy policy from ``select_after_frames`` on, every
    ``select_every_frames``, and at the end the final policy chosen among them by measured returns
    (``irdrc.agents.select.choose_final``); inert when ``select_every_frames`` is 0."""

    def __init__(self, cfg: Any) -> None:
        self.cfg = cfg
        self.snapshots = Snapshots(
            getattr(cfg, "select_every_frames", 0), getattr(cfg, "select_after_frames", 0)
        )

    @property
    def on(self) -> bool:
        """Whether selection is on."""
        return self.snapshots.on

    def due(self, before: int, now: int) -> bool:
        """Whether a snapshot falls in (before, now] before the run's end."""
        return self.snapshots.due(before, now) and now < self.cfg.total_frames

    def take(self, frames: int, table: torch.Tensor, q: torch.Tensor) -> None:
        """Keep the greedy ``table`` and its values ``q`` taken at ``frames`` env steps."""
        self.snapshots.take(frames, table, q)

    def state(self) -> dict[str, Any]:
        """The checkpoint entry (none when off)."""
        return {"snapshots": self.snapshots.state()} if self.on else {}

    def load(self, checkpoint: dict[str, Any]) -> None:
        """Restore the snapshots from a checkpoint."""
        self.snapshots.load(checkpoint.get("snapshots"))

    def finish(
        self, record: RunRecord, params: Params, seed: int, scorer: ExactScorer, optimal: float
    ) -> None:
        """Replace the record's final table by the chosen one; the measurement steps join
        ``env_steps`` as ``measurement_env_steps`` (``info``: ``select_*``, and ``selected_ratio``, the
        chosen table's exact score, for benchmarks; the exact model never steers the choice)."""
        cfg, snaps = self.cfg, self.snapshots
        snaps.take(record.env_steps, record.greedy[0], record.q[0])
        index, facts = choose_final(
            params,
            snaps,
            envs=cfg.select_envs,
            steps=cfg.select_steps,
            burn_in=cfg.select_burn_in,
            z=cfg.select_z,
            seed=seed + SELECT_SEED_OFFSET,
        )
        record.greedy = snaps.tables[index].to(record.greedy.device)[None]
        record.q = snaps.values[index].to(record.q.device)[None]
        snaps.pop()
        record.measurement_env_steps = int(facts["select_env_steps"])
        record.env_steps += record.measurement_env_steps
        record.info["selected_ratio"] = float(scorer.metrics(record.greedy[0]).avg_reward / optimal)
        record.info.update(facts)
