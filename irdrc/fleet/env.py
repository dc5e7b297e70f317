"""``FleetEnv``: the fleet as a batched TorchRL multi-agent env (MODEL.md § C).

TorchRL's multi-agent conventions (as its VMAS wrapper): the agents' entries under the group key
``"agents"`` with shape [*batch, N] — each agent's ``observation`` (``OBSERVE``: by default its
own d, c, v, m and the shared r, w, as the single-vehicle env's observation), ``action`` (0 comm,
1 radar), ``reward`` [*batch, N, 1], and the per-step signals ``event``, ``missed``,
``detected_by_other``, ``granted``, ``denied``, ``sent``, ``dropped`` — and the shared entries at
the root: ``state`` (the exact fleet model's joint index, for exact scoring, where the exact model
reaches), ``vehicle_state`` [*batch, N] (each vehicle's single-vehicle state), ``step_count`` and
``done`` / ``terminated`` / ``truncated`` (episodes end by truncation at the horizon).
``group_map`` is ``{"agents": ["vehicle_1", …]}``.
"""

from __future__ import annotations

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Bounded, Categorical, Composite, Unbounded
from torchrl.envs import EnvBase

from irdrc.core.env import checked_actions, fresh_seed, observation_high
from irdrc.fleet.exact import FleetModel, FleetSpec
from irdrc.fleet.sim import FleetDynamics

GROUP = "agents"
"""The key of the agents' entries."""

OBSERVE = ("own", "full")
"""What a vehicle observes: ``own`` — its own d, c, v, m and the shared r, w (the single-vehicle
observation); ``full`` — that, then every other vehicle's d, c, v, m (vehicles i + 1, i + 2, …
cyclically), as if the vehicles shared their states over V2V links."""


def own_columns(params) -> list[int]:
    """The single-vehicle observation's columns that are a vehicle's own (d, c, v, m[, phase])."""
    width = observation_high(params).shape[0]
    return [0, 1, *range(4, width)]


def fleet_observation(obs: torch.Tensor, own: list[int], observe: str) -> torch.Tensor:
    """Each vehicle's observation [..., N, W′] from the vehicles' single-vehicle observations
    [..., N, W] (``OBSERVE``)."""
    if observe == "own":
        return obs
    mine = obs[..., own]
    n = obs.shape[-2]
    others = [mine.roll(-k, dims=-2) for k in range(1, n)]  # vehicle (i + k) mod N at row i
    return torch.cat([obs, *others], -1)


def fleet_observation_high(params, n: int, observe: str) -> torch.Tensor:
    """[W′] the largest value of each entry of ``fleet_observation``."""
    high = observation_high(params)
    if observe == "own":
        return high
    return torch.cat([high, *([high[own_columns(params)]] * (n - 1))])


SIGNALS = ("event", "missed", "detected_by_other", "granted", "denied")
"""Per-agent boolean signals of a step (with ``sent`` and ``dropped``, int64)."""


def done_spec(rows: int, dev: torch.device | str) -> Composite:
    """The done / terminated / truncated flags of ``rows`` env rows (one per row)."""
    flag = Categorical(2, shape=(rows, 1), dtype=torch.bool, device=dev)
    return Composite(
        done=flag.clone(),
        terminated=flag.clone(),
        truncated=flag.clone(),
        shape=(rows,),
        device=dev,
    )


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


class FleetEnv(EnvBase):
    """A batch of fleets (see the module docstring).

    Args:
        spec: the fleet (``FleetSpec``), or a built ``FleetModel``.
        batch_size: fleets stepped together (one dimension).
        device: the device of the tensors.
        seed: the generator's seed (None: a fresh one).
        observe: ``own`` or ``full`` (``OBSERVE``).
    """

    def __init__(
        self,
        spec: FleetSpec | FleetModel | None = None,
        batch_size: int | tuple | list | torch.Size = (1,),
        device: torch.device | str = "cpu",
        seed: int | None = None,
        observe: str = "own",
    ) -> None:
        if observe not in OBSERVE:
            raise ValueError(f"observe={observe!r} must be one of {', '.join(OBSERVE)}")
        self.observe = observe
        if isinstance(batch_size, int):
            batch_size = (batch_size,)
        batch_size = torch.Size(batch_size)
        if len(batch_size) != 1 or batch_size[0] < 1:
            raise ValueError(f"batch_size={list(batch_size)} must be one positive dimension")
        super().__init__(device=device, batch_size=batch_size)
        self.model = spec if isinstance(spec, FleetModel) else FleetModel(spec or FleetSpec())
        self.sim = FleetDynamics(self.model)
        self.n_agents = self.model.N
        self.group_map = {GROUP: [f"vehicle_{i + 1}" for i in range(self.n_agents)]}
        self.rng = torch.Generator()
        self._make_specs()
        self.set_seed(seed if seed is not None else fresh_seed())

    def _make_specs(self) -> None:
        B, N, dev = self.batch_size[0], self.n_agents, self.device
        params = self.model.spec.vehicle
        high = fleet_observation_high(params, N, self.observe)
        self.own = own_columns(params)
        width = high.shape[0]
        cap = int(self.sim.dyn.capacity.max())
        agent = (B, N)
        signals = {k: Categorical(2, shape=agent, dtype=torch.bool, device=dev) for k in SIGNALS}
        self.observation_spec = Composite(
            {
                GROUP: Composite(
                    observation=Bounded(
                        low=torch.zeros(B, N, width, device=dev),
                        high=high.to(dev).expand(B, N, width).clone(),
                        shape=(B, N, width),
                        dtype=torch.float32,
                        device=dev,
                    ),
                    sent=Bounded(0, cap, shape=agent, dtype=torch.int64, device=dev),
                    dropped=Unbounded(shape=agent, dtype=torch.int64, device=dev),
                    **signals,
                    shape=agent,
                    device=dev,
                ),
                **(
                    {
                        "state": Categorical(
                            self.model.num_states, shape=(B,), dtype=torch.int64, device=dev
                        )
                    }
                    if self.model.exact
                    else {}
                ),
                "vehicle_state": Categorical(
                    self.model.single.num_states, shape=agent, dtype=torch.int64, device=dev
                ),
                "step_count": Bounded(
                    0, params.env.horizon, shape=(B, 1), dtype=torch.int64, device=dev
                ),
            },
            shape=(B,),
            device=dev,
        )
        self.action_spec = Composite(
            {
                GROUP: Composite(
                    action=Categorical(2, shape=agent, dtype=torch.int64, device=dev),
                    shape=agent,
                    device=dev,
                )
            },
            shape=(B,),
            device=dev,
        )
        self.reward_spec = Composite(
            {
                GROUP: Composite(
                    reward=Unbounded(shape=(B, N, 1), dtype=torch.float32, device=dev),
                    shape=agent,
                    device=dev,
                )
            },
            shape=(B,),
            device=dev,
        )
        self.done_spec = done_spec(B, dev)

    def _set_seed(self, seed: int | None) -> None:
        self.rng.manual_seed(int(seed if seed is not None else fresh_seed()))

    def _out(self, states: torch.Tensor, steps: torch.Tensor, res=None) -> TensorDict:
        B, N = self.batch_size[0], self.n_agents
        obs = self.sim.dyn.obs[states.reshape(-1)].reshape(B, N, -1)
        obs = fleet_observation(obs, self.own, self.observe)
        agents: dict[str, torch.Tensor] = {"observation": obs.to(self.device)}
        falses = torch.zeros(B, N, dtype=torch.bool)
        zeros = torch.zeros(B, N, dtype=torch.int64)
        if res is None:
            agents.update(dict.fromkeys(SIGNALS, falses), sent=zeros, dropped=zeros)
        else:
            agents.update(
                event=res.event,
                missed=res.missed,
                detected_by_other=res.by_other,
                granted=res.granted,
                denied=res.denied,
                sent=res.sent,
                dropped=res.dropped,
                reward=res.reward.to(torch.float32).unsqueeze(-1),
            )
        truncated = (steps >= self.model.spec.vehicle.env.horizon).reshape(B, 1)
        root = {"state": self.sim.fleet_index(states)} if self.model.exact else {}
        return TensorDict(
            {
                GROUP: TensorDict(agents, batch_size=(B, N)),
                **root,
                "vehicle_state": states,
                "step_count": steps.reshape(B, 1),
                "done": truncated,
                "terminated": torch.zeros_like(truncated),
                "truncated": truncated,
            },
            batch_size=(B,),
            device=self.device,
        )

    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs) -> TensorDict:
        B, m = self.batch_size[0], self.model
        rw = torch.randint(0, m.RW, (B, 1), generator=self.rng)
        x = torch.randint(0, m.X, (B, self.n_agents), generator=self.rng)
        states = m.index[rw.expand(B, self.n_agents), x]  # uniform over the joint states
        return self._out(states, torch.zeros(B, dtype=torch.int64))

    def _step(self, tensordict: TensorDictBase) -> TensorDict:
        states = tensordict.get("vehicle_state", None)
        action = tensordict.get((GROUP, "action"), None)
        if states is None or tensordict.get("step_count", None) is None:
            raise ValueError(
                "FleetEnv.step needs the 'vehicle_state' and 'step_count' that reset() returns: "
                "call env.reset() first"
            )
        if action is None:
            raise ValueError(
                f"FleetEnv.step needs ('{GROUP}', 'action'): per vehicle 0 (communication) or 1 "
                "(radar)"
            )
        B, N = self.batch_size[0], self.n_agents
        action = checked_actions(action.reshape(-1)).reshape(B, N)
        res = self.sim.step(states.reshape(B, N).cpu(), action.cpu(), self.rng)
        steps = tensordict.get("step_count").reshape(-1).cpu() + 1
        return self._out(res.state, steps, res)


class FleetRowsEnv(EnvBase):
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
        self.model = spec if isinstance(spec, FleetModel) else FleetModel(spec or FleetSpec())
        self.sim = FleetDynamics(self.model)
        self.dynamics = self.sim.dyn
        self.agent_index = bool(agent_index)
        N, single = self.model.N, self.sim.dyn.obs
        if self.agent_index:  # every (vehicle, state) pair: the vehicle's one-hot index appended
            eye = torch.eye(N, dtype=single.dtype).repeat_interleave(single.shape[0], 0)
            self.obs_table = torch.cat([single.repeat(N, 1), eye], 1)  # [N·S, width + N]
        else:
            self.obs_table = single
        self.fleets, self.n_agents = int(fleets), self.model.N
        if self.fleets < 1:
            raise ValueError(f"fleets={fleets} must be >= 1")
        rows = self.fleets * self.n_agents
        super().__init__(device=device, batch_size=torch.Size([rows]))
        self.params = self.model.spec.vehicle
        self.rng = torch.Generator()
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

    @property
    def observation_table(self) -> torch.Tensor:
        """Every observation a row can see, one per ``num_states`` (greedy tables read it)."""
        return self.obs_table

    def _set_seed(self, seed: int | None) -> None:
        self.rng.manual_seed(int(seed if seed is not None else fresh_seed()))

    def _out(self, states: torch.Tensor, steps: torch.Tensor, reward=None) -> TensorDict:
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

    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs) -> TensorDict:
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


class FleetJointEnv(EnvBase):
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
        self.model = spec if isinstance(spec, FleetModel) else FleetModel(spec or FleetSpec())
        self.model.check_exact()
        self.sim = FleetDynamics(self.model)
        self.dynamics = self.sim.dyn
        self.fleets, self.n_agents = int(fleets), self.model.N
        if self.fleets < 1:
            raise ValueError(f"fleets={fleets} must be >= 1")
        super().__init__(device=device, batch_size=torch.Size([self.fleets]))
        self.params = params = self.model.spec.vehicle
        self.own = own_columns(params)
        self.vehicles = self.model.vehicle_states()  # [S, N]
        self.obs_table = self._observe(self.vehicles)
        high = fleet_observation_high(params, self.n_agents, "full")
        set_row_specs(self, high, self.model.num_states, 2**self.n_agents, params.env.horizon)
        self.rng = torch.Generator()
        self.set_seed(seed if seed is not None else fresh_seed())

    @property
    def num_states(self) -> int:
        """The fleet's joint states (the observation table's rows)."""
        return self.model.num_states

    @property
    def observation_table(self) -> torch.Tensor:
        """[S, W] the observation of every joint state (greedy tables read it)."""
        return self.obs_table

    def _observe(self, vehicle_states: torch.Tensor) -> torch.Tensor:
        obs = self.sim.dyn.obs[vehicle_states]  # [n, N, W]
        return fleet_observation(obs, self.own, "full")[:, 0]

    def _set_seed(self, seed: int | None) -> None:
        self.rng.manual_seed(int(seed if seed is not None else fresh_seed()))

    def _out(self, states: torch.Tensor, steps: torch.Tensor, reward=None) -> TensorDict:
        joint = self.sim.fleet_index(states)
        return row_output(
            self.obs_table[joint], joint, steps, self.params.env.horizon, self.device, reward
        )

    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs) -> TensorDict:
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
