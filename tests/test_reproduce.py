"""Figure 2 and the trade-off: claims logic on synthetic numbers, statistics helpers, the bisection on
the exact solver, and both recipes end to end with tiny settings."""

from __future__ import annotations

import csv
import json
import math
import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest

from irdrc import Params
from irdrc.core.metrics import first_reaching
from irdrc.paper import claims as cl
from irdrc.paper.figures import band_rows, mean_ci, moving_average, t975
from irdrc.paper.tradeoff import smallest_r4
from irdrc.recipes.constrained.frontier import optimal_at

ROOT = Path(__file__).resolve().parents[1]
P = [0.1, 0.4, 0.7, 1.0]


def numbers(**changes) -> cl.FigureNumbers:
    """Synthetic numbers for which every claim holds; ``changes`` break some."""
    n = cl.FigureNumbers(
        optimum_episode=360.0,
        round_robin_episode=30.0,
        final_episode={"dqn": 358.0, "qlearning": 350.0},
        episodes_to_95={"dqn": 170.0, "qlearning": 280.0},
        p1_speed=P,
        sweep={
            "dqn": {
                "avg_reward": [0.9, 1.1, 1.4, 1.8],
                "throughput": [0.9, 0.9, 0.9, 0.9],
                "link_capacity": [2.4, 2.4, 2.4, 2.4],
                "miss_detection": [0.29, 0.25, 0.2, 0.16],
            },
            "round_robin": {
                "avg_reward": [0.08, -0.4, -0.9, -1.4],
                "throughput": [0.5, 0.5, 0.5, 0.5],
                "link_capacity": [1.9, 1.9, 1.9, 1.9],
                "miss_detection": [0.5, 0.5, 0.5, 0.5],
            },
        },
        r4_miss={5.0: 0.29, 50.0: 0.1, 100.0: 0.05},
    )
    for k, v in changes.items():
        setattr(n, k, v)
    return n


def verdicts(n: cl.FigureNumbers) -> dict[tuple[str, str], str]:
    return {(v.claim.split(".")[0], v.subject): v.verdict for v in cl.check_claims(n)}


def test_every_claim_holds_on_numbers_made_to_hold():
    got = verdicts(numbers())
    assert set(got.values()) == {cl.HOLDS}, got
    # one verdict per (claim, subject): 1a, 1b ×2, 1c, 2a, 2b, 2c ×2, 2d, 2e, 2f, 3
    assert len(got) == 12


@pytest.mark.parametrize(
    ("changes", "broken"),
    [
        # Q-learning ends 10 % of the optimum below DQN: not "the same total reward"
        ({"final_episode": {"dqn": 358.0, "qlearning": 322.0}}, [("1a", "dqn vs qlearning")]),
        # closes only 40 % of the gap from round-robin (30) to the optimum (360)
        (
            {"final_episode": {"dqn": 358.0, "qlearning": 162.0}},
            [("1a", "dqn vs qlearning"), ("1b", "qlearning")],
        ),
        # DQN slower than Q-learning, or never there
        ({"episodes_to_95": {"dqn": 300.0, "qlearning": 280.0}}, [("1c", "dqn vs qlearning")]),
        ({"episodes_to_95": {"dqn": None, "qlearning": 280.0}}, [("1c", "dqn vs qlearning")]),
        # the optimum's r4 = 100 misses more than r4 = 5
        ({"r4_miss": {5.0: 0.29, 50.0: 0.1, 100.0: 0.3}}, [("3", "optimal")]),
    ],
)
def test_each_claim_fails_when_its_numbers_do(changes, broken):
    got = verdicts(numbers(**changes))
    assert sorted(k for k, v in got.items() if v == cl.FAILS) == sorted(broken), got


def test_sweep_claims_fail_on_their_own_numbers():
    n = numbers()
    n.sweep["dqn"]["avg_reward"] = [0.9, 1.1, 0.8, 0.85]  # down at the end, ρ = −0.6
    n.sweep["dqn"]["throughput"] = [0.502, 0.9, 0.9, 0.9]  # a tie (0.4 % better) at p = 0.1
    n.sweep["dqn"]["miss_detection"] = [
        0.29,
        0.3,
        0.31,
        0.12,
    ]  # ends lower but ρ = −0.2; 0.12 < 0.15
    n.sweep["round_robin"]["avg_reward"] = [0.0, 0.1, 0.2, 0.3]
    got = verdicts(n)
    assert sorted(k for k, v in got.items() if v == cl.FAILS) == sorted(
        [
            ("2a", "dqn"),
            ("2b", "round_robin"),
            ("2c", "dqn (packets sent)"),
            ("2e", "dqn"),
            ("2f", "dqn"),
        ]
    ), got


def test_untested_without_the_needed_numbers():
    got = verdicts(
        numbers(
            final_episode={"dqn": 358.0}, episodes_to_95={"dqn": 170.0}, p1_speed=[0.1], r4_miss={}
        )
    )
    assert got[("1a", "-")] == got[("3", "optimal")] == cl.UNTESTED
    assert got[("1c", "-")] == got[("2", "-")] == cl.UNTESTED
    table = cl.format_claims(cl.check_claims(numbers()))
    assert table.startswith("| claim | subject | measured | verdict |") and "**holds**" in table


def test_spearman_and_trend():
    assert cl.spearman([1, 2, 3, 4], [10, 20, 30, 40]) == pytest.approx(1.0)
    assert cl.spearman([1, 2, 3, 4], [4, 3, 2, 1]) == pytest.approx(-1.0)
    assert cl.spearman([1, 2, 3], [1, 1, 2]) == pytest.approx(math.sqrt(3) / 2)  # tie: avg ranks
    assert math.isnan(cl.spearman([1, 2, 3], [5, 5, 5]))
    ok, msg = cl.trend([1, 2, 3], [5, 5, 5], +1)
    assert not ok and "constant" in msg


def test_statistics_helpers():
    assert t975(1) == pytest.approx(12.706) and t975(4) == pytest.approx(2.776)
    assert t975(1000) == pytest.approx(1.96, abs=1e-3)
    s = mean_ci([1.0, 2.0, 3.0, 4.0, 5.0])
    # sd = √2.5, half-width = 2.776 · √2.5 / √5
    assert s["mean"] == 3.0 and s["hi"] - 3.0 == pytest.approx(2.776 * math.sqrt(0.5))
    assert mean_ci([float("nan"), 2.0])["n"] == 1 and mean_ci([])["n"] == 0
    assert moving_average([1, 2, 3, 4], 2) == [1.0, 1.5, 2.5, 3.5]
    rows = band_rows("x", [0, 10, 20], [[0, 5, 9], [0, 7, 11]])
    assert [r["mean"] for r in rows] == [0, 6, 10]
    assert first_reaching(rows, 6, value="mean", at="x") == 10
    assert first_reaching(rows, 11, value="mean", at="x") is None


def test_panel_bands_are_bounded_with_bursty_arrivals_too():
    """Panels (b)-(d) clip each band to the range its metric lies in; throughput's was the arrival
    rate, which bursty arrivals leave unset (None), and figure2.py on such a scenario failed at its
    panels ('<' between None and float). The bound is then the largest phase's rate."""
    from irdrc.paper.panels import value_bounds

    assert value_bounds(Params().env)["throughput"] == (0.0, 1.0)
    bursty = Params.from_overrides(
        {
            "env.arrival_rate": None,
            "env.bursty": {"rates": [0.5, 2.0], "transition": [[0.9, 0.1], [0.2, 0.8]]},
        }
    )
    bounds = value_bounds(bursty.env)
    assert bounds["throughput"] == (0.0, 2.0) and bounds["miss_detection"] == (0.0, 1.0)
    rows = band_rows("x", [0.1], [[3.0], [2.5]], bounds["throughput"])
    assert rows[0]["hi"] == 2.0


def test_the_report_prints_values_below_the_solves_accuracy_as_such():
    from irdrc.paper.report import _fmt

    # an always-radar DQN's exact throughput is 0 up to float noise (1e-15)
    assert [_fmt(v) for v in (1.068e-15, -1.0e-15, 0.0, 0.03699, "7")] == [
        "<1e-12",
        "<1e-12",
        "0",
        "0.03699",
        "7",
    ]


def test_bisection_on_a_step_function():
    calls = []

    def miss(r4):
        calls.append(r4)
        return 0.3 if r4 < 41.5 else 0.0

    r4, n = smallest_r4(miss, 0.05, lo=0.5, hi=200, resolution=0.5)
    assert r4 == 41.5 and n == len(calls) <= 2 + math.ceil(math.log2(400))
    assert smallest_r4(miss, 0.05, lo=50, hi=60, resolution=1)[0] == 50  # lo already meets it
    assert smallest_r4(miss, -1, lo=1, hi=60, resolution=1)[0] is None  # nothing does


def test_bisection_on_the_exact_solver_meets_the_target_and_its_neighbour_does_not():
    """Paper scenario: the smallest integer r4 whose optimal policy misses ≤ 5 % of events."""
    params = Params()
    r4, _ = smallest_r4(lambda r: optimal_at(params, r, 0.99)[1].miss_detection, 0.05, 1, 200, 1)
    assert r4 is not None and 5 < r4 <= 50  # r4 = 5 misses 0.289; r4 = 50 is radar everywhere
    assert optimal_at(params, r4, 0.99)[1].miss_detection <= 0.05
    assert optimal_at(params, r4 - 1, 0.99)[1].miss_detection > 0.05


def _run(
    script: str, out: Path, *overrides: str, netns: bool = False
) -> subprocess.CompletedProcess:
    cmd = [sys.executable, str(ROOT / "recipes" / script), *overrides, f"hydra.run.dir={out}"]
    if netns:
        cmd = ["unshare", "-n", "sh", "-c", f"ip link set lo up; exec {shlex.join(cmd)}"]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=600, cwd=ROOT)


TINY_FIGURE = [
    "seeds=[0,1]",
    "p1_speed=[0.1,1.0]",
    "env.horizon=100",
    "learners.dqn.overrides=['algo=dqn','eval.every_frames=400','algo.num_envs=8','algo.frames_per_batch=32','algo.total_frames=800','algo.init_random_frames=128','algo.batch_size=32']",
    "learners.dqn_paper.overrides=['algo=dqn_paper','algo.total_frames=400']",
    "learners.qlearning.overrides=['algo=qlearning','algo.episodes=4','eval.every_frames=200']",
    "learners.qlearning_paper.overrides=['algo=qlearning_paper','algo.episodes=4','eval.every_frames=200']",
]
FIGURE_FILES = [
    *(f"panel_{p}.{ext}" for p in "abcd" for ext in ("png", "csv")),
    "claims.md",
    "claims.csv",
    "summary.json",
    "summary.csv",
]


def _check_figure(out: Path) -> None:
    for name in FIGURE_FILES:
        assert (out / name).is_file() and (out / name).stat().st_size > 0, name
    s = json.loads((out / "summary.json").read_text())
    # 2 seeds × (2 p values for dqn + 1 for dqn_paper) DQN runs + one batch per Q-learning profile
    assert s["training_runs"] == 8 and s["p1_speed"] == [0.1, 1.0]
    assert set(s["final_episode_reward"]) == {"dqn", "dqn_paper", "qlearning", "qlearning_paper"}
    rows = list(csv.DictReader((out / "panel_b.csv").open()))
    series = {r["series"] for r in rows}
    assert series == {"dqn", "qlearning", "qlearning_paper", "optimal", "round_robin"}
    opt = {float(r["x"]): float(r["mean"]) for r in rows if r["series"] == "optimal"}
    # the exact optimum at p = 0.1 (paper scenario, any horizon: stationary)
    assert opt[0.1] == pytest.approx(0.8985, abs=1e-4)
    for r in rows:
        if r["series"] in ("dqn", "qlearning"):
            assert r["n"] == "2" and float(r["mean"]) <= opt[float(r["x"])] + 1e-9
    c = list(csv.DictReader((out / "panel_c.csv").open()))
    assert {r["metric"] for r in c} == {"throughput", "link_capacity"}
    a = list(csv.DictReader((out / "panel_a.csv").open()))
    assert {r["view"] for r in a} == {"greedy_exact", "training_smoothed", "reference"}
    claims = list(csv.DictReader((out / "claims.csv").open()))
    assert {r["verdict"] for r in claims} <= {cl.HOLDS, cl.FAILS, cl.UNTESTED}
    assert any(r["claim"].startswith("3.") and r["verdict"] == cl.HOLDS for r in claims)


@pytest.fixture(scope="module")
def tiny_figure(tmp_path_factory) -> tuple[Path, subprocess.CompletedProcess]:
    out = tmp_path_factory.mktemp("figure2")
    return out, _run("figure2.py", out, *TINY_FIGURE, "executor=local")


@pytest.fixture(scope="module")
def tiny_tradeoff(tmp_path_factory) -> tuple[Path, subprocess.CompletedProcess]:
    out = tmp_path_factory.mktemp("tradeoff")
    return out, _run(
        "tradeoff.py",
        out,
        "r4=[5,50]",
        "p1_speed=[0.1]",
        "search.resolution=1",
        "search.lo=1",
        "search.hi=100",
        "dqn.r4=[5]",
        "dqn.seeds=[0,1]",
        "dqn.overrides=['algo=dqn','algo.num_envs=8','algo.frames_per_batch=32','algo.total_frames=320','algo.init_random_frames=64','algo.batch_size=16','eval.every_frames=320']",
        "executor=local",
    )


@pytest.mark.e2e
def test_figure2_end_to_end_tiny_local(tiny_figure):
    out, r = tiny_figure
    assert r.returncode == 0, (r.stdout[-3000:], r.stderr[-3000:])
    assert "| claim | subject | measured | verdict |" in r.stdout and "Wall time" in r.stdout
    _check_figure(out)
    # resume: every run is DONE, nothing retrains, the figure is rebuilt
    r = _run("figure2.py", out, *TINY_FIGURE, "executor=local", "resume=true")
    assert r.returncode == 0 and "8 grid points, 0 to run (resume)" in r.stdout, r.stdout[-2000:]
    assert json.loads((out / "summary.json").read_text())["resumed"] is True


@pytest.mark.parametrize(
    ("override", "msg"),
    [
        ("seeds=[0,0]", "seeds"),
        ("p1_speed=[0.1,1.5]", "p1_speed[1]=1.5"),
        ("methods=[dqn,sarsa]", "methods[1]='sarsa'"),
        ("learners.dqn.panels=[e]", "learners.dqn.panels"),
    ],
)
def test_figure2_rejects_bad_settings(override, msg):
    from conftest import load

    with pytest.raises(ValueError, match=re.escape(msg)):
        load("figure2", override, "executor=local")


def _unshare_works() -> bool:
    try:
        return subprocess.run(["unshare", "-n", "true"], capture_output=True).returncode == 0
    except FileNotFoundError:
        return False


@pytest.mark.e2e
@pytest.mark.skipif(not _unshare_works(), reason="Ray may only start in a loopback-only namespace")
def test_figure2_end_to_end_tiny_on_ray(tmp_path):
    pytest.importorskip("ray")
    r = _run("figure2.py", tmp_path, *TINY_FIGURE, "ray.num_cpus=2", netns=True)
    assert r.returncode == 0, (r.stdout[-3000:], r.stderr[-3000:])
    _check_figure(tmp_path)


@pytest.mark.e2e
def test_tradeoff_end_to_end_tiny(tiny_tradeoff):
    out, r = tiny_tradeoff
    assert r.returncode == 0, (r.stdout[-3000:], r.stderr[-3000:])
    for name in ("tradeoff.csv", "tradeoff.png", "tradeoff_dqn.csv", "r4_scan.csv", "summary.json"):
        assert (out / name).is_file(), name
    rows = {float(x["r4"]): x for x in csv.DictReader((out / "tradeoff.csv").open())}
    assert float(rows[5.0]["miss_detection"]) == pytest.approx(0.289, abs=1e-3)
    s = json.loads((out / "summary.json").read_text())
    found = s["smallest_r4"]["0.1"]
    assert found["metrics"]["miss_detection"] <= 0.05 < found["miss_at_lower_neighbour"]
    assert found["verified"] is True and found["r4"] == found["bisection_r4"]
    assert "smallest r4 meeting miss detection ≤ 0.05" in r.stdout


@pytest.mark.e2e
def test_report_fills_every_generated_block(tiny_figure, tiny_tradeoff, tmp_path):
    """ci/reproduce.sh's last step: figures copied, every generated block of the report filled."""
    from irdrc.paper.report import FIGURES, write_report

    fig, tr = tiny_figure[0], tiny_tradeoff[0]
    if json.loads((fig / "summary.json").read_text()).get("resumed"):
        # the figure test resumed this run; a resumed run is refused (its wall time is partial)
        with pytest.raises(ValueError, match="resumed"):
            write_report(fig, tr, tmp_path, "cmd")
        data = json.loads((fig / "summary.json").read_text())
        data["resumed"] = False
        (fig / "summary.json").write_text(json.dumps(data))
    template = (ROOT / "docs" / "REPRODUCTION.md").read_text()
    (tmp_path / "REPRODUCTION.md").write_text(template)
    write_report(fig, tr, tmp_path, "bash ci/reproduce.sh seeds=[0,1]")
    text = (tmp_path / "REPRODUCTION.md").read_text()
    for name in (*FIGURES, "tradeoff.png"):
        assert (tmp_path / "figures" / name).stat().st_size > 0
    assert "bash ci/reproduce.sh seeds=[0,1]" in text and "8 training runs" in text
    assert (fig / "claims.md").read_text().strip() in text
    assert "smallest r4 with miss detection ≤ 0.05" in text and "DQN (ours)" in text
    # writing twice replaces the blocks instead of appending to them
    write_report(fig, tr, tmp_path, "bash ci/reproduce.sh seeds=[0,1]")
    assert (tmp_path / "REPRODUCTION.md").read_text() == text


def test_learner_block_is_the_benchmark_table(tmp_path):
    """The report's learner block is the benchmark's own table file plus the total run time."""
    from irdrc.paper.report import learner_block
    from irdrc.runs.results import write_rows_csv

    write_rows_csv(
        tmp_path / "bench_constrained.csv", [{"wall_seconds": 60.0}, {"wall_seconds": 120.0}]
    )
    (tmp_path / "bench_constrained.md").write_text("| a |\n|---|\n| 1 |\n")
    block = learner_block(tmp_path)
    assert block.startswith("| a |\n|---|\n| 1 |") and "2 runs, 3 min" in block


def test_study_block_is_the_study_table(tmp_path):
    """The report's study block is the study's own table file, its optima and its total time."""
    from irdrc.paper.report import study_block

    (tmp_path / "study.md").write_text("| a |\n|---|\n| 1 |\n")
    summary = {
        "scenarios": {
            "paper": {
                "states": 352,
                "solver": "ExactScorer",
                "solve_seconds": 0.7,
                "avg_reward": 0.89851,
                "radar_fraction": 0.1,
            }
        },
        "learners": ["dqn"],
        "seeds": [100, 101],
        "wall_seconds": 600.0,
    }
    (tmp_path / "summary.json").write_text(json.dumps(summary))
    block = study_block(tmp_path)
    assert block.startswith("| a |\n|---|\n| 1 |")
    assert "Seeds 100, 101. paper: S = 352, optimum 0.8985" in block and "10 min" in block
