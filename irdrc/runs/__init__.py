"""The run machinery every recipe uses: from a command line to a run directory.

- ``scenarios``: the named scenarios (``irdrc/scenarios/``); ``compose``: the one Hydra
  composition of a run; ``grid``: the command line's grammar (an override's key, ``{key: [values]}`` grids, values as typed);
- ``app``: what every recipe does around its run (composed once, checked before any work, one-line
  errors); ``cli``: the ``irdrc`` command;
- ``sections``: the config sections recipes share (scenario, eval, logger, checkpoint, executor …);
  ``limits``: what this machine can run (the exact model's size, a learner's memory, the device);
- ``scaffold``: the run directory (lock, log, config files), threads, logger, progress,
  checkpoints (with their digest) and the finishing of a run; ``signals``: SIGINT/SIGTERM in any
  phase; ``resume``: a resumed run's configuration and what it refuses; ``progress``;
  ``tracking``: W&B / CSV / TensorBoard;
- ``report``: how a single-vehicle learner's run finishes (files, table, last lines); ``tables``
  (``policy.csv``), ``curves`` (the learning curve), ``results`` (atomic files, summaries).

May import: ``irdrc.core``, ``irdrc.fleet``, ``irdrc.agents``, Hydra/OmegaConf. No recipe, no
sweep, nothing of ``irdrc.paper``.
"""
