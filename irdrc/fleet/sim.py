"""The fleet's simulator: N vehicles stepped by the single-vehicle ``Dynamics`` (MODEL.md § C).

Each vehicle's own components move by one ``Dynamics.step`` of its single-vehicle state; road and
weather are the first vehicle's draw, copied to every vehicle (they follow their own chain,
whatever the vehicles do). A vehicle denied the uplink takes its queue from a radar-mode step
(nothing sent) and its other components from a comm-mode step (no radar reaction); the two steps
draw independent numbers, as the components' draws within a step are. Events are each vehicle's
own draw; an event its radar misses is detected by each other vehicle in radar mode with
probability ``share``. Rewards follow the table of ``irdrc.fleet.exact``.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from irdrc.core.env import Dynamics, decode_state
from irdrc.fleet.exact import FleetModel


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
        params = spec.vehicle
        self.dyn = Dynamics(params)
        S = model.single.num_states
        cols = decode_state(torch.arange(S), params.env.levels)
        channel = params.factor("channel")
        self.r_comm = torch.tensor(channel.comm_reward, dtype=torch.float64)[cols[:, 1]]
        b = (cols[:, 2] + cols[:, 3] + cols[:, 4] + cols[:, 5]).to(torch.float64)
        self.detect_reward = params.reward.r4 * (b + 1.0)
        self.r3, self.r5 = float(params.reward.r3), float(params.reward.r5)

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

    def step(self, states: torch.Tensor, actions: torch.Tensor, gen: torch.Generator) -> FleetStep:
        """One step of every fleet from [n, N] ``states`` under [n, N] ``actions``."""
        n, N = states.shape
        flat = states.reshape(-1)
        as_comm = self.dyn.step(flat, torch.zeros_like(flat), gen)
        as_radar = self.dyn.step(flat, torch.ones_like(flat), gen)

        def v(t: torch.Tensor) -> torch.Tensor:
            return t.reshape(n, N)

        radar = actions == 1
        granted = self.grant(actions, gen)
        denied = ~radar & ~granted
        d_c, f_c = (v(t) for t in self.dyn.split(as_comm.state))
        d_r, f_r = (v(t) for t in self.dyn.split(as_radar.state))
        f_next = torch.where(radar, f_r, f_c)  # a denied vehicle's components move as in comm
        d_next = torch.where(granted, d_c, d_r)  # … and its queue as in radar
        nxt = d_next * self.dyn.num_configs + f_next
        m = self.model
        x = m.x_of[nxt]
        shared = m.rw_of[nxt[:, :1]].expand(n, N)  # road and weather: the first vehicle's draw
        nxt = m.index[shared, x]
        event = torch.where(radar, v(as_radar.event), v(as_comm.event))
        self_missed = v(as_radar.missed) & radar  # radar mode, event, not detected by itself
        # another vehicle in radar mode detects it with probability share, independently
        u = torch.rand(n, N, N, generator=gen, dtype=torch.float64)
        watching = radar[:, None, :] & ~torch.eye(N, dtype=torch.bool)[None]
        by_others = ((u < m.spec.share) & watching).any(-1)
        unseen = event & (~radar | self_missed)  # not detected by the vehicle's own radar
        undetected = unseen & ~by_others
        s = states
        rc = torch.where(granted, self.r_comm[s], torch.zeros_like(self.r_comm[s]))
        alarm = v(as_radar.false_alarm) & radar
        reward = torch.where(
            radar,
            torch.where(event & ~self_missed, self.detect_reward[s], 0.0)
            - self.r5 * alarm.to(torch.float64),
            rc,
        )
        reward = torch.where(undetected, torch.full_like(reward, -self.r3), reward)
        sent = torch.where(granted, v(as_comm.sent), torch.zeros_like(v(as_comm.sent)))
        dropped = torch.where(granted, v(as_comm.dropped), v(as_radar.dropped))
        return FleetStep(
            nxt, reward, event, undetected, unseen & by_others, granted, denied, sent, dropped
        )
