"""What a structure-aware learner is told and what it counts (MODEL.md § E): the model's *form*, never
its numbers.

It is told the form: each factor (channel, road, weather, speed, object, and the traffic phase with
bursty arrivals) is a Markov chain over the levels it observes; an event's probability depends on
the event factors' levels (road, weather, speed, object) by the scenario's event model — noisy-or,
one probability per factor and level, the event happening when any factor's fires, or their sum,
which it treats as one probability per combination of levels; packets arrive as Poisson counts whose
rate may depend on the traffic phase; a comm step carries a fixed number of packets per channel
level; the reward has eq. (3)'s form (a comm reward per channel level, a penalty for a missed event,
a detection reward times b + 1, a false-alarm cost), and a radar step detects an event with some
probability and raises a false alarm with another. It is not told whether the radar reaction is
on: speed and object are counted as one joint chain per action, which covers the reaction's
coupling either way.

From the stream it counts each chain's transitions, events per combination of event-factor levels
(under noisy-or, a Gibbs sampler gives the per-factor probabilities' posterior: each event's firing
factors are drawn given the probabilities, then the probabilities given the firings, Beta by
Beta),
arrivals, detections and false alarms, and it reads the numbers that a step shows exactly (a comm
reward, the penalty, the detection reward, a channel level's packets once a step is limited by
them). ``estimate`` gives the posterior mean or one posterior sample of every number, and
``tables`` the model's per-configuration tables (``irdrc.core.tables.ModelTables``), which the exact
core plans on (``irdrc.core.exact.factored_model``). A number never shown is planned
optimistically: a gain (a channel level's comm reward, the detection reward) as the largest reward
the stream has shown, a cost (the miss penalty, the false-alarm cost) as 0, a channel level's
packets as everything the queue could send.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from irdrc.core.exact.factored import FactoredModel, factored_model
from irdrc.core.params import Params
from irdrc.core.states import decode_state
from irdrc.core.stream import Step
from irdrc.core.tables import ModelTables, squared_reward


@dataclass
class Estimate:
    """Every number of the model, as a learner estimates it.

    Attributes:
        chains: the transition matrix of channel, road, weather and the traffic phase ([L, L]).
        speed_object: [2, Lv·Lm, Lv·Lm] the joint chain of (speed, object) under each action.
        event: [Lr·Lw·Lv·Lm] the event probability per combination of event-factor levels.
        rate: [L_phase] Poisson arrivals per step.
        packets: [Lc] packets a comm step carries per channel level.
        comm_reward: [Lc]; miss_penalty (r3), detect_reward (r4), alarm_cost (r5).
        detection, false_alarm: P_d and P_fa.
    """

    chains: dict[str, torch.Tensor]
    speed_object: torch.Tensor
    event: torch.Tensor
    rate: torch.Tensor
    packets: torch.Tensor
    comm_reward: torch.Tensor
    miss_penalty: float
    detect_reward: float
    alarm_cost: float
    detection: float
    false_alarm: float


class FormCounts:
    """The counts of one vehicle's stream under the model's form (see the module docstring).

    Args:
        params: the scenario; only its observation space is read (the queue's capacity and each
            factor's number of levels: what the vehicle's own observations range over).
        prior: the pseudo-count of each outcome in every Dirichlet and Beta prior.
    """

    CHAINS = ("channel", "road", "weather", "phase")

    def __init__(self, params: Params, prior: float = 1.0) -> None:
        env = params.env
        self.levels = Lc, Lr, Lw, Lv, Lm, Lp = env.factor_levels
        self.noisy_or = env.event_model == "noisy_or"
        self.D = env.queue_capacity
        self.horizon = env.horizon
        self.num_states = S = env.num_states
        self.prior = float(prior)
        cols = decode_state(torch.arange(S), self.levels)
        if Lp == 1:
            cols = torch.cat([cols, torch.zeros(S, 1, dtype=cols.dtype)], 1)
        # per state: (d, c, r, w, v, m, phase, event combination, b, speed-object index)
        d, c, r, w, v, m, ph = cols.T.tolist()
        self._state = [
            (d[s], c[s], r[s], w[s], v[s], m[s], ph[s], ((r[s] * Lw + w[s]) * Lv + v[s]) * Lm + m[s],
             r[s] + w[s] + v[s] + m[s], v[s] * Lm + m[s])
            for s in range(S)
        ]  # fmt: skip
        sizes = {"channel": Lc, "road": Lr, "weather": Lw, "phase": Lp}
        self.chain = {k: [[0] * n for _ in range(n)] for k, n in sizes.items()}
        nvm = Lv * Lm
        self.speed_object = [[[0] * nvm for _ in range(nvm)] for _ in (0, 1)]
        ncombo = Lr * Lw * Lv * Lm
        self.event_n, self.event_k = [0] * ncombo, [0] * ncombo
        self.arrivals_sum, self.arrivals_n = [0] * Lp, [0] * Lp
        self.packets_known: list[int | None] = [None] * Lc
        self.arrivals_top = 0
        self.comm_reward: list[float | None] = [None] * Lc
        self.miss_penalty: float | None = None
        self.detect_reward: float | None = None
        self.alarm_cost: float | None = None
        self.top_reward = 0.0  # the largest |reward| shown so far
        self.detected, self.radar_events = 0, 0
        self.alarms, self.quiet_radar = 0, 0
        # noisy-or: each combination's levels per event factor, and the sampler's state
        grid = np.stack(np.meshgrid(*(np.arange(n) for n in (Lr, Lw, Lv, Lm)), indexing="ij"))
        self._combo_levels = grid.reshape(4, -1).T  # [combos, 4], combination order
        self._subsets = np.array(
            [[(m >> i) & 1 for i in range(4)] for m in range(1, 16)], dtype=float
        )  # the 15 non-empty sets of firing factors
        self.fire = [np.full(n, 0.01) for n in (Lr, Lw, Lv, Lm)]

    @property
    def steps(self) -> int:
        """Steps counted."""
        return sum(self.event_n)

    def observe(self, state: int, action: int, step: Step) -> None:
        """Count one step."""
        d, c, r, w, _, _, ph, combo, b, vm = self._state[state]
        _, c2, r2, w2, _, _, ph2, _, _, vm2 = self._state[step.state]
        chain = self.chain
        chain["channel"][c][c2] += 1
        chain["road"][r][r2] += 1
        chain["weather"][w][w2] += 1
        chain["phase"][ph][ph2] += 1
        self.speed_object[action][vm][vm2] += 1
        self.event_n[combo] += 1
        self.event_k[combo] += step.event
        self.arrivals_sum[ph] += step.arrivals
        self.arrivals_n[ph] += 1
        if step.arrivals > self.arrivals_top:
            self.arrivals_top = step.arrivals
        self.top_reward = max(self.top_reward, abs(step.reward))
        if action == 0:
            if step.sent < d + step.arrivals:  # the link was full: its capacity shows
                self.packets_known[c] = step.sent
            if step.event:
                self.miss_penalty = -step.reward
            else:
                self.comm_reward[c] = step.reward
        elif step.event:
            self.radar_events += 1
            if step.missed:
                self.miss_penalty = -step.reward
            else:
                self.detected += 1
                self.detect_reward = step.reward / (b + 1)
        else:
            self.quiet_radar += 1
            if step.false_alarm:
                self.alarms += 1
                self.alarm_cost = -step.reward

    # -- estimates ---------------------------------------------------------------------------------

    def estimate(self, rng: np.random.Generator | None = None) -> Estimate:
        """The posterior mean of every number (``rng`` None), or one posterior sample."""
        a0 = self.prior

        def rows(counts: list[list[int]]) -> torch.Tensor:
            x = np.asarray(counts, dtype=np.float64) + a0
            if rng is None:
                out = x / x.sum(1, keepdims=True)
            else:
                out = np.stack([rng.dirichlet(row) for row in x])
            return torch.from_numpy(out)

        def beta(k: np.ndarray | np.float64, n: np.ndarray | np.float64) -> np.ndarray | float:
            a, b = k + a0, n - k + a0
            return a / (a + b) if rng is None else rng.beta(a, b)

        event = self.event_probabilities(rng)
        shape = np.asarray(self.arrivals_sum, float) + a0
        rate_n = np.asarray(self.arrivals_n, float) + a0
        rate = shape / rate_n if rng is None else rng.gamma(shape, 1.0 / rate_n)
        # a level whose capacity never showed may carry everything (optimism): the queue and
        # the most packets seen arriving at once
        top = self.D + max(self.arrivals_top, 1)
        packets = [known if known is not None else top for known in self.packets_known]
        # a gain never shown (a level's comm reward, the detection reward) may be as large as
        # the largest reward seen (optimism, so that the plan tries it); a cost never shown, 0
        gain = self.top_reward
        comm = [x if x is not None else gain for x in self.comm_reward]
        detect = self.detect_reward if self.detect_reward is not None else gain
        return Estimate(
            chains={name: rows(self.chain[name]) for name in self.CHAINS},
            speed_object=torch.stack([rows(self.speed_object[a]) for a in (0, 1)]),
            event=torch.from_numpy(event),
            rate=torch.from_numpy(np.asarray(rate, dtype=np.float64)),
            packets=torch.tensor(packets, dtype=torch.float64),
            comm_reward=torch.tensor(comm, dtype=torch.float64),
            miss_penalty=self.miss_penalty or 0.0,
            detect_reward=detect,
            alarm_cost=self.alarm_cost or 0.0,
            detection=float(beta(np.float64(self.detected), np.float64(self.radar_events))),
            false_alarm=float(beta(np.float64(self.alarms), np.float64(self.quiet_radar))),
        )

    GIBBS_SWEEPS = 10
    """Sweeps of the noisy-or sampler between two draws (it goes on from where the last stopped)."""
    GIBBS_MEAN_DRAWS = 20
    """Draws averaged for the noisy-or posterior mean (from a copy of the sampler's state)."""

    def advance(self, rng: np.random.Generator, sweeps: int) -> None:
        """Run the noisy-or sampler ``sweeps`` sweeps on, so that the posterior mean, drawn from
        where it stands, starts from a chain that has mixed (a learner that never draws from the
        posterior calls it before it asks for the mean; nothing to do without noisy-or)."""
        if self.noisy_or:
            k, n = np.asarray(self.event_k, float), np.asarray(self.event_n, float)
            for _ in range(sweeps):
                self.fire = self._gibbs(self.fire, k, n, rng)

    def event_probabilities(self, rng: np.random.Generator | None = None) -> np.ndarray:
        """[combinations] each combination's event probability: a posterior draw (``rng``), or
        the posterior mean."""
        k, n = np.asarray(self.event_k, float), np.asarray(self.event_n, float)
        if not self.noisy_or:
            a, b = k + self.prior, n - k + self.prior
            return a / (a + b) if rng is None else rng.beta(a, b)
        if rng is not None:
            for _ in range(self.GIBBS_SWEEPS):
                self.fire = self._gibbs(self.fire, k, n, rng)
            return self._combined(self.fire)
        # the mean: draws from a copy of the chain, on a generator fixed by the data (so that it
        # is the same whenever it is asked for)
        local = np.random.default_rng([int(n.sum()), int(k.sum())])
        fire = [f.copy() for f in self.fire]
        total: np.ndarray | float = 0.0
        for _ in range(self.GIBBS_MEAN_DRAWS):
            fire = self._gibbs(fire, k, n, local)
            total = total + self._combined(fire)
        return np.asarray(total / self.GIBBS_MEAN_DRAWS)

    def _combined(self, fire: list[np.ndarray]) -> np.ndarray:
        """[combinations] 1 − Π (1 − p_i[level]): noisy-or's event probabilities."""
        lv = self._combo_levels
        quiet = np.prod([1.0 - fire[i][lv[:, i]] for i in range(4)], axis=0)
        return 1.0 - quiet

    def _gibbs(
        self, fire: list[np.ndarray], k: np.ndarray, n: np.ndarray, rng: np.random.Generator
    ) -> list[np.ndarray]:
        """One sweep: the firing factors of every event given the probabilities (a multinomial
        over the non-empty sets, per combination), then each probability given the firings."""
        lv, sets = self._combo_levels, self._subsets
        p = np.stack([fire[i][lv[:, i]] for i in range(4)], 1)  # [combos, 4]
        logw = np.log(p) @ sets.T + np.log1p(-p) @ (1.0 - sets).T  # [combos, 15]
        w = np.exp(logw - logw.max(1, keepdims=True))
        counts = rng.multinomial(k.astype(np.int64), w / w.sum(1, keepdims=True))
        fired = counts @ sets  # [combos, 4]: events at which each factor fired
        out = []
        for i in range(4):
            size = len(fire[i])
            f = np.bincount(lv[:, i], weights=fired[:, i], minlength=size)
            trials = np.bincount(lv[:, i], weights=n, minlength=size)
            draw = rng.beta(f + self.prior, trials - f + self.prior)
            out.append(np.clip(draw, 1e-12, 1.0 - 1e-12))
        return out

    # -- the model ---------------------------------------------------------------------------------

    @property
    def _radix(self) -> torch.Tensor:
        """[6] the weight of each factor's level in a configuration's index."""
        radix = [1] * 6
        for i in range(4, -1, -1):
            radix[i] = radix[i + 1] * self.levels[i + 1]
        return torch.tensor(radix, dtype=torch.int64)

    @functools.cached_property
    def _config_index(self) -> tuple[torch.Tensor, ...]:
        """Per configuration f: (channel level, event combination, b, phase)."""
        nf = math.prod(self.levels)
        per = [self._state[f] for f in range(nf)]  # d = 0: the first F states
        return tuple(torch.tensor([p[i] for p in per]) for i in (1, 7, 8, 6))

    def tables(self, est: Estimate) -> ModelTables:
        """The per-configuration tables of the model ``est`` describes."""
        ch = est.chains
        F = torch.stack(
            [
                functools.reduce(
                    torch.kron,
                    (ch["channel"], ch["road"], ch["weather"], est.speed_object[a], ch["phase"]),
                )
                for a in (0, 1)
            ]
        )
        c, combo, b, phase = self._config_index
        e = est.event[combo]
        pd, pfa = est.detection, est.false_alarm
        r_comm = est.comm_reward[c]
        detect = est.detect_reward * (b.to(torch.float64) + 1.0)
        R0 = (1.0 - e) * r_comm - e * est.miss_penalty
        R1 = e * (pd * detect - (1.0 - pd) * est.miss_penalty) - (1.0 - e) * pfa * est.alarm_cost
        zeros = torch.zeros_like(e)
        return ModelTables(
            levels=tuple(self.levels),
            radix=self._radix,
            F=F,
            event=e,
            comm_reward=r_comm,
            detect_reward=detect,
            R=torch.stack([R0, R1]),
            R2=squared_reward(e, r_comm, detect, pd, pfa, est.miss_penalty, est.alarm_cost),
            missed=torch.stack([e, e * (1.0 - pd)]),
            false_alarm=torch.stack([zeros, (1.0 - e) * pfa]),
            nu=torch.stack([est.packets[c], zeros]),
            rate=est.rate[phase],
            upper=(),
        )

    def model(self, est: Estimate) -> FactoredModel:
        """The exact model of ``est`` (``tables``) on the factored operator."""
        return factored_model(self.tables(est), self.D, episode_steps=self.horizon)

    def state_dict(self) -> dict[str, Any]:
        """The counts (a checkpoint's entry)."""
        keep = (
            "chain",
            "speed_object",
            "event_n",
            "event_k",
            "arrivals_sum",
            "arrivals_n",
            "packets_known",
            "arrivals_top",
            "comm_reward",
            "miss_penalty",
            "detect_reward",
            "alarm_cost",
            "detected",
            "radar_events",
            "alarms",
            "quiet_radar",
            "top_reward",
            "fire",
        )
        out = {k: getattr(self, k) for k in keep}
        out["fire"] = [f.tolist() for f in self.fire]
        return out

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore ``state_dict``'s counts."""
        for k, v in state.items():
            setattr(self, k, v)
        self.fire = [np.asarray(f, dtype=float) for f in state["fire"]]
