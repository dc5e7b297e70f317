"""The fleet as single-agent batched envs, for learners written for one agent: ``FleetRowsEnv`` (a
row per vehicle, the team reward, for independent learners with parameter sharing) and
``FleetJointEnv`` (a row per fleet over the 2^N joint actions). Both step ``irdrc.fleet.sim`` as
``irdrc.fleet.env.FleetEnv`` does and share its observations."""

from __future__ import annotations

from typing import Any

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Bounded, Categorical, Composite, Unbounded
from torchrl.envs import EnvBase

from irdrc.core.dynamics import checked_actions, fresh_seed, observation_high
from irdrc.fleet.env import done_spec, fleet_observation, fleet_observation_high, own_columns
from irdrc.fleet.model import FleetModel
from irdrc.fleet.sim import FleetDynamics
from irdrc.fleet.spec import FleetSpec


def set_row_specs(
    env: EnvBase, high: torch.Tensor, num_states: int, num_actions: int, horizon: int
) -> None:
    """The specs of a single-agent view of the fleet (one row per vehicle or per fleet): an
    ``observation`` in [0, ``high``], the exact ``state`` index, ``step_count``, a categorical
    ``action``, a [rows, 1] ``reward`` and the done flags."""
    rows, width, dev = env.batch_size[0], high.shape[0], env.device
    env.observation_spec = Composite(
        observation=Bounded(
            low=torch.zeros(rows, width, device=dev),
            high=high.to(dev).expand(rows, width).clone(),
            shape=(rows, width),
            dtype=torch.float32,
            device=dev,
        ),
        state=Categorical(num_states, shape=(rows,), dtype=torch.int64),
        step_count=Bounded(0, horizon, shape=(rows, 1), dtype=torch.int64),
        shape=(rows,),
        device=dev,
    )
    env.action_spec = Categorical(num_actions, shape=(rows,), dtype=torch.int64, device=dev)
    env.reward_spec = Unbounded(shape=(rows, 1), dtype=torch.float32, device=dev)
    env.done_spec = done_spec(rows, dev)


def row_output(
    obs: torch.Tensor,
    state: torch.Tensor,
    steps: torch.Tensor,
    horizon: int,
    device: torch.device,
    reward: torch.Tensor | None = None,
) -> TensorDict:
    """One step's output of a single-agent view (``set_row_specs``): episodes end by truncation at
    ``horizon``."""
    rows = obs.shape[0]
    truncated = (steps >= horizon).reshape(rows, 1)
    out = {
        "observation": obs.to(device),
        "state": state,
        "step_count": steps.reshape(rows, 1),
        "done": truncated,
        "terminated": torch.zeros_like(truncated),
        "truncated": truncated,
    }
    if reward is not None:
        out["reward"] = reward.reshape(rows, 1).to(torch.float32)
    return TensorDict(out, batch_size=(rows,), device=device)


class FleetView(EnvBase):
    """What both single-agent views share: the fleet's model and simulator, ``fleets`` fleets of one
    row per vehicle (``per_vehicle``) or one row each, their generator and observation table."""

    def _build(
        self, spec: FleetSpec | FleetModel | None, fleets: int, per_vehicle: bool, device: Any
    ) -> None:
        self.model = spec if isinstance(spec, FleetModel) else FleetModel(spec or FleetSpec())
        if not per_vehicle:
            self.model.check_exact()  # a row per fleet: its state is the exact joint index
        self.sim = FleetDynamics(self.model)
        self.dynamics = self.sim.dyn
        self.fleets, self.n_agents = int(fleets), self.model.N
        if self.fleets < 1:
            raise ValueError(f"fleets={fleets} must be >= 1")
        rows = self.fleets * (self.n_agents if per_vehicle else 1)
        super().__init__(device=device, batch_size=torch.Size([rows]))
        self.params = self.model.spec.vehicle
        self.rng = torch.Generator()

    @property
    def observation_table(self) -> torch.Tensor:
        """Every observation a row can see, one per ``num_states`` (greedy tables read it)."""
        return self.obs_table

    def _set_seed(self, seed: int | None) -> None:
        self.rng.manual_seed(int(seed if seed is not None else fresh_seed()))


class FleetRowsEnv(FleetView):
    """The fleet as rows of one agent each, for learners written for a single-agent batched env
    (independent learners with parameter sharing): ``fleets`` fleets of N vehicles give
    ``fleets·N`` rows (vehicle i of fleet b is row b·N + i), each with its vehicle's
    ``observation``, ``action`` and, as ``reward``, the fleet's team reward (the sum over its
    vehicles, MODEL.md § C); a fleet's rows step together and end together. ``dynamics`` is the
    single-vehicle ``Dynamics`` (its ``obs`` table is every row's observation space), so a
    network's greedy table over the single-vehicle states is the whole decentralised policy.
    """

    def __init__(
        self,
        spec: FleetSpec | FleetModel | None = None,
        fleets: int = 1,
        device: torch.device | str = "cpu",
        seed: int | None = None,
        reward: str = "team",
        agent_index: bool = False,
    ) -> None:
        if reward not in ("team", "own"):
            raise ValueError(f"reward={reward!r} must be team or own")
        self.reward_kind = reward
        self._build(spec, fleets, True, device)
        self.agent_index = bool(agent_index)
        N, single = self.model.N, self.sim.dyn.obs
        if self.agent_index:  # every (vehicle, state) pair: the vehicle's one-hot index appended
            eye = torch.eye(N, dtype=single.dtype).repeat_interleave(single.shape[0], 0)
            self.obs_table = torch.cat([single.repeat(N, 1), eye], 1)  # [N·S, width + N]
        else:
            self.obs_table = single
        params = self.params
        high = observation_high(params)
        if self.agent_index:
            high = torch.cat([high, torch.ones(self.n_agents, dtype=high.dtype)])
        set_row_specs(self, high, self.dynamics.num_states, 2, params.env.horizon)
        self.set_seed(seed if seed is not None else fresh_seed())

    @property
    def num_states(self) -> int:
        """The observation table's rows: the single-vehicle states, or with ``agent_index`` every
        (vehicle, state) pair (vehicle-major)."""
        return self.obs_table.shape[0]

    def _out(
        self, states: torch.Tensor, steps: torch.Tensor, reward: torch.Tensor | None = None
    ) -> TensorDict:
        return row_output(
            self._observe(states),
            states.reshape(-1),
            steps,
            self.params.env.horizon,
            self.device,
            reward,
        )

    def _observe(self, states: torch.Tensor) -> torch.Tensor:
        flat = states.reshape(-1)
        if not self.agent_index:
            return self.obs_table[flat]
        vehicle = torch.arange(flat.shape[0]) % self.n_agents
        return self.obs_table[vehicle * self.dynamics.num_states + flat]

    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs: Any) -> TensorDict:
        # Fresh fleets for every row; torchrl keeps the rows the "_reset" mask selects, and a
        # fleet's rows always end together.
        m, B, N = self.model, self.fleets, self.n_agents
        rw = torch.randint(0, m.RW, (B, 1), generator=self.rng)
        x = torch.randint(0, m.X, (B, N), generator=self.rng)
        states = m.index[rw.expand(B, N), x]
        return self._out(states, torch.zeros(B * N, dtype=torch.int64))

    def _step(self, tensordict: TensorDictBase) -> TensorDict:
        states, action = tensordict.get("state", None), tensordict.get("action", None)
        if states is None or tensordict.get("step_count", None) is None:
            raise ValueError("FleetRowsEnv.step needs the 'state' and 'step_count' of reset()")
        if action is None:
            raise ValueError("FleetRowsEnv.step needs an 'action': 0 (communication) or 1 (radar)")
        B, N = self.fleets, self.n_agents
        action = checked_actions(action.reshape(-1)).reshape(B, N).cpu()
        res = self.sim.step(states.reshape(B, N).cpu(), action, self.rng)
        team = (
            res.reward.sum(1, keepdim=True).expand(B, N)
            if self.reward_kind == "team"
            else res.reward
        )
        steps = tensordict.get("step_count").reshape(-1).cpu() + 1
        return self._out(res.state, steps, team)


class FleetJointEnv(FleetView):
    """The fleet as one agent choosing the joint action: ``fleets`` rows, each fleet's
    ``observation`` every vehicle's state (vehicle 1's ``full`` observation, ``OBSERVE``),
    ``action`` the joint action a = Σ_i a_i·2^(i−1) (2^N of them), ``reward`` the team reward,
    ``state`` the exact model's joint index. A network learned here is executed by every vehicle
    alike — each sees the fleet's states (shared over V2V), computes the same joint action and
    takes its own bit — so its greedy table over the joint states is the fleet's policy.
    """

    def __init__(
        self,
        spec: FleetSpec | FleetModel | None = None,
        fleets: int = 1,
        device: torch.device | str = "cpu",
        seed: int | None = None,
    ) -> None:
        self._build(spec, fleets, False, device)
        params = self.params
        self.own = own_columns(params)
        self.vehicles = self.model.vehicle_states()  # [S, N]
        self.obs_table = self._observe(self.vehicles)
        high = fleet_observation_high(params, self.n_agents, "full")
        set_row_specs(self, high, self.model.num_states, 2**self.n_agents, params.env.horizon)
        self.set_seed(seed if seed is not None else fresh_seed())

    @property
    def num_states(self) -> int:
        """The fleet's joint states (the observation table's rows)."""
        return self.model.num_states

    def _observe(self, vehicle_states: torch.Tensor) -> torch.Tensor:
        obs = self.sim.dyn.obs[vehicle_states]  # [n, N, W]
        return fleet_observation(obs, self.own, "full")[:, 0]

    def _out(
        self, states: torch.Tensor, steps: torch.Tensor, reward: torch.Tensor | None = None
    ) -> TensorDict:
        joint = self.sim.fleet_index(states)
        return row_output(
            self.obs_table[joint], joint, steps, self.params.env.horizon, self.device, reward
        )

    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs: Any) -> TensorDict:
        joint = torch.randint(0, self.model.num_states, (self.fleets,), generator=self.rng)
        return self._out(self.vehicles[joint], torch.zeros(self.fleets, dtype=torch.int64))

    def _step(self, tensordict: TensorDictBase) -> TensorDict:
        joint, action = tensordict.get("state", None), tensordict.get("action", None)
        if joint is None or tensordict.get("step_count", None) is None:
            raise ValueError("FleetJointEnv.step needs the 'state' and 'step_count' of reset()")
        if action is None:
            raise ValueError(
                f"FleetJointEnv.step needs an 'action': a joint action in 0 … {2**self.n_agents - 1}"
            )
        action = action.reshape(-1).long().cpu()
        if bool(((action < 0) | (action >= 2**self.n_agents)).any()):
            raise ValueError(f"joint actions must lie in 0 … {2**self.n_agents - 1}")
        bits = (action[:, None] >> torch.arange(self.n_agents)) & 1
        res = self.sim.step(self.vehicles[joint.reshape(-1).cpu()], bits, self.rng)
        steps = tensordict.get("step_count").reshape(-1).cpu() + 1
        return self._out(res.state, steps, res.reward.sum(1))
