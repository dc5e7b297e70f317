"""Benchmark: multi-agent learners on a fleet against the exact centralised optimum and the baselines.

    python recipes/bench_fleet.py                                   # on Ray (loopback-only namespace)
    python recipes/bench_fleet.py executor=local 'learners=[vdn]' 'seeds=[0]' 'vehicles=[2,4]'
    python recipes/bench_fleet.py "overrides=['algo.total_frames=100000']" search=false

Part A: N = 2, every (share, channels) cell × learner × seed, scored exactly; part B: N = 2 … 8,
own-observation learners against the baselines by Monte-Carlo (docs/FLEET.md).
"""

from irdrc.bench import fleet
from irdrc.runs import app

if __name__ == "__main__":
    app.main(fleet)
