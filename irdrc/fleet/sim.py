"""The fleet's simulator: N vehicles stepped by the single-vehicle ``Dynamics`` (MODEL.md § C).

Each vehicle's own components move by one ``Dynamics.step`` of its single-vehicle state (its own
dynamics where the vehicles differ); road and
weather are the first vehicle's draw, copied to every vehicle (they follow their own chain,
whatever the vehicles do). A vehicle denied the uplink takes its queue from a radar-mode step
(nothing sent) and its other components from a comm-mode step (no radar reaction); the two steps
draw independent numbers, as the components' draws within a step are. Events are each vehicle's
own draw; an event its radar misses is detected by each other vehicle in radar mode with
probability ``share``. Rewards follow the table of ``irdrc.fleet.model``.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from irdrc.core.dynamics import Dynamics
from irdrc.core.states import decode_state
from irdrc.fleet.model import FleetModel


@dataclass(frozen=True)
class FleetStep:
    """One fleet step, [n, N] per vehicle: next single-vehicle ``state``, ``reward`` (float64),
    ``event``, ``missed``, ``by_other`` (an event only another vehicle detected), ``granted``,
    ``denied`` (bool), ``sent``, ``dropped`` (int64)."""

    state: torch.Tensor
    reward: torch.Tensor
    event: torch.Tensor
    missed: torch.Tensor
    by_other: torch.Tensor
    granted: torch.Tensor
    denied: torch.Tensor
    sent: torch.Tensor
    dropped: torch.Tensor


class FleetDynamics:
    """Steps batches of fleets of ``model`` (states as [n, N] single-vehicle state indices that
    share road and weather)."""

    def __init__(self, model: FleetModel) -> None:
        self.model = model
        spec = model.spec
        per = spec.vehicle_params
        distinct = list(dict.fromkeys(per))
        self.dyns = [Dynamics(p) for p in distinct]
        self.dyn = self.dyns[0]  # every vehicle's state space and observation table
        self.groups = [
            torch.tensor([i for i, q in enumerate(per) if q == p], dtype=torch.int64)
            for p in distinct
        ]
        S = model.single.num_states
        cols = decode_state(torch.arange(S), spec.vehicle.env.factor_levels)
        b = (cols[:, 2] + cols[:, 3] + cols[:, 4] + cols[:, 5]).to(torch.float64)
        # [N, S] per vehicle: its comm reward and detection reward in every state; [N] r3, r5
        self.r_comm = torch.stack(
            [
                torch.tensor(p.factor("channel").comm_reward, dtype=torch.float64)[cols[:, 1]]
                for p in per
            ]
        )
        self.detect_reward = torch.stack([p.reward.r4 * (b + 1.0) for p in per])
        self.r3 = torch.tensor([float(p.reward.r3) for p in per], dtype=torch.float64)
        self.r5 = torch.tensor([float(p.reward.r5) for p in per], dtype=torch.float64)
        self.vehicle = torch.arange(model.N)

    def start(self, rows: int, gen: torch.Generator) -> torch.Tensor:
        """[rows, N] single-vehicle states of ``rows`` fleets drawn uniformly over the joint states
        (road and weather first, then each vehicle's own components)."""
        m, N = self.model, self.model.N
        rw = torch.randint(0, m.RW, (rows, 1), generator=gen)
        x = torch.randint(0, m.X, (rows, N), generator=gen)
        return m.index[rw.expand(rows, N), x]

    def fleet_index(self, states: torch.Tensor) -> torch.Tensor:
        """[n] joint state indices of the exact model from [n, N] single-vehicle states."""
        m = self.model
        idx = m.rw_of[states[:, 0]]
        for i in range(m.N):
            idx = idx * m.X + m.x_of[states[:, i]]
        return idx

    def grant(self, actions: torch.Tensor, gen: torch.Generator) -> torch.Tensor:
        """[n, N] granted: every request when at most K ask; else K of them at random
        (``scheduled``) or none (``collision``)."""
        K, comm = self.model.spec.channels, actions == 0
        asking = comm.sum(1, keepdim=True)
        if self.model.spec.access == "collision":
            return comm & (asking <= K)
        score = torch.rand(actions.shape, generator=gen, dtype=torch.float64)
        score = torch.where(comm, score, torch.full_like(score, 2.0))
        rank = score.argsort(1).argsort(1)  # 0 = the smallest score
        return comm & (rank < K)

    def _dynamics(
        self, states: torch.Tensor, action: int, gen: torch.Generator
    ) -> dict[str, torch.Tensor]:
        """Every vehicle's single-vehicle step from [n, N] ``states`` under one ``action``, by its
        own dynamics: ``state``, ``event``, ``missed``, ``false_alarm``, ``sent``, ``dropped``
        as [n, N]."""
        n, N = states.shape
        keys = ("state", "event", "missed", "false_alarm", "sent", "dropped")
        if len(self.dyns) == 1:
            flat = states.reshape(-1)
            res = self.dyn.step(flat, torch.full_like(flat, action), gen)
            return {k: getattr(res, k).reshape(n, N) for k in keys}
        out: dict[str, torch.Tensor] = {}
        for dyn, idx in zip(self.dyns, self.groups, strict=True):
            flat = states[:, idx].reshape(-1)
            res = dyn.step(flat, torch.full_like(flat, action), gen)
            for k in keys:
                v = getattr(res, k)
                if k not in out:
                    out[k] = torch.empty((n, N), dtype=v.dtype)
                out[k][:, idx] = v.reshape(n, len(idx))
        return out

    def step(self, states: torch.Tensor, actions: torch.Tensor, gen: torch.Generator) -> FleetStep:
        """One step of every fleet from [n, N] ``states`` under [n, N] ``actions``."""
        n, N = states.shape
        as_comm = self._dynamics(states, 0, gen)
        as_radar = self._dynamics(states, 1, gen)
        radar = actions == 1
        granted = self.grant(actions, gen)
        denied = ~radar & ~granted
        d_c, f_c = self.dyn.split(as_comm["state"])
        d_r, f_r = self.dyn.split(as_radar["state"])
        f_next = torch.where(radar, f_r, f_c)  # a denied vehicle's components move as in comm
        d_next = torch.where(granted, d_c, d_r)  # … and its queue as in radar
        nxt = d_next * self.dyn.num_configs + f_next
        m = self.model
        x = m.x_of[nxt]
        shared = m.rw_of[nxt[:, :1]].expand(n, N)  # road and weather: the first vehicle's draw
        nxt = m.index[shared, x]
        event = torch.where(radar, as_radar["event"], as_comm["event"])
        self_missed = as_radar["missed"] & radar  # radar mode, event, not detected by itself
        # another vehicle in radar mode detects it with probability share, independently
        u = torch.rand(n, N, N, generator=gen, dtype=torch.float64)
        watching = radar[:, None, :] & ~torch.eye(N, dtype=torch.bool)[None]
        by_others = ((u < m.spec.share) & watching).any(-1)
        unseen = event & (~radar | self_missed)  # not detected by the vehicle's own radar
        undetected = unseen & ~by_others
        r_comm = self.r_comm[self.vehicle, states]  # [n, N]: vehicle i's table at its state
        detect = self.detect_reward[self.vehicle, states]
        rc = torch.where(granted, r_comm, torch.zeros_like(r_comm))
        alarm = as_radar["false_alarm"] & radar
        reward = torch.where(
            radar,
            torch.where(event & ~self_missed, detect, 0.0) - self.r5 * alarm.to(torch.float64),
            rc,
        )
        reward = torch.where(undetected, -self.r3.expand(n, N), reward)
        sent = torch.where(granted, as_comm["sent"], torch.zeros_like(as_comm["sent"]))
        dropped = torch.where(granted, as_comm["dropped"], as_radar["dropped"])
        return FleetStep(
            nxt, reward, event, undetected, unseen & by_others, granted, denied, sent, dropped
        )
