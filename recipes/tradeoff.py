"""The radar/communication trade-off the paper only mentions (its claim 3), exactly.

    python recipes/tradeoff.py                                    # r4 ∈ 5 … 200, target miss 0.05
    python recipes/tradeoff.py target_miss=0.1 'p1_speed=[0.1,1.0]' search.resolution=0.01
    python recipes/tradeoff.py 'r4=[5,10,20,30,40,45,50]' dqn.r4=[]     # exact only, no training

DQN runs (``dqn.r4``) go through the sweep engine like any sweep (Ray: see recipes/sweep.py).
"""

from irdrc.paper import tradeoff
from irdrc.runs import app

if __name__ == "__main__":
    app.main(tradeoff)
