"""``recipes/evaluate.py``: a saved network or policy table scored on any scenario."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
from conftest import TINY_DQN

ROOT = Path(__file__).resolve().parents[1]
TINY = [*TINY_DQN, "eval.mc_episodes=0", "reward.r4=50"]


def run(recipe: str, *args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, str(ROOT / "recipes" / recipe), *args],
        capture_output=True,
        text=True,
        timeout=300,
        cwd=ROOT,
    )


@pytest.fixture(scope="module")
def trained(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("trained")
    r = run("dqn.py", *TINY, f"hydra.run.dir={out}")
    assert r.returncode == 0, r.stderr[-2000:]
    return out


@pytest.mark.e2e
def test_a_network_on_its_own_scenario_scores_as_its_run_did(trained, tmp_path):
    """On the scenario it was trained on, the checkpoint's greedy policy is the run's final
    policy: the same table (policy.csv) and the same exact ratio; the episodic Monte-Carlo row
    comes with the exact episodic row it estimates."""
    out = tmp_path / "e"
    r = run(
        "evaluate.py",
        f"checkpoint={trained / 'checkpoint.pt'}",
        "reward.r4=50",
        "eval.mc_episodes=16",
        "eval.mc_num_envs=16",
        f"hydra.run.dir={out}",
    )
    assert r.returncode == 0, r.stderr[-2000:]
    run_summary = json.loads((trained / "summary.json").read_text())
    s = json.loads((out / "summary.json").read_text())
    assert s["optimality_ratio"] == pytest.approx(run_summary["optimality_ratio"], abs=1e-12)
    assert (out / "policy.csv").read_text() == (trained / "policy.csv").read_text()
    assert {
        "network (exact, long run)",
        "network (exact, episodic)",
        "network (Monte-Carlo, episodic)",
        "optimal (exact, long run)",
    } <= set(s["table"])
    assert "of this scenario's optimum" in r.stdout


@pytest.mark.e2e
def test_a_network_on_another_scenario_and_a_table_elsewhere(trained, tmp_path):
    """Transfer: the network on multilevel (S = 792) is scored against multilevel's own optimum;
    a policy.csv of the paper scenario is scored under other reward weights; a table of another
    size is refused before any work, naming both sizes."""
    r = run(
        "evaluate.py",
        f"checkpoint={trained / 'checkpoint.pt'}",
        "env=multilevel",
        "eval.mc_episodes=0",
        f"hydra.run.dir={tmp_path / 'ml'}",
    )
    assert r.returncode == 0, r.stderr[-2000:]
    s = json.loads((tmp_path / "ml" / "summary.json").read_text())
    assert (
        s["scenario"] == "multilevel"
        and len((tmp_path / "ml" / "policy.csv").read_text().splitlines()) == 793
    )
    assert 0 < s["optimality_ratio"] <= 1 + 1e-9
    r = run(
        "evaluate.py",
        f"policy={trained / 'policy.csv'}",
        "reward.r4=5",
        "eval.mc_episodes=0",
        f"hydra.run.dir={tmp_path / 'p'}",
    )
    assert r.returncode == 0, r.stderr[-2000:]
    assert json.loads((tmp_path / "p" / "summary.json").read_text())["source"].startswith("policy")
    bad = run(
        "evaluate.py",
        f"policy={trained / 'policy.csv'}",
        "env=multilevel",
        f"hydra.run.dir={tmp_path / 'bad'}",
    )
    assert bad.returncode == 2 and "352 states, expected 792" in bad.stderr, bad.stderr
    assert not (tmp_path / "bad").exists()
    neither = run("evaluate.py", f"hydra.run.dir={tmp_path / 'n'}")
    assert neither.returncode == 2 and "exactly one of checkpoint" in neither.stderr


def test_a_wrong_file_is_refused_naming_the_key_and_what_it_needs(tmp_path):
    """The key the user typed, the columns a table needs, and a fleet's table said to be out of
    scope — each one line, exit 2, nothing written."""
    missing = run("evaluate.py", "checkpoint=/no/such.pt", f"hydra.run.dir={tmp_path / 'm'}")
    assert missing.returncode == 2 and missing.stderr.startswith("error: checkpoint=/no/such.pt")
    columns = tmp_path / "columns.csv"
    columns.write_text("a,b\n1,2\n")
    wrong = run("evaluate.py", f"policy={columns}", f"hydra.run.dir={tmp_path / 'w'}")
    assert wrong.returncode == 2 and "d,c,r,w,v,m,action,p_radar" in wrong.stderr, wrong.stderr
    fleet = tmp_path / "fleet.csv"
    fleet.write_text("r,w,d1,c1,v1,m1,d2,c2,v2,m2,action1,action2,optimal1,optimal2\n")
    joint = run("evaluate.py", f"policy={fleet}", f"hydra.run.dir={tmp_path / 'f'}")
    assert joint.returncode == 2 and "a fleet run's policy.csv" in joint.stderr, joint.stderr
    for r in (missing, wrong, joint):
        assert len(r.stderr.splitlines()) == 1 and "Traceback" not in r.stderr
    assert not any((tmp_path / d).exists() for d in "mwf")


def test_a_radar_share_policy_is_scored_exactly_and_by_monte_carlo(tmp_path):
    """A ``rho`` table (``recipes/sac.py``'s policy.csv) against the optimum over ρ: the
    optimum's own shares score 1 exactly, and the Monte-Carlo row plays the shares."""
    from irdrc.core.exact.continuum import ContinuumScorer
    from irdrc.core.params import Params
    from irdrc.recipes import evaluate
    from irdrc.runs.app import execute
    from irdrc.runs.tables import write_policy_csv

    params = Params.from_overrides({"env.actions": "continuous"})
    rho = ContinuumScorer(params).optimal.rho.double()
    write_policy_csv(tmp_path / "policy.csv", rho, params.env.factor_levels, shares=())
    out = tmp_path / "run"
    args = [f"policy={tmp_path / 'policy.csv'}", "eval.mc_episodes=32", "eval.mc_num_envs=32"]
    assert execute(evaluate, [*args, f"hydra.run.dir={out}"]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["metrics"]["avg_reward"] == pytest.approx(summary["optimal"]["avg_reward"])
    mc = summary["table"]["policy (Monte-Carlo, episodic)"]
    # the shares are played, not rounded to comm/radar: the radar fraction is the policy's
    assert mc["radar_fraction"] == pytest.approx(summary["metrics"]["radar_fraction"], abs=0.02)
    binary = summary["table"]["optimal binary (exact, long run)"]["avg_reward"]
    assert summary["metrics"]["avg_reward"] > binary


@pytest.mark.e2e
@pytest.mark.parametrize("recipe", ["sac", "ppo"])
def test_a_radar_share_network_is_scored_as_its_run_did(recipe, tmp_path):
    """A SAC or PPO checkpoint: on its own scenario its shares are the run's final shares
    (policy.csv) with the same exact ratio to the optimum over ρ; on another scenario they are
    scored against that scenario's optimum over ρ."""
    from test_ppo import TINY_PPO
    from test_sac import TINY_SAC

    tiny = TINY_SAC if recipe == "sac" else TINY_PPO
    trained = tmp_path / "trained"
    r = run(f"{recipe}.py", *tiny, "logger=none", f"hydra.run.dir={trained}")
    assert r.returncode == 0, r.stderr[-2000:]
    out = tmp_path / "e"
    r = run(
        "evaluate.py",
        f"checkpoint={trained / 'checkpoint.pt'}",
        "env.actions=continuous",
        "eval.mc_episodes=16",
        "eval.mc_num_envs=16",
        f"hydra.run.dir={out}",
    )
    assert r.returncode == 0, r.stderr[-2000:]
    mine = json.loads((trained / "summary.json").read_text())
    s = json.loads((out / "summary.json").read_text())
    assert s["metrics"]["avg_reward"] == pytest.approx(mine["metrics"]["avg_reward"], abs=1e-9)
    assert (out / "policy.csv").read_text() == (trained / "policy.csv").read_text()
    assert s["source"].startswith(f"{recipe} radar shares trained 2000 env steps")
    assert "policy (Monte-Carlo, episodic)" in s["table"]
    other = run(
        "evaluate.py",
        f"checkpoint={trained / 'checkpoint.pt'}",
        "env.p1.speed=1.0",
        "eval.mc_episodes=0",
        f"hydra.run.dir={tmp_path / 'o'}",
    )
    assert other.returncode == 0, other.stderr[-2000:]
    assert "of this scenario's optimum over ρ" in other.stdout


def test_target_miss_reads_a_table_against_the_lp(tmp_path, capsys):
    """``target_miss=…``: the LP's own randomised policy is 1.0000 of the LP's packets and meets the
    target; the unconstrained optimum sends more than the LP and is over it, by its exact miss
    detection; a target no policy meets (an imperfect radar misses 1 − P_d = 0.1 of the events in
    radar mode) is said, not raised; a radar-share policy and env.actions=continuous are refused."""
    from irdrc.core.cmdp import solve_cmdp
    from irdrc.core.exact import build_model, exact_scorer
    from irdrc.core.params import Params
    from irdrc.recipes import evaluate
    from irdrc.runs.app import execute
    from irdrc.runs.tables import write_policy_csv

    params = Params()
    model = build_model(params)
    lp = solve_cmdp(model, 0.05)
    assert lp.randomised  # a randomised table goes through as one
    write_policy_csv(tmp_path / "lp.csv", lp.policy, params.env.factor_levels)
    optimum = exact_scorer(params)
    write_policy_csv(tmp_path / "opt.csv", optimum.optimal.policy, params.env.factor_levels)

    def scored(table: str, *more: str) -> dict:
        out = tmp_path / table
        args = [f"policy={tmp_path / table}.csv", "target_miss=0.05", "eval.mc_episodes=0", *more]
        assert execute(evaluate, [*args, f"hydra.run.dir={out}"]) == 0
        return json.loads((out / "summary.json").read_text())

    own = scored("lp")
    assert own["lp_ratio"] == pytest.approx(1.0, abs=1e-6) and own["meets_target"] is True
    assert own["lp"]["throughput"] == pytest.approx(lp.value)
    assert "target_miss=0.05: 1.0000 of the LP's packets" in capsys.readouterr().out
    best = scored("opt")
    miss = optimum.optimal_metrics.miss_detection
    assert best["meets_target"] is False and miss > 0.05 and best["lp_ratio"] > 1.0
    assert best["lp_ratio"] == pytest.approx(optimum.optimal_metrics.throughput / lp.value)
    assert f"its long-run miss detection {miss:.4f} over it" in capsys.readouterr().out
    assert "LP at target_miss=0.05 (exact, long run)" in best["table"]

    radar = Params.from_overrides({"env.detection_prob": 0.9})
    write_policy_csv(tmp_path / "radar.csv", [1] * 352, radar.env.factor_levels)
    none = scored("radar", "env.detection_prob=0.9")
    assert none["lp"] is None and none["meets_target"] is False
    assert "no policy meets it on this scenario" in capsys.readouterr().out

    rho = tmp_path / "rho.csv"
    write_policy_csv(rho, [0.5] * 352, params.env.factor_levels, shares=())
    refused = run(
        "evaluate.py", f"policy={rho}", "target_miss=0.05", f"hydra.run.dir={tmp_path / 'x'}"
    )
    assert (
        refused.returncode == 2 and "a radar-share policy's constrained optimum" in refused.stderr
    )
    shares = run(
        "evaluate.py", f"policy={rho}", "target_miss=0.05", "env.actions=continuous",
        f"hydra.run.dir={tmp_path / 'y'}",
    )  # fmt: skip
    assert shares.returncode == 2 and "env.actions=continuous" in shares.stderr, shares.stderr
    assert not (tmp_path / "x").exists() and not (tmp_path / "y").exists()  # before any work


def test_a_comm_radar_table_on_a_scenario_of_radar_shares_means_comm_and_radar(tmp_path):
    """A comm/radar table's action 1 is radar: ρ = 1. On ``env.actions=levels`` it is the last
    level, not level 1 (ρ = 1/(G − 1)); on ``continuous`` it is scored as the shares 0 and 1
    (before, the first was scored as another policy without a word and the second failed). The
    binary optimum's table, so played, earns the binary optimum's reward: ρ ∈ {0, 1} are the
    binary model's actions in every model of MODEL.md § D."""
    import torch

    from irdrc.core.exact import exact_scorer
    from irdrc.core.params import Params
    from irdrc.recipes import evaluate
    from irdrc.runs.app import execute
    from irdrc.runs.tables import write_policy_csv

    params = Params()
    best = exact_scorer(params)
    write_policy_csv(tmp_path / "policy.csv", best.optimal.policy, params.env.factor_levels)
    want = best.optimal_metrics.avg_reward
    policy = f"policy={tmp_path / 'policy.csv'}"
    for actions in ("levels", "continuous"):
        out = tmp_path / actions
        args = [policy, f"env.actions={actions}", "eval.mc_episodes=16", "eval.mc_num_envs=16"]
        assert execute(evaluate, [*args, f"hydra.run.dir={out}"]) == 0
        summary = json.loads((out / "summary.json").read_text())
        assert summary["metrics"]["avg_reward"] == pytest.approx(want, rel=1e-9), actions
    played = (tmp_path / "levels" / "policy.csv").read_text().splitlines()[1:]
    levels = {int(row.split(",")[6]) for row in played}
    assert levels == {0, Params().env.levels - 1}
    with pytest.raises(ValueError, match=r"randomised comm/radar table .* env\.actions=levels"):
        evaluate.fit_actions(
            torch.full((4, 2), 0.5),
            (0.0, 1.0),
            Params.from_overrides({"env.actions": "levels"}),
            "t",
        )
    fifths = (0.0, 0.25, 0.5, 0.75, 1.0)
    with pytest.raises(ValueError, match=r"shares \[0\.25\] are not among .*continuous scores any"):
        evaluate.fit_actions(torch.tensor([0, 1, 4]), fifths, params, "a levels network")


def test_a_checkpoint_without_a_network_to_read_names_its_recipe_and_its_table(tmp_path, capsys):
    """A one-stream tabular learner's checkpoint has no network: the refusal names the recipe and
    learner that wrote it and the run's table, which evaluate scores."""
    from irdrc.online import recipe
    from irdrc.recipes import evaluate
    from irdrc.runs.app import execute

    run_dir = tmp_path / "online"
    args = ["learner=qlearning", "algo.episodes=1", "logger=none", "progress=false"]
    assert execute(recipe, [*args, f"hydra.run.dir={run_dir}"]) == 0
    capsys.readouterr()
    out = [f"hydra.run.dir={tmp_path / 'e'}", "eval.mc_episodes=0"]
    assert execute(evaluate, [f"checkpoint={run_dir / 'checkpoint.pt'}", *out]) == 2
    err = capsys.readouterr().err
    assert "(this one: online learner=qlearning)" in err, err
    assert f"policy={run_dir / 'policy.csv'}" in err, err
    assert execute(evaluate, [f"policy={run_dir / 'policy.csv'}", *out]) == 0


@pytest.mark.parametrize("learner", ["dqn", "dqn_paper"])
def test_a_one_stream_dqn_network_scores_as_its_run_did_and_goes_elsewhere(
    learner, tmp_path, capsys
):
    """``online.py learner=dqn``'s checkpoint holds a network: on its own scenario evaluate scores
    the table the run scored (its policy.csv, its ratio: the target network's greedy table), and
    on a scenario of another state space the network's greedy table there. ``dqn_paper`` scores
    its online network, which the checkpoint holds one update past the table its run scored."""
    from irdrc.online import recipe
    from irdrc.recipes import evaluate
    from irdrc.runs.app import execute

    run_dir = tmp_path / "online"
    args = [f"learner={learner}", "algo.episodes=3", "logger=none", "progress=false"]
    assert execute(recipe, [*args, f"hydra.run.dir={run_dir}"]) == 0
    out = [f"checkpoint={run_dir / 'checkpoint.pt'}", "eval.mc_episodes=0"]
    assert execute(evaluate, [*out, f"hydra.run.dir={tmp_path / 'same'}"]) == 0
    assert "on one stream, trained 1200 env steps" in capsys.readouterr().out
    same = json.loads((tmp_path / "same" / "summary.json").read_text())
    ran = json.loads((run_dir / "summary.json").read_text())
    if learner == "dqn":
        assert same["optimality_ratio"] == pytest.approx(ran["optimality_ratio"], abs=1e-12)
        table = (tmp_path / "same" / "policy.csv").read_text()
        assert table == (run_dir / "policy.csv").read_text()
    assert execute(evaluate, [*out, "env=multilevel", f"hydra.run.dir={tmp_path / 'ml'}"]) == 0
    rows = (tmp_path / "ml" / "policy.csv").read_text().splitlines()
    assert len(rows) - 1 == 792  # multilevel's S (11 queue lengths × 2·2·2·3·3 levels), not 352


def test_a_table_of_another_state_space_says_what_must_match(tmp_path):
    """A table written for another state space (here a longer queue) is refused with what it must
    share with the scenario (it said only "704 states, expected 352")."""
    import torch

    from irdrc.core.params import Params
    from irdrc.runs.tables import read_policy_csv, read_share_csv, write_policy_csv

    longer = Params.from_overrides({"env.queue_capacity": 12})
    write_policy_csv(
        tmp_path / "p.csv", torch.zeros(longer.env.num_states), longer.env.factor_levels
    )
    with pytest.raises(ValueError, match=r"416 states, expected 352 \(.*env\.queue_capacity"):
        read_policy_csv(tmp_path / "p.csv", num_states=352)
    rho = torch.zeros(longer.env.num_states)
    write_policy_csv(tmp_path / "r.csv", rho, longer.env.factor_levels, shares=())
    with pytest.raises(ValueError, match=r"S = 352 states \(a table fits the state space"):
        read_share_csv(tmp_path / "r.csv", 352)


@pytest.mark.parametrize("kind", ["policy", "share"])
def test_a_table_that_is_not_text_is_refused_with_its_name(tmp_path, kind):
    """A policy file that is not UTF-8 text is refused with its path. The policy reader's message
    asked the decode error for an OSError's ``strerror`` and died with an AttributeError; the
    share reader and ``evaluate.py``'s header check let the bare decode error through."""
    from irdrc.runs.tables import read_policy_csv, read_share_csv

    path = tmp_path / "policy.csv"
    path.write_bytes(b"d,c,r,w,v,m,action,p_radar\n\xff\xfe\x00\n")
    read = read_policy_csv if kind == "policy" else lambda p: read_share_csv(p, 352)
    with pytest.raises(ValueError, match=r"policy\.csv: not a text table \(byte \d+"):
        read(path)
    with pytest.raises(ValueError, match="not a readable file"):
        read(tmp_path / "absent.csv")


def test_evaluate_refuses_a_table_that_is_not_text(tmp_path, capsys):
    """``evaluate.py policy=`` on a binary file names the file (it printed the decode error
    alone)."""
    from irdrc.recipes import evaluate
    from irdrc.runs.app import execute

    path = tmp_path / "policy.csv"
    path.write_bytes(b"\xff\xfe" * 64)
    out = [f"hydra.run.dir={tmp_path / 'e'}", "eval.mc_episodes=0"]
    assert execute(evaluate, [f"policy={path}", *out]) == 2
    assert f"{path}: not a text table" in capsys.readouterr().err
