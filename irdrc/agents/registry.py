"""Every learner by name, each a module with ``NAME``, ``Config`` (``from_node(cfg)``) and
``train(scenarios, config, *, num_learners, seed, device, scorers, eval_every_frames, hooks,
resume) -> RunRecord`` (``irdrc.agents.base``)."""

from __future__ import annotations

from types import ModuleType

from irdrc.agents import dqn, lagrangian, qlearning

LEARNERS: dict[str, ModuleType] = {m.NAME: m for m in (dqn, qlearning, lagrangian)}
"""Learner modules by name: ``dqn``, ``qlearning``, ``dqn_lagrangian``."""
