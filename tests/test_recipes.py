"""Recipes run end to end from the command line with tiny settings."""

from __future__ import annotations

import csv
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def run_recipe(name: str, *overrides: str, timeout: int = 300) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, str(ROOT / "recipes" / name), *overrides],
        capture_output=True,
        text=True,
        timeout=timeout,
        cwd=ROOT,
    )


def test_demo_prints_metrics(tmp_path):
    out = run_recipe(
        "demo.py",
        "num_envs=16",
        "episodes=16",
        "env=ref_impl",
        "reward.r4=50",
        f"hydra.run.dir={tmp_path}",
    )
    assert out.returncode == 0, out.stderr
    assert "scenario=ref_impl p1.speed=0.5 r4=50.0" in out.stdout
    for name in ("round_robin", "always_radar", "miss_detection", "throughput", "link_capacity"):
        assert name in out.stdout
    # round-robin is radar exactly half the time
    rr = next(line for line in out.stdout.splitlines() if line.startswith("round_robin"))
    assert " 0.5 " in rr


def test_demo_rejects_bad_value(tmp_path):
    out = run_recipe("demo.py", "env.p1.speed=1.5", f"hydra.run.dir={tmp_path}")
    assert out.returncode != 0
    assert "env.p1.speed=1.5" in out.stderr


def test_bench_env_writes_csv(tmp_path):
    out = run_recipe(
        "bench_env.py",
        "sizes=[4,64]",
        "threads=[1]",
        "repeats=2",
        "max_iters=20",
        f"hydra.run.dir={tmp_path}",
    )
    assert out.returncode == 0, out.stderr
    assert "best env throughput" in out.stdout
    rows = list(csv.DictReader((tmp_path / "bench_env.csv").open()))
    assert len(rows) == 2 * 3
    assert all(float(r["median_steps_per_s"]) > 0 for r in rows)
