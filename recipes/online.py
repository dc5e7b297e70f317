"""One vehicle learning on the road from its own stream, with the price of learning counted exactly.

python recipes/online.py                                 # posterior sampling on the model's form
python recipes/online.py learner=dqn env=multilevel      # DQN on one stream, told nothing
python recipes/online.py learner=safe algo.target_miss=0.1
python recipes/online.py learner=qlearning_paper algo.episodes=600
"""

from irdrc.online import recipe
from irdrc.runs import app

if __name__ == "__main__":
    app.main(recipe)
