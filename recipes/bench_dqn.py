"""Benchmark: how fast each DQN profile reaches 95 % / 99 % of the exact optimum, over seeds.

    python recipes/bench_dqn.py                                # both profiles, 5 seeds
    python recipes/bench_dqn.py profiles=[dqn] seeds=[0,1,2]

Each profile is composed exactly as ``recipes/dqn.py algo=<profile>`` composes it, then trained with
the same ``irdrc.agents.dqn.train``. Seconds are wall time of training (exact evaluations included).
"""

from __future__ import annotations

from irdrc.experiments.app import recipe
from irdrc.experiments.bench import run_bench_dqn

main = recipe("bench_dqn", run_bench_dqn)

if __name__ == "__main__":
    main()
