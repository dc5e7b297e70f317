"""The model and everything exact: parameters, the simulator, the exact MDP and its solutions.

- ``checks``: the one validation toolkit every layer's configs use (numbers, choices, lists, keys);
- ``params``: validated model parameters (frozen dataclasses, config names as in MODEL.md), with
  ``factors`` (the Markov factors) and ``overrides`` (dotted keys onto nested mappings);
- ``tables``: the per-(action, factors) tables the simulator and the exact models share;
- ``states``: the state index (``state_index``, ``decode_state``);
- ``dynamics``: ``Dynamics``, the step on integer state tensors;
- ``env``: ``DFRCEnv``, the batched TorchRL env; ``gym``: the gymnasium wrapper (``irdrc/DFRC-v0``);
- ``exact``: everything exact on one interface generic over the number of actions (dense and
  factored models, one value iteration, stationary and episodic metrics, scorers);
- ``sizes``: how large a model the dense exact side takes (pure Python, read by the config checks);
- ``cmdp``: the constrained optimum, a linear program on any exact model;
- ``metrics``: the ``Metrics`` record, its names and the one definition of every rate;
- ``policies``: baseline and table policies as TensorDictModules;
- ``evaluate``: Monte-Carlo evaluation with confidence intervals.

May import: torch, tensordict, torchrl (env specs), gymnasium, numpy. Nothing from any layer
above it (``irdrc.fleet``, ``irdrc.agents`` … ``irdrc.paper``); nothing of Hydra, files or Ray.
"""
