"""The radar/communication trade-off the paper only mentions (its claim 3), exactly.

    python recipes/tradeoff.py                                    # r4 ∈ 5 … 200, target miss 0.05
    python recipes/tradeoff.py target_miss=0.1 'p1_speed=[0.1,1.0]' search.resolution=0.01
    python recipes/tradeoff.py 'r4=[5,10,20,30,40,45,50]' dqn.r4=[]     # exact only, no training

DQN runs (``dqn.r4``) go through the sweep engine like any sweep (Ray: see recipes/sweep.py).
"""

from __future__ import annotations

import sys
from pathlib import Path

import hydra
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig

from irdrc.config import CONF_DIR, register_scenarios, scenario_overrides
from irdrc.reproduce import run_tradeoff

register_scenarios()


@hydra.main(config_path=str(CONF_DIR), config_name="tradeoff", version_base=None)
def main(cfg: DictConfig) -> None:
    """Run ``irdrc.reproduce.run_tradeoff`` into the Hydra run directory."""
    code = run_tradeoff(cfg, Path(HydraConfig.get().runtime.output_dir), scenario_overrides())
    if code:
        sys.exit(code)


if __name__ == "__main__":
    main()
