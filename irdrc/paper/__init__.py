"""The paper's experiments: Figure 2, the r4 trade-off, their claims, figures and the report.

- ``figure2``: Fig. 2 regenerated (training runs through ``irdrc.sweeps.trials``), its
  panels drawn by ``panels``;
- ``tradeoff``: the exact optimum as r4 varies, and the smallest r4 meeting a miss target;
- ``report``: fills ``docs/REPRODUCTION.md`` from run directories;
- ``claims``: the paper's claims as functions of numbers; ``figures``: bands and curves; ``plots``:
  drawing.

- ``road``: Fig. 2(a) on one vehicle, from ``recipes/bench_online.py``'s runs.

May import every layer below (``irdrc.core`` … ``irdrc.bench``); it trains only through the
recipes and the sweep engine.
"""
