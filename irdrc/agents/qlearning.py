"""Tabular Q-learning, vectorised: one batched env trains N independent learners (one Q-table each).

Row n of the batch is learner n: its own table, its own ε-greedy actions, its own trajectory. All
rows share episode boundaries (every episode is ``env.horizon`` steps from a uniform reset), so the
loop steps ``irdrc.core.dynamics.Dynamics`` directly — the same step code as the env, without the per-step
tensordict overhead that dominates at small batch sizes. Given several scenarios (e.g. every p^v_1
value of a figure), the batch holds ``num_learners`` rows per scenario and trains them all at once.

Two profiles: ``PAPER`` (the reference profile of MODEL.md: α = 0.01, ε = 0.1 fixed, γ = 0.99,
2 500 episodes) and ``DEFAULT`` (ours: visit-count step sizes and a decaying ε; see below).
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from typing import Any

import torch

from irdrc.agents.base import Hooks, RunRecord, progress_record
from irdrc.agents.configs import QLearningConfig
from irdrc.core.dynamics import Dynamics
from irdrc.core.params import Params

DEFAULT_EVAL_EVERY_FRAMES = 4_000
"""Exact evaluation period when the caller gives none: every 10 episodes of 400 steps."""

PAPER = QLearningConfig(
    episodes=2500,
    alpha=0.01,
    alpha_schedule="constant",
    epsilon_end=0.1,
    name="qlearning_paper",
)
"""The reference profile (MODEL.md § Learning setup): α = 0.01, γ = 0.99, ε = 0.1, 2 500 episodes."""

DEFAULT = QLearningConfig()
"""Our profile: α_k = 1/k for the k-th update of (s, a) (a running average), uniform exploration
(ε = 1: Q-learning is off-policy and only the greedy table is scored), 600 episodes."""


def train(
    params: Params | Sequence[Params],
    cfg: QLearningConfig = DEFAULT,
    *,
    num_learners: int = 1,
    seed: int = 0,
    device: str = "cpu",
    scorers: Any = None,
    eval_every_frames: int = DEFAULT_EVAL_EVERY_FRAMES,
    hooks: Hooks | None = None,
    resume: dict[str, Any] | None = None,
) -> RunRecord:
    """Train ``num_learners`` independent tabular Q-learners per scenario on one batched step.

    Rows are scenario-major: row n is learner ``n % num_learners`` of scenario ``n // num_learners``
    (``RunRecord.group[n]``). Every row draws from the shared generators, so a run is reproducible
    for given (seed, scenarios, num_learners).

    Args:
        params: the model, or several scenarios trained together (same queue capacity and horizon).
        cfg: hyperparameters (``PAPER`` or ``DEFAULT`` or your own).
        num_learners: learners per scenario.
        seed: seed of the dynamics and of the exploration generator.
        device: torch device.
        scorers: exact scorer per scenario, or one for a single scenario
            (``irdrc.core.exact.exact_scorer`` if omitted).
        eval_every_frames: exact evaluation of every greedy table at the end of the first episode
            reaching each multiple of this many env steps (per learner), and at the end.
        hooks: progress callbacks (``on_eval`` per evaluation, ``on_batch`` per episode,
            ``on_checkpoint`` every ``checkpoint_every_frames`` env steps).
        resume: an earlier run's ``RunRecord.state``: the tables, counts and both random streams,
            so a resumed run goes on exactly as the uninterrupted one would have.
    """
    if num_learners < 1:
        raise ValueError(f"num_learners={num_learners!r} must be >= 1")
    if eval_every_frames < 1:
        raise ValueError(f"eval.every_frames={eval_every_frames!r} must be >= 1")
    hooks = hooks or Hooks()
    scenarios = [params] if isinstance(params, Params) else list(params)
    horizons = {p.env.horizon for p in scenarios}
    if len(horizons) > 1:
        raise ValueError(
            f"scenarios trained together must share env.horizon; got {sorted(horizons)}"
        )
    dyn = Dynamics(scenarios, device)
    G = len(scenarios)
    if scorers is None:
        from irdrc.core.exact import exact_scorer

        scorers = [exact_scorer(p) for p in scenarios]
    elif not isinstance(scorers, Sequence):
        scorers = [scorers]
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
    record = RunRecord(method=cfg.name, greedy=q.view(N, S, 2).argmax(-1), group=group_of)
    optima = [sc.optimal_metrics.avg_reward for sc in scorers]
    t0 = time.perf_counter()
    start = 0
    if resume is not None:
        missing = [k for k in ("q", "visits", "rng", "gen", "frames", "history") if k not in resume]
        if missing:
            raise ValueError(
                f"resume: the checkpoint has no {', '.join(missing)}: not a Q-learning checkpoint"
            )
        if resume["q"].shape != q.shape:
            raise ValueError(
                f"resume: the checkpoint holds {resume['q'].numel() // (S * 2)} learners' tables "
                f"of this model, this run {N}"
            )
        q.copy_(resume["q"])
        visits.copy_(resume["visits"])
        rng.set_state(resume["rng"])
        gen.set_state(resume["gen"])
        start = int(resume["frames"]) // T
        record.history = list(resume["history"])
        record.episode_rewards = list(resume["episode_rewards"])
        t0 -= float(resume["wall_seconds"])

    def state(done: int) -> dict[str, Any]:
        return {
            "q": q.clone(),
            "visits": visits.clone(),
            "rng": rng.get_state(),
            "gen": gen.get_state(),
            "frames": done * T,
            "updates": done * T,
            "wall_seconds": time.perf_counter() - t0,
            "history": list(record.history),
            "episode_rewards": list(record.episode_rewards),
        }

    def evaluate(episodes: int) -> None:
        greedy = q.view(N, S, 2).argmax(-1).cpu()
        scored = [scorers[group_of[n]].metrics(greedy[n]) for n in range(N)]
        wall = time.perf_counter() - t0  # evaluations included, as DQN's
        records = [
            progress_record(
                n, episodes * T, episodes, wall, episodes * T, scored[n], optima[group_of[n]]
            )
            for n in range(N)
        ]
        record.history += records
        hooks.eval(records)

    if resume is None:
        evaluate(0)
    next_eval = (start * T // eval_every_frames + 1) * eval_every_frames
    for episode in range(start, cfg.episodes):
        eps = cfg.epsilon(episode)
        total = _episode(cfg, dyn, q, visits, row, eps, T, rng, gen, group)
        done = episode + 1
        record.episode_rewards += [
            {"learner": n, "episode": done, "env_steps": done * T, "reward": float(r)}
            for n, r in enumerate(total.cpu().tolist())
        ]
        hooks.batch({"env_steps": done * T, "episodes": done, "epsilon": eps})
        stop = hooks.stop_requested()
        if done * T >= next_eval or done == cfg.episodes or stop:
            evaluate(done)
            next_eval = (done * T // eval_every_frames + 1) * eval_every_frames
        if hooks.checkpoint_due((done - 1) * T, done * T) and done < cfg.episodes:
            hooks.checkpoint(state(done))
        if stop:
            record.interrupted = True
            break
    record.wall_seconds = time.perf_counter() - t0
    record.q = q.view(N, S, 2).cpu()
    record.greedy = record.q.argmax(-1)
    record.episodes = len(record.episode_rewards) // N
    record.env_steps = record.updates = record.episodes * T
    record.state = state(record.episodes)
    return record


def _episode(
    cfg: QLearningConfig,
    dyn: Dynamics,
    q: torch.Tensor,
    visits: torch.Tensor,
    row: torch.Tensor,
    eps: float,
    steps: int,
    rng: torch.Generator,
    gen: torch.Generator,
    group: torch.Tensor | None,
) -> torch.Tensor:
    """One episode of every learner from a uniform reset, updating ``q`` (and ``visits``) in place;
    returns each learner's total reward."""
    n = row.shape[0]
    state = dyn.reset_states(n, rng)
    total = torch.zeros(n, dtype=torch.float64, device=q.device)
    for _ in range(steps):
        base = row + state * 2
        qs = torch.stack([q[base], q[base + 1]], -1)
        u = torch.rand(n, 2, generator=gen, device=q.device)
        action = torch.where(u[:, 0] < eps, (u[:, 1] < 0.5).long(), qs.argmax(-1))
        res = dyn.step(state, action, rng, group)
        nbase = row + res.state * 2
        target = res.reward + cfg.gamma * torch.maximum(q[nbase], q[nbase + 1])
        idx = base + action
        alpha: torch.Tensor | float = cfg.alpha
        if cfg.alpha_schedule == "count":
            visits[idx] += 1
            alpha = (cfg.alpha / visits[idx] ** cfg.alpha_power).clamp(min=cfg.alpha_min)
        q[idx] += alpha * (target - q[idx])
        total += res.reward
        state = res.state
    return total
