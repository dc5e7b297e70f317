"""The DFRC simulator as a natively batched TorchRL environment (``DFRCEnv``), on the batched
dynamics of ``irdrc.core.dynamics`` (whose docstring gives the state index)."""

from __future__ import annotations

from typing import Any

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Bounded, Categorical, Composite, Unbounded
from torchrl.envs import EnvBase

from irdrc.core.dynamics import (
    Dynamics,
    StepResult,
    checked_actions,
    checked_shares,
    fresh_seed,
    observation_high,
    step_shares,
)
from irdrc.core.params import Params


class DFRCEnv(EnvBase):
    """The iRDRC radar/communication mode-selection environment of MODEL.md, natively batched.

    Stateless in the TorchRL sense: the state index travels in the tensordict (``"state"``), so a
    step can start from any hand-set state, and partial resets touch only the masked rows.

    Keys (B = batch shape; S = (D + 1)·Π L states, v1: (D + 1)·32):

    - ``observation`` float32 [B, 6]: (d, c, r, w, v, m), raw levels (d in 0 … D, a factor in
      0 … L − 1; v1: flags 0/1); [B, 7] with the traffic phase last when arrivals are bursty. The
      spec's ``high`` is each entry's largest level (``observation_high``), which the agents'
      ``scale`` encoding divides by.
    - ``state`` int64 [B]: the state index (see module docstring), for tabular methods.
    - ``step_count`` int64 [B, 1]: steps taken this episode; the episode is truncated at
      ``env.horizon``.
    - ``action`` int64 [B]: 0 = communication, 1 = radar (``env.actions=binary``); with
      ``levels`` a level g in 0 … G − 1 (radar share g / (G − 1)); with ``continuous`` float32
      [B, 1], the radar share ρ in [0, 1] (MODEL.md § D).
    - ``reward`` float32 [B, 1]; ``done`` = ``truncated`` (time limit), ``terminated`` always False.
    - per-step info, describing the transition that led to this observation (zero after reset):
      ``event`` bool [B] (an unexpected event occurred), ``missed`` bool [B] (it occurred in comm
      mode), ``sent`` int64 [B] (packets transmitted), ``dropped`` int64 [B] (packets lost to
      overflow), ``capacity`` int64 [B] (link capacity ν of the step: ν1/ν2 in comm mode, 0 in radar),
      ``false_alarm`` bool [B] (radar without an event raised an alarm: P_fa, MODEL.md § B.3),
      and with bursty arrivals ``phase`` int64 [B] (the traffic phase the step's arrivals came from).
      ``missed`` also counts events the radar did not detect (P_d < 1).

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
        batch_size: int | torch.Size | tuple[int, ...] | list[int] = (),
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
        high = observation_high(self.params)
        width = high.shape[0]
        max_cap = int(self.dynamics.capacity.max())
        extra = {}
        if self.dynamics.num_phases > 1:
            extra["phase"] = Categorical(
                self.dynamics.num_phases, shape=b, dtype=torch.int64, device=dev
            )
        self.observation_spec = Composite(
            observation=Bounded(
                low=torch.zeros(*b, width, device=dev),
                high=high.to(dev).expand(*b, width).clone(),
                shape=(*b, width),
                dtype=torch.float32,
                device=dev,
            ),
            false_alarm=Categorical(2, shape=b, dtype=torch.bool, device=dev),
            **extra,
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
        if env.actions == "continuous":  # the radar share ρ of the step (MODEL.md § D)
            self.action_spec = Bounded(0.0, 1.0, shape=(*b, 1), dtype=torch.float32, device=dev)
        else:  # binary: 0 comm, 1 radar; levels: ρ = a / (G − 1)
            n = 2 if env.actions == "binary" else env.levels
            self.action_spec = Categorical(n, shape=b, dtype=torch.int64, device=dev)
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
            event = missed = false_alarm = falses
            sent = dropped = capacity = zeros
            phase: torch.Tensor | None = zeros
        else:
            event, missed = info.event.view(b), info.missed.view(b)
            sent, dropped, capacity = info.sent.view(b), info.dropped.view(b), info.capacity.view(b)
            false_alarm = info.false_alarm.view(b)
            phase = info.phase.view(b) if info.phase is not None else None
        truncated = truncated.view(*b, 1)
        out = {
            "observation": self.dynamics.obs[state].view(*b, -1),
            "state": state.view(b),
            "step_count": steps.view(*b, 1),
            "event": event,
            "missed": missed,
            "sent": sent,
            "dropped": dropped,
            "capacity": capacity,
            "false_alarm": false_alarm,
            "done": truncated,
            "terminated": torch.zeros_like(truncated),
            "truncated": truncated,
        }
        if self.dynamics.num_phases > 1 and phase is not None:
            out["phase"] = phase
        if reward is not None:
            out["reward"] = reward.view(*b, 1)
        return TensorDict(out, batch_size=b, device=self.device)

    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs: Any) -> TensorDict:
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
        state = state.reshape(-1)
        rho = None if self.params.env.actions == "binary" else self._shares(action.reshape(-1))
        if rho is None:  # the modes, checked before the states
            action = checked_actions(action.reshape(-1))
        if state.dtype.is_floating_point or bool(
            ((state < 0) | (state >= self.dynamics.num_states)).any()
        ):
            bad = state[(state < 0) | (state >= self.dynamics.num_states)][:3].tolist()
            raise ValueError(
                f"state must hold integer state indices in [0, {self.dynamics.num_states}); "
                f"got {bad or state.dtype}"
            )
        steps = tensordict.get("step_count").reshape(-1) + 1
        if rho is None:
            res = self.dynamics.step(state, action, self.rng)
        else:
            res = step_shares(self.dynamics, state, rho, self.rng)
        truncated = steps >= self.params.env.horizon
        return self._out(res.state, steps, res, truncated, res.reward)

    def _shares(self, action: torch.Tensor) -> torch.Tensor:
        """The radar shares of ``levels`` / ``continuous`` actions (``checked_shares``)."""
        return checked_shares(self.params.env, action)

    @property
    def num_states(self) -> int:
        """Number of states, (D + 1)·Π L (v1: (D + 1)·32)."""
        return self.dynamics.num_states
