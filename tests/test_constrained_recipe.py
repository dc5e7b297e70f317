"""recipes/constrained.py: the exact constrained optimum's files, the frontier, and refusals."""

from __future__ import annotations

import csv
import json
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def run(tmp_path, *overrides):
    return subprocess.run(
        [
            sys.executable,
            str(ROOT / "recipes" / "constrained.py"),
            *overrides,
            f"hydra.run.dir={tmp_path}",
        ],
        capture_output=True,
        text=True,
        timeout=600,
        cwd=ROOT,
    )


def test_single_target_writes_the_lp_optimum(tmp_path):
    res = run(tmp_path, "target_miss=0.05")
    assert res.returncode == 0, res.stderr
    s = json.loads((tmp_path / "summary.json").read_text())
    assert s["method"] == "constrained" and s["target_miss"] == 0.05
    assert s["optimal"]["miss_detection"] <= 0.05
    assert s["optimal"]["throughput"] > 0.3  # the LP uses the queue: far above radar-always's 0
    assert s["metrics"] == s["optimal"]
    assert s["randomised_states"] >= 1
    assert s["reward_optimal"]["miss_detection"] > 0.05
    rows = list(csv.DictReader((tmp_path / "policy.csv").open()))
    assert list(rows[0]) == ["d", "c", "r", "w", "v", "m", "action", "p_radar"]
    fractional = [r for r in rows if 0 < float(r["p_radar"]) < 1]
    assert len(fractional) == s["randomised_states"]
    assert "radar with probability" in res.stdout


def test_frontier_writes_csvs_figure_and_the_r4_table(tmp_path):
    res = run(
        tmp_path,
        "frontier=true",
        "frontier_grid.p1_speed=[0.1]",
        "frontier_grid.points=3",
        "frontier_grid.r4.lo=40",
        "frontier_grid.r4.hi=50",
        "frontier_grid.r4.step=10",
        "frontier_grid.targets=[0.05]",
    )
    assert res.returncode == 0, res.stderr
    rows = list(csv.DictReader((tmp_path / "frontier.csv").open()))
    assert {r["route"] for r in rows} == {"lp", "r4"}
    assert len([r for r in rows if r["route"] == "r4"]) == 2
    gap = list(csv.DictReader((tmp_path / "frontier_gap.csv").open()))
    assert len(gap) == 1
    # At p1.speed = 0.1 the reward route meets 5 % only with radar always (r4 = 50): no data.
    assert float(gap[0]["r4_throughput"]) == 0.0
    assert float(gap[0]["lp_throughput"]) > 0.3
    assert (tmp_path / "frontier.png").stat().st_size > 10_000


def test_bad_and_infeasible_targets_refused_before_work(tmp_path):
    res = run(tmp_path / "a", "target_miss=1.5")
    assert res.returncode == 2 and "target_miss" in res.stderr and "Traceback" not in res.stderr
    assert not (tmp_path / "a").exists()
    res = run(tmp_path / "b", "target_miss=0.0", "max_drop=0.01")
    assert res.returncode == 2 and "max_drop" in res.stderr, res.stderr
    assert not (tmp_path / "b").exists()
