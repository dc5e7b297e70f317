"""DQN on one stream (``learner=dqn``, ``learner=dqn_paper``): TorchRL's MLP and replay buffer, the
update written out below, in TorchRL's component order — model → exploration → buffer → loss →
target → optimiser; the loop is the vehicle's own stream (``irdrc.online.loop``).

A vehicle's steps come one at a time, and its observation is one of S states' (a few hundred on
most scenarios), so the parts are driven the way one stream allows:

- the vehicle acts ε-greedily on the online network's greedy table, one look-up per step;
- its steps go into the replay as they come; every ``update_every`` steps, ``updates`` gradient
  updates on ``batch_size`` sampled transitions follow;
- an update evaluates the network once on the S observations and reads every sampled transition's
  values from that pass, so a sample costs the same whatever its size. Above ``FULL_PASS_STATES``
  states (``env=large``: 100 800) it evaluates only the states its sample names, and the vehicle's
  greedy action comes from a pass on its own state until a policy over every state is asked for
  (the ledger's, once an episode). The TD(0) target is double
  DQN's: r − r̄ + γ·Q_target(s′, argmax_a Q(s′, a)) (``double_dqn``; else the target's own
  maximum), r̄ the reward centre (below);
- the rewards are centred: r̄, the collected rewards' average, moves after every burst by (1 − γ)
  times the mean greedy value of the states just visited, so the values the network fits stay near
  zero (Naik et al. 2024; ``irdrc.agents.offpolicy.RewardCenter``).

TorchRL's ``DQNLoss`` would do the same update through three parameter swaps of a functional copy of
the network: about 5 ms a call here, which at one update every 16 env steps already holds a stream
to ~1 500 env steps/s. Written out, an update of 2 048 sampled transitions costs about a
millisecond (``seconds_update`` over ``updates`` in a run's summary.json).
"""

from __future__ import annotations

import copy
import random
import time
from typing import Any

import torch
from torchrl.data import LazyTensorStorage, ReplayBuffer
from torchrl.data.replay_buffers.samplers import RandomSampler

from irdrc.agents.offpolicy import RewardCenter, make_body
from irdrc.core.dynamics import observation_high
from irdrc.core.params import Params
from irdrc.core.states import decode_state
from irdrc.core.stream import Step
from irdrc.online.configs import StreamDQNConfig
from irdrc.online.loop import StreamLearner
from irdrc.online.qlearning import tuple_state

STORE_EVERY = 64
"""Steps are written into the replay at least this many at a time (a write costs about as much
whatever its size): a transition waits at most this many steps before it can be sampled."""

FULL_PASS_STATES = 4096
"""Up to this many states an update passes every state's observation through the network (a few
tenths of a millisecond at a few hundred states) and the vehicle acts on that pass's table; above
it, where a pass over every state costs more than one over a sample's at most 2 × ``batch_size``
states (53 ms an update at 100 800 states), an update passes only the sample's states."""


class StreamDQN(StreamLearner):
    """DQN learning from one vehicle's steps as they come (see the module docstring).

    Args:
        cfg: the profile (``irdrc.online.configs.DQN`` or ``DQN_PAPER``).
        params: the scenario (only its observation space is read: the state's levels).
        seed: seeds torch (the network's initial weights, the replay's draws) and the exploration.
    """

    def __init__(self, cfg: StreamDQNConfig, params: Params, seed: int = 0) -> None:
        self.cfg, self.name = cfg, cfg.name
        torch.manual_seed(seed)
        self.num_states = S = params.env.num_states
        self.full = S <= FULL_PASS_STATES
        self.decay_steps = cfg.lr_decay_episodes * params.env.horizon

        # 1. model: every state's observation, scaled → MLP → one Q-value per action
        self.obs = decode_state(torch.arange(S), params.env.factor_levels).to(torch.float32)
        self.qnet = make_body(observation_high(params), cfg.network, 2)
        # 2. exploration: ε-greedy on the greedy table, its own stream of uniforms
        self.rng = random.Random(seed + 7919)
        self.eps = cfg.epsilon(0)
        # 3. buffer: uniform replay of the vehicle's transitions, rows (s, a, r, s′)
        self.buffer = ReplayBuffer(
            storage=LazyTensorStorage(cfg.buffer_size),
            sampler=RandomSampler(),
            batch_size=cfg.batch_size,
        )
        # 4. loss: TD(0) in l2 on centred rewards (``td_loss``)
        self.center = RewardCenter(cfg.reward_centering)
        # 5. target: a copy of the network, Polyak-averaged after every update
        self.target = copy.deepcopy(self.qnet).requires_grad_(False)
        self._online_params = [p.data for p in self.qnet.parameters()]
        self._target_params = [p.data for p in self.target.parameters()]
        # 6. optimiser: Adam, its learning rate annealed over ``lr_decay_episodes`` episodes
        self.optimizer = torch.optim.Adam(self.qnet.parameters(), lr=cfg.lr, fused=True)

        self.log: list[tuple[int, int, float, int]] = []  # every transition, in order
        self.stored = 0  # transitions of ``log`` in the replay
        self.steps = 0
        self.updates = 0
        self.last_loss = float("nan")
        self.seconds = {"replay_write": 0.0, "replay_sample": 0.0, "update": 0.0}
        # the last update's full pass (None above FULL_PASS_STATES, where no update makes one)
        self.last_values = self._values(self.qnet) if self.full else None
        self.table: list[int] | None = self._last_table()

    # -- acting -----------------------------------------------------------------------------------

    def begin_episode(self, episode: int) -> None:
        self.eps = self.cfg.epsilon(episode)

    def act(self, state: int) -> int:
        if self.eps > 0 and self.rng.random() < self.eps:
            return self.rng.randrange(2)
        if self.table is None:  # above FULL_PASS_STATES, between two full tables
            with torch.no_grad():
                return int(self.qnet(self.obs[state]).argmax())
        return self.table[state]

    def observe(self, state: int, action: int, step: Step) -> None:
        self.log.append((state, action, step.reward, step.state))
        self.steps += 1
        if self.steps % self.cfg.update_every == 0:
            if self.steps - self.stored >= STORE_EVERY or not self.stored:
                self._store()
            if len(self.buffer) >= max(self.cfg.warmup_steps, 1):
                self._learn()

    # -- learning ---------------------------------------------------------------------------------

    def _store(self) -> None:
        """The transitions not yet stored into the replay (and the reward centre)."""
        t0 = time.perf_counter()
        rows = torch.tensor(self.log[self.stored :], dtype=torch.float64)
        self.stored = len(self.log)
        self.center.update(rows[:, 2])
        self.buffer.extend(rows)
        self.seconds["replay_write"] += time.perf_counter() - t0

    def td_loss(self, sample: torch.Tensor) -> torch.Tensor:
        """The double-DQN TD(0) loss of a replay sample (rows s, a, r, s′), from one pass over
        every state (over the sample's states above ``FULL_PASS_STATES``): the mean over the
        sample of (Q(s, a) − target)², summed per (state, action) first — the same gradient, with
        no per-sample indexing in the backward pass."""
        s, a, s2 = (sample[:, i].long() for i in (0, 1, 3))
        obs = self.obs
        if not self.full:  # the sample's states alone, s and s′ as rows of that pass
            rows, inverse = torch.unique(torch.cat([s, s2]), return_inverse=True)
            obs, s, s2 = obs[rows], inverse[: len(s)], inverse[len(s) :]
        q = self.qnet(obs)  # [S, 2] (or [rows, 2]), recorded
        with torch.no_grad():
            if self.full:
                self.last_values = q.detach()
            target_next = self.target(obs)[s2]
            # double DQN: the online network picks the next action, the target values it
            pick = (q[s2] if self.cfg.double_dqn else target_next).argmax(-1, keepdim=True)
            next_value = target_next.gather(1, pick).squeeze(1)
            target = self.center.centred(sample[:, 2].float()) + self.cfg.gamma * next_value
            at = s * 2 + a
            n = torch.zeros(q.numel()).index_add_(0, at, torch.ones_like(target))
            total = torch.zeros(q.numel()).index_add_(0, at, target)
        # Σ_i (q − t_i)² = n·q² − 2·q·Σ t_i + Σ t_i², per (state, action)
        flat = q.reshape(-1)
        square = float((target.double() ** 2).sum())
        return ((n * flat * flat - 2.0 * flat * total).sum() + square) / target.numel()

    def _learn(self) -> None:
        """A burst of updates on replay samples, then the acting table anew."""
        cfg = self.cfg
        progress = min(1.0, self.steps / self.decay_steps)
        for group in self.optimizer.param_groups:
            group["lr"] = cfg.lr + (cfg.lr_end - cfg.lr) * progress
        for _ in range(cfg.updates):
            t0 = time.perf_counter()
            sample = self.buffer.sample()
            t1 = time.perf_counter()
            loss = self.td_loss(sample)
            self.optimizer.zero_grad(set_to_none=True)
            loss.backward()
            if cfg.max_grad_norm > 0:
                torch.nn.utils.clip_grad_norm_(
                    self.qnet.parameters(), cfg.max_grad_norm, foreach=True
                )
            self.optimizer.step()
            torch._foreach_lerp_(self._target_params, self._online_params, cfg.tau)
            self.last_loss = float(loss.detach())
            self.updates += 1
            self.seconds["replay_sample"] += t1 - t0
            self.seconds["update"] += time.perf_counter() - t1
        recent = torch.tensor([r[0] for r in self.log[-cfg.update_every :]])
        if self.last_values is not None:  # full: the last update's pass (one step behind)
            values = self.last_values
            self.table = values.argmax(-1).tolist()
            recent_values = values[recent]
        else:
            self.table = None  # a whole table only when asked for (``_table``)
            with torch.no_grad():
                recent_values = self.qnet(self.obs[recent])
        # r̄ follows the values: the states just visited are valued near zero on average
        self.center.follow(float(recent_values.max(-1).values.double().mean()), cfg.gamma)

    def _last_table(self) -> list[int] | None:
        """The greedy table of the last full pass (None where there is none)."""
        return None if self.last_values is None else self.last_values.argmax(-1).tolist()

    def _values(self, net: torch.nn.Module) -> torch.Tensor:
        """[S, 2] ``net``'s action values of every state (no gradient)."""
        with torch.no_grad():
            return net(self.obs)

    def values(self, online: bool = False) -> torch.Tensor:
        """[S, 2] the online or the target network's action values."""
        return self._values(self.qnet if online else self.target)

    # -- what the loop reads ----------------------------------------------------------------------

    def end_episode(self, episode: int) -> dict[str, float]:
        return {"epsilon": self.eps, "loss": self.last_loss, "buffer": len(self.buffer)}

    def info(self) -> dict[str, Any]:
        return {f"seconds_{k}": v for k, v in self.seconds.items()}

    def _table(self) -> list[int]:
        """The acting table (the online network's greedy action in every state), made from one
        pass over every state where the last burst left none."""
        if self.table is None:
            self.table = self.values(online=True).argmax(-1).tolist()
        return self.table

    def greedy(self) -> torch.Tensor:
        if self.cfg.policy_network == "online":
            return torch.tensor(self._table())
        return self.values(online=False).argmax(-1)

    def behaviour(self) -> torch.Tensor:
        probs = torch.nn.functional.one_hot(torch.tensor(self._table()), 2).to(torch.float64)
        return (1.0 - self.eps) * probs + self.eps / 2.0

    def state_dict(self) -> dict[str, Any]:
        log = torch.tensor([(s, a, s2) for s, a, _, s2 in self.log], dtype=torch.int64)
        return {
            "qnet": self.qnet.state_dict(),
            "target": self.target.state_dict(),
            "optimizer": self.optimizer.state_dict(),
            "log": log.reshape(-1, 3),
            "rewards": torch.tensor([r for _, _, r, _ in self.log], dtype=torch.float32),
            "stored": self.stored,
            "steps": self.steps,
            "updates": self.updates,
            "last_loss": self.last_loss,
            "center": self.center.state(),
            "last_values": self.last_values,
            "rng": self.rng.getstate(),
            "torch_rng": torch.get_rng_state(),
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.qnet.load_state_dict(state["qnet"])
        self.target.load_state_dict(state["target"])
        self.optimizer.load_state_dict(state["optimizer"])
        log, rewards = state["log"].tolist(), state["rewards"].tolist()
        self.log = [(s, a, r, s2) for (s, a, s2), r in zip(log, rewards, strict=True)]
        # the replay refilled with the same transitions in the same order
        stored, self.stored = int(state["stored"]), 0
        pending, self.log = self.log[stored:], self.log[:stored]
        if stored:
            self._store()
        self.log += pending
        self.center = RewardCenter(self.cfg.reward_centering)
        self.center.load(state["center"])
        self.steps = int(state["steps"])
        self.updates = int(state["updates"])
        self.last_loss = float(state["last_loss"])
        self.rng.setstate(tuple_state(state["rng"]))
        torch.set_rng_state(state["torch_rng"])
        self.last_values = state["last_values"] if self.full else None
        self.table = self._last_table()


def saved_greedy(
    learner: dict[str, Any], cfg: StreamDQNConfig, trained: Params, params: Params
) -> torch.Tensor:
    """[S] the greedy table, on the states of ``params``, of a saved run's network (its
    ``policy_network``: the target, whose table is the one its run scored; or the online one, as
    saved: one update past the acting table its run scored last), each state's levels scaled as in
    its training on ``trained``, ties to comm. ``learner`` is the run's ``state_dict``."""
    net = make_body(observation_high(trained), cfg.network, 2)
    net.load_state_dict(learner["qnet" if cfg.policy_network == "online" else "target"])
    obs = decode_state(torch.arange(params.env.num_states), params.env.factor_levels)
    with torch.no_grad():
        return net(obs.to(torch.float32)).argmax(-1)
