"""Benchmark: every learner of the radar share against the exact optimum over ρ, on seeds no tuning used.

    python recipes/bench_timeshare.py                          # sac, ppo, dqn_levels × 5 scenarios × 5 seeds
    python recipes/bench_timeshare.py 'learners=[sac]' 'seeds=[5]' executor=local
    python recipes/bench_timeshare.py 'scenarios={p0.1: [env.p1.speed=0.1]}'

Each (learner, scenario, seed) is one run of ``recipes/sac.py``, ``recipes/ppo.py`` or
``recipes/dqn.py env.actions=levels`` through the sweep engine (Ray: start it in a loopback-only
namespace where the network must stay local, see recipes/sweep.py).
"""

from irdrc.bench import timeshare
from irdrc.runs import app

if __name__ == "__main__":
    app.main(timeshare)
