"""The Lagrangian DQN's final policy, chosen by measured rates alone.

The learned heads give Q_J (objective) and Q_C (cost: missed − m*·event) per state and action; the
greedy table of Q_J − μ·Q_C changes one state at a time as μ grows (``greedy_path``). The search
finds, by long-run Monte-Carlo measurements on the simulator (``irdrc.core.evaluate.long_run``,
common random numbers across candidates, the signals' rates per state and action pooled over
every measurement), the two neighbouring tables on either side of the
miss-detection target, and randomises between them in the one state where they differ — the
shape of the exact LP optimum. A confirmation re-measures the result on fresh random numbers
(the search keeps what read low by chance), and a second family of tables, ranked by each
state's *measured* data per missed event in comm (``rate_order``), gives a second pair of
neighbours where the heads misorder states — the learned heads resolve the rare events of one
state poorly, the measured rates do not. The exact model never steers the choice; every
measurement step is counted.
"""

from __future__ import annotations

import bisect
import math
from collections.abc import Callable
from typing import Any

import torch

from irdrc.agents.configs import SearchConfig
from irdrc.core.evaluate import long_run
from irdrc.core.params import Params

SEARCH_FLOOR = 1e-6
"""The search goes down the path no further than this fraction of the trained μ."""

MIXING_STEPS_PER_BLOCK = 1
"""The final policy's randomisation is searched on its log-odds within ±log(measure_steps / this):
a probability closer to 0 or 1 in a state the chain lingers in (a full queue) makes the chain mix
more slowly than a measurement block can see."""

CONFIRM_SEED_OFFSET = 104_729
"""The confirmation's random numbers: the search's seed plus this (independent of the search's)."""

PROBE_COMM = 0.1
"""The probe (one measurement before the ranking) communicates with this probability in every
state: mostly radar lets the queue fill, so the long-queue states where a comm step fills the link
are seen in comm too (a table's own measurements see comm only where the table communicates)."""

RATE_PRIOR_STEPS = 500.0
"""The ranking shrinks each state's measured missed events per comm step towards the average over
every state seen in comm, with the weight of this many comm steps: at the paper's rates (0.02 missed
events per comm step in the all-favourable states) a state seen 200 times in comm has missed about
4, too few to rank it by alone (``rate_order``)."""

MIX_TOLERANCE = 0.02
"""The randomisation's search stops once a measured miss detection at or below the target is
within this fraction of it (``FinalPolicySearch.mix``)."""


def greedy_path(q: torch.Tensor) -> tuple[list[float], list[torch.Tensor]]:
    """The greedy tables of Q_J − μ·Q_C as μ goes from 0 to ∞, from values ``q`` [S, 2, 2].

    Returns ``(breaks, tables)``: ``tables[k]`` is greedy on (breaks[k−1], breaks[k]) (breaks[−1]
    = 0), consecutive tables differ in exactly one state, ``len(tables) = len(breaks) + 1``.
    Ties go to comm, as in ``irdrc.agents.offpolicy.greedy_table``.
    """
    dj = q[:, 0, 0] - q[:, 0, 1]  # objective gain of comm over radar
    dc = q[:, 1, 0] - q[:, 1, 1]  # cost of comm over radar
    table = (dj < 0).long()  # μ = 0: greedy on Q_J (1 = radar)
    # State s switches at μ_s = dj/dc where the sign of dj − μ·dc changes for some μ > 0.
    switch = torch.where(dc != 0, dj / dc, torch.full_like(dj, math.inf))
    crosses = (switch > 0) & torch.isfinite(switch)
    order = sorted(crosses.nonzero().flatten().tolist(), key=lambda s: float(switch[s]))
    breaks, tables = [], [table.clone()]
    for s in order:
        table = table.clone()
        table[s] = 1 - table[s]
        breaks.append(float(switch[s]))
        tables.append(table)
    return breaks, tables


def path_index(breaks: list[float], mu: float) -> int:
    """The index of the table of ``greedy_path`` that is greedy at multiplier ``mu``."""
    return bisect.bisect_right(breaks, mu)


def rate_order(pool: dict[str, torch.Tensor], key: str) -> list[int]:
    """The states seen in comm in ``pool`` (per state and action sums, as ``long_run(...,
    by_state=True)`` returns them, summed over measurements), in the order the ranked family
    gives them to radar: ascending measured objective per comm step over missed events per comm
    step, the latter shrunk towards the average over every state seen in comm with the weight of
    ``RATE_PRIOR_STEPS`` comm steps (a state seen seldom has the average's rate, not its own few
    events'). Ties go to the lower state first."""
    n = pool["steps"][:, 0].double()
    seen = (n > 0).nonzero().flatten().tolist()
    if not seen:
        return []
    missed = pool["missed"][:, 0].double()
    average = float(missed.sum() / n.sum())
    gain = pool[key][:, 0].double() / n.clamp_min(1.0)
    risk = (missed + RATE_PRIOR_STEPS * average) / (n + RATE_PRIOR_STEPS)
    score = gain / risk.clamp_min(1e-12)
    return sorted(seen, key=lambda s: (float(score[s]), s))


def pooled(visits: torch.Tensor, pool: dict[str, torch.Tensor], signal: str) -> tuple[float, float]:
    """(miss detection, objective per step) of a policy from its ``visits`` [S, 2] per state and
    action, with each signal's expected value in (s, a) estimated from ``pool`` (sums over every
    step measured so far, of every policy: the rates given the state, which is the observation,
    and the action do not depend on the policy). The event noise of one measurement — events are
    rare — is averaged over all of them; only the visits are the policy's own."""
    seen = pool["steps"].clamp_min(1.0)
    event = (visits * pool["event"] / seen).sum()
    missed = (visits * pool["missed"] / seen).sum()
    objective = (visits * pool[signal] / seen).sum() / visits.sum()
    miss = float(missed / event) if float(event) > 0 else math.nan
    return miss, float(objective)


Pair = tuple[torch.Tensor | None, torch.Tensor]
"""Neighbouring tables (radar probabilities [S]): the one above the target (or None when the
other is the best found) and the one at or below it."""


class FinalPolicySearch:
    """The search of the final policy for one run (see the module docstring).

    Args:
        q: the learned heads' values [S, 2, 2] (objective, cost) × (comm, radar).
        params: the scenario (measurements run on its simulator).
        mu: the trained multiplier (where the search starts on the path).
        target: the miss-detection target m*.
        signal: the objective's per-step signal (``sent``, ``reward``, ``capacity``).
        cfg: how to search.
        seed: the measurements' random numbers (the confirmation's are offset).
    """

    def __init__(
        self,
        q: torch.Tensor,
        params: Params,
        mu: float,
        target: float,
        signal: str,
        cfg: SearchConfig,
        seed: int,
    ) -> None:
        self.breaks, self.tables = greedy_path(q)
        self.params, self.mu, self.target, self.cfg, self.seed = params, mu, target, cfg, seed
        self.signal = signal
        self.rank = signal != "reward"  # radar earns reward too: no per-step trade to rank by
        self.steps = 0
        self.visits: dict[tuple[bool, bytes], torch.Tensor] = {}
        n = len(self.tables[0])
        self.pool = {  # one pool per stream: the confirmation's numbers stay independent
            fresh: {
                k: torch.zeros(n, 2, dtype=torch.float64)
                for k in ("steps", "event", "missed", signal)
            }
            for fresh in (False, True)
        }

    @property
    def last(self) -> int:
        """The index of the path's safest table."""
        return len(self.tables) - 1

    def table(self, k: int) -> torch.Tensor:
        """The path's table ``k`` as radar probabilities."""
        return self.tables[k].double()

    # -- measurements ------------------------------------------------------------------------------

    def rates(self, p_radar: torch.Tensor, fresh: bool = False) -> tuple[float, float]:
        """Estimated (miss detection, objective) of a policy: its measured visits per state and
        action (each policy measured once per stream: the search's, or with ``fresh`` the
        confirmation's) weighted by the signals' rates per state and action pooled over every
        measurement of that stream so far (``pooled``)."""
        key = (fresh, p_radar.double().numpy().tobytes())
        if key not in self.visits:
            cfg = self.cfg
            ev = long_run(
                self.params,
                p_radar.double(),
                envs=cfg.measure_envs,
                steps=cfg.measure_steps,
                burn_in=cfg.measure_burn_in,
                max_blocks=cfg.measure_max_blocks,
                seed=self.seed + 7919 + (CONFIRM_SEED_OFFSET if fresh else 0),
                by_state=True,
            )
            self.steps += ev.steps
            sums = ev.by_state
            assert sums is not None  # measured by_state
            for k, total in self.pool[fresh].items():
                total += sums[k]
            self.visits[key] = sums["visits"]
        return pooled(self.visits[key], self.pool[fresh], self.signal)

    def miss(self, p_radar: torch.Tensor, fresh: bool = False) -> float:
        """Measured miss detection of a policy (NaN when its measurement saw no event)."""
        return self.rates(p_radar, fresh)[0]

    def meets(self, miss: float) -> bool:
        """Whether a measured miss detection shows the target met: at or below it (a measurement
        that saw no event, NaN, shows nothing and does not)."""
        return miss <= self.target

    def bracket(
        self, lo: int, hi: int, fresh: bool, miss_of: Callable[[int, bool], float] | None = None
    ) -> tuple[int, int]:
        """Bisection to neighbours: miss(lo) > target ≥ miss(hi) on entry and on return."""
        miss_of = miss_of or (lambda k, f: self.miss(self.table(k), f))
        while hi - lo > 1:
            mid = (lo + hi) // 2
            if not self.meets(miss_of(mid, fresh)):
                lo = mid
            else:
                hi = mid
        return lo, hi

    # -- the search ------------------------------------------------------------------------------

    def path_search(self) -> tuple[torch.Tensor | None, torch.Tensor, bool, float | None]:
        """The path's neighbours (above the target or None, at or below it — or the safest end of
        the path when no table meets the target), the stream that decides, and the multiplier of
        the switch.

        From the table greedy at μ: if it meets the target, down the path (μ ÷ ``search_span`` at
        a time) while tables meet it and their measured objective grows; if not, up to
        μ·``search_span`` and then the safest end. A bisection finds the neighbours; with
        ``confirm`` the one kept is measured again on fresh numbers, and while that is above the
        target the search climbs the path (doubling its steps, then bisecting) on them."""
        cfg, mu = self.cfg, self.mu
        k0 = path_index(self.breaks, mu)
        lo: int | None
        if self.meets(self.miss(self.table(k0))):
            lo, hi, m = None, k0, mu
            while hi > 0 and m > mu * SEARCH_FLOOR:
                m /= cfg.search_span
                k = path_index(self.breaks, m)
                if k == hi:
                    continue
                if not self.meets(self.miss(self.table(k))):
                    lo = k
                    break
                if self.rates(self.table(k))[1] <= self.rates(self.table(hi))[1]:
                    break  # no more data lower down: the heads' differences there are noise
                hi = k
        else:
            lo, hi = k0, path_index(self.breaks, mu * cfg.search_span)
            if not self.meets(self.miss(self.table(hi))):
                hi = self.last  # beyond the range: the safest tables of the path
                if hi == lo or not self.meets(self.miss(self.table(hi))):
                    return None, self.table(hi), cfg.confirm, None
        if lo is not None:
            lo, hi = self.bracket(lo, hi, fresh=False)
        fresh = cfg.confirm
        if fresh and not self.meets(self.miss(self.table(hi), fresh)):
            # Kept because its measurement fell at or below the target, which noise alone can
            # do: climb the path on fresh numbers until a table meets it.
            step, lo = 1, hi
            while True:
                k = min(hi + step, self.last)
                if self.meets(self.miss(self.table(k), fresh)):
                    lo, hi = self.bracket(lo, k, fresh)
                    break
                if k == self.last:
                    return None, self.table(self.last), True, None
                lo, step = k, 2 * step
        if lo is None:
            return None, self.table(hi), fresh, None
        return self.table(lo), self.table(hi), fresh, self.breaks[lo]

    def promise(self, pair: Pair, fresh: bool) -> float:
        """The objective a mixture of the pair promises at the target, from their measured rates
        by linear interpolation in miss detection (−∞ when the safer table does not meet it)."""
        t_lo, t_hi = pair
        m_hi, j_hi = self.rates(t_hi, fresh)
        if t_lo is None:
            return j_hi if self.meets(m_hi) else -math.inf
        m_lo, j_lo = self.rates(t_lo, fresh)
        if not self.meets(m_hi):
            return -math.inf
        if self.meets(m_lo):
            return max(j_lo, j_hi)
        if math.isnan(m_lo):  # the riskier table's measurement saw no event: nothing to interpolate
            return j_hi
        w = (m_lo - self.target) / (m_lo - m_hi)  # the weight of t_hi that lands on the target
        return (1 - w) * j_lo + w * j_hi

    def rank_search(self, fresh: bool) -> tuple[Pair, int, int]:
        """Neighbours on either side of the target in the ranked family: the probe (comm with
        probability ``PROBE_COMM`` everywhere) is measured on the search's numbers, the states
        seen in comm by every measurement so far are ranked (``rate_order``), and table k of the
        family gives the first k of them to radar (communicating in the rest, radar elsewhere).
        A bisection on k (on the ``fresh`` stream) finds the pair; also the number of states the
        safer table communicates in, and the number ranked."""
        n = len(self.tables[0])
        self.rates(torch.full((n,), 1.0 - PROBE_COMM, dtype=torch.float64))
        order = rate_order(self.pool[False], self.signal)

        def ranked(k: int) -> torch.Tensor:
            t = torch.ones(n, dtype=torch.float64)
            t[order[k:]] = 0.0
            return t

        m = len(order)
        if self.meets(self.miss(ranked(0), fresh)):
            return (None, ranked(0)), m, m
        if not self.meets(self.miss(ranked(m), fresh)):
            return (None, ranked(m)), 0, m
        lo, hi = self.bracket(0, m, fresh, miss_of=lambda k, f: self.miss(ranked(k), f))
        return (ranked(lo), ranked(hi)), m - hi, m

    def mix(self, pair: Pair, fresh: bool) -> tuple[torch.Tensor, int | None, bool]:
        """The final radar probabilities: the safer table, randomised in the one state where the
        pair differs with the weight found on its log-odds by regula falsi (Illinois) on measured
        miss detection, keeping the side at or below the target; returns (probabilities, that
        state, whether it was mixed at all)."""
        t_lo, t_hi = pair
        if t_lo is None:
            return t_hi, None, False
        s = int((t_lo != t_hi).nonzero().flatten()[0])
        a_lo, a_hi = float(t_lo[s]), float(t_hi[s])

        def mixed(z: float) -> torch.Tensor:
            w = 1.0 / (1.0 + math.exp(-z))  # weight of t_hi's action in s
            p = t_hi.clone()
            p[s] = w * a_hi + (1 - w) * a_lo
            return p

        def excess(z: float) -> float:  # a measurement that saw no event counts as above the target
            m = self.miss(mixed(z), fresh)
            return math.inf if math.isnan(m) else m - self.target

        span = math.log(max(2.0, self.cfg.measure_steps / MIXING_STEPS_PER_BLOCK))
        z_lo, z_hi = -span, span
        f_hi = excess(z_hi)
        if f_hi > 0:
            return t_hi, s, False
        f_lo = excess(z_lo)
        if f_lo <= 0:
            return mixed(z_lo), s, True
        side, g_lo, g_hi = 0, f_lo, f_hi  # g: the secant's weights (Illinois halves a stale end)
        for _ in range(self.cfg.mix_steps):
            if f_hi >= -MIX_TOLERANCE * self.target:
                break
            z = z_hi - g_hi * (z_hi - z_lo) / (g_hi - g_lo)
            f = excess(z)
            if f > 0:
                z_lo, g_lo = z, f
                if side == -1:
                    g_hi /= 2
                side = -1
            else:
                z_hi, f_hi, g_hi = z, f, f
                if side == 1:
                    g_lo /= 2
                side = 1
        return mixed(z_hi), s, True

    def run(self) -> tuple[torch.Tensor, dict[str, Any]]:
        """The final [S, 2] policy (comm, radar probabilities) and facts about the search:
        ``path_tables``, ``measured_final_miss``, ``measurements``, ``measure_env_steps``,
        ``confirmed``, ``switch_state``, ``p_switch``, ``mu_switch``, and the ranked family's
        (``ranked``: whether its pair was kept, None where it is not tried; ``ranked_states``,
        ``rank_candidates``, ``path_promise``, ``rank_promise``)."""
        t_lo, t_hi, fresh, mu_switch = self.path_search()
        extra: dict[str, Any] = {"ranked": None}
        if self.rank:
            # Each pair is judged when found: by its promise at the target, then by the safer
            # table's miss detection (a path whose safest table misses the target loses).
            path = (self.promise((t_lo, t_hi), fresh), -self.miss(t_hi, fresh))
            pair, k, n = self.rank_search(fresh)
            rank = (self.promise(pair, fresh), -self.miss(pair[1], fresh))
            won = rank > path
            extra = {
                "ranked": won,
                "ranked_states": k,
                "rank_candidates": n,
                # −∞ (neither table of the pair meets the target) is written as None
                "path_promise": path[0] if math.isfinite(path[0]) else None,
                "rank_promise": rank[0] if math.isfinite(rank[0]) else None,
            }
            if won:
                (t_lo, t_hi), mu_switch = pair, None
        p, state, mixed = self.mix((t_lo, t_hi), fresh)
        facts = {
            "path_tables": len(self.tables),
            "measured_final_miss": self.miss(p, fresh),
            "measurements": len(self.visits),
            "measure_env_steps": self.steps,
            "confirmed": fresh,
            "switch_state": state,
            "p_switch": None if state is None else float(p[state]),
            **({"mu_switch": mu_switch} if mixed else {}),
            **extra,
        }
        return torch.stack([1 - p.double(), p.double()], -1), facts
