"""Overrides named as on the command line — ``{"env.p1.speed": 0.5, "reward.r4": 50}`` or nested
``{"env": {"p1": {"speed": 0.5}}}`` — applied to a plain config mapping (the Python API's and the
gym constructors' way to name a scenario; recipes compose theirs with Hydra)."""

from __future__ import annotations

from collections.abc import Iterator, Mapping
from typing import Any

REWARD_KEYS = ("r1", "r2", "r3", "r4", "r5")
"""The reward weights (``reward.r1`` … ``reward.r5``)."""


def full_key(key: str) -> str:
    """``key`` with its section: ``r4`` → ``reward.r4``, ``p1.speed`` → ``env.p1.speed`` (as it is
    when it has one)."""
    head = key.split(".", 1)[0]
    if head in ("env", "reward"):
        return key
    return f"reward.{key}" if head in REWARD_KEYS else f"env.{key}"


def apply_overrides(merged: dict[str, Any], overrides: Mapping[str, Any]) -> None:
    """Set dotted or nested overrides into ``merged`` ({"env": …, "reward": …}); every key starts
    with its section (``env.`` or ``reward.``), as on the command line."""
    for key, value in overrides.items():
        parts = str(key).split(".")
        if parts[0] not in ("env", "reward"):
            raise ValueError(
                f"override {key!r} needs its section: write {full_key(str(key))!r} (keys are "
                "named as on the command line: 'env.p1.speed', 'reward.r4', or nested "
                "{'env': {...}, 'reward': {...}})"
            )
        if len(parts) == 1 and not isinstance(value, Mapping):
            raise ValueError(
                f"{key}={value!r}: a section is a mapping of its keys ({key}={{'p1': {{'speed': "
                f"0.5}}}} or **{{'{key}.p1.speed': 0.5}}); a named scenario of irdrc/scenarios/ is "
                f"irdrc.scenario({value!r}), a Params"
            )
        target = merged
        for p in parts[:-1]:
            target = target.setdefault(p, {})
            if not isinstance(target, dict):
                raise ValueError(f"override {key!r} conflicts with another key")
        deep_set(target, parts[-1], value)


def deep_set(target: dict[str, Any], key: str, value: Any) -> None:
    """``target[key] = value``, merging mappings into mappings key by key."""
    if isinstance(value, Mapping) and isinstance(target.get(key), dict):
        for k, v in value.items():
            deep_set(target[key], k, v)
    else:
        target[key] = value


SHARE_KEYS = ("env.levels", "env.sensing", "env.dwell_gain")
"""Keys of the radar share (MODEL.md § D), read only where a step may be shared (``env.actions``
levels or continuous)."""


def refuse_share_keys(actions: str, given: Mapping[str, str]) -> None:
    """Refuse a key of ``SHARE_KEYS`` among ``given`` (each key → how its caller wrote it) where
    ``actions`` is ``binary``: each step is all comm or all radar, so nothing would read it."""
    if actions != "binary":
        return
    for key, shown in given.items():
        if key in SHARE_KEYS:
            raise ValueError(
                f"{shown}: with env.actions=binary each step is all comm or all radar; {key} "
                "shapes the radar share (env.actions=levels or continuous, MODEL.md § D)"
            )


def refuse_share_overrides(overrides: Mapping[str, Any]) -> None:
    """``refuse_share_keys`` for overrides as a constructor takes them (dotted or nested)."""
    given = dict(dotted(overrides))
    refuse_share_keys(
        given.get("env.actions", "binary"), {k: f"{k}={v!r}" for k, v in given.items()}
    )


def dotted(overrides: Mapping[str, Any], prefix: str = "") -> Iterator[tuple[str, Any]]:
    """The overrides as (dotted key, value) pairs, nested mappings opened."""
    for key, value in overrides.items():
        if isinstance(value, Mapping) and value:
            yield from dotted(value, f"{prefix}{key}.")
        else:
            yield f"{prefix}{key}", value
