"""The demo behind ``recipes/demo.py``: the paper's baselines rolled out on a batch of envs."""

from __future__ import annotations

import time
from pathlib import Path

import torch
from omegaconf import DictConfig

from irdrc.core import policies
from irdrc.core.env import DFRCEnv
from irdrc.core.evaluate import evaluate
from irdrc.core.metrics import format_table
from irdrc.core.params import Params
from irdrc.experiments.config import scenario_name

POLICIES = {
    "round_robin": policies.round_robin,
    "always_radar": policies.always_radar,
    "always_comm": policies.always_comm,
    "random": policies.uniform_random,
}


def run_demo(cfg: DictConfig, out: Path | None = None) -> int:
    """Evaluate each policy of ``cfg.policies`` and print the side-by-side table."""
    torch.set_num_threads(1)
    params = Params.from_config(cfg)
    unknown = [p for p in cfg.policies if p not in POLICIES]
    if unknown:
        raise ValueError(f"policies: unknown {unknown}; choose from {sorted(POLICIES)}")
    num_envs, episodes = int(cfg.eval.mc_num_envs), int(cfg.eval.mc_episodes)
    if num_envs < 1 or episodes < 1:
        raise ValueError("eval.mc_num_envs and eval.mc_episodes must be >= 1")
    rows, errs = {}, {}
    t0 = time.perf_counter()
    for i, name in enumerate(cfg.policies):
        env = DFRCEnv(params, batch_size=[num_envs], device=cfg.device, seed=cfg.seed + i)
        policy = POLICIES[name]() if name != "random" else policies.uniform_random(seed=cfg.seed)
        ev = evaluate(policy.to(env.device), env, episodes=episodes)
        rows[name], errs[name] = ev.metrics, ev.ci95
    steps = ev.steps * len(cfg.policies)
    print(f"scenario={scenario_name(cfg)} p1.speed={params.env.p1.speed} r4={params.reward.r4}")
    print(f"{ev.episodes} episodes of {params.env.horizon} steps per policy (± = 95 % CI)\n")
    print(format_table(rows, errors=errs))
    print(f"\n{steps} env steps in {time.perf_counter() - t0:.1f} s")
    return 0
