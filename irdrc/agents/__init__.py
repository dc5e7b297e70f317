"""Learners, one loop: every value learner composes the parts of ``offpolicy`` and runs the loop of
``loop``, which owns evaluation, stopping and checkpoints.

- ``configs``: every learner's hyperparameters (pure Python, checked before any heavy import);
- ``base``: the hooks every learner reports through, the record it returns, checkpoints;
- ``offpolicy`` and ``loop``: the shared parts (network, ε ladder, collector, replay, target,
  optimiser) and the one loop;
- ``dqn``: the default DQN, top to bottom; ``lagrangian`` (+ ``policy_search``): the constrained
  learner; ``marl``: the fleet's learners; ``qlearning``: vectorised tabular Q-learning;
- ``replay``: prioritised sampling behind TorchRL's ``Sampler`` interface.

May import: ``irdrc.core``, ``irdrc.fleet``, torch, tensordict, torchrl. Nothing from a
layer above (``irdrc.runs`` and up); no files, Hydra or loggers (a learner reports through
its hooks).
"""
