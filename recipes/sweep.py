"""Sweeps on Ray Tune: every point of a grid of overrides is one run of a recipe's run function.

    python recipes/sweep.py sweep.grid='{env.p1.speed: [0.1,0.5,1.0], reward.r4: [5,50], seed: [0,1,2]}'
    python recipes/sweep.py method=qlearning sweep.grid='{seed: [0,1,2,3,4]}' sweep.base=[algo.episodes=300]
    python recipes/sweep.py resume=true hydra.run.dir=outputs/my_sweep     # finish what did not finish
    python recipes/sweep.py ray.address=auto sweep.grid=...                # on a running Ray cluster

On machines without outside network, start it inside a loopback-only namespace:
``unshare -n sh -c 'ip link set lo up; python recipes/sweep.py …'``.
"""

from __future__ import annotations

from irdrc.experiments.app import recipe
from irdrc.experiments.sweep import run_sweep

main = recipe("sweep", run_sweep)

if __name__ == "__main__":
    main()
