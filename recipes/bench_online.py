"""Benchmark: the learners on one stream, scored by the price of learning, on seeds and scenarios no
tuning used.

    python recipes/bench_online.py                                    # the whole benchmark
    python recipes/bench_online.py 'scenarios=[paper]' random_draws=0 'safe_targets=[]'
    python recipes/bench_online.py resume=true hydra.run.dir=outputs/…   # run only what is missing
"""

from irdrc.bench import online
from irdrc.runs import app

if __name__ == "__main__":
    app.main(online)
