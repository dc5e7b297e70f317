"""A Lagrangian DQN for the constrained problem (MODEL.md § A): the most of an objective subject to
miss detection ≤ a target, learned from interaction alone.

The DQN machinery of ``irdrc.agents.dqn`` (network body, ε-greedy, replay, TorchRL's collector and
``SoftUpdate``) with two value heads per action, learned by double-DQN TD(0) from the per-step
signals the env writes under ``("next", key)``:

- Q_J(s, a): the objective (``sent`` for throughput, ``reward``, or ``capacity``);
- Q_C(s, a): the constraint cost c = missed − m*·event, whose long-run average is ≤ 0 exactly when
  miss detection ≤ m* (MODEL.md § A).

The agent acts greedily on Q_J − μ·Q_C: the per-step Lagrangian signal J − μ·(missed − m*·event),
with the multiplier μ ≥ 0 adapted by dual ascent from the learner's own measured miss detection
(missed / event over its recent experience). Keeping the two heads apart keeps both signals at
their own scale whatever μ is, and gives the greedy policy for *every* μ from one network: action
comm wins in state s while μ < ΔJ(s)/ΔC(s) (Δ = comm − radar), so as μ grows the greedy table
changes one state at a time at those breakpoints.

The final policy is chosen the way a vehicle could: along that path of tables, a bisection on
measured miss detection (Monte-Carlo episodes on the simulator, counted in ``env_steps``) finds the
two neighbouring tables on either side of the target; they differ in one state, and the final
policy randomises there with the probability found by bisection on measured rates — the same shape
as the exact LP optimum. The heads can misorder states they seldom see (a risky state at a long
queue kept in comm after better ones went to radar); the prune (``algo.prune``) finds a second pair
of neighbours by giving the comm states of the path's upper neighbour to radar in the order of
their measured data per missed event, and the pair that promises more is kept. The exact model
only scores (``history``, the final metrics).
"""

from __future__ import annotations

import bisect
import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
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
from irdrc.core.env import DFRCEnv
from irdrc.core.evaluate import long_run
from irdrc.core.params import (
    Params,
    check_bool,
    check_choice,
    check_number,
    reject_unknown_keys,
    to_plain,
)
from irdrc.core.solve import ExactScorer

NAME = "dqn_lagrangian"
OBJECTIVE_KEYS = {"throughput": "sent", "avg_reward": "reward", "link_capacity": "capacity"}
"""The env's per-step signal (under ``("next", key)``) for each objective of ``irdrc.core.cmdp``."""

LAGRANGIAN_KEYS = (
    "mu_init",
    "mu_lr",
    "mu_min",
    "mu_max",
    "cost_window_frames",
    "search_span",
    "measure_envs",
    "measure_steps",
    "measure_burn_in",
    "measure_max_blocks",
    "mix_steps",
    "confirm",
    "prune",
)

DQN_VARIANT_KEYS = frozenset(
    {"distributional", "atoms", "support_span"}
    | {f"select_{k}" for k in ("every_frames", "after_frames", "envs", "steps", "burn_in", "z")}
)
"""DQN's variant keys (``irdrc.agents.dqn_variants``): refused here, rather than ignored."""

SEARCH_FLOOR = 1e-6
"""The final search goes down the path no further than this fraction of the trained μ."""

MIXING_STEPS_PER_BLOCK = 1
"""The final policy's randomisation is searched on its log-odds within ±log(measure_steps / this):
a probability closer to 0 or 1 in a state the chain lingers in (a full queue) makes the chain mix
more slowly than a measurement block can see (at 1 − 1/measure_steps, measured and exact miss
detection still agreed within 0.002 here)."""


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
        mix_steps: bisection steps on the log-odds of the final policy's randomisation.
        confirm: re-measure the search's result on fresh random numbers before the final choice
            (``final_policy``): the search keeps the tables whose measured miss detection fell at
            or below the target, so a table whose measurement read low by chance is kept
            (selection on noise); the confirmation moves up the path while the fresh measurement
            is above the target, and the randomisation is found on the fresh measurements.
        prune: also look for the final neighbours by giving the comm states of the path's
            neighbour above the target to radar in the order of their measured objective per
            missed event (``prune_order``), and keep whichever pair promises more at the target
            (objectives ``throughput`` and ``link_capacity``; ``final_policy``). The heads'
            ordering of rarely visited states can be wrong where a state's measured rates are not.
    """

    # Centering is off here (unlike DQN's default): on the constrained benchmark it did not help.
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
    search_span: float = 4.0
    measure_envs: int = 2048
    measure_steps: int = 2_000
    measure_burn_in: int = 2_000
    measure_max_blocks: int = 8
    mix_steps: int = 10
    confirm: bool = True
    prune: bool = True
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
        num("search_span", 1)
        num("measure_envs", 2, 10**7, integer=True)
        num("measure_steps", 1, 10**9, integer=True)
        num("measure_burn_in", 0, 10**9, integer=True)
        num("measure_max_blocks", 1, 10**6, integer=True)
        num("mix_steps", 0, 60, integer=True)
        check_bool("algo.confirm", self.confirm)
        check_bool("algo.prune", self.prune)
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
        dqn = OffPolicyConfig.from_dict({"reward_centering": 0.0, **data, "name": NAME}, network)
        return cls(dqn=dqn, target_miss=target_miss, objective=objective, **own)

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
    """Double-DQN TD(0) on both heads: the next action is the online network's greedy action on
    Q_J − μ·Q_C, valued by the target network's heads. Writes ``td_error`` (|δ_J| + |δ_C|) for
    prioritised replay; the loss is the (importance-weighted) mean of δ_J² + δ_C² (or the chosen
    distance)."""

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
    ) -> None:
        super().__init__()
        self.convert_to_functional(heads, "value_network", create_target_params=True)
        self.mu = mu
        self.gamma = float(gamma)
        self.objective_key = objective_key
        self.target_miss = float(target_miss)
        self.loss_function = loss_function
        self.objective_center = 0.0

    def signals(self, td: TensorDictBase) -> torch.Tensor:
        """[B, 2] per-step (objective, cost) of a batch of transitions; the objective less
        ``objective_center`` (reward centering: a constant shift, so Q_J − μ·Q_C ranks actions
        the same at every μ)."""
        nxt = td["next"]
        j = nxt[self.objective_key].reshape(-1).to(torch.float32) - self.objective_center
        c = nxt["missed"].reshape(-1).float() - self.target_miss * nxt["event"].reshape(-1).float()
        return torch.stack([j, c], -1)

    def forward(self, td: TensorDictBase) -> TensorDict:
        obs, nobs = td["observation"], td["next", "observation"]
        action = td["action"].reshape(-1).long()
        with self.value_network_params.to_module(self.value_network):
            q = self.value_network(obs)  # [B, 2, 2]
        taken = q.gather(-1, action.view(-1, 1, 1).expand(-1, 2, 1)).squeeze(-1)  # [B, 2]
        with torch.no_grad():
            with self.value_network_params.data.to_module(self.value_network):
                qn = self.value_network(nobs)
            best = (qn[:, 0] - self.mu * qn[:, 1]).argmax(-1)
            with self.target_value_network_params.to_module(self.value_network):
                qt = self.value_network(nobs)
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


def greedy_path(q: torch.Tensor) -> tuple[list[float], list[torch.Tensor]]:
    """The greedy tables of Q_J − μ·Q_C as μ goes from 0 to ∞, from values ``q`` [S, 2, 2].

    Returns ``(breaks, tables)``: ``tables[k]`` is greedy on (breaks[k−1], breaks[k]) (breaks[−1]
    = 0), consecutive tables differ in exactly one state, ``len(tables) = len(breaks) + 1``.
    Ties go to comm, as in ``irdrc.agents.dqn.greedy_table``.
    """
    dj = q[:, 0, 0] - q[:, 0, 1]  # objective gain of comm over radar
    dc = q[:, 1, 0] - q[:, 1, 1]  # cost of comm over radar
    table = (dj < 0).long()  # μ = 0: greedy on Q_J (1 = radar)
    # State s switches at μ_s = dj/dc where the sign of dj − μ·dc changes for some μ > 0.
    switch = torch.where(dc != 0, dj / dc, torch.full_like(dj, math.inf))
    crosses = (switch > 0) & torch.isfinite(switch)
    order = sorted(crosses.nonzero().flatten().tolist(), key=lambda s: float(switch[s]))
    breaks, tables = [], [table.clone()]
    for s in order:
        table = table.clone()
        table[s] = 1 - table[s]
        breaks.append(float(switch[s]))
        tables.append(table)
    return breaks, tables


def path_index(breaks: list[float], mu: float) -> int:
    """The index of the table of ``greedy_path`` that is greedy at multiplier ``mu``."""
    return bisect.bisect_right(breaks, mu)


CONFIRM_SEED_OFFSET = 104_729
"""The confirmation's random numbers: the search's seed plus this (independent of the search's)."""


def prune_order(by_state: dict[str, torch.Tensor], table: torch.Tensor, key: str) -> list[int]:
    """The states where ``table`` (1 = radar) communicates, in the order the prune gives them to
    radar: ascending measured objective per missed event in their comm steps, Σ``key`` / (Σmissed
    + 1) over ``by_state`` (``long_run(..., by_state=True)``). The + 1 keeps states seen too
    seldom to have missed an event from looking best: they go early, which costs little data."""
    comm = (table == 0).nonzero().flatten().tolist()
    score = by_state[key].double() / (by_state["missed"].double() + 1.0)
    return sorted(comm, key=lambda s: (float(score[s]), s))


def final_policy(
    q: torch.Tensor, params: Params, mu: float, cfg: LagrangianConfig, seed: int
) -> tuple[torch.Tensor, dict[str, Any]]:
    """The final [S, 2] policy from the learned heads ``q`` [S, 2, 2] and the trained multiplier
    ``mu``, chosen by measured rates alone (long-run Monte-Carlo runs on the simulator,
    ``irdrc.core.evaluate.long_run``, all with the same random numbers so that measurements of
    neighbouring policies compare like with like). Returns (policy, facts); facts include the
    measurement env steps (``measure_env_steps``) and the measured rates of the final policy.

    Along the greedy path (``greedy_path``), from the table greedy at ``mu``: if it meets the
    target, down the path (multipliers ÷ ``search_span`` at a time) while tables meet it and
    their measured objective grows; if not, up to ``mu``·``search_span`` and then the safest end.
    A bisection between the last table above the target and the first at or below it finds
    neighbours on either side of it. With ``cfg.confirm`` the table found is measured again on
    fresh random numbers, and while that measurement is above the target the search climbs the
    path (doubling its steps, then bisecting) on the fresh numbers.

    With ``cfg.prune`` (objectives ``throughput`` and ``link_capacity``) a second pair of
    neighbours comes from the measurements instead of the heads' ordering: the comm states of the
    path's neighbour above the target go to radar one at a time in ``prune_order`` (from that
    table's own per-state measurement), and a bisection on their number finds the two tables on
    either side of the target. The pair whose measured (miss, objective) promise more at the
    target, by linear interpolation between its two tables, is kept (the path's on a tie).

    The final policy randomises in the one state where the kept neighbours differ, with the
    probability found by bisection (on its log-odds) on measured miss detection (the fresh
    numbers' with ``cfg.confirm``).
    """
    breaks, tables = greedy_path(q)
    target = cfg.target_miss
    last = len(tables) - 1
    steps = 0
    seen: dict[tuple[bool, bytes], tuple[float, float]] = {}
    per_state: dict[tuple[bool, bytes], dict[str, torch.Tensor]] = {}

    key = OBJECTIVE_KEYS[cfg.objective]
    metric = {"sent": "throughput", "reward": "avg_reward", "capacity": "link_capacity"}[key]
    prune = cfg.prune and key != "reward"  # radar earns reward too: no per-comm-step trade

    def rates(p_radar: torch.Tensor, fresh: bool = False) -> tuple[float, float]:
        """Measured (miss detection, objective) of a policy (each policy measured once per
        stream: the search's, or with ``fresh`` the confirmation's)."""
        nonlocal steps
        k = (fresh, p_radar.double().numpy().tobytes())
        if k not in seen:
            ev = long_run(
                params,
                p_radar.double(),
                envs=cfg.measure_envs,
                steps=cfg.measure_steps,
                burn_in=cfg.measure_burn_in,
                max_blocks=cfg.measure_max_blocks,
                seed=seed + 7919 + (CONFIRM_SEED_OFFSET if fresh else 0),
                by_state=prune,  # the per-state sums the prune orders by
            )
            steps += ev.steps
            seen[k] = (float(ev.metrics.miss_detection), float(getattr(ev.metrics, metric)))
            per_state[k] = ev.by_state
        return seen[k]

    def miss(p_radar: torch.Tensor, fresh: bool = False) -> float:
        return rates(p_radar, fresh)[0]

    def table(k: int) -> torch.Tensor:
        return tables[k].double()

    def done(
        p_radar: torch.Tensor, fresh: bool = False, **extra: Any
    ) -> tuple[torch.Tensor, dict[str, Any]]:
        facts = {
            "path_tables": len(tables),
            "measured_final_miss": miss(p_radar, fresh),
            "measurements": len(seen),
            "measure_env_steps": steps,
            "confirmed": fresh,
            **extra,
        }
        return torch.stack([1 - p_radar.double(), p_radar.double()], -1), facts

    def bracket(lo: int, hi: int, fresh: bool, miss_of=lambda k, f: miss(table(k), f)):
        """Bisection to neighbours: miss(lo) > target ≥ miss(hi) on entry and on return."""
        while hi - lo > 1:
            mid = (lo + hi) // 2
            if miss_of(mid, fresh) > target:
                lo = mid
            else:
                hi = mid
        return lo, hi

    def path_search() -> tuple[torch.Tensor | None, torch.Tensor, bool, float | None]:
        """The path's neighbours (above the target or None, at or below it — or the safest end
        of the path when no table meets the target), the stream that decides, and the
        multiplier of the switch."""
        k0 = path_index(breaks, mu)
        lo: int | None
        if miss(table(k0)) <= target:
            # Down the path (more data) by factors of search_span while the tables stay within
            # the target and their measured objective grows; the first one above it brackets.
            lo, hi = None, k0
            m = mu
            while hi > 0 and m > mu * SEARCH_FLOOR:
                m /= cfg.search_span
                k = path_index(breaks, m)
                if k == hi:
                    continue
                if miss(table(k)) > target:
                    lo = k
                    break
                if rates(table(k))[1] <= rates(table(hi))[1]:
                    break  # no more data lower down: the heads' differences there are noise
                hi = k
        else:
            lo, hi = k0, path_index(breaks, mu * cfg.search_span)
            if miss(table(hi)) > target:
                hi = last  # beyond the range: the safest tables of the path
                if hi == lo or miss(table(hi)) > target:
                    return None, table(hi), cfg.confirm, None
        if lo is not None:
            lo, hi = bracket(lo, hi, fresh=False)
        fresh = cfg.confirm
        if fresh and miss(table(hi), fresh) > target:
            # The search kept this table because its measurement fell at or below the target,
            # which noise alone can do: climb the path on fresh numbers until a table meets it.
            step, lo = 1, hi
            while True:
                k = min(hi + step, last)
                if miss(table(k), fresh) <= target:
                    lo, hi = bracket(lo, k, fresh)
                    break
                if k == last:
                    return None, table(last), True, None
                lo, step = k, 2 * step
        if lo is None:
            return None, table(hi), fresh, None
        return table(lo), table(hi), fresh, breaks[lo]

    def promise(t_lo: torch.Tensor | None, t_hi: torch.Tensor, fresh: bool) -> float:
        """The objective a mixture of the pair promises at the target, from their measured
        rates by linear interpolation in miss detection (−∞ when its safer table ``t_hi`` does
        not meet it)."""
        m_hi, j_hi = rates(t_hi, fresh)
        if t_lo is None:
            return j_hi if m_hi <= target else -math.inf
        m_lo, j_lo = rates(t_lo, fresh)
        if m_hi > target:
            return -math.inf
        if m_lo <= target:
            return max(j_lo, j_hi)
        w = (m_lo - target) / (m_lo - m_hi)  # the weight of t_hi that lands on the target
        return (1 - w) * j_lo + w * j_hi

    def prune_search(
        top: torch.Tensor, fresh: bool
    ) -> tuple[torch.Tensor | None, torch.Tensor, int, int]:
        """Neighbours on either side of the target among ``top`` with its first k comm states
        (``prune_order``) given to radar; also k (of the upper neighbour) and how many there are."""
        rates(top, fresh)
        order = prune_order(per_state[(fresh, top.numpy().tobytes())], top, key)

        def pruned(k: int) -> torch.Tensor:
            t = top.clone()
            t[order[:k]] = 1.0
            return t

        n = len(order)
        if miss(top, fresh) <= target:
            return None, top, 0, n
        if miss(pruned(n), fresh) > target:
            return None, pruned(n), n, n
        lo, hi = bracket(0, n, fresh, miss_of=lambda k, f: miss(pruned(k), f))
        return pruned(lo), pruned(hi), hi, n

    t_lo, t_hi, fresh, mu_switch = path_search()
    extra: dict[str, Any] = {"pruned": None}
    if prune and (t_lo is not None or miss(t_hi, fresh) > target):
        top = t_lo if t_lo is not None else t_hi
        p_lo, p_hi, k, n = prune_search(top, fresh)
        path_promise, prune_promise = promise(t_lo, t_hi, fresh), promise(p_lo, p_hi, fresh)
        won = prune_promise > path_promise
        extra = {
            "pruned": won,
            "prune_states": k,
            "prune_candidates": n,
            # −∞ (neither table of the pair meets the target) is written as None
            "path_promise": path_promise if math.isfinite(path_promise) else None,
            "prune_promise": prune_promise if math.isfinite(prune_promise) else None,
        }
        if won:
            t_lo, t_hi, mu_switch = p_lo, p_hi, None
    if t_lo is None:
        return done(t_hi, fresh, switch_state=None, p_switch=None, **extra)
    s = int((t_lo != t_hi).nonzero().flatten()[0])
    a_lo, a_hi = float(t_lo[s]), float(t_hi[s])

    def mixed(z: float) -> torch.Tensor:
        w = 1.0 / (1.0 + math.exp(-z))  # weight of t_hi's action in s
        p = t_hi.clone()
        p[s] = w * a_hi + (1 - w) * a_lo
        return p

    # Bisection on the log-odds z of the weight: miss(mixed(z)) falls as z grows.
    span = math.log(max(2.0, cfg.measure_steps / MIXING_STEPS_PER_BLOCK))
    z_lo, z_hi = -span, span
    if miss(mixed(z_hi), fresh) > target:
        return done(t_hi, fresh, switch_state=s, p_switch=float(t_hi[s]), **extra)
    if miss(mixed(z_lo), fresh) <= target:
        z_hi = z_lo
    else:
        for _ in range(cfg.mix_steps):
            z = 0.5 * (z_lo + z_hi)
            if miss(mixed(z), fresh) > target:
                z_lo = z
            else:
                z_hi = z
    p = mixed(z_hi)
    return done(p, fresh, switch_state=s, p_switch=float(p[s]), mu_switch=mu_switch, **extra)


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
    optimal_value: float | None = None,
) -> RunRecord:
    """Train the Lagrangian DQN and choose its final (possibly randomised) policy.

    The interface of ``irdrc.agents.base``, on the machinery of ``irdrc.agents.offpolicy`` (the
    same rows, ladder, replay and loop as DQN). ``hooks.on_batch`` gets ``env_steps``,
    ``episodes``, ``loss``, ``mu`` (the multiplier), ``measured_miss`` (M̂), ``buffer``. Each exact
    evaluation scores the greedy table at the current μ; its ``optimality_ratio`` is the objective
    over ``optimal_value`` (the LP optimum, when given; else over the reward-optimal average
    reward). The record's ``policy`` is the final [1, S, 2] policy, ``greedy`` its most likely
    action, and ``info`` the final search's facts. Runs do not resume (``resume`` must be None).
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
    metric = {"sent": "throughput", "reward": "avg_reward", "capacity": "link_capacity"}
    obj_name = metric[objective_key]

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
        if optimal_value is not None:
            entry["optimality_ratio"] = getattr(m, obj_name) / optimal_value
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
        hooks.batch(
            {
                "env_steps": loop.frames,
                "episodes": len(record.episode_rewards),
                "loss": loop.last_loss,
                "mu": float(mu),
                "measured_miss": measured,
                "buffer": len(buffer),
            }
        )
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
