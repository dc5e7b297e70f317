"""The DFRC simulator: MODEL.md as a natively batched TorchRL environment.

State indexing (shared with the exact model and every policy table)::

    s = d·32 + c·16 + r·8 + w·4 + v·2 + m        (0 ≤ s < (D + 1)·32)

so ``s & 31`` holds the five Markov factors (channel in bit 4 … object in bit 0), ``s & 15`` the
four event factors, and ``s >> 5`` the queue length d.

One step is a handful of table look-ups on that integer: every probability and reward that depends
on (action, factors) is precomputed once from the parameters, so the step costs the same few
kernels whatever the batch size.
"""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from dataclasses import dataclass

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Bounded, Categorical, Composite, Unbounded
from torchrl.envs import EnvBase

from irdrc.core.params import EVENT_FACTORS, Params

# Bit of each Markov factor in the state index, in MARKOV_FACTORS order (c, r, w, v, m).
FACTOR_BITS = (4, 3, 2, 1, 0)
NUM_FACTOR_CONFIGS = 32


def fresh_seed() -> int:
    """A seed from OS entropy (leaves torch's global generator alone, unlike ``torch.seed()``)."""
    return int.from_bytes(os.urandom(8), "little") % 2**62


def state_index(d, c, r, w, v, m):
    """State index of (d, c, r, w, v, m); works on ints and integer tensors alike."""
    return d * 32 + c * 16 + r * 8 + w * 4 + v * 2 + m


def decode_state(s: torch.Tensor) -> torch.Tensor:
    """Integer tensor of state indices → [..., 6] integer tensor (d, c, r, w, v, m)."""
    cols = [s >> 5] + [(s >> b) & 1 for b in FACTOR_BITS]
    return torch.stack(cols, dim=-1)


def event_probability(params: Params) -> torch.Tensor:
    """P(event | r, w, v, m) for the 16 event-factor configurations (index r·8 + w·4 + v·2 + m).

    ``noisy_or``: 1 − Π(1 − p^i_{s_i});  ``sum``: min(1, Σ p^i_{s_i}) (MODEL.md step 1).
    """
    env = params.env
    p = torch.tensor([env.p0.as_tuple(), env.p1.as_tuple()], dtype=torch.float64)  # [j, i]
    cfg = torch.arange(16)
    bits = torch.stack([(cfg >> b) & 1 for b in (3, 2, 1, 0)], dim=-1)  # r, w, v, m
    per_factor = p[bits, torch.arange(len(EVENT_FACTORS))]  # [16, 4]
    if env.event_model == "noisy_or":
        return 1.0 - torch.prod(1.0 - per_factor, dim=-1)
    return per_factor.sum(-1).clamp(max=1.0)


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
    missed: torch.Tensor  # bool: event while in comm mode
    sent: torch.Tensor  # int64, packets that left the queue
    dropped: torch.Tensor  # int64, packets lost to overflow
    capacity: torch.Tensor  # int64, ν: link capacity of this step (0 in radar mode)
    arrivals: torch.Tensor  # int64, A


class Dynamics:
    """MODEL.md's step on flat integer state tensors, driven by a ``torch.Generator``.

    Shared by ``DFRCEnv`` and the gymnasium wrapper, so both have the very same dynamics.

    Given a sequence of ``Params`` instead of one, the tables of every scenario are stacked and a
    ``group`` tensor passed to ``step`` picks each row's scenario: one batch then steps several
    scenarios at once (e.g. every p^v_1 value of a sweep). The scenarios must share the queue capacity
    (hence the state space); horizons are the caller's business.
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
        self.scenarios = scenarios
        self.params = scenarios[0]
        self.num_groups = len(scenarios)
        self.device = torch.device(device)
        self.num_states = self.params.env.num_states
        self.queue_capacity = self.params.env.queue_capacity
        tables = [_scenario_tables(p) for p in scenarios]
        # Flat tables, one block per scenario; ``step`` offsets indices by group · block size.
        self.event_prob = torch.cat([t["event_prob"] for t in tables])
        self.next1 = torch.cat([t["next1"] for t in tables])
        self.reward = torch.cat([t["reward"] for t in tables])
        self.capacity = torch.cat([t["capacity"] for t in tables])
        self.factor_weights = torch.tensor([1 << b for b in FACTOR_BITS])
        cdfs = [t["arrival_cdf"] for t in tables]
        self._shared_arrivals = all(torch.equal(c, cdfs[0]) for c in cdfs)
        width = max(len(c) for c in cdfs)
        # Padded with 1s, so a row's inverse CDF never goes past its own last entry.
        self.arrival_cdf = torch.stack(
            [torch.cat([c, torch.ones(width - len(c), dtype=torch.float64)]) for c in cdfs]
        )
        if self._shared_arrivals:
            self.arrival_cdf = self.arrival_cdf[0]

        # Observation of every state: [S, 6] float32.
        self.obs = decode_state(torch.arange(self.num_states)).to(torch.float32)

        for name in (
            "event_prob",
            "next1",
            "factor_weights",
            "reward",
            "capacity",
            "arrival_cdf",
            "obs",
        ):
            setattr(self, name, getattr(self, name).to(self.device))

    def reset_states(self, n: int, generator: torch.Generator) -> torch.Tensor:
        """n states drawn uniformly from all (D + 1)·32 (MODEL.md step 5)."""
        return torch.randint(0, self.num_states, (n,), generator=generator, device=self.device)

    def step(
        self,
        state: torch.Tensor,
        action: torch.Tensor,
        generator: torch.Generator,
        group: torch.Tensor | None = None,
    ) -> StepResult:
        """One step of MODEL.md from flat int64 ``state`` and ``action`` (0 comm, 1 radar).

        ``group`` (int64, like ``state``) is each row's scenario index when several were given;
        None means scenario 0 for every row.
        """
        n = state.shape[0]
        # 7 uniforms per env in one call: event, arrivals, then the 5 factor chains. float64 so the
        # Poisson tail is sampled down to ~1e-16 (see ``poisson_cdf``).
        u = torch.rand(n, 7, generator=generator, device=self.device, dtype=torch.float64)
        f = state & 31
        ev_idx, af, rw_idx = f & 15, action * NUM_FACTOR_CONFIGS + f, action * 64 + f
        cap_idx = action * 2 + (f >> 4)
        if group is not None:
            ev_idx = ev_idx + group * 16
            af = af + group * (2 * NUM_FACTOR_CONFIGS)
            rw_idx = rw_idx + group * 128
            cap_idx = cap_idx + group * 4
        event = u[:, 0] < self.event_prob[ev_idx]
        nxt = u[:, 2:] < self.next1[af]
        f_next = (nxt * self.factor_weights).sum(-1)
        if group is None or self._shared_arrivals:
            cdf = self.arrival_cdf if self._shared_arrivals else self.arrival_cdf[0]
            arrivals = torch.searchsorted(cdf, u[:, 1].contiguous(), right=True)
        else:
            arrivals = torch.searchsorted(
                self.arrival_cdf[group], u[:, 1:2].contiguous(), right=True
            ).squeeze(-1)
        capacity = self.capacity[cap_idx]
        sent, d_next, dropped = queue_update(state >> 5, arrivals, capacity, self.queue_capacity)
        reward = self.reward[rw_idx + event * 32]
        return StepResult(
            state=d_next * 32 + f_next,
            reward=reward,
            event=event,
            missed=event & (action == 0),
            sent=sent,
            dropped=dropped,
            capacity=capacity,
            arrivals=arrivals,
        )


def _scenario_tables(params: Params) -> dict[str, torch.Tensor]:
    """The flat look-up tables of one scenario (see ``Dynamics.step`` for their indexing)."""
    env, rw = params.env, params.reward
    f = torch.arange(NUM_FACTOR_CONFIGS)
    bits = torch.stack([(f >> b) & 1 for b in FACTOR_BITS], dim=-1)  # [32, 5]: c r w v m

    # P(factor′ = 1 | action, factors): [2, 32, 5], flattened on (action·32 + f).
    g = torch.tensor(env.stay_good.as_tuple(), dtype=torch.float64)
    h = torch.tensor(env.stay_bad.as_tuple(), dtype=torch.float64)
    next1 = torch.where(bits == 1, h, 1.0 - g)
    next1 = torch.stack([next1, next1.clone()])
    if env.radar_reaction:
        react = bits[:, 4] == 1  # radar with an object nearby
        next1[1, react, 3] = 0.0  # v′ = 0
        next1[1, react, 4] = 1.0 - env.reaction_clear  # m′ = 0 w.p. reaction_clear

    # Reward of eq. (3): [a, event, f] flattened on (a·64 + event·32 + f).
    b = bits[:, 1:].sum(-1).to(torch.float64)
    reward = torch.zeros(2, 2, NUM_FACTOR_CONFIGS, dtype=torch.float64)
    reward[0, 0] = torch.where(bits[:, 0] == 0, rw.r1, rw.r2)
    reward[0, 1] = -rw.r3
    reward[1, 1] = rw.r4 * (b + 1.0)
    return {
        "event_prob": event_probability(params),  # P(event | f & 15)
        "next1": next1.reshape(2 * NUM_FACTOR_CONFIGS, 5),
        "reward": reward.reshape(-1).to(torch.float32),
        # Link capacity ν: [a, c] flattened on (a·2 + c).
        "capacity": torch.tensor([env.packets_good, env.packets_bad, 0, 0]),
        "arrival_cdf": poisson_cdf(env.arrival_rate),
    }


def checked_actions(action: torch.Tensor) -> torch.Tensor:
    """``action`` as int64 if every entry is 0 (communication) or 1 (radar), else a ``ValueError``.

    Floating-point 0.0 / 1.0 are accepted; 0.5, 1.7, −1 or 2 are not (they would index the tables
    out of their meaning)."""
    bad = (action != 0) & (action != 1)
    if bool(bad.any()):
        raise ValueError(
            f"action must be 0 (communication) or 1 (radar); got {action[bad][:3].tolist()}"
        )
    return action.to(torch.int64)


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


class DFRCEnv(EnvBase):
    """The iRDRC radar/communication mode-selection environment of MODEL.md, natively batched.

    Stateless in the TorchRL sense: the state index travels in the tensordict (``"state"``), so a
    step can start from any hand-set state, and partial resets touch only the masked rows.

    Keys (B = batch shape; S = (D + 1)·32 states):

    - ``observation`` float32 [B, 6]: (d, c, r, w, v, m), raw values (d in 0 … D, flags 0/1).
    - ``state`` int64 [B]: the state index (see module docstring), for tabular methods.
    - ``step_count`` int64 [B, 1]: steps taken this episode; the episode is truncated at
      ``env.horizon``.
    - ``action`` int64 [B]: 0 = communication, 1 = radar.
    - ``reward`` float32 [B, 1]; ``done`` = ``truncated`` (time limit), ``terminated`` always False.
    - per-step info, describing the transition that led to this observation (zero after reset):
      ``event`` bool [B] (an unexpected event occurred), ``missed`` bool [B] (it occurred in comm
      mode), ``sent`` int64 [B] (packets transmitted), ``dropped`` int64 [B] (packets lost to
      overflow), ``capacity`` int64 [B] (link capacity ν of the step: ν1/ν2 in comm mode, 0 in radar).

    Example:
        >>> env = DFRCEnv(Params(), batch_size=[1024], seed=0)
        >>> td = env.rollout(400)            # random actions
        >>> td["next", "reward"].shape
        torch.Size([1024, 400, 1])

    Args:
        params: the model (``Params()`` is the paper scenario).
        batch_size: batch shape; ``[]`` for a single env. An int N means ``[N]``.
        device: torch device for state, tables and the generator.
        seed: seed of the env's generator (``set_seed`` reseeds it).
    """

    def __init__(
        self,
        params: Params | None = None,
        batch_size: int | torch.Size | tuple | list = (),
        device: torch.device | str = "cpu",
        seed: int | None = None,
    ) -> None:
        if isinstance(batch_size, int):
            batch_size = (batch_size,)
        batch_size = torch.Size(batch_size)
        if any(n < 1 for n in batch_size):
            raise ValueError(f"batch_size={list(batch_size)} must have positive dimensions")
        super().__init__(device=device, batch_size=batch_size)
        self.params = params if params is not None else Params()
        self.dynamics = Dynamics(self.params, self.device)
        self._n = batch_size.numel()
        self.rng = torch.Generator(device=self.device)
        self._make_specs()
        self.set_seed(seed if seed is not None else fresh_seed())

    def _make_specs(self) -> None:
        env = self.params.env
        b = self.batch_size
        dev = self.device
        high = torch.tensor([env.queue_capacity, 1, 1, 1, 1, 1], dtype=torch.float32)
        max_cap = max(env.packets_good, env.packets_bad)
        self.observation_spec = Composite(
            observation=Bounded(
                low=torch.zeros(*b, 6, device=dev),
                high=high.to(dev).expand(*b, 6).clone(),
                shape=(*b, 6),
                dtype=torch.float32,
                device=dev,
            ),
            state=Categorical(self.dynamics.num_states, shape=b, dtype=torch.int64, device=dev),
            step_count=Bounded(0, env.horizon, shape=(*b, 1), dtype=torch.int64, device=dev),
            event=Categorical(2, shape=b, dtype=torch.bool, device=dev),
            missed=Categorical(2, shape=b, dtype=torch.bool, device=dev),
            sent=Bounded(0, max_cap, shape=b, dtype=torch.int64, device=dev),
            dropped=Unbounded(shape=b, dtype=torch.int64, device=dev),
            capacity=Bounded(0, max_cap, shape=b, dtype=torch.int64, device=dev),
            shape=b,
            device=dev,
        )
        self.action_spec = Categorical(2, shape=b, dtype=torch.int64, device=dev)
        self.reward_spec = Unbounded(shape=(*b, 1), dtype=torch.float32, device=dev)
        self.done_spec = Composite(
            done=Categorical(2, shape=(*b, 1), dtype=torch.bool, device=dev),
            terminated=Categorical(2, shape=(*b, 1), dtype=torch.bool, device=dev),
            truncated=Categorical(2, shape=(*b, 1), dtype=torch.bool, device=dev),
            shape=b,
            device=dev,
        )

    def _set_seed(self, seed: int | None) -> None:
        if seed is None:
            seed = fresh_seed()
        self.rng.manual_seed(int(seed))

    def _out(
        self,
        state: torch.Tensor,
        steps: torch.Tensor,
        info: StepResult | None,
        truncated: torch.Tensor,
        reward: torch.Tensor | None = None,
    ) -> TensorDict:
        b = self.batch_size
        if info is None:
            zeros = torch.zeros(b, dtype=torch.int64, device=self.device)
            falses = torch.zeros(b, dtype=torch.bool, device=self.device)
            event = missed = falses
            sent = dropped = capacity = zeros
        else:
            event, missed = info.event.view(b), info.missed.view(b)
            sent, dropped, capacity = info.sent.view(b), info.dropped.view(b), info.capacity.view(b)
        truncated = truncated.view(*b, 1)
        out = {
            "observation": self.dynamics.obs[state].view(*b, 6),
            "state": state.view(b),
            "step_count": steps.view(*b, 1),
            "event": event,
            "missed": missed,
            "sent": sent,
            "dropped": dropped,
            "capacity": capacity,
            "done": truncated,
            "terminated": torch.zeros_like(truncated),
            "truncated": truncated,
        }
        if reward is not None:
            out["reward"] = reward.view(*b, 1)
        return TensorDict(out, batch_size=b, device=self.device)

    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs) -> TensorDict:
        # Fresh values for every row; torchrl keeps only the rows the "_reset" mask selects.
        state = self.dynamics.reset_states(self._n, self.rng)
        steps = torch.zeros(self._n, dtype=torch.int64, device=self.device)
        return self._out(state, steps, None, torch.zeros_like(steps, dtype=torch.bool))

    def _step(self, tensordict: TensorDictBase) -> TensorDict:
        state, action = tensordict.get("state", None), tensordict.get("action", None)
        if state is None or tensordict.get("step_count", None) is None:
            raise ValueError(
                "DFRCEnv.step needs the 'state' and 'step_count' that reset() returns: call "
                "env.reset() first (or set them by hand)"
            )
        if action is None:
            raise ValueError("DFRCEnv.step needs an 'action': 0 (communication) or 1 (radar)")
        state, action = state.reshape(-1), checked_actions(action.reshape(-1))
        if state.dtype.is_floating_point or bool(
            ((state < 0) | (state >= self.dynamics.num_states)).any()
        ):
            bad = state[(state < 0) | (state >= self.dynamics.num_states)][:3].tolist()
            raise ValueError(
                f"state must hold integer state indices in [0, {self.dynamics.num_states}); "
                f"got {bad or state.dtype}"
            )
        steps = tensordict.get("step_count").reshape(-1) + 1
        res = self.dynamics.step(state, action, self.rng)
        truncated = steps >= self.params.env.horizon
        return self._out(res.state, steps, res, truncated, res.reward)

    @property
    def num_states(self) -> int:
        """Number of states, (D + 1)·32."""
        return self.dynamics.num_states
