"""Benchmark: does the Lagrangian DQN reach the exact constrained optimum, on every seed?

    python recipes/bench_constrained.py                                  # 2 targets × 2 p^v_1 × 10 seeds
    python recipes/bench_constrained.py 'seeds=[0,1]' 'targets=[0.15]' executor=local
    python recipes/bench_constrained.py "overrides=['algo.total_frames=40000']"

Each (p^v_1, target, seed) is one run of ``recipes/constrained.py learner=dqn_lagrangian`` through
the sweep engine (Ray: start it in a loopback-only namespace where the network must stay local,
see recipes/sweep.py), scored exactly against the LP optimum of its own cell.
"""

from irdrc.bench import constrained
from irdrc.runs import app

if __name__ == "__main__":
    app.main(constrained)
