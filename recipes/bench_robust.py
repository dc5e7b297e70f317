"""Benchmark: does DQN reach the exact optimum on seeds it was never tuned on, in every scenario?

    python recipes/bench_robust.py                              # 20 seeds × 6 scenarios, on Ray
    python recipes/bench_robust.py 'seeds=[5,6,7]' 'p1_speed=[0.1]' 'r4=[5]' executor=local
    python recipes/bench_robust.py "overrides=['algo=dqn','algo.total_frames=40000']"

Each (scenario, seed) is one run of ``recipes/dqn.py`` through the sweep engine (Ray: start it in a
loopback-only namespace where the network must stay local, see recipes/sweep.py).
"""

from irdrc.bench import robust
from irdrc.runs import app

if __name__ == "__main__":
    app.main(robust)
