"""Files every recipe writes, atomically: ``summary.json``, CSV rows, Markdown tables, figures."""

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

from irdrc.core.checks import grouped
from irdrc.core.metrics import Metrics


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


def atomic_write(path: Path, write: Callable[[BinaryIO], object]) -> None:
    """Write ``path`` all at once or not at all: ``write`` fills a temporary file beside it, which
    is flushed, fsynced and renamed over ``path``. On any error (a full disk, a signal) the
    temporary file is removed and ``path`` keeps its previous content.

    Raises:
        OSError: with the file named, e.g. ``No space left on device``.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    existed = path.exists()
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
            kept = "its previous content is intact" if existed else "nothing was written there"
            raise OSError(err.errno, f"cannot write {path}: {reason} ({kept})") from err
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

    import torch

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


def measured_line(wall_seconds: float | None = None, kept_runs: int = 0) -> str:
    """``Measured on DATE on MACHINE[, in N s].``: the one line a generated table carries about where
    and when it was measured (``machine_description``). ``kept_runs``: runs a resumed benchmark
    took from an earlier invocation, whose time N does not count (said on the line)."""
    import datetime

    date = datetime.date.today().isoformat()
    took = ""
    if wall_seconds is not None:
        took = ", in " + grouped(wall_seconds) + " s"
    if kept_runs:
        took += (
            f" (the runs of this invocation; {kept_runs} more were kept from an earlier one "
            "into the same directory)"
        )
    return f"Measured on {date} on {machine_description()}{took}."


def write_table_md(
    path: Path, table: str, wall_seconds: float | None = None, kept_runs: int = 0
) -> None:
    """Write a benchmark's Markdown table with its ``measured_line`` under it (atomically): the
    file ``python -m irdrc.paper.docs`` embeds in docs/."""
    line = measured_line(wall_seconds, kept_runs)
    atomic_write_text(Path(path), table.rstrip() + "\n\n" + line + "\n")


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
    """The ``summary.json`` record. ``optimality_ratio`` = avg_reward / optimal avg_reward (None
    where the optimum earns ≤ 0: such a ratio would not rank policies)."""
    out = {
        "method": method,
        "scenario": scenario,
        "seed": int(seed),
        "env_steps": int(env_steps),
        "wall_seconds": float(wall_seconds),
        "metrics": {k: clean_number(v) for k, v in metrics.as_dict().items()},
        "optimal": {k: clean_number(v) for k, v in optimal.as_dict().items()},
        "optimality_ratio": clean_number(metrics.avg_reward / optimal.avg_reward)
        if optimal.avg_reward > 0
        else None,
    }
    out.update(extra)
    return out


def write_summary(path: Path, summary: dict[str, Any]) -> None:
    """Write a summary record as JSON (atomically); an undefined number (NaN, e.g. the miss
    detection of a stream with no event yet) is written as null, wherever it is in the record."""
    atomic_write_text(
        Path(path), json.dumps(_json_clean(summary), indent=2, allow_nan=False) + "\n"
    )


def _json_clean(value: Any) -> Any:
    if isinstance(value, dict):
        return {k: _json_clean(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_json_clean(v) for v in value]
    if isinstance(value, float) and math.isnan(value):
        return None
    return value


def read_csv_table(path: Path) -> tuple[list[str], list[dict[str, str]]]:
    """A CSV file's header and its rows as dicts of strings (what ``write_rows_csv`` wrote).

    Raises:
        ValueError: naming the file, if it cannot be read or is not UTF-8 text.
    """
    try:
        with Path(path).open(newline="", encoding="utf-8") as f:
            reader = csv.DictReader(f)
            rows = list(reader)
            return list(reader.fieldnames or []), rows
    except OSError as err:
        raise ValueError(f"{path}: not a readable file ({err.strerror or err})") from err
    except UnicodeDecodeError as err:
        raise ValueError(
            f"{path}: not a text table (byte {err.start}: {err.reason} in UTF-8)"
        ) from err


def read_csv_rows(path: Path) -> list[dict[str, str]]:
    """Rows of a CSV file as dicts of strings (``read_csv_table``'s rows)."""
    return read_csv_table(path)[1]


def write_metrics_csv(path: Path, history: Sequence[dict[str, Any]]) -> None:
    """``metrics.csv``: every exact evaluation of a run, in ``PROGRESS_FIELDS``, with
    ``false_alarm_rate`` after them where a row has it (a scenario with radar false alarms), then
    any columns a learner adds (a learner on one stream: its ledger, ``irdrc.online.ledger``)."""
    from irdrc.agents.base import PROGRESS_FIELDS

    extra = ["false_alarm_rate"] if any("false_alarm_rate" in r for r in history) else []
    for row in history:
        extra += [k for k in row if k not in PROGRESS_FIELDS and k not in extra]
    write_rows_csv(path, history, (*PROGRESS_FIELDS, *extra))


def write_rows_csv(
    path: Path, rows: Iterable[dict[str, Any]], fieldnames: Sequence[str] | None = None
) -> None:
    """A list of flat dicts as CSV, atomically. The header is ``fieldnames`` (written even with no
    rows), else every row's keys in the order they first appear (a metric defined in some rows
    only, such as ``false_alarm_rate`` where a policy never senses, is blank in the others)."""
    rows = list(rows)
    if not rows and fieldnames is None:
        atomic_write_text(Path(path), "")
        return
    buf = io.StringIO()
    names = fieldnames or dict.fromkeys(k for row in rows for k in row)
    w = csv.DictWriter(buf, fieldnames=list(names))
    w.writeheader()
    w.writerows(rows)
    atomic_write_text(Path(path), buf.getvalue())
