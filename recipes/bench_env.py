"""Benchmark: env steps per second of DFRCEnv for several batch sizes (medians of repeated runs).

python recipes/bench_env.py                          # table + bench_env.csv in the run dir
python recipes/bench_env.py sizes=[1024,65536] threads=[1] repeats=3
python recipes/bench_env.py modes=[numpy_single,gym] sizes=[]   # single-env speed only
"""

from __future__ import annotations

import irdrc  # noqa: F401 - registers irdrc/DFRC-v0 for the gym modes
from irdrc.experiments.app import recipe
from irdrc.experiments.bench_env import run_bench_env

main = recipe("bench_env", run_bench_env)

if __name__ == "__main__":
    main()
