"""The trials engine every recipe of many runs uses (``recipes/sweep.py``, figure2, tradeoff, the
benchmarks): a grid of config overrides, each point one run of a recipe module, on Ray Tune or one
after another here.

The driver composes and checks every grid point's config itself (so workers need the ``irdrc``
package only, not the recipes' YAML files) before any trial starts, runs the points as trials,
and receives each trial's ``summary.json`` and run files through Tune's reporting. Per-point
results are kept under ``<out>/trials/<point id>/``; ``resume`` reruns only points that are not
DONE; ``summary.csv`` joins the results against the expected grid, so a missing trial shows up as a
row.
"""

from __future__ import annotations

import contextlib
import csv
import io
import json
import tempfile
import time
import traceback
from collections.abc import Sequence
from pathlib import Path
from types import ModuleType
from typing import Any

from irdrc.runs.compose import SeededCompose, recipe_call, recorded
from irdrc.runs.grid import (
    format_value,
    point_id,
    point_overrides,
    shell_quote,
)
from irdrc.runs.results import atomic_write_text
from irdrc.runs.sections import Executor
from irdrc.sweeps.point import (
    STATUSES,
    last_line,
    progress_line,
    read_status,
    record,
    run_point,
)
from irdrc.sweeps.seeds import plot_seed_curves, write_seed_summary


def _matches(point_ov: list[str], fail_on: list[str]) -> bool:
    return bool(fail_on) and set(fail_on) <= set(point_ov)


SUMMARY_SECTIONS = ("metrics", "ledger")
"""The sections of a trial's ``summary.json`` whose entries are ``summary.csv``'s columns: the final
metrics, and the price of learning where the recipe counts it (``online``: regret, missed events …)."""


def plan(
    module: ModuleType, points: list[dict[str, Any]], base: list[str], fail_on: Sequence[str] = ()
) -> list[dict[str, Any]]:
    """Compose and check every point's config for the recipe ``module`` on the driver (a bad key or
    value, in the base or in any grid value, fails here, naming the point, before Ray starts or
    any trial runs). A recipe's ``SWEEP_DEFAULTS`` (e.g. no progress bar, no logger) come before
    ``base``.

    Returns one record per point: ``point_id``, ``point``, ``overrides``, ``method`` (the recipe's
    name), ``module`` (its path, which a worker imports), ``base``, the ``composed`` config and the
    recipe's typed ``config``, ``scenario`` and ``fail``. Plans of several recipes may be
    concatenated and executed together.
    """
    method, base = module.NAME, [str(o) for o in base]
    defaults = list(getattr(module, "SWEEP_DEFAULTS", ()))
    planned, compose = [], SeededCompose(module)
    for point in points:
        ov = point_overrides(point)
        try:
            composed = compose([*defaults, *base, *ov])
            config = module.load(composed)
            composed = recorded(module, config, composed)
        except Exception as err:
            where = " ".join([*base, *ov]) or "(no overrides)"
            raise ValueError(f"grid point {where}: {str(err).strip().splitlines()[0]}") from err
        planned.append(
            {
                "point_id": point_id(point, method, base),
                "point": point,
                "overrides": ov,
                "method": method,
                "module": module.__name__,
                "base": base,
                "composed": composed,
                "config": config,
                "scenario": composed.scenario,
                "fail": _matches(ov, [str(o) for o in fail_on]),
            }
        )
    return planned


def execute(cfg: Executor, planned: list[dict[str, Any]], out: Path, recipe: str = "sweep") -> int:
    """Run the planned points (``plan``) with the executor options ``cfg``; write ``summary.csv``.
    Results land in ``<out>/trials/<point id>/``; an interrupted run's go-on command names
    ``recipe``.

    Returns:
        0 if every point is DONE, 1 otherwise (130 when interrupted).
    """
    executor = cfg.executor
    ids = [p["point_id"] for p in planned]
    if len(set(ids)) != len(ids):
        raise ValueError("two planned points share an id (the same method, base and overrides)")
    out = Path(out).resolve()
    trials_dir = out / "trials"
    _adopt_earlier_ids(cfg, planned, trials_dir)
    todo = [p for p in planned if not _kept(cfg, trials_dir / p["point_id"])]
    total = len(planned)
    methods = ", ".join(sorted({p["method"] for p in planned}))
    print(
        f"sweep: method={methods}, {total} grid points, {len(todo)} to run"
        + (" (resume)" if cfg.resume else ""),
        flush=True,
    )
    interrupted = False
    try:
        if todo and executor == "ray":
            from irdrc.sweeps.tune_runner import run_tune

            run_tune(cfg, out, todo, total - len(todo), total, trials_dir)
        elif todo:
            _run_local(todo, total - len(todo), total, trials_dir)
    except KeyboardInterrupt:
        interrupted = True
        print(
            "\nsweep: interrupted; finished points are kept, the ones that were running are "
            f"INCOMPLETE in summary.csv; go on with: {go_on_command(out, recipe)}",
            flush=True,
        )
    finally:
        # Whatever happened, summary.csv lists every planned point: DONE, ERROR or INCOMPLETE.
        code = write_summary_csv(out / "summary.csv", planned, trials_dir)
    # A grid over seeds: mean ± 95 % interval per point, and the learning curves with bands.
    by_point = write_seed_summary(out / "summary.csv", out)
    curves = plot_seed_curves(out / "summary.csv", trials_dir, out)
    if by_point is not None:
        print(f"wrote {by_point}" + (f" and {curves}" if curves else ""), flush=True)
    return 130 if interrupted else code


def kept_points(cfg: Executor, planned: list[dict[str, Any]], out: Path) -> int:
    """How many of the planned points ``execute`` will keep from an earlier invocation into
    ``out`` rather than run (DONE points, with ``resume``): what a benchmark's time line says its
    time leaves out."""
    trials_dir = Path(out).resolve() / "trials"
    _adopt_earlier_ids(cfg, planned, trials_dir)
    return sum(_kept(cfg, trials_dir / p["point_id"]) for p in planned)


def _adopt_earlier_ids(cfg: Executor, planned: list[dict[str, Any]], trials_dir: Path) -> None:
    """With ``resume``, a point's trial directory named by an earlier version of ``point_id``
    (another readable prefix before the same hash) takes this version's name, so its results
    are kept."""
    if not cfg.resume or not trials_dir.is_dir():
        return
    for p in planned:
        here = trials_dir / p["point_id"]
        digest = p["point_id"].rpartition("__")[2]
        earlier = list(trials_dir.glob(f"*__{digest}")) if digest != p["point_id"] else []
        if not here.exists() and len(earlier) == 1 and earlier[0].is_dir():
            earlier[0].rename(here)


def _kept(cfg: Executor, trial_dir: Path) -> bool:
    """A point a resumed run does not run again: it finished (DONE) in an earlier invocation."""
    return cfg.resume and (read_status(trial_dir) or {}).get("status") == "DONE"


def go_on_command(out: Path, recipe: str = "sweep") -> str:
    """The command that goes on with the interrupted run in ``out``: the python that runs this
    process (``python_command``), its recipe with ``resume=true`` and the directory (the run's
    stored overrides come back on their own)."""
    from irdrc.runs.scaffold import python_command

    return (
        f"{python_command()} {recipe_call(recipe)} resume=true "
        f"hydra.run.dir={shell_quote(str(out))}"
    )


def _run_local(todo: list[dict[str, Any]], already: int, total: int, trials_dir: Path) -> None:
    """Run the points one after another in this process (no Ray): same files, same statuses."""
    import torch

    torch.set_num_threads(1)
    t0 = time.perf_counter()
    for i, p in enumerate(todo):
        tdir = trials_dir / p["point_id"]
        tdir.mkdir(parents=True, exist_ok=True)
        # The run's own printout goes to the trial's log, as a Ray trial's does.
        with (
            (tdir / "run.log").open("w") as log,
            contextlib.redirect_stdout(log),
            tempfile.TemporaryDirectory(prefix="irdrc-trial-") as tmp,
        ):
            try:
                result, error = run_point(p, Path(tmp) / "run"), None
            except KeyboardInterrupt:
                raise
            except Exception as exc:  # a crashed point is an ERROR row, as under Ray
                result, error = None, f"{type(exc).__name__}: {exc}"
                print(traceback.format_exc())
        record(tdir, p, result, error)
        tail = (
            f"ERROR: {last_line(error)}" if error else "DONE" + (result or {}).get("progress", "")
        )
        progress_line(already + i + 1, total, already, t0, p, tail)


def write_summary_csv(path: Path, planned: list[dict[str, Any]], trials_dir: Path) -> int:
    """``summary.csv``: one row per expected grid point (overrides, status, and the entries of its
    summary's ``SUMMARY_SECTIONS``).

    Returns 0 if every point is DONE, else 1.
    """
    keys = list(dict.fromkeys(k for p in planned for k in p["point"]))
    # Plans of several methods or bases (e.g. a figure's) name them in two leading columns.
    mixed = len({(p["method"], tuple(p.get("base", ()))) for p in planned}) > 1
    lead = ["method", "base"] if mixed else []
    rows, metric_names = [], []
    for p in planned:
        tdir = trials_dir / p["point_id"]
        st = read_status(tdir) or {"status": "INCOMPLETE"}
        row: dict[str, Any] = (
            {"method": p["method"], "base": " ".join(p.get("base", ()))} if mixed else {}
        )
        row.update({k: format_value(p["point"][k]) for k in keys if k in p["point"]})
        row["status"] = st["status"]
        row["point_id"] = p["point_id"]
        if st["status"] == "DONE" and (tdir / "summary.json").is_file():
            s = json.loads((tdir / "summary.json").read_text())
            row["optimality_ratio"] = s.get("optimality_ratio")
            row["env_steps"] = s.get("env_steps")
            row["wall_seconds"] = s.get("wall_seconds")
            for section in SUMMARY_SECTIONS:
                for k, v in (s.get(section) or {}).items():
                    row[k] = v
                    if k not in metric_names:
                        metric_names.append(k)
        rows.append(row)
    fields = [
        *lead,
        *keys,
        "status",
        "point_id",
        "optimality_ratio",
        "env_steps",
        "wall_seconds",
        *metric_names,
    ]
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=fields, restval="")
    w.writeheader()
    w.writerows(rows)
    atomic_write_text(path, buf.getvalue())
    counts = {s: sum(r["status"] == s for r in rows) for s in STATUSES}
    print(
        f"\n{len(rows)} grid points: "
        + ", ".join(f"{n} {s}" for s, n in counts.items())
        + f"; wrote {path}",
        flush=True,
    )
    return 0 if counts["DONE"] == len(rows) else 1
