"""One grid point of the trials engine: running it into a directory (``run_point``; ``trial`` is the
same as a Ray Tune trial), storing a finished point's files and status (``record``) and reading
them back (``read_status``). Both executors (here, one after another, in ``irdrc.sweeps.trials``;
on Ray in ``irdrc.sweeps.tune_runner``) use it. A point carries the path of its recipe's module
(``plan`` is handed the module by the recipe that sweeps), and a worker imports it from there: the
engine imports no recipe."""

from __future__ import annotations

import importlib
import json
import tempfile
import time
from pathlib import Path
from typing import Any

from irdrc.runs.results import atomic_write_text

STATUSES = ("DONE", "ERROR", "INCOMPLETE")


def trial(config: dict[str, Any]) -> None:
    """One Tune trial: run the planned point and report its results."""
    import torch
    from ray import tune

    from irdrc.runs.scaffold import Run

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
    from irdrc.runs.scaffold import Run
    from irdrc.runs.signals import RunInterrupted

    if point.get("fail"):
        raise RuntimeError(f"injected failure (sweep.fail_on) in {point['point_id']}")
    module = importlib.import_module(point["module"])
    run = Run(module.NAME, point["composed"], out).open()
    try:
        summary = module.run(point["config"], run)
    except RunInterrupted as err:
        raise KeyboardInterrupt(str(err)) from None  # the sweep stops, the point stays INCOMPLETE
    finally:
        run.close()
    return {
        "optimality_ratio": summary.get("optimality_ratio"),
        "progress": done_tail(summary),
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


def record(tdir: Path, p: dict[str, Any], result: dict[str, Any] | None, error: Any) -> None:
    """Write a finished point's files and status into its trial directory."""
    tdir.mkdir(parents=True, exist_ok=True)
    if error is None and not (result and "summary_json" in result):
        error = "the trial reported no summary"
    if error is None and result and "summary_json" in result:
        atomic_write_text(tdir / "summary.json", result["summary_json"] + "\n")
        for name, text in (result.get("files") or {}).items():
            atomic_write_text(tdir / name, text)
        status: dict[str, Any] = {"status": "DONE"}
    else:
        status = {"status": "ERROR", "error": [last_line(error)]}
    atomic_write_text(
        tdir / "status.json",
        # default=str: a grid value JSON cannot hold still names the point, never fails the write
        json.dumps({**status, "point": p["point"], "overrides": p["overrides"]}, default=str)
        + "\n",
    )


def last_line(error: Any) -> str:
    """The last non-empty line of an error (a traceback's message)."""
    lines = [line for line in str(error).strip().splitlines() if line.strip()]
    return lines[-1].strip() if lines else "unknown error"


def progress_line(
    done: int, total: int, already: int, t0: float, p: dict[str, Any], tail: str
) -> None:
    """Print one sweep progress line: points done of ``total``, the ETA, the point and ``tail``
    (its status); ``already`` points were done before this run started at ``t0``."""
    elapsed = time.perf_counter() - t0
    ran = done - already
    eta = elapsed / ran * (total - done) if ran else float("nan")
    label = " ".join([*p["base"], *p["overrides"]]) if p.get("base") else " ".join(p["overrides"])
    print(
        f"[{done}/{total}] {label} → {tail}  (elapsed {elapsed:.0f} s, ETA {eta:.0f} s)", flush=True
    )


def done_tail(result: dict[str, Any]) -> str:
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
