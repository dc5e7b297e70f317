"""Benchmark: env steps per second of DFRCEnv for several batch sizes (medians of repeated runs).

python recipes/bench_env.py                          # table + bench_env.csv in the run dir
python recipes/bench_env.py sizes=[1024,65536] threads=[1] repeats=3
python recipes/bench_env.py modes=[numpy_single,gym] sizes=[]   # single-env speed only
"""

from irdrc.bench import env
from irdrc.runs import app

if __name__ == "__main__":
    app.main(env)
