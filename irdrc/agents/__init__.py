"""Learners, one interface: ``train(scenarios, config, …) -> RunRecord`` (see ``irdrc.agents.base``).

- ``base``: the progress record, the run record and the hooks every learner shares;
- ``qlearning``: vectorised tabular Q-learning;
- ``dqn``: DQN from TorchRL parts;
- ``replay``: prioritised sampling behind TorchRL's ``Sampler`` interface.

May import: ``irdrc.core``, torch, tensordict, torchrl. Nothing from ``irdrc.experiments`` or
``irdrc.paper``; no files, Hydra or loggers (a learner reports through its hooks).
"""
