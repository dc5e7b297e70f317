"""Benchmark: the exact solver's time and peak memory against S, up to a million states.

    python recipes/bench_scale.py                                   # paper and large, S = 1e3 … 1e6
    python recipes/bench_scale.py 'scenarios=[paper]' 'states=[1000,2000000]' repeats=1

Each solve (value iteration to ``tol`` on the factored operator, then the exact long-run metrics of
its policy) runs in a fresh process; the dense solver runs beside it where S × S fits.
"""

from __future__ import annotations

from irdrc.experiments.app import recipe
from irdrc.experiments.bench_scale import run_bench_scale

main = recipe("bench_scale", run_bench_scale)

if __name__ == "__main__":
    main()
