"""DQN from TorchRL parts, evaluated exactly against the optimum — the main job.

python recipes/dqn.py                                   # our profile, paper scenario
python recipes/dqn.py reward.r4=50 network=large env=ref_impl
python recipes/dqn.py algo=dqn_paper                    # the reference profile (1 M steps)
python recipes/dqn.py logger=wandb logger.mode=offline
python recipes/dqn.py resume=outputs/…/checkpoint.pt algo.total_frames=40000
"""

from __future__ import annotations

from pathlib import Path

import hydra
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig

from irdrc.config import CONF_DIR, register_scenarios
from irdrc.runs import run_dqn

register_scenarios()


@hydra.main(config_path=str(CONF_DIR), config_name="dqn", version_base=None)
def main(cfg: DictConfig) -> None:
    """Run ``irdrc.runs.run_dqn`` into the Hydra run directory."""
    run_dqn(cfg, Path(HydraConfig.get().runtime.output_dir))


if __name__ == "__main__":
    main()
