"""The DFRC simulator's dynamics (MODEL.md): ``Dynamics`` steps a batch of state indices by table
look-ups; ``irdrc.core.env.DFRCEnv`` wraps it as a TorchRL environment, the fleet's simulator
steps each vehicle with it, and tabular Q-learning calls it directly. The state index is
``irdrc.core.states``'.

One step is a handful of table look-ups on that integer: every probability and reward that depends
on (action, factors) is precomputed once from the parameters, so the step costs the same few
kernels whatever the batch size.
"""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
import torch

from irdrc.core.params import Params
from irdrc.core.states import decode_state
from irdrc.core.tables import model_tables

if TYPE_CHECKING:
    from irdrc.core.tables import ModelTables


def fresh_seed() -> int:
    """A seed from OS entropy (leaves torch's global generator alone, unlike ``torch.seed()``)."""
    return int.from_bytes(os.urandom(8), "little") % 2**62


def poisson_cdf(rate: float) -> torch.Tensor:
    """CDF of Poisson(rate) at 0, 1, …, K, float64, with the last entry forced to 1.

    K is the first count ≥ 2·rate whose pmf is below 1e-17. For k ≥ 2·rate the pmf ratio
    rate/(k + 1) is below 1/2, so the upper tail P(A > K) ≤ pmf(K) < 1e-17: beneath what a float64
    uniform in [0, 1) resolves (2⁻⁵³ ≈ 1.1e-16), so inverse-CDF sampling loses nothing representable.
    """
    if rate == 0.0:
        return torch.ones(1, dtype=torch.float64)
    pmf, k = [], 0
    log_rate = math.log(rate)
    while True:
        p = math.exp(k * log_rate - rate - math.lgamma(k + 1))
        pmf.append(p)
        if k >= 2 * rate and p < 1e-17:
            break
        k += 1
    out = torch.tensor(pmf, dtype=torch.float64).cumsum(0)
    out[-1] = 1.0
    return out


@dataclass
class StepResult:
    """What one step of the dynamics produced, flat over the batch."""

    state: torch.Tensor  # int64, next state index
    reward: torch.Tensor  # float32
    event: torch.Tensor  # bool
    missed: torch.Tensor  # bool: event in comm mode, or undetected in radar mode
    sent: torch.Tensor  # int64, packets that left the queue
    dropped: torch.Tensor  # int64, packets lost to overflow
    capacity: torch.Tensor  # int64, ν: link capacity of this step (0 in radar mode)
    arrivals: torch.Tensor  # int64, A
    false_alarm: torch.Tensor  # bool: radar without an event raised an alarm
    phase: torch.Tensor | None = None  # int64: the traffic phase of the step (bursty arrivals)


class Dynamics:
    """MODEL.md's step on flat integer state tensors, driven by a ``torch.Generator``.

    Shared by ``DFRCEnv`` and the gymnasium wrappers, so all have the very same dynamics. It is
    table-driven (``irdrc.core.tables``): one step is a few look-ups on the state index, whatever
    the factors' levels. Uniforms per step, in order: event, arrivals, one per factor (c, r, w, v,
    m, then the traffic phase when arrivals are bursty), then one for the radar's detection / false
    alarm when the radar is imperfect (v1 draws exactly 7).

    Given a sequence of ``Params`` instead of one, the tables of every scenario are stacked and a
    ``group`` tensor passed to ``step`` picks each row's scenario: one batch then steps several
    scenarios at once (e.g. every p^v_1 value of a sweep). The scenarios must share the state space
    (queue capacity and factor levels); horizons are the caller's business.
    """

    def __init__(
        self, params: Params | Sequence[Params], device: torch.device | str = "cpu"
    ) -> None:
        scenarios = [params] if isinstance(params, Params) else list(params)
        if not scenarios:
            raise ValueError("Dynamics needs at least one Params")
        caps = {p.env.queue_capacity for p in scenarios}
        if len(caps) > 1:
            raise ValueError(
                f"scenarios stepped together must share env.queue_capacity; got {sorted(caps)}"
            )
        tabs = [model_tables(p) for p in scenarios]
        if len({t.levels for t in tabs}) > 1:
            raise ValueError(
                "scenarios stepped together must share the factors' levels (the state space); "
                f"got {sorted({t.levels for t in tabs})}"
            )
        self.scenarios = scenarios
        self.params = scenarios[0]
        self.num_groups = len(scenarios)
        self.device = torch.device(device)
        self.num_states = self.params.env.num_states
        self.queue_capacity = self.params.env.queue_capacity
        t0 = tabs[0]
        self.levels = t0.levels
        self.num_configs = nf = t0.num_configs
        self.num_phases = t0.levels[-1]
        # Factors drawn each step: c, r, w, v, m and, with bursty arrivals, the phase.
        self._nfac = 6 if self.num_phases > 1 else 5
        self._lmax = max(t0.levels[: self._nfac]) - 1
        self._imperfect = any(
            p.env.detection_prob < 1.0 or p.env.false_alarm_prob > 0.0 for p in scenarios
        )
        self._pow2 = nf & (nf - 1) == 0
        self._shift = nf.bit_length() - 1
        tables = [
            _scenario_tables(p, t, self._nfac, self._lmax)
            for p, t in zip(scenarios, tabs, strict=True)
        ]
        # Flat tables, one block per scenario; ``step`` offsets indices by group · block size.
        self.event_prob = torch.cat([t["event_prob"] for t in tables])  # [G·F]
        self.thresholds = torch.cat([t["thresholds"] for t in tables])  # [G·2F, factors, L − 1]
        self.reward = torch.cat([t["reward"] for t in tables])  # [G·2·2·F]: (a, event, f)
        self.capacity = torch.cat([t["capacity"] for t in tables])  # [G·2F]: (a, f)
        self.radix = t0.radix[: self._nfac].clone()
        self.detection = torch.tensor(
            [p.env.detection_prob for p in scenarios], dtype=torch.float64
        )
        self.false_alarm = torch.tensor(
            [p.env.false_alarm_prob for p in scenarios], dtype=torch.float64
        )
        self.miss_reward = torch.tensor([-p.reward.r3 for p in scenarios], dtype=torch.float32)
        self.alarm_reward = torch.tensor([-p.reward.r5 for p in scenarios], dtype=torch.float32)
        cdfs = [c for t in tables for c in t["arrival_cdf"]]  # G·P rows: (group, phase)
        self._shared_arrivals = all(torch.equal(c, cdfs[0]) for c in cdfs)
        width = max(len(c) for c in cdfs)
        # Padded with 1s, so a row's inverse CDF never goes past its own last entry.
        self.arrival_cdf = torch.stack(
            [torch.cat([c, torch.ones(width - len(c), dtype=torch.float64)]) for c in cdfs]
        )
        if self._shared_arrivals:
            self.arrival_cdf = self.arrival_cdf[0]

        # Observation of every state: [S, 6] float32 (7 with the traffic phase).
        self.obs = decode_state(torch.arange(self.num_states), self.levels).to(torch.float32)

        for name in (
            "event_prob",
            "thresholds",
            "radix",
            "reward",
            "capacity",
            "arrival_cdf",
            "obs",
            "detection",
            "false_alarm",
            "miss_reward",
            "alarm_reward",
        ):
            setattr(self, name, getattr(self, name).to(self.device))

    @property
    def num_uniforms(self) -> int:
        """Uniforms one step draws per row: event, arrivals, one per drawn factor, and the radar's
        detection / false alarm when it is imperfect."""
        return 2 + self._nfac + (1 if self._imperfect else 0)

    @property
    def next1(self) -> torch.Tensor:
        """[G·2F, 5]: P(factor′ = 1 | a, f) of two-level factors (v1's table)."""
        if self._lmax != 1:
            raise ValueError("next1 is defined only when every factor has two levels")
        return self.thresholds[..., 0]

    def reset_states(self, n: int, generator: torch.Generator) -> torch.Tensor:
        """n states drawn uniformly from all S (MODEL.md step 5)."""
        return torch.randint(0, self.num_states, (n,), generator=generator, device=self.device)

    def split(self, state: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(d, f): queue length and factor configuration of state indices."""
        if self._pow2:
            return state >> self._shift, state & (self.num_configs - 1)
        return state // self.num_configs, state % self.num_configs

    def next_configs(self, af: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        """The next factor configurations from rows ``af`` (action·F + f, offset by the group) of
        the thresholds and one uniform per drawn factor ``u`` [n, factors]."""
        thr = self.thresholds[af]
        nxt = u < thr[..., 0] if self._lmax == 1 else (u[..., None] < thr).sum(-1)
        return (nxt * self.radix).sum(-1)

    def step(
        self,
        state: torch.Tensor,
        action: torch.Tensor,
        generator: torch.Generator,
        group: torch.Tensor | None = None,
        uniforms: torch.Tensor | None = None,
    ) -> StepResult:
        """One step of MODEL.md from flat int64 ``state`` and ``action`` (0 comm, 1 radar).

        ``group`` (int64, like ``state``) is each row's scenario index when several were given;
        None means scenario 0 for every row. ``uniforms`` [n, ``num_uniforms``] (float64): the
        step's draws, in the class docstring's order, in place of drawing them from ``generator``.
        """
        n = state.shape[0]
        nf, nfac = self.num_configs, self._nfac
        # Uniforms per env in one call (see the class docstring). float64 so the Poisson tail is
        # sampled down to ~1e-16 (see ``poisson_cdf``).
        u = uniforms
        if u is None:
            u = torch.rand(
                n, self.num_uniforms, generator=generator, device=self.device, dtype=torch.float64
            )
        d, f = self.split(state)
        ev_idx, af, rw_idx = f, action * nf + f, action * (2 * nf) + f
        if group is not None:
            ev_idx = ev_idx + group * nf
            af = af + group * (2 * nf)
            rw_idx = rw_idx + group * (4 * nf)
        event = u[:, 0] < self.event_prob[ev_idx]
        f_next = self.next_configs(af, u[:, 2 : 2 + nfac])
        phase = f % self.num_phases if self.num_phases > 1 else None
        if self._shared_arrivals:
            arrivals = torch.searchsorted(self.arrival_cdf, u[:, 1].contiguous(), right=True)
        else:
            row = (group if group is not None else torch.zeros_like(f)) * self.num_phases
            if phase is not None:
                row = row + phase
            arrivals = torch.searchsorted(
                self.arrival_cdf[row], u[:, 1:2].contiguous(), right=True
            ).squeeze(-1)
        capacity = self.capacity[af]
        sent, d_next, dropped = queue_update(d, arrivals, capacity, self.queue_capacity)
        reward = self.reward[rw_idx + event * nf]
        missed = event & (action == 0)
        false_alarm = torch.zeros_like(event)
        if self._imperfect:
            g = group if group is not None else torch.zeros_like(f)
            radar, ud = action == 1, u[:, -1]
            undetected = event & radar & (ud >= self.detection[g])
            false_alarm = ~event & radar & (ud < self.false_alarm[g])
            missed = missed | undetected
            reward = torch.where(undetected, self.miss_reward[g], reward)
            reward = torch.where(false_alarm, self.alarm_reward[g], reward)
        return StepResult(
            state=d_next * nf + f_next,
            reward=reward,
            event=event,
            missed=missed,
            sent=sent,
            dropped=dropped,
            capacity=capacity,
            arrivals=arrivals,
            false_alarm=false_alarm,
            phase=phase,
        )


def step_shares(
    dyn: Dynamics, state: torch.Tensor, rho: torch.Tensor, generator: torch.Generator
) -> StepResult:
    """One step of MODEL.md § D from flat int64 ``state`` and radar shares ``rho`` (float, in
    [0, 1]) on one scenario's ``Dynamics``. Uniforms per step, in order: event, arrivals, one per
    factor, then detection (an event is seen w.p. q(ρ); without one a false alarm w.p. ρ·P_fa),
    the capacity's rounding (k + 1 w.p. frac ν(1 − ρ)) and the reaction (w.p. u(ρ): the factors
    move as after a radar step)."""
    from irdrc.core.share import reaction

    env = dyn.params.env
    n, nf, nfac = state.shape[0], dyn.num_configs, dyn._nfac
    u = torch.rand(n, 5 + nfac, generator=generator, device=dyn.device, dtype=torch.float64)
    rho = rho.to(torch.float64)
    seen = reaction(rho, env.sensing, env.dwell_gain)  # u(ρ) = q(ρ) / P_d
    d, f = dyn.split(state)
    event = u[:, 0] < dyn.event_prob[f]
    react = (u[:, -1] < seen).long()
    f_next = dyn.next_configs(react * nf + f, u[:, 2 : 2 + nfac])
    phase = f % dyn.num_phases if dyn.num_phases > 1 else None
    cdf = dyn.arrival_cdf if dyn._shared_arrivals else dyn.arrival_cdf[phase]
    if dyn._shared_arrivals:
        arrivals = torch.searchsorted(cdf, u[:, 1].contiguous(), right=True)
    else:
        arrivals = torch.searchsorted(cdf, u[:, 1:2].contiguous(), right=True).squeeze(-1)
    x = dyn.capacity[f].to(torch.float64) * (1.0 - rho)  # ν(c)(1 − ρ): comm's row of the table
    k = torch.floor(x + 1e-9)
    capacity = (k + (u[:, -2] < (x - k)).to(torch.float64)).to(torch.int64)
    sent, d_next, dropped = queue_update(d, arrivals, capacity, dyn.queue_capacity)
    ud = u[:, -3]
    detected = event & (ud < env.detection_prob * seen)
    false_alarm = ~event & (ud < rho * env.false_alarm_prob)
    comm = dyn.reward[f]  # [a = 0, event = 0, f]: r_comm of the channel
    reward = torch.where(
        event,
        torch.where(detected, dyn.reward[3 * nf + f], dyn.miss_reward[0]),
        ((1.0 - rho) * comm).to(torch.float32),
    )
    reward = torch.where(false_alarm, reward + dyn.alarm_reward[0], reward)
    return StepResult(
        state=d_next * nf + f_next,
        reward=reward,
        event=event,
        missed=event & ~detected,
        sent=sent,
        dropped=dropped,
        capacity=capacity,
        arrivals=arrivals,
        false_alarm=false_alarm,
        phase=phase,
    )


def _scenario_tables(params: Params, t: ModelTables, nfac: int, lmax: int) -> dict[str, Any]:
    """The flat look-up tables of one scenario (see ``Dynamics.step`` for their indexing)."""
    rw = params.reward
    nf = t.num_configs
    # P(level′ ≥ k | a, f) per drawn factor: [2F, factors, L − 1], padded with 0 (never drawn).
    thr = torch.zeros(2, nf, nfac, max(lmax, 1), dtype=torch.float64)
    for i in range(nfac):
        up = t.upper[i]  # [2, F, L_i − 1]
        thr[:, :, i, : up.shape[-1]] = up
    # Reward of eq. (3) with a perfect radar: [a, event, f], flattened on (a·2F + event·F + f);
    # an imperfect radar's misses and false alarms are applied in ``step``.
    reward = torch.zeros(2, 2, nf, dtype=torch.float64)
    reward[0, 0] = t.comm_reward
    reward[0, 1] = -rw.r3
    reward[1, 1] = t.detect_reward
    rates = params.env.bursty.rates if params.env.bursty else (params.env.arrival_rate,)
    return {
        "event_prob": t.event,
        "thresholds": thr.reshape(2 * nf, nfac, -1),
        "reward": reward.reshape(-1).to(torch.float32),
        "capacity": t.nu.reshape(-1).to(torch.int64),  # ν: (a·F + f)
        "arrival_cdf": [poisson_cdf(r) for r in rates],
    }


def observation_high(params: Params) -> torch.Tensor:
    """[6] (or [7] with a traffic phase) float32: the largest value of each observation entry,
    (D, L_c − 1, L_r − 1, L_w − 1, L_v − 1, L_m − 1[, L_phase − 1]) — what the agents' ``scale``
    encoding divides by, so each factor is normalised by its own levels."""
    levels = params.env.factor_levels
    top = [params.env.queue_capacity, *(n - 1 for n in levels[:5])]
    if levels[5] > 1:
        top.append(levels[5] - 1)
    return torch.tensor(top, dtype=torch.float32)


def checked_actions(action: torch.Tensor, name: str = "action") -> torch.Tensor:
    """``action`` as int64 if every entry is 0 (communication) or 1 (radar), else a ``ValueError``
    naming ``name`` and the first values refused.

    Floating-point 0.0 / 1.0 are accepted; 0.5, 1.7, −1 or 2 are not (they would index the tables
    out of their meaning)."""
    bad = (action != 0) & (action != 1)
    if bool(bad.any()):
        raise ValueError(
            f"{_shown(name, action[bad].tolist())} must be 0 (communication) or 1 (radar)"
        )
    return action.to(torch.int64)


def binary_actions(values: Any, name: str = "action") -> torch.Tensor:
    """Actions from outside (a user's policy, a trainer's step): numbers, each 0 or 1
    (``checked_actions``); a bool or a string is refused naming ``name``, never cast."""
    a = np.asarray(values)
    if a.dtype.kind not in "iuf":
        raise ValueError(f"{_shown(name, a.tolist())} must be 0 (communication) or 1 (radar)")
    return checked_actions(torch.from_numpy(a), name)


def _shown(name: str, values: Any) -> str:
    """``action 0.5`` or ``actions [0.5, 2.0, …]`` (the first three) for a message."""
    if not isinstance(values, list):
        return f"{name} {values!r}"
    return f"{name} {values[0]!r}" if len(values) == 1 else f"{name}s {values[:3]}"


def checked_shares(env: Any, action: torch.Tensor) -> torch.Tensor:
    """The radar shares (float64) of ``levels`` / ``continuous`` actions of ``env`` (an
    ``EnvParams``); a value out of range is a ``ValueError``, never clipped."""
    if env.actions == "levels":
        top = env.levels - 1
        bad = (action != action.round()) | (action < 0) | (action > top)
        if bool(bad.any()):
            raise ValueError(
                f"action must be a level in 0 … {top} (radar share level / {top}); got "
                f"{action[bad][:3].tolist()}"
            )
        return action.to(torch.float64) / top
    bad = ~((action >= 0) & (action <= 1))  # NaN too
    if bool(bad.any()):
        raise ValueError(f"action must be a radar share in [0, 1]; got {action[bad][:3].tolist()}")
    return action.to(torch.float64)


def queue_update(
    d: torch.Tensor, arrivals: torch.Tensor, capacity: torch.Tensor, queue_capacity: int
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """MODEL.md step 3: (sent, d′, dropped) from queue d, arrivals A and link capacity ν.

    Packets arriving during the step may leave in it: sent = min(d + A, ν),
    d′ = min(D, d + A − sent), dropped = d + A − sent − d′.
    """
    total = d + arrivals
    sent = torch.minimum(total, capacity)
    rest = total - sent
    d_next = rest.clamp(max=queue_capacity)
    return sent, d_next, rest - d_next
