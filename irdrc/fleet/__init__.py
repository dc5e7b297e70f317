"""Several vehicles on one stretch of road sharing one base station (MODEL.md § C).

- ``spec``: the fleet's parameters and the uplink's access rule (pure Python);
- ``config``: a fleet scenario (``env=fleet``) from a config mapping, per-vehicle lists included;
- ``model``: the exact fleet model on factored kernels built from the single-vehicle exact model —
  an ``irdrc.core.exact.ExactMDP`` with 2^N joint actions, so its centralised optimum and exact
  metrics come from the exact core;
- ``policies``: decentralised tables as joint policies, each vehicle's single optimum, the baselines;
- ``scorer``: exact metrics per vehicle and for the fleet, and ``FleetScorer`` (decentralised
  policies against the centralised optimum);
- ``sim``: the fleet's batched simulator, each vehicle stepped by the single-vehicle ``Dynamics``;
- ``env``: ``FleetEnv``, the fleet as a batched TorchRL multi-agent env (group ``"agents"``);
- ``views``: its single-agent views (a row per vehicle; a row per fleet over the joint actions);
- ``evaluate``: Monte-Carlo metrics and baselines at any N;
- ``search``: local search for the best decentralised policy;
- ``parallel``: the fleet as a PettingZoo ``ParallelEnv`` (``irdrc.fleet.parallel_env``).

May import: torch, tensordict, torchrl (env specs), gymnasium and pettingzoo (spaces, ``parallel``)
and ``irdrc.core``. Nothing from
``irdrc.agents`` or any layer above it; nothing of Hydra, files or Ray.
"""

from __future__ import annotations

from typing import Any


def parallel_env(*args: Any, **kwargs: Any) -> Any:
    """The fleet as a PettingZoo ``ParallelEnv`` (``irdrc.fleet.parallel.parallel_env``; imports
    PettingZoo only when called).

    Raises:
        ModuleNotFoundError: PettingZoo is not installed (saying how to install it).
    """
    try:
        from irdrc.fleet.parallel import parallel_env as make
    except ModuleNotFoundError as err:
        if err.name != "pettingzoo":
            raise
        raise ModuleNotFoundError(
            "irdrc.fleet.parallel_env needs PettingZoo: pip install 'irdrc[pettingzoo]' "
            "(pettingzoo==1.24.3)",
            name="pettingzoo",
        ) from err
    return make(*args, **kwargs)
