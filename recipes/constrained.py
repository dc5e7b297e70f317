"""The design question, answered exactly: the most data subject to a miss-detection target.

python recipes/constrained.py target_miss=0.05               # LP optimum, summary.json, policy.csv
python recipes/constrained.py target_miss=0.15 env.p1.speed=1.0 objective=avg_reward
python recipes/constrained.py target_miss=0.05 max_drop=0.01 min_radar=0.5
python recipes/constrained.py frontier=true                  # frontier vs the r4 route
"""

from __future__ import annotations

from irdrc.experiments.app import recipe
from irdrc.paper.frontier import run_constrained_recipe

main = recipe("constrained", run_constrained_recipe)

if __name__ == "__main__":
    main()
