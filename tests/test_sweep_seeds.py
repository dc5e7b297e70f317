"""A sweep over seeds: mean and 95 % interval per point, banded learning curves, legends that name
only what differs (``irdrc.sweeps.seeds``)."""

from __future__ import annotations

import csv
from pathlib import Path

import pytest


def rows(path: Path) -> list[dict]:
    with open(path) as f:
        return list(csv.DictReader(f))


def test_seed_statistics_per_point_and_banded_curves(tmp_path):
    """A grid over seeds: ``summary_by_point.csv`` has, per point without its seed, the mean and
    the 95 % t half-width over the DONE seeds (an ERROR seed left out); ``learning_curves.png``
    bands the curves read from each trial's metrics.csv. Numbers computed by hand."""
    from irdrc.sweeps.seeds import plot_seed_curves, write_seed_summary

    ratios = {
        ("5", "0"): 0.9,
        ("5", "1"): 1.0,
        ("5", "2"): 0.95,
        ("50", "0"): 0.8,
        ("50", "1"): 0.7,
    }
    lines = ["reward.r4,seed,status,point_id,optimality_ratio,env_steps,wall_seconds"]
    for (r4, seed), ratio in ratios.items():
        pid = f"p{r4}_{seed}"
        lines.append(f"{r4},{seed},DONE,{pid},{ratio},1000,1.0")
        (tmp_path / "trials" / pid).mkdir(parents=True)
        (tmp_path / "trials" / pid / "metrics.csv").write_text(
            f"learner,env_steps,optimality_ratio\n0,0,0.5\n0,1000,{ratio}\n"
        )
    lines.append("50,2,ERROR,p50_2,,,")
    (tmp_path / "summary.csv").write_text("\n".join(lines) + "\n")
    path = write_seed_summary(tmp_path / "summary.csv", tmp_path)
    table = {r["reward.r4"]: r for r in rows(path)}
    assert table["5"]["seeds"] == "3" and table["5"]["done"] == "3"
    assert float(table["5"]["optimality_ratio_mean"]) == pytest.approx(0.95)
    # sd 0.05 over 3 seeds: 4.303 · 0.05 / √3
    assert float(table["5"]["optimality_ratio_ci95"]) == pytest.approx(0.1242, abs=1e-4)
    assert table["50"]["done"] == "2" and float(
        table["50"]["optimality_ratio_mean"]
    ) == pytest.approx(0.75)
    # sd 0.0707 over 2 seeds: 12.706 · 0.0707 / √2
    assert float(table["50"]["optimality_ratio_ci95"]) == pytest.approx(0.6353, abs=1e-3)
    png = plot_seed_curves(tmp_path / "summary.csv", tmp_path / "trials", tmp_path)
    assert png is not None and png.read_bytes()[:4] == b"\x89PNG"
    (tmp_path / "nogrid.csv").write_text("reward.r4,status,point_id\n5,DONE,x\n")
    assert write_seed_summary(tmp_path / "nogrid.csv", tmp_path / "x") is None


def test_seed_curve_labels_leave_out_what_every_point_shares():
    """A benchmark's points differ by method and a few overrides; the legend names only those."""
    from irdrc.sweeps.seeds import series_labels

    points = [
        {"method": "sac", "base": "env.p1.speed=1.0 optimum_gamma=0.99"},
        {"method": "dqn", "base": "env.p1.speed=1.0 env.actions=levels optimum_gamma=0.99"},
    ]
    assert series_labels(points) == ["method=sac", "method=dqn, env.actions=levels"]
    assert series_labels([{"reward.r4": "5"}]) == ["all"]
