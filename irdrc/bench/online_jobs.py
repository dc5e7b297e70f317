"""``recipes/bench_online.py``'s runs: one ``Job`` (a learner on a scenario with a seed) run in a
process of its own, ``workers`` at a time, each result kept in ``runs/`` as it finishes. A failed
run, SIGINT or SIGTERM ends every worker at once."""

from __future__ import annotations

import json
import math
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from irdrc.online.configs import SAFE_LEARNERS


@dataclass(frozen=True)
class Job:
    """One run: ``learner`` on ``scenario`` (a named scenario, or ``draw N``) with ``seed``;
    ``target`` for the safe learner and the Lagrangian DQN."""

    learner: str
    scenario: str
    seed: int
    episodes: int
    target: float | None = None
    overrides: dict[str, Any] = field(default_factory=dict)

    @property
    def name(self) -> str:
        """The run's file name in ``runs/``."""
        tail = f"__m{self.target:g}" if self.target is not None else ""
        return f"{self.learner}__{self.scenario.replace(' ', '')}__{self.seed}{tail}"

    @property
    def target_miss(self) -> float:
        """The miss-detection target of a constrained learner's run."""
        if self.target is None:
            raise ValueError(f"{self.learner} runs at a target_miss: give the job one")
        return self.target


def scenario_params(job: Job) -> Any:
    """The job's ``Params``: a named scenario with the paper's reward, or a random draw's keys."""
    from irdrc.core.params import Params

    if job.overrides:
        return Params.from_overrides(job.overrides)
    from irdrc.runs.compose import compose

    cfg = compose("solve", [f"env={job.scenario}"]).cfg
    return Params.from_config({"env": cfg["env"], "reward": cfg["reward"]})


def run_job(job: Job, gamma: float) -> dict[str, Any]:
    """One run in this process: its history and wall time (a learner on one stream), or the
    Lagrangian DQN's cumulative miss detection over its training."""
    import torch

    torch.set_num_threads(1)
    params = scenario_params(job)
    from irdrc.core.exact import exact_scorer

    scorer = exact_scorer(params, gamma)
    t0 = time.perf_counter()
    if job.learner == "dqn_lagrangian":
        from irdrc.agents import lagrangian
        from irdrc.agents.base import Hooks
        from irdrc.agents.configs import LagrangianConfig
        from irdrc.agents.configs.lagrangian import SearchConfig

        trace: list[dict[str, float]] = []
        hooks = Hooks(on_batch=lambda info: trace.append(dict(info)))
        # its training is what is read: the final policy's search after it is kept to one look
        quick = SearchConfig(
            measure_envs=2,
            measure_steps=1,
            measure_burn_in=0,
            measure_max_blocks=1,
            mix_steps=0,
            confirm=False,
        )
        lagrangian.train(
            params,
            LagrangianConfig(target_miss=job.target_miss, search=quick),
            seed=job.seed,
            scorer=scorer,
            hooks=hooks,
        )
        points = [
            {"env_steps": r["env_steps"], "cumulative_miss": r["cumulative_miss"]}
            for r in trace
            if not math.isnan(r["cumulative_miss"])
        ]
        return {"trace": points, "wall_seconds": time.perf_counter() - t0}
    from irdrc.online.configs import learner_config
    from irdrc.online.learners import make_learner
    from irdrc.online.loop import learn_on_stream
    from irdrc.online.recipe import lp_cost
    from irdrc.online.safe import SafeLearner

    algo = {"episodes": job.episodes, **({"target_miss": job.target} if job.target else {})}
    cfg = learner_config(job.learner, algo)
    greedy_scorer = None
    if job.learner in SAFE_LEARNERS:
        from irdrc.online.safe import ConstrainedScorer

        greedy_scorer = ConstrainedScorer(scorer, job.target_miss)
    learner = make_learner(job.learner, cfg, params, job.seed)
    record = learn_on_stream(
        learner, params, scorer, episodes=job.episodes, seed=job.seed, greedy_scorer=greedy_scorer
    )
    return {
        "history": record.history,
        "wall_seconds": record.wall_seconds,
        "seconds_learning": record.info["seconds_episode_start"]
        + record.info["seconds_act_and_learn"]
        + record.info["seconds_episode_end"],
        "slowest_decision": record.info["seconds_slowest_decision"],
        "lp_throughput": greedy_scorer.lp.value if greedy_scorer is not None else None,
        "lp_cost": lp_cost(scorer, greedy_scorer) if greedy_scorer is not None else None,
        "plan_confidence": (
            learner.plan_confidence() if isinstance(learner, SafeLearner) else None
        ),
    }


def _worker_start() -> None:
    """A worker's start: Ctrl-C reaches the whole process group, and the benchmark's own process
    decides; SIGTERM, which it sends to end a worker, releases what the worker holds first."""
    import signal

    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, _worker_end)


def _worker_end(signum: int, frame: Any) -> None:
    """End this worker now, after the finalizers a normal exit runs (the replay buffer's
    semaphores, which the resource tracker would otherwise report as leaked)."""
    import os
    from multiprocessing import util

    util._exit_function()  # type: ignore[attr-defined]  # what a process runs at its exit
    os._exit(128 + signum)


def _end_workers(pool: Any) -> None:
    """Cancel the runs not begun and end the running ones now (their workers' processes)."""
    workers = list((getattr(pool, "_processes", None) or {}).values())
    for worker in workers:
        worker.terminate()
    pool.shutdown(wait=True, cancel_futures=True)  # the pool sees its workers gone, and cleans up


def ran(job: Job, gamma: float) -> dict[str, Any]:
    """What a kept result records of its run: the job and the optimum's discount (as JSON reads
    them back)."""
    return json.loads(json.dumps({**asdict(job), "optimum_gamma": gamma}))


def _same_job(path: Path, stored: dict[str, Any] | None, planned: dict[str, Any]) -> None:
    """Refuse a kept result run with other keys (one written before results recorded their job
    is kept as it is)."""
    if stored is None or stored == planned:
        return
    changed = ", ".join(
        f"{k} {stored.get(k)!r} → {planned.get(k)!r}"
        for k in planned
        if stored.get(k) != planned.get(k)
    )
    raise ValueError(
        f"resume: {path} ran with other keys ({changed}); resume with the keys the benchmark "
        "was started with (resume=true brings them back), or write to another hydra.run.dir"
    )


def execute(
    jobs: list[Job], out: Path, *, workers: int, resume: bool, gamma: float
) -> tuple[dict[str, dict[str, Any]], int]:
    """Run every job not in ``out/runs`` yet (all of them unless ``resume``), ``workers`` at a time
    in processes of their own (the optimum discounted by ``gamma``), keeping each result as it
    finishes, with the job it ran; returns every job's result and how many were kept from an
    earlier invocation. A kept result whose job differs from this invocation's is refused before
    any work. A failed run, SIGINT or SIGTERM ends every worker at once; the results kept so far
    stay, and the message says how to go on."""
    import concurrent.futures as cf
    import multiprocessing

    from irdrc.runs.progress import Ticker
    from irdrc.runs.results import atomic_write_text
    from irdrc.runs.signals import RunInterrupted, Signalled
    from irdrc.sweeps.trials import go_on_command

    runs = out / "runs"
    runs.mkdir(parents=True, exist_ok=True)
    results = {}
    todo = []
    for job in jobs:
        path = runs / f"{job.name}.json"
        if resume and path.is_file():
            results[job.name] = kept = json.loads(path.read_text())
            _same_job(path, kept.get("job"), ran(job, gamma))
        else:
            todo.append(job)
    ticker = Ticker(len(todo), "bench_online", every_seconds=30)
    ctx = multiprocessing.get_context("spawn")
    pool = cf.ProcessPoolExecutor(workers, mp_context=ctx, initializer=_worker_start)
    try:
        futures = {pool.submit(run_job, job, gamma): job for job in todo}
        for fut in cf.as_completed(futures):
            job = futures[fut]
            try:
                result = fut.result()
            except Exception as err:
                raise RuntimeError(f"bench_online: run {job.name} failed: {err}") from err
            kept = {**result, "job": ran(job, gamma)}
            atomic_write_text(runs / f"{job.name}.json", json.dumps(_clean(kept)))
            results[job.name] = result
            ticker.tick()
    except Signalled as sig:
        _end_workers(pool)
        raise RunInterrupted(
            f"stopped by {sig}: {len(results)} of {len(jobs)} runs are kept in {runs}; go on "
            f"with: {go_on_command(out, 'bench_online')}",
            128 + sig.signum,
        ) from None
    except BaseException:
        _end_workers(pool)
        raise
    pool.shutdown()
    return results, len(jobs) - len(todo)


def _clean(x: Any) -> Any:
    """NaN as None (JSON)."""
    if isinstance(x, float) and math.isnan(x):
        return None
    if isinstance(x, dict):
        return {k: _clean(v) for k, v in x.items()}
    if isinstance(x, list):
        return [_clean(v) for v in x]
    return x
