"""Demo: roll out the paper's baselines on a batch of envs and print MODEL.md's metrics.

python recipes/demo.py                       # paper scenario
python recipes/demo.py env=ref_impl reward.r4=50 eval.mc_num_envs=4096
"""

from irdrc.recipes import demo
from irdrc.runs import app

if __name__ == "__main__":
    app.main(demo)
