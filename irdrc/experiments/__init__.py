"""From a config to a run directory: one module per recipe on one house.

- one module per recipe (``dqn``, ``qlearning``, ``solve``, ``evaluate``, ``constrained``,
  ``fleet``, ``sweep``, ``study``, ``demo``, ``bench_*``), each with ``NAME``, its frozen ``Config``,
  ``load`` (the composed config to that ``Config``, checked) and ``run``;
- ``compose``: scenarios (``envs/``) and the one Hydra composition of a run;
- ``app``: what every recipe does around its run (composed once, checked before any work, one-line
  errors);
- ``scaffold``: the run directory (lock, log, config files), threads, logger, progress, signals,
  checkpoints and the finishing of a run;
- ``sections``: the config sections recipes share (eval, logger, checkpoint, executor, …);
- ``trials``: grids of runs on Ray Tune or locally; ``grid``: the ``{key: [values]}`` grammar;
- ``report``, ``tables``, ``curves``, ``results``: what a run prints and writes, atomically;
- ``tracking``: W&B / CSV / TensorBoard / no logger; ``progress``; ``cli``: the ``irdrc`` command.

May import: ``irdrc.core``, ``irdrc.agents``, Hydra/OmegaConf, Ray (lazily). Nothing from
``irdrc.paper``.
"""
