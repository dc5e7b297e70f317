"""The exact optimum: value iteration on the exact model, and exact metrics beside the baselines.

python recipes/solve.py                            # paper scenario
python recipes/solve.py env.p1.speed=1.0 reward.r4=50 hydra.run.dir=runs/solve_v1
python recipes/solve.py env=large                  # S = 100 800, on the factored operator
python recipes/solve.py env=fleet env.share=1.0    # two vehicles: the joint optimum
"""

from irdrc.recipes import solve
from irdrc.runs import app

if __name__ == "__main__":
    app.main(solve)
