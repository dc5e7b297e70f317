"""Demo: roll out the paper's baselines on a batch of envs and print MODEL.md's metrics.

python recipes/demo.py                       # paper scenario
python recipes/demo.py env=ref_impl reward.r4=50 num_envs=4096
"""

from __future__ import annotations

import time

import hydra
import torch
from omegaconf import DictConfig

from irdrc import DFRCEnv, Params, policies
from irdrc.config import CONF_DIR, register_scenarios, scenario_name
from irdrc.evaluate import evaluate
from irdrc.metrics import format_table

POLICIES = {
    "round_robin": policies.round_robin,
    "always_radar": policies.always_radar,
    "always_comm": policies.always_comm,
    "random": policies.uniform_random,
}

register_scenarios()


@hydra.main(config_path=str(CONF_DIR), config_name="demo", version_base=None)
def main(cfg: DictConfig) -> None:
    """Evaluate each policy of ``cfg.policies`` and print the side-by-side table."""
    torch.set_num_threads(1)
    params = Params.from_config(cfg)
    unknown = [p for p in cfg.policies if p not in POLICIES]
    if unknown:
        raise ValueError(f"policies: unknown {unknown}; choose from {sorted(POLICIES)}")
    if cfg.num_envs < 1 or cfg.episodes < 1:
        raise ValueError("num_envs and episodes must be >= 1")
    rows, errs = {}, {}
    t0 = time.perf_counter()
    for i, name in enumerate(cfg.policies):
        env = DFRCEnv(params, batch_size=[cfg.num_envs], device=cfg.device, seed=cfg.seed + i)
        policy = POLICIES[name]() if name != "random" else policies.uniform_random(seed=cfg.seed)
        ev = evaluate(policy.to(env.device), env, episodes=cfg.episodes)
        rows[name], errs[name] = ev.metrics, ev.ci95
    steps = ev.steps * len(cfg.policies)
    print(f"scenario={scenario_name(cfg)} p1.speed={params.env.p1.speed} r4={params.reward.r4}")
    print(f"{ev.episodes} episodes of {params.env.horizon} steps per policy (± = 95 % CI)\n")
    print(format_table(rows, errors=errs))
    print(f"\n{steps} env steps in {time.perf_counter() - t0:.1f} s")


if __name__ == "__main__":
    main()
