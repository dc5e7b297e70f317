"""A grid of overrides, each point one run of a recipe, on Ray Tune (or executor=local).

python recipes/sweep.py 'sweep.grid={env.p1.speed: [0.1,0.5,1.0], reward.r4: [5,50], seed: [0,1,2]}'
python recipes/sweep.py method=constrained executor=local 'sweep.grid={target_miss: [0.02,0.05,0.1]}'
python recipes/sweep.py resume=true hydra.run.dir=outputs/DATE/TIME   # finish an interrupted sweep
"""

from irdrc.recipes import sweep
from irdrc.runs import app

if __name__ == "__main__":
    app.main(sweep)
