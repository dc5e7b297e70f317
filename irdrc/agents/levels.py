"""Observations as integer levels: their mixed-radix code, and a network that evaluates each
distinct observation of a batch once.

Every DFRCEnv observation is a vector of integer levels in [0, high] (queue length, channel,
weather, …), so a batch of thousands of env rows holds at most a few hundred distinct observations
(352 in the paper's scenario). ``DistinctRows`` evaluates its layers on those alone and copies the
result to every row: the same outputs as evaluating every row (a row's output depends on that row
alone; ``tests/test_levels.py`` holds them to the plain network bit for bit), at a fraction of the
cost when rows outnumber the possible observations — DQN's collector steps 10³–10⁴ rows at once,
and its loss samples thousands of transitions from them. In a pass that autograd records, the copy's
backward adds the gradients of a distinct observation's rows before the layers' backward: the
plain network's gradient, summed in another order.
"""

from __future__ import annotations

import weakref
from typing import Any

import torch
from torch import nn


def mixed_radix(high: torch.Tensor) -> tuple[torch.Tensor, int]:
    """The radix of each entry of observations with integer entries in [0, ``high``] (the last
    entry fastest), and the number of codes: ``(obs * radix).sum(-1)`` is an observation's code.

    Raises:
        ValueError: an entry of ``high`` is negative.
    """
    levels = high.round().to(torch.int64).reshape(-1) + 1
    if bool((levels < 1).any()):
        raise ValueError(f"observation high={high.tolist()} must be >= 0")
    radix = torch.ones_like(levels)
    for i in range(levels.numel() - 2, -1, -1):
        radix[i] = radix[i + 1] * levels[i + 1]
    return radix, int(torch.prod(levels.double()).item())


class DistinctRows(nn.Sequential):
    """``nn.Sequential`` (same children, same state-dict keys) that evaluates a batch [rows, n] of
    integer-level observations once per distinct observation when the rows outnumber the possible
    codes; otherwise (fewer rows, other shapes, or inputs that are not integers in [0, high]) it is
    the plain ``nn.Sequential``. Every pass takes it: the collector's, the evaluations', and each of
    a loss's passes (the one autograd records included).

    Args:
        *layers: the network's layers.
        high: [n] the largest value of each observation entry.
    """

    def __init__(self, *layers: nn.Module, high: torch.Tensor) -> None:
        super().__init__(*layers)
        radix, codes = mixed_radix(high)
        # plain attributes, not buffers: the loss's functional copies and the target network's
        # Polyak steps walk parameters and buffers, and these are constants
        self.radix = radix.to(high.device)
        self.top = high.round().to(torch.int64).to(high.device)
        self.codes = codes
        self._last: tuple[Any, int, tuple[torch.Tensor, torch.Tensor]] | None = (
            None  # (weak reference to an input, its version, its answer)
        )

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        rows = x.shape[0] if x.dim() == 2 else 0
        if rows <= self.codes or x.shape[-1] != self.radix.numel():
            return super().forward(x)
        found = self._distinct(x)
        if found is None:
            return super().forward(x)
        pick, position = found
        return super().forward(x[pick])[position]

    def _distinct(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor] | None:
        """(a row of ``x`` holding each distinct observation, the position of every row's
        observation among them), or None where ``x`` is not integer levels in [0, high]. The last
        answer is kept while its ``x`` lives unchanged: a loss's two passes over the next
        observations read the same tensor."""
        last = self._last
        if last is not None and last[0]() is x and last[1] == x._version:
            return last[2]
        levels = x.to(torch.int64)
        low, high = levels.aminmax(dim=0)
        if not (
            bool((low >= 0).all())
            and bool((high <= self.top).all())
            and torch.equal(levels.to(x.dtype), x)
        ):
            return None
        code = (levels * self.radix).sum(-1)
        present = torch.zeros(self.codes, dtype=torch.bool, device=x.device)
        present[code] = True
        first = torch.empty(self.codes, dtype=torch.int64, device=x.device)
        first[code] = torch.arange(x.shape[0], device=x.device)  # any row of a code: they are equal
        position = torch.cumsum(present, 0) - 1
        found = (first[present.nonzero().squeeze(-1)], position[code])
        self._last = (weakref.ref(x), x._version, found)
        return found
