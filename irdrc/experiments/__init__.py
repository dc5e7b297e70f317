"""From a config to a run directory: run functions per method, grids, sweeps, files, tracking, cli.

- ``config``: scenarios (``envs/``) and Hydra composition;
- ``app``: what every recipe does before its run (deprecated keys, clear config errors);
- ``grid``: the ``{key: [values]}`` grid grammar shared by sweeps and batched scenarios;
- ``runs``: one run function per method and the one way every run finishes;
- ``sweep``: grids of runs on Ray Tune or locally;
- ``results``: ``summary.json``, ``policy.csv``, ``metrics.csv``, atomically written;
- ``tracking``: W&B / CSV / no logger;
- ``cli``: the ``irdrc`` command.

May import: ``irdrc.core``, ``irdrc.agents``, Hydra/OmegaConf, Ray (lazily). Nothing from
``irdrc.paper``.
"""
