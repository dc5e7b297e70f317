"""Vectorised tabular Q-learning: several learners, several scenarios in one batch, scored exactly.

python recipes/qlearning.py                               # our profile
python recipes/qlearning.py algo=qlearning_paper          # the reference profile
python recipes/qlearning.py num_learners=5 'batch_grid={env.p1.speed: [0.1,0.5,1.0]}'
"""

from irdrc.recipes import qlearning
from irdrc.runs import app

if __name__ == "__main__":
    app.main(qlearning)
