"""Benchmark: how fast each DQN profile trains, and how soon it reaches the exact optimum.

Env steps/s and updates/s of training on one thread, where the time goes, and env steps and seconds
to 95 % / 99 % of the optimum, over seeds.

    python recipes/bench_dqn.py                                # the default against the previous shape
    python recipes/bench_dqn.py 'seeds=[0]' 'profiles={dqn: [algo=dqn]}'

Each profile is ``recipes/dqn.py`` with its overrides, trained with ``irdrc.agents.dqn.train``;
profiles alternate seed by seed, so their speeds are measured under the same load.
"""

from irdrc.bench import dqn
from irdrc.runs import app

if __name__ == "__main__":
    app.main(dqn)
