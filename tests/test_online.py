"""``recipes/online.py``: its keys, files, printout and refusals, and ONLINE.md's own-learner example."""

from __future__ import annotations

import dataclasses
import json

import pytest

from irdrc.core.params import Params
from irdrc.online import configs

PAPER = Params()


def test_learner_keys_are_checked_against_the_chosen_learner():
    with pytest.raises(ValueError, match=r"algo.batch_sze \(did you mean algo.batch_size\?\)"):
        configs.learner_config("dqn", {"batch_sze": 3})
    with pytest.raises(ValueError, match=r"algo\.target_miss"):
        configs.learner_config("posterior", {"target_miss": 0.1})
    with pytest.raises(ValueError, match="learner='rainbow' must be one of"):
        configs.learner_config("rainbow", {})
    with pytest.raises(ValueError, match="learner=ppo is not a learner on one vehicle's stream"):
        configs.learner_config("ppo", {})
    with pytest.raises(ValueError, match=r"algo.hidden\[0\]"):
        configs.learner_config("dqn", {"hidden": [0]})
    assert dataclasses.replace(configs.DQN, episodes=5).epsilon(0) == configs.DQN.eps_start


def test_the_recipe_writes_the_ledger_everywhere(tmp_path, capsys):
    """``recipes/online.py`` in-process, 3 episodes of its default learner (posterior sampling):
    exit 0; the ledger in metrics.csv (a row per episode), summary.json and the printout; a
    checkpoint to resume from."""
    import csv

    from irdrc.online import recipe
    from irdrc.runs import app

    args = ["algo.episodes=3", f"hydra.run.dir={tmp_path}", "logger=none"]
    assert app.execute(recipe, [*args, "progress=false"]) == 0
    rows = list(csv.DictReader((tmp_path / "metrics.csv").open()))
    assert [int(r["episodes"]) for r in rows] == [0, 1, 2, 3]
    assert {"regret", "expected_missed", "floor_missed", "realised_missed"} <= set(rows[0])
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary["learner"] == "posterior" and summary["episodes"] == 3
    assert summary["ledger"]["regret"] == pytest.approx(float(rows[-1]["regret"]))
    assert (tmp_path / "checkpoint.pt").is_file() and (tmp_path / "learning_curve.png").is_file()
    out = capsys.readouterr().out
    assert "the price of learning over 3 episodes" in out and "where the optimum misses" in out
    # 3 episodes end at 0.4228 of the optimum (it reaches 1.0000 at 4): it is told twice as many
    assert "below 0.99" in out and out.count("try algo.episodes=6\n") == 1
    # the slowest decision, timed as the vehicle waits for it (irdrc.online.loop)
    slowest = f"its slowest decision took {1e3 * summary['seconds_slowest_decision']:.1f} ms, "
    assert slowest + f"{summary['decisions_over_1ms']} of 1200 over 1 ms" in out
    # nothing left to train at 3 episodes; a longer run goes on from the checkpoint
    resume = [f"resume={tmp_path / 'checkpoint.pt'}", "logger=none", "progress=false"]
    assert app.execute(recipe, resume) == 2
    assert "nothing left to train" in capsys.readouterr().err
    # … unless its files are gone (a crash while they were written): then it writes them again
    (tmp_path / "summary.json").unlink()
    assert app.execute(recipe, resume) == 0
    again = json.loads((tmp_path / "summary.json").read_text())
    assert again["episodes"] == 3 and again["ledger"] == summary["ledger"]
    assert app.execute(recipe, [*resume, "algo.episodes=5"]) == 0
    rows = list(csv.DictReader((tmp_path / "metrics.csv").open()))
    assert [int(r["episodes"]) for r in rows] == [0, 1, 2, 3, 4, 5]


def test_a_run_records_its_learners_whole_profile_and_resumes_with_it(tmp_path, monkeypatch):
    """``config.yaml`` and the checkpoint hold every key of the learner's profile, the command
    line's over it (they held only the command line's): a resumed run, a checkpoint's evaluation
    and a sweep's point read the profile the run learned with, whatever this version's is."""
    from omegaconf import OmegaConf

    from irdrc.online import recipe
    from irdrc.recipes import evaluate
    from irdrc.runs import app
    from irdrc.sweeps.trials import plan

    args = ["learner=dqn", "algo.episodes=1", "algo.lr=0.002", "logger=none", "progress=false"]
    assert app.execute(recipe, [*args, f"hydra.run.dir={tmp_path}"]) == 0
    algo = OmegaConf.to_container(OmegaConf.load(tmp_path / "config.yaml"))["algo"]
    assert algo == {**configs.recorded_algo(configs.DQN), "episodes": 1, "lr": 0.002}
    assert algo["hidden"] == [32, 32] and algo["eps_decay_episodes"] == 10
    # another version's profile: the run's own is read back
    other = dataclasses.replace(configs.DQN, hidden=(64, 64), eps_decay_episodes=3)
    monkeypatch.setitem(configs.PROFILES, "dqn", other)
    checkpoint = f"resume={tmp_path / 'checkpoint.pt'}"
    resumed = app.prepare(recipe, [checkpoint, "algo.episodes=2"])
    assert resumed.config.algo == dataclasses.replace(configs.DQN, episodes=2, lr=0.002)
    score = [f"checkpoint={tmp_path / 'checkpoint.pt'}", f"hydra.run.dir={tmp_path / 'e'}"]
    assert app.execute(evaluate, [*score, "eval.mc_episodes=0"]) == 0
    (point,) = plan(recipe, [{"learner": "dqn"}], ["algo.episodes=1"])
    assert point["composed"].cfg["algo"] == {**configs.recorded_algo(other), "episodes": 1}


def test_a_learner_planning_beside_its_acting_says_how_late_its_plans_came(tmp_path, capsys):
    """``learner=posterior_anytime`` and ``learner=safe_anytime``: summary.json's ``planning`` and
    the printout's line give the plans made beside the acting and the steps each took to come into
    force; the default learner, which waits for its plans, writes neither."""
    from irdrc.online import recipe
    from irdrc.runs import app

    args = ["algo.episodes=2", "logger=none", "progress=false"]
    for learner, out_dir in (("posterior_anytime", tmp_path / "a"), ("posterior", tmp_path / "w")):
        assert app.execute(recipe, [*args, f"learner={learner}", f"hydra.run.dir={out_dir}"]) == 0
    plans = json.loads((tmp_path / "a" / "summary.json").read_text())["planning"]
    assert plans["sweeps_per_step"] == 1 and plans["plans_made_beside_acting"] >= 2
    assert 1 <= plans["plan_lag_steps_median"] <= plans["plan_lag_steps_max"]
    line = (
        f"it planned beside its acting, 1 sweep of value iteration a step: "
        f"{plans['plans_made_beside_acting']} plans, in force a median of "
        f"{plans['plan_lag_steps_median']} steps after their draw"
    )
    out = capsys.readouterr().out
    assert out.count(line) == 1
    assert "planning" not in json.loads((tmp_path / "w" / "summary.json").read_text())

    safe = ["learner=safe_anytime", "algo.target_miss=0.1", f"hydra.run.dir={tmp_path / 's'}"]
    assert app.execute(recipe, [*args, *safe]) == 0
    plans = json.loads((tmp_path / "s" / "summary.json").read_text())["planning"]
    assert plans["evaluations_per_step"] == 1 and plans["plans_made_beside_acting"] >= 2
    line = (
        "it planned beside its acting, 1 unit of work (a batch of sweeps, the model, or one "
        f"policy evaluation of the LP's dual) a step: {plans['plans_made_beside_acting']} plans, "
        f"in force a median of {plans['plan_lag_steps_median']} steps after their data"
    )
    assert capsys.readouterr().out.count(line) == 1


def test_a_stream_without_an_event_yet_writes_its_summary(tmp_path, capsys):
    """Two 7-step episodes with no event: the cumulative miss detection is undefined. The run
    ends well (it raised on writing summary.json), with null there and 'n/a' in the printout;
    each episode is evaluated."""
    from irdrc.online import recipe
    from irdrc.runs import app

    args = ["env.horizon=7", "algo.episodes=2", "env.p0.road=0"]
    quiet = ["env.p0.weather=0", "env.p0.speed=0", "env.p0.object=0", "env.p1.road=0"]
    quiet += ["env.p1.weather=0", "env.p1.speed=0", "env.p1.object=0", "reward.r4=0"]
    run = [f"hydra.run.dir={tmp_path}", "logger=none", "progress=false"]
    assert app.execute(recipe, [*args, *quiet, *run]) == 0
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary["ledger"]["cumulative_miss_detection"] is None
    # the greedy policy is scored every episode by default, whatever the horizon (not every 400)
    rows = (tmp_path / "metrics.csv").read_text().splitlines()[1:]
    assert [int(r.split(",")[2]) for r in rows] == [0, 1, 2]
    assert "cumulative miss detection n/a (no event yet)" in capsys.readouterr().out


@pytest.mark.parametrize(
    ("first", "stay", "words"),
    [
        (None, None, "never ≥ 0.99"),
        (1, None, "first ≥ 0.99 after 1 episode (the last evaluation)"),
        (4, 0.5, "first ≥ 0.99 after 4 episodes, ≥ 0.99 at 50% of the evaluations since"),
    ],
)
def test_the_printed_ledger_says_when_the_greedy_policy_first_reached_099(
    capsys, first, stay, words
):
    """The console's convergence clause, in words that agree with the count."""
    from types import SimpleNamespace

    from irdrc.online.recipe import print_ledger

    keys = ("regret", "realised_regret", "expected_missed", "realised_missed", "floor_missed")
    row = dict.fromkeys((*keys, "expected_sent", "realised_sent", "cumulative_miss_detection"), 1.0)
    summary = {"episodes_to_99": first, "stay_99": stay, "episodes": 6, "env_steps": 2400}
    summary.update(env_steps_per_second=1.0, seconds_slowest_decision=0.001, decisions_over_1ms=0)
    print_ledger(row, summary, SimpleNamespace(learner="posterior"))
    assert f"greedy policy: {words}\n" in capsys.readouterr().out


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["algo.batch_size=64"], "algo.batch_size is read by learner=dqn|dqn_paper, not by"),
        (["algo.batch_sise=64"], "unknown key(s) algo.batch_sise"),
        (["learner=dqn", "algo.batch_sze=64"], "did you mean algo.batch_size?"),
        (["learner=nobody"], "learner='nobody' must be one of"),
        (
            ["learner=sac"],
            "learner=sac is not a learner on one vehicle's stream: use python recipes/sac.py",
        ),
        (["learner=vdn"], "use python recipes/fleet.py learner=vdn"),
        (["learner=dqn_lagrangian"], "use python recipes/constrained.py learner=dqn_lagrangian"),
        (["env.actions=continuous"], "env.actions=continuous"),
        (["learner=safe", "algo.target_miss=1.5"], "algo.target_miss=1.5"),
    ],
)
def test_the_recipe_refuses_before_any_work(tmp_path, capsys, args, message):
    from irdrc.online import recipe
    from irdrc.runs import app

    run_dir = tmp_path / "run"
    code = app.execute(recipe, ["learner=posterior", *args, f"hydra.run.dir={run_dir}"])
    assert code == 2 and message in capsys.readouterr().err
    assert not run_dir.exists()


@pytest.mark.parametrize("learner", ["safe", "safe_anytime"])
def test_a_safe_run_past_the_dense_limit_whose_chain_does_not_fit_says_so_first(
    tmp_path, capsys, monkeypatch, learner
):
    """Past the dense limit the safe learners plan on the LP's dual, whose sparse chain SuperLU
    factorises (``env=large``'s does not fit in 24 GB). With both limits lowered under the paper
    model's 352 states and SuperLU out of memory, the run stops before its first episode with the
    chain's size in one line (the constrained optimum it is read against is solved first)."""
    import scipy.sparse.linalg

    from irdrc.core import chains, sizes
    from irdrc.online import recipe
    from irdrc.runs import app

    def no_memory(_):
        raise MemoryError

    monkeypatch.setattr(sizes, "DENSE_LIMIT_BYTES", 16 * 300**2)
    monkeypatch.setattr(chains, "SPARSE_FROM_STATES", 100)
    monkeypatch.setattr(scipy.sparse.linalg, "splu", no_memory)
    run_dir = tmp_path / "run"
    code = app.execute(recipe, [f"learner={learner}", f"hydra.run.dir={run_dir}"])
    err = capsys.readouterr().err
    assert code == 2 and "the LU of the sparse chain of S = 352 states does not fit" in err
    assert not (run_dir / "metrics.csv").exists()


def test_onlines_own_learner_example_runs_as_printed_and_prints_what_the_page_says():
    """ONLINE.md's *Your own learner on one stream*: its code, run as printed in a fresh
    interpreter, prints exactly the line the page shows (the stream and the coin are seeded)."""
    import subprocess
    import sys
    from pathlib import Path

    page = (Path(__file__).parents[1] / "docs" / "ONLINE.md").read_text()
    section = page.split("## Your own learner on one stream\n", 1)[1].split("\n## ", 1)[0]
    code = section.split("```python\n", 1)[1].split("```", 1)[0]
    shown = section.split("```text\n", 1)[1].split("```", 1)[0].strip()
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=120, check=True
    )
    assert out.stdout.strip() == shown


def test_a_learner_of_ones_own_is_told_which_of_its_methods_went_wrong():
    """``learn_on_stream`` is the door for a user's learner: an action that is neither comm nor
    radar (was an IndexError of the stream's tables, or -1 read as radar), a table that is not a
    policy, a method not written, no episodes, and a scorer of another scenario (whose ledger was
    silently wrong) are each named."""
    import torch

    from irdrc.core.exact import exact_scorer
    from irdrc.online.loop import StreamLearner, learn_on_stream

    params = Params()
    scorer = exact_scorer(params)
    comm = torch.zeros(params.env.num_states, dtype=torch.long)

    class Fixed(StreamLearner):
        name = "fixed"

        def __init__(self, action=0, behaviour=None, greedy=None):
            self.action, self.table, self.deploy = action, behaviour, greedy

        def act(self, state):
            return self.action

        def behaviour(self):
            return (
                torch.nn.functional.one_hot(comm, 2).double() if self.table is None else self.table
            )

        def greedy(self):
            return comm if self.deploy is None else self.deploy

    def run(learner, **kw):
        return learn_on_stream(learner, kw.pop("params", params), scorer, episodes=1, **kw)

    assert run(Fixed()).history[-1]["regret"] > 0
    for action in (2, -1, None):
        with pytest.raises(ValueError, match=rf"fixed\.act\(\d+\) returned {action}: .*0 \(comm"):
            run(Fixed(action=action))
    with pytest.raises(ValueError, match=r"fixed\.behaviour\(\): policy probabilities must"):
        run(Fixed(behaviour=torch.full((params.env.num_states, 2), 0.3)))
    with pytest.raises(ValueError, match=r"fixed\.greedy\(\): policy table has shape \(10,\)"):
        run(Fixed(greedy=torch.zeros(10, dtype=torch.long)))
    with pytest.raises(ValueError, match="scorer is another scenario's"):
        run(Fixed(), params=Params.from_overrides({"env.queue_capacity": 5}))
    with pytest.raises(ValueError, match="episodes=0 must be an integer >= 1"):
        learn_on_stream(Fixed(), params, scorer, episodes=0)
    with pytest.raises(NotImplementedError, match="StreamLearner must define greedy"):
        run(StreamLearner())
