"""The model and everything exact: parameters, the simulator, the exact MDP and its solutions.

- ``params``: validated model parameters (frozen dataclasses, config names as in MODEL.md);
- ``env``: ``Dynamics`` (the step on integer state tensors) and ``DFRCEnv`` (the batched TorchRL env);
- ``gym``: the gymnasium wrapper (``irdrc/DFRC-v0``);
- ``model``: the exact transition and expectation tensors;
- ``solve``: value iteration, policy evaluation, stationary and episodic exact metrics;
- ``metrics``: the ``Metrics`` record and its names;
- ``policies``: baseline and table policies as TensorDictModules;
- ``evaluate``: Monte-Carlo evaluation with confidence intervals.

May import: torch, tensordict, torchrl (env specs), gymnasium, numpy. Nothing from ``irdrc.agents``,
``irdrc.experiments`` or ``irdrc.paper``; nothing of Hydra, files or Ray.
"""
