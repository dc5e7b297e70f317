"""The fleet's learners and their hyperparameters (MODEL.md § C)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from irdrc.agents.configs.continuous import PPOConfig
from irdrc.agents.configs.value import DEFAULT_NETWORK, OffPolicyConfig
from irdrc.core.checks import INT, check_bool, check_choice, check_numbers

FLEET_LEARNERS = ("idqn", "vdn", "qmix", "joint", "mappo", "ippo")
"""The fleet's learners (``learner=…``): independent DQN with parameter sharing, value
decomposition (VDN, QMIX), DQN over the joint actions, and multi-agent PPO with a centralised
(MAPPO) or each vehicle's own (IPPO) critic."""

FLEET_OBSERVES = {
    "idqn": ("own",),
    "vdn": ("own", "full"),
    "qmix": ("own", "full"),
    "joint": ("full",),
    "mappo": ("own", "full"),
    "ippo": ("own", "full"),
}
"""What each fleet learner's vehicles may observe (``env.observe``)."""

MIXERS = ("vdn", "qmix")

POLICY_GRADIENT = ("mappo", "ippo")
"""The fleet learners whose hyperparameters are PPO's (section ``ppo``); the others' are DQN's
machinery (section ``algo``)."""


@dataclass(frozen=True)
class FleetPPOConfig(PPOConfig):
    """PPO's keys for the fleet (section ``ppo`` of ``irdrc/conf/fleet.yaml``), counted in fleets
    and fleet steps: ``num_envs`` fleets, ``frames_per_batch`` fleet steps a rollout."""

    num_envs: int = 500
    frames_per_batch: int = 16_000
    total_frames: int = 800_000
    entropy_coeff: float = 0.01
    name: str = field(default="mappo", compare=False)
    _section: str = field(default="ppo", compare=False, repr=False)


def check_fleet_learner(learner: str, model: Any, observe: str) -> None:
    """Refuse a learner the fleet (``irdrc.fleet.model.FleetModel``, or a callable that builds
    it, called only when needed) or the observation cannot serve, before any work."""
    check_choice("learner", learner, FLEET_LEARNERS)
    if observe not in FLEET_OBSERVES[learner]:
        raise ValueError(
            f"learner={learner} with env.observe={observe}: {learner} takes env.observe="
            f"{' or '.join(FLEET_OBSERVES[learner])}"
        )
    if learner == "joint" or observe == "full":  # scored and acted on joint states
        model = model() if callable(model) else model
        if not model.exact:
            model.check_exact()


def fleet_dqn() -> OffPolicyConfig:
    """The fleet's value learners' DQN profile (``FleetLearnerConfig.dqn``'s default)."""
    return OffPolicyConfig(
        # the shape the fleet's learners were measured at: 1 000 fleets, 500 000 fleet steps,
        # 1 000 updates of 1 000 transitions on the sampled team rewards, 64-64
        num_envs=1000,
        frames_per_batch=2000,
        total_frames=500_000,
        batch_size=1000,
        updates_per_batch=4,
        reward_means=False,
        network=DEFAULT_NETWORK,
        prioritized=False,
        double_dqn=False,
        center_on="rewards",
        lr=3e-3,
        name="vdn",
    )


@dataclass(frozen=True)
class FleetLearnerConfig:
    """A fleet learner's hyperparameters (``recipes/fleet.py``): the off-policy machinery's, counted
    in fleets and fleet steps (``num_envs`` fleets stepped together; ``idqn`` steps a row per
    vehicle), and the mixers' own.

    Attributes:
        learner: ``FLEET_LEARNERS``.
        dqn: the value learners' machinery (section ``algo``); ``algo.prioritized`` and
            ``algo.double_dqn`` left null take the learner's default — idqn, joint: true; vdn,
            qmix: false (TorchRL's ``QMixerLoss`` takes each vehicle's maximum under the target
            network and weighs no sample by importance).
        ppo: mappo and ippo's PPO (section ``ppo``): each rollout of ``ppo.num_envs`` fleets.
        mixing_embed_dim: QMIX's mixing width.
        agent_index: vdn, qmix: each vehicle's network input carries its one-hot index (idqn,
            mappo, ippo: always; joint: every vehicle's state is its input).
    """

    learner: str = "vdn"
    dqn: OffPolicyConfig = field(default_factory=fleet_dqn)
    ppo: FleetPPOConfig = field(default_factory=FleetPPOConfig)
    mixing_embed_dim: int = 32
    agent_index: bool = True

    @property
    def machinery(self) -> OffPolicyConfig | FleetPPOConfig:
        """The hyperparameters the learner trains with (``ppo`` or ``dqn``)."""
        return self.ppo if self.learner in POLICY_GRADIENT else self.dqn

    def __post_init__(self) -> None:
        check_choice("learner", self.learner, FLEET_LEARNERS)
        check_numbers(self, "algo.", (("mixing_embed_dim", 1, 4096, INT),))
        check_bool("algo.agent_index", self.agent_index)
        if self.dqn.center_on != "rewards":
            raise ValueError(
                f"algo.center_on={self.dqn.center_on}: the fleet's learners centre on the team "
                "rewards' average; set algo.center_on=rewards"
            )
        if self.dqn.reward_means:
            raise ValueError(
                "algo.reward_means=true: the fleet's learners read each sample's own team "
                "reward; set algo.reward_means=false"
            )
        if self.learner in MIXERS:
            for key, why in (
                ("double_dqn", "takes each vehicle's maximum under the target network"),
                ("prioritized", "weighs no sample by its importance (docs/FLEET.md)"),
            ):
                if getattr(self.dqn, key):
                    raise ValueError(
                        f"algo.{key}=true: TorchRL's QMixerLoss {why}; set algo.{key}=false"
                    )

    @classmethod
    def from_sections(
        cls, learner: str, algo: Any, network: Any = None, ppo: Any = None
    ) -> FleetLearnerConfig:
        """From ``learner``, the ``algo`` mapping (DQN's keys and the mixers'), ``network`` and the
        ``ppo`` mapping (mappo, ippo): null values take the learner's defaults (``center_on``:
        ``rewards``, the team rewards' average), and a mixer's key set for a learner that does not
        read it is refused."""
        check_choice("learner", learner, FLEET_LEARNERS)
        if learner in POLICY_GRADIENT:
            data = {**dict(ppo or {}), "name": learner}
            return cls(learner=learner, ppo=FleetPPOConfig.from_sections(data, network or {}))
        data = dict(algo)
        read_by = {"mixing_embed_dim": ("qmix",), "agent_index": ("vdn", "qmix")}
        own = {k: data.pop(k) for k in read_by if k in data}
        for key, readers in read_by.items():
            default = cls.__dataclass_fields__[key].default
            if learner not in readers and key in own and own[key] != default:
                raise ValueError(
                    f"algo.{key}={own[key]!r} is read by learner={' or '.join(readers)} only, not "
                    f"{learner}"
                )
        mixer = learner in MIXERS
        for key in ("prioritized", "double_dqn"):
            if data.get(key) is None:
                data[key] = not mixer
        data.setdefault("center_on", "rewards")  # DQN's own default follows its values
        data["name"] = learner
        own_dqn = fleet_dqn()
        dqn = OffPolicyConfig.from_sections(data, network, base=own_dqn)
        return cls(learner=learner, dqn=dqn, **own)
