"""Run outputs shared by every recipe: ``summary.json``, ``policy.csv``, ``metrics.csv``, policy tables."""

from __future__ import annotations

import csv
import io
import json
import math
import os
import tempfile
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Any

import torch

from irdrc.core.env import decode_state
from irdrc.core.metrics import Metrics
from irdrc.core.model import ExactModel


def clean_number(x: float | None) -> float | None:
    """A number for JSON/CSV: NaN (an undefined metric) becomes None."""
    return None if x is None or (isinstance(x, float) and math.isnan(x)) else float(x)


def atomic_write_text(path: Path, text: str) -> None:
    """Write ``text`` to ``path`` through a temporary file and a rename."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.")
    with os.fdopen(fd, "w") as f:
        f.write(text)
    os.replace(tmp, path)


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


def write_policy_csv(path: Path, actions: torch.Tensor) -> None:
    """``policy.csv``: header ``d,c,r,w,v,m,action``, one row per state in index order."""
    actions = torch.as_tensor(actions).long().cpu()
    cols = decode_state(torch.arange(actions.numel()))
    lines = ["d,c,r,w,v,m,action"]
    lines += [",".join(map(str, [*c.tolist(), int(a)])) for c, a in zip(cols, actions, strict=True)]
    atomic_write_text(Path(path), "\n".join(lines) + "\n")


def read_policy_csv(path: Path) -> torch.Tensor:
    """Inverse of ``write_policy_csv``: the [S] action table."""
    with Path(path).open() as f:
        rows = list(csv.DictReader(f))
    return torch.tensor([int(r["action"]) for r in rows])


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
    otherwise a string with one letter per d = 0 … D (C = comm, R = radar).
    """
    D = model.params.env.queue_capacity
    acts = torch.as_tensor(actions).long().view(D + 1, 32)
    lines = ["c r w v m  b  P(event)  mode (by d = 0 … D when it varies)"]
    for f in range(32):
        bits = [(f >> s) & 1 for s in (4, 3, 2, 1, 0)]
        col = acts[:, f]
        if bool((col == col[0]).all()):
            mode = "radar" if int(col[0]) else "comm"
        else:
            mode = "".join("R" if int(a) else "C" for a in col)
        pe = float(model.event[f])
        lines.append(f"{' '.join(map(str, bits))}  {sum(bits[1:])}  {pe:8.4f}  {mode}")
    return "\n".join(lines)
