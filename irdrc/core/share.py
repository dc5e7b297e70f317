"""The radar share ρ of a step (MODEL.md § D): the sensing curve, and the model's tables for any
set of shares — what the exact models build their actions from.

At ρ = 0 and ρ = 1 every table here is v1/v2's (``irdrc.core.tables``) exactly; between them the
reward, the missed events and the radar reaction follow the sensing curve q(ρ), the false alarms
and the link's capacity ν(1 − ρ) are linear in ρ (the capacity rounded at random:
k = ⌊ν(1 − ρ)⌋ + Bernoulli(frac ν(1 − ρ))).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import torch

from irdrc.core.params import Params
from irdrc.core.tables import ModelTables, model_tables


def reaction(rho: torch.Tensor, sensing: str, gain: float) -> torch.Tensor:
    """u(ρ) = q(ρ) / q(1): the share of a full step's detection a share ρ gets (float64).
    ``dwell``: (1 − e^{−κρ}) / (1 − e^{−κ}); ``linear``: ρ. u(0) = 0, u(1) = 1."""
    rho = torch.as_tensor(rho, dtype=torch.float64)
    if sensing == "linear":
        return rho.clone()
    return torch.expm1(-gain * rho) / math.expm1(-gain)


def reaction_slope_bound(lo: float, sensing: str, gain: float) -> tuple[float, float]:
    """(sup |u′|, sup |u″|) on [lo, 1]: u′ and |u″| decrease in ρ, so both are at ``lo``."""
    if sensing == "linear":
        return 1.0, 0.0
    d1 = gain * math.exp(-gain * lo) / -math.expm1(-gain)
    return d1, gain * d1


def detection(params: Params, rho: torch.Tensor) -> torch.Tensor:
    """q(ρ) = P_d · u(ρ): the probability that an event in the step is detected."""
    env = params.env
    return env.detection_prob * reaction(rho, env.sensing, env.dwell_gain)


def capacity_split(nu: torch.Tensor, rho: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(k, p): the link carries k packets, or k + 1 with probability p, where ν(1 − ρ) = k + p.
    A value within 1e-9 of an integer is that integer (a breakpoint is not split by rounding)."""
    x = nu * (1.0 - rho)
    k = torch.floor(x + 1e-9)
    return k, (x - k).clamp(0.0, 1.0)


def breakpoints(params: Params) -> tuple[float, ...]:
    """The shares where ν(c)(1 − ρ) is an integer for some channel level c, 0 and 1 included,
    sorted: between two of them every state's Q(s, ρ) is α + βρ + (γ + δρ)·u(ρ)."""
    packets = params.factor("channel").packets
    points = {0.0, 1.0}
    for nu in packets:
        points.update(1.0 - j / nu for j in range(1, int(nu)))
    return tuple(sorted(points))


@dataclass(frozen=True)
class ShareTables:
    """The model's tables over F configurations for A radar shares (float64).

    Attributes:
        shares: [A] the actions' radar shares ρ.
        F: [A, F, F] P(f′ | ρ, f) = u(ρ)·F_radar + (1 − u(ρ))·F_comm.
        R, missed, false_alarm: [A, F] expected reward, missed events, false alarms.
        k, p: [A, F] link capacity k, or k + 1 with probability p (``capacity_split``).
        nu: [A, F] expected capacity ν(1 − ρ).
        base: the v1 tables they were built from.
    """

    shares: torch.Tensor
    F: torch.Tensor
    R: torch.Tensor
    missed: torch.Tensor
    false_alarm: torch.Tensor
    k: torch.Tensor
    p: torch.Tensor
    nu: torch.Tensor
    base: ModelTables


def share_tables(params: Params, shares: Any = None) -> ShareTables:
    """The tables of ``params`` for the radar shares ``shares`` (default: ``params.env.shares``;
    binary gives v1's tables, with ``p`` = 0)."""
    t = model_tables(params)
    env, rw = params.env, params.reward
    rho = torch.as_tensor(env.shares if shares is None else shares, dtype=torch.float64)
    if rho.ndim != 1 or bool(((rho < 0) | (rho > 1)).any()):
        raise ValueError(f"radar shares must be a list of values in [0, 1]; got {rho.tolist()}")
    if env.actions == "binary" and shares is None:
        return ShareTables(
            shares=rho,
            F=t.F,
            R=t.R,
            missed=t.missed,
            false_alarm=t.false_alarm,
            k=t.nu,
            p=torch.zeros_like(t.nu),
            nu=t.nu,
            base=t,
        )
    u = reaction(rho, env.sensing, env.dwell_gain)[:, None]  # [A, 1]
    q = env.detection_prob * u
    e, r = t.event[None], rho[:, None]
    R = (1.0 - e) * ((1.0 - r) * t.comm_reward - r * env.false_alarm_prob * rw.r5)
    R = R + e * (q * t.detect_reward - (1.0 - q) * rw.r3)
    k, p = capacity_split(t.nu[0][None], r)

    def ends(table: torch.Tensor, base: torch.Tensor) -> torch.Tensor:
        """``table`` with v1's rows where ρ is 0 or 1 (the same values, summed in v1's order)."""
        table = torch.where(r == 0.0, base[0][None], table)
        return torch.where(r == 1.0, base[1][None], table)

    return ShareTables(
        shares=rho,
        F=u[:, :, None] * t.F[1][None] + (1.0 - u[:, :, None]) * t.F[0][None],
        R=ends(R, t.R),
        missed=ends(e * (1.0 - q), t.missed),
        false_alarm=ends((1.0 - e) * r * env.false_alarm_prob, t.false_alarm),
        k=k,
        p=p,
        nu=t.nu[0][None] * (1.0 - r),
        base=t,
    )
