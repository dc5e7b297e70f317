"""``FleetEnv``: the fleet as a batched TorchRL multi-agent env (MODEL.md § C).

TorchRL's multi-agent conventions (as its VMAS and PettingZoo wrappers, and BenchMARL's tasks):
the agents' entries under the group key ``"agents"`` with shape [*batch, N] — each agent's
``observation`` (``OBSERVE``: by default its own d, c, v, m and the shared r, w, as the
single-vehicle env's observation), ``action`` (0 comm, 1 radar), ``reward`` [*batch, N, 1]
(``REWARDS``: each vehicle's own, or the team's — the fleet's sum, the same for every vehicle — for
a cooperative learner), and the per-step signals ``event``, ``missed``, ``detected_by_other``,
``granted``, ``denied``, ``sent``, ``dropped`` — and the shared entries at the root: ``state`` (a
centralised critic's features: the shared r, w, then every vehicle's own d, c, v, m, as floats,
the same layout at every N — ``critic_state``), ``joint_index`` (the exact fleet model's joint
state, for exact scoring, where the exact model reaches), ``vehicle_state`` [*batch, N] (each
vehicle's single-vehicle state), ``step_count`` and ``done`` / ``terminated`` / ``truncated``
(episodes end by truncation at the horizon). ``group_map`` is ``{"agents": ["vehicle_1", …]}``.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Bounded, Categorical, Composite, Unbounded
from torchrl.envs import EnvBase

from irdrc.core.dynamics import checked_actions, fresh_seed, observation_high
from irdrc.fleet.model import FleetModel
from irdrc.fleet.sim import FleetDynamics
from irdrc.fleet.spec import OBSERVE, FleetSpec

if TYPE_CHECKING:
    from irdrc.core.params import Params

GROUP = "agents"
"""The key of the agents' entries."""


def own_columns(params: Params) -> list[int]:
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


def fleet_observation_high(params: Params, n: int, observe: str) -> torch.Tensor:
    """[W′] the largest value of each entry of ``fleet_observation``."""
    high = observation_high(params)
    if observe == "own":
        return high
    return torch.cat([high, *([high[own_columns(params)]] * (n - 1))])


def shared_columns() -> list[int]:
    """The single-vehicle observation's columns every vehicle shares (r, w)."""
    return [2, 3]


def critic_state(obs: torch.Tensor, own: list[int]) -> torch.Tensor:
    """A centralised critic's features [..., 2 + N·len(own)] from the vehicles' single-vehicle
    observations [..., N, W]: the shared r, w, then each vehicle's own columns in vehicle order."""
    shared = obs[..., 0, shared_columns()]
    return torch.cat([shared, obs[..., own].flatten(-2)], -1)


def critic_state_high(params: Params, n: int) -> torch.Tensor:
    """[2 + N·len(own)] the largest value of each entry of ``critic_state``."""
    high = observation_high(params)
    return torch.cat([high[shared_columns()], *([high[own_columns(params)]] * n)])


REWARDS = ("own", "team")
"""``FleetEnv``'s ``("agents", "reward")``: each vehicle's own reward, or the team's (the fleet's sum,
given to every vehicle)."""

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


class FleetEnv(EnvBase):
    """A batch of fleets (see the module docstring).

    Args:
        spec: the fleet (``FleetSpec``), or a built ``FleetModel``.
        batch_size: fleets stepped together (one dimension).
        device: the device of the tensors.
        seed: the generator's seed (None: a fresh one).
        observe: ``own`` or ``full`` (``OBSERVE``).
        reward: ``own`` or ``team`` (``REWARDS``).
    """

    def __init__(
        self,
        spec: FleetSpec | FleetModel | None = None,
        batch_size: int | tuple[int, ...] | list[int] | torch.Size = (1,),
        device: torch.device | str = "cpu",
        seed: int | None = None,
        observe: str = "own",
        reward: str = "own",
    ) -> None:
        if observe not in OBSERVE:
            raise ValueError(f"observe={observe!r} must be one of {', '.join(OBSERVE)}")
        if reward not in REWARDS:
            raise ValueError(f"reward={reward!r} must be one of {', '.join(REWARDS)}")
        self.observe, self.reward = observe, reward
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
        critic = critic_state_high(params, N)
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
                "state": Bounded(
                    low=torch.zeros(B, critic.shape[0], device=dev),
                    high=critic.to(dev).expand(B, -1).clone(),
                    shape=(B, critic.shape[0]),
                    dtype=torch.float32,
                    device=dev,
                ),
                **(
                    {
                        "joint_index": Categorical(
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

    def _out(self, states: torch.Tensor, steps: torch.Tensor, res: Any = None) -> TensorDict:
        B, N = self.batch_size[0], self.n_agents
        single = self.sim.dyn.obs[states.reshape(-1)].reshape(B, N, -1)
        obs = fleet_observation(single, self.own, self.observe)
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
                reward=self._reward(res.reward).to(torch.float32).unsqueeze(-1),
            )
        truncated = (steps >= self.model.spec.vehicle.env.horizon).reshape(B, 1)
        root = {"joint_index": self.sim.fleet_index(states)} if self.model.exact else {}
        return TensorDict(
            {
                GROUP: TensorDict(agents, batch_size=(B, N)),
                "state": critic_state(single, self.own).to(self.device),
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

    def _reward(self, reward: torch.Tensor) -> torch.Tensor:
        """[B, N] each vehicle's reward as ``reward`` asks (``team``: the fleet's sum, to each)."""
        if self.reward == "team":
            return reward.sum(-1, keepdim=True).expand_as(reward)
        return reward

    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs: Any) -> TensorDict:
        B = self.batch_size[0]
        states = self.sim.start(B, self.rng)  # uniform over the joint states
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
