"""What every learner shares: the hooks it reports through and the record it returns, whose
progress is one schema (``PROGRESS_FIELDS``), whatever the method.

Learners know nothing of files or loggers: they report through ``Hooks`` and return their
``RunRecord``; the run scaffold (``irdrc.runs.scaffold``) turns that into a run directory
the same way for every method.
"""

from __future__ import annotations

import hashlib
import io
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

import torch

from irdrc.core.checks import check_file
from irdrc.core.metrics import METRIC_NAMES, Metrics, first_reaching

PROGRESS_FIELDS = (
    "learner",
    "env_steps",
    "episodes",
    "wall_seconds",
    "updates",
    "optimality_ratio",
    *METRIC_NAMES,
)
"""One exact evaluation of one learner's greedy policy: the columns of every ``metrics.csv``
(``false_alarm_rate`` joins them in a scenario with radar false alarms:
``irdrc.runs.results.write_metrics_csv``).
``env_steps`` and ``episodes`` count this learner's own interaction; metrics are exact stationary."""


EPISODE_FIELDS = ("learner", "episode", "env_steps", "reward")
"""One finished training episode (exploration included): the columns of ``episode_rewards.csv``."""


class BatchSchedule(Protocol):
    """What the shared training loop, its collector and its optimiser read of a learner's
    hyperparameters (``OffPolicyConfig``, ``SACConfig``, ``PPOConfig``, ``FleetPPOConfig``)."""

    @property
    def name(self) -> str: ...

    @property
    def num_envs(self) -> int: ...

    @property
    def frames_per_batch(self) -> int: ...

    @property
    def total_frames(self) -> int: ...

    @property
    def init_random_frames(self) -> int: ...

    @property
    def batch_size(self) -> int: ...

    @property
    def updates_per_batch(self) -> int: ...

    @property
    def prioritized(self) -> bool: ...

    @property
    def lr(self) -> float: ...

    @property
    def lr_end(self) -> float: ...


class ReplayConfig(Protocol):
    """What replay is built from (``OffPolicyConfig``, ``SACConfig``)."""

    @property
    def buffer_size(self) -> int: ...

    @property
    def prioritized(self) -> bool: ...

    @property
    def alpha(self) -> float: ...

    @property
    def batch_size(self) -> int: ...


@dataclass
class Hooks:
    """What a learner calls while it trains (all optional).

    Attributes:
        on_eval: after each exact evaluation, with its progress records (one per learner).
        on_batch: after each batch of interaction, with ``env_steps`` and the learner's training
            scalars (e.g. ``epsilon``, ``loss``), logged as ``train/<name>``.
        on_start: once the learner is built, with facts about it (e.g. the replay sampler).
        on_checkpoint: with the resumable state, every ``checkpoint_every_frames`` env steps or
            ``checkpoint_every_seconds`` of wall time, whichever comes first (learners that
            checkpoint; 0 and 0: never during the run).
        should_stop: polled after each batch; True makes the learner stop there, evaluate, and
            return its record with ``interrupted`` set (and ``state`` to resume from).
    """

    on_eval: Callable[[list[dict[str, Any]]], None] | None = None
    on_batch: Callable[[dict[str, Any]], None] | None = None
    on_start: Callable[[dict[str, Any]], None] | None = None
    on_checkpoint: Callable[[dict[str, Any]], None] | None = None
    checkpoint_every_frames: int = 0
    should_stop: Callable[[], bool] | None = None
    checkpoint_every_seconds: float = 0.0
    _last_checkpoint: float = field(default_factory=time.monotonic, repr=False)

    def start(self, info: dict[str, Any]) -> None:
        """Call ``on_start`` (what the learner built, before the first step) if set."""
        if self.on_start is not None:
            self.on_start(info)

    def checkpoint_due(self, before: int, after: int) -> bool:
        """Whether a multiple of ``checkpoint_every_frames`` lies in (before, after], or
        ``checkpoint_every_seconds`` have passed since the last checkpoint (or the start)."""
        if self.on_checkpoint is None:
            return False
        every, seconds = self.checkpoint_every_frames, self.checkpoint_every_seconds
        due = bool(every) and after // every > before // every
        due = due or (seconds > 0 and time.monotonic() - self._last_checkpoint >= seconds)
        if due:
            self._last_checkpoint = time.monotonic()
        return due

    def checkpoint(self, state: dict[str, Any]) -> None:
        """Call ``on_checkpoint`` with the resumable ``state`` if set."""
        if self.on_checkpoint is not None:
            self.on_checkpoint(state)

    def stop_requested(self) -> bool:
        """Whether the caller asked the learner to stop after this batch (e.g. on SIGTERM)."""
        return self.should_stop is not None and self.should_stop()

    def eval(self, records: list[dict[str, Any]]) -> None:
        """Call ``on_eval`` if set."""
        if self.on_eval is not None:
            self.on_eval(records)

    def batch(self, info: dict[str, Any]) -> None:
        """Call ``on_batch`` if set."""
        if self.on_batch is not None:
            self.on_batch(info)


class RunContext:
    """How a learner's run is watched and continued — what every learner takes beside its model and
    hyperparameters, passed down as one.

    Attributes:
        scorer: scores the learner's policy tables (``metrics(table)``, ``optimal_metrics``).
        eval_every_frames: exact evaluation period, env steps.
        hooks: where progress, checkpoints and stop requests go.
        resume: a checkpoint (a ``RunRecord.state``) to go on from, or None.
    """

    def __init__(
        self,
        scorer: Any,
        eval_every_frames: int,
        hooks: Hooks | None = None,
        resume: dict[str, Any] | None = None,
    ) -> None:
        if eval_every_frames < 1:
            raise ValueError(f"eval.every_frames={eval_every_frames!r} must be >= 1")
        self.scorer, self.eval_every_frames = scorer, eval_every_frames
        self.hooks = hooks or Hooks()
        self.resume = resume


@dataclass
class RunRecord:
    """What a learner returns.

    Attributes:
        method: the learner's name.
        greedy: [N, S] final greedy action per learner and state (ties → comm).
        history: progress records (``PROGRESS_FIELDS``) of every evaluation of every learner.
        episode_rewards: finished training episodes (``EPISODE_FIELDS``).
        env_steps: env steps per learner, all counted: training and ``measurement_env_steps``.
        measurement_env_steps: of those, the steps spent measuring candidate final policies on
            the simulator after training (final-policy selection, the Lagrangian search); 0 for
            learners that do not.
        episodes: finished training episodes per learner.
        updates: learning updates (per learner).
        wall_seconds: training wall time, evaluations included.
        group: scenario index of each learner (row n of ``greedy``).
        q: [N, S, 2] final action values per learner and state, where the learner has them.
        info: learner-specific facts worth reporting (e.g. the replay sampler).
        state: a resumable state (written as ``checkpoint.pt``), or None for learners that do not
            checkpoint.
        interrupted: the run stopped early because ``Hooks.should_stop`` asked it to.
        policy: [N, S, 2] final probabilities of (comm, radar), for learners whose final policy
            may randomise (``greedy`` is then its most likely action); None: ``greedy`` is it.
    """

    method: str
    greedy: torch.Tensor
    history: list[dict[str, Any]] = field(default_factory=list)
    episode_rewards: list[dict[str, Any]] = field(default_factory=list)
    env_steps: int = 0
    measurement_env_steps: int = 0
    episodes: int = 0
    updates: int = 0
    wall_seconds: float = 0.0
    group: list[int] = field(default_factory=lambda: [0])
    q: torch.Tensor | None = None
    info: dict[str, Any] = field(default_factory=dict)
    state: dict[str, Any] | None = None
    interrupted: bool = False
    policy: torch.Tensor | None = None

    @property
    def training_env_steps(self) -> int:
        """Env steps of training (``env_steps`` less the measurement steps)."""
        return self.env_steps - self.measurement_env_steps

    @property
    def num_learners(self) -> int:
        """Rows of ``greedy``."""
        return int(self.greedy.shape[0])

    def curve(self, learner: int = 0) -> list[dict[str, Any]]:
        """The progress records of one learner, in order."""
        return [r for r in self.history if r["learner"] == learner]

    def first_reaching(self, threshold: float, learner: int = 0, at: str = "env_steps") -> Any:
        """``at`` (env steps, wall seconds, …) of the first evaluation ≥ ``threshold`` of the optimum."""
        return first_reaching(self.curve(learner), threshold, at=at)


def progress_record(
    learner: int,
    env_steps: int,
    episodes: int,
    wall_seconds: float,
    updates: int,
    metrics: Metrics,
    optimal_avg_reward: float,
) -> dict[str, Any]:
    """One row of ``PROGRESS_FIELDS``; ``optimality_ratio`` is NaN where the optimum earns ≤ 0
    (the constrained learner is read against the LP, whatever the rewards)."""
    return {
        "learner": int(learner),
        "env_steps": int(env_steps),
        "episodes": int(episodes),
        "wall_seconds": float(wall_seconds),
        "updates": int(updates),
        "optimality_ratio": (
            metrics.avg_reward / optimal_avg_reward if optimal_avg_reward > 0 else math.nan
        ),
        **metrics.as_dict(),
    }


CHECKPOINT_KEYS = ("frames", "updates", "wall_seconds", "history", "config")
"""What every learner's checkpoint holds (its ``RunRecord.state`` and the run's ``config``)."""


DIGEST_SUFFIX = ".sha256"
"""Beside ``checkpoint.pt``, ``checkpoint.sha256``: the SHA-256 of the checkpoint its run wrote
(while a new one replaces it, the previous one's too)."""


def load_checkpoint(path: Path | str, key: str = "resume") -> dict[str, Any]:
    """Load a learner's checkpoint (``RunRecord.state`` plus the run's ``config``).

    Raises:
        ValueError: one line naming ``key`` and the file when it is missing, truncated, corrupt
            or not a checkpoint of a learner of this package.
    """
    path = check_file(key, Path(path), "checkpoint.pt", "checkpoint file")
    data = path.read_bytes()
    digests = path.with_suffix(DIGEST_SUFFIX)
    if digests.is_file() and hashlib.sha256(data).hexdigest() not in digests.read_text().split():
        raise ValueError(
            f"{key}={path}: the file differs from the one its run wrote (its SHA-256 is not in "
            f"{digests.name}): it was damaged or changed since; nothing was read or written"
        )
    try:
        state = torch.load(io.BytesIO(data), map_location="cpu", weights_only=True)
    except Exception as err:  # truncated or corrupt: EOFError, RuntimeError, UnpicklingError …
        raise ValueError(
            f"{key}={path}: not a readable checkpoint ({type(err).__name__}); it may be truncated "
            "or from another program"
        ) from err
    missing = [k for k in CHECKPOINT_KEYS if not isinstance(state, dict) or k not in state]
    if missing:
        raise ValueError(f"{key}={path}: not an irdrc checkpoint (no {', '.join(missing)})")
    return state
