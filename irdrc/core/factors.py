"""The general model's factors (MODEL.md § B.1, § B.2): a Markov factor with L ≥ 2 levels, its
transition matrix and what each level does, and Markov-modulated (bursty) arrivals."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import MISSING, dataclass
from typing import Any

from irdrc.core.checks import check_choice, check_number, reject_unknown_keys

MARKOV_FACTORS = ("channel", "road", "weather", "speed", "object")
"""Factors that follow Markov chains, in state order (c, r, w, v, m)."""


def _plain(value: Any) -> Any:
    """Tuples as lists (a config read back from a dataclass), anything else as it is."""
    return list(value) if isinstance(value, tuple) else value


def _factor_specs(value: Any) -> tuple[FactorSpec, ...]:
    """``env.factors`` (a mapping factor name → its levels, transition, …) as FactorSpecs in state
    order; an empty mapping (v1) gives ()."""
    value = _plain(value)
    if value is None or (isinstance(value, tuple | list) and not value):
        return ()
    if isinstance(value, list) and all(isinstance(v, FactorSpec) for v in value):
        return tuple(value)  # already built (``dataclasses.replace`` of an EnvParams)
    if not isinstance(value, Mapping):
        raise ValueError(
            f"env.factors={value!r} must be a mapping: factor name → levels, transition, …"
        )
    reject_unknown_keys("env.factors.", value, MARKOV_FACTORS)
    specs = []
    for name in MARKOV_FACTORS:
        if name not in value:
            continue
        spec = _plain(value[name])
        if not isinstance(spec, Mapping):
            raise ValueError(f"env.factors.{name}={spec!r} must be a mapping")
        reject_unknown_keys(f"env.factors.{name}.", spec, FACTOR_SPEC_KEYS)
        if "transition" not in spec:
            raise ValueError(f"env.factors.{name} needs a transition matrix")
        specs.append(FactorSpec(name=name, **spec))
    return tuple(specs)


def _matrix(key: str, value: Any, n: int | None = None) -> tuple[tuple[float, ...], ...]:
    """A row-stochastic square matrix (n × n when ``n`` is given) as a tuple of tuples, else a
    ``ValueError`` naming ``key``."""
    value = _plain(value)
    if not isinstance(value, list | tuple) or not all(isinstance(r, list | tuple) for r in value):
        raise ValueError(f"{key}={value!r} must be a square matrix (a list of rows)")
    size = len(value)
    if size < 2 or any(len(r) != size for r in value) or (n is not None and size != n):
        want = f"{n} × {n}" if n is not None else "square, at least 2 × 2"
        raise ValueError(f"{key} must be {want}; got rows of lengths {[len(r) for r in value]}")
    rows = tuple(
        tuple(check_number(f"{key}[{i}][{j}]", x, 0.0, 1.0) for j, x in enumerate(r))
        for i, r in enumerate(value)
    )
    for i, r in enumerate(rows):
        if abs(sum(r) - 1.0) > 1e-9:
            raise ValueError(f"{key}[{i}]={list(r)} must sum to 1 (it sums to {sum(r):.12g})")
    return rows


def _vector(
    key: str, value: Any, n: int, lo: float, hi: float, *, integer: bool = False
) -> tuple[Any, ...]:
    """A list of ``n`` numbers in [lo, hi] as a tuple, else a ``ValueError`` naming ``key``."""
    value = _plain(value)
    if not isinstance(value, list | tuple) or len(value) != n:
        raise ValueError(f"{key}={value!r} must be a list of {n} values (one per level)")
    return tuple(
        check_number(f"{key}[{i}]", x, lo, hi, integer=integer) for i, x in enumerate(value)
    )


FACTOR_SPEC_KEYS = ("levels", "transition", "event", "packets", "comm_reward")


@dataclass(frozen=True)
class FactorSpec:
    """One Markov factor with L ≥ 2 ordered levels, 0 the most favourable (MODEL.md § B.1), in one
    place: its level names, its L × L transition matrix, and what each level does.

    Attributes:
        name: the factor (``channel``, ``road``, ``weather``, ``speed`` or ``object``).
        transition: T[ℓ][ℓ′] = P(next level ℓ′ | level ℓ); rows sum to 1.
        levels: a name per level (default ``0`` … ``L − 1``).
        event: p^i[ℓ], the event probability per level (road, weather, speed, object: required).
        packets: ν[ℓ], packets per comm step per level (channel: required).
        comm_reward: r_comm[ℓ], reward of a comm step without an event per level (channel:
            required; v1's r1, r2).
    """

    name: str
    transition: tuple[tuple[float, ...], ...]
    levels: tuple[str, ...] = ()
    event: tuple[float, ...] = ()
    packets: tuple[int, ...] = ()
    comm_reward: tuple[float, ...] = ()

    def __post_init__(self) -> None:
        set_ = object.__setattr__
        key = f"env.factors.{self.name}"
        check_choice("env.factors", self.name, MARKOV_FACTORS)
        set_(self, "transition", _matrix(f"{key}.transition", self.transition))
        n = len(self.transition)
        levels = _plain(self.levels) or [str(i) for i in range(n)]
        if not isinstance(levels, list | tuple) or len(levels) != n:
            raise ValueError(
                f"{key}.levels={levels!r} must name the {n} levels of {key}.transition"
            )
        set_(self, "levels", tuple(str(x) for x in levels))
        if self.name == "channel":
            for extra in ("event",):
                if _plain(getattr(self, extra)):
                    raise ValueError(f"{key}.{extra} is not used: the channel drives no event")
            set_(
                self, "packets", _vector(f"{key}.packets", self.packets, n, 0, 10_000, integer=True)
            )
            set_(self, "comm_reward", _vector(f"{key}.comm_reward", self.comm_reward, n, 0.0, 1e9))
        else:
            for extra in ("packets", "comm_reward"):
                if _plain(getattr(self, extra)):
                    raise ValueError(f"{key}.{extra} is not used: only the channel has it")
            set_(self, "event", _vector(f"{key}.event", self.event, n, 0.0, 1.0))

    @property
    def num_levels(self) -> int:
        """L."""
        return len(self.transition)

    def as_config(self) -> dict[str, Any]:
        """The config mapping (without ``name``), as written in an ``irdrc/scenarios/`` file."""
        out: dict[str, Any] = {
            "levels": list(self.levels),
            "transition": [list(r) for r in self.transition],
        }
        if self.name == "channel":
            out["packets"] = list(self.packets)
            out["comm_reward"] = list(self.comm_reward)
        else:
            out["event"] = list(self.event)
        return out


@dataclass(frozen=True)
class BurstySpec:
    """Markov-modulated Poisson arrivals (MODEL.md § B.2): a traffic phase with its own chain,
    Poisson(rates[phase]) packets per step. The phase is one more state factor (after m)."""

    rates: tuple[float, ...]
    transition: tuple[tuple[float, ...], ...]

    def __post_init__(self) -> None:
        rates = _plain(self.rates)
        if not isinstance(rates, list | tuple) or len(rates) < 2:
            raise ValueError(
                f"env.bursty.rates={rates!r} must list a Poisson rate per traffic phase (>= 2)"
            )
        object.__setattr__(
            self,
            "rates",
            tuple(
                check_number(f"env.bursty.rates[{i}]", r, 0.0, 1000.0) for i, r in enumerate(rates)
            ),
        )
        object.__setattr__(
            self, "transition", _matrix("env.bursty.transition", self.transition, len(rates))
        )

    def as_config(self) -> dict[str, Any]:
        """The config mapping."""
        return {"rates": list(self.rates), "transition": [list(r) for r in self.transition]}


def check_general(env: Any) -> None:
    """The general model's keys of ``env`` (an ``irdrc.core.params.EnvParams``, MODEL.md § B):
    bursty arrivals, and that no v1 key of a factor given in ``factors`` was set (it would be
    silently unused)."""
    set_ = object.__setattr__
    bursty = env.bursty
    if bursty is not None and not isinstance(bursty, BurstySpec):
        if not isinstance(bursty, Mapping):
            raise ValueError(f"env.bursty={bursty!r} must be a mapping with rates, transition")
        reject_unknown_keys("env.bursty.", bursty, ("rates", "transition"))
        if set(bursty) != {"rates", "transition"}:
            raise ValueError("env.bursty needs both rates and transition")
        bursty = BurstySpec(**bursty)
    set_(env, "bursty", bursty)
    if bursty is not None and env.arrival_rate is not None:
        raise ValueError(
            f"env.arrival_rate={env.arrival_rate} is not used with bursty arrivals (the "
            "rates are env.bursty.rates); set env.arrival_rate=null"
        )
    if bursty is None and env.arrival_rate is None:
        raise ValueError("env.arrival_rate=null needs env.bursty (rates and transition)")
    defaults = type(env).__dataclass_fields__
    for spec in env.factors:
        name = spec.name
        used = [("stay_good", name), ("stay_bad", name)]
        if name == "channel":
            used += [("packets_good", None), ("packets_bad", None)]
        else:
            used += [("p0", name), ("p1", name)]
        for key, sub in used:
            dflt = defaults[key]
            base = dflt.default_factory() if dflt.default_factory is not MISSING else dflt.default
            mine = getattr(env, key)
            if sub is not None:
                base, mine = getattr(base, sub), getattr(mine, sub)
            if mine != base:
                full = f"env.{key}" + (f".{sub}" if sub else "")
                raise ValueError(
                    f"{full}={mine} is not used: env.factors.{name} describes the {name} "
                    f"(levels, transition{', packets, comm_reward' if name == 'channel' else ', event'}); "
                    f"set it there or leave {full} at its default {base}"
                )
