"""A saved policy scored on any scenario: exactly, by Monte-Carlo, against that scenario's optimum.

python recipes/evaluate.py checkpoint=outputs/DATE/TIME/checkpoint.pt env.p1.speed=1.0
python recipes/evaluate.py policy=outputs/DATE/TIME/policy.csv env=ref_impl
"""

from irdrc.recipes import evaluate
from irdrc.runs import app

if __name__ == "__main__":
    app.main(evaluate)
