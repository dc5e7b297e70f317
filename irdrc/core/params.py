"""Model parameters (MODEL.md), validated on construction.

The one place where the model's defaults live in code. Config names are part of the user
interface: ``env.queue_capacity``, ``env.p1.speed``, ``reward.r4`` … (see ``EnvParams`` and
``RewardParams``). Every bad value raises a ``ValueError`` naming the key, the value and the
allowed range.
"""

from __future__ import annotations

import dataclasses
import difflib
import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field, fields
from typing import Any

EVENT_FACTORS = ("road", "weather", "speed", "object")
"""Factors that drive the unexpected event, in state order (r, w, v, m)."""

MARKOV_FACTORS = ("channel", *EVENT_FACTORS)
"""Factors that follow two-state Markov chains, in state order (c, r, w, v, m)."""

EVENT_MODELS = ("noisy_or", "sum")


def to_plain(node: Any) -> Any:
    """Turn an OmegaConf node (or anything mapping-like) into plain Python containers."""
    try:
        from omegaconf import DictConfig, ListConfig, OmegaConf

        if isinstance(node, DictConfig | ListConfig):
            return OmegaConf.to_container(node, resolve=True)
    except ImportError:  # pragma: no cover - omegaconf is a dependency
        pass
    if isinstance(node, Mapping):
        return {k: to_plain(v) for k, v in node.items()}
    return node


def check_number(
    key: str,
    value: Any,
    lo: float = -math.inf,
    hi: float = math.inf,
    *,
    integer: bool = False,
    open_lo: bool = False,
    open_hi: bool = False,
) -> Any:
    """``value`` as an int or float if it is a finite number within the bounds, else a ``ValueError``
    naming ``key``, the value and the allowed range (``open_lo`` / ``open_hi`` exclude a bound)."""
    kind = "an integer" if integer else "a number"
    left, right = "(" if open_lo else "[", ")" if open_hi else "]"
    if hi == math.inf:
        bounds = f"> {lo}" if open_lo else f">= {lo}"
    elif lo == -math.inf:
        bounds = f"< {hi}" if open_hi else f"<= {hi}"
    else:
        bounds = f"{left}{lo}, {hi}{right}"
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise ValueError(
            f"{key}={value!r} must be {kind} {'in ' if lo > -math.inf and hi < math.inf else ''}{bounds}"
        )
    if integer and not (
        isinstance(value, int) or (math.isfinite(value) and float(value).is_integer())
    ):
        raise ValueError(f"{key}={value!r} must be {kind} (a whole number)")
    ok = (lo < value if open_lo else lo <= value) and (value < hi if open_hi else value <= hi)
    if not math.isfinite(value) or not ok:
        raise ValueError(f"{key}={value!r} is outside the allowed range {bounds}")
    return int(value) if integer else float(value)


def check_choice(key: str, value: Any, choices: Iterable[Any]) -> Any:
    """``value`` if it is one of ``choices``, else a ``ValueError`` naming the key and the choices."""
    choices = list(choices)
    if isinstance(value, bool) and not any(isinstance(c, bool) for c in choices):
        raise ValueError(f"{key}={value!r} must be one of {', '.join(map(str, choices))}")
    if value not in choices:
        raise ValueError(f"{key}={value!r} must be one of {', '.join(map(str, choices))}")
    return value


def check_bool(key: str, value: Any) -> bool:
    """``value`` if it is true or false, else a ``ValueError`` naming the key."""
    if not isinstance(value, bool):
        raise ValueError(f"{key}={value!r} must be true or false")
    return value


def reject_unknown_keys(prefix: str, keys: Iterable[Any], allowed: Iterable[str]) -> None:
    """Raise a ``ValueError`` naming every key of ``keys`` not in ``allowed`` (with ``prefix``), the
    closest allowed key for each, and the allowed ones. The one check behind every config section."""
    allowed = sorted(allowed)
    extra = sorted(str(k) for k in set(keys) - set(allowed))
    if not extra:
        return
    hints = []
    for k in extra:
        close = difflib.get_close_matches(k, allowed, n=1, cutoff=0.6)
        hints.append(f"{prefix}{k}" + (f" (did you mean {prefix}{close[0]}?)" if close else ""))
    raise ValueError(
        f"unknown key(s) {', '.join(hints)}; allowed: {', '.join(prefix + n for n in allowed)}"
    )


def _check_keys(prefix: str, data: Mapping, cls: type, *, strict: bool) -> None:
    names = {f.name for f in fields(cls) if not f.name.startswith("_")}
    reject_unknown_keys(prefix, data, names)
    missing = sorted(names - set(data))
    if strict and missing:
        raise ValueError(f"missing key(s) {', '.join(prefix + k for k in missing)}")


def _from_mapping(cls: type, data: Any, prefix: str, *, strict: bool) -> Any:
    data = to_plain(data)
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
        return tuple(getattr(self, n) for n in EVENT_FACTORS)  # type: ignore[return-value]


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
        return tuple(getattr(self, n) for n in MARKOV_FACTORS)  # type: ignore[return-value]


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


@dataclass(frozen=True)
class EnvParams:
    """The environment of MODEL.md. Defaults are the paper scenario (``envs/paper.yaml``).

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

    def __post_init__(self) -> None:
        set_ = object.__setattr__
        set_(
            self,
            "queue_capacity",
            check_number("env.queue_capacity", self.queue_capacity, 1, 1_000_000, integer=True),
        )
        # The exact model sums arrivals up to a tail bucket; rates above 1000 packets/step are not a
        # regime this model is meant for and would make that table huge.
        set_(self, "arrival_rate", check_number("env.arrival_rate", self.arrival_rate, 0.0, 1000.0))
        set_(
            self,
            "packets_good",
            check_number("env.packets_good", self.packets_good, 0, 10_000, integer=True),
        )
        set_(
            self,
            "packets_bad",
            check_number("env.packets_bad", self.packets_bad, 0, 10_000, integer=True),
        )
        for name, cls in (
            ("p0", EventProbs),
            ("p1", EventProbs),
            ("stay_good", StayProbs),
            ("stay_bad", StayProbs),
        ):
            if not isinstance(getattr(self, name), cls):
                raise ValueError(f"env.{name} must be a mapping of {cls.__name__} values")
        for name, g, h in zip(
            MARKOV_FACTORS, self.stay_good.as_tuple(), self.stay_bad.as_tuple(), strict=True
        ):
            if g == 1.0 and h == 1.0:
                raise ValueError(
                    f"env.stay_good.{name}=1 and env.stay_bad.{name}=1: the {name} never changes, so "
                    "the long-run behaviour depends on where it starts and the exact long-run "
                    "metrics are not defined; make at least one of them < 1"
                )
        if self.event_model not in EVENT_MODELS:
            raise ValueError(
                f"env.event_model={self.event_model!r} must be one of {', '.join(EVENT_MODELS)}"
            )
        if not isinstance(self.radar_reaction, bool):
            raise ValueError(f"env.radar_reaction={self.radar_reaction!r} must be true or false")
        set_(
            self,
            "reaction_clear",
            check_number("env.reaction_clear", self.reaction_clear, 0.0, 1.0),
        )
        set_(self, "horizon", check_number("env.horizon", self.horizon, 1, 10**9, integer=True))

    @property
    def num_states(self) -> int:
        """(D + 1) · 2⁵ states."""
        return (self.queue_capacity + 1) * 32

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
    missed event (comm while an event occurs); r4: radar detects an event, times (b + 1).
    """

    r1: float = 2.0
    r2: float = 1.0
    r3: float = 50.0
    r4: float = 5.0

    def __post_init__(self) -> None:
        for name in ("r1", "r2", "r3", "r4"):
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

    @classmethod
    def from_config(cls, cfg: Any, *, strict: bool = True) -> Params:
        """Build from a config holding ``env`` and ``reward`` (other top-level keys are ignored).

        Args:
            cfg: a dict or OmegaConf node, e.g. a recipe's Hydra config.
            strict: if True both sections must be complete; if False missing keys take defaults.
        """
        cfg = to_plain(cfg)
        if not isinstance(cfg, Mapping):
            raise ValueError(f"config must be a mapping, got {cfg!r}")
        for key in ("env", "reward"):
            if strict and key not in cfg:
                raise ValueError(f"missing key(s) {key}")
        return cls(
            env=EnvParams.from_dict(cfg.get("env", {}), strict=strict),
            reward=RewardParams.from_dict(cfg.get("reward", {}), strict=strict),
        )

    @classmethod
    def from_overrides(cls, overrides: Mapping[str, Any] | None = None, **kwargs: Any) -> Params:
        """Defaults updated by overrides, nested or dotted.

        Accepts ``{"env": {"p1": {"speed": 0.5}}}``, ``{"env.p1.speed": 0.5}``, and, for brevity,
        env keys without their prefix (``{"p1": {"speed": 0.5}, "horizon": 100}``) and reward weights
        by name (``{"r4": 50}``).
        """
        merged: dict[str, Any] = {"env": {}, "reward": {}}
        _apply_overrides(merged, {**(overrides or {}), **kwargs})
        return cls.from_config(merged, strict=False)

    def with_overrides(self, overrides: Mapping[str, Any]) -> Params:
        """A copy with dotted-key overrides applied (``{"env.p1.speed": 0.5, "reward.r4": 50}``).

        Keys follow ``from_overrides`` (a bare ``r4`` or ``p1.speed`` is accepted); values are
        validated as in ``from_config``.
        """
        merged = self.to_dict()
        _apply_overrides(merged, overrides)
        return Params.from_config(merged)

    def to_dict(self) -> dict[str, Any]:
        """Plain nested dict with the config names (round-trips through ``from_config``)."""
        return {"env": as_dict(self.env), "reward": as_dict(self.reward)}


def _apply_overrides(merged: dict[str, Any], overrides: Mapping[str, Any]) -> None:
    """Set dotted or nested overrides into ``merged`` ({"env": …, "reward": …}); a key without
    its section prefix is an env key, except the reward weights r1 … r4."""
    for key, value in overrides.items():
        parts = str(key).split(".")
        if parts[0] not in ("env", "reward"):
            parts = ["reward" if parts[0] in ("r1", "r2", "r3", "r4") else "env", *parts]
        target = merged
        for p in parts[:-1]:
            target = target.setdefault(p, {})
            if not isinstance(target, dict):
                raise ValueError(f"override {key!r} conflicts with another key")
        _deep_set(target, parts[-1], to_plain(value))


def _deep_set(target: dict, key: str, value: Any) -> None:
    if isinstance(value, Mapping) and isinstance(target.get(key), dict):
        for k, v in value.items():
            _deep_set(target[key], k, v)
    else:
        target[key] = value


def as_dict(obj: Any) -> dict[str, Any]:
    """A params dataclass as a plain nested dict, without private fields."""
    out = {}
    for f in fields(obj):
        if f.name.startswith("_"):
            continue
        value = getattr(obj, f.name)
        out[f.name] = as_dict(value) if dataclasses.is_dataclass(value) else value
    return out


def _fill(defaults: Any, data: Any) -> dict[str, Any]:
    """Defaults (as a dict) updated recursively by ``data``; unknown keys are kept for the checks."""
    base = as_dict(defaults)
    data = to_plain(data)
    if not isinstance(data, Mapping):
        return data
    for k, v in data.items():
        _deep_set(base, k, v)
    return base
