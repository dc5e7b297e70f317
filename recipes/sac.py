"""SAC on the radar share of each step (MODEL.md § D), scored exactly against the optimum over ρ.

python recipes/sac.py                                      # the paper scenario
python recipes/sac.py env.p1.speed=1.0 seed=3
python recipes/sac.py env=multilevel algo.total_frames=1600000
"""

from irdrc.recipes.shares import sac
from irdrc.runs import app

if __name__ == "__main__":
    app.main(sac)
