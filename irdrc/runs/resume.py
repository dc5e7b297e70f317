"""A resumed run's configuration: the checkpoint's own, what the command line may change, a
``config.yaml`` edited since, a checkpoint of another recipe, a complete training with its files
missing."""

from __future__ import annotations

import copy
from pathlib import Path
from typing import Any

RESUME_MAY_DIFFER = (
    "algo.total_frames",
    "algo.episodes",
    "eval.",
    "logger.",
    "progress",
    "resume",
    "device",
    "num_threads",
    "checkpoint.",
    "plot.",
    "hydra.",
)
"""Config keys a resumed run may change (where and how long it runs, not what it learns)."""


def _flatten(node: Any, prefix: str = "") -> dict[str, Any]:
    if isinstance(node, dict):
        out: dict[str, Any] = {}
        for k, v in node.items():
            out.update(_flatten(v, f"{prefix}{k}."))
        return out
    return {prefix[:-1]: node}


def _covered(key: str, explicit: frozenset[str]) -> bool:
    return any(key == e or key.startswith(e + ".") for e in explicit)


def checkpoint_recipe(path: Path, state: dict[str, Any]) -> str | None:
    """The recipe that wrote the checkpoint at ``path``: its own record, or its run directory's
    ``.hydra/hydra.yaml`` (None when neither says)."""
    if state.get("recipe"):
        return str(state["recipe"])
    job = path.parent / ".hydra" / "hydra.yaml"
    if job.is_file():
        from omegaconf import OmegaConf

        return OmegaConf.select(OmegaConf.load(job), "hydra.job.name")
    return None


def edited_config(path: Path, saved: dict[str, Any]) -> list[str]:
    """The keys whose value in the run directory's ``config.yaml`` differs from the checkpoint's
    configuration (the file edited after the run wrote it), as ``key: checkpoint → file``."""
    file = path.parent / "config.yaml"
    if not file.is_file():
        return []
    from omegaconf import OmegaConf

    on_disk = _flatten(OmegaConf.to_container(OmegaConf.load(file)))
    old = _flatten(saved)
    return [
        f"{k}: {old.get(k, '<absent>')} → {on_disk.get(k, '<absent>')}"
        for k in sorted(set(old) | set(on_disk))
        if old.get(k, "<absent>") != on_disk.get(k, "<absent>")
        and not k.startswith(RESUME_MAY_DIFFER)
    ]


CLASHES_SHOWN = 3
"""Differing keys named per key the command line set (a scenario changes dozens)."""


def resumed_config(
    path: Path, saved: dict[str, Any], current: dict[str, Any], explicit: frozenset[str]
) -> dict[str, Any]:
    """The configuration of a run resumed from the checkpoint at ``path``: the checkpoint's own
    (``saved``), except what the command line set on purpose (``explicit``, groups included),
    which ``current`` gives — so ``resume=PATH`` alone goes on exactly as the run started, and
    ``algo.total_frames=…`` extends it. A section this version no longer has (a checkpoint of an
    earlier version) is dropped.

    Raises:
        ValueError: naming every key the command line set to another value that a resumed run may
            not change (what it learns; ``RESUME_MAY_DIFFER``).
    """
    explicit = frozenset(k for k in explicit if not k.startswith("hydra"))
    old, new = _flatten(saved), _flatten(current)
    clash = []
    for key in sorted(explicit):
        if f"{key}.".startswith(RESUME_MAY_DIFFER):  # logger=none: a group of keys that may differ
            continue
        differ = [
            f"{k}: {old.get(k, '<absent>')} → {new.get(k, '<absent>')}"
            for k in sorted(set(old) | set(new))
            if _covered(k, frozenset([key])) and old.get(k, "<absent>") != new.get(k, "<absent>")
        ]
        if len(differ) > CLASHES_SHOWN:  # a group (env=…) that changes a whole section
            differ = [*differ[:CLASHES_SHOWN], f"… {len(differ) - CLASHES_SHOWN} more under {key}"]
        clash += differ
    if clash:
        raise ValueError(
            f"resume={path} was trained with another configuration; these keys differ "
            f"(checkpoint → this run): {'; '.join(clash)}. A resumed run keeps the checkpoint's "
            "configuration: leave them out"
        )
    out = copy.deepcopy(current)
    for key, value in old.items():
        gone = key.split(".")[0] not in current
        if not gone and not _covered(key, explicit) and key not in ("resume", "progress", "device"):
            node = out
            *parents, last = key.split(".")
            for part in parents:
                node = node.setdefault(part, {})
            node[last] = value
    return out


def nothing_left(resume_path: Any, done: int, total: int) -> bool:
    """Whether a run resumed from ``resume_path`` at ``done`` of ``total`` steps has nothing to do:
    its training is complete and its files (``summary.json``) are written. A complete training
    whose files are missing (a signal during the final evaluation, a crash) is finished again."""
    written = (Path(str(resume_path)).expanduser().parent / "summary.json").is_file()
    return done >= total and written


def refuse_finished(
    resume_path: Any, done: int, total: int, key: str, value: int, unit: str = "env steps"
) -> None:
    """Refuse a resumed run with nothing left to do (``nothing_left``: ``done`` of ``total``
    ``unit`` trained, its files written), naming the key ``key`` (now ``value``) that trains it
    longer.

    Raises:
        ValueError: the run is finished.
    """
    if nothing_left(resume_path, done, total):
        raise ValueError(
            f"resume={resume_path} is at {done} {unit}, {key}={value}: nothing left to train; "
            f"raise {key} to train it longer"
        )
