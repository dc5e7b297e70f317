"""Several vehicles on one stretch of road sharing one base station (MODEL.md § C).

- ``exact``: the fleet model on factored kernels built from the single-vehicle exact model, its
  centralised optimum (value iteration over the joint state and the 2^N joint actions) and exact
  metrics per vehicle and for the fleet;
- ``sim``: the fleet's batched simulator, each vehicle stepped by the single-vehicle ``Dynamics``;
- ``env``: ``FleetEnv``, the fleet as a batched TorchRL multi-agent env (group ``"agents"``);
- ``__main__``: ``python -m irdrc.fleet``, the optimum beside N copies of the single optimum.

May import: torch, tensordict, torchrl (env specs) and ``irdrc.core``. Nothing from ``irdrc.agents``, ``irdrc.experiments`` or
``irdrc.paper``; nothing of Hydra, files or Ray.
"""
