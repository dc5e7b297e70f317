"""The fleet's recipes (``recipes/fleet.py``, ``solve.py env=fleet``, ``sweep.py method=fleet``,
``bench_fleet.py``): their files, tables, refusals and words."""

from __future__ import annotations

import csv
import json
import subprocess
import sys
from pathlib import Path

import pytest

from irdrc.agents.configs import FleetLearnerConfig

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.parametrize("learner", ["idqn", "vdn", "qmix"])
def test_the_fleet_recipe_runs_the_value_learners_as_measured(learner):
    """``recipes/fleet.py`` composes DQN's machinery (algo/dqn.yaml) but its value learners keep
    the learning rate they were measured at (3e-3, FleetLearnerConfig's), whatever DQN's own
    default becomes."""
    from conftest import load

    cfg = load("fleet", f"learner={learner}").learner
    assert cfg.dqn.lr == FleetLearnerConfig().dqn.lr == 3e-3


def run_recipe(*args: str, cwd: Path) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, str(ROOT / "recipes" / args[0]), *args[1:]],
        cwd=cwd,
        capture_output=True,
        text=True,
        timeout=600,
    )


TINY = [
    "algo.num_envs=16",
    "algo.frames_per_batch=32",
    "algo.total_frames=256",
    "algo.batch_size=32",
    "eval.every_frames=128",
    "progress=false",
    "logger=none",
]


@pytest.mark.parametrize(
    "args, prioritized, double_dqn",
    [
        (["learner=idqn"], True, True),
        (["learner=qmix"], False, False),
        (["learner=joint", "env.observe=full", "algo.double_dqn=false"], True, False),
    ],
)
def test_the_run_records_what_a_null_replay_key_resolved_to(
    tmp_path, monkeypatch, capsys, args, prioritized, double_dqn
):
    """``fleet.yaml``'s null ``algo.prioritized`` and ``algo.double_dqn`` take the learner's
    default; config.yaml (here ``--cfg``'s) records the value the run learned with, not null."""
    import yaml

    from irdrc.recipes.fleet import recipe
    from irdrc.runs import app

    monkeypatch.chdir(tmp_path)
    assert app.execute(recipe, [*args, "--cfg"]) == 0
    algo = yaml.safe_load(capsys.readouterr().out)["algo"]
    assert (algo["prioritized"], algo["double_dqn"]) == (prioritized, double_dqn)
    assert app.execute(recipe, ["learner=mappo", "--cfg"]) == 0  # PPO: algo.* is not read
    assert yaml.safe_load(capsys.readouterr().out)["algo"]["prioritized"] is None


@pytest.mark.e2e
def test_fleet_recipe_files_and_tables(tmp_path):
    """``recipes/fleet.py`` (N = 2, exact): summary.json with the learner's per-vehicle and fleet
    metrics beside the optimum and the baselines, policy.csv (joint state → each vehicle's action
    and the optimum's), metrics.csv in fleet steps, the curve."""
    out = tmp_path / "vdn"
    r = run_recipe("fleet.py", *TINY, f"hydra.run.dir={out}", cwd=tmp_path)
    assert r.returncode == 0, r.stderr[-2000:]
    s = json.loads((out / "summary.json").read_text())
    assert s["method"] == "qmix" and s["reference"] == "centralised optimum (exact)"
    assert s["fleet"] == {
        "vehicles": 2,
        "channels": 1,
        "access": "scheduled",
        "share": 0.5,
        "observe": "own",
        "joint_states": 30976,
        "exact": True,
        "per_vehicle": {},
    }
    assert [row["vehicle"] for row in s["per_vehicle"]] == [1, 2, "fleet"]
    assert s["per_vehicle"][-1]["avg_reward"] == pytest.approx(s["metrics"]["avg_reward"])
    assert {"centralised optimum", "N copies of the single optimum", "sensing rotation"} <= set(
        s["table"]
    )
    assert s["optimal"]["avg_reward"] == pytest.approx(1.8155, abs=1e-4)
    assert s["env_steps"] == 256 and s["vehicle_steps"] == 512
    lines = (out / "policy.csv").read_text().splitlines()
    assert lines[0] == "r,w,d1,c1,v1,m1,d2,c2,v2,m2,action1,action2,optimal1,optimal2"
    assert len(lines) == 1 + 30976
    assert (out / "metrics.csv").read_text().splitlines()[-1].split(",")[1] == "256"
    assert (out / "learning_curve.png").is_file()
    assert "fleet reward / the centralised optimum" in r.stdout
    # 256 fleet steps end far below the optimum: the warning names the one override to try
    assert "warning: qmix ends at" in r.stdout and "learner=joint env.observe=full" in r.stdout
    # a finished run is refused on resume, unless its files are gone: then it writes them again
    resume = [f"resume={out / 'checkpoint.pt'}", "progress=false"]
    r = run_recipe("fleet.py", *resume, cwd=tmp_path)
    assert r.returncode == 2 and "nothing left to train" in r.stderr, r.stderr[-2000:]
    (out / "summary.json").unlink()
    r = run_recipe("fleet.py", *resume, cwd=tmp_path)
    assert r.returncode == 0, r.stderr[-2000:]
    again = json.loads((out / "summary.json").read_text())
    assert again["env_steps"] == 256 and again["metrics"] == s["metrics"]


@pytest.mark.e2e
def test_fleet_recipe_beyond_the_exact_model(tmp_path):
    """N = 3 (2.7 M joint states): the learner and the baselines by Monte-Carlo, ratios to the best
    baseline, a confidence half-width per row."""
    out = tmp_path / "idqn3"
    r = run_recipe(
        "fleet.py",
        "learner=idqn",
        "env.vehicles=3",
        *TINY,
        "eval.mc_fleets=16",
        "eval.mc_steps=50",
        "eval.mc_burn_in=10",
        f"hydra.run.dir={out}",
        cwd=tmp_path,
    )
    assert r.returncode == 0, r.stderr[-2000:]
    s = json.loads((out / "summary.json").read_text())
    assert s["reference"] == "best baseline (Monte-Carlo)" and not s["fleet"]["exact"]
    assert [row["vehicle"] for row in s["per_vehicle"]] == [1, 2, 3, "fleet"]
    assert set(s["monte_carlo"]["ci95"]) == set(s["table"])
    assert "Monte-Carlo 95 %" in r.stdout
    # which wins, learner or best baseline, is said in words on the last printed line
    assert s["verdict"].startswith("idqn earns ") and "the best baseline (" in s["verdict"]
    assert s["verdict"] in r.stdout
    assert (
        "more than the best baseline" in s["verdict"]
        or "wins" in s["verdict"]
        or "neither" in s["verdict"]
    )


@pytest.mark.e2e
@pytest.mark.parametrize("learner", ["mappo", "ippo"])
def test_multiagent_ppo_runs_on_own_observations_scored_exactly(tmp_path, learner):
    """``learner=mappo|ippo``: TorchRL's MAPPOLoss / IPPOLoss on FleetEnv with the team reward,
    one rollout of every fleet per batch, no replay, scored exactly (N = 2) every evaluation."""
    out = tmp_path / learner
    r = run_recipe(
        "fleet.py",
        f"learner={learner}",
        "ppo.num_envs=16",
        "ppo.frames_per_batch=128",
        "ppo.total_frames=256",
        "ppo.batch_size=64",
        "eval.every_frames=128",
        "progress=false",
        "logger=none",
        f"hydra.run.dir={out}",
        cwd=tmp_path,
    )
    assert r.returncode == 0, r.stderr[-2000:]
    s = json.loads((out / "summary.json").read_text())
    assert s["method"] == learner and s["replay_sampler"] == "none (on-policy)"
    assert s["env_steps"] == 256 and s["updates"] == 2 * 2 * 4  # 2 rollouts × 2 batches × 4 epochs
    steps = [int(x.split(",")[1]) for x in (out / "metrics.csv").read_text().splitlines()[1:]]
    assert steps == [0, 128, 256]


def test_per_vehicle_values(tmp_path):
    """``env.p1.speed=[0.1,1.0]``: vehicle 2 is the paper's vehicle at speed 1.0 — its row in the
    summary is its own, the summary names what differs, and the copies' baseline gives each
    vehicle its own single-vehicle optimum."""
    out = tmp_path / "solve"
    r = run_recipe(
        "solve.py", "env=fleet", "env.p1.speed=[0.1,1.0]", f"hydra.run.dir={out}", cwd=tmp_path
    )
    assert r.returncode == 0, r.stderr[-2000:]
    assert "vehicles differ in env.p1.speed=[0.1, 1.0]" in r.stdout
    s = json.loads((out / "summary.json").read_text())
    assert s["fleet"]["per_vehicle"] == {"env.p1.speed": [0.1, 1.0]}
    copies = s["table"]["N copies of the single optimum"]
    assert copies[0]["avg_reward"] != pytest.approx(copies[1]["avg_reward"], abs=1e-3)


def test_a_list_valued_key_is_shared_as_it_is_and_per_vehicle_as_a_list_of_lists():
    """``env.bursty.rates=[0.5,2.0]`` is every vehicle's two traffic phases (it was read as one
    rate per vehicle and refused); a list of such lists gives each vehicle its own, beside a
    per-vehicle scalar list."""
    from conftest import load

    bursty = ["env.arrival_rate=null", "+env.bursty.transition=[[0.9,0.1],[0.2,0.8]]"]
    spec, _ = load("fleet", *bursty, "+env.bursty.rates=[0.5,2.0]", "env.p1.speed=[0.1,1.0]").fleet
    assert [v.env.bursty.rates for v in spec.per_vehicle] == [(0.5, 2.0), (0.5, 2.0)]
    assert [v.env.p1.speed for v in spec.per_vehicle] == [0.1, 1.0]
    spec, _ = load("fleet", *bursty, "+env.bursty.rates=[[0.5,2.0],[0.3,1.0]]").fleet
    assert [v.env.bursty.rates for v in spec.per_vehicle] == [(0.5, 2.0), (0.3, 1.0)]
    levels = ["+env.factors.speed.transition=[[0.8,0.2,0],[0.1,0.8,0.1],[0,0.25,0.75]]"]
    spec, _ = load(
        "fleet", *levels, "+env.factors.speed.event=[[0.003,0.01,0.1],[0.003,0.02,0.5]]"
    ).fleet
    assert [v.env.factor("speed").event for v in spec.per_vehicle] == [
        (0.003, 0.01, 0.1),
        (0.003, 0.02, 0.5),
    ]
    spec, _ = load("fleet", *levels, "+env.factors.speed.event=[0.003,0.01,0.1]").fleet
    assert spec.per_vehicle is None and spec.vehicle.env.factor("speed").event == (0.003, 0.01, 0.1)


def test_solve_env_fleet_prints_what_cooperation_is_worth(tmp_path):
    """``recipes/solve.py env=fleet``: the centralised optimum beside N independent single-vehicle
    optima (1.8155 against 1.0962 per fleet step at N = 2, K = 1, share 0.5)."""
    out = tmp_path / "solve"
    r = run_recipe("solve.py", "env=fleet", f"hydra.run.dir={out}", cwd=tmp_path)
    assert r.returncode == 0, r.stderr[-2000:]
    assert "cooperation is worth +0.7192 per fleet step" in r.stdout
    s = json.loads((out / "summary.json").read_text())
    assert s["cooperation"]["independent_over_optimum"] == pytest.approx(0.6038, abs=1e-4)
    assert (out / "policy.csv").read_text().splitlines()[0].endswith("action1,action2")


@pytest.mark.parametrize(
    ("recipe", "args", "message"),
    [
        ("fleet.py", ["env.share=2"], "env.share"),
        ("fleet.py", ["env.vehicles=0"], "env.vehicles"),
        ("fleet.py", ["env.access=aloha"], "env.access"),
        ("fleet.py", ["env.observe=all"], "env.observe"),
        ("fleet.py", ["learner=maddpg"], "learner"),
        ("fleet.py", ["learner=mappo", "algo.lr=0.1"], "learner=mappo reads ppo.*"),
        ("fleet.py", ["learner=vdn", "ppo.lr=0.1"], "learner=vdn reads algo.*"),
        ("fleet.py", ["learner=ippo", "ppo.total_frames=100000"], "whole rollouts"),
        ("fleet.py", ["learner=joint"], "env.observe=full"),
        ("fleet.py", ["learner=idqn", "env.observe=full"], "env.observe=own"),
        ("fleet.py", ["learner=joint", "env.observe=full", "env.vehicles=3"], "joint states"),
        ("fleet.py", ["algo.prioritized=true"], "importance"),
        ("fleet.py", ["learner=vdn", "algo.mixing_embed_dim=64"], "learner=qmix only"),
        ("fleet.py", ["learner=idqn", "algo.agent_index=false"], "algo.agent_index"),
        ("fleet.py", ["env=paper"], "not a fleet"),
        ("fleet.py", ["env.p1.speed=[0.1,1.0,0.5]"], "one value per vehicle"),
        ("fleet.py", ["env.queue_capacity=[10,5]"], "not in their states"),
        ("fleet.py", ["env.p1.speed=[0.1,1.5]"], "vehicle 2: env.p1.speed"),
        ("fleet.py", ["env.horizon=-1"], "env.horizon"),
        ("solve.py", ["env=fleet", "env.vehicles=3"], "joint states"),
        ("fleet.py", ["env.queue_capacity=300"], "env.queue_capacity ≤ 255 here"),
        ("dqn.py", ["env=fleet"], "recipes/fleet.py"),
        ("qlearning.py", ["env=fleet"], "recipes/fleet.py"),
    ],
)
def test_bad_fleet_configs_are_refused_before_work(tmp_path, recipe, args, message):
    """Every bad fleet config fails with one line naming the key, and leaves no run directory."""
    out = tmp_path / "run"
    r = run_recipe(recipe, *args, f"hydra.run.dir={out}", cwd=tmp_path)
    assert r.returncode == 2, r.stdout[-1000:]
    assert message in r.stderr and "Traceback" not in r.stderr
    assert not out.exists()


@pytest.mark.e2e
def test_sweep_method_fleet(tmp_path):
    """``recipes/sweep.py method=fleet``: one fleet run per grid point (here two learners), each
    with its fleet summary; a bad fleet value in the grid is refused before any trial."""
    out = tmp_path / "sweep"
    grid = "sweep.grid={learner: [vdn, idqn]}"
    base = "sweep.base=[" + ",".join(f"'{o}'" for o in TINY) + "]"
    r = run_recipe(
        "sweep.py",
        "method=fleet",
        "executor=local",
        grid,
        base,
        f"hydra.run.dir={out}",
        cwd=tmp_path,
    )
    assert r.returncode == 0, r.stderr[-2000:]
    summaries = [json.loads(p.read_text()) for p in sorted(out.glob("trials/*/summary.json"))]
    assert sorted(s["method"] for s in summaries) == ["idqn", "vdn"]
    assert all(s["fleet"]["vehicles"] == 2 for s in summaries)
    bad = run_recipe(
        "sweep.py",
        "method=fleet",
        "executor=local",
        "sweep.grid={env.share: [0.5, 3]}",
        f"hydra.run.dir={tmp_path / 'bad'}",
        cwd=tmp_path,
    )
    assert bad.returncode == 2 and "env.share" in bad.stderr


@pytest.mark.e2e
def test_bench_fleet_tables_search_and_figure(tmp_path):
    """``recipes/bench_fleet.py`` (a tiny grid on a D = 1 fleet, local executor): part A's table
    per cell with the exact baselines, the best decentralised policy found (at least the learner's
    own, which is among its starts), part B's table with N = 2 and 3, the CSVs and the frontier
    figure."""
    out = tmp_path / "bench"
    r = run_recipe(
        "bench_fleet.py",
        "executor=local",
        "learners=[vdn]",
        "seeds=[0]",
        "share=[0.5]",
        "channels=[1]",
        "scale_learners=[vdn]",
        "vehicles=[3]",
        "scale_seeds=[0]",
        "overrides=['algo.num_envs=16','algo.frames_per_batch=32','algo.total_frames=256',"
        "'algo.batch_size=32','eval.mc_fleets=8','eval.mc_steps=20','eval.mc_burn_in=0',"
        "'env.queue_capacity=1']",
        "eval.every_frames=128",
        "search_sweeps=1",
        f"hydra.run.dir={out}",
        cwd=tmp_path,
    )
    assert r.returncode == 0, r.stderr[-2000:]
    md = (out / "bench_fleet.md").read_text()
    assert "**N = 2, share 0.5, 1 channel(s)**" in md and "*sensing rotation* (exact)" in md
    assert "The best decentralised policy found and the two gaps" in md
    best = list(csv.DictReader((out / "best_decentralised_summary.csv").open()))
    assert len(best) == 1 and float(best[0]["best_ratio"]) >= float(best[0]["vdn_ratio"]) - 1e-9
    tables = list(csv.DictReader((out / "best_decentralised.csv").open()))
    assert len(tables) == 2 * 64  # two vehicles' tables over D = 1's 2 · 32 states
    # D = 1: N = 3 has 4·16³ joint states, within the exact model (the Monte-Carlo rows: the
    # recipe's own test beyond it)
    assert "| 3 | vdn (exact, 1 seed(s)) |" in md and "| 2 | vdn (exact, 1 seed(s)) |" in md
    rows = (out / "bench_fleet.csv").read_text().splitlines()
    assert len(rows) == 1 + 2
    assert (out / "fleet_frontier.png").is_file()
    # the finished search is kept for a resumed run, and reused only for the same starts
    from irdrc.bench.fleet_best import _cached

    saved = json.loads((out / "search" / "share0.5_channels1.json").read_text())
    key = saved["key"]
    assert _cached(out, 0.5, 1, key)["reward"] == float(best[0]["best_decentralised"])
    assert _cached(out, 0.5, 1, {**key, "starts": key["starts"][1:]}) is None
    assert _cached(out, 0.5, 1, {**key, "sweeps": key["sweeps"] + 1}) is None


def test_a_starved_vehicle_is_named_in_words_and_a_win_over_a_baseline_is_no_verdict():
    from types import SimpleNamespace

    from irdrc.recipes.fleet.recipe import verdict
    from irdrc.recipes.fleet.report import starvation

    def row(vehicle, throughput, drop):
        return {"vehicle": vehicle, "throughput": throughput, "drop_rate": drop}

    per = [row(1, 0.8, 0.01), row(2, 0.7, 0.02), row(3, 0.0, 0.999), row(4, 0.0, 0.999)]
    line = starvation("qmix", [*per, row("fleet", 1.5, 0.5)])
    assert line is not None and "vehicles 3, 4 of 4 never send" in line
    assert "vehicle 3: throughput 0.0000, drop rate 0.999" in line
    assert starvation("qmix", [*per[:2], row("fleet", 1.5, 0.01)]) is None

    def measured(reward):
        return SimpleNamespace(fleet=SimpleNamespace(avg_reward=reward), ci95=0.001)

    text = verdict(
        "qmix", {"qmix (Monte-Carlo)": measured(1.0), "rule (Monte-Carlo)": measured(0.7)}, "rule"
    )
    assert "earns 0.3000 more than the best baseline" in text
    assert "no verdict on the optimum" in text and "wins" not in text


def test_a_rate_that_is_zero_up_to_the_solves_accuracy_is_printed_as_zero():
    """Round-robin in anti-phase drops nothing; the exact solve gives its drop rate as −4.4e-15
    (at env.queue_capacity=40), which the table printed as "-0.0000"."""
    from irdrc.recipes.fleet.report import format_rows

    row = {"vehicle": 1, "avg_reward": 0.6139, "drop_rate": -4.4e-15, "denial_rate": 0.0}
    table = format_rows({"round-robin": [row, {**row, "vehicle": "fleet"}]}, reference=1.0)
    assert "-0.0000" not in table and " 0.0000" in table, table
    negative = format_rows({"p": [{**row, "avg_reward": -0.25}, {**row, "vehicle": "fleet"}]}, 1.0)
    assert "-0.2500" in negative


def test_a_fleet_whose_exact_evaluations_are_slow_says_so_first():
    """Past SLOW_EXACT_STATES joint states every exact evaluation takes several seconds or more
    (one linear solve over the joint states): the run's first lines say so, so that a quiet
    terminal is not taken for a hung one. At the paper's sizes and at a queue of 31 (262 144 joint
    states, about two seconds each) nothing is said."""
    from irdrc.core.params import Params
    from irdrc.fleet.model import FleetModel
    from irdrc.fleet.spec import FleetSpec
    from irdrc.recipes.fleet.report import SLOW_EXACT_STATES, describe

    for queue in (10, 31):
        spec = FleetSpec(vehicle=Params.from_overrides({"env.queue_capacity": queue}), vehicles=2)
        assert "[fleet]" not in describe(spec, "own", FleetModel(spec))
    deep = FleetSpec(vehicle=Params.from_overrides({"env.queue_capacity": 60}), vehicles=2)
    model = FleetModel(deep)
    assert model.exact and model.num_states > SLOW_EXACT_STATES
    assert "several seconds to over a minute" in describe(deep, "own", model).splitlines()[1]
