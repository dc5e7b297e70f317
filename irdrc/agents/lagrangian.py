"""A Lagrangian DQN for the constrained problem (MODEL.md § A): the most of an objective subject to
miss detection ≤ a target, learned from interaction alone.

DQN's machinery (``irdrc.agents.offpolicy``: the env rows and their ε ladder, replay, TorchRL's
collector, target updater and the shared loop) with two value heads per action, learned by TD(0)
from the per-step signals the env writes under ``("next", key)``:

- Q_J(s, a): the objective (``sent`` for throughput, ``reward``, or ``capacity``);
- Q_C(s, a): the constraint cost c = missed − m*·event, whose long-run average is ≤ 0 exactly when
  miss detection ≤ m* (MODEL.md § A).

The agent acts greedily on Q_J − μ·Q_C: the per-step Lagrangian signal J − μ·(missed − m*·event),
with the multiplier μ ≥ 0 adapted by dual ascent from the learner's own measured miss detection
(missed / event over its recent experience). Keeping the two heads apart keeps both signals at
their own scale whatever μ is, and gives the greedy policy for *every* μ from one network: action
comm wins in state s while μ < ΔJ(s)/ΔC(s) (Δ = comm − radar), so as μ grows the greedy table
changes one state at a time at those breakpoints.

The final policy is chosen the way a vehicle could, by measured rates: along that path of tables,
and along the states ranked by their measured data per missed event in comm
(``irdrc.agents.policy_search``); it may randomise in one state, as the exact LP optimum does. The
exact model only scores (``history``, the final metrics).
"""

from __future__ import annotations

import math
import time
from typing import Any

import torch
from tensordict import TensorDict, TensorDictBase, TensorDictParams
from tensordict.nn import TensorDictSequential
from torch import nn
from torchrl.modules import QValueActor
from torchrl.objectives import LossModule

from irdrc.agents.base import Hooks, RunContext, RunRecord
from irdrc.agents.configs import LagrangianConfig
from irdrc.agents.loop import Learner, TrainingLoop, start_frames
from irdrc.agents.offpolicy import (
    STORED_KEYS,
    CenteredRewards,
    PolyakUpdate,
    RewardCenter,
    clip_and_step,
    greedy_table,
    make_buffer,
    make_collector,
    make_exploration,
    make_mlp,
    make_optimizer,
    policy_view,
)
from irdrc.agents.policy_search import FinalPolicySearch
from irdrc.core.env import DFRCEnv
from irdrc.core.params import Params

OBJECTIVE_KEYS = {"throughput": "sent", "avg_reward": "reward", "link_capacity": "capacity"}
"""The env's per-step signal (under ``("next", key)``) for each objective of ``irdrc.core.cmdp``."""


class TwoHeads(nn.Module):
    """Observation → [..., 2, 2]: (objective, cost) heads × (comm, radar) actions."""

    def __init__(self, body: nn.Module) -> None:
        super().__init__()
        self.body = body

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        out = self.body(obs)
        return out.reshape(*out.shape[:-1], 2, 2)


class Lagrangian(nn.Module):
    """Q_J − μ·Q_C per action, μ a buffer the dual ascent sets: the acting network's values."""

    mu: torch.Tensor

    def __init__(self, heads: TwoHeads, mu: float) -> None:
        super().__init__()
        self.heads = heads
        self.register_buffer("mu", torch.tensor(float(mu)))

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        q = self.heads(obs)
        return q[..., 0, :] - self.mu * q[..., 1, :]


class LagrangianDQNLoss(LossModule):
    """TD(0) on both heads: the next action is greedy on Q_J − μ·Q_C in the online network (double
    DQN, ``double_dqn``) or in the target network, and valued by the target network's heads. Writes
    ``td_error`` (|δ_J| + |δ_C|) for prioritised replay; the loss is the (importance-weighted) mean
    of δ_J² + δ_C². The objective signal arrives centred when reward
    centering is on (``TrainingLoop`` centres it in every sample)."""

    value_network: TwoHeads
    value_network_params: TensorDictParams
    target_value_network_params: TensorDictParams

    def __init__(
        self,
        heads: TwoHeads,
        mu: torch.Tensor,
        *,
        gamma: float,
        objective_key: str,
        target_miss: float,
        double_dqn: bool = True,
    ) -> None:
        super().__init__()
        self.convert_to_functional(heads, "value_network", create_target_params=True)
        self.mu = mu
        self.gamma = float(gamma)
        self.objective_key = objective_key
        self.target_miss = float(target_miss)
        self.double_dqn = bool(double_dqn)

    def signals(self, td: TensorDictBase) -> torch.Tensor:
        """[B, 2] per-step (objective, cost) of a batch of transitions."""
        nxt = td["next"]
        j = nxt[self.objective_key].reshape(-1).to(torch.float32)
        c = nxt["missed"].reshape(-1).float() - self.target_miss * nxt["event"].reshape(-1).float()
        return torch.stack([j, c], -1)

    def forward(self, td: TensorDictBase) -> TensorDict:
        obs, nobs = td["observation"], td["next", "observation"]
        action = td["action"].reshape(-1).long()
        with self.value_network_params.to_module(self.value_network):
            q = self.value_network(obs)  # [B, 2, 2]
        taken = q.gather(-1, action.view(-1, 1, 1).expand(-1, 2, 1)).squeeze(-1)  # [B, 2]
        with torch.no_grad():
            with self.target_value_network_params.to_module(self.value_network):
                qt = self.value_network(nobs)
            qn = qt
            if self.double_dqn:
                with self.value_network_params.data.to_module(self.value_network):
                    qn = self.value_network(nobs)
            best = (qn[:, 0] - self.mu * qn[:, 1]).argmax(-1)
            nxt = qt.gather(-1, best.view(-1, 1, 1).expand(-1, 2, 1)).squeeze(-1)
            terminated = td["next", "terminated"].reshape(-1, 1).float()
            target = self.signals(td) + self.gamma * (1.0 - terminated) * nxt
        delta = taken - target
        per = delta.pow(2).sum(-1)
        td.set("td_error", delta.detach().abs().sum(-1), inplace=False)
        if "priority_weight" in td:
            per = per * td["priority_weight"].reshape(-1)
        return TensorDict(loss=per.mean())


def make_network(env: DFRCEnv, cfg: LagrangianConfig) -> tuple[TwoHeads, Lagrangian, QValueActor]:
    """The two heads, their Lagrangian combination (holding μ) and the acting Q-value actor
    (greedy on Q_J − μ·Q_C)."""
    heads = TwoHeads(make_mlp(env, cfg.dqn.network, 4))
    combined = Lagrangian(heads, cfg.mu_init)
    actor = QValueActor(module=combined, in_keys=["observation"], spec=env.action_spec_unbatched)
    return heads, combined, actor


def heads_table(heads: TwoHeads, env: DFRCEnv) -> torch.Tensor:
    """[S, 2, 2] (objective, cost) × (comm, radar) values of every state."""
    with torch.no_grad():
        return heads(env.dynamics.obs).double().cpu()


def final_policy(
    q: torch.Tensor, params: Params, mu: float, cfg: LagrangianConfig, seed: int
) -> tuple[torch.Tensor, dict[str, Any]]:
    """The final [S, 2] policy from the learned heads ``q`` [S, 2, 2] and the trained multiplier
    ``mu``, and facts about its search (``irdrc.agents.policy_search.FinalPolicySearch``)."""
    signal = OBJECTIVE_KEYS[cfg.objective]
    return FinalPolicySearch(q, params, mu, cfg.target_miss, signal, cfg.search, seed).run()


class Multiplier:
    """The multiplier μ and the learner's own measured constraint: missed / event on the steps
    where it acted greedily (exploration's random comm steps would bias it), exponentially averaged
    over ``cost_window_frames``; dual ascent after each batch that learned. Beside it, every
    training step's missed events and events so far: the cumulative miss detection its training
    realised (``cumulative_miss``), what a vehicle learning this way would have missed."""

    def __init__(self, mu: torch.Tensor, cfg: LagrangianConfig) -> None:
        self.mu, self.cfg = mu, cfg
        self.missed = self.events = 0.0
        self.total_missed = self.total_events = 0
        self.measured = math.nan
        self.trace: list[dict[str, float]] = []

    def after_batch(self, data: TensorDictBase, learned: bool) -> dict[str, Any]:
        """Fold a collected batch into the measured miss detection (greedy steps, over about
        ``cost_window_frames``) and, once the learner learns, take one dual step; returns the
        scalars to report."""
        keep = math.exp(-data.numel() / self.cfg.cost_window_frames)
        self.missed *= keep
        self.events *= keep
        if "action_value" in data:
            greedy = data["action"].reshape(-1) == data["action_value"].argmax(-1).reshape(-1)
            self.missed += float((data["next", "missed"].reshape(-1) & greedy).sum())
            self.events += float((data["next", "event"].reshape(-1) & greedy).sum())
        self.measured = self.missed / self.events if self.events > 0 else math.nan
        self.total_missed += int(data["next", "missed"].sum())
        self.total_events += int(data["next", "event"].sum())
        if learned and not math.isnan(self.measured):
            self.mu.fill_(dual_step(float(self.mu), self.measured, data.numel(), self.cfg))
        cumulative = self.total_missed / self.total_events if self.total_events else math.nan
        return {"mu": float(self.mu), "measured_miss": self.measured, "cumulative_miss": cumulative}

    def state(self) -> dict[str, Any]:
        """The multiplier's part of a checkpoint."""
        return {
            "mu": float(self.mu),
            "measured": [self.missed, self.events],
            "cumulative": [self.total_missed, self.total_events],
            "mu_trace": list(self.trace),
        }

    def load(self, resume: dict[str, Any]) -> None:
        """Go on from a checkpoint's ``state``."""
        self.mu.fill_(float(resume["mu"]))
        self.missed, self.events = (float(x) for x in resume["measured"])
        self.total_missed, self.total_events = (int(x) for x in resume.get("cumulative", (0, 0)))
        self.trace = list(resume["mu_trace"])


def train(
    params: Params,
    cfg: LagrangianConfig | None = None,
    *,
    seed: int = 0,
    device: str = "cpu",
    scorer: Any = None,
    eval_every_frames: int = 25_000,
    hooks: Hooks | None = None,
    resume: dict[str, Any] | None = None,
) -> RunRecord:
    """Train the Lagrangian DQN and choose its final (possibly randomised) policy.

    DQN's parts and loop (``irdrc.agents.offpolicy``, ``irdrc.agents.loop``) with two heads.
    ``hooks.on_batch`` gets ``env_steps``, ``episodes``, ``loss``, ``mu`` (the multiplier),
    ``measured_miss`` (M̂), ``buffer``. Each exact evaluation scores the greedy table at the
    current μ (its ``optimality_ratio`` against the reward optimum, as every learner's; the
    constrained recipe reads it against the LP's objective in its ``on_eval`` hook). The record's
    ``policy`` is the final [1, S, 2] policy, ``greedy`` its most likely action, ``info`` the final
    search's facts and ``mu_trace``; ``resume`` goes on from a checkpoint (``state``).
    """
    cfg = cfg or LagrangianConfig()
    dq = cfg.dqn
    torch.manual_seed(seed)
    env = DFRCEnv(params, batch_size=[dq.num_envs], device=device, seed=seed)
    if scorer is None:
        from irdrc.core.exact import exact_scorer

        scorer = exact_scorer(params)
    start = start_frames(resume)

    # Components in DQN's order: model → exploration → collector → buffer → loss → target → optimiser.
    heads, combined, actor = make_network(env, cfg)
    exploration = make_exploration(env, dq)
    collector = make_collector(env, TensorDictSequential(actor, exploration), dq, seed, start)
    objective_key = OBJECTIVE_KEYS[cfg.objective]
    # the objective's signal, centred by its running average (``algo.reward_centering``; 0: off)
    center = RewardCenter(dq.reward_centering)
    buffer, sampler = make_buffer(dq, [CenteredRewards(center, ("next", objective_key))])
    loss = LagrangianDQNLoss(
        heads,
        combined.mu,
        gamma=dq.gamma,
        objective_key=objective_key,
        target_miss=cfg.target_miss,
        double_dqn=dq.double_dqn,
    )
    target = PolyakUpdate(loss, tau=dq.tau)
    optimizer = make_optimizer(loss, dq)
    multiplier = Multiplier(combined.mu, cfg)

    def update(sample: TensorDictBase) -> float:
        value = clip_and_step(loss, optimizer, dq.max_grad_norm, loss(sample)["loss"])
        target.step()
        if dq.prioritized:
            buffer.update_priority(sample["index"], sample["td_error"].detach().reshape(-1))
        return value

    def policy() -> torch.Tensor:
        with policy_view(loss, dq):
            return greedy_table(actor, env)

    def collected(data: TensorDictBase) -> None:
        center.update(data.get(("next", objective_key)))

    def after_batch(data: TensorDictBase, learned: bool) -> dict[str, Any]:
        scalars = multiplier.after_batch(data, learned)
        multiplier.trace.append({"env_steps": loop.frames, **scalars})
        return scalars

    def load(resume: dict[str, Any]) -> None:
        center.load(resume)
        multiplier.load(resume)

    signals = (("next", objective_key), ("next", "missed"), ("next", "event"))
    run = RunContext(scorer, eval_every_frames, hooks, resume)
    loop = TrainingLoop(
        dq,
        collector,
        buffer,
        sampler,
        optimizer,
        run,
        keys=tuple(dict.fromkeys((*STORED_KEYS, *signals))),
    )
    learner = Learner(
        loss=loss,
        update=update,
        policy=policy,
        collected=collected,
        after_batch=after_batch,
        state=lambda: {**center.state(), **multiplier.state()},
        load=load,
    )
    record = loop.run(learner)
    record.info["mu_trace"] = multiplier.trace
    if record.interrupted:
        return record
    # The final policy, from measurements on a separate batch of envs (counted in env_steps and
    # in the run's wall time).
    measuring = time.perf_counter()
    with policy_view(loss, dq):
        q = heads_table(heads, env)
    mu = float(combined.mu)
    probs, facts = final_policy(q, params, mu, cfg, seed)
    record.measurement_env_steps = int(facts["measure_env_steps"])
    record.env_steps += record.measurement_env_steps
    record.wall_seconds += time.perf_counter() - measuring
    record.policy = probs[None]
    record.greedy = (probs[:, 1] > 0.5).long()[None]
    record.q = (q[:, 0] - mu * q[:, 1]).float()[None]
    record.info.update({"mu": mu, "measured_miss": multiplier.measured, **facts})
    return record


def dual_step(mu: float, measured: float, frames: int, cfg: LagrangianConfig) -> float:
    """One dual-ascent step in log space: μ ← μ·exp(mu_lr·e·frames/1000), e the measured miss
    detection's relative excess over the target, (M̂ − m*)/max(m*, 0.01), clipped to [−1, 1];
    kept in [mu_min, mu_max]. Relative steps cover the multiplier's unknown scale (0.1 … 1 000
    here) at one rate, and a full-error step is the same whether μ is small or large."""
    err = (measured - cfg.target_miss) / max(cfg.target_miss, 0.01)
    err = min(1.0, max(-1.0, err))
    return min(cfg.mu_max, max(cfg.mu_min, mu * math.exp(cfg.mu_lr * err * frames / 1000.0)))
