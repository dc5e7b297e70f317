"""The fleet's learners by name (MODEL.md § C), one ``train`` for all of them.

- ``idqn``: independent DQN with parameter sharing (``irdrc.agents.fleet_dqn``): a row per vehicle,
  the team reward, each vehicle's index in its observation;
- ``vdn`` / ``qmix``: value decomposition with TorchRL's ``QMixerLoss`` (``irdrc.agents.fleet_mix``);
- ``joint``: DQN over the 2^N joint actions on every vehicle's state (``FleetJointEnv``): one
  network every vehicle executes alike on the shared states, taking its own bit.

Every learner's env steps are fleet steps (one step of every vehicle of a fleet), whatever its rows.
"""

from __future__ import annotations

from dataclasses import replace
from typing import Any

from irdrc.agents import dqn, fleet_dqn, fleet_mix
from irdrc.agents.base import Hooks, RunRecord
from irdrc.agents.offpolicy import NetworkConfig
from irdrc.core.params import to_plain
from irdrc.fleet.env import FleetJointEnv
from irdrc.fleet.exact import FleetModel

LEARNERS = ("idqn", "vdn", "qmix", "joint")
"""The fleet's learners (``learner=…``)."""

OBSERVES = {
    "idqn": ("own",),
    "vdn": ("own", "full"),
    "qmix": ("own", "full"),
    "joint": ("full",),
}
"""What each learner's vehicles may observe (``env.observe``)."""


READ_BY = {"mixing_embed_dim": ("qmix",), "agent_index": ("vdn", "qmix")}
"""Keys of the fleet recipe's ``algo`` that only some learners read (set for another: refused)."""


def config(learner: str, algo: Any, network: Any) -> dqn.DQNConfig | fleet_mix.MixConfig:
    """The learner's config from the fleet recipe's ``algo`` node (``num_envs`` fleets,
    ``frames_per_batch`` and ``total_frames`` in fleet steps); null values take the learner's
    defaults (``prioritized``, ``double_dqn``), keys the learner does not read are left out."""
    if learner not in LEARNERS:
        raise ValueError(f"learner={learner!r} must be one of {', '.join(LEARNERS)}")
    cls = fleet_mix.MixConfig if learner in ("vdn", "qmix") else dqn.DQNConfig
    known = cls.keys()
    given = dict(to_plain(algo))
    defaults = fleet_mix.MixConfig()
    for key, readers in READ_BY.items():
        if learner not in readers and key in given and given[key] != getattr(defaults, key):
            raise ValueError(
                f"algo.{key}={given[key]!r} is read by learner={' or '.join(readers)} only, not "
                f"{learner}"
            )
    data = {k: v for k, v in given.items() if v is not None and k in known}
    data["name"] = learner
    if cls is fleet_mix.MixConfig:
        data["mixer"] = learner
    return cls(**data, network=NetworkConfig.from_dict(network))


def check(learner: str, model: FleetModel, observe: str) -> None:
    """Refuse a learner the fleet or the observation cannot serve, before any work."""
    if observe not in OBSERVES[learner]:
        raise ValueError(
            f"learner={learner} with env.observe={observe}: {learner} takes env.observe="
            f"{' or '.join(OBSERVES[learner])}"
        )
    if not model.exact and (learner == "joint" or observe == "full"):
        model.check_exact()  # joint actions and fleet observations are scored on joint states


def train(
    learner: str,
    model: FleetModel,
    cfg: dqn.DQNConfig | fleet_mix.MixConfig,
    *,
    observe: str = "own",
    seed: int = 0,
    scorer: Any = None,
    eval_every_frames: int = 50_000,
    hooks: Hooks | None = None,
) -> RunRecord:
    """Train ``learner`` on the fleet ``model``; its history and env steps count fleet steps.
    ``scorer``: ``FleetScorer`` (exact, against the centralised optimum) or ``FleetMCScorer``."""
    check(learner, model, observe)
    N = model.N
    if learner in ("vdn", "qmix"):
        return fleet_mix.train(
            model,
            cfg,
            seed=seed,
            scorer=scorer,
            eval_every_frames=eval_every_frames,
            hooks=hooks,
            observe=observe,
        )
    if learner == "joint":
        env = FleetJointEnv(model, fleets=cfg.num_envs, seed=seed)
        return dqn.train_on(
            env,
            model.spec.vehicle,
            cfg,
            seed=seed,
            scorers=[scorer],
            eval_every_frames=eval_every_frames,
            hooks=hooks,
        )
    # idqn: a row per vehicle, so N vehicle steps per fleet step
    rows = replace(
        cfg,
        num_envs=cfg.num_envs * N,
        frames_per_batch=cfg.frames_per_batch * N,
        total_frames=cfg.total_frames * N,
    )
    hooks = hooks or Hooks()

    def on_eval(records: list[dict[str, Any]]) -> None:
        hooks.eval([_per_fleet(r, N) for r in records])

    def on_batch(info: dict[str, Any]) -> None:
        hooks.batch(_per_fleet(info, N))

    per_fleet = replace(hooks, on_eval=on_eval, on_batch=on_batch)
    record = fleet_dqn.train(
        model.spec,
        rows,
        seed=seed,
        scorer=scorer,
        eval_every_frames=eval_every_frames * N,
        hooks=per_fleet,
        agent_index=True,
        model=model,
    )
    record.history = [_per_fleet(r, N) for r in record.history]
    record.env_steps //= N
    return record


def _per_fleet(record: dict[str, Any], n: int) -> dict[str, Any]:
    return {**record, "env_steps": record["env_steps"] // n}
