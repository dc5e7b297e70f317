"""PPO on the radar share of each step (MODEL.md § D), scored exactly against the optimum over ρ.

python recipes/ppo.py                                      # the paper scenario
python recipes/ppo.py env.p1.speed=1.0 seed=3
python recipes/ppo.py env=multilevel algo.total_frames=4000000
"""

from irdrc.recipes.shares import ppo
from irdrc.runs import app

if __name__ == "__main__":
    app.main(ppo)
