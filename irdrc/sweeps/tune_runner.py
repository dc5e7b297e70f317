"""The trials engine's Ray Tune executor (``executor=ray``): one Tune trial per grid point, each
trial's files stored by the driver the moment it finishes, Ctrl-C ending the sweep as interrupted
with the running points INCOMPLETE (``irdrc.sweeps.trials.execute`` calls it)."""

from __future__ import annotations

import logging
import os
import signal
import socket
import time
from pathlib import Path
from typing import Any

from irdrc.runs.sections import Executor, ray_host_port
from irdrc.sweeps.point import last_line, progress_line, read_status, record, trial

REACH_SECONDS = 10.0
"""How long a cluster's address (``ray.address=HOST:PORT``) has to answer before the sweep starts
(Ray itself retries for minutes, printing warnings)."""


def check_reachable(address: str, timeout: float = REACH_SECONDS) -> None:
    """Raise a ``ValueError`` when nothing answers at a cluster's Ray address."""
    where = ray_host_port(address)
    if where is None:  # local or auto: Ray answers for itself at once
        return
    try:
        socket.create_connection(where, timeout=timeout).close()
    except OSError as err:
        raise ValueError(
            f"ray.address={address}: nothing answers there within {timeout:g} s "
            f"({err.strerror or err}); start the cluster's head there (ray start --head), or run "
            "on this machine with ray.address=local"
        ) from None


def _ray_init(address: str, num_cpus: int | None) -> None:
    check_reachable(address)
    import ray

    os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")
    os.environ.setdefault("RAY_DEDUP_LOGS", "0")
    os.environ.setdefault("RAY_AIR_NEW_OUTPUT", "0")
    kwargs: dict[str, Any] = {
        "include_dashboard": False,
        "log_to_driver": False,
        "logging_level": logging.WARNING,
        "ignore_reinit_error": True,
    }
    if address == "local":
        ray.init(num_cpus=num_cpus, **kwargs)
    else:
        ray.init(address=address, **kwargs)


def run_tune(
    cfg: Executor, out: Path, todo: list[dict[str, Any]], already: int, total: int, trials_dir: Path
) -> None:
    """Run the points ``todo`` as Tune trials (``already`` of ``total`` were done before), storing
    each one's results under ``trials_dir``; a Ctrl-C raises KeyboardInterrupt once Tune stops."""
    # Ctrl-C reaches this driver as KeyboardInterrupt (Tune's own handler would mark the running
    # trials as errors and print its Tuner.restore hint): they stay INCOMPLETE, resume reruns them.
    os.environ.setdefault("TUNE_DISABLE_SIGINT_HANDLER", "1")
    import ray
    from ray import tune

    t0 = time.perf_counter()
    done = {"n": already}
    # Ctrl-C raises KeyboardInterrupt at once, except while a finished trial's files are being
    # stored (they are finished either way). One that lands inside a Tune callback can be
    # swallowed there: the flag keeps it, the stopper ends every trial at Tune's next check, and
    # the sweep still ends as interrupted.
    asked = {"stop": False, "storing": False}

    def on_sigint(signum: int, frame: Any) -> None:
        asked["stop"] = True
        if not asked["storing"]:
            raise KeyboardInterrupt

    class StopOnSigint(tune.stopper.Stopper):
        def __call__(self, trial_id: str, result: dict[str, Any]) -> bool:
            return asked["stop"]

        def stop_all(self) -> bool:
            return asked["stop"]

    class Progress(tune.Callback):
        def _line(self, trial: Any, status: str, extra: str = "") -> None:
            done["n"] += 1
            progress_line(done["n"], total, already, t0, trial.config["point"], status + extra)

        def on_trial_start(self, iteration: int, trials: Any, trial: Any, **info: Any) -> None:
            p = trial.config["point"]
            label = (
                " ".join([*p["base"], *p["overrides"]])
                if p.get("base")
                else " ".join(p["overrides"])
            )
            print(f"[started] {label}  (elapsed {time.perf_counter() - t0:.0f} s)", flush=True)

        def on_trial_complete(self, iteration: int, trials: Any, trial: Any, **info: Any) -> None:
            # The trial's files are stored now, not when the sweep ends: a killed driver keeps them.
            result = trial.last_result or {}
            if "summary_json" not in result and asked["stop"]:
                return  # stopped by Ctrl-C before it finished: it stays INCOMPLETE
            p = trial.config["point"]
            asked["storing"] = True
            try:
                record(trials_dir / p["point_id"], p, result, None)
            finally:
                asked["storing"] = False
            self._line(trial, "DONE", result.get("progress", ""))
            if asked["stop"]:
                raise KeyboardInterrupt

        def on_trial_error(self, iteration: int, trials: Any, trial: Any, **info: Any) -> None:
            if asked["stop"]:
                return
            p = trial.config["point"]
            try:
                error = str(trial.get_error() or "the trial failed")
            except Exception:  # the error file may not be readable yet
                error = "the trial failed"
            record(trials_dir / p["point_id"], p, None, error)
            self._line(trial, "ERROR: " + last_line(error))

    _ray_init(str(cfg.ray.address), cfg.ray.num_cpus)
    previous = signal.signal(signal.SIGINT, on_sigint)
    try:
        storage = (
            Path(str(cfg.storage_path)).expanduser().resolve() if cfg.storage_path else out / "ray"
        )
        tuner = tune.Tuner(
            tune.with_resources(trial, {"cpu": int(cfg.cpus_per_trial)}),
            param_space={"point": tune.grid_search(todo), "cpus": int(cfg.cpus_per_trial)},
            # A worker process runs trial after trial: no process start and imports per trial.
            tune_config=tune.TuneConfig(reuse_actors=True),
            run_config=tune.RunConfig(
                name=f"sweep-{int(time.time())}",
                storage_path=str(storage),
                failure_config=tune.FailureConfig(max_failures=int(cfg.max_failures)),
                verbose=0,
                callbacks=[Progress()],
                stop=StopOnSigint(),
            ),
        )
        results = tuner.fit()
        if asked["stop"]:
            raise KeyboardInterrupt
        for result in (results[i] for i in range(len(results))):
            p = (result.config or {}).get("point")
            if p is not None and read_status(trials_dir / p["point_id"]) is None:
                record(trials_dir / p["point_id"], p, result.metrics, result.error)
    finally:
        signal.signal(signal.SIGINT, previous)
        ray.shutdown()
