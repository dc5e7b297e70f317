"""The exact solver at scale (``recipes/bench_scale.py``): wall time and peak memory of an exact
solve — value iteration to ``tol`` on the factored operator and the exact long-run metrics of the
resulting policy — against S, for every scenario asked, with the dense solver (S × S matrices)
measured in the same run where it fits.

Each measurement runs in a fresh Python process, so its peak resident memory (``ru_maxrss``) is its
own; the memory after the imports alone is reported beside it.
"""

from __future__ import annotations

import json
import math
import statistics
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

from omegaconf import DictConfig

from irdrc.core.params import to_plain
from irdrc.experiments.results import write_rows_csv, write_table_md

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


def _configs(scenario: str) -> int:
    """F = Π L of a scenario (v1: 32)."""
    from irdrc.core.params import Params
    from irdrc.experiments.config import compose

    return math.prod(Params.from_config(compose("solve", [f"env={scenario}"])).env.levels)


def measure_once(scenario: str, queue: int, solver: str, device: str, tol: float) -> dict:
    """One exact solve in this process (see the module docstring); what the child prints."""
    import resource

    import torch

    from irdrc.core.params import Params
    from irdrc.experiments.config import compose

    torch.set_num_threads(1)
    rss0 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    params = Params.from_config(
        compose("solve", [f"env={scenario}", f"env.queue_capacity={queue}"])
    )
    t0 = time.perf_counter()
    if solver == "dense":
        from irdrc.core.model import build_model
        from irdrc.core.solve import stationary_metrics, value_iteration

        model = build_model(params)
        sol = value_iteration(model, tol=tol)
        m = stationary_metrics(model, sol.policy)
        sweeps, steps = sol.iterations, 0
    else:
        from irdrc.core.factored import (
            build_factored,
            stationary_distribution_factored,
            stationary_metrics_factored,
            value_iteration_factored,
        )

        model = build_factored(params, device=device)
        sol = value_iteration_factored(model, tol=tol)
        mu, steps = stationary_distribution_factored(model, sol.policy)
        m = stationary_metrics_factored(model, sol.policy, mu=mu)
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


def _child(scenario: str, queue: int, solver: str, device: str, tol: float, timeout: float):
    cmd = [
        sys.executable,
        "-m",
        "irdrc.experiments.bench_scale",
        json.dumps([scenario, queue, solver, device, tol]),
    ]
    res = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout)
    if res.returncode != 0:
        raise RuntimeError(res.stderr.strip().splitlines()[-1] if res.stderr else "failed")
    return json.loads(res.stdout.strip().splitlines()[-1])


def growth_exponents(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Per (scenario, solver, device) measured at two sizes or more: k of time ∝ S^k, the
    least-squares slope of log(median s) on log(S) over every size, and between the two largest."""
    out = []
    keys = list(dict.fromkeys((r["scenario"], r["solver"], r["device"]) for r in rows))
    for key in keys:
        pts = sorted(
            (r["num_states"], r["median_seconds"])
            for r in rows
            if (r["scenario"], r["solver"], r["device"]) == key and r["median_seconds"] > 0
        )
        if len(pts) < 2:
            continue
        xs = [math.log(S) for S, _ in pts]
        ys = [math.log(t) for _, t in pts]
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
                "sizes": [S for S, _ in pts],
                "k_fit": fit,
                "k_last": last,
            }
        )
    return out


def run_bench_scale(cfg: DictConfig, out: Path) -> int:
    """Every (scenario, S, solver[, device]) of ``cfg``: ``repeats`` fresh-process solves, median
    wall time, peak memory; the table printed and written as CSV and Markdown."""
    start = time.perf_counter()
    import torch

    from irdrc.core.model import DENSE_MODEL_LIMIT_BYTES

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    devices = ["cpu"] + (["cuda"] if bool(cfg.gpu) and torch.cuda.is_available() else [])
    rows: list[dict[str, Any]] = []
    header = (
        f"{'scenario':>12} {'solver':>8} {'device':>6} {'S':>9} {'median s':>9} {'sweeps':>7} "
        f"{'stat. steps':>11} {'peak MB':>8}"
    )
    print(header, flush=True)
    skipped: list[str] = []
    for scenario in to_plain(cfg.scenarios):
        slow = False
        configs = _configs(scenario)
        for states in to_plain(cfg.states):
            queue = _queue_for(int(states), configs)
            S = (queue + 1) * configs
            if slow:
                skipped.append(f"{scenario} at S = {S:,}")
                print(
                    f"{scenario:>12}  skipped at S = {S}: the previous size took more than "
                    f"{float(cfg.skip_after_seconds):g} s",
                    flush=True,
                )
                continue
            runs = [("factored", d) for d in devices]
            if 16 * S * S <= DENSE_MODEL_LIMIT_BYTES:
                runs.insert(0, ("dense", "cpu"))
            for solver, device in runs:
                got = [
                    _child(scenario, queue, solver, device, float(cfg.tol), float(cfg.timeout))
                    for _ in range(int(cfg.repeats))
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
                    solver == "factored" and row["median_seconds"] > float(cfg.skip_after_seconds)
                )
                print(
                    f"{scenario:>12} {solver:>8} {device:>6} {S:>9} {row['median_seconds']:>9.2f} "
                    f"{row['sweeps']:>7} {row['stationary_steps']:>11} {row['peak_rss_mb']:>8.0f}",
                    flush=True,
                )
    write_rows_csv(out / cfg.csv, rows, COLUMNS)
    lines = [
        "| scenario | solver | device | S | median s (of "
        f"{int(cfg.repeats)}) | value-iteration sweeps | stationary steps | peak memory (MB; "
        "after imports) |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r['scenario']} | {r['solver']} | {r['device']} | {r['num_states']:,} | "
            f"{r['median_seconds']:.2f} | {r['sweeps']} | {r['stationary_steps']} | "
            f"{r['peak_rss_mb']:.0f} ({r['import_rss_mb']:.0f}) |"
        )
    growth = growth_exponents(rows)
    if growth:
        lines += [
            "",
            "| scenario | solver | device | S measured | time ∝ S^k: k fitted over them | k between "
            "the two largest |",
            "|---|---|---|---|---|---|",
        ]
        for g in growth:
            lines.append(
                f"| {g['scenario']} | {g['solver']} | {g['device']} | "
                f"{', '.join(f'{S:,}' for S in g['sizes'])} | {g['k_fit']:.2f} | {g['k_last']:.2f} |"
            )
    if skipped:
        lines.append(
            f"\nNot run (the size before took more than {float(cfg.skip_after_seconds):g} s): "
            + "; ".join(skipped)
            + "."
        )
    write_table_md(out / "bench_scale.md", "\n".join(lines), time.perf_counter() - start)
    print(f"\nwrote {out / cfg.csv} and {out / 'bench_scale.md'}")
    return 0


if __name__ == "__main__":
    args = json.loads(sys.argv[1])
    print(json.dumps(measure_once(*args)))
