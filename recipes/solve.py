"""The exact optimum: value iteration on the exact model, and exact metrics beside the baselines.

python recipes/solve.py                            # paper scenario
python recipes/solve.py env.p1.speed=1.0 reward.r4=50 hydra.run.dir=runs/solve_v1
"""

from __future__ import annotations

from irdrc.experiments.app import recipe
from irdrc.experiments.runs import run_solve

main = recipe("solve", run_solve)

if __name__ == "__main__":
    main()
