"""One Monte-Carlo evaluation for every method: ``evaluate(policy, env, episodes)`` → metrics + CIs."""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from tensordict import TensorDictBase
from torchrl.envs.utils import step_mdp

from irdrc.core.env import DFRCEnv
from irdrc.core.metrics import METRIC_NAMES, Metrics

# Per-episode sums collected by ``evaluate``: numerator of each metric, and its denominator.
_RATIOS = {
    "avg_reward": ("reward", "steps"),
    "throughput": ("sent", "steps"),
    "link_capacity": ("capacity", "steps"),
    "miss_detection": ("missed", "event"),
    "radar_fraction": ("radar", "steps"),
    "drop_rate": ("dropped", "steps"),
    "mean_queue": ("queue", "steps"),
}


@dataclass(frozen=True)
class Evaluation:
    """Sampled metrics with 95 % confidence half-widths.

    Attributes:
        metrics: ratio-of-sums estimates over every step evaluated.
        ci95: metric → half-width of a 95 % interval (delta method over episodes, which are
            independent; NaN when fewer than two episodes or no event).
        episodes: episodes evaluated.
        steps: env steps evaluated.
    """

    metrics: Metrics
    ci95: dict[str, float]
    episodes: int
    steps: int


def ratio_ci(x: torch.Tensor, y: torch.Tensor, z: float = 1.959964) -> tuple[float, float]:
    """Ratio of sums Σx/Σy over independent clusters, and the half-width of its z-interval.

    The standard error is the delta-method (cluster-robust) one:
    se² = n/(n−1) · Σ(xᵢ − R·yᵢ)² / (Σy)².
    """
    x, y = x.double(), y.double()
    n, sy = x.numel(), float(y.sum())
    if sy == 0:
        return math.nan, math.nan
    r = float(x.sum()) / sy
    if n < 2:
        return r, math.nan
    resid = x - r * y
    se = math.sqrt(n / (n - 1) * float((resid**2).sum())) / sy
    return r, z * se


@torch.no_grad()
def evaluate(policy, env: DFRCEnv, episodes: int | None = None) -> Evaluation:
    """Run full episodes of ``policy`` on the batched ``env`` and aggregate MODEL.md's metrics.

    Every batch row plays whole episodes of ``env.params.env.horizon`` steps from a reset, so
    ``ceil(episodes / N)`` batched rounds are run (all of one round's episodes count).

    Args:
        policy: any TensorDictModule writing ``action`` (see ``irdrc.core.policies``).
        env: a ``DFRCEnv`` (its own seed decides the randomness).
        episodes: episodes to run at least; default one per batch row.
    """
    n = env.batch_size.numel()
    rounds = 1 if episodes is None else max(1, math.ceil(episodes / n))
    horizon = env.params.env.horizon
    keys = ("reward", "event", "missed", "sent", "capacity", "radar", "dropped", "queue")
    per_episode = {k: [] for k in keys}
    for _ in range(rounds):
        sums = {k: torch.zeros(n, dtype=torch.float64, device=env.device) for k in keys}
        td: TensorDictBase = env.reset()
        for _ in range(horizon):
            td = policy(td)
            sums["queue"] += td["observation"][..., 0].reshape(-1)
            sums["radar"] += td["action"].reshape(-1)
            td = env.step(td)
            nxt = td["next"]
            sums["reward"] += nxt["reward"].reshape(-1)
            for k in ("event", "missed", "sent", "capacity", "dropped"):
                sums[k] += nxt[k].reshape(-1)
            td = step_mdp(td)
        for k in keys:
            per_episode[k].append(sums[k].cpu())
    cols = {k: torch.cat(v) for k, v in per_episode.items()}
    cols["steps"] = torch.full_like(cols["reward"], float(horizon))
    values, ci = {}, {}
    for name, (num, den) in _RATIOS.items():
        values[name], ci[name] = ratio_ci(cols[num], cols[den])
    values["episode_reward"] = values["avg_reward"] * horizon
    ci["episode_reward"] = ci["avg_reward"] * horizon
    return Evaluation(
        metrics=Metrics(**{k: values[k] for k in METRIC_NAMES}),
        ci95={k: ci[k] for k in METRIC_NAMES},
        episodes=int(cols["reward"].numel()),
        steps=int(cols["steps"].sum()),
    )
