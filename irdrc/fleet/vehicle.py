"""One vehicle of a fleet (MODEL.md § C) on the fleet's grid: its kernels and its expected
rewards, events and detection, from its single-vehicle exact model.

The kernels come from the single-vehicle exact model (``irdrc.core.exact.build_model``), which is
held to the simulator by its own tests: its transition factorises as P_rw(r′w′ | rw)·K_a(x′ | x)
(road and weather follow their chains whatever the vehicle does), and K_a as the queue's
Q_a(d′ | d, f) times the other components' F_a(f′ | f) — both checked when the model is built. A
vehicle denied the uplink moves its queue as in radar mode (nothing sent) and its components as in
comm mode (no radar reaction). Each kernel is also kept as those two factors, which is how the
fleet model applies it.

Rewards, events and detection (per vehicle, given the joint action and who is granted):
e = P(event | r, w, v_i, m_i); k_i = other vehicles in radar; q_i = 1 − (1 − share)^k_i the chance
that another vehicle detects vehicle i's event (cooperative perception); P_d, P_fa the radar's.

| a_i | outcome | reward | missed |
|---|---|---|---|
| radar | event, detected by itself (P_d) | r4·(b_i + 1) | 0 |
| radar | event, not by itself, by another (q_i) | 0 | 0 |
| radar | event, by nobody | −r3 | 1 |
| radar | no event, false alarm (P_fa) | −r5 | 0 |
| comm, granted | no event, or an event another vehicle detects | r_comm[c_i] | 0 |
| comm, denied | no event, or an event another vehicle detects | 0 | 0 |
| comm | event, by nobody | −r3 | 1 |
"""

from __future__ import annotations

import math

import torch

from irdrc.core.exact import build_model
from irdrc.core.exact.dense import DENSE_MAX_STATES
from irdrc.core.params import Params

TERMS = (
    "reward",
    "missed",
    "false_alarms",
    "event",
    "sent",
    "dropped",
    "capacity",
    "radar",
    "comm",
    "denied",
    "queue",
)
"""A vehicle's per-step expectations (``VehicleTables.terms``)."""


class VehicleTables:
    """One vehicle's kernels and expectations on the fleet's [RW, X] grid, from its single-vehicle
    exact model (see the module docstring: the factorisations are checked here).

    Attributes:
        single: the vehicle's single-vehicle exact model.
        P_rw: [RW, RW] the road and weather chain it implies.
        K: {"comm", "radar", "denied"} → [X, X] the vehicle's kernel.
        factors: the same kernels as their two factors: the queue's Q [D+1, F, D+1′] and the other
            components' chain F [F, F′] (K[(d, f), (d′, f′)] = Q[d, f, d′]·F[f, f′]).
        queue_by_rest: each kernel's Q as [F, D+1′, D+1] (Qᵀ per value of the other components).
    """

    def __init__(self, params: Params, grid: torch.Tensor, cols: torch.Tensor) -> None:
        """``grid`` [RW, X]: the single-vehicle state at each (road and weather, own components);
        ``cols`` [S, 6 or 7]: each single-vehicle state's components (d, c, r, w, v, m[, phase])."""
        S = params.env.num_states
        if S > DENSE_MAX_STATES:
            top = DENSE_MAX_STATES // math.prod(params.env.factor_levels) - 1
            raise ValueError(
                f"env.queue_capacity={params.env.queue_capacity}: a fleet's vehicle is built from "
                f"its single-vehicle dense model, at most {DENSE_MAX_STATES} states "
                f"(env.queue_capacity ≤ {top} here); this one has S = {S}"
            )
        single = build_model(params)
        self.single = single
        RW, X = grid.shape
        D1 = params.env.queue_capacity + 1
        F = X // D1  # the components besides the queue
        P = single.P[:, grid.reshape(-1)][:, :, grid.reshape(-1)]
        P = P.reshape(2, RW, X, RW, X)
        self.P_rw = P[0, :, 0].sum(-1)  # [RW, RW′] from any x
        kern = []
        for a in (0, 1):
            K = P[a, 0, :, :, :].sum(1)  # [X, X′] from rw = 0
            want = self.P_rw[:, None, :, None] * K[None, :, None, :]
            if not torch.allclose(P[a], want, atol=1e-12, rtol=0):
                raise ValueError("the single-vehicle model does not factorise over (r, w)")
            kern.append(K)
        # queue × other components: K_a[(d, f), (d′, f′)] = Q_a[(d, f), d′]·F_a[f, f′]
        split = [k.reshape(D1, F, D1, F) for k in kern]
        Q = [k.sum(3) for k in split]  # [D1, F, D1′]
        Fk = [k.sum(2)[0] for k in split]  # [F, F′] from d = 0
        for k, q, f in zip(split, Q, Fk, strict=True):
            if not torch.allclose(k, q[:, :, :, None] * f[None, :, None, :], atol=1e-12, rtol=0):
                raise ValueError("the single-vehicle kernel does not factorise into queue × rest")
        denied = (Q[1][:, :, :, None] * Fk[0][None, :, None, :]).reshape(X, X)
        self.K = {"comm": kern[0], "radar": kern[1], "denied": denied}
        self.factors = {"comm": (Q[0], Fk[0]), "radar": (Q[1], Fk[1]), "denied": (Q[1], Fk[0])}
        self.queue_by_rest = {
            k: q.permute(1, 2, 0).contiguous() for k, (q, _) in self.factors.items()
        }
        self.event = single.event[grid]  # [RW, X]
        env, rew = params.env, params.reward
        b = (cols[:, 2] + cols[:, 3] + cols[:, 4] + cols[:, 5]).to(torch.float64)[grid]
        channel = params.factor("channel")
        self.r_comm = torch.tensor(channel.comm_reward, dtype=torch.float64)[cols[:, 1][grid]]
        self.detect_reward = rew.r4 * (b + 1.0)
        self.r3, self.r5 = float(rew.r3), float(rew.r5)
        self.p_detect, self.p_alarm = float(env.detection_prob), float(env.false_alarm_prob)
        self.sent = {"comm": single.sent[0][grid], "radar": single.sent[1][grid]}
        self.dropped = {"comm": single.dropped[0][grid], "radar": single.dropped[1][grid]}
        self.capacity = single.capacity[0][grid]
        self.queue = single.queue.to(torch.float64)[grid]

    def terms(
        self, act: int, others_radar: int, granted: bool, share: float
    ) -> dict[str, torch.Tensor]:
        """The vehicle's expected reward, missed events, false alarms, events, sent, dropped,
        capacity, radar, comm and denied steps per step ([RW, X]) given its action, how many others watch the road, whether
        its uplink request is granted, and the fleet's ``share``."""
        e = self.event
        q = 1.0 - (1.0 - share) ** others_radar  # another vehicle detects the event
        zero = torch.zeros_like(e)
        if act == 1:
            nobody = (1.0 - self.p_detect) * (1.0 - q)
            reward = e * (self.p_detect * self.detect_reward - nobody * self.r3)
            reward = reward - (1.0 - e) * self.p_alarm * self.r5
            return {
                "reward": reward,
                "missed": e * nobody,
                "false_alarms": (1.0 - e) * self.p_alarm,
                "event": e,
                "sent": self.sent["radar"],
                "dropped": self.dropped["radar"],
                "capacity": zero,
                "radar": torch.ones_like(e),
                "comm": zero,
                "denied": zero,
                "queue": self.queue,
            }
        r_ok = self.r_comm if granted else zero
        reward = (1.0 - e) * r_ok + e * (q * r_ok - (1.0 - q) * self.r3)
        key = "comm" if granted else "radar"  # a denied vehicle's queue moves as in radar mode
        return {
            "reward": reward,
            "missed": e * (1.0 - q),
            "false_alarms": zero,
            "event": e,
            "sent": self.sent[key],
            "dropped": self.dropped[key],
            "capacity": self.capacity if granted else zero,
            "radar": zero,
            "comm": torch.ones_like(e),
            "denied": zero if granted else torch.ones_like(e),
            "queue": self.queue,
        }
