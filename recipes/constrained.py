"""The design question, answered exactly: the most data subject to a miss-detection target.

python recipes/constrained.py target_miss=0.05               # LP optimum, summary.json, policy.csv
python recipes/constrained.py target_miss=0.15 env.p1.speed=1.0 objective=avg_reward
python recipes/constrained.py target_miss=0.05 max_drop=0.01 min_radar=0.5
python recipes/constrained.py frontier=true                  # frontier vs the r4 route
python recipes/constrained.py learner=dqn_lagrangian target_miss=0.05 seed=3
"""

from irdrc.recipes.constrained import recipe
from irdrc.runs import app

if __name__ == "__main__":
    app.main(recipe)
