"""Gymnasium entry point: ``gymnasium.make("irdrc/DFRC-v0", **overrides)`` after ``import irdrc``.

A single, unbatched env with exactly the dynamics of ``DFRCEnv`` (both call ``irdrc.core.env.Dynamics``).
Overrides use the config names, nested or dotted: ``gymnasium.make("irdrc/DFRC-v0",
env={"p1": {"speed": 0.5}}, reward={"r4": 50})``, ``p1={"speed": 0.5}``, ``horizon=100``,
``r4=50`` or ``**{"env.p1.speed": 0.5}``.
"""

from __future__ import annotations

from typing import Any

import gymnasium
import numpy as np
import torch
from gymnasium import spaces

from irdrc.core.env import Dynamics
from irdrc.core.params import Params

ENV_ID = "irdrc/DFRC-v0"


class DFRCGymEnv(gymnasium.Env):
    """One iRDRC env for gymnasium users (SB3, CleanRL, …).

    Observation: float32 array (d, c, r, w, v, m). Action: 0 = communication, 1 = radar.
    ``terminated`` is always False; ``truncated`` is True at step ``env.horizon``.
    ``info`` holds ``state`` (index), ``event``, ``missed``, ``sent``, ``dropped``, ``capacity``,
    ``step_count``.
    """

    metadata = {"render_modes": []}  # noqa: RUF012 - gymnasium's convention

    def __init__(self, params: Params | None = None, **overrides: Any) -> None:
        if params is not None and overrides:
            raise ValueError("pass either params or overrides, not both")
        self.params = params if params is not None else Params.from_overrides(overrides)
        self.dynamics = Dynamics(self.params)
        env = self.params.env
        high = np.array([env.queue_capacity, 1, 1, 1, 1, 1], dtype=np.float32)
        self.observation_space = spaces.Box(np.zeros(6, dtype=np.float32), high, dtype=np.float32)
        self.action_space = spaces.Discrete(2)
        self._rng = torch.Generator()
        self._rng.manual_seed(int(np.random.SeedSequence().generate_state(1)[0]))
        self._state = torch.zeros(1, dtype=torch.int64)
        self._steps = 0

    def _obs(self) -> np.ndarray:
        return self.dynamics.obs[self._state[0]].numpy().copy()

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[np.ndarray, dict[str, Any]]:
        """Start an episode from a uniformly drawn state; ``seed`` reseeds the generator."""
        super().reset(seed=seed)
        if seed is not None:
            self._rng.manual_seed(int(seed))
        self._state = self.dynamics.reset_states(1, self._rng)
        self._steps = 0
        return self._obs(), {"state": int(self._state[0]), "step_count": 0}

    def step(self, action: Any) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        """Apply action 0 (comm) or 1 (radar)."""
        a = int(action)
        if a not in (0, 1):
            raise ValueError(f"action={action!r} must be 0 (communication) or 1 (radar)")
        res = self.dynamics.step(self._state, torch.tensor([a]), self._rng)
        self._state = res.state
        self._steps += 1
        info = {
            "state": int(res.state[0]),
            "event": bool(res.event[0]),
            "missed": bool(res.missed[0]),
            "sent": int(res.sent[0]),
            "dropped": int(res.dropped[0]),
            "capacity": int(res.capacity[0]),
            "step_count": self._steps,
        }
        truncated = self._steps >= self.params.env.horizon
        return self._obs(), float(res.reward[0]), False, truncated, info


def register() -> None:
    """Register ``irdrc/DFRC-v0`` with gymnasium (idempotent)."""
    if ENV_ID not in gymnasium.registry:
        gymnasium.register(id=ENV_ID, entry_point="irdrc.core.gym:DFRCGymEnv")
