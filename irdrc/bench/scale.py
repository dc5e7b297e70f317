"""``recipes/bench_scale.py``: the exact solver at scale — wall time and peak memory of an exact
solve (value iteration to ``tol`` and the exact long-run metrics of the resulting policy) against
S, for every scenario asked, on the factored operator, and on the dense model (S × S matrices)
where it fits, measured in the same run.

Each measurement runs in a fresh Python process, so its peak resident memory (``ru_maxrss``) is its
own; the memory after the imports alone is reported beside it.

    python recipes/bench_scale.py                    # SCALE.md's table
    python recipes/bench_scale.py 'scenarios=[large]' 'states=[1000,10000]'
"""

from __future__ import annotations

import json
import math
import statistics
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from irdrc.core import checks
from irdrc.runs.compose import Composed, compose
from irdrc.runs.results import md_table, write_rows_csv, write_table_md
from irdrc.runs.sections import one_vehicle_scenarios

if TYPE_CHECKING:
    from irdrc.core.params import Params
    from irdrc.runs.scaffold import Run

NAME = "bench_scale"

COLUMNS = (
    "scenario",
    "solver",
    "device",
    "num_states",
    "queue_capacity",
    "median_seconds",
    "min_seconds",
    "max_seconds",
    "repeats",
    "sweeps",
    "stationary_steps",
    "peak_rss_mb",
    "import_rss_mb",
    "avg_reward",
    "throughput",
)


def _queue_for(states: int, configs: int = 32) -> int:
    """The queue capacity D whose S = (D + 1)·F is the smallest ≥ ``states`` (F = ``configs``,
    the scenario's factor configurations)."""
    return max(1, math.ceil(states / configs) - 1)


def scenario_params(scenario: str, queue: int | None = None) -> Params:
    """The model of a named scenario (its queue capacity set, when given)."""
    from irdrc.recipes import solve

    extra = [f"env.queue_capacity={queue}"] if queue is not None else []
    return solve.load(compose("solve", [f"env={scenario}", *extra])).model


def _configs(scenario: str) -> int:
    """F = Π L of a scenario (v1: 32)."""
    return math.prod(scenario_params(scenario).env.factor_levels)


def measure_once(scenario: str, queue: int, solver: str, device: str, tol: float) -> dict[str, Any]:
    """One exact solve in this process (see the module docstring); what the child prints."""
    import resource

    import torch

    from irdrc.core.exact import (
        as_probs,
        build_factored,
        build_model,
        metrics_from_occupancy,
        stationary_distribution_factored,
        stationary_metrics,
        value_iteration,
    )

    torch.set_num_threads(1)
    rss0 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    params = scenario_params(scenario, queue)
    t0 = time.perf_counter()
    if solver == "dense":
        model = build_model(params)
        sol = value_iteration(model, tol=tol)
        m = stationary_metrics(model, sol.policy)
        sweeps, steps = sol.iterations, 0
    else:
        factored = build_factored(params, device=device)
        sol = value_iteration(factored, tol=tol)
        mu, steps = stationary_distribution_factored(factored, sol.policy)
        probs = as_probs(sol.policy, factored.num_states, factored.num_actions).to(mu.device)
        m = metrics_from_occupancy(factored, (mu[:, None] * probs).T.contiguous())
        sweeps = sol.iterations
        if device != "cpu":
            torch.cuda.synchronize()
    wall = time.perf_counter() - t0
    return {
        "seconds": wall,
        "sweeps": sweeps,
        "stationary_steps": steps,
        "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
        "import_rss_mb": rss0,
        "avg_reward": m.avg_reward,
        "throughput": m.throughput,
    }


def _child(
    scenario: str, queue: int, solver: str, device: str, tol: float, timeout: float
) -> dict[str, Any]:
    cmd = [
        sys.executable,
        "-m",
        "irdrc.bench.scale",
        json.dumps([scenario, queue, solver, device, tol]),
    ]
    res = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout)
    if res.returncode != 0:
        raise RuntimeError(res.stderr.strip().splitlines()[-1] if res.stderr else "failed")
    return json.loads(res.stdout.strip().splitlines()[-1])


def growth_exponents(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Per (scenario, solver, device) measured at two sizes or more: k of time ∝ S^k, the
    least-squares slope of log(median s) on log(S) over every size (rows of one size averaged in
    the log), and between the two largest."""
    out = []
    keys = list(dict.fromkeys((r["scenario"], r["solver"], r["device"]) for r in rows))
    for key in keys:
        pts = sorted(
            (r["num_states"], r["median_seconds"])
            for r in rows
            if (r["scenario"], r["solver"], r["device"]) == key and r["median_seconds"] > 0
        )
        by_size: dict[int, list[float]] = {}
        for S, t in pts:  # two requested sizes can build one state space
            by_size.setdefault(S, []).append(math.log(t))
        if len(by_size) < 2:
            continue
        xs = [math.log(S) for S in by_size]
        ys = [statistics.fmean(ts) for ts in by_size.values()]
        mx, my = statistics.fmean(xs), statistics.fmean(ys)
        fit = sum((x - mx) * (y - my) for x, y in zip(xs, ys, strict=True)) / sum(
            (x - mx) ** 2 for x in xs
        )
        last = (ys[-1] - ys[-2]) / (xs[-1] - xs[-2])
        out.append(
            {
                "scenario": key[0],
                "solver": key[1],
                "device": key[2],
                "sizes": list(by_size),
                "k_fit": fit,
                "k_last": last,
            }
        )
    return out


@dataclass(frozen=True)
class Config:
    """The benchmark's keys (``irdrc/conf/bench_scale.yaml``)."""

    scenarios: tuple[str, ...] = ("paper", "large")
    states: tuple[int, ...] = (1000, 10_000, 100_000, 1_000_000)
    tol: float = 1e-6
    repeats: int = 3
    timeout: float = 1800.0
    skip_after_seconds: float = 60.0
    gpu: bool = True
    csv: str = "bench_scale.csv"

    def __post_init__(self) -> None:
        object.__setattr__(self, "scenarios", one_vehicle_scenarios("scenarios", self.scenarios))
        checks.check_file_name("csv", self.csv)
        sizes = checks.check_list(
            "states", self.states, checks.numbers(64, 32 * 10**6, integer=True), distinct=True
        )
        object.__setattr__(self, "states", sizes)
        checks.check_numbers(
            self,
            "",
            (
                ("tol", 0, 1, {"open_lo": True}),
                ("repeats", 1, 1000, checks.INT),
                ("timeout", 1, 10**6, {}),
                ("skip_after_seconds", 0, 10**9, {}),
            ),
        )
        checks.check_bool("gpu", self.gpu)


def load(composed: Composed, resume: dict[str, Any] | None = None) -> Config:
    """The typed config, checked."""
    return checks.build(Config, composed.cfg)


def run(cfg: Config, run: Run) -> int:
    """Every (scenario, S, solver[, device]): ``repeats`` fresh-process solves, median wall time,
    peak memory; the table printed and written as CSV and Markdown."""
    run_bench_scale(cfg, run.dir)
    run.finish(None)
    return 0


def run_bench_scale(cfg: Config, out: Path) -> None:
    """The benchmark (see ``run``) into ``out``."""
    start = time.perf_counter()
    import torch

    from irdrc.core.sizes import DENSE_LIMIT_BYTES

    devices = ["cpu"] + (["cuda"] if cfg.gpu and torch.cuda.is_available() else [])
    rows: list[dict[str, Any]] = []
    header = (
        f"{'scenario':>12} {'solver':>8} {'device':>6} {'S':>9} {'median s':>9} {'sweeps':>7} "
        f"{'stat. steps':>11} {'peak MB':>8}"
    )
    print(header, flush=True)
    skipped: list[str] = []
    for scenario in cfg.scenarios:
        slow = False
        configs = _configs(scenario)
        for states in cfg.states:
            queue = _queue_for(int(states), configs)
            S = (queue + 1) * configs
            if slow:
                skipped.append(f"{scenario} at S = {checks.grouped(S)}")
                print(
                    f"{scenario:>12}  skipped at S = {checks.grouped(S)}: the previous size took more than "
                    f"{cfg.skip_after_seconds:g} s",
                    flush=True,
                )
                continue
            runs = [("factored", d) for d in devices]
            if 16 * S * S <= DENSE_LIMIT_BYTES:
                runs.insert(0, ("dense", "cpu"))
            for solver, device in runs:
                got = [
                    _child(scenario, queue, solver, device, cfg.tol, cfg.timeout)
                    for _ in range(cfg.repeats)
                ]
                secs = [g["seconds"] for g in got]
                row = {
                    "scenario": scenario,
                    "solver": solver,
                    "device": device,
                    "num_states": S,
                    "queue_capacity": queue,
                    "median_seconds": statistics.median(secs),
                    "min_seconds": min(secs),
                    "max_seconds": max(secs),
                    "repeats": len(secs),
                    "sweeps": got[0]["sweeps"],
                    "stationary_steps": got[0]["stationary_steps"],
                    "peak_rss_mb": max(g["peak_rss_mb"] for g in got),
                    "import_rss_mb": min(g["import_rss_mb"] for g in got),
                    "avg_reward": got[0]["avg_reward"],
                    "throughput": got[0]["throughput"],
                }
                rows.append(row)
                slow = slow or (
                    solver == "factored" and row["median_seconds"] > cfg.skip_after_seconds
                )
                print(
                    f"{scenario:>12} {solver:>8} {device:>6} {S:>9} {row['median_seconds']:>9.2f} "
                    f"{row['sweeps']:>7} {row['stationary_steps']:>11} {row['peak_rss_mb']:>8.0f}",
                    flush=True,
                )
    write_rows_csv(out / cfg.csv, rows, COLUMNS)
    table = md_table(
        [
            "scenario",
            "solver",
            "device",
            "S",
            f"median s (of {cfg.repeats})",
            "value-iteration sweeps",
            "stationary steps",
            "peak memory (MB; after imports)",
        ],
        [
            [
                r["scenario"],
                r["solver"],
                r["device"],
                checks.grouped(r["num_states"]),
                f"{r['median_seconds']:.2f}",
                r["sweeps"],
                r["stationary_steps"],
                f"{r['peak_rss_mb']:.0f} ({r['import_rss_mb']:.0f})",
            ]
            for r in rows
        ],
    )
    growth = growth_exponents(rows)
    if growth:
        table += "\n\n" + md_table(
            [
                "scenario",
                "solver",
                "device",
                "S measured",
                "time ∝ S^k: k fitted over them",
                "k between the two largest",
            ],
            [
                [
                    g["scenario"],
                    g["solver"],
                    g["device"],
                    ", ".join(checks.grouped(S) for S in g["sizes"]),
                    f"{g['k_fit']:.2f}",
                    f"{g['k_last']:.2f}",
                ]
                for g in growth
            ],
        )
    if skipped:
        table += (
            f"\n\nNot run (the size before took more than {cfg.skip_after_seconds:g} s): "
            + "; ".join(skipped)
            + "."
        )
    write_table_md(out / "bench_scale.md", table, time.perf_counter() - start)


if __name__ == "__main__":
    args = json.loads(sys.argv[1])
    print(json.dumps(measure_once(*args)))
