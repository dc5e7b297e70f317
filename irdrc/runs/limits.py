"""What this machine can run, checked before any work: the exact model's size (dense and
factored), a one-vehicle learner's memory, and the device; each refusal names the key to change
and its largest value that fits."""

from __future__ import annotations

import math
from typing import Any

from irdrc.core import checks, sizes
from irdrc.core.params import Params


def check_dense(params: Params) -> None:
    """Refuse a model whose dense transition tensor would exhaust memory, with its estimate and
    the largest queue that fits."""
    if not sizes.fits_dense(params):
        S = params.env.num_states
        dense = 16 * S * S
        top = sizes.dense_fit_states() // math.prod(params.env.factor_levels) - 1
        raise ValueError(
            f"env.queue_capacity={params.env.queue_capacity}: the exact model has S = {S} states "
            f"and its dense transition tensor would take {dense / 2**30:.1f} GiB (limit "
            f"{sizes.DENSE_LIMIT_BYTES / 2**30:.1f} GiB); use env.queue_capacity ≤ {top}"
        )


EXACT_LIMIT_STATES = 10**7
"""The largest model the exact scorer takes (docs/SCALE.md: the factored model of 10⁶ states
took 377 MB above the imports' 234 MB)."""
EXACT_BYTES_PER_STATE = 377
"""The factored model's memory per state, as measured there."""


def check_exact(params: Params) -> None:
    """Refuse a model too large for the exact scorer (dense or factored), with its size."""
    S = params.env.num_states
    if S > EXACT_LIMIT_STATES:
        per_state = math.prod(params.env.factor_levels) or 1
        top = EXACT_LIMIT_STATES // per_state - 1
        raise ValueError(
            f"env.queue_capacity={params.env.queue_capacity}: the exact model has S = "
            f"{checks.grouped(S)} states, about {S * EXACT_BYTES_PER_STATE / 2**30:.1f} GiB "
            f"factored (limit {checks.grouped(EXACT_LIMIT_STATES)} states); use "
            f"env.queue_capacity ≤ {top}"
        )


TRAINING_BYTES = (5.4e8, 260, 620, 95)
"""A one-vehicle learner's peak memory in bytes: a fixed part (imports, the exact model of the paper
scenario), then per env row, per env step of a collection and per replay slot — fitted to the peak
resident memory of ``recipes/dqn.py`` runs of 250 000 and 1 000 000 rows, collections of one and
two steps a row, and replays of 2 and 4 million (2026-11-28)."""


def available_memory() -> int | None:
    """The memory this machine has available, in bytes (``MemAvailable``; None where unknown)."""
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    return None


def check_memory(algo: Any) -> None:
    """Refuse a learner whose env rows, collections and replay (``algo.num_envs``,
    ``frames_per_batch``, ``buffer_size``) would not fit this machine's available memory, with
    the estimate and the largest ``num_envs`` that fits (``TRAINING_BYTES``)."""
    have = available_memory()
    if have is None:
        return
    base, per_row, per_step, per_slot = TRAINING_BYTES
    rows, steps = int(algo.num_envs), int(algo.frames_per_batch)
    slots = int(getattr(algo, "buffer_size", 0) or 0)
    need = base + per_row * rows + per_step * steps + per_slot * slots
    if need <= have:
        return
    per_rows = steps / rows  # a collection's steps per row, kept
    room = (have - base - per_slot * slots) / (per_row + per_step * per_rows)
    fits = (
        f"use algo.num_envs ≤ {checks.grouped(int(room))}"
        if room >= 1
        else "lower algo.buffer_size"
    )
    raise ValueError(
        f"algo.num_envs={rows}, algo.frames_per_batch={steps}, algo.buffer_size={slots}: about "
        f"{need / 2**30:.1f} GiB of memory, this machine has {have / 2**30:.1f} GiB available; {fits}"
        " (with frames_per_batch a multiple of it)"
    )


def check_device(device: Any) -> str:
    """``device`` if torch can use it here (``cpu``, or ``cuda[:n]`` with a CUDA device)."""
    if device == "cpu":
        return device
    if not isinstance(device, str) or not device.startswith("cuda"):
        raise ValueError(f"device={device!r} must be cpu or cuda")
    import torch

    try:
        dev = torch.device(device)
    except RuntimeError as err:
        raise ValueError(f"device={device!r} is not a torch device (cpu, cuda, cuda:0 …)") from err
    if not torch.cuda.is_available():
        raise ValueError(f"device={device}: no CUDA device here (use device=cpu)")
    if dev.index is not None and dev.index >= torch.cuda.device_count():
        raise ValueError(f"device={device}: only {torch.cuda.device_count()} CUDA device(s)")
    return device
