"""A saved policy on any scenario: exact (long run, episodic) and Monte-Carlo metrics against that
scenario's optimum — transfer and robustness checks in one command.

python recipes/evaluate.py checkpoint=outputs/DATE/TIME/checkpoint.pt env.p1.speed=1.0
python recipes/evaluate.py checkpoint=outputs/DATE/TIME/checkpoint.pt env=multilevel
python recipes/evaluate.py policy=outputs/DATE/TIME/policy.csv reward.r4=50
"""

from __future__ import annotations

from irdrc.experiments.app import recipe
from irdrc.experiments.evaluation import run_evaluate

main = recipe("evaluate", run_evaluate)

if __name__ == "__main__":
    main()
