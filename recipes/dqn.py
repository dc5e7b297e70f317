"""DQN from TorchRL parts, evaluated exactly against the optimum — the main job.

python recipes/dqn.py                                   # our profile, paper scenario
python recipes/dqn.py reward.r4=50 network=large env=ref_impl
python recipes/dqn.py algo=dqn_paper                    # the reference profile (1 M steps)
python recipes/dqn.py logger=wandb logger.mode=offline
python recipes/dqn.py resume=outputs/…/checkpoint.pt algo.total_frames=1000000
"""

from irdrc.recipes import dqn
from irdrc.runs import app

if __name__ == "__main__":
    app.main(dqn)
