"""Model parameters (MODEL.md), validated on construction.

The one place where the model's defaults live in code. Config names are part of the user
interface: ``env.queue_capacity``, ``env.p1.speed``, ``reward.r4`` … (see ``EnvParams`` and
``RewardParams``). Every bad value raises a ``ValueError`` naming the key, the value and the
allowed range.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from dataclasses import dataclass, field, fields
from typing import Any

from irdrc.core.checks import check_bool, check_choice, check_number, reject_unknown_keys
from irdrc.core.factors import MARKOV_FACTORS, BurstySpec, FactorSpec, _factor_specs, check_general
from irdrc.core.overrides import apply_overrides, deep_set

EVENT_FACTORS = ("road", "weather", "speed", "object")
"""Factors that drive the unexpected event, in state order (r, w, v, m)."""

EVENT_MODELS = ("noisy_or", "sum")


def _check_keys(prefix: str, data: Mapping[str, Any], cls: type, *, strict: bool) -> None:
    names = {f.name for f in fields(cls) if not f.name.startswith("_")}
    reject_unknown_keys(prefix, data, names)
    optional = {f.name for f in fields(cls) if f.metadata.get("optional")}
    missing = sorted(names - set(data) - optional)
    if strict and missing:
        raise ValueError(f"missing key(s) {', '.join(prefix + k for k in missing)}")


def _from_mapping(cls: type, data: Any, prefix: str, *, strict: bool) -> Any:
    if not isinstance(data, Mapping):
        raise ValueError(f"{prefix.rstrip('.')} must be a mapping, got {data!r}")
    _check_keys(prefix, data, cls, strict=strict)
    kwargs = {}
    for f in fields(cls):
        if f.name not in data:
            continue
        value = data[f.name]
        sub = f.metadata.get("nested")
        if sub is not None:
            value = _from_mapping(sub, value, f"{prefix}{f.name}.", strict=strict)
        kwargs[f.name] = value
    if any(f.name == "_prefix" for f in fields(cls)):
        kwargs["_prefix"] = prefix
    return cls(**kwargs)


@dataclass(frozen=True)
class EventProbs:
    """Event probability p^i_j of each factor i in condition j (one instance per j)."""

    road: float
    weather: float
    speed: float
    object: float
    _prefix: str = field(default="", repr=False, compare=False)

    def __post_init__(self) -> None:
        for name in EVENT_FACTORS:
            object.__setattr__(
                self, name, check_number(self._prefix + name, getattr(self, name), 0.0, 1.0)
            )

    def as_tuple(self) -> tuple[float, float, float, float]:
        """Values in state order (road, weather, speed, object)."""
        return tuple(getattr(self, n) for n in EVENT_FACTORS)


@dataclass(frozen=True)
class StayProbs:
    """Probability that each Markov factor stays in its current condition (one instance per condition)."""

    channel: float = 0.9
    road: float = 0.9
    weather: float = 0.9
    speed: float = 0.9
    object: float = 0.9
    _prefix: str = field(default="", repr=False, compare=False)

    def __post_init__(self) -> None:
        for name in MARKOV_FACTORS:
            object.__setattr__(
                self, name, check_number(self._prefix + name, getattr(self, name), 0.0, 1.0)
            )

    def as_tuple(self) -> tuple[float, float, float, float, float]:
        """Values in state order (channel, road, weather, speed, object)."""
        return tuple(getattr(self, n) for n in MARKOV_FACTORS)


def _p0() -> EventProbs:
    # MODEL.md: p^i_0 = 0.005 for every factor (paper for weather and speed, ref impl otherwise).
    return EventProbs(road=0.005, weather=0.005, speed=0.005, object=0.005, _prefix="env.p0.")


def _p1() -> EventProbs:
    # MODEL.md: road 0.05 (ref impl), weather 0.046 (paper, rain), speed 0.1 (paper, Fig. 2(a)),
    # object 0.05 (ref impl).
    return EventProbs(road=0.05, weather=0.046, speed=0.1, object=0.05, _prefix="env.p1.")


def _stay_good() -> StayProbs:
    return StayProbs(*(0.9,) * 5, _prefix="env.stay_good.")  # ref impl: P(0→0) = 0.9


def _stay_bad() -> StayProbs:
    return StayProbs(*(0.1,) * 5, _prefix="env.stay_bad.")  # ref impl: P(1→1) = 0.1


ACTION_SPACES = ("binary", "levels", "continuous")
"""``env.actions`` (MODEL.md § D): comm or radar each step (v1); G radar shares; any share."""

SENSING_CURVES = ("dwell", "linear")
"""``env.sensing``: the detection probability q(ρ) of a radar share ρ (MODEL.md § D)."""

_ENV_NUMBERS = (
    ("queue_capacity", 1, 1_000_000, True),
    ("packets_good", 0, 10_000, True),
    ("packets_bad", 0, 10_000, True),
    ("reaction_clear", 0.0, 1.0, False),
    ("horizon", 1, 10**9, True),
    ("detection_prob", 0.0, 1.0, False),
    ("false_alarm_prob", 0.0, 1.0, False),
)
"""The environment's numeric keys: (key, low, high, integer)."""


@dataclass(frozen=True)
class EnvParams:
    """The environment of MODEL.md. Defaults are the paper scenario
    (``irdrc/scenarios/paper.yaml``).

    Attributes:
        queue_capacity: D, packets the data queue holds (paper: 10).
        arrival_rate: λ, mean Poisson packet arrivals per step (paper: 1.0).
        packets_good: ν1, packets the link carries per comm step on a good channel (paper: 4).
        packets_bad: ν2, packets per comm step on a bad channel (paper: 2).
        p0: p^i_0, event probability of each factor in its favourable condition.
        p1: p^i_1, event probability of each factor in its unfavourable condition.
        stay_good: g, P(0→0) of each factor's Markov chain (ref impl: 0.9).
        stay_bad: h, P(1→1) of each factor's Markov chain (ref impl: 0.1).
        event_model: ``noisy_or`` (ref impl, default) or ``sum`` (paper eq. (1) as a conditional).
        radar_reaction: whether radar with an object nearby slows the AV (v′ = 0) and clears the
            object with probability ``reaction_clear`` (ref impl: on).
        reaction_clear: P(m′ = 0) after a radar reaction (ref impl: 0.9).
        horizon: T, steps per episode; episodes end by truncation (ref impl: 400).
        actions: ``binary`` (v1), ``levels`` or ``continuous``: the radar share ρ of each step
            (MODEL.md § D).
        levels: G, the radar shares of ``levels`` (0, 1/(G − 1), …, 1).
        sensing: ``dwell`` (q(ρ) = P_d (1 − e^{−κρ}) / (1 − e^{−κ})) or ``linear`` (P_d ρ).
        dwell_gain: κ of ``dwell`` sensing.
    """

    queue_capacity: int = 10
    arrival_rate: float = 1.0
    packets_good: int = 4
    packets_bad: int = 2
    p0: EventProbs = field(default_factory=_p0, metadata={"nested": EventProbs})
    p1: EventProbs = field(default_factory=_p1, metadata={"nested": EventProbs})
    stay_good: StayProbs = field(default_factory=_stay_good, metadata={"nested": StayProbs})
    stay_bad: StayProbs = field(default_factory=_stay_bad, metadata={"nested": StayProbs})
    event_model: str = "noisy_or"
    radar_reaction: bool = True
    reaction_clear: float = 0.9
    horizon: int = 400
    factors: Any = field(default=(), metadata={"optional": True})
    bursty: Any = field(default=None, metadata={"optional": True})
    detection_prob: float = field(default=1.0, metadata={"optional": True})
    false_alarm_prob: float = field(default=0.0, metadata={"optional": True})
    actions: str = field(default="binary", metadata={"optional": True})
    levels: int = field(default=5, metadata={"optional": True})
    sensing: str = field(default="dwell", metadata={"optional": True})
    dwell_gain: float = field(default=3.0, metadata={"optional": True})

    def __post_init__(self) -> None:
        for key, lo, hi, integer in _ENV_NUMBERS:
            value = check_number(f"env.{key}", getattr(self, key), lo, hi, integer=integer)
            object.__setattr__(self, key, value)
        if self.arrival_rate is not None:  # None: bursty arrivals (checked in check_general)
            # The exact model sums arrivals up to a tail bucket; rates above 1000 packets/step are
            # not a regime this model is meant for and would make that table huge.
            rate = check_number("env.arrival_rate", self.arrival_rate, 0.0, 1000.0)
            object.__setattr__(self, "arrival_rate", rate)
        for name, cls in (("p0", EventProbs), ("p1", EventProbs)):
            if not isinstance(getattr(self, name), cls):
                raise ValueError(f"env.{name} must be a mapping of {cls.__name__} values")
        for name in ("stay_good", "stay_bad"):
            if not isinstance(getattr(self, name), StayProbs):
                raise ValueError(f"env.{name} must be a mapping of StayProbs values")
        for name, g, h in zip(
            MARKOV_FACTORS, self.stay_good.as_tuple(), self.stay_bad.as_tuple(), strict=True
        ):
            if g == 1.0 and h == 1.0:
                raise ValueError(
                    f"env.stay_good.{name}=1 and env.stay_bad.{name}=1: the {name} never changes, so "
                    "the long-run behaviour depends on where it starts and the exact long-run "
                    "metrics are not defined; make at least one of them < 1"
                )
        check_choice("env.event_model", self.event_model, EVENT_MODELS)
        check_choice("env.actions", self.actions, ACTION_SPACES)
        check_choice("env.sensing", self.sensing, SENSING_CURVES)
        object.__setattr__(
            self, "levels", check_number("env.levels", self.levels, 2, 1001, integer=True)
        )
        gain = check_number("env.dwell_gain", self.dwell_gain, 0.0, 100.0, open_lo=True)
        object.__setattr__(self, "dwell_gain", gain)
        check_bool("env.radar_reaction", self.radar_reaction)
        object.__setattr__(self, "factors", _factor_specs(self.factors))
        check_general(self)

    @property
    def factor_levels(self) -> tuple[int, ...]:
        """Levels L_i of the Markov factors (c, r, w, v, m) and, last, the traffic phases (1 for
        Poisson arrivals)."""
        by_name = {f.name: f.num_levels for f in self.factors}
        phases = len(self.bursty.rates) if self.bursty is not None else 1
        return (*(by_name.get(n, 2) for n in MARKOV_FACTORS), phases)

    @property
    def shares(self) -> tuple[float, ...] | None:
        """The radar shares ρ of the discrete actions (MODEL.md § D): ``binary`` (0, 1) — action
        0 is communication, 1 radar —, ``levels`` G equally spaced values; None for
        ``continuous`` (any ρ in [0, 1])."""
        if self.actions == "binary":
            return (0.0, 1.0)
        if self.actions == "levels":
            return tuple(g / (self.levels - 1) for g in range(self.levels))
        return None

    @property
    def is_v1(self) -> bool:
        """True when the model is MODEL.md's v1: two levels per factor, Poisson arrivals, perfect
        radar (the general keys at their defaults)."""
        return (
            not self.factors
            and self.bursty is None
            and self.detection_prob == 1.0
            and self.false_alarm_prob == 0.0
            and self.actions == "binary"
        )

    def factor(self, name: str, comm_reward: tuple[float, float] = (2.0, 1.0)) -> FactorSpec:
        """The factor ``name`` as a ``FactorSpec``: from ``factors`` if given there, else from the
        v1 keys (two levels, T = [[g, 1 − g], [1 − h, h]]; the channel's comm rewards are then
        ``comm_reward``, i.e. (r1, r2): use ``Params.factor`` to get them from the reward weights)."""
        for spec in self.factors:
            if spec.name == name:
                return spec
        i = MARKOV_FACTORS.index(name)
        g, h = self.stay_good.as_tuple()[i], self.stay_bad.as_tuple()[i]
        T = ((g, 1.0 - g), (1.0 - h, h))
        if name == "channel":
            return FactorSpec(
                name,
                T,
                ("good", "bad"),
                packets=(self.packets_good, self.packets_bad),
                comm_reward=comm_reward,
            )
        j = EVENT_FACTORS.index(name)
        return FactorSpec(
            name,
            T,
            ("favourable", "unfavourable"),
            event=(self.p0.as_tuple()[j], self.p1.as_tuple()[j]),
        )

    @property
    def num_states(self) -> int:
        """(D + 1) · Π L_i states (v1: (D + 1) · 2⁵)."""
        return (self.queue_capacity + 1) * math.prod(self.factor_levels)

    @classmethod
    def from_dict(cls, data: Any, *, strict: bool = True) -> EnvParams:
        """Build from a plain dict or an OmegaConf node holding the ``env`` keys.

        Args:
            data: the mapping (without the ``env.`` prefix).
            strict: if True every key must be present; if False missing keys take the defaults.
        """
        return _from_mapping(cls, _fill(cls(), data) if not strict else data, "env.", strict=True)


@dataclass(frozen=True)
class RewardParams:
    """Reward weights of paper eq. (3): (r1, r2, r3, r4) = (2, 1, 50, 5) (paper).

    r1: comm on a good channel, no event; r2: comm on a bad channel, no event; r3: penalty for a
    missed event (comm while an event occurs, or radar misses it); r4: radar detects an event,
    times (b + 1); r5: a radar false alarm (MODEL.md § B.3; default 0, as in v1).
    """

    r1: float = 2.0
    r2: float = 1.0
    r3: float = 50.0
    r4: float = 5.0
    r5: float = field(default=0.0, metadata={"optional": True})

    def __post_init__(self) -> None:
        for name in ("r1", "r2", "r3", "r4", "r5"):
            # Weights are magnitudes: the signs live in eq. (3) (r3 is subtracted).
            value = check_number(f"reward.{name}", getattr(self, name), 0.0, 1e9)
            object.__setattr__(self, name, value)

    @classmethod
    def from_dict(cls, data: Any, *, strict: bool = True) -> RewardParams:
        """Build from a plain dict or an OmegaConf node holding the ``reward`` keys."""
        return _from_mapping(
            cls, _fill(cls(), data) if not strict else data, "reward.", strict=True
        )


@dataclass(frozen=True)
class Params:
    """The whole model: environment and reward weights."""

    env: EnvParams = field(default_factory=EnvParams)
    reward: RewardParams = field(default_factory=RewardParams)

    def __post_init__(self) -> None:
        if any(f.name == "channel" for f in self.env.factors):
            for name, default in (("r1", 2.0), ("r2", 1.0)):
                if getattr(self.reward, name) != default:
                    raise ValueError(
                        f"reward.{name}={getattr(self.reward, name)} is not used: "
                        "env.factors.channel.comm_reward gives the comm reward per channel level; "
                        f"set it there or leave reward.{name} at its default {default}"
                    )

    def factor(self, name: str) -> FactorSpec:
        """The Markov factor ``name`` as a ``FactorSpec`` (levels, transition, event probabilities;
        the channel's packets and comm rewards, v1's (ν1, ν2) and (r1, r2))."""
        return self.env.factor(name, (self.reward.r1, self.reward.r2))

    @classmethod
    def from_config(cls, cfg: Any, *, strict: bool = True) -> Params:
        """Build from a config holding ``env`` and ``reward`` (other top-level keys are ignored).

        Args:
            cfg: a dict or OmegaConf node, e.g. a recipe's Hydra config.
            strict: if True both sections must be complete; if False missing keys take defaults.
        """
        if not isinstance(cfg, Mapping):
            raise ValueError(f"config must be a mapping, got {cfg!r}")
        for key in ("env", "reward"):
            if strict and key not in cfg:
                raise ValueError(f"missing key(s) {key}")
        env = cfg.get("env", {})
        if isinstance(env, Mapping) and "vehicles" in env:
            raise ValueError(
                "env.vehicles is a fleet's key: Params is one vehicle (a fleet is "
                "irdrc.fleet.spec.FleetSpec)"
            )
        return cls(
            env=EnvParams.from_dict(cfg.get("env", {}), strict=strict),
            reward=RewardParams.from_dict(cfg.get("reward", {}), strict=strict),
        )

    @classmethod
    def from_overrides(cls, overrides: Mapping[str, Any] | None = None) -> Params:
        """Defaults updated by overrides named as on the command line: each key starts with its
        section, dotted (``{"env.p1.speed": 0.5, "reward.r4": 50}``) or nested (``{"env": {"p1":
        {"speed": 0.5}}, "reward": {"r4": 50}}``).

        Raises:
            ValueError: a key without its section (``"r4"``, ``"horizon"``), naming the full key.
        """
        merged: dict[str, Any] = {"env": {}, "reward": {}}
        apply_overrides(merged, overrides or {})
        return cls.from_config(merged, strict=False)

    def with_overrides(self, overrides: Mapping[str, Any]) -> Params:
        """A copy with dotted-key overrides applied (``{"env.p1.speed": 0.5, "reward.r4": 50}``).

        Keys follow ``from_overrides`` (a bare ``r4`` or ``p1.speed`` is accepted); values are
        validated as in ``from_config``.
        """
        merged = self.to_dict()
        apply_overrides(merged, overrides)
        return Params.from_config(merged)

    def to_dict(self) -> dict[str, Any]:
        """Plain nested dict with the config names (round-trips through ``from_config``)."""
        return {"env": as_dict(self.env), "reward": as_dict(self.reward)}


def as_dict(obj: Any) -> dict[str, Any]:
    """A params dataclass as a plain nested dict, without private fields."""
    out = {}
    for f in fields(obj):
        if f.name.startswith("_"):
            continue
        value = getattr(obj, f.name)
        if f.metadata.get("optional") and value == f.default:
            continue  # the general model's keys at their v1 defaults: v1 configs stay as they were
        if isinstance(value, BurstySpec):
            value = value.as_config()
        elif f.name == "factors":
            value = {spec.name: spec.as_config() for spec in value}
        elif dataclasses.is_dataclass(value):
            value = as_dict(value)
        out[f.name] = value
    return out


def _fill(defaults: Any, data: Any) -> dict[str, Any]:
    """Defaults (as a dict) updated recursively by ``data``; unknown keys are kept for the checks."""
    base = as_dict(defaults)
    if not isinstance(data, Mapping):
        return data
    for k, v in data.items():
        deep_set(base, k, v)
    return base
