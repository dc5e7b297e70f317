"""The reward table: the mean collected reward of every (observation, action), which a value learner's
targets read in place of the one sampled reward (``OffPolicyConfig.reward_means``), as a TorchRL
replay transform.

In an MDP the reward of a step is drawn given its state and action, so the mean of every reward
collected at the same (observation, action) estimates the expected reward E[r | s, a] that the
Q-learning target needs, from *every* step collected — not only the one a replay sample holds, and
not only the ones the updates happen to draw. A target r̂(s, a) + γ·Q̄(s′, …) has the expectation of
r + γ·Q̄(s′, …) and none of the reward's own noise: where a rare event costs r3 = 50 in one step of
fifty, one sample of r spreads by about 7 and the mean of n by 7/√n. The table is indexed by the
observation's integer levels (mixed radix over the observation spec's ``high``), so it applies to
any env whose observations are integer levels in [0, high] — every DFRCEnv scenario.

It is not checkpointed: a resumed run refills it, as it refills its replay.
"""

from __future__ import annotations

from typing import Any

import torch
from tensordict import TensorDictBase
from torchrl.envs.transforms import Transform

from irdrc.agents.levels import mixed_radix

MAX_ENTRIES = 10**8
"""The largest table (observations × actions) accepted: 1.6 GB of float64 sums and counts."""


class RewardTable(Transform):
    """Running sums and counts of the collected rewards per (observation, action) (``add``, fed
    every collected batch), and, as a replay buffer's transform, every sample drawn with each
    reward replaced by its (observation, action)'s mean (``apply``).

    Args:
        high: [n] the largest value of each observation entry (entries are integers in [0, high]).
        num_actions: the number of discrete actions.
        reward_key: where the reward sits in a collected batch and in a replay sample.
    """

    def __init__(
        self, high: torch.Tensor, num_actions: int, reward_key: Any = ("next", "reward")
    ) -> None:
        super().__init__()
        radix, codes = mixed_radix(high)
        size = codes * int(num_actions)
        if size > MAX_ENTRIES:
            raise ValueError(
                f"algo.reward_means: {size} (observation, action) pairs exceed {MAX_ENTRIES}; "
                "set algo.reward_means=false"
            )
        self.radix, self.num_actions, self.reward_key = radix, int(num_actions), reward_key
        self.sums = torch.zeros(size, dtype=torch.float64)
        self.counts = torch.zeros(size, dtype=torch.float64)

    def index(self, observation: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        """[N] the table entry of each (observation [..., n], action [...]) pair."""
        obs = observation.reshape(-1, self.radix.numel()).round().to(torch.int64)
        return (obs * self.radix).sum(-1) * self.num_actions + action.reshape(-1).to(torch.int64)

    def add(self, data: TensorDictBase) -> None:
        """Fold in a collected batch (``observation``, ``action`` and the reward, any shape)."""
        at = self.index(data.get("observation"), data.get("action"))
        reward = data.get(self.reward_key).reshape(-1).to(torch.float64)
        self.sums.index_add_(0, at, reward)
        self.counts.index_add_(0, at, torch.ones_like(reward))

    def apply(self, sample: TensorDictBase) -> TensorDictBase:
        """``sample`` with each reward replaced by the mean of its (observation, action)."""
        at = self.index(sample.get("observation"), sample.get("action"))
        reward = sample.get(self.reward_key)
        mean = self.sums[at] / self.counts[at].clamp(min=1.0)
        sample.set(self.reward_key, mean.to(reward.dtype).reshape(reward.shape))
        return sample

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        """A replay sample as it is drawn: ``apply``."""
        return self.apply(tensordict)

    def _inv_call(self, tensordict: TensorDictBase) -> TensorDictBase:
        """A batch as it is written: stored as collected (``add`` is fed by the learner)."""
        return tensordict
