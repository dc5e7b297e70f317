"""The paper's Figure 2 and its claims, regenerated against the exact optimum.

    python recipes/figure2.py                                     # the default run (docs/REPRODUCTION.md)
    python recipes/figure2.py seeds=[0,1,2] p1_speed=[0.1,0.5,1.0] methods=[dqn,qlearning]
    python recipes/figure2.py 'learners.dqn_paper.overrides=[algo=dqn_paper,algo.total_frames=200000]'
    python recipes/figure2.py executor=local                      # without Ray, one run after another
    python recipes/figure2.py resume=true hydra.run.dir=outputs/figure2   # finish an interrupted run

Training runs go through the sweep engine (Ray Tune by default); on machines without outside
network start it inside a loopback-only namespace: ``unshare -n sh -c 'ip link set lo up; …'``.
"""

from __future__ import annotations

import sys
from pathlib import Path

import hydra
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig

from irdrc.config import CONF_DIR, register_scenarios, scenario_overrides
from irdrc.reproduce import run_figure2

register_scenarios()


@hydra.main(config_path=str(CONF_DIR), config_name="figure2", version_base=None)
def main(cfg: DictConfig) -> None:
    """Run ``irdrc.reproduce.run_figure2`` into the Hydra run directory."""
    code = run_figure2(cfg, Path(HydraConfig.get().runtime.output_dir), scenario_overrides())
    if code:
        sys.exit(code)


if __name__ == "__main__":
    main()
