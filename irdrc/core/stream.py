"""One vehicle's own stream (MODEL.md § E): the simulator's step for a single env row, one step at a
time, at the speed of plain Python.

``Dynamics.step`` costs the same few kernels whatever its batch, about 200 µs for a batch of one. A
vehicle that learns from its own stream steps one row at a time, so ``ScalarStep`` takes the
``Dynamics`` tables as Python lists and steps an integer state with Python arithmetic (a few µs).
Given the same uniforms it returns exactly what ``Dynamics.step`` returns (tests/test_stream.py holds
the two equal on every state and action of several scenarios): it is the same simulator. The
gymnasium env (``irdrc.core.gym``) steps with it too.

The uniforms are drawn from a ``torch.Generator`` one episode at a time: ``[horizon, k + 1]``, the
``k = Dynamics.num_uniforms`` columns of each step and, in row 0, one more for the reset that
starts the episode (a state drawn uniformly from all S, MODEL.md step 5). A stream checkpointed
between episodes is restored from its generator's state alone.
"""

from __future__ import annotations

from bisect import bisect_right
from typing import Any, NamedTuple

import torch

from irdrc.core.dynamics import Dynamics
from irdrc.core.params import Params


class Step(NamedTuple):
    """What one step of the stream produced (``Dynamics.StepResult`` for one row, as Python
    numbers)."""

    state: int
    reward: float
    event: bool
    missed: bool
    sent: int
    dropped: int
    false_alarm: bool
    arrivals: int


class ScalarStep:
    """MODEL.md's step for one state at a time: ``Dynamics``' tables (scenario 0) as Python lists and
    Python arithmetic, a few µs a step where ``Dynamics.step`` on one row costs ~200 µs. Given the
    same uniforms it returns exactly what ``Dynamics.step`` returns. Shared by ``VehicleStream``
    and the gymnasium env (``irdrc.core.gym``).

    Attributes:
        num_uniforms: uniforms one step reads (``Dynamics.num_uniforms``).
        num_configs, num_phases: F and the traffic phases.
    """

    def __init__(self, dyn: Dynamics) -> None:
        self.num_configs = dyn.num_configs
        self.num_phases = dyn.num_phases
        self.num_uniforms = dyn.num_uniforms
        self._D = dyn.queue_capacity
        self._event = dyn.event_prob.tolist()
        levels = dyn.levels[: dyn._nfac]
        # Each drawn factor's thresholds P(level′ ≥ k | a, f), k = 1 … L − 1 (Dynamics pads them
        # with zeros up to the largest L, which no uniform falls below).
        self._thr = [
            tuple(tuple(row[i][: levels[i] - 1]) for i in range(dyn._nfac))
            for row in dyn.thresholds.tolist()
        ]
        self._radix = tuple(int(r) for r in dyn.radix.tolist())
        self._reward = dyn.reward.tolist()  # the float32 values, as Python floats
        self._capacity = [int(c) for c in dyn.capacity.tolist()]
        cdf = dyn.arrival_cdf
        self._cdfs = [cdf.tolist()] if dyn._shared_arrivals else cdf.tolist()
        self._phases = dyn.num_phases if not dyn._shared_arrivals else 1
        self._imperfect = dyn._imperfect
        self._pd = float(dyn.detection[0])
        self._pfa = float(dyn.false_alarm[0])
        self._miss_reward = float(dyn.miss_reward[0])
        self._alarm_reward = float(dyn.alarm_reward[0])

    def transition(self, state: int, action: int, u: list[float]) -> Step:
        """MODEL.md's step from ``state`` with ``action`` and the step's uniforms ``u`` (in
        ``Dynamics.step``'s order: event, arrivals, each factor, the radar's draw)."""
        nf = self.num_configs
        d, f = divmod(state, nf)
        event = u[0] < self._event[f]
        af = action * nf + f
        f_next = 0
        for i, (thr, radix) in enumerate(zip(self._thr[af], self._radix, strict=False)):
            x = u[2 + i]
            f_next += sum(1 for t in thr if x < t) * radix
        cdf = self._cdfs[f % self._phases if self._phases > 1 else 0]
        arrivals = bisect_right(cdf, u[1])
        total = d + arrivals
        sent = min(total, self._capacity[af])
        rest = total - sent
        d_next = min(rest, self._D)
        reward = self._reward[action * 2 * nf + (nf if event else 0) + f]
        missed = event and action == 0
        false_alarm = False
        if self._imperfect and action == 1:
            ud = u[len(self._radix) + 2]
            if event and ud >= self._pd:
                missed, reward = True, self._miss_reward
            elif not event and ud < self._pfa:
                false_alarm, reward = True, self._alarm_reward
        return Step(
            d_next * nf + f_next, reward, event, missed, sent, rest - d_next, false_alarm, arrivals
        )

    def capacity(self, state: int, action: int) -> int:
        """ν of ``action`` in ``state`` (0 in radar mode)."""
        return self._capacity[action * self.num_configs + state % self.num_configs]


class VehicleStream:
    """One vehicle's trajectory: episodes of ``env.horizon`` steps, each from a uniform reset.

    Args:
        params: the scenario (binary actions: comm 0, radar 1).
        seed: the stream's generator seed.

    Attributes:
        num_states: S.
        horizon: steps per episode.
        state: the current state index (after ``reset``).
        steps_left: steps left in the current episode.
    """

    def __init__(self, params: Params, seed: int = 0) -> None:
        if params.env.actions != "binary":
            raise ValueError(
                f"env.actions={params.env.actions}: one vehicle's stream takes the binary modes "
                "(comm or radar each step)"
            )
        dyn = Dynamics(params)
        self.params = params
        self.num_states = dyn.num_states
        self.horizon = int(params.env.horizon)
        self.steps = ScalarStep(dyn)
        self._ncol = dyn.num_uniforms
        self.generator = torch.Generator()
        self.generator.manual_seed(int(seed))
        self._u: list[list[float]] = []
        self._t = 0
        self.state = 0
        self.steps_left = 0

    def reset(self) -> int:
        """Start an episode: draw its uniforms and a uniform initial state; returns the state."""
        u = torch.rand(self.horizon, self._ncol + 1, generator=self.generator, dtype=torch.float64)
        self._u = u.tolist()
        self._t = 0
        self.steps_left = self.horizon
        self.state = min(int(self._u[0][self._ncol] * self.num_states), self.num_states - 1)
        return self.state

    def step(self, action: int) -> Step:
        """One step of the current episode from ``state`` with ``action`` (0 comm, 1 radar)."""
        if self.steps_left <= 0:
            raise RuntimeError("the episode is over: call reset() first")
        if action != 0 and action != 1:  # an index past the tables, or -1 read as radar
            raise ValueError(f"action={action!r} must be 0 (communication) or 1 (radar)")
        out = self.steps.transition(self.state, action, self._u[self._t])
        self._t += 1
        self.steps_left -= 1
        self.state = out.state
        return out

    def transition(self, state: int, action: int, u: list[float]) -> Step:
        """``ScalarStep.transition``: the step from ``state`` with ``action`` and uniforms ``u``."""
        return self.steps.transition(state, action, u)

    def state_dict(self) -> dict[str, Any]:
        """The stream between episodes: its generator's state."""
        if self.steps_left:
            raise RuntimeError("a stream is checkpointed between episodes")
        return {"generator": self.generator.get_state()}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore ``state_dict``'s generator (the next ``reset`` goes on from there)."""
        self.generator.set_state(state["generator"])
        self.steps_left = 0


class OwnStream:
    """A stream of one's own (``learn_on_stream(stream=…)``: a vehicle's own steps, or a world the
    model does not describe), held to what the loop reads: ``reset()`` gives a state index,
    ``step(action)`` a ``Step`` whose ``state`` is one, episodes of ``env.horizon`` steps;
    ``state_dict`` / ``load_state_dict`` where it has them (a run on it resumes only with both).

    Args:
        stream: the stream.
        params: the scenario whose state index it speaks (``irdrc.state_index``).
    """

    def __init__(self, stream: Any, params: Params) -> None:
        self.name = type(stream).__name__
        missing = [m for m in ("reset", "step") if not callable(getattr(stream, m, None))]
        if missing:
            raise TypeError(
                f"stream={self.name} has no {' or '.join(f'{m}()' for m in missing)}: a stream "
                "has reset() -> state index and step(action) -> irdrc.core.stream.Step"
            )
        self.horizon = getattr(stream, "horizon", params.env.horizon)
        if self.horizon != params.env.horizon:
            raise ValueError(
                f"stream={self.name} has horizon={self.horizon!r}: its episodes must be "
                f"env.horizon={params.env.horizon} steps, the scenario's"
            )
        self.num_states = params.env.num_states
        self.inner = stream

    def _index(self, state: Any, where: str) -> int:
        if (
            isinstance(state, bool)
            or not isinstance(state, int)
            or not 0 <= state < self.num_states
        ):
            raise ValueError(
                f"{self.name}.{where} gave state {state!r}: a state is an index in "
                f"[0, {self.num_states}) (irdrc.state_index)"
            )
        return state

    def reset(self) -> int:
        """The inner stream's ``reset()``, checked."""
        return self._index(self.inner.reset(), "reset()")

    def step(self, action: int) -> Step:
        """The inner stream's ``step(action)``, checked."""
        out = self.inner.step(action)
        if not isinstance(out, Step):
            raise TypeError(
                f"{self.name}.step() returned {type(out).__name__}: a step is "
                "irdrc.core.stream.Step(state, reward, event, missed, sent, dropped, false_alarm, "
                "arrivals)"
            )
        self._index(out.state, "step()")
        return out

    def state_dict(self) -> dict[str, Any]:
        """The inner stream's ``state_dict()`` ({} where it has none)."""
        save = getattr(self.inner, "state_dict", None)
        return save() if callable(save) else {}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """The inner stream's ``load_state_dict``; refused where it has none."""
        load = getattr(self.inner, "load_state_dict", None)
        if not callable(load):
            raise ValueError(
                f"resume: the stream {self.name} has no load_state_dict(): a run on it cannot "
                "go on from a checkpoint"
            )
        load(state)
