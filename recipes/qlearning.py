"""Tabular Q-learning: train (vectorised over learners), evaluate exactly and by Monte-Carlo.

python recipes/qlearning.py                                  # our profile, paper scenario
python recipes/qlearning.py algo=qlearning_paper num_learners=5
python recipes/qlearning.py env.p1.speed=0.5 reward.r4=50 seed=3 hydra.run.dir=runs/q3
"""

from __future__ import annotations

from irdrc.experiments.app import recipe
from irdrc.experiments.runs import run_qlearning

main = recipe("qlearning", run_qlearning)

if __name__ == "__main__":
    main()
