"""The recipes' modules: one module (or folder, with its helpers beside it) per ``recipes/<name>.py``,
each with ``NAME``, its frozen ``Config``, ``load`` (the composed config to that ``Config``,
checked) and ``run``; a recipe a sweep may run also has ``SWEEP_DEFAULTS``.

- ``dqn`` (the main job), ``qlearning``, ``solve``, ``evaluate``, ``study``, ``demo``, ``sweep``;
- ``constrained/``: the most data subject to a miss target (``recipe``), its ``frontier``, and the
  trade-off ``region`` over the radar share;
- ``fleet/``: several vehicles (``recipe``) and their ``report``;
- ``shares/``: the radar share's learners, ``sac`` and ``ppo``, on their shared ``learning``.

May import: ``irdrc.core``, ``irdrc.fleet``, ``irdrc.agents``, ``irdrc.runs``, ``irdrc.sweeps``, and
of ``irdrc.online`` (the layer beside this one) its ``recipe`` alone, which ``sweep`` runs as a
method. Nothing of ``irdrc.bench`` or ``irdrc.paper``.
"""
