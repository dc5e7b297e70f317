"""The fleet as a PettingZoo ``ParallelEnv`` (MODEL.md § C), for MARL code that speaks PettingZoo
(TorchRL's ``PettingZooWrapper``, EPyMARL, RLlib, …).

``parallel_env(**overrides)`` follows PettingZoo's naming convention. One fleet is stepped by the
same simulator as ``FleetEnv`` (``irdrc.fleet.sim.FleetDynamics``): the same start distribution,
the same transitions and rewards. Agents are ``vehicle_1`` … ``vehicle_N``; each acts in
``Discrete(2)`` (0 communication, 1 radar) and observes a ``Box`` (``env.observe``: ``own`` — its
d, c, v, m and the shared r, w — or ``full``, every vehicle's, as ``FleetEnv``). ``state()`` is the
centralised critic's features (``FleetEnv``'s root ``state``). Episodes end by truncation at
``env.horizon`` (every agent truncated together, then ``agents`` is empty); nothing terminates.
Each agent's info holds the step's ``event``, ``missed``, ``detected_by_other``, ``granted``,
``denied``, ``sent``, ``dropped`` and its single-vehicle ``state``; where the exact model reaches,
``joint_index`` is the fleet's exact joint state (for exact scoring).

Needs PettingZoo (``pip install pettingzoo``; the ``dev`` extra installs it).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Any

import numpy as np
import torch
from gymnasium import spaces
from pettingzoo import ParallelEnv

from irdrc.core.checks import check_number
from irdrc.core.dynamics import binary_actions, fresh_seed
from irdrc.core.overrides import apply_overrides, refuse_share_overrides
from irdrc.core.params import Params
from irdrc.fleet.config import fleet_from_config
from irdrc.fleet.env import (
    REWARDS,
    critic_state,
    critic_state_high,
    fleet_observation,
    fleet_observation_high,
    own_columns,
)
from irdrc.fleet.model import FleetModel
from irdrc.fleet.sim import FleetDynamics
from irdrc.fleet.spec import OBSERVE, FleetSpec

INFO_KEYS = ("event", "missed", "detected_by_other", "granted", "denied", "sent", "dropped")
"""Each agent's per-step signals in ``infos`` (with its single-vehicle ``state``)."""


def fleet_spec(overrides: Mapping[str, Any]) -> tuple[FleetSpec, str]:
    """The fleet and what each vehicle observes from overrides named as on the command line
    (``{"env.vehicles": 4, "env.observe": "full", "env.p1.speed": 0.5, "reward.r4": 50}``, or
    nested), on top of ``env=fleet``'s defaults (two of the paper's vehicles)."""
    if isinstance(overrides.get("env"), str):
        raise ValueError(
            f"env={overrides['env']!r}: parallel_env is the fleet of irdrc/scenarios/fleet.yaml, "
            "overrides on top of it (**{'env.vehicles': 4, 'env.share': 0.5}); a FleetSpec as spec= builds any "
            "other"
        )
    refuse_share_overrides(overrides)
    merged = Params().to_dict()
    merged["env"]["vehicles"] = 2
    apply_overrides(merged, overrides)
    return fleet_from_config(merged)


class FleetParallelEnv(ParallelEnv):
    """One fleet as a PettingZoo ``ParallelEnv`` (see the module docstring).

    Args:
        spec: the fleet (``FleetSpec``) or a built ``FleetModel``.
        observe: ``own`` or ``full``.
        rewards: ``own`` (each vehicle's reward) or ``team`` (the fleet's sum, to every vehicle).
        seed: the generator's seed (None: a fresh one; ``reset(seed=…)`` reseeds).
    """

    metadata = {"name": "irdrc_fleet_v0", "render_modes": [], "is_parallelizable": True}  # noqa: RUF012 - PettingZoo's convention
    render_mode = None

    def __init__(
        self,
        spec: FleetSpec | FleetModel,
        observe: str = "own",
        rewards: str = "own",
        seed: int | None = None,
    ) -> None:
        if observe not in OBSERVE:
            raise ValueError(f"observe={observe!r} must be one of {', '.join(OBSERVE)}")
        if rewards not in REWARDS:
            raise ValueError(f"rewards={rewards!r} must be one of {', '.join(REWARDS)}")
        self.model = spec if isinstance(spec, FleetModel) else FleetModel(spec)
        self.sim = FleetDynamics(self.model)
        self.observe, self.rewards = observe, rewards
        n, params = self.model.N, self.model.spec.vehicle
        self.possible_agents = [f"vehicle_{i + 1}" for i in range(n)]
        self.agents: list[str] = []
        self.own = own_columns(params)
        high = fleet_observation_high(params, n, observe).numpy().astype(np.float32)
        obs_space = spaces.Box(np.zeros_like(high), high, dtype=np.float32)
        # one space object per agent, the same on every call (PettingZoo's API test checks it)
        self.observation_spaces = {
            a: spaces.Box(obs_space.low, obs_space.high, dtype=np.float32)
            for a in self.possible_agents
        }
        self.action_spaces = {a: spaces.Discrete(2) for a in self.possible_agents}
        critic = critic_state_high(params, n).numpy().astype(np.float32)
        self.state_space = spaces.Box(np.zeros_like(critic), critic, dtype=np.float32)
        self.horizon = params.env.horizon
        self.rng = torch.Generator()
        self.rng.manual_seed(fresh_seed() if seed is None else _checked_seed(seed))
        self._states: torch.Tensor | None = None
        self._steps = 0
        self._joint: torch.Tensor | None = None  # [S_fleet, N], built on the first start state
        self._scorers: dict[float, Any] = {}  # FleetScorer per discount, built by score()

    def observation_space(self, agent: str) -> spaces.Box:
        """The observation space of ``agent`` (the same object on every call)."""
        return self.observation_spaces[agent]

    def action_space(self, agent: str) -> spaces.Discrete:
        """The action space of ``agent``: 0 communication, 1 radar (the same object every call)."""
        return self.action_spaces[agent]

    def reset(
        self, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[dict[str, np.ndarray], dict[str, dict[str, Any]]]:
        """Start an episode from a joint state drawn uniformly (as ``FleetEnv``), or from
        ``options={"state": s}`` (the exact model's joint index; other keys are ignored, as
        PettingZoo's ``parallel_api_test`` requires); ``seed`` reseeds."""
        if seed is not None:
            seed = _checked_seed(seed)
            self.rng.manual_seed(seed)
            for i, agent in enumerate(self.possible_agents):
                self.action_spaces[agent].seed(int(seed) + i)
        start = (options or {}).get("state")
        states = self.sim.start(1, self.rng) if start is None else self._joint_state(start)
        self._states = states
        self._steps = 0
        self.agents = list(self.possible_agents)
        zeros = dict.fromkeys(INFO_KEYS, 0)
        return self._observations(states), self._infos(states, dict.fromkeys(self.agents, zeros))

    def _joint_state(self, start: Any) -> torch.Tensor:
        """[1, N] the vehicles' states of the exact model's joint index ``start``."""
        self.model.check_exact()
        S = self.model.num_states
        if not isinstance(start, int | np.integer) or not 0 <= int(start) < S:
            raise ValueError(f"options['state']={start!r} must be a joint state index in [0, {S})")
        if self._joint is None:
            self._joint = self.model.vehicle_states()
        return self._joint[int(start)].reshape(1, -1)

    def step(
        self, actions: dict[str, Any]
    ) -> tuple[
        dict[str, np.ndarray],
        dict[str, float],
        dict[str, bool],
        dict[str, bool],
        dict[str, dict[str, Any]],
    ]:
        """Every vehicle's action (0 comm, 1 radar) → observations, rewards, terminations,
        truncations and infos per agent."""
        if self._states is None or not self.agents:
            raise RuntimeError("call reset() before step() (and after an episode's last step)")
        unknown = [str(a) for a in actions if a not in self.agents]
        if unknown:  # before the missing ones: a misspelt agent is the cause of both
            raise ValueError(
                f"unknown agent(s) {', '.join(unknown)}: this env's agents are "
                f"{', '.join(self.agents)}"
            )
        missing = [a for a in self.agents if a not in actions]
        if missing:
            raise ValueError(f"no action for {', '.join(missing)}: every vehicle acts every step")
        act = torch.tensor([[_agent_action(a, actions[a]) for a in self.agents]])
        res = self.sim.step(self._states, act, self.rng)
        self._states = res.state
        self._steps += 1
        reward = res.reward[0]
        if self.rewards == "team":
            reward = reward.sum().expand_as(reward)
        signals = {
            "event": res.event,
            "missed": res.missed,
            "detected_by_other": res.by_other,
            "granted": res.granted,
            "denied": res.denied,
            "sent": res.sent,
            "dropped": res.dropped,
        }
        per = {a: {k: int(v[0, i]) for k, v in signals.items()} for i, a in enumerate(self.agents)}
        obs, infos = self._observations(res.state), self._infos(res.state, per)
        rewards = {a: float(reward[i]) for i, a in enumerate(self.agents)}
        truncated = self._steps >= self.horizon
        terminations = dict.fromkeys(self.agents, False)
        truncations = dict.fromkeys(self.agents, truncated)
        if truncated:
            self.agents = []
        return obs, rewards, terminations, truncations, infos

    def _observations(self, states: torch.Tensor) -> dict[str, np.ndarray]:
        single = self.sim.dyn.obs[states.reshape(-1)]  # [N, W]
        obs = fleet_observation(single, self.own, self.observe).numpy().astype(np.float32)
        return {a: obs[i] for i, a in enumerate(self.possible_agents)}

    def _infos(
        self, joint_states: torch.Tensor, per: dict[str, dict[str, Any]]
    ) -> dict[str, dict[str, Any]]:
        states = joint_states[0]
        joint = int(self.sim.fleet_index(joint_states)[0]) if self.model.exact else -1
        return {
            a: {**per[a], "state": int(states[i]), "joint_index": joint}
            for i, a in enumerate(self.possible_agents)
        }

    def state(self) -> np.ndarray:
        """The centralised critic's features: the shared r, w, then every vehicle's own d, c, v,
        m (``irdrc.fleet.env.critic_state``)."""
        if self._states is None:
            raise RuntimeError("call reset() before state()")
        single = self.sim.dyn.obs[self._states.reshape(-1)]
        return critic_state(single, self.own).numpy().astype(np.float32)

    def close(self) -> None:
        """Nothing to release."""

    def policy_table(
        self, policy: Callable[[dict[str, np.ndarray]], Mapping[str, Any]]
    ) -> torch.Tensor:
        """The decentralised table a ``policy`` acts by, as ``FleetScorer`` reads it.

        ``policy`` maps a batch of observations per agent (``{agent: [B, W] float32}``) to a batch
        of actions per agent (``{agent: [B]}``, 0 or 1) — a trained network's greedy actions.
        With ``own`` observations every single-vehicle state is shown to every vehicle ([N·S],
        vehicle-major); with ``full`` observations every joint state ([S_fleet])."""
        model, n = self.model, self.model.N
        if self.observe == "own":
            states = torch.arange(model.single.num_states)[:, None].expand(-1, n)
        else:
            states = model.vehicle_states()
        obs = fleet_observation(self.sim.dyn.obs[states], self.own, self.observe).numpy()
        out = policy({a: obs[:, i].astype(np.float32) for i, a in enumerate(self.possible_agents)})
        act = torch.stack(
            [binary_actions(out[a], f"{a}'s action").reshape(-1) for a in self.possible_agents], 1
        )
        if act.shape[0] != len(states):
            raise ValueError(
                f"policy returned {act.shape[0]} actions per agent for {len(states)} rows"
            )
        if self.observe == "own":
            return act.T.reshape(-1)
        return (act << torch.arange(n)).sum(1)

    def score(
        self, policy: Callable[[dict[str, np.ndarray]], Mapping[str, Any]], gamma: float = 0.99
    ) -> dict[str, float]:
        """A ``policy``'s exact long-run metrics against the centralised optimum (``FleetScorer``,
        the optimum at discount ``gamma``), as the fleet recipe scores its learners: ``ratio``
        (average reward over the optimum's), ``avg_reward``, ``optimum``, ``throughput``,
        ``miss_detection``, ``radar_fraction``. ``policy`` is as ``policy_table`` takes it."""
        from irdrc.core.exact.scorer import score_summary
        from irdrc.fleet.scorer import FleetScorer

        if gamma not in self._scorers:
            self._scorers[gamma] = FleetScorer(self.model, gamma=gamma)
        scorer = self._scorers[gamma]
        table = self.policy_table(policy)
        return score_summary(scorer, table)


def parallel_env(
    spec: FleetSpec | FleetModel | None = None,
    *,
    rewards: str = "own",
    seed: int | None = None,
    **overrides: Any,
) -> FleetParallelEnv:
    """The fleet as a PettingZoo ``ParallelEnv``: a ``FleetSpec`` (or ``FleetModel``), or
    overrides named as on the command line on top of ``env=fleet``'s defaults, e.g.
    ``parallel_env(**{"env.vehicles": 4, "env.observe": "full", "env.share": 0.5})``.

    Args:
        spec: the fleet; None builds it from ``overrides``.
        rewards: ``own`` or ``team``.
        seed: the generator's seed.
        overrides: ``env.*`` and ``reward.*`` keys (``env.observe`` picks the observation).

    Raises:
        ValueError: both ``spec`` and overrides, or a bad key or value (as the recipes say it).
    """
    if spec is not None:
        observe = overrides.pop("env.observe", "own")
        if overrides:
            raise ValueError("pass either a spec or overrides (besides env.observe), not both")
        return FleetParallelEnv(spec, observe=observe, rewards=rewards, seed=seed)
    fleet, observe = fleet_spec(overrides)
    return FleetParallelEnv(fleet, observe=observe, rewards=rewards, seed=seed)


def _agent_action(agent: str, action: Any) -> int:
    """One agent's action of a step: one number, 0 or 1 (``binary_actions``)."""
    a = binary_actions(action, f"{agent}'s action")
    if a.numel() != 1:
        raise ValueError(f"{agent}'s action {action!r} must be one number, 0 or 1")
    return int(a.reshape(()))


def _checked_seed(seed: Any) -> int:
    """``seed`` as an int, if it is a whole number in [0, 2³² − 1] (the recipes' range; a NumPy
    integer too)."""
    seed = int(seed) if isinstance(seed, np.integer) else seed
    return int(check_number("seed", seed, 0, 2**32 - 1, integer=True))
