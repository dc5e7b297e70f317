"""Benchmark: how fast each DQN profile trains (env steps/s and updates/s on one thread, where the
time goes) and how soon it reaches 95 % / 99 % of the exact optimum, over seeds.

    python recipes/bench_dqn.py                                # the default against the previous shape
    python recipes/bench_dqn.py 'seeds=[0]' stacked=[]

Each profile is ``recipes/dqn.py`` with its overrides, trained with ``irdrc.agents.dqn.train``;
profiles alternate seed by seed, so their speeds are measured under the same load.
"""

from __future__ import annotations

from irdrc.experiments.app import recipe
from irdrc.experiments.bench import run_bench_dqn

main = recipe("bench_dqn", run_bench_dqn)

if __name__ == "__main__":
    main()
