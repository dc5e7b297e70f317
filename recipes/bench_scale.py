"""Benchmark: the exact solver's time and peak memory against S, up to a million states.

    python recipes/bench_scale.py                                   # paper and large, S = 1e3 … 1e6
    python recipes/bench_scale.py 'scenarios=[paper]' 'states=[1000,2000000]' repeats=1

Each solve (value iteration to ``tol`` on the factored operator, then the exact long-run metrics of
its policy) runs in a fresh process; the dense solver runs beside it where S × S fits.
"""

from irdrc.bench import scale
from irdrc.runs import app

if __name__ == "__main__":
    app.main(scale)
