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
from pathlib import Path
from typing import Any

from irdrc.core.checks import check_choice
from irdrc.experiments import constrained, dqn, fleet, ppo, qlearning, sac, solve
from irdrc.experiments.compose import compose, rename_overrides
from irdrc.experiments.grid import (
    format_value,
    point_id,
    point_overrides,
    shell_quote,
)
from irdrc.experiments.results import atomic_write_text
from irdrc.experiments.sections import Executor
from irdrc.experiments.seeds import plot_seed_curves, write_seed_summary

METHODS = {m.NAME: m for m in (dqn, qlearning, solve, constrained, fleet, sac, ppo)}
"""The recipes a grid point may run (``method``)."""
# Settings a sweep gives every trial before the user's base overrides (which may change them).
TRIAL_DEFAULTS = {
    "dqn": ["progress=false", "logger=none"],
    "qlearning": ["progress=false", "logger=none"],
    "solve": [],
    "constrained": ["progress=false", "logger=none"],
    "fleet": ["progress=false", "logger=none"],
    "sac": ["progress=false", "logger=none"],
    "ppo": ["progress=false", "logger=none"],
}
STATUSES = ("DONE", "ERROR", "INCOMPLETE")


def _matches(point_ov: list[str], fail_on: list[str]) -> bool:
    return bool(fail_on) and set(fail_on) <= set(point_ov)


def trial(config: dict[str, Any]) -> None:
    """One Tune trial: run the planned point and report its results."""
    import torch
    from ray import tune

    from irdrc.experiments.scaffold import Run

    Run.max_threads = int(config.get("cpus", 1))  # the recipe's num_threads, within its CPUs
    config = config["point"]
    torch.set_num_threads(1)
    try:
        out = Path(tune.get_context().get_trial_dir())
    except Exception:
        out = Path(tempfile.mkdtemp(prefix="irdrc-trial-"))
    tune.report(run_point(config, out / "run"))


# The run files a trial sends back to the driver (through Tune's reporting, so a cluster needs no
# shared file system); checkpoints and logs stay in the trial's own directory.
RESULT_FILES = ("metrics.csv", "policy.csv", "learners.csv", "episode_rewards.csv")


def run_point(point: dict[str, Any], out: Path) -> dict[str, Any]:
    """Run one planned point into ``out`` (its recipe's run function, in a run scaffold of its
    own); return what a trial reports (summary and run files)."""
    from irdrc.experiments.scaffold import Run, RunInterrupted

    if point.get("fail"):
        raise RuntimeError(f"injected failure (sweep.fail_on) in {point['point_id']}")
    module = METHODS[point["method"]]
    run = Run(module.NAME, point["composed"], out).open()
    try:
        summary = module.run(point["config"], run)
    except RunInterrupted as err:
        raise KeyboardInterrupt(str(err)) from None  # the sweep stops, the point stays INCOMPLETE
    finally:
        run.close()
    return {
        "optimality_ratio": summary.get("optimality_ratio"),
        "progress": _done_tail(summary),
        "summary_json": json.dumps(summary),
        "files": {n: (out / n).read_text() for n in RESULT_FILES if (out / n).is_file()},
    }


def read_status(trial_dir: Path) -> dict[str, Any] | None:
    """A trial's status, or None when it has none. DONE counts only with its ``summary.json``; a
    status file that cannot be read is reported (naming it) and counts as not done."""
    path = trial_dir / "status.json"
    if not path.is_file():
        return None
    try:
        status = json.loads(path.read_text())
        if not isinstance(status, dict) or status.get("status") not in STATUSES:
            raise ValueError("no status")
    except (OSError, ValueError) as err:
        print(
            f"sweep: ignoring {path}: unreadable ({err}); the point counts as not done", flush=True
        )
        return None
    if status["status"] == "DONE" and not (trial_dir / "summary.json").is_file():
        return {**status, "status": "INCOMPLETE"}
    return status


def plan(
    method: str, points: list[dict[str, Any]], base: list[str], fail_on: list[str] = ()
) -> list[dict[str, Any]]:
    """Compose and check every point's config on the driver (a bad key or value, in the base or
    in any grid value, fails here, naming the point, before Ray starts or any trial runs).

    Returns one record per point: ``point_id``, ``point``, ``overrides``, ``method``, ``base``, the
    ``composed`` config and the recipe's typed ``config``, ``scenario`` and ``fail``. Plans of
    several methods may be concatenated and executed together.
    """
    check_choice("method", method, tuple(METHODS))
    module, base = METHODS[method], [str(o) for o in base]
    planned = []
    for point in points:
        ov = point_overrides(point)
        try:
            args, _ = rename_overrides(
                [*TRIAL_DEFAULTS[method], *base, *ov],
                getattr(module, "RENAMED", {}),
                getattr(module, "REMOVED", {}),
            )
            composed = compose(method, args)
            config = module.load(composed)
        except Exception as err:
            where = " ".join([*base, *ov]) or "(no overrides)"
            raise ValueError(f"grid point {where}: {str(err).strip().splitlines()[0]}") from err
        planned.append(
            {
                "point_id": point_id(point, method, base),
                "point": point,
                "overrides": ov,
                "method": method,
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
    todo = [
        p
        for p in planned
        if not (
            cfg.resume and (read_status(trials_dir / p["point_id"]) or {}).get("status") == "DONE"
        )
    ]
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
            from irdrc.experiments.tune_runner import run_tune

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


def go_on_command(out: Path, recipe: str = "sweep") -> str:
    """The command that goes on with the interrupted run in ``out``: its recipe with
    ``resume=true`` and the directory (the run's stored overrides come back on their own)."""
    return f"python recipes/{recipe}.py resume=true hydra.run.dir={shell_quote(str(out))}"


def _record(tdir: Path, p: dict[str, Any], result: dict[str, Any] | None, error: Any) -> None:
    """Write a finished point's files and status into its trial directory."""
    tdir.mkdir(parents=True, exist_ok=True)
    if error is None and not (result and "summary_json" in result):
        error = "the trial reported no summary"
    if error is None and result and "summary_json" in result:
        atomic_write_text(tdir / "summary.json", result["summary_json"] + "\n")
        for name, text in (result.get("files") or {}).items():
            atomic_write_text(tdir / name, text)
        status = {"status": "DONE"}
    else:
        status = {"status": "ERROR", "error": [_last_line(error)]}
    atomic_write_text(
        tdir / "status.json", json.dumps({**status, "overrides": p["overrides"]}) + "\n"
    )


def _last_line(error: Any) -> str:
    lines = [line for line in str(error).strip().splitlines() if line.strip()]
    return lines[-1].strip() if lines else "unknown error"


def _progress_line(done: int, total: int, already: int, t0: float, p: dict, tail: str) -> None:
    elapsed = time.perf_counter() - t0
    ran = done - already
    eta = elapsed / ran * (total - done) if ran else float("nan")
    label = " ".join([*p["base"], *p["overrides"]]) if p.get("base") else " ".join(p["overrides"])
    print(
        f"[{done}/{total}] {label} → {tail}  (elapsed {elapsed:.0f} s, ETA {eta:.0f} s)", flush=True
    )


def _run_local(todo: list[dict], already: int, total: int, trials_dir: Path) -> None:
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
        _record(tdir, p, result, error)
        tail = f"ERROR: {_last_line(error)}" if error else "DONE" + result.get("progress", "")
        _progress_line(already + i + 1, total, already, t0, p, tail)


def _done_tail(result: dict[str, Any]) -> str:
    """What a finished point's progress line says: a learner's ratio to the optimum; an exact
    solve's own value (it is the optimum, so a ratio would read 1 by construction)."""
    metrics = result.get("metrics") or {}

    def num(x: Any) -> float:  # a summary's undefined metric is None
        return float("nan") if x is None else float(x)

    if result.get("method") == "constrained" and result.get("env_steps") == 0:
        return (
            f", LP optimum {result.get('objective')} {num(result.get('value')):.4f}, "
            f"miss detection {num(metrics.get('miss_detection')):.4f}"
        )
    if result.get("method") == "optimal":
        return f", exact optimum avg reward {num(metrics.get('avg_reward')):.4f}"
    ratio = result.get("optimality_ratio")
    return f", optimality ratio {ratio:.4f}" if ratio is not None else ""


def write_summary_csv(path: Path, planned: list[dict], trials_dir: Path) -> int:
    """``summary.csv``: one row per expected grid point (overrides, status, final metrics).

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
            for k, v in (s.get("metrics") or {}).items():
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
