"""Gymnasium entry points, registered by ``import irdrc``:

- ``gymnasium.make("irdrc/DFRC-v0", **overrides)``: one env, for SB3, CleanRL and other single-env
  code. It steps the same tables as ``irdrc.core.dynamics.Dynamics`` in plain Python (a batched torch
  step costs ~100 µs of overhead for one env; this costs a few µs), so its transitions have exactly
  the distribution of the batched env's, not the same draws for a seed.
- ``gymnasium.make_vec("irdrc/DFRC-v0", num_envs=N, **overrides)``: N envs stepped together by
  ``Dynamics`` (torch), with gymnasium's next-step autoreset.

The action space follows ``env.actions`` (MODEL.md § D): ``Discrete(2)`` (binary, the default),
``Discrete(G)`` (``levels``: radar share level / (G − 1)) or ``Box(0, 1, (1,))`` (``continuous``:
the radar share ρ). Time-sharing steps go through ``irdrc.core.dynamics.step_shares`` (torch, one
env at a time in ``DFRCGymEnv``); an action out of range is an error, never clipped.

``reset(options={"state": s})`` starts from a state index (the vector env: one for every env, or
one per env); another option is refused by name.

The scenario is ``params=Params(...)``, or overrides named as everywhere else (each key with its
section, as on the command line): ``env={"p1": {"speed": 0.5}}, reward={"r4": 50}`` (nested), or
``**{"env.p1.speed": 0.5, "reward.r4": 50}`` (dotted).
"""

from __future__ import annotations

import random
from collections.abc import Callable
from typing import Any

import gymnasium
import numpy as np
import torch
from gymnasium import spaces
from gymnasium.vector import AutoresetMode, VectorEnv

from irdrc.core.checks import reset_option
from irdrc.core.dynamics import (
    Dynamics,
    binary_actions,
    checked_shares,
    observation_high,
    step_shares,
)
from irdrc.core.overrides import full_key, refuse_share_overrides
from irdrc.core.params import Params
from irdrc.core.stream import ScalarStep

ENV_ID = "irdrc/DFRC-v0"


GYM_KEYWORDS = ("params", "env", "reward", "env.<key>", "reward.<key>")
"""What the gym constructors take besides ``num_envs``."""


def _params(params: Params | None, overrides: dict[str, Any]) -> Params:
    if params is not None and overrides:
        raise ValueError("pass either params or overrides, not both")
    if params is not None:
        if not isinstance(params, Params):
            raise TypeError(
                f"params={params!r} must be a Params (irdrc.scenario(name), "
                "Params.from_overrides({…})), or pass overrides instead"
            )
        return params
    if "scenario" in overrides:
        name = overrides["scenario"]
        raise ValueError(
            "irdrc/DFRC-v0 takes no scenario=: a named scenario is "
            f"params=irdrc.scenario({name!r}) (with overrides: "
            f"irdrc.scenario({name!r}, **{{'env.p1.speed': 0.5}}))"
        )
    bare = [k for k in overrides if k.split(".", 1)[0] not in ("env", "reward")]
    if bare:
        fixes = ", ".join(f"{k} → {full_key(k)!r}" for k in bare)
        raise ValueError(
            f"irdrc/DFRC-v0 takes {', '.join(GYM_KEYWORDS)}; got {', '.join(bare)}: name each "
            f"key with its section ({fixes}), e.g. env={{'p1': {{'speed': 0.5}}}}, "
            "reward={'r4': 50} or **{'env.p1.speed': 0.5}"
        )
    refuse_share_overrides(overrides)
    return Params.from_overrides(overrides)


def _action_space(params: Params) -> spaces.Space[Any]:
    """The gymnasium action space of ``env.actions``."""
    env = params.env
    if env.actions == "continuous":
        return spaces.Box(0.0, 1.0, shape=(1,), dtype=np.float32)
    return spaces.Discrete(2 if env.actions == "binary" else env.levels)


def _shares(params: Params, action: Any, n: int) -> torch.Tensor:
    """``n`` gymnasium actions of a time-sharing env as radar shares (``checked_shares``)."""
    a = torch.as_tensor(np.asarray(action, dtype=np.float64)).reshape(-1)
    if a.numel() != n:
        raise ValueError(f"{a.numel()} actions for {n} env(s): action={action!r}")
    return checked_shares(params.env, a)


def _observation_space(params: Params) -> spaces.Box:
    high = observation_high(params).numpy()
    return spaces.Box(np.zeros_like(high), high, dtype=np.float32)


def _action(action: Any) -> int:
    """A gymnasium action as 0 or 1: an int or a 0-d integer array; anything else is refused."""
    if isinstance(action, bool | np.bool_):
        raise ValueError(f"action={action!r} must be 0 (communication) or 1 (radar), not a bool")
    if isinstance(action, int | np.integer) or (
        isinstance(action, np.ndarray) and action.shape == () and action.dtype.kind in "iu"
    ):
        a = int(action)
        if a in (0, 1):
            return a
        raise ValueError(f"action={action!r} must be 0 (communication) or 1 (radar)")
    raise ValueError(
        f"action={action!r} must be 0 (communication) or 1 (radar) as an integer: its space is "
        "Discrete(2), whose actions are Python or NumPy integers (a 0-d integer array too)"
    )


class DFRCGymEnv(gymnasium.Env):
    """One iRDRC env for gymnasium users (SB3, CleanRL, …).

    Observation: float32 array (d, c, r, w, v, m). Action: 0 = communication, 1 = radar (an int or a
    0-d integer array). ``terminated`` is always False; ``truncated`` is True at step
    ``env.horizon``. ``info`` holds ``state`` (index), ``event``, ``missed``, ``false_alarm``,
    ``sent``, ``dropped``, ``arrivals``, ``capacity``, ``step_count`` (every field of
    ``irdrc.core.stream.Step``, so a stream over it can feed ``learn_on_stream(stream=…)``).
    """

    metadata = {"render_modes": []}  # noqa: RUF012 - gymnasium's convention

    def __init__(self, params: Params | None = None, **overrides: Any) -> None:
        self.params = _params(params, overrides)
        self.dynamics = dyn = Dynamics(self.params)
        self.observation_space = _observation_space(self.params)
        self.action_space = _action_space(self.params)
        # Dynamics' step on one state at a time, in Python (``irdrc.core.stream.ScalarStep``)
        self._step = ScalarStep(dyn)
        self._nf, self._phases = dyn.num_configs, dyn.num_phases
        self._obs = [o for o in dyn.obs.numpy()]
        self._D = dyn.queue_capacity
        self._S = dyn.num_states
        self._horizon = self.params.env.horizon
        self._rng = random.Random(int(np.random.SeedSequence().generate_state(1)[0]))
        self._torch_rng = torch.Generator()  # time-sharing steps (``step_shares``)
        self._torch_rng.manual_seed(self._rng.getrandbits(63))
        self._state = -1  # no episode yet: step() before reset() is refused
        self._steps = 0

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[np.ndarray, dict[str, Any]]:
        """Start an episode from a uniformly drawn state, or from ``options={"state": s}`` (a state
        index, see ``irdrc.state_index``); ``seed`` reseeds the generator."""
        super().reset(seed=seed)
        if seed is not None:
            self._rng.seed(int(seed))
            self._torch_rng.manual_seed(self._rng.getrandbits(63))
        start = reset_option(options)
        if start is None:
            self._state = int(self._rng.random() * self._S)
        elif isinstance(start, int | np.integer) and 0 <= int(start) < self._S:
            self._state = int(start)
        else:
            raise ValueError(f"options['state']={start!r} must be a state index in [0, {self._S})")
        self._steps = 0
        return self._obs[self._state].copy(), {"state": self._state, "step_count": 0}

    def step(self, action: Any) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        """Apply action 0 (comm) or 1 (radar), or a radar share (``env.actions``)."""
        if self._state < 0:
            raise gymnasium.error.ResetNeeded("call reset() before step()")
        if self.params.env.actions != "binary":
            return self._step_shares(_shares(self.params, action, 1))
        a = _action(action)
        s, u = self._state, self._rng.random
        # The uniforms in Dynamics' order: event, arrivals, each factor, then the radar's draw.
        out = self._step.transition(s, a, [u() for _ in range(self._step.num_uniforms)])
        phase = (s % self._nf) % self._phases
        self._state = out.state
        self._steps += 1
        reward = out.reward
        info = {
            "state": self._state,
            "event": out.event,
            "missed": out.missed,
            "false_alarm": out.false_alarm,
            "sent": out.sent,
            "dropped": out.dropped,
            "arrivals": out.arrivals,
            "capacity": self._step.capacity(s, a),
            "step_count": self._steps,
        }
        if self._phases > 1:
            info["phase"] = phase
        truncated = self._steps >= self._horizon
        return self._obs[self._state].copy(), reward, False, truncated, info

    def policy_table(self, predict: Callable[[np.ndarray], Any]) -> torch.Tensor:
        """The table a policy acts by: ``predict`` maps a batch of observations [S, W] (every
        state's, in state order) to a batch of actions — e.g. a Stable-Baselines3 model's
        ``lambda obs: model.predict(obs, deterministic=True)[0]``. Returns [S] actions 0 / 1
        (``binary``) or [S] radar shares (``levels``: level / (G − 1); ``continuous``: ρ).

        Raises:
            ValueError: another number of actions, or an action outside the action space.
        """
        obs = self.dynamics.obs.numpy().astype(np.float32)
        out = np.asarray(predict(obs))
        S, actions = obs.shape[0], self.params.env.actions
        if out.size != S:
            raise ValueError(
                f"predict returned {out.size} actions for the {S} states' observations"
            )
        out = out.reshape(S)
        if actions == "binary":
            return binary_actions(out, "predict's action")
        return checked_shares(self.params.env, torch.as_tensor(out, dtype=torch.float64))

    def score(self, predict: Callable[[np.ndarray], Any], gamma: float = 0.99) -> dict[str, float]:
        """A policy's exact long-run metrics against this scenario's optimum (binary: the optimum
        at discount ``gamma``; radar shares: the optimum over ρ ∈ [0, 1]), as the recipes score
        their learners: ``ratio`` (average reward over the optimum's), ``avg_reward``,
        ``optimum``, ``throughput``, ``miss_detection``, ``radar_fraction``. ``predict`` is as
        ``policy_table`` takes it."""
        from irdrc.core.exact import exact_scorer
        from irdrc.core.exact.continuum import ContinuumScorer
        from irdrc.core.exact.scorer import score_summary

        table = self.policy_table(predict)
        if self.params.env.actions == "binary":
            scorer: Any = exact_scorer(self.params, gamma)
        else:
            scorer = ContinuumScorer(
                self.params.with_overrides({"env.actions": "continuous"}), gamma
            )
        return score_summary(scorer, table)

    def _step_shares(
        self, rho: torch.Tensor
    ) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        """One time-sharing step (MODEL.md § D) through ``step_shares``."""
        state = torch.tensor([self._state])
        res = step_shares(self.dynamics, state, rho, self._torch_rng)
        self._state = int(res.state[0])
        self._steps += 1
        info = {
            "state": self._state,
            "event": bool(res.event[0]),
            "missed": bool(res.missed[0]),
            "false_alarm": bool(res.false_alarm[0]),
            "sent": int(res.sent[0]),
            "dropped": int(res.dropped[0]),
            "arrivals": int(res.arrivals[0]),
            "capacity": int(res.capacity[0]),
            "step_count": self._steps,
        }
        truncated = self._steps >= self._horizon
        return self._obs[self._state].copy(), float(res.reward[0]), False, truncated, info


class DFRCVectorEnv(VectorEnv):
    """``num_envs`` iRDRC envs stepped together by ``Dynamics``, for gymnasium's vector API.

    Autoreset is gymnasium's default (next step): the step after an episode's last one resets that
    env, ignoring its action and returning reward 0. ``info`` holds arrays ``state``, ``event``,
    ``missed``, ``false_alarm``, ``sent``, ``dropped``, ``arrivals``, ``capacity``.
    """

    metadata = {"autoreset_mode": AutoresetMode.NEXT_STEP}  # noqa: RUF012 - gymnasium's convention

    def __init__(self, num_envs: int = 1, params: Params | None = None, **overrides: Any) -> None:
        if isinstance(num_envs, bool) or not isinstance(num_envs, int) or num_envs < 1:
            raise ValueError(f"num_envs={num_envs!r} must be an integer >= 1")
        self.params = _params(params, overrides)
        self.dynamics = Dynamics(self.params)
        self.num_envs = num_envs
        self.single_observation_space = _observation_space(self.params)
        self.single_action_space = _action_space(self.params)
        self.observation_space = gymnasium.vector.utils.batch_space(
            self.single_observation_space, num_envs
        )
        self.action_space = gymnasium.vector.utils.batch_space(self.single_action_space, num_envs)
        self._rng = torch.Generator()
        self._rng.manual_seed(int(np.random.SeedSequence().generate_state(1)[0]))
        self._state: torch.Tensor | None = None
        self._steps = torch.zeros(num_envs, dtype=torch.int64)
        self._autoreset = torch.zeros(num_envs, dtype=torch.bool)

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[np.ndarray, dict[str, Any]]:
        """Reset every env from a uniformly drawn state, or from ``options={"state": s}`` (one
        state index for every env, or one per env); ``seed`` reseeds the shared generator."""
        start = reset_option(options)
        if seed is not None:
            self._rng.manual_seed(int(seed))
        self._state = self.dynamics.reset_states(self.num_envs, self._rng)
        if start is not None:
            self._state = self._start_states(start)
        self._steps.zero_()
        self._autoreset.zero_()
        return self.dynamics.obs[self._state].numpy(), {"state": self._state.numpy().copy()}

    def _start_states(self, start: Any) -> torch.Tensor:
        """[num_envs] the states ``options["state"]`` gives: one index for all, or one per env."""
        given = np.asarray(start)
        S = self.dynamics.num_states
        if (
            given.dtype.kind not in "iu"
            or given.shape not in ((), (self.num_envs,))
            or bool(((given < 0) | (given >= S)).any())
        ):
            raise ValueError(
                f"options['state']={start!r} must be a state index in [0, {S}), or "
                f"{self.num_envs} of them (one per env)"
            )
        return torch.from_numpy(np.broadcast_to(given, (self.num_envs,)).astype(np.int64))

    def step(self, actions: Any) -> tuple[Any, Any, Any, Any, dict[str, Any]]:
        """Step every env with ``actions`` (0 or 1 each, or radar shares: ``env.actions``)."""
        if self._state is None:
            raise gymnasium.error.ResetNeeded("call reset() before step()")
        if self.params.env.actions != "binary":
            rho = _shares(self.params, actions, self.num_envs)
            res = step_shares(self.dynamics, self._state, rho, self._rng)
        else:
            a = binary_actions(actions).reshape(-1)
            if a.numel() != self.num_envs:
                raise ValueError(f"{a.numel()} actions for {self.num_envs} envs")
            res = self.dynamics.step(self._state, a, self._rng)
        fresh = self.dynamics.reset_states(self.num_envs, self._rng)
        done_before = self._autoreset
        state = torch.where(done_before, fresh, res.state)
        reward = torch.where(done_before, 0.0, res.reward).numpy().astype(np.float64)
        self._steps = torch.where(done_before, 0, self._steps + 1)
        truncated = (self._steps >= self.params.env.horizon).numpy()
        self._state, self._autoreset = state, torch.as_tensor(truncated)
        keep = ~done_before
        info = {
            "state": state.numpy().copy(),
            "event": (res.event & keep).numpy(),
            "missed": (res.missed & keep).numpy(),
            "sent": torch.where(keep, res.sent, 0).numpy(),
            "dropped": torch.where(keep, res.dropped, 0).numpy(),
            "arrivals": torch.where(keep, res.arrivals, 0).numpy(),
            "capacity": torch.where(keep, res.capacity, 0).numpy(),
            "false_alarm": (res.false_alarm & keep).numpy(),
        }
        terminated = np.zeros(self.num_envs, dtype=bool)
        return self.dynamics.obs[state].numpy(), reward, terminated, truncated, info
