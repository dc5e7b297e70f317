"""Every mistake gets a clear answer before any work: bad values, typos, ``+`` keys, a run directory
that cannot be used, more rows than memory holds (misused envs: test_env.py, test_gym.py).

Most cases run the checks in-process on the composed config (what a recipe does before its run);
a few go through the command line to check that the answer is one line, exit status 2, no traceback.
"""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from conftest import load

import irdrc  # noqa: F401 - registers irdrc/DFRC-v0
from irdrc.recipes import solve
from irdrc.sweeps.trials import plan

ROOT = Path(__file__).resolve().parents[1]


def refused(recipe: str, *overrides: str) -> str:
    """The message a recipe refuses ``overrides`` with, before any work (fails if it accepts)."""
    with pytest.raises(ValueError) as err:
        load(recipe, *overrides)
    return str(err.value)


@pytest.mark.parametrize(
    ("recipe", "overrides", "named"),
    [
        # typos, with or without +, name the closest valid key
        ("dqn", ["rewards.r4=50"], "did you mean reward.r4"),
        ("dqn", ["+rewards.r4=50"], "did you mean reward.r4"),
        ("solve", ["+foo=1"], "unknown key 'foo'"),
        ("dqn", ["algo.lrr=0.1"], "did you mean algo.lr"),
        ("dqn", ["env=nope"], "env='nope' is not a choice"),
        # a W&B project W&B would refuse mid-run (a traceback after set-up), for every backend
        (
            "qlearning",
            ["logger=wandb", "logger.project=a/b"],
            "logger.project='a/b' must be a name",
        ),
        ("dqn", ["logger.project="], "logger.project='' must be a name"),
        # one stream is comm or radar: the radar share's recipes, for each of its action spaces
        ("online", ["env.actions=continuous"], "recipes/sac.py (continuous)"),
        ("online", ["env.actions=levels"], "recipes/dqn.py algo=dqn_levels (levels)"),
        ("online", ["algo.sweeps_per_step=-1"], "algo.sweeps_per_step=-1"),
        ("online", ["learner=safe", "algo.evaluations_per_step=-1"], "evaluations_per_step=-1"),
        # another learner's key names the learners that read it
        (
            "online",
            ["learner=posterior", "algo.evaluations_per_step=1"],
            "algo.evaluations_per_step is read by learner=safe|safe_anytime, not by learner=posterior",
        ),
        (
            "online",
            ["learner=dqn", "algo.sweeps_per_step=1"],
            "algo.sweeps_per_step is read by learner=posterior|posterior_anytime, not by learner=dqn",
        ),
        ("online", ["algo.alpha=0.1"], "is read by learner=qlearning|qlearning_paper, not by"),
        ("online", ["learner=qlearning", "algo.alfa=0.1"], "did you mean algo.alpha?"),
        # wrong types and ranges name the key
        ("dqn", ["optimum_gamma=1.0"], "optimum_gamma=1.0"),
        ("dqn", ["seed=abc"], "seed='abc'"),
        ("dqn", ["seed=-1"], "seed=-1"),
        ("dqn", ["num_threads=0"], "num_threads=0"),
        ("solve", ["optimum_gamma=abc"], "optimum_gamma='abc'"),
        ("solve", ["gamma=abc"], "did you mean optimum_gamma?"),
        ("dqn", ["total_frames=4000"], "did you mean algo.total_frames?"),
        # a learner's key the online recipe's algo: {} does not hold (its profiles' keys)
        ("online", ["learner=safe", "target_miss=0.1"], "did you mean algo.target_miss?"),
        ("online", ["device=cuda"], "online runs one vehicle's stream on the CPU"),
        ("qlearning", ["algo.alpha=abc"], "algo.alpha='abc'"),
        ("qlearning", ["num_learners=1000000"], "num_learners=1000000"),
        ("qlearning", ["batch_grid={}"], "batch_grid is empty"),
        ("qlearning", ["batch_grid={algo.alpha: [0.1]}"], "must be an env. or reward. key"),
        # a list where the mapping belongs (was "'int' object has no attribute 'items'")
        ("qlearning", ["batch_grid=[1,2]"], "must be a mapping of override key"),
        ("dqn", ["algo.alpha=inf"], "algo.alpha=inf"),
        ("solve", ["tol=nan"], "tol=nan"),
        ("tradeoff", ["search.lo=10", "search.hi=5"], "search.lo=10"),
        ("figure2", ["claim3_r4=[-5]"], "claim3_r4[0]=-5"),
        ("bench_online", ["scenarios=paper"], "(one item: scenarios=[paper])"),
        ("dqn", ["algo.updates_per_batch=0"], "algo.updates_per_batch=0"),
        ("qlearning", ["algo.init_q=nan"], "algo.init_q=nan"),
        ("qlearning", ["algo.epsilon_decay_episodes=2.5"], "algo.epsilon_decay_episodes=2.5"),
        ("qlearning", ["eval.every_frames=10000000"], "eval.every_frames=10000000"),
        ("qlearning", ["algo.eval_every_episodes=5"], "did you mean algo.episodes?"),
        ("solve", ["env.stay_good.road=1", "env.stay_bad.road=1"], "env.stay_good.road=1"),
        ("solve", ["env.p1.speed=1.5"], "env.p1.speed=1.5"),
        ("dqn", ["network.hidden=[0]"], "network.hidden"),
        ("dqn", ["logger.mode=sometimes"], "logger.mode"),
        # what cannot run is refused with its cost
        ("qlearning", ["env.queue_capacity=400000"], "GiB"),
        ("dqn", ["env.queue_capacity=400000"], "GiB"),
        ("tradeoff", ["search.resolution=0.001"], "exact solves"),
        # the frontier's dense models: at load, with the largest queue that fits (it was the
        # dense builder's advice to use an operator no key reaches)
        ("constrained", ["frontier=true", "env.queue_capacity=300"], "env.queue_capacity ≤ 180"),
        ("tradeoff", ["env.queue_capacity=300"], "env.queue_capacity ≤ 180"),
        # … and the figure's exact references, built after its hours of training
        ("figure2", ["env.queue_capacity=300"], "env.queue_capacity ≤ 180"),
        ("sweep", ["sweep.grid={}"], "sweep.grid is empty"),
        ("sweep", ["method=sarsa", "sweep.grid={seed: [0]}"], "method='sarsa'"),
        ("dqn", ["algo=qlearning_paper"], "recipes/qlearning.py algo=qlearning_paper"),
        ("dqn", ["algo.max_lr=1"], "did you mean algo.lr?"),
        ("demo", ["eval.mc_num_envs=null"], "eval.mc_num_envs=null: the demo is a Monte-Carlo"),
        # a benchmark whose lists leave nothing to run, or an empty mapping read as the default
        ("bench_online", ["scenarios=[]", "random_draws=0", "safe_targets=[]"], "nothing to run"),
        ("bench_online", ["scenarios=[]", "random_learners=[]", "safe_targets=[]"], "nothing"),
        ("bench_fleet", ["learners=[]", "scale_learners=[]"], "nothing to run"),
        ("bench_fleet", ["learners=[]", "vehicles=[]"], "nothing to run"),
        ("bench_timeshare", ["seeds=[]"], "seeds=[] must be a non-empty list"),
        ("bench_timeshare", ["scenarios={}"], "scenarios={} must map names"),
        ("bench_robust", ["candidates={}"], "candidates={} must map names"),
        ("bench_dqn", ["profiles={}"], "profiles={} must map names"),
        # a fleet where one vehicle runs, a seed twice, a table written outside the run
        ("study", ["scenarios=[paper,fleet]"], "scenarios[1]='fleet' is a fleet of vehicles"),
        ("bench_online", ["safe_scenarios=[fleet]"], "'fleet' is a fleet of vehicles"),
        ("bench_scale", ["scenarios=[fleet]"], "'fleet' is a fleet of vehicles"),
        ("study", ["seeds=[0,1,0]"], "seeds=[0, 1, 0] repeats seed 0"),
        ("bench_dqn", ["seeds=[3,3]"], "repeats seed 3"),
        ("bench_fleet", ["scale_seeds=[2,2]"], "scale_seeds=[2, 2] repeats seed 2"),
        ("bench_online", ["lagrangian_seeds=[a]"], "lagrangian_seeds[0]='a'"),
        ("study", ["csv=../x.csv"], "csv='../x.csv' must be a file name"),
        ("bench_scale", ["csv=/tmp/x.csv"], "must be a file name"),
        ("bench_fleet", ["csv=a/b.csv"], "must be a file name"),
        # a frontier per env.p1.speed where the speed has its own levels: at load, naming the key
        ("constrained", ["frontier=true", "env=multilevel"], "frontier_grid.p1_speed=[0.1] takes"),
        ("tradeoff", ["env=multilevel"], "p1_speed=[0.1, 1.0] sets env.p1.speed one value at a"),
        # a study's per-learner overrides: checked before any run, never the scenario
        ("study", ["overrides.dqn=['env.p1.speed=0.5']"], "overrides.dqn: 'env.p1.speed=0.5' sets"),
        ("study", ["overrides.qlearning=['algo.nosuch=1']"], "unknown key 'algo.nosuch'"),
        # a learner's seed, evaluation or device in its overrides was never read
        ("study", ["overrides.dqn=['seed=3']"], "overrides.dqn: 'seed=3' is not read"),
    ],
)
def test_bad_input_is_refused_naming_the_key(recipe, overrides, named):
    assert named in refused(recipe, *overrides)


@pytest.mark.skipif(torch.cuda.is_available(), reason="a CUDA device is present")
def test_a_sweep_on_ray_without_ray_says_how_to_get_it(monkeypatch):
    """Without Ray (an install without the sweep extra) a recipe that runs on Ray is refused at
    load, saying how to install it or to run without it; ``executor=local`` goes on (it was an
    ImportError traceback once the sweep started)."""
    from irdrc.runs import sections

    monkeypatch.setattr(sections, "ray_installed", lambda: False)
    for recipe, args in (
        ("sweep", ["sweep.grid={seed: [0]}"]),
        ("figure2", []),
        ("bench_robust", []),
    ):
        message = refused(recipe, *args)
        assert message.startswith("executor=ray needs Ray Tune, which is not installed"), recipe
        assert "pip install 'irdrc[sweep]'" in message and "executor=local" in message
    assert load("sweep", "sweep.grid={seed: [0]}", "executor=local").executor.executor == "local"


def test_an_unknown_key_with_no_near_name_gets_no_guess():
    """``progress`` is a key of the learning recipes, not of evaluate.py: no guess (it was
    'did you mean target_miss?')."""
    message = refused("evaluate", "progress=false")
    assert "unknown key 'progress' in evaluate" in message and "did you mean" not in message


def test_a_near_name_is_looked_for_in_the_keys_own_section():
    """``algo.total_frames`` is DQN's budget; Q-learning's is ``algo.episodes``. No key of
    Q-learning's ``algo`` is spelled like it, so no guess (it was 'did you mean algo.name?', the
    whole dotted key being close)."""
    message = refused("qlearning", "algo.total_frames=4000")
    assert "unknown key 'algo.total_frames' in qlearning" in message
    assert "did you mean" not in message


def test_an_unquoted_list_of_overrides_is_answered_with_the_quoted_form():
    """``sweep.base=[algo.episodes=2]`` is not a Hydra value (an element with '=' must be
    quoted); the answer is the argument written as it must be (it was Hydra's parser message
    alone: "OverrideParseException: no viable alternative at input '[algo.episodes='")."""
    message = refused("sweep", "method=qlearning", "sweep.base=[algo.episodes=2, seed=3]")
    assert "\"sweep.base=['algo.episodes=2','seed=3']\"" in message, message
    # the lists of a mapping too (a benchmark's candidates, scenarios)
    message = refused("bench_robust", "candidates={a: [algo.lr=0.001, algo.gamma=0.9], b: []}")
    assert "\"candidates={a: ['algo.lr=0.001','algo.gamma=0.9'], b: []}\"" in message, message


def test_a_comma_separated_value_or_multirun_points_to_the_sweep():
    """``seed=0,1`` is a Hydra sweep, and ``-m`` Hydra's multirun; a recipe runs once, so each
    answer names the sweep recipe (the first was Hydra's "ConfigCompositionException: Ambiguous
    value for argument 'seed=0,1'")."""
    message = refused("solve", "seed=0,1")
    assert message.startswith("seed=0,1: one run takes one value")
    assert "sweep.grid='{seed: [0,1]}'" in message
    assert "recipes/sweep.py" in refused("solve", "-m", "seed=0")


def test_cuda_without_a_device_is_refused():
    assert "no CUDA device" in refused("dqn", "device=cuda")


def test_long_horizon_is_cheap_not_refused():
    """A horizon of 10⁹ is accepted, and its exact episodic metrics cost ~log2(10⁹) matrix
    products (repeated squaring): episodes that long average to the long-run metrics."""
    from irdrc.core.exact import build_model, episodic_metrics, stationary_metrics

    cfg = load("solve", "env.horizon=1000000000", "eval.mc_episodes=0")
    assert cfg.model.env.horizon == 10**9
    model = build_model(cfg.model)
    long = episodic_metrics(model, "round_robin")
    assert long.avg_reward == pytest.approx(
        stationary_metrics(model, "round_robin").avg_reward, abs=1e-6
    )
    # an episode of no steps has no metrics (it gave NaN for every one)
    with pytest.raises(ValueError, match=r"horizon=0 is outside the allowed range >= 1"):
        episodic_metrics(model, "round_robin", horizon=0)


def test_all_zero_rewards_warn():
    with pytest.warns(UserWarning, match="all 0"):
        load("solve", *(f"reward.r{i}=0" for i in range(1, 5)))


NOTHING_TO_EARN = ("reward.r1=0", "reward.r2=0", "reward.r4=0")


@pytest.mark.parametrize(
    ("recipe", "args"),
    [
        ("irdrc.online.recipe", ["env=imperfect_radar"]),  # the optimum earns −0.205 per step
        ("irdrc.online.recipe", ["learner=dqn"]),  # … 0: radar always, no penalty
        ("irdrc.recipes.dqn", []),
        ("irdrc.recipes.qlearning", []),
        ("irdrc.recipes.shares.sac", []),
    ],
)
def test_learners_refuse_an_optimum_that_earns_nothing(tmp_path, capsys, recipe, args):
    """Learners are scored by their ratio to the optimum's reward; at an optimum that earns ≤ 0
    per step that ratio does not rank policies (online.py reported a worse policy as 1.0000 of the
    optimum, others divided by zero). Refused: one line, exit 2, no run directory."""
    import importlib

    from irdrc.runs import app

    module = importlib.import_module(recipe)
    run = [*NOTHING_TO_EARN, *args, f"hydra.run.dir={tmp_path / 'run'}", "progress=false"]
    assert app.execute(module, [*run, "logger=none"]) == 2
    err = capsys.readouterr().err
    assert "the exact optimum earns" in err and "needs an optimum that earns more than 0" in err
    assert not (tmp_path / "run").exists()


def test_a_progress_row_has_no_ratio_to_an_optimum_that_earns_nothing():
    """The Lagrangian DQN is read against the LP whatever the rewards: on a scenario whose reward
    optimum earns 0 it trains (constrained.py divided by zero in its first evaluation)."""
    import math

    from irdrc.agents.base import progress_record
    from irdrc.core.metrics import Metrics

    m = Metrics(**dict.fromkeys(Metrics.__dataclass_fields__, 0.5))
    assert progress_record(0, 1, 1, 0.1, 1, m, 0.25)["optimality_ratio"] == 2.0
    assert math.isnan(progress_record(0, 1, 1, 0.1, 1, m, 0.0)["optimality_ratio"])
    assert math.isnan(progress_record(0, 1, 1, 0.1, 1, m, -0.2)["optimality_ratio"])


def test_an_optimum_that_earns_nothing_is_read_without_a_ratio(tmp_path, capsys):
    from irdrc.recipes import evaluate
    from irdrc.runs import app

    table = tmp_path / "policy.csv"
    assert app.execute(solve, [f"hydra.run.dir={tmp_path / 'solved'}"]) == 0
    (tmp_path / "solved" / "policy.csv").rename(table)
    args = [f"policy={table}", "eval.mc_episodes=0", f"hydra.run.dir={tmp_path / 'run'}"]
    assert app.execute(evaluate, [*args, *NOTHING_TO_EARN]) == 0
    out = capsys.readouterr().out
    assert (
        "below this scenario's optimum (0 per step: no ratio to an optimum that earns ≤ 0)" in out
    )
    summary = json.loads((tmp_path / "run" / "summary.json").read_text())
    assert summary["optimality_ratio"] is None and summary["optimal"]["avg_reward"] == 0
    # solve.py's closest decisions: no ratio either (it divided by zero)
    assert app.execute(solve, [*NOTHING_TO_EARN, f"hydra.run.dir={tmp_path / 'zero'}"]) == 0
    rows = capsys.readouterr().out.split("closest decisions")[1].split("exact metrics")[0]
    assert rows.count(" n/a ") == 6


def test_sweep_values_are_validated_before_any_trial():
    """A bad value inside the grid (not only in the base) fails at planning, naming the point."""
    with pytest.raises(ValueError, match=r"env\.p1\.speed=1\.5.*env\.p1\.speed=1\.5 is outside"):
        plan(solve, [{"env.p1.speed": 0.5}, {"env.p1.speed": 1.5}], [])


@pytest.mark.parametrize(
    ("args", "named"),
    [
        (["recipes/dqn.py", "rewards.r4=50"], "did you mean reward.r4"),
        (["recipes/qlearning.py", "algo.alpha=abc"], "algo.alpha='abc'"),
        (["recipes/dqn.py", "env.queue_capacity=400000"], "GiB"),
    ],
)
def test_command_line_answer_is_one_line_without_traceback(tmp_path, args, named):
    r = subprocess.run(
        [sys.executable, *args, f"hydra.run.dir={tmp_path / 'run'}"],
        capture_output=True,
        text=True,
        timeout=120,
        cwd=ROOT,
    )
    assert r.returncode == 2, r.stderr[-2000:]
    assert named in r.stderr and "Traceback" not in r.stderr
    assert len([line for line in r.stderr.splitlines() if line.startswith("error:")]) == 1
    assert not (tmp_path / "run").exists()  # refused before any work


def test_a_run_refused_after_its_directory_exists_leaves_none_and_logs_what_it_printed(tmp_path):
    """A recipe whose run refuses (a ``ValueError`` after the scaffold made the run directory)
    removes the directory it made: one line, exit 2, nothing left. A run that works keeps what it
    printed in ``<recipe>.log``."""
    script = (
        "import types\n"
        "from irdrc.recipes import solve\n"
        "from irdrc.runs import app\n"
        "def run(cfg, run):\n"
        "    print('working on it')\n"
        "    if cfg.seed == 1:\n"
        "        raise ValueError('refused on purpose')\n"
        "module = types.SimpleNamespace(NAME='solve', load=solve.load, run=run)\n"
        "app.main(module)\n"
    )
    refused, kept = tmp_path / "refused", tmp_path / "kept"
    r = subprocess.run(
        [sys.executable, "-c", script, "seed=1", f"hydra.run.dir={refused}"],
        capture_output=True,
        text=True,
        timeout=120,
        cwd=ROOT,
    )
    assert r.returncode == 2 and r.stderr.strip() == "error: refused on purpose", r.stderr
    assert not refused.exists()
    r = subprocess.run(
        [sys.executable, "-c", script, "seed=0", f"hydra.run.dir={kept}"],
        capture_output=True,
        text=True,
        timeout=120,
        cwd=ROOT,
    )
    assert r.returncode == 0, r.stderr
    assert "working on it" in (kept / "solve.log").read_text()


# -- the run directory and long solves ------------------------------------------------------------


def _run(*args: str, timeout: float = 120) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, *args], capture_output=True, text=True, timeout=timeout, cwd=ROOT
    )


def test_a_second_run_into_a_directory_in_use_is_refused_naming_the_first(tmp_path):
    """A run holds its directory (``.lock``, with its process id): another run started there is
    refused with one line naming that process, exit 2, and writes nothing there."""
    from irdrc.runs.compose import compose
    from irdrc.runs.scaffold import Run

    out = tmp_path / "run"
    first = Run("solve", compose("solve", ["seed=1"]), out).open()
    try:
        before = (out / "config.yaml").read_text()
        r = _run("recipes/solve.py", "seed=2", f"hydra.run.dir={out}")
        assert r.returncode == 2, r.stderr
        assert r.stderr.strip() == (
            f"error: hydra.run.dir={out} is in use by process {os.getpid()} (python "
            "recipes/solve.py): two runs would mix their files; wait for it to finish or choose "
            "another hydra.run.dir"
        )
        assert (out / "config.yaml").read_text() == before and not (out / "policy.csv").exists()
    finally:
        first.close(refused=False)
    r = _run("recipes/solve.py", "seed=2", "eval.mc_episodes=0", f"hydra.run.dir={out}")
    assert r.returncode == 0, r.stderr  # once the first run is done, the directory is free


@pytest.mark.parametrize("where", ["/proc/irdrc", "/etc/hostname/run"])
def test_an_unwritable_run_directory_is_one_line(where):
    r = _run("recipes/solve.py", f"hydra.run.dir={where}")
    assert r.returncode == 2 and "Traceback" not in r.stderr and "HYDRA_FULL_ERROR" not in r.stderr
    assert r.stderr.startswith(f"error: hydra.run.dir={where}: cannot create the run directory")


def test_a_solve_past_its_time_limit_is_refused_with_its_estimate(tmp_path):
    """A factored solve says its size and estimate first; past ``max_minutes`` it is refused,
    before any sweep, naming the key that allows it."""
    out = tmp_path / "run"
    r = _run("recipes/solve.py", "env=large", "max_minutes=0.001", f"hydra.run.dir={out}")
    assert r.returncode == 2, r.stderr
    assert r.stdout.startswith("scenario=large: S = 100 800 states, factored value iteration;")
    assert "estimate here" in r.stdout and "value iteration:" not in r.stdout
    assert "above max_minutes=0.001; raise max_minutes to solve it anyway" in r.stderr
    assert not out.exists()


def test_env_rows_are_bounded_by_this_machines_memory(monkeypatch):
    """``algo.num_envs`` is refused where the estimated memory of its rows, collections and replay
    exceeds what the machine has available, naming the estimate and a number of rows that fits
    (which the estimate then accepts); nothing is refused where the memory is unknown."""
    from irdrc.runs import limits

    monkeypatch.setattr(limits, "available_memory", lambda: 4 * 2**30)
    load("dqn")  # the main job: 8 000 rows
    load("sac")
    big = ("algo.num_envs=10000000", "algo.frames_per_batch=10000000", "algo.total_frames=40000000")
    with pytest.raises(
        ValueError, match=r"GiB of memory, this machine has 4\.0 GiB available"
    ) as err:
        load("dqn", *big)
    rows = int(re.search(r"algo\.num_envs ≤ ([\d ]+)", str(err.value)).group(1).replace(" ", ""))
    assert 100_000 < rows < 10_000_000
    load(
        "dqn",
        f"algo.num_envs={rows}",
        f"algo.frames_per_batch={rows}",
        "algo.total_frames=40000000",
    )
    with pytest.raises(ValueError, match="GiB of memory"):
        load(
            "sac",
            "algo.num_envs=5000000",
            "algo.frames_per_batch=5000000",
            "algo.total_frames=40000000",
        )
    monkeypatch.setattr(limits, "available_memory", lambda: None)
    load("dqn", *big)


def test_an_lp_past_this_machines_memory_is_refused_before_it_is_built(monkeypatch, tmp_path):
    """The LP's memory is read from its transitions' non-zeros, counted from the factors: ``large``'s
    binary LP (318.8 M non-zeros) is refused at load on a machine of 24 GB, with its estimate and
    the dual named (HiGHS was stopped by the system at 24 GB after a minute); the paper's LP and
    ``learner=dual`` go on; ``evaluate.py target_miss=…`` is held to the same estimate; where the
    memory is unknown nothing is refused."""
    import torch

    from irdrc.recipes.constrained.lp_cost import LP_BYTES_PER_NONZERO
    from irdrc.runs import limits
    from irdrc.runs.tables import write_policy_csv

    monkeypatch.setattr(limits, "available_memory", lambda: 24 * 2**30)
    load("constrained")
    says = r"318\.8 M non-zeros for S = 100 800 states and would need ~\d+\.\d GB, more than"
    with pytest.raises(ValueError, match=says) as err:
        load("constrained", "env=large")
    assert str(err.value).startswith("env.queue_capacity=699: the LP over 201 600 occupation")
    assert "learner=dual" in str(err.value)
    load("constrained", "env=large", "learner=dual")
    table = tmp_path / "policy.csv"
    write_policy_csv(table, torch.ones(352, dtype=torch.long), None)
    load("evaluate", f"policy={table}", "target_miss=0.05")
    paper = (94_720 + 50_688) * LP_BYTES_PER_NONZERO  # the paper LP's non-zeros
    monkeypatch.setattr(limits, "available_memory", lambda: int(paper))
    with pytest.raises(ValueError, match="or leave target_miss out"):
        load("evaluate", f"policy={table}", "target_miss=0.05")
    load("evaluate", f"policy={table}")
    monkeypatch.setattr(limits, "available_memory", lambda: None)
    load("constrained", "env=large")


@pytest.mark.parametrize(
    ("recipe", "override", "says"),
    [
        ("bench_online", "learners=[dqn,dqn]", "learners=['dqn', 'dqn'] repeats 'dqn'"),
        ("bench_online", "safe_targets=[0.1,0.1]", "safe_targets=[0.1, 0.1] repeats 0.1"),
        ("bench_timeshare", "learners=[sac,sac]", "learners=['sac', 'sac'] repeats 'sac'"),
        ("bench_fleet", "vehicles=[3,3]", "vehicles=[3, 3] repeats 3"),
        ("study", "learners=[dqn,dqn]", "learners=['dqn', 'dqn'] repeats 'dqn'"),
        ("study", "scenarios=[paper,paper]", "scenarios=['paper', 'paper'] repeats 'paper'"),
        ("bench_scale", "scenarios=[paper,paper]", "repeats 'paper'"),
        ("tradeoff", "p1_speed=[0.1,0.1]", "p1_speed=[0.1, 0.1] repeats 0.1"),
        ("bench_robust", "r4=[5,5]", "r4=[5, 5] repeats 5"),
    ],
)
def test_a_list_that_makes_runs_refuses_a_repeat(recipe: str, override: str, says: str) -> None:
    """A list whose items each make runs (learners, scenarios, sizes, targets) refuses a repeated
    item by name: the same runs twice. Before, ``bench_online`` and ``tradeoff`` ran them twice,
    ``study`` failed mid-run ("Converting a tensordict to boolean value is not permitted"),
    ``bench_scale`` at its end (ZeroDivisionError), ``bench_timeshare`` and ``bench_fleet`` said
    only "two planned points share an id"."""
    message = refused(recipe, override)
    assert says in message and "the same runs twice" in message, message


def test_a_list_for_a_mapping_and_a_mapping_for_a_list_are_named():
    """``profiles=[dqn]`` (``profiles`` maps names to overrides) and ``seeds={a: 1}`` were Hydra's
    "ConfigCompositionException: Error merging override …" alone; each answer names the key's
    kind and how to write it."""
    message = refused("bench_dqn", "profiles=[dqn]")
    assert message.startswith("profiles is a mapping, not a list"), message
    assert "profiles='{KEY: …}'" in message
    assert refused("dqn", "env.p1=[1]").startswith("env.p1 is a mapping, not a list")
    assert refused("bench_dqn", "seeds={a: 1}") == "seeds is a list, not a mapping: seeds='[…]'"


SMALL = {
    "figure2": ["seeds=[0]", "p1_speed=[0.5]"],
    "bench_fleet": ["learners=[idqn]", "share=[0.5]", "channels=[1]", "seeds=[0]", "vehicles=[3]"],
}


@pytest.mark.parametrize(
    ("recipe", "overrides", "says"),
    [
        ("figure2", ["env.p1.speed=0.5"], "figure2 sets env.p1.speed per run; set p1_speed=[…]"),
        ("figure2", ["learners.qlearning.overrides=['seed=3']"], "set seeds=[…]"),
        ("tradeoff", ["reward.r4=50"], "set r4=[…] (the exact curves) and dqn.r4=[…]"),
        ("tradeoff", ["dqn.overrides=['seed=3']"], "set dqn.seeds=[…]"),
        ("bench_robust", ["overrides=['env.p1.speed=0.3']"], "set p1_speed=[…]"),
        ("bench_robust", ["candidates={a: ['reward.r4=50'], b: []}"], "set r4=[…]"),
        ("bench_constrained", ["overrides=['target_miss=0.1']"], "set targets=[…]"),
        ("bench_fleet", ["overrides=['env.share=0.3']"], "set share=[…] (part B: 0.5)"),
        ("bench_fleet", ["overrides=['eval.every_frames=100']"], "set eval.every_frames=…"),
        ("bench_timeshare", ["overrides=['seed=3']"], "set seeds=[…]"),
        ("figure2", ["learners.dqn.overrides=['eval.mc_episodes=9']"], "scored exactly"),
        ("tradeoff", ["dqn.overrides=['optimum_gamma=0.9']"], "set optimum_gamma=…"),
        ("bench_robust", ["overrides=['eval.every_frames=5000']"], "set eval.every_frames=…"),
        ("bench_constrained", ["overrides=['checkpoint.every_frames=9']"], "keep no checkpoints"),
    ],
)
def test_a_key_a_recipe_sets_per_run_is_not_taken_to_be_overwritten(recipe, overrides, says):
    """``figure2.py env.p1.speed=0.5`` ran the whole figure at p1_speed's values, the 0.5 lost
    without a word; the same held for every recipe whose runs set a key from a list of its own,
    and for the keys it sets for every run after a learner's overrides (``eval.mc_episodes=0``,
    its ``optimum_gamma``). The key is refused, naming what to set; the scenario's other keys
    still pass."""
    message = refused(recipe, *overrides)
    assert "would be overwritten" in message and says in message, message
    road = "env.p1.road=0.3"
    other = road if recipe in ("figure2", "tradeoff", "bench_robust", "bench_constrained") else ""
    few = SMALL.get(recipe, [])  # fewer runs to plan: the check is the same
    first_run = load(recipe, *few, other or f"overrides=['{road}']").planned[0]["composed"]
    assert first_run.cfg["env"]["p1"]["road"] == 0.3
    if recipe == "bench_fleet":  # its own key on its own command line is what sets the runs'
        runs = load(recipe, *few, "eval.every_frames=1000").planned
        assert {p["composed"].cfg["eval"]["every_frames"] for p in runs} == {1000}


@pytest.mark.parametrize(
    ("recipe", "overrides", "says"),
    [
        # an exact solve learns nothing: the learner's keys
        ("constrained", ["algo.lr=0.001"], "learner=lp solves exactly and learns nothing"),
        ("constrained", ["learner=dual", "network=large"], "learner=dual solves exactly"),
        ("constrained", ["checkpoint.every_frames=5"], "read with learner=dqn_lagrangian"),
        ("constrained", ["frontier=true", "eval.every_frames=5"], "frontier=true solves LPs"),
        # the frontier sets its own targets and speeds; its grid needs it
        ("constrained", ["frontier=true", "target_miss=0.3"], "frontier_grid.targets=[…]"),
        ("constrained", ["frontier=true", "env.p1.speed=0.5"], "frontier_grid.p1_speed=[…]"),
        ("constrained", ["frontier_grid.points=5"], "the frontier's grid is read with frontier"),
        # a batch's scenarios, a sweep's points
        (
            "qlearning",
            ["env.p1.speed=0.5", "batch_grid={env.p1.speed: [0.1,1.0]}"],
            "batch_grid sets env.p1.speed in every scenario of the batch",
        ),
        (
            "sweep",
            [
                "executor=local",
                "method=solve",
                "sweep.grid={env.p1.speed: [0.1,1.0]}",
                "sweep.base=['env.p1.speed=0.5']",
            ],
            "env.p1.speed=0.5 would be overwritten: sweep sets env.p1.speed per run; sweep.grid",
        ),
        # an exact solve with no Monte-Carlo check
        ("solve", ["env.actions=continuous", "eval.mc_episodes=3"], "the optimum over ρ is"),
        ("solve", ["env=large", "eval.mc_episodes=3"], "100 800 states (the factored solve)"),
        ("solve", ["env=fleet", "eval.mc_num_envs=8"], "the fleet's optimum is scored exactly"),
        # a part of a benchmark that does not run
        ("bench_robust", ["draws=5"], "draws=5: the random draws need scenarios=random"),
        ("bench_robust", ["scenarios=random", "r4=[10]"], "scenarios=random draws every"),
        ("bench_timeshare", ["first_draw=3"], "the random draws need scenarios=random"),
        ("bench_online", ["random_draws=0", "random_seed=3"], "no random draw runs (random_d"),
        ("bench_online", ["random_learners=[]", "random_draws=4"], "(random_learners=[])"),
        ("bench_online", ["safe_targets=[]", "safe_seeds=[1]"], "no safe learner runs"),
        ("bench_online", ["scenarios=[multilevel]", "paper_seeds=[3]"], "scenarios leaves out"),
        ("figure2", ["methods=[dqn]", "learners.qlearning.panels=[a]"], "not among methods"),
        ("tradeoff", ["target_miss=null", "search.lo=2"], "skipped (target_miss=null)"),
        ("tradeoff", ["dqn.r4=[]", "dqn.seeds=[3]"], "no DQN run (dqn.r4=[])"),
        ("study", ["learners=[dqn]", "overrides.qlearning=['algo.episodes=3']"], "not among"),
        ("study", ["scenarios=[paper]", "evals.large=3"], "large is not among scenarios"),
        ("bench_fleet", ["search=false", "search_sweeps=3"], "no search runs (search=false)"),
        ("bench_fleet", ["vehicles=[]", "scale_seeds=[4]"], "part B does not run (vehicles=[])"),
        # the radar share's keys where each step is all comm or all radar
        ("solve", ["env.levels=9"], "env.levels=9: with env.actions=binary each step is all"),
        ("dqn", ["env.dwell_gain=2"], "env.dwell_gain shapes the radar share"),
        ("online", ["env.sensing=linear"], "env.sensing shapes the radar share"),
    ],
)
def test_a_key_the_run_would_not_read_is_refused(recipe, overrides, says):
    """Each of these ran, the key set on the command line never read: ``constrained.py
    algo.lr=0.001`` solved the LP, ``frontier=true target_miss=0.3`` drew the frontier at its own
    targets, ``solve.py env.levels=9`` solved whole-step modes. Each is refused, saying what
    reads it; the same keys where they are read still pass."""
    assert says in refused(recipe, *overrides)


def test_the_same_keys_pass_where_they_are_read():
    """The keys the test above refuses, in the runs that read them."""
    cfg = load("constrained", "learner=dqn_lagrangian", "algo.lr=0.001", "network=small")
    assert cfg.algo.dqn.lr == 0.001
    cfg = load("constrained", "frontier=true", "frontier_grid.points=5", "objective=avg_reward")
    assert cfg.frontier_grid.points == 5
    assert load("constrained", "target_miss=0.2", "env.p1.speed=0.5").target_miss == 0.2
    assert load("solve", "eval.mc_episodes=8").eval.mc_episodes == 8
    assert load("solve", "env.actions=levels", "env.levels=9").model.env.levels == 9
    assert load("sac", "env.dwell_gain=2").params.env.dwell_gain == 2
    cfg = load("qlearning", "env.p1.road=0.3", "batch_grid={env.p1.speed: [0.1,1.0]}")
    assert [p.env.p1.road for p in cfg.scenarios] == [0.3, 0.3]
    # a value that asks for nothing passes where nothing reads it
    cfg = load("bench_online", "safe_targets=[]", "lagrangian_seeds=[]", "random_draws=0")
    assert cfg.lagrangian_seeds == () and cfg.random_draws == 0
    assert load("bench_online", "scenarios=[paper]", "paper_seeds=[3]").paper_seeds == (3,)
    assert load("bench_timeshare", "scenarios=random", "draws=1", "first_draw=3").draws == 1


def test_a_dqn_profile_that_sets_what_bench_dqn_owns_is_refused():
    """``bench_dqn.py 'profiles={b: [algo=dqn, env.p1.speed=0.9]}'`` ran b on the benchmark's own
    scenario, the 0.9 never read; a profile is DQN's algo and network keys."""
    message = refused("bench_dqn", "profiles={b: ['algo=dqn','env.p1.speed=0.9']}")
    assert message.startswith("profiles.b: env.p1.speed=0.9 is not read"), message
    assert "overrides: seed=3 is not read" in refused("bench_dqn", "overrides=['seed=3']")
    cfg = load("bench_dqn", "profiles={b: ['algo=dqn','network=small']}", "env.p1.speed=0.9")
    assert cfg.algos["b"].network.hidden == (32, 32) and cfg.params.env.p1.speed == 0.9
