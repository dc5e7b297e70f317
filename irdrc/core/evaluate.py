"""One Monte-Carlo evaluation for every method: ``evaluate(policy, env, episodes)`` → metrics + CIs."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import torch
from tensordict import TensorDictBase
from torchrl.envs.utils import step_mdp

from irdrc.core.env import DFRCEnv
from irdrc.core.metrics import METRIC_NAMES, Metrics

if TYPE_CHECKING:
    from irdrc.core.params import Params

# Per-episode sums collected by ``evaluate``: numerator of each metric, and its denominator.
_RATIOS = {
    "avg_reward": ("reward", "steps"),
    "throughput": ("sent", "steps"),
    "link_capacity": ("capacity", "steps"),
    "miss_detection": ("missed", "event"),
    "radar_fraction": ("radar", "steps"),
    "drop_rate": ("dropped", "steps"),
    "mean_queue": ("queue", "steps"),
    "false_alarm_rate": ("alarm", "quiet"),
}
_KEYS = (
    "reward",
    "event",
    "missed",
    "sent",
    "capacity",
    "radar",
    "dropped",
    "queue",
    "alarm",
    "quiet",
)


def _metrics(
    values: dict[str, float], ci: dict[str, float], params: Params
) -> tuple[Metrics, dict[str, float]]:
    """The Metrics record (false alarms only where the scenario has them) and its CIs."""
    names = list(METRIC_NAMES)
    if params.env.false_alarm_prob > 0.0:
        names.append("false_alarm_rate")
    return Metrics(**{k: values[k] for k in names}), {k: ci[k] for k in names}


@dataclass(frozen=True)
class Evaluation:
    """Sampled metrics with 95 % confidence half-widths.

    Attributes:
        metrics: ratio-of-sums estimates over every step evaluated.
        ci95: metric → half-width of a 95 % interval (delta method over episodes, which are
            independent; NaN when fewer than two episodes or no event).
        episodes: episodes evaluated.
        steps: env steps evaluated.
        by_state: ``long_run(..., by_state=True)`` only: per-(state, action) sums [S, 2] (float64,
            action 0 = comm) of ``STATE_ACTION_SUMS`` over every step run (burn-in included: the
            signals' rates given the state and action do not depend on the policy), and
            ``visits``, the steps per state and action in the measured (last) block.
    """

    metrics: Metrics
    ci95: dict[str, float]
    episodes: int
    steps: int
    by_state: dict[str, torch.Tensor] | None = None


def ratio_ci(x: torch.Tensor, y: torch.Tensor, z: float = 1.959964) -> tuple[float, float]:
    """Ratio of sums Σx/Σy over independent clusters, and the half-width of its z-interval.

    The standard error is the delta-method (cluster-robust) one:
    se² = n/(n−1) · Σ(xᵢ − R·yᵢ)² / (Σy)².
    """
    x, y = x.double(), y.double()
    n, sy = x.numel(), float(y.sum())
    if sy == 0:
        return math.nan, math.nan
    r = float(x.sum()) / sy
    if n < 2:
        return r, math.nan
    resid = x - r * y
    se = math.sqrt(n / (n - 1) * float((resid**2).sum())) / sy
    return r, z * se


@torch.no_grad()
def evaluate(policy: Any, env: DFRCEnv, episodes: int | None = None) -> Evaluation:
    """Run full episodes of ``policy`` on the batched ``env`` and aggregate MODEL.md's metrics.

    Every batch row plays whole episodes of ``env.params.env.horizon`` steps from a reset, so
    ``ceil(episodes / N)`` batched rounds are run (all of one round's episodes count).

    Args:
        policy: any TensorDictModule writing ``action`` (see ``irdrc.core.policies``).
        env: a ``DFRCEnv`` (its own seed decides the randomness).
        episodes: episodes to run at least; default one per batch row.
    """
    n = env.batch_size.numel()
    rounds = 1 if episodes is None else max(1, math.ceil(episodes / n))
    horizon = env.params.env.horizon
    keys = _KEYS
    per_episode: dict[str, list[torch.Tensor]] = {k: [] for k in keys}
    shares = env.params.env.shares  # the radar share of each action (binary: 0, 1)
    share = None if shares is None else torch.tensor(shares, dtype=torch.float64, device=env.device)
    for _ in range(rounds):
        sums = {k: torch.zeros(n, dtype=torch.float64, device=env.device) for k in keys}
        td: TensorDictBase = env.reset()
        for _ in range(horizon):
            td = policy(td)
            sums["queue"] += td["observation"][..., 0].reshape(-1)
            action = td["action"].reshape(-1)
            radar = action.double() if share is None else share[action.long()]  # ρ itself
            sums["radar"] += radar
            td = env.step(td)
            nxt = td["next"]
            sums["reward"] += nxt["reward"].reshape(-1)
            for k in ("event", "missed", "sent", "capacity", "dropped"):
                sums[k] += nxt[k].reshape(-1)
            sums["alarm"] += nxt["false_alarm"].reshape(-1)
            sums["quiet"] += radar * ~nxt["event"].reshape(-1)
            td = step_mdp(td)
        for k in keys:
            per_episode[k].append(sums[k].cpu())
    cols = {k: torch.cat(v) for k, v in per_episode.items()}
    cols["steps"] = torch.full_like(cols["reward"], float(horizon))
    values, ci = {}, {}
    for name, (num, den) in _RATIOS.items():
        values[name], ci[name] = ratio_ci(cols[num], cols[den])
    values["episode_reward"] = values["avg_reward"] * horizon
    ci["episode_reward"] = ci["avg_reward"] * horizon
    metrics, ci95 = _metrics(values, ci, env.params)
    return Evaluation(
        metrics=metrics,
        ci95=ci95,
        episodes=int(cols["reward"].numel()),
        steps=int(cols["steps"].sum()),
    )


STATE_ACTION_SUMS = ("steps", "sent", "capacity", "reward", "event", "missed")
"""What ``long_run(..., by_state=True)`` sums per state and action over every step run: the steps
taken and the step's signals of ``irdrc.core.dynamics`` (``StepResult``)."""

STATIONARITY_KEYS = ("miss_detection", "throughput", "mean_queue")
"""Rates that two consecutive blocks of ``long_run`` must agree on (it checks stationarity)."""


@torch.no_grad()
def long_run(
    params: Params,
    p_radar: torch.Tensor,
    *,
    envs: int = 256,
    steps: int = 2_000,
    burn_in: int = 1_000,
    max_blocks: int = 1,
    seed: int = 0,
    device: str = "cpu",
    by_state: bool = False,
) -> Evaluation:
    """Long-run (stationary) Monte-Carlo metrics of the stationary policy ``p_radar`` ([S]
    probability of radar per state) on the simulator: ``envs`` independent chains from uniform
    states, never reset, run ``burn_in`` steps and then measured over blocks of ``steps`` steps.

    The counterpart of ``irdrc.core.exact.stationary_metrics`` by sampling, with no episode
    boundary: a policy that lingers in some states (e.g. a full queue) is measured as it would
    run on a vehicle, not biased by resets. With ``max_blocks`` > 1 the chains run block after
    block until two consecutive blocks agree on ``STATIONARITY_KEYS`` (within twice the combined
    95 % half-width), at most ``max_blocks`` blocks: a policy that drifts slowly towards a
    trap (e.g. a full queue it never empties) is then measured after the drift, not during it.
    The result describes the last block; ``steps`` counts every step run. Confidence
    half-widths treat each chain as one independent sample (delta method). With ``by_state`` the
    result also carries, per state and action, the sums of ``STATE_ACTION_SUMS`` over every step
    run and the last block's visits (``Evaluation.by_state``); the random numbers, and so the
    metrics, are the same either way.
    """
    from irdrc.core.dynamics import Dynamics

    if envs < 2 or steps < 1 or burn_in < 0 or max_blocks < 1:
        raise ValueError(
            "long_run needs envs >= 2, steps >= 1, burn_in >= 0, max_blocks >= 1; got "
            f"{envs}, {steps}, {burn_in}, {max_blocks}"
        )
    dyn = Dynamics(params, device=device)
    p = torch.as_tensor(p_radar, dtype=torch.float64, device=dyn.device).reshape(-1)
    if p.shape[0] != dyn.num_states or bool(((p < 0) | (p > 1)).any()):
        raise ValueError(f"p_radar must be {dyn.num_states} probabilities in [0, 1]")
    gen = torch.Generator(device=dyn.device).manual_seed(int(seed))
    state = dyn.reset_states(envs, gen)
    shape = (dyn.num_states * 2,)
    per_state = (
        {
            k: torch.zeros(shape, dtype=torch.float64, device=dyn.device)
            for k in (*STATE_ACTION_SUMS, "visits")
        }
        if by_state
        else None
    )
    ones = torch.ones(envs, dtype=torch.float64, device=dyn.device)

    def run(n: int, sums: dict[str, torch.Tensor] | None) -> torch.Tensor:
        nonlocal state
        if per_state is not None and sums is not None:
            per_state["visits"].zero_()  # the visits of the last block only
        for _ in range(n):
            u = torch.rand(envs, generator=gen, device=dyn.device, dtype=torch.float64)
            action = (u < p[state]).long()
            out = dyn.step(state, action, gen)
            if per_state is not None:
                sa = state * 2 + action
                per_state["steps"].index_add_(0, sa, ones)
                if sums is not None:
                    per_state["visits"].index_add_(0, sa, ones)
                for k in STATE_ACTION_SUMS[1:]:
                    per_state[k].index_add_(0, sa, getattr(out, k).double())
            if sums is not None:
                sums["queue"] += dyn.split(state)[0].double()
                sums["radar"] += action.double()
                for k in ("reward", "event", "missed", "sent", "capacity", "dropped"):
                    sums[k] += getattr(out, k).double()
                sums["alarm"] += out.false_alarm.double()
                sums["quiet"] += ((action == 1) & ~out.event).double()
            state = out.state
        return state

    def block() -> tuple[dict[str, float], dict[str, float]]:
        sums = {k: torch.zeros(envs, dtype=torch.float64, device=dyn.device) for k in _KEYS}
        run(steps, sums)
        sums = {k: v.cpu() for k, v in sums.items()}
        sums["steps"] = torch.full((envs,), float(steps), dtype=torch.float64)
        values, ci = {}, {}
        for name, (num, den) in _RATIOS.items():
            values[name], ci[name] = ratio_ci(sums[num], sums[den])
        return values, ci

    def agree(
        a: tuple[dict[str, float], dict[str, float]], b: tuple[dict[str, float], dict[str, float]]
    ) -> bool:
        for k in STATIONARITY_KEYS:
            va, vb, ha, hb = a[0][k], b[0][k], a[1][k], b[1][k]
            if math.isnan(va) != math.isnan(vb):
                return False
            if not math.isnan(va) and abs(va - vb) > 2 * math.hypot(ha, hb) + 1e-12:
                return False
        return True

    run(burn_in, None)
    last = block()
    blocks = 1
    while blocks < max_blocks:
        nxt = block()
        blocks += 1
        settled = agree(last, nxt)
        last = nxt
        if settled:
            break
    values, ci = last
    horizon = params.env.horizon
    values["episode_reward"] = values["avg_reward"] * horizon
    ci["episode_reward"] = ci["avg_reward"] * horizon
    metrics, ci95 = _metrics(values, ci, params)
    return Evaluation(
        metrics=metrics,
        ci95=ci95,
        episodes=envs,
        steps=envs * (burn_in + blocks * steps),
        by_state=None
        if per_state is None
        else {k: v.cpu().reshape(-1, 2) for k, v in per_state.items()},
    )


@torch.no_grad()
def chain_rewards(
    params: Params,
    tables: torch.Tensor,
    *,
    envs: int = 64,
    steps: int = 1_000,
    burn_in: int = 200,
    seed: int = 0,
    device: str = "cpu",
) -> torch.Tensor:
    """Each chain's mean reward per step under each deterministic policy of ``tables`` ([K, S]
    actions, 1 = radar), with common random numbers: → [K, envs].

    Every policy runs ``envs`` chains from the same uniform start states on the same random
    stream (the simulator draws the same numbers each step whatever the action), for ``burn_in``
    steps and then ``steps`` measured steps. Chain ``i`` therefore meets the same arrivals,
    channel and events under every policy, and the per-chain difference of two rows measures
    their difference with far less noise than two independent runs. ``K·envs·(burn_in + steps)``
    env steps in all.
    """
    from irdrc.core.dynamics import Dynamics

    if envs < 2 or steps < 1 or burn_in < 0:
        raise ValueError(
            f"chain_rewards needs envs >= 2, steps >= 1, burn_in >= 0; got {envs}, {steps}, "
            f"{burn_in}"
        )
    dyn = Dynamics(params, device=device)
    tables = torch.as_tensor(tables, device=dyn.device).long()
    if tables.dim() != 2 or tables.shape[1] != dyn.num_states:
        raise ValueError(f"tables must be [K, {dyn.num_states}] actions; got {tuple(tables.shape)}")
    if bool(((tables < 0) | (tables > 1)).any()):
        raise ValueError("tables hold actions 0 (comm) or 1 (radar)")
    out = torch.zeros(tables.shape[0], envs, dtype=torch.float64)
    for k, table in enumerate(tables):
        gen = torch.Generator(device=dyn.device).manual_seed(int(seed))
        state = dyn.reset_states(envs, gen)
        total = torch.zeros(envs, dtype=torch.float64, device=dyn.device)
        for t in range(burn_in + steps):
            step = dyn.step(state, table[state], gen)
            if t >= burn_in:
                total += step.reward.double()
            state = step.state
        out[k] = (total / steps).cpu()
    return out
