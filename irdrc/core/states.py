"""The state index, shared by the simulator, the exact models and every policy table: mixed radix
with d most significant (MODEL.md § B.1)::

    s = d·F + f,  f = ((((c·L_r + r)·L_w + w)·L_v + v)·L_m + m)·L_phase + phase,  F = Π L

which for v1 (two levels each, Poisson arrivals) is s = d·32 + c·16 + r·8 + w·4 + v·2 + m, so
``s & 31`` holds the five Markov factors (channel in bit 4 … object in bit 0) and ``s >> 5`` the
queue length d.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any, overload

import torch

# Bit of each Markov factor in the state index, in MARKOV_FACTORS order (c, r, w, v, m).
FACTOR_BITS = (4, 3, 2, 1, 0)
NUM_FACTOR_CONFIGS = 32


def state_index(
    d: Any,
    c: Any,
    r: Any,
    w: Any,
    v: Any,
    m: Any,
    phase: Any = 0,
    levels: Sequence[int] | None = None,
) -> Any:
    """State index of (d, c, r, w, v, m[, phase]); works on ints and integer tensors alike.

    ``levels``: L of (c, r, w, v, m, phase) (``Params.env.factor_levels``); None is v1 (two levels each,
    no phase): s = d·32 + c·16 + r·8 + w·4 + v·2 + m.
    """
    if levels is None:
        return d * 32 + c * 16 + r * 8 + w * 4 + v * 2 + m
    s = d
    for x, n in zip((c, r, w, v, m, phase), levels, strict=True):
        s = s * n + x
    return s


@overload
def decode_state(s: int, levels: Sequence[int] | None = None) -> tuple[int, ...]: ...


@overload
def decode_state(s: torch.Tensor, levels: Sequence[int] | None = None) -> torch.Tensor: ...


def decode_state(
    s: int | torch.Tensor, levels: Sequence[int] | None = None
) -> tuple[int, ...] | torch.Tensor:
    """State indices → their components: an integer tensor [...] → [..., 6] (d, c, r, w, v, m), or
    [..., 7] with the traffic phase last when ``levels`` (L of c, r, w, v, m, phase) has several
    phases; a plain int → a tuple of ints (``decode_state(5)`` → (0, 0, 0, 1, 0, 1))."""
    if isinstance(s, int):
        return tuple(int(x) for x in decode_state(torch.tensor(s), levels).tolist())
    if levels is None:
        cols = [s >> 5] + [(s >> b) & 1 for b in FACTOR_BITS]
        return torch.stack(cols, dim=-1)
    levels = list(levels)
    nf = math.prod(levels)
    cols, rest = [], s % nf
    for n in reversed(levels):
        cols.append(rest % n)
        rest = rest // n
    cols = [s // nf, *reversed(cols)]
    if levels[-1] == 1:
        cols = cols[:-1]
    return torch.stack(cols, dim=-1)
