"""One vehicle on the road (MODEL.md § E): learners that learn from the vehicle's own stream, in
real time, and the exact price of their learning.

- ``ledger``: the price of learning — regret, expected and realised missed events, the floor — of
  the behaviour policy in force in each episode, on the exact model;
- ``loop``: the one loop on one ``irdrc.core.stream.VehicleStream`` (what a learner supplies:
  ``StreamLearner``), evaluations, checkpoints, resume;
- ``form``: what a structure-aware learner is told (the model's form) and what it counts;
- the learners: ``posterior`` (posterior sampling on the form, planned on the exact core between
  steps, or beside the acting: ``posterior_anytime``),
  ``dqn`` (DQN from TorchRL parts), ``qlearning`` (tabular), ``safe`` (misses kept under a target
  while it learns); ``learners`` builds one by name, ``configs`` holds their profiles, ``own``
  loads a learner of one's own (``learner=PATH.py:Class``);
- ``recipe``: ``recipes/online.py``; ``figures``: its curves against episodes (its benchmark is
  ``irdrc.bench.online``).

May import: ``irdrc.core``, ``irdrc.agents``, ``irdrc.runs`` (the run machinery). Nothing of
``irdrc.sweeps``, the other recipes, ``irdrc.bench`` or ``irdrc.paper``.
"""
