"""The model's per-configuration tables (MODEL.md v1 and § B), computed once from ``Params`` and
shared by the simulator (``irdrc.core.env``) and the exact models (``irdrc.core.exact``: dense and
factored).

A *configuration* f is the joint level of the Markov factors and the traffic phase, mixed radix
with the channel most significant::

    f = ((((c·L_r + r)·L_w + w)·L_v + v)·L_m + m)·L_phase + phase

and a state is s = d·F + f with F = Π L (v1: F = 32, L_phase = 1, s = d·32 + c·16 + r·8 + w·4 +
v·2 + m). Everything the step needs besides the queue is a function of (action, f).
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from typing import Any, cast

import torch

from irdrc.core.factors import MARKOV_FACTORS
from irdrc.core.params import EVENT_FACTORS, Params

FACTOR_NAMES = (*MARKOV_FACTORS, "phase")
"""The configuration's factors in mixed-radix order (the traffic phase last)."""


@dataclass(frozen=True)
class ModelTables:
    """Float64 tables over the F factor configurations (see the module docstring).

    Attributes:
        levels: L of each factor of ``FACTOR_NAMES`` (the phase has 1 level for Poisson arrivals).
        radix: [6] int64, the weight of each factor's level in f.
        F: [2, F, F] P(f′ | a, f): one chain per factor, the radar reaction coupling v and m with a.
        event: [F] probability of an unexpected event.
        comm_reward: [F] reward of a comm step without an event (r_comm of the channel level).
        detect_reward: [F] reward of a detected event, r4·(b + 1), b = Σ of the event factors'
            levels.
        R: [2, F] expected reward.
        R2: [2, F] expected squared reward (its spread: ``irdrc.core.exact.one_step_spread``).
        missed: [2, F] expected missed events (comm: the event; radar: the event undetected).
        false_alarm: [2, F] expected false alarms (radar without an event, times P_fa).
        nu: [2, F] link capacity ν (0 in radar mode).
        rate: [F] Poisson arrival rate of the configuration's traffic phase.
        upper: per factor of ``FACTOR_NAMES`` a [2, F, L − 1] table of P(level′ ≥ k | a, f),
            k = 1 … L − 1: the simulator draws level′ = #{k : u < upper[k]} from one uniform u.
    """

    levels: tuple[int, ...]
    radix: torch.Tensor
    F: torch.Tensor
    event: torch.Tensor
    comm_reward: torch.Tensor
    detect_reward: torch.Tensor
    R: torch.Tensor
    R2: torch.Tensor
    missed: torch.Tensor
    false_alarm: torch.Tensor
    nu: torch.Tensor
    rate: torch.Tensor
    upper: tuple[torch.Tensor, ...]

    @property
    def num_configs(self) -> int:
        """F = Π L."""
        return math.prod(self.levels)

    def level(self, f: torch.Tensor, name: str) -> torch.Tensor:
        """The level of factor ``name`` in configurations ``f``."""
        i = FACTOR_NAMES.index(name)
        return (f // self.radix[i]) % self.levels[i]


def _f64(x: Any) -> torch.Tensor:
    return torch.as_tensor(x, dtype=torch.float64)


def model_tables(params: Params) -> ModelTables:
    """The tables of ``params`` (see ``ModelTables``)."""
    env, rw = params.env, params.reward
    specs = [params.factor(n) for n in MARKOV_FACTORS]
    bursty = env.bursty
    levels = (*(s.num_levels for s in specs), len(bursty.rates) if bursty else 1)
    n = math.prod(levels)
    radix = [1] * len(levels)
    for i in range(len(levels) - 2, -1, -1):
        radix[i] = radix[i + 1] * levels[i + 1]
    radix_t = torch.tensor(radix, dtype=torch.int64)
    f = torch.arange(n)
    lv = [(f // radix[i]) % levels[i] for i in range(len(levels))]  # per factor, [F]
    chains = [_f64(s.transition) for s in specs]
    chains.append(_f64(bursty.transition) if bursty else torch.ones(1, 1, dtype=torch.float64))

    # Factor transitions: the Kronecker product in mixed-radix order (c, r, w, v, m, phase).
    base = functools.reduce(torch.kron, chains)
    radar = base.clone()
    c_i, v_i, m_i = 0, 3, 4
    marg = [[ch[lv[i]] for i, ch in enumerate(chains)] for _ in (0, 1)]  # [a][factor] -> [F, L]
    if env.radar_reaction:
        # Radar with m ≥ 1: v′ = 0, m′ = 0 w.p. reaction_clear (else m′ = m); the others follow
        # their chains (MODEL.md step 4 and § B.1).
        react = lv[m_i] >= 1
        clear = env.reaction_clear
        Lv, Lm = levels[v_i], levels[m_i]
        v_next = torch.zeros(n, Lv, dtype=torch.float64)
        v_next[:, 0] = 1.0
        m_next = torch.zeros(n, Lm, dtype=torch.float64)
        m_next[:, 0] = clear
        m_next[torch.arange(n), lv[m_i]] += 1.0 - clear
        marg[1][v_i] = torch.where(react[:, None], v_next, marg[1][v_i])
        marg[1][m_i] = torch.where(react[:, None], m_next, marg[1][m_i])
        for g in torch.nonzero(react).flatten().tolist():
            rows = [marg[1][i][g] for i in range(len(levels))]
            radar[g] = functools.reduce(torch.kron, rows)
    F = torch.stack([base, radar])

    # Sampling tables: P(level′ ≥ k | a, f), k = 1 … L − 1, from each factor's marginal.
    upper = []
    for i in range(len(levels)):
        per_a = []
        for a in (0, 1):
            m = marg[a][i]  # [F, L]
            tail = torch.flip(torch.cumsum(torch.flip(m, [1]), 1), [1])
            per_a.append(tail[:, 1:])
        upper.append(torch.stack(per_a))

    # Events (MODEL.md step 1), levels of (r, w, v, m).
    per = [_f64(specs[1 + j].event)[lv[1 + j]] for j in range(len(EVENT_FACTORS))]
    if env.event_model == "noisy_or":
        event = 1.0 - cast(torch.Tensor, math.prod(1.0 - p for p in per))
    else:
        event = torch.clamp(cast(torch.Tensor, sum(per)), max=1.0)
    b = cast(torch.Tensor, sum(lv[1 + j].to(torch.float64) for j in range(len(EVENT_FACTORS))))
    comm_reward = _f64(specs[c_i].comm_reward)[lv[c_i]]
    detect_reward = rw.r4 * (b + 1.0)
    pd, pfa = env.detection_prob, env.false_alarm_prob
    R0 = (1.0 - event) * comm_reward - event * rw.r3
    R1 = event * rw.r4 * (b + 1.0)
    if pd < 1.0:
        R1 = event * (pd * detect_reward - (1.0 - pd) * rw.r3)
    if pfa > 0.0:
        R1 = R1 - (1.0 - event) * pfa * rw.r5
    R = torch.stack([R0, R1])
    R2 = squared_reward(event, comm_reward, detect_reward, pd, pfa, rw.r3, rw.r5)
    missed = torch.stack([event, event * (1.0 - pd)])
    false_alarm = torch.stack([torch.zeros_like(event), (1.0 - event) * pfa])
    nu = torch.stack([_f64(specs[c_i].packets)[lv[c_i]], torch.zeros(n, dtype=torch.float64)])
    rates = _f64(bursty.rates) if bursty else _f64([env.arrival_rate])
    return ModelTables(
        levels=levels,
        radix=radix_t,
        F=F,
        event=event,
        comm_reward=comm_reward,
        detect_reward=detect_reward,
        R=R,
        R2=R2,
        missed=missed,
        false_alarm=false_alarm,
        nu=nu,
        rate=rates[lv[-1]],
        upper=tuple(upper),
    )


def squared_reward(
    event: torch.Tensor,
    comm_reward: torch.Tensor,
    detect_reward: torch.Tensor,
    pd: float,
    pfa: float,
    r3: float,
    r5: float,
) -> torch.Tensor:
    """[2, F] the expected squared reward of a comm and a radar step: comm earns ``comm_reward``
    without an event and −r3 with one; radar earns ``detect_reward`` for a detected event (w.p.
    ``pd``), −r3 for one it misses, −r5 for a false alarm (w.p. ``pfa`` without an event), else 0."""
    return torch.stack(
        [
            (1.0 - event) * comm_reward**2 + event * r3**2,
            event * (pd * detect_reward**2 + (1.0 - pd) * r3**2) + (1.0 - event) * pfa * r5**2,
        ]
    )
