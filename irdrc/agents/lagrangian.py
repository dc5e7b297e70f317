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
from collections.abc import Sequence
from dataclasses import dataclass, field, fields
from typing import Any

import torch
from tensordict import TensorDict, TensorDictBase, TensorDictParams
from tensordict.nn import TensorDictSequential
from torch import nn
from torchrl.modules import QValueActor
from torchrl.objectives import LossModule

from irdrc.agents.base import Hooks, RunRecord, make_scorers, progress_record, scenario_list
from irdrc.agents.offpolicy import (
    STORED_KEYS,
    OffPolicyConfig,
    OffPolicyLoop,
    RewardCenter,
    clip_and_step,
    greedy_table,
    make_buffer,
    make_collector,
    make_exploration,
    make_mlp,
    make_optimizer,
    make_target_updater,
    policy_view,
)
from irdrc.agents.policy_search import FinalPolicySearch, SearchConfig
from irdrc.core.env import DFRCEnv
from irdrc.core.params import (
    Params,
    check_choice,
    check_number,
    reject_unknown_keys,
    to_plain,
)
from irdrc.core.solve import ExactScorer

NAME = "dqn_lagrangian"
OBJECTIVE_KEYS = {"throughput": "sent", "avg_reward": "reward", "link_capacity": "capacity"}
"""The env's per-step signal (under ``("next", key)``) for each objective of ``irdrc.core.cmdp``."""

SEARCH_KEYS = tuple(f.name for f in fields(SearchConfig))
"""The final search's ``algo.*`` keys (``irdrc.agents.policy_search.SearchConfig``)."""

LAGRANGIAN_KEYS = ("mu_init", "mu_lr", "mu_min", "mu_max", "cost_window_frames", *SEARCH_KEYS)
"""The ``algo.*`` keys of this learner beside the machinery's (``OffPolicyConfig``)."""

DQN_VARIANT_KEYS = frozenset(
    {"distributional", "atoms", "support_span"}
    | {f"select_{k}" for k in ("every_frames", "after_frames", "envs", "steps", "burn_in", "z")}
)
"""DQN's variant keys (``irdrc.agents.dqn_variants``): refused here, rather than ignored."""


@dataclass(frozen=True)
class LagrangianConfig:
    """The Lagrangian DQN (config group ``algo: dqn_lagrangian``): DQN's keys plus these.

    Attributes:
        dqn: the machinery's hyperparameters (every ``OffPolicyConfig`` key; DQN's variants are
            refused, and so are n-step returns: the two heads learn TD(0)).
        target_miss: m*, miss detection ≤ this (the recipe's top-level ``target_miss``).
        objective: what is maximised (the recipe's top-level ``objective``).
        mu_init: the multiplier at the start.
        mu_lr: dual ascent rate in log space (``dual_step``): at full relative error μ changes by
            a factor e^mu_lr per 1 000 env steps; M̂ is the measured miss detection.
        mu_min, mu_max: the multiplier's bounds.
        cost_window_frames: M̂ is missed / event over about this many recent env steps
            (exponential average).
        search_span: the final search looks at multipliers within this factor of the trained μ.
        measure_envs, measure_steps, measure_burn_in, measure_max_blocks: each long-run
            measurement of a candidate final policy runs ``measure_envs`` chains for
            ``measure_burn_in`` steps, then blocks of ``measure_steps`` until two consecutive
            blocks agree (at most ``measure_max_blocks``; ``irdrc.core.evaluate.long_run``).
        mix_steps: at most this many measurements to find the final policy's randomisation
            (regula falsi on its log-odds).
        confirm: re-measure the search's result on fresh random numbers before the final choice
            (``final_policy``): the search keeps the tables whose measured miss detection fell at
            or below the target, so a table whose measurement read low by chance is kept
            (selection on noise); the confirmation moves up the path while the fresh measurement
            is above the target, and the randomisation is found on the fresh measurements.

    For objectives ``throughput`` and ``link_capacity`` the search also ranks the states by their
    measured objective per missed event in comm and keeps whichever pair of neighbours, the
    path's or the ranking's, promises more at the target (``irdrc.agents.policy_search``).
    """

    # DQN's machinery at small sizes (80 000 env steps, a few seconds): in the cells where the
    # target binds, the measured ranking rather than the heads' order decides (docs/CONSTRAINED.md).
    dqn: OffPolicyConfig = field(
        default_factory=lambda: OffPolicyConfig(
            num_envs=8,
            frames_per_batch=32,
            total_frames=80_000,
            init_random_frames=512,
            buffer_size=20_000,
            batch_size=256,
            lr=5e-4,
            tau=0.01,
            reward_centering=0.0,
            name=NAME,
        )
    )
    target_miss: float = 0.05
    objective: str = "throughput"
    mu_init: float = 1.0
    mu_lr: float = 1.0
    mu_min: float = 1e-3
    mu_max: float = 1e5
    cost_window_frames: int = 4_000
    search: SearchConfig = field(default_factory=SearchConfig)
    name: str = field(default=NAME, compare=False)

    def __post_init__(self) -> None:
        def num(key: str, lo: float, hi: float = math.inf, **kw: Any) -> None:
            object.__setattr__(
                self, key, check_number(f"algo.{key}", getattr(self, key), lo, hi, **kw)
            )

        object.__setattr__(self, "target_miss", check_number("target_miss", self.target_miss, 0, 1))
        check_choice("objective", self.objective, tuple(OBJECTIVE_KEYS))
        num("mu_lr", 0)
        num("mu_min", 0, open_lo=True)
        num("mu_max", 0, open_lo=True)
        num("mu_init", self.mu_min, self.mu_max)
        num("cost_window_frames", 1, 10**12, integer=True)
        if not isinstance(self.search, SearchConfig):
            raise ValueError(f"search={self.search!r} must be a SearchConfig")
        if not isinstance(self.dqn, OffPolicyConfig):
            raise ValueError(f"dqn={self.dqn!r} must be an OffPolicyConfig")
        if self.dqn.n_steps != 1:
            raise ValueError(
                f"algo.n_steps={self.dqn.n_steps}: the Lagrangian DQN's two heads learn one-step "
                "targets (set algo.n_steps=1)"
            )

    @classmethod
    def from_dict(
        cls,
        data: Any,
        network: Any = None,
        target_miss: float = 0.05,
        objective: str = "throughput",
    ) -> LagrangianConfig:
        """From the ``algo`` node (DQN's keys and ``LAGRANGIAN_KEYS``), the ``network`` node and
        the problem (``target_miss``, ``objective``); unknown keys are rejected."""
        data = {k: v for k, v in dict(to_plain(data)).items() if k != "name"}
        variants = sorted(k for k in data if k in DQN_VARIANT_KEYS)
        if variants:
            raise ValueError(
                f"algo.{variants[0]}: the Lagrangian DQN does not implement DQN's variants "
                f"({', '.join(sorted(DQN_VARIANT_KEYS))}); remove it"
            )
        reject_unknown_keys(
            "algo.", data, (OffPolicyConfig.keys() - {"name"}) | set(LAGRANGIAN_KEYS)
        )
        own = {k: data.pop(k) for k in LAGRANGIAN_KEYS if k in data}
        search = SearchConfig(**{k: own.pop(k) for k in SEARCH_KEYS if k in own})
        dqn = OffPolicyConfig.from_dict({"reward_centering": 0.0, **data, "name": NAME}, network)
        return cls(dqn=dqn, target_miss=target_miss, objective=objective, search=search, **own)

    @classmethod
    def from_node(cls, cfg: Any) -> LagrangianConfig:
        """From a recipe's config: ``algo``, ``network``, ``target_miss``, ``objective``."""
        return cls.from_dict(
            cfg["algo"],
            cfg["network"],
            target_miss=cfg["target_miss"],
            objective=cfg.get("objective", "throughput"),
        )

    def env_steps(self, horizon: int) -> int:
        """Env steps of training (the final policy's measurements come on top)."""
        return self.dqn.total_frames


Config = LagrangianConfig
"""This learner's config class (the interface of ``irdrc.agents.base``)."""


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
    of δ_J² + δ_C² (or the chosen distance). The objective signal arrives centred when reward
    centering is on (``OffPolicyLoop`` centres it in every sample)."""

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
        loss_function: str = "l2",
        double_dqn: bool = True,
    ) -> None:
        super().__init__()
        self.convert_to_functional(heads, "value_network", create_target_params=True)
        self.mu = mu
        self.gamma = float(gamma)
        self.objective_key = objective_key
        self.target_miss = float(target_miss)
        self.loss_function = loss_function
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
        if self.loss_function == "l2":
            per = delta.pow(2).sum(-1)
        elif self.loss_function == "l1":
            per = delta.abs().sum(-1)
        else:
            per = nn.functional.smooth_l1_loss(taken, target, reduction="none").sum(-1)
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


def train(
    params: Params | Sequence[Params],
    cfg: LagrangianConfig | None = None,
    *,
    num_learners: int = 1,
    seed: int = 0,
    device: str = "cpu",
    scorers: ExactScorer | Sequence[ExactScorer] | None = None,
    eval_every_frames: int = 25_000,
    hooks: Hooks | None = None,
    resume: dict[str, Any] | None = None,
) -> RunRecord:
    """Train the Lagrangian DQN and choose its final (possibly randomised) policy.

    The interface of ``irdrc.agents.base``, on the machinery of ``irdrc.agents.offpolicy`` (the
    same rows, ladder, replay and loop as DQN). ``hooks.on_batch`` gets ``env_steps``,
    ``episodes``, ``loss``, ``mu`` (the multiplier), ``measured_miss`` (M̂), ``buffer``. Each exact
    evaluation scores the greedy table at the current μ (its ``optimality_ratio`` against the
    reward optimum, as every learner's; the constrained recipe reads it against the LP's objective
    in its ``on_eval`` hook). The record's ``policy`` is the final [1, S, 2] policy, ``greedy`` its
    most likely action, and ``info`` the final search's facts. Runs do not resume (``resume`` must
    be None).
    """
    cfg = cfg or LagrangianConfig()
    dq = cfg.dqn
    hooks = hooks or Hooks()
    if resume is not None:
        raise ValueError(f"{NAME} runs do not resume: start again")
    scenarios = scenario_list(params)
    if len(scenarios) != 1 or num_learners != 1:
        raise ValueError(f"{NAME} trains one network on one scenario per run (num_learners=1)")
    if eval_every_frames < 1:
        raise ValueError(f"eval.every_frames={eval_every_frames!r} must be >= 1")
    (params,) = scenarios
    (scorer,) = make_scorers(scenarios, scorers)
    torch.manual_seed(seed)
    env = DFRCEnv(params, batch_size=[dq.num_envs], device=device, seed=seed)

    # Components in DQN's order: model → exploration → buffer → loss → target → optimiser.
    heads, combined, actor = make_network(env, cfg)
    exploration = make_exploration(env, dq)
    buffer, sampler = make_buffer(dq)
    mu = combined.mu
    objective_key = OBJECTIVE_KEYS[cfg.objective]
    loss = LagrangianDQNLoss(
        heads,
        mu,
        gamma=dq.gamma,
        objective_key=objective_key,
        target_miss=cfg.target_miss,
        loss_function=dq.loss_function,
        double_dqn=dq.double_dqn,
    )
    target = make_target_updater(loss, dq)
    optimizer = make_optimizer(loss, dq)
    record = RunRecord(method=cfg.name, greedy=torch.zeros(1, env.num_states, dtype=torch.int64))
    record.info["replay_sampler"] = type(sampler).__name__ + (
        " (prioritised)" if dq.prioritized else " (uniform)"
    )
    hooks.start(dict(record.info))
    center = RewardCenter(dq.reward_centering, dq.gamma)  # on the objective signal
    collector = make_collector(
        env, TensorDictSequential(actor, exploration), dq, dq.total_frames, seed
    )
    signals = (("next", objective_key), ("next", "missed"), ("next", "event"))
    keys = tuple(dict.fromkeys((*STORED_KEYS, *signals)))
    loop = OffPolicyLoop(
        dq,
        collector,
        buffer,
        sampler,
        optimizer,
        center,
        record,
        hooks,
        keys=keys,
        center_key=("next", objective_key),
    )

    def update(sample) -> float:
        out = loss(sample)
        value = clip_and_step(loss, optimizer, dq.max_grad_norm, out["loss"])
        target.step()
        if dq.prioritized:
            buffer.update_priority(sample["index"], sample["td_error"].detach().reshape(-1))
        return value

    t0 = time.perf_counter()

    def evaluate_now() -> None:
        with policy_view(loss, dq):
            m = scorer.metrics(greedy_table(actor, env))
        entry = progress_record(
            0,
            loop.frames,
            len(record.episode_rewards),
            time.perf_counter() - t0,
            loop.updates,
            m,
            scorer.optimal_metrics.avg_reward,
        )
        record.history.append(entry)
        hooks.eval([entry])

    evaluate_now()
    next_eval = eval_every_frames
    missed_avg = event_avg = 0.0
    measured = math.nan
    mu_trace: list[dict[str, float]] = []
    for data in loop.batches():
        n = data.numel()
        # The learner's own measured constraint: missed / event on the steps where it acted
        # greedily (exploration's random comm steps would bias it), exponentially averaged.
        keep = math.exp(-n / cfg.cost_window_frames)
        missed_avg *= keep
        event_avg *= keep
        if "action_value" in data:
            greedy = data["action"].reshape(-1) == data["action_value"].argmax(-1).reshape(-1)
            missed_avg += float((data["next", "missed"].reshape(-1) & greedy).sum())
            event_avg += float((data["next", "event"].reshape(-1) & greedy).sum())
        measured = missed_avg / event_avg if event_avg > 0 else math.nan
        if loop.learn(update) is not None and not math.isnan(measured):
            mu.fill_(dual_step(float(mu), measured, n, cfg))  # dual ascent
        mu_trace.append({"env_steps": loop.frames, "mu": float(mu), "measured_miss": measured})
        hooks.batch(loop.scalars(mu=float(mu), measured_miss=measured))
        stop = loop.stop_due()
        if loop.frames >= next_eval or loop.frames >= dq.total_frames or stop:
            evaluate_now()
            next_eval = (loop.frames // eval_every_frames + 1) * eval_every_frames
        if stop:
            record.interrupted = True
            break
    loop.shutdown()
    record.env_steps = loop.frames
    record.episodes = len(record.episode_rewards)
    # The final policy, from measurements on a separate batch of envs (counted in env_steps).
    with policy_view(loss, dq):
        q = heads_table(heads, env)
    probs, facts = final_policy(q, params, float(mu), cfg, seed)
    record.measurement_env_steps = int(facts["measure_env_steps"])
    record.env_steps += record.measurement_env_steps
    record.wall_seconds = time.perf_counter() - t0
    record.policy = probs[None]
    record.greedy = (probs[:, 1] > 0.5).long()[None]
    record.q = (q[:, 0] - float(mu) * q[:, 1]).float()[None]
    record.info.update(
        {
            "mu": float(mu),
            "measured_miss": measured,
            **facts,
        }
    )
    record.info["mu_trace"] = mu_trace
    return record


def dual_step(mu: float, measured: float, frames: int, cfg: LagrangianConfig) -> float:
    """One dual-ascent step in log space: μ ← μ·exp(mu_lr·e·frames/1000), e the measured miss
    detection's relative excess over the target, (M̂ − m*)/max(m*, 0.01), clipped to [−1, 1];
    kept in [mu_min, mu_max]. Relative steps cover the multiplier's unknown scale (0.1 … 1 000
    here) at one rate, and a full-error step is the same whether μ is small or large."""
    err = (measured - cfg.target_miss) / max(cfg.target_miss, 0.01)
    err = min(1.0, max(-1.0, err))
    return min(cfg.mu_max, max(cfg.mu_min, mu * math.exp(cfg.mu_lr * err * frames / 1000.0)))
