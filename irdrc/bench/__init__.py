"""Benchmarks: one module per ``recipes/bench_<name>.py`` (``constrained``, ``dqn``, ``env``,
``fleet``, ``online``, ``robust``, ``scale``, ``timeshare``), each writing a generated table, and
what they draw from: ``random_scenarios`` (contested scenarios of every model key) and
``fleet_best`` (the best decentralised policy of a fleet's cell).

May import every layer below it: ``irdrc.core``, ``irdrc.fleet``, ``irdrc.agents``, ``irdrc.runs``,
``irdrc.sweeps``, ``irdrc.recipes``, ``irdrc.online``. Nothing of ``irdrc.paper``.
"""
