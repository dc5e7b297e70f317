"""Recipes run end to end from the command line with tiny settings."""

from __future__ import annotations

import csv
import json
import subprocess
import sys
from pathlib import Path

import pytest
import torch

ROOT = Path(__file__).resolve().parents[1]


def run_recipe(name: str, *overrides: str, timeout: int = 300) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, str(ROOT / "recipes" / name), *overrides],
        capture_output=True,
        text=True,
        timeout=timeout,
        cwd=ROOT,
    )


@pytest.mark.e2e
def test_demo_prints_metrics(tmp_path):
    out = run_recipe(
        "demo.py",
        "eval.mc_num_envs=16",
        "eval.mc_episodes=16",
        "env=ref_impl",
        "reward.r4=50",
        f"hydra.run.dir={tmp_path}",
    )
    assert out.returncode == 0, out.stderr
    assert "scenario=ref_impl[reward.r4=50] p1.speed=0.5 r4=50.0" in out.stdout
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
        "single_steps=2000",
        f"hydra.run.dir={tmp_path}",
    )
    assert out.returncode == 0, out.stderr
    assert "best batched env throughput" in out.stdout and "numpy baseline" in out.stdout
    rows = list(csv.DictReader((tmp_path / "bench_env.csv").open()))
    # 2 single-env modes at N = 1, then 4 batched modes at each of 2 sizes
    assert [r["mode"] for r in rows[:2]] == ["numpy_single", "gym"] and len(rows) == 2 + 2 * 4
    assert all(float(r["median_steps_per_s"]) > 0 for r in rows)


def _check_summary(path: Path, method: str) -> dict:
    import json

    s = json.loads((path / "summary.json").read_text())
    assert set(s) >= {
        "method",
        "scenario",
        "seed",
        "env_steps",
        "wall_seconds",
        "metrics",
        "optimal",
        "optimality_ratio",
    }
    keys = {
        "avg_reward",
        "episode_reward",
        "throughput",
        "link_capacity",
        "miss_detection",
        "radar_fraction",
        "drop_rate",
    }
    assert keys <= set(s["metrics"]) and keys <= set(s["optimal"])
    assert s["method"] == method
    rows = list(csv.DictReader((path / "policy.csv").open()))
    assert list(rows[0]) == ["d", "c", "r", "w", "v", "m", "action", "p_radar"] and len(rows) == 352
    assert all(r["p_radar"] == r["action"] for r in rows)  # deterministic: p_radar is 0 or 1
    # summary.json holds the printed table: the optimum's row, exact, in every recipe
    assert {"optimal (exact, long run)", "optimal (exact)", "optimal (stationary)"} & set(
        s["table"]
    )
    assert {r["action"] for r in rows} <= {"0", "1"}
    from irdrc.runs.tables import read_policy_csv

    assert read_policy_csv(path / "policy.csv").tolist() == [int(r["action"]) for r in rows]
    return s


@pytest.mark.e2e
def test_solve_recipe(tmp_path):
    out = run_recipe(
        "solve.py",
        "eval.mc_episodes=32",
        "eval.mc_num_envs=32",
        "env.p1.speed=1.0",
        f"hydra.run.dir={tmp_path}",
    )
    assert out.returncode == 0, out.stderr
    assert "optimal (stationary)" in out.stdout and "round_robin (episodic)" in out.stdout
    assert (
        "the optimum's closest decisions" in out.stdout and "other mode here: ratio" in out.stdout
    )
    s = _check_summary(tmp_path, "optimal")
    assert s["optimality_ratio"] == 1.0
    assert s["scenario"] == "paper[env.p1.speed=1.0]"


@pytest.mark.e2e
def test_qlearning_recipe(tmp_path):
    out = run_recipe(
        "qlearning.py",
        "algo.episodes=4",
        "eval.every_frames=800",
        "num_learners=2",
        "eval.mc_episodes=8",
        "eval.mc_num_envs=8",
        "progress=false",
        "seed=3",
        "reward.r4=50",
        f"hydra.run.dir={tmp_path}",
    )
    assert out.returncode == 0, out.stderr
    # four episodes end far below the optimum: the last line says so and what to try
    from irdrc.runs.report import ADVICE

    warning = [ln for ln in out.stdout.splitlines() if ln.startswith("warning:")]
    assert len(warning) == 1 and warning[0].endswith("; try " + ADVICE["qlearning"]), warning
    s = _check_summary(tmp_path, "qlearning")
    assert s["seed"] == 3 and s["env_steps"] == 4 * 400 and len(s["learners"]) == 2
    hist = list(csv.DictReader((tmp_path / "metrics.csv").open()))
    assert [int(r["env_steps"]) for r in hist if r["learner"] == "0"] == [0, 800, 1600]
    assert list(hist[0])[:6] == [
        "learner",
        "env_steps",
        "episodes",
        "wall_seconds",
        "updates",
        "optimality_ratio",
    ]
    assert set(s["table"]) == {
        "qlearning (exact, long run)",
        "qlearning (exact, episodic)",
        "qlearning (Monte-Carlo, episodic)",
        "optimal (exact, long run)",
        "optimal (exact, episodic)",
        "round_robin (exact, long run)",
    }
    # the exact episodic row is what the Monte-Carlo row estimates: within 4 of its 95 %
    # half-widths (≈ 8σ over 8 episodes; a seeded run, so a loose bound)
    t = s["table"]
    mc, ex = t["qlearning (Monte-Carlo, episodic)"], t["qlearning (exact, episodic)"]
    for key in ("avg_reward", "mean_queue"):
        assert abs(mc[key] - ex[key]) <= 4 * mc["ci95"][key] + 1e-9, (key, mc, ex)


@pytest.mark.e2e
@pytest.mark.parametrize(
    ("recipe", "tiny"),
    [
        (
            "dqn.py",
            [
                "algo.num_envs=8",
                "algo.frames_per_batch=32",
                "algo.total_frames=640",
                "algo.init_random_frames=128",
                "algo.batch_size=32",
            ],
        ),
        ("qlearning.py", ["algo.episodes=2"]),
    ],
)
def test_learner_recipes_on_a_scenario_with_false_alarms(tmp_path, recipe, tiny):
    """With radar false alarms the metrics gain ``false_alarm_rate``: ``metrics.csv`` (written at
    the end, and beside DQN's checkpoint) carries it as a last column instead of failing the run."""
    out = run_recipe(
        recipe,
        "env=imperfect_radar",
        "reward=imperfect_radar",
        *tiny,
        "eval.every_frames=320",
        "progress=false",
        f"hydra.run.dir={tmp_path}",
    )
    assert out.returncode == 0, out.stderr[-2000:]
    s = json.loads((tmp_path / "summary.json").read_text())
    hist = list(csv.DictReader((tmp_path / "metrics.csv").open()))
    assert list(hist[0])[-2:] == ["mean_queue", "false_alarm_rate"]
    final = s["metrics"]["false_alarm_rate"]
    assert 0 <= final <= 1 and float(hist[-1]["false_alarm_rate"]) == pytest.approx(final)


def test_qlearning_recipe_scores_beyond_the_dense_model(tmp_path):
    """Q-learning's recipe scores a scenario above the dense model's 8 192 states on the factored
    operator, as DQN's does (it failed after creating its run directory, proposing an operator no
    key reaches); its ratio is the one the same scorer gives its policy table."""
    from irdrc.core.exact import exact_scorer
    from irdrc.core.params import Params

    out = run_recipe(
        "qlearning.py",
        "env.queue_capacity=300",  # S = 301 · 32 = 9 632
        "algo.episodes=1",
        "eval.mc_episodes=0",
        "progress=false",
        f"hydra.run.dir={tmp_path}",
    )
    assert out.returncode == 0, out.stderr
    s = json.loads((tmp_path / "summary.json").read_text())
    table = torch.tensor(
        [int(r["action"]) for r in csv.DictReader((tmp_path / "policy.csv").open())]
    )
    scorer = exact_scorer(Params.from_overrides({"env.queue_capacity": 300}))
    assert len(table) == 9632
    assert s["optimality_ratio"] == pytest.approx(scorer.ratio(table), abs=1e-9)


def test_qlearning_recipe_batch_grid(tmp_path):
    out = run_recipe(
        "qlearning.py",
        "algo.episodes=2",
        "num_learners=2",
        "eval.mc_episodes=0",
        "progress=false",
        "batch_grid={env.p1.speed: [0.1,1.0], reward.r4: [5,50]}",
        f"hydra.run.dir={tmp_path}",
    )
    assert out.returncode == 0, out.stderr
    rows = list(csv.DictReader((tmp_path / "learners.csv").open()))
    # 4 scenarios × 2 learners, scenario-major, each row scored against its own scenario
    assert [(r["env.p1.speed"], r["reward.r4"], r["replicate"]) for r in rows[:3]] == [
        ("0.1", "5", "0"),
        ("0.1", "5", "1"),
        ("0.1", "50", "0"),
    ]
    assert len(rows) == 8 and all(float(r["final_ratio"]) <= 1 + 1e-9 for r in rows)
    s = json.loads((tmp_path / "summary.json").read_text())
    optima = [g["optimal"]["avg_reward"] for g in s["batch_grid"]]
    assert optima[0] == pytest.approx(0.8985, abs=1e-4) and len(set(optima)) == 4
    bad = run_recipe("qlearning.py", "batch_grid={algo.alpha: [0.1]}", f"hydra.run.dir={tmp_path}")
    assert bad.returncode != 0 and "must be an env. or reward. key" in bad.stderr


def test_qlearning_recipe_rejects_bad_algo_key(tmp_path):
    out = run_recipe("qlearning.py", "+algo.bogus=1", f"hydra.run.dir={tmp_path}")
    assert out.returncode != 0 and "algo.bogus" in out.stderr


def test_cli_lists_every_recipe_with_a_whole_summary():
    from irdrc.runs.cli import recipes

    known = recipes()
    assert {"dqn", "online", "solve", "bench_online"} <= set(known)
    # a summary cut at the docstring's first line break ends mid-sentence
    assert [n for n, what in known.items() if not what.endswith((".", "?"))] == []


def test_cli_runs_the_module_each_script_runs_with_its_summary():
    """``irdrc NAME`` runs, in its own process, the module ``recipes/NAME.py`` hands
    ``app.main``: every script is in the command's registry with that module, and the registry's
    one sentence is the first paragraph of that script's docstring."""
    import ast

    from conftest import recipe_module

    from irdrc.runs.cli import RECIPES

    scripts = {p.stem: p for p in (ROOT / "recipes").glob("*.py")}
    assert set(RECIPES) == set(scripts)
    for name, (module, what) in RECIPES.items():
        assert recipe_module(name).__name__ == module, name
        doc = ast.get_docstring(ast.parse(scripts[name].read_text())) or ""
        assert " ".join(doc.strip().split("\n\n")[0].split()) == what, name


def test_cli_lists_every_scenario_with_its_purpose(capsys, tmp_path):
    """``irdrc`` lists each named scenario with the first line of its file; a scenario file that
    does not open with its purpose is named."""
    from irdrc.runs.cli import main
    from irdrc.runs.scenarios import scenario_purposes

    assert main([]) == 0
    out = capsys.readouterr().out.split("scenarios (env=NAME):\n", 1)[1]
    assert "  multilevel       Speed low / medium / high and traffic density" in out
    assert len(out.strip().splitlines()) == len(scenario_purposes()) + 1 >= 8
    assert out.strip().splitlines()[-1].startswith("  PATH.yaml        A scenario of your own")
    (tmp_path / "mine.yaml").write_text("queue_capacity: 5\n")
    with pytest.raises(ValueError, match=r"mine\.yaml: its first line must say its purpose"):
        scenario_purposes(tmp_path)


def test_cfg_prints_the_runs_config_checked_and_runs_nothing(tmp_path, monkeypatch, capsys):
    """``--cfg`` (Hydra's flag, ``--cfg job`` too) prints the config.yaml the run would write, the
    learner's profile in it, after the same checks; nothing runs and nothing is written."""
    import yaml

    from irdrc.online import configs, recipe
    from irdrc.runs import app

    monkeypatch.chdir(tmp_path)
    for flag in (["--cfg"], ["--cfg", "job"]):
        assert app.execute(recipe, ["learner=safe", *flag, "algo.target_miss=0.1"]) == 0
        cfg = yaml.safe_load(capsys.readouterr().out)
        assert cfg["algo"] == {**configs.recorded_algo(configs.SAFE), "target_miss": 0.1}
        assert cfg["learner"] == "safe" and cfg["env"]["queue_capacity"] == 10
    assert app.execute(recipe, ["--cfg", "algo.target_miss=2"]) == 2
    assert "algo.target_miss" in capsys.readouterr().err
    assert list(tmp_path.iterdir()) == []


def test_a_recipe_is_named_as_the_user_can_run_it(tmp_path, monkeypatch):
    """Resume hints name ``recipes/NAME.py`` where the working directory is a checkout, and
    ``-m irdrc NAME`` elsewhere (an installed package, or another directory)."""
    from irdrc.runs.compose import recipe_call
    from irdrc.runs.scaffold import resume_hint

    monkeypatch.chdir(ROOT)
    assert recipe_call("dqn") == "recipes/dqn.py"
    monkeypatch.chdir(tmp_path)
    assert recipe_call("dqn") == "-m irdrc dqn"
    (tmp_path / "checkpoint.pt").write_bytes(b"")
    assert resume_hint("sac", tmp_path).endswith(f"-m irdrc sac resume={tmp_path}/checkpoint.pt")


def test_cli_proposes_the_closest_recipe_and_prints_its_version(capsys):
    from irdrc import __version__
    from irdrc.runs.cli import main

    assert main(["solv"]) == 2
    assert "unknown recipe 'solv'; did you mean solve? recipes:" in capsys.readouterr().err
    assert main(["xyz"]) == 2 and "did you mean" not in capsys.readouterr().err
    assert main(["--version"]) == 0 and capsys.readouterr().out == f"irdrc {__version__}\n"


@pytest.mark.e2e
def test_cli_lists_and_dispatches(tmp_path):
    listing = subprocess.run(
        [sys.executable, "-m", "irdrc"], capture_output=True, text=True, cwd=ROOT
    )
    assert listing.returncode == 0 and "solve" in listing.stdout and "ref_impl" in listing.stdout
    bad = subprocess.run(
        [sys.executable, "-m", "irdrc", "nope"],
        capture_output=True,
        text=True,
        cwd=ROOT,
    )
    assert bad.returncode == 2 and "unknown recipe" in bad.stderr
    run = subprocess.run(
        [
            sys.executable,
            "-m",
            "irdrc",
            "solve",
            "eval.mc_episodes=0",
            f"hydra.run.dir={tmp_path}",
        ],
        capture_output=True,
        text=True,
        cwd=ROOT,
    )
    assert run.returncode == 0, run.stderr
    assert (tmp_path / "summary.json").is_file()


@pytest.mark.e2e
def test_bench_robust_recipe(tmp_path):
    tiny = "'algo.num_envs=8','algo.frames_per_batch=32','algo.total_frames=640','algo.init_random_frames=128','algo.batch_size=32'"
    out = run_recipe(
        "bench_robust.py",
        "seeds=[5,6]",
        "p1_speed=[0.1]",
        "r4=[5]",
        f"candidates={{ladder: [{tiny}], plain: [{tiny},'algo.eps_duration_max=1']}}",
        "eval.every_frames=320",
        "executor=local",
        f"hydra.run.dir={tmp_path}",
    )
    assert out.returncode == 0, out.stderr[-2000:]
    rows = list(csv.DictReader((tmp_path / "bench_robust.csv").open()))
    assert [(r["candidate"], r["seed"]) for r in rows] == [
        ("ladder", "5"),
        ("ladder", "6"),
        ("plain", "5"),
        ("plain", "6"),
    ]
    assert all(int(r["env_steps"]) == 640 for r in rows)
    assert all(-2 < float(r["final_ratio"]) <= 1 + 1e-9 for r in rows)
    # the final ratio is the last evaluation's (the greedy policy of the last network)
    for r in rows:
        hist = list(csv.DictReader((tmp_path / "trials" / r["point_id"] / "metrics.csv").open()))
        assert float(r["final_ratio"]) == pytest.approx(float(hist[-1]["optimality_ratio"]))
        # a trial directory names its candidate, as does the sweep's summary.csv
        status = json.loads((tmp_path / "trials" / r["point_id"] / "status.json").read_text())
        assert (status["point"]["candidate"], status["point"]["seed"]) == (
            r["candidate"],
            int(r["seed"]),
        )
    summary = list(csv.DictReader((tmp_path / "summary.csv").open()))
    assert sorted(s["candidate"] for s in summary) == ["ladder", "ladder", "plain", "plain"]
    table = (tmp_path / "bench_robust.md").read_text()
    assert "| ladder | env.p1.speed = 0.1, reward.r4 = 5 | " in table
    assert "| plain | env.p1.speed = 0.1, reward.r4 = 5 | " in table
    assert "Measured on " in table and "ladder: `" in table
    for r in rows:  # every failing run is explained state by state, in the table's file too
        if r["holds"] == "False":
            line = f"{r['candidate']} env.p1.speed=0.1 reward.r4=5.0 seed={r['seed']}: final"
            assert line in out.stdout and line in table
            assert "differs from the optimum" in table
    # resumed into the same directory: nothing runs again, the same rows, and the time line says
    # that it counts none of them
    again = run_recipe("bench_robust.py", "resume=true", f"hydra.run.dir={tmp_path}")
    assert again.returncode == 0, again.stderr[-2000:]
    assert "4 grid points, 0 to run (resume)" in again.stdout
    assert list(csv.DictReader((tmp_path / "bench_robust.csv").open())) == rows
    assert "4 more were kept from an earlier one" in (tmp_path / "bench_robust.md").read_text()
    assert "kept from an earlier one" not in table
    bad = run_recipe("bench_robust.py", "p1_speed=[1.5]", f"hydra.run.dir={tmp_path / 'x'}")
    assert bad.returncode == 2 and "p1_speed[0]=1.5" in bad.stderr
    bad = run_recipe(
        "bench_robust.py", "candidates={a: [nokey]}", f"hydra.run.dir={tmp_path / 'y'}"
    )
    assert bad.returncode == 2 and "candidates.a" in bad.stderr


@pytest.mark.e2e
def test_bench_dqn_recipe_measures_speed(tmp_path):
    tiny = "'algo.num_envs=8','algo.frames_per_batch=32','algo.init_random_frames=64','algo.batch_size=16'"
    out = run_recipe(
        "bench_dqn.py",
        f"profiles={{a: ['algo=dqn',{tiny},'algo.total_frames=320'], b: ['algo=dqn',{tiny},'algo.total_frames=640']}}",
        "seeds=[0]",
        "eval.every_frames=160",
        f"hydra.run.dir={tmp_path}",
    )
    assert out.returncode == 0, out.stderr[-2000:]
    rows = list(csv.DictReader((tmp_path / "bench_dqn.csv").open()))
    assert [(r["profile"], int(r["env_steps"])) for r in rows] == [("a", 320), ("b", 640)]
    for r in rows:
        shares = [float(r[f"share_{k}"]) for k in ("collect", "store", "learn")]
        assert all(x > 0 for x in shares) and sum(shares) == pytest.approx(1, abs=0.01)
        assert float(r["env_steps_per_second"]) > 0 and float(r["updates_per_second"]) > 0
    table = (tmp_path / "bench_dqn.md").read_text()
    assert "| a | 1 | 320 |" in table and "| b | 1 | 640 |" in table
    bad = run_recipe(
        "bench_dqn.py", "profiles={a: ['algo.lr=7']}", f"hydra.run.dir={tmp_path / 'x'}"
    )
    assert bad.returncode == 2 and "profiles.a" in bad.stderr and "algo.lr" in bad.stderr
