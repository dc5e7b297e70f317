"""Tabular Q-learning, vectorised: one batched env trains N independent learners (one Q-table each).

Row n of the batch is learner n: its own table, its own ε-greedy actions, its own trajectory. All
rows share episode boundaries (every episode is ``env.horizon`` steps from a uniform reset), so the
loop steps ``irdrc.env.Dynamics`` directly — the same step code as the env, without the per-step
tensordict overhead that dominates at small batch sizes. Given several scenarios (e.g. every p^v_1
value of a figure), the batch holds ``num_learners`` rows per scenario and trains them all at once.

Two profiles: ``PAPER`` (the reference profile of MODEL.md: α = 0.01, ε = 0.1 fixed, γ = 0.99,
2 500 episodes) and ``DEFAULT`` (ours: visit-count step sizes and a decaying ε; see below).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, fields, replace
from typing import Any

import torch

from irdrc.env import Dynamics
from irdrc.model import build_model
from irdrc.params import Params
from irdrc.solve import ExactScorer


@dataclass(frozen=True)
class QLearningConfig:
    """Hyperparameters of tabular Q-learning (config group ``algo`` for ``recipes/qlearning.py``).

    Attributes:
        episodes: training episodes per learner (each ``env.horizon`` steps).
        gamma: discount γ.
        alpha: step size; with ``alpha_schedule="count"`` the step size of the k-th update of a
            (state, action) pair is ``max(alpha_min, alpha / k**alpha_power)``.
        alpha_schedule: ``constant`` or ``count``.
        alpha_power: ω of the count schedule (1/2 < ω ≤ 1 keeps the Robbins–Monro conditions).
        alpha_min: floor of the count schedule.
        epsilon_start: exploration rate at the first episode.
        epsilon_end: exploration rate after ``epsilon_decay_episodes`` (linear in between).
        epsilon_decay_episodes: episodes over which ε decays; 0 keeps ``epsilon_end`` throughout.
        init_q: initial value of every Q entry.
        eval_every_episodes: exact evaluation of the greedy tables every this many episodes.
    """

    episodes: int = 600
    gamma: float = 0.99
    alpha: float = 1.0
    alpha_schedule: str = "count"
    alpha_power: float = 1.0
    alpha_min: float = 0.0
    epsilon_start: float = 1.0
    epsilon_end: float = 1.0
    epsilon_decay_episodes: int = 0
    init_q: float = 0.0
    eval_every_episodes: int = 10

    def __post_init__(self) -> None:
        checks = [
            ("episodes", self.episodes >= 1 and isinstance(self.episodes, int), ">= 1 (integer)"),
            ("gamma", 0.0 <= self.gamma < 1.0, "in [0, 1)"),
            ("alpha", 0.0 < self.alpha <= 1.0, "in (0, 1]"),
            ("init_q", isinstance(self.init_q, int | float), "a number"),
            ("alpha_schedule", self.alpha_schedule in ("constant", "count"), "constant or count"),
            ("alpha_power", 0.0 <= self.alpha_power <= 1.0, "in [0, 1]"),
            ("alpha_min", 0.0 <= self.alpha_min <= 1.0, "in [0, 1]"),
            ("epsilon_start", 0.0 <= self.epsilon_start <= 1.0, "in [0, 1]"),
            ("epsilon_end", 0.0 <= self.epsilon_end <= 1.0, "in [0, 1]"),
            ("epsilon_decay_episodes", self.epsilon_decay_episodes >= 0, ">= 0"),
            ("eval_every_episodes", self.eval_every_episodes >= 1, ">= 1"),
        ]
        for key, ok, allowed in checks:
            if not ok:
                raise ValueError(f"algo.{key}={getattr(self, key)!r} must be {allowed}")

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> QLearningConfig:
        """From a mapping of the fields above; unknown keys are rejected (``name`` is ignored)."""
        data = {k: v for k, v in dict(data).items() if k != "name"}
        names = {f.name for f in fields(cls)}
        extra = sorted(set(data) - names)
        if extra:
            raise ValueError(f"unknown key(s) {', '.join('algo.' + k for k in extra)}")
        return cls(**data)

    def epsilon(self, episode: int) -> float:
        """ε during ``episode`` (0-based)."""
        if self.epsilon_decay_episodes == 0 or episode >= self.epsilon_decay_episodes:
            return self.epsilon_end
        frac = episode / self.epsilon_decay_episodes
        return self.epsilon_start + frac * (self.epsilon_end - self.epsilon_start)


PAPER = QLearningConfig(
    episodes=2500,
    gamma=0.99,
    alpha=0.01,
    alpha_schedule="constant",
    alpha_power=0.0,
    alpha_min=0.0,
    epsilon_start=0.1,
    epsilon_end=0.1,
    epsilon_decay_episodes=0,
    eval_every_episodes=25,
)
"""The reference profile (MODEL.md § Learning setup): α = 0.01, γ = 0.99, ε = 0.1, 2 500 episodes."""

DEFAULT = QLearningConfig()
"""Our profile: α_k = 1/k for the k-th update of (s, a) (a running average), uniform exploration
(ε = 1: Q-learning is off-policy and only the greedy table is scored), 600 episodes."""


@dataclass
class QLearningResult:
    """Outcome of ``train``.

    Rows are scenario-major: row n is learner ``n % num_learners`` of scenario
    ``n // num_learners`` (``group[n]``).

    Attributes:
        q: [N, S, 2] final Q-tables.
        greedy: [N, S] greedy actions (ties → comm).
        episode_rewards: [episodes, N] total reward of each training episode.
        history: one dict per evaluation: ``episode``, ``env_steps`` (per learner),
            ``wall_seconds``, ``avg_reward`` and ``optimality_ratio`` (lists over rows).
        optimal_avg_reward: stationary average reward of the optimal policy (scenario 0).
        wall_seconds: training time.
        group: [N] scenario index of each row.
        optimal_avg_rewards: optimal average reward of each scenario.
    """

    q: torch.Tensor
    greedy: torch.Tensor
    episode_rewards: torch.Tensor
    history: list[dict[str, Any]] = field(default_factory=list)
    optimal_avg_reward: float = float("nan")
    wall_seconds: float = 0.0
    group: list[int] = field(default_factory=list)
    optimal_avg_rewards: list[float] = field(default_factory=list)


def train(
    params: Params | Sequence[Params],
    cfg: QLearningConfig = DEFAULT,
    num_learners: int = 1,
    seed: int = 0,
    device: str = "cpu",
    scorer: ExactScorer | Sequence[ExactScorer] | None = None,
    on_eval: Callable[[dict[str, Any]], None] | None = None,
) -> QLearningResult:
    """Train ``num_learners`` independent tabular Q-learners per scenario on one batched step.

    Args:
        params: the model, or several scenarios trained together (same queue capacity and horizon).
        cfg: hyperparameters (``PAPER`` or ``DEFAULT`` or your own).
        num_learners: learners per scenario; the batch has ``num_learners × scenarios`` rows, all
            drawing from the shared generators, so a run is reproducible for given (seed, scenarios,
            num_learners).
        seed: seed of the dynamics and of the exploration generator.
        device: torch device.
        scorer: exact evaluator per scenario (built from ``params`` if omitted).
        on_eval: called with each history entry (progress reporting, logging).
    """
    if num_learners < 1:
        raise ValueError(f"num_learners={num_learners!r} must be >= 1")
    scenarios = [params] if isinstance(params, Params) else list(params)
    horizons = {p.env.horizon for p in scenarios}
    if len(horizons) > 1:
        raise ValueError(
            f"scenarios trained together must share env.horizon; got {sorted(horizons)}"
        )
    dyn = Dynamics(scenarios, device)
    G = len(scenarios)
    if scorer is None:
        scorers = [ExactScorer(build_model(p), cfg.gamma) for p in scenarios]
    elif isinstance(scorer, ExactScorer):
        scorers = [scorer]
    else:
        scorers = list(scorer)
    if len(scorers) != G:
        raise ValueError(f"{len(scorers)} scorers for {G} scenarios")
    S, L, T = dyn.num_states, num_learners, scenarios[0].env.horizon
    N = G * L
    group_of = [n // L for n in range(N)]
    group = torch.tensor(group_of, dtype=torch.int64, device=device) if G > 1 else None
    rng = torch.Generator(device=device)
    rng.manual_seed(seed)  # the dynamics' stream
    gen = torch.Generator(device=device)
    gen.manual_seed(seed + 7919)  # exploration stream, distinct from the dynamics'

    q = torch.full((N * S * 2,), float(cfg.init_q), dtype=torch.float32, device=device)
    visits = torch.zeros(N * S * 2, dtype=torch.float32, device=device)
    row = torch.arange(N, device=device) * (S * 2)
    ep_rewards = torch.zeros(cfg.episodes, N, dtype=torch.float64)
    result = QLearningResult(q=q, greedy=q, episode_rewards=ep_rewards, group=group_of)
    result.optimal_avg_rewards = [sc.optimal_metrics.avg_reward for sc in scorers]
    result.optimal_avg_reward = result.optimal_avg_rewards[0]
    t0 = time.perf_counter()

    def evaluate(episode: int) -> None:
        greedy = q.view(N, S, 2).argmax(-1).cpu()
        per = [scorers[group_of[n]].metrics(greedy[n]) for n in range(N)]
        entry = {
            "episode": episode,
            "env_steps": episode * T,
            "wall_seconds": time.perf_counter() - t0,
            "avg_reward": [m.avg_reward for m in per],
            "optimality_ratio": [
                m.avg_reward / result.optimal_avg_rewards[group_of[n]] for n, m in enumerate(per)
            ],
        }
        result.history.append(entry)
        if on_eval is not None:
            on_eval(entry)

    evaluate(0)
    for episode in range(cfg.episodes):
        eps = cfg.epsilon(episode)
        state = dyn.reset_states(N, rng)
        total = torch.zeros(N, dtype=torch.float64, device=device)
        for _ in range(T):
            base = row + state * 2
            qs = torch.stack([q[base], q[base + 1]], -1)
            u = torch.rand(N, 2, generator=gen, device=device)
            action = torch.where(u[:, 0] < eps, (u[:, 1] < 0.5).long(), qs.argmax(-1))
            res = dyn.step(state, action, rng, group)
            nbase = row + res.state * 2
            target = res.reward + cfg.gamma * torch.maximum(q[nbase], q[nbase + 1])
            idx = base + action
            if cfg.alpha_schedule == "count":
                visits[idx] += 1
                alpha = (cfg.alpha / visits[idx] ** cfg.alpha_power).clamp(min=cfg.alpha_min)
            else:
                alpha = cfg.alpha
            q[idx] += alpha * (target - q[idx])
            total += res.reward
            state = res.state
        ep_rewards[episode] = total.cpu()
        if (episode + 1) % cfg.eval_every_episodes == 0 or episode + 1 == cfg.episodes:
            evaluate(episode + 1)
    result.wall_seconds = time.perf_counter() - t0
    result.q = q.view(N, S, 2)
    result.greedy = result.q.argmax(-1)
    return result


def steps_to_ratio(history: list[dict[str, Any]], learner: int, threshold: float) -> int | None:
    """First evaluated ``env_steps`` at which ``learner``'s optimality ratio is ≥ ``threshold``."""
    for entry in history:
        if entry["optimality_ratio"][learner] >= threshold:
            return int(entry["env_steps"])
    return None


def profile(name: str, **overrides: Any) -> QLearningConfig:
    """``"paper"`` or ``"default"``, with field overrides."""
    base = {"paper": PAPER, "default": DEFAULT}.get(name)
    if base is None:
        raise ValueError(f"unknown Q-learning profile {name!r}; choose paper or default")
    return replace(base, **overrides)
