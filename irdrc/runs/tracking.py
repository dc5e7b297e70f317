"""Experiment tracking: one factory for W&B (online / offline / disabled), CSV, or nothing.

W&B defaults to offline when no API key is configured, so nothing ever waits on a network or a
login prompt; ``logger.mode=online`` without a key fails at start-up instead of hanging.
"""

from __future__ import annotations

import hashlib
import netrc
import os
from pathlib import Path
from typing import Any

BACKENDS = ("none", "csv", "tensorboard", "wandb")
WANDB_MODES = ("auto", "online", "offline", "disabled")
MAX_NAME_BYTES = 120
"""The longest run name (a directory's name under ``logs/``; file systems allow 255 bytes)."""


def wandb_api_key_configured() -> bool:
    """Whether W&B has credentials: ``WANDB_API_KEY`` or an ``api.wandb.ai`` entry in ~/.netrc."""
    if os.environ.get("WANDB_API_KEY"):
        return True
    try:
        return netrc.netrc().authenticators("api.wandb.ai") is not None
    except (FileNotFoundError, netrc.NetrcParseError, OSError):
        return False


def resolve_wandb_mode(mode: str) -> str:
    """``auto`` → ``online`` with credentials, else ``offline``; other modes are checked and kept."""
    if mode not in WANDB_MODES:
        raise ValueError(f"logger.mode={mode!r} must be one of {', '.join(WANDB_MODES)}")
    if mode == "auto":
        return "online" if wandb_api_key_configured() else "offline"
    if mode == "online" and not wandb_api_key_configured():
        raise ValueError(
            "logger.mode=online needs W&B credentials (WANDB_API_KEY or `wandb login`); "
            "use logger.mode=offline and `wandb sync` later"
        )
    return mode


def run_name(scenario: str, learner: str, seed: Any) -> str:
    """The run's name, ``scenario__learner__seed``, usable as one directory's name: ``/`` replaced,
    and a scenario too long for it (a command line of many overrides) cut to its first characters
    and ``~`` with a digest of the whole, so that different scenarios keep different names (the run's
    summary.json and config hold the scenario in full)."""
    head, tail = str(scenario).replace("/", "_"), f"__{learner}__{seed}".replace("/", "_")
    if len((head + tail).encode()) <= MAX_NAME_BYTES:
        return head + tail
    digest = hashlib.sha1(str(scenario).encode()).hexdigest()[:10]
    room = max(0, MAX_NAME_BYTES - len(tail.encode()) - len(digest) - 1)
    return head.encode()[:room].decode(errors="ignore") + "~" + digest + tail


def make_logger(
    backend: str,
    exp_name: str,
    log_dir: str | Path,
    *,
    project: str = "irdrc",
    mode: str = "auto",
    config: dict[str, Any] | None = None,
) -> Any:
    """A TorchRL logger (``CSVLogger``, ``TensorboardLogger`` or ``WandbLogger``), or None for
    ``backend="none"``.

    Args:
        backend: ``none``, ``csv``, ``tensorboard`` or ``wandb``.
        exp_name: the run's name.
        log_dir: where files go (CSV: ``<log_dir>/<exp_name>/scalars``; TensorBoard:
            ``<log_dir>/<exp_name>``, read with ``tensorboard --logdir <log_dir>``; W&B:
            ``<log_dir>/wandb``).
        project: W&B project.
        mode: W&B mode (see ``resolve_wandb_mode``).
        config: hyperparameters recorded with the run (W&B).
    """
    if backend not in BACKENDS:
        raise ValueError(f"logger={backend!r} must be one of {', '.join(BACKENDS)}")
    if backend == "none":
        return None
    if backend == "csv":
        from torchrl.record.loggers import CSVLogger

        return CSVLogger(exp_name=exp_name, log_dir=str(log_dir))
    if backend == "tensorboard":
        from torchrl.record.loggers import TensorboardLogger

        return TensorboardLogger(exp_name=exp_name, log_dir=str(log_dir))
    import wandb
    from torchrl.record.loggers import WandbLogger

    mode = resolve_wandb_mode(mode)
    logger = WandbLogger(
        exp_name=exp_name,
        offline=mode != "online",
        save_dir=str(log_dir),
        project=project,
        mode=mode,
        config=config or {},
        settings=wandb.Settings(console="off", silent=True),
        log_env_packages=False,
    )
    return logger


def log_scalars(logger: Any, values: dict[str, float], step: int) -> None:
    """Log every finite scalar of ``values`` at ``step`` (no-op without a logger)."""
    if logger is None:
        return
    for key, value in values.items():
        if value is None or value != value:  # NaN
            continue
        logger.log_scalar(key, float(value), step=step)
