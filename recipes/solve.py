"""The exact optimum: value iteration on the exact model, and exact metrics beside the baselines.

python recipes/solve.py                            # paper scenario
python recipes/solve.py env.p1.speed=1.0 reward.r4=50 hydra.run.dir=runs/solve_v1
"""

from __future__ import annotations

from pathlib import Path

import hydra
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig

from irdrc.config import CONF_DIR, register_scenarios
from irdrc.runs import run_solve

register_scenarios()


@hydra.main(config_path=str(CONF_DIR), config_name="solve", version_base=None)
def main(cfg: DictConfig) -> None:
    """Run ``irdrc.runs.run_solve`` into the Hydra run directory."""
    run_solve(cfg, Path(HydraConfig.get().runtime.output_dir))


if __name__ == "__main__":
    main()
