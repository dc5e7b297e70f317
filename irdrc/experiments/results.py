"""Run outputs shared by every recipe: ``summary.json``, ``policy.csv``, ``metrics.csv``, policy tables."""

from __future__ import annotations

import contextlib
import csv
import io
import json
import math
import os
import tempfile
from collections.abc import Callable, Iterable, Sequence
from pathlib import Path
from typing import Any, BinaryIO

import torch

from irdrc.core.env import decode_state
from irdrc.core.metrics import Metrics
from irdrc.core.model import ExactModel


def clean_number(x: float | None) -> float | None:
    """A number for JSON/CSV: NaN (an undefined metric) becomes None."""
    return None if x is None or (isinstance(x, float) and math.isnan(x)) else float(x)


def _umask() -> int:
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


FILE_MODE = 0o666 & ~_umask()
"""Mode of the files a run writes: what ``open`` would give under the user's umask (a temporary
file is created 0600, so it is set explicitly)."""


def atomic_write(path: Path, write: Callable[[BinaryIO], None]) -> None:
    """Write ``path`` all at once or not at all: ``write`` fills a temporary file beside it, which
    is flushed, fsynced and renamed over ``path``. On any error (a full disk, a signal) the
    temporary file is removed and ``path`` keeps its previous content.

    Raises:
        OSError: with the file named, e.g. ``No space left on device``.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as f:
            write(f)
            f.flush()
            os.fsync(f.fileno())
        os.chmod(tmp, FILE_MODE)
        os.replace(tmp, path)
    except BaseException as err:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        if isinstance(err, OSError) and not isinstance(err, FileNotFoundError):
            reason = err.strerror or str(err)
            raise OSError(
                err.errno, f"cannot write {path}: {reason} (its previous content is intact)"
            ) from err
        raise


def atomic_savefig(fig: Any, path: Path, dpi: int) -> None:
    """Write a Matplotlib figure atomically (a reader never sees half a file) in the format its
    suffix names (``.png``, ``.pdf``, ``.svg``), and close it."""
    import matplotlib.pyplot as plt

    buf = io.BytesIO()
    fig.savefig(buf, dpi=dpi, format=Path(path).suffix.lstrip(".") or "png")
    plt.close(fig)
    data = buf.getvalue()
    atomic_write(Path(path), lambda f: f.write(data))


def atomic_write_text(path: Path, text: str) -> None:
    """Write ``text`` to ``path`` atomically (see ``atomic_write``)."""
    data = text.encode()
    atomic_write(path, lambda f: f.write(data))


def md_table(header: Sequence[str], rows: Sequence[Sequence[Any]]) -> str:
    """A Markdown table (GitHub style) of ``rows`` under ``header``."""
    lines = ["| " + " | ".join(str(h) for h in header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(str(c) for c in r) + " |" for r in rows]
    return "\n".join(lines)


def machine_description() -> str:
    """This machine in a few words: CPU model, cores, torch version (and the GPU when one is
    used), for the one line under each generated table that says where it was measured."""
    import platform

    cpu = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo") as f:
            cpu = next(
                (line.split(":", 1)[1].strip() for line in f if line.startswith("model name")),
                cpu,
            )
    except OSError:
        pass
    gpu = f", {torch.cuda.get_device_name(0)}" if torch.cuda.is_available() else ""
    return f"{os.cpu_count()} cores ({cpu}){gpu}, torch {torch.__version__}"


def measured_line(wall_seconds: float | None = None) -> str:
    """``Measured on DATE on MACHINE[, in N s].``: the one line a generated table carries about where
    and when it was measured (``machine_description``)."""
    import datetime

    date = datetime.date.today().isoformat()
    took = ""
    if wall_seconds is not None:
        took = ", in " + f"{wall_seconds:,.0f}".replace(",", " ") + " s"
    return f"Measured on {date} on {machine_description()}{took}."


def write_table_md(path: Path, table: str, wall_seconds: float | None = None) -> None:
    """Write a benchmark's Markdown table with its ``measured_line`` under it (atomically): the
    file ``python -m irdrc.paper.docs`` embeds in docs/."""
    atomic_write_text(Path(path), table.rstrip() + "\n\n" + measured_line(wall_seconds) + "\n")


def summary_dict(
    *,
    method: str,
    scenario: str,
    seed: int,
    env_steps: int,
    wall_seconds: float,
    metrics: Metrics,
    optimal: Metrics,
    **extra: Any,
) -> dict[str, Any]:
    """The ``summary.json`` record. ``optimality_ratio`` = avg_reward / optimal avg_reward."""
    out = {
        "method": method,
        "scenario": scenario,
        "seed": int(seed),
        "env_steps": int(env_steps),
        "wall_seconds": float(wall_seconds),
        "metrics": {k: clean_number(v) for k, v in metrics.as_dict().items()},
        "optimal": {k: clean_number(v) for k, v in optimal.as_dict().items()},
        "optimality_ratio": clean_number(metrics.avg_reward / optimal.avg_reward)
        if optimal.avg_reward != 0
        else None,
    }
    out.update(extra)
    return out


def write_summary(path: Path, summary: dict[str, Any]) -> None:
    """Write a summary record as JSON (atomically)."""
    atomic_write_text(Path(path), json.dumps(summary, indent=2, allow_nan=False) + "\n")


POLICY_COLUMNS = ("d", "c", "r", "w", "v", "m", "action", "p_radar")
"""``policy.csv``: one row per state in index order: the state's factors, ``action`` (the mode
chosen: 0 = communication, 1 = radar; the likelier one for a randomised policy) and ``p_radar``
(the probability of radar: 0 or 1 for a deterministic policy)."""


def state_label(s: int, levels: Sequence[int] | None = None) -> str:
    """``d=3 c=0 r=1 w=0 v=2 m=0`` (and ``phase=1`` with bursty arrivals) for state index ``s``;
    ``levels`` as in ``Params.env.levels`` (None: v1)."""
    cols = decode_state(torch.tensor(int(s)), levels).tolist()
    names = ("d", "c", "r", "w", "v", "m", "phase")
    return " ".join(f"{n}={int(x)}" for n, x in zip(names, cols, strict=False))


def write_policy_csv(path: Path, policy: torch.Tensor, levels: Sequence[int] | None = None) -> None:
    """``policy.csv`` (see ``POLICY_COLUMNS``; a ``phase`` column after ``m`` with bursty arrivals)
    from an [S] action table or [S, 2] probabilities; ``levels`` as in ``Params.env.levels``
    (None: v1)."""
    policy = torch.as_tensor(policy).cpu()
    if policy.ndim == 2:
        p_radar = policy[:, 1].double()
        actions = (p_radar > 0.5).long()
    else:
        actions = policy.long()
        p_radar = actions.double()
    cols = decode_state(torch.arange(actions.numel()), levels)
    header = list(POLICY_COLUMNS)
    if cols.shape[-1] == 7:
        header.insert(6, "phase")
    lines = [",".join(header)]
    lines += [
        ",".join(map(str, [*c.tolist(), int(a), _prob(float(p))]))
        for c, a, p in zip(cols, actions, p_radar, strict=True)
    ]
    atomic_write_text(Path(path), "\n".join(lines) + "\n")


def _prob(p: float) -> str:
    return "0" if p == 0 else "1" if p == 1 else repr(p)


def read_policy_csv(
    path: Path, num_states: int | None = None, probabilities: bool = False
) -> torch.Tensor:
    """Inverse of ``write_policy_csv``: the [S] action table, or with ``probabilities`` the [S, 2]
    probabilities of (comm, radar) from ``p_radar`` (files without that column: 0 or 1 from
    ``action``).

    Raises:
        ValueError: naming the file, if it is not a policy table (of ``num_states`` rows).
    """
    try:
        with Path(path).open() as f:
            rows = list(csv.DictReader(f))
        actions = torch.tensor([int(r["action"]) for r in rows], dtype=torch.int64)
        p_radar = torch.tensor(
            [float(r.get("p_radar") or r["action"]) for r in rows], dtype=torch.float64
        )
    except (OSError, KeyError, ValueError, TypeError) as err:
        raise ValueError(f"{path}: not a readable policy table ({type(err).__name__})") from err
    if actions.numel() == 0 or bool(((actions != 0) & (actions != 1)).any()):
        raise ValueError(f"{path}: a policy table holds one action 0 or 1 per state")
    if bool(((p_radar < 0) | (p_radar > 1) | p_radar.isnan()).any()):
        raise ValueError(f"{path}: p_radar must be a probability in every row")
    if num_states is not None and actions.numel() != num_states:
        raise ValueError(f"{path}: {actions.numel()} states, expected {num_states}")
    if probabilities:
        return torch.stack([1 - p_radar, p_radar], -1)
    return actions


def read_csv_rows(path: Path) -> list[dict[str, str]]:
    """Rows of a CSV file as dicts of strings (what ``write_rows_csv`` wrote)."""
    with Path(path).open(newline="") as f:
        return list(csv.DictReader(f))


def write_rows_csv(
    path: Path, rows: Iterable[dict[str, Any]], fieldnames: Sequence[str] | None = None
) -> None:
    """A list of flat dicts as CSV, atomically. The header is ``fieldnames`` (written even with no
    rows), else the first row's keys."""
    rows = list(rows)
    if not rows and fieldnames is None:
        atomic_write_text(Path(path), "")
        return
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=list(fieldnames or rows[0]))
    w.writeheader()
    w.writerows(rows)
    atomic_write_text(Path(path), buf.getvalue())


def policy_table(model: ExactModel, actions: torch.Tensor) -> str:
    """Readable policy: one line per factor combination, its event probability and mode by queue.

    The mode column is ``comm``/``radar`` when the action is the same at every queue length,
    otherwise a string with one letter per d = 0 … D (C = comm, R = radar), or for D ≥ 64 its runs
    (``C×5 R×3120``). ``model`` is an ``ExactModel`` or a ``FactoredModel``.
    """
    D = model.params.env.queue_capacity
    labels = _config_labels(model.params)
    acts = torch.as_tensor(actions).long().view(D + 1, len(labels))
    phase = " phase" if model.params.env.levels[-1] > 1 else ""
    lines = [f"c r w v m{phase}  b  P(event)  mode (by d = 0 … D when it varies)"]
    for f, (bits, b) in enumerate(labels):
        col = acts[:, f]
        if bool((col == col[0]).all()):
            mode = "radar" if int(col[0]) else "comm"
        elif D + 1 <= 64:
            mode = "".join("R" if int(a) else "C" for a in col)
        else:  # runs: "C×5 R×3120" = comm for d = 0 … 4, radar above
            change = (col[1:] != col[:-1]).nonzero().flatten().tolist()
            ends = [*(i + 1 for i in change), D + 1]
            starts = [0, *ends[:-1]]
            mode = " ".join(
                f"{'R' if int(col[a]) else 'C'}×{b - a}" for a, b in zip(starts, ends, strict=True)
            )
        pe = float(model.event[f])
        lines.append(f"{bits}  {b}  {pe:8.4f}  {mode}")
    return "\n".join(lines)


def _config_labels(params) -> list[tuple[str, int]]:
    """Per factor configuration f: its levels as ``c r w v m[ phase]`` and b (MODEL.md § B.1)."""
    levels = params.env.levels
    cols = decode_state(torch.arange(math.prod(levels)), levels)[:, 1:].tolist()
    return [(" ".join(map(str, c)), sum(c[1:5])) for c in cols]


def policy_differences(model: ExactModel, actions: torch.Tensor, optimal: torch.Tensor) -> str:
    """In words, where a policy differs from the optimum: one line per factor combination (c, r, w,
    v, m) with a difference, each policy's mode by queue length (C = comm, R = radar, d = 0 … D)."""
    D = model.params.env.queue_capacity
    labels = _config_labels(model.params)
    acts = torch.as_tensor(actions).long().view(D + 1, len(labels))
    opt = torch.as_tensor(optimal).long().view(D + 1, len(labels))
    n_diff = int((acts != opt).sum())
    if n_diff == 0:
        return f"the learned policy equals the optimum in all {model.num_states} states"
    lines = [
        f"the learned policy differs from the optimum in {n_diff} of {model.num_states} states "
        "(mode by queue length d = 0 … D; C = comm, R = radar):",
        f"  c r w v m{' phase' if model.params.env.levels[-1] > 1 else ''}  P(event)  learned       optimum",
    ]
    for f, (bits, _) in enumerate(labels):
        if bool((acts[:, f] == opt[:, f]).all()):
            continue

        def mode(col: torch.Tensor) -> str:
            if bool((col == col[0]).all()):
                return "radar" if int(col[0]) else "comm"
            return "".join("R" if int(a) else "C" for a in col)

        lines.append(
            f"  {bits}  {float(model.event[f]):8.4f}  {mode(acts[:, f]):<12}  {mode(opt[:, f])}"
        )
    return "\n".join(lines)
