"""Tabular Q-learning: train (vectorised over learners), evaluate exactly and by Monte-Carlo.

python recipes/qlearning.py                                  # our profile, paper scenario
python recipes/qlearning.py algo=qlearning_paper num_learners=5
python recipes/qlearning.py env.p1.speed=0.5 reward.r4=50 seed=3 hydra.run.dir=runs/q3
"""

from __future__ import annotations

from pathlib import Path

import hydra
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig

from irdrc.config import CONF_DIR, register_scenarios
from irdrc.runs import run_qlearning

register_scenarios()


@hydra.main(config_path=str(CONF_DIR), config_name="qlearning", version_base=None)
def main(cfg: DictConfig) -> None:
    """Run ``irdrc.runs.run_qlearning`` into the Hydra run directory."""
    run_qlearning(cfg, Path(HydraConfig.get().runtime.output_dir))


if __name__ == "__main__":
    main()
