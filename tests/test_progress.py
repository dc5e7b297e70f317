"""The run's progress lines: each shows the evaluation of its own env step, when there is one."""

from __future__ import annotations

from irdrc.runs.progress import RunProgress
from irdrc.runs.report import end_warning


def _eval(steps: int, ratio: float) -> list[dict]:
    return [
        {
            "learner": 0,
            "env_steps": steps,
            "episodes": 0,
            "wall_seconds": 0.0,
            "updates": 0,
            "optimality_ratio": ratio,
        }
    ]


def test_line_shows_the_evaluation_made_at_its_own_step(capsys):
    """The loop reports a batch, then evaluates at the same env step: the line waits for it (it
    printed the previous evaluation's ratio before)."""
    p = RunProgress(1000, True, None, "dqn")
    p.on_eval(_eval(0, 0.4228))
    p.on_batch({"env_steps": 100})
    p.on_eval(_eval(100, 1.0))
    p.close()
    lines = capsys.readouterr().out.splitlines()
    assert lines == [lines[0]] and "100/1000 env steps (10%), ratio 1.0000," in lines[0], lines
    assert "ETA" in lines[0] and "ETA -" not in lines[0]


def test_line_without_an_evaluation_names_where_its_ratio_comes_from(capsys):
    p = RunProgress(1000, True, None, "dqn")
    p.on_eval(_eval(0, 0.4228))
    p.on_batch({"env_steps": 100})
    p.on_batch({"env_steps": 200})  # no evaluation at 100: the line comes now, naming step 0
    p.on_batch({"env_steps": 1000})
    p.close()  # the last line (no evaluation after it) is printed at the end, ETA 0
    lines = capsys.readouterr().out.splitlines()
    assert "100/1000 env steps (10%), ratio 0.4228 at 0," in lines[0], lines
    assert lines[-1].startswith("[dqn] 1000/1000") and "ETA 0 s" in lines[-1], lines


def _hist(*pairs: tuple[int, float], learner: int = 0) -> list[dict]:
    return [{"learner": learner, "env_steps": s, "optimality_ratio": r} for s, r in pairs]


def test_a_run_that_ends_badly_says_so_and_where_its_best_was():
    assert end_warning(_hist((0, 0.42), (1000, 0.995), (2000, 0.999))) is None
    low = end_warning(_hist((0, 0.42), (2016, 1.0), (4000, 0.4228)))
    assert low.startswith("warning: the final greedy policy is 0.4228 of the optimum (below 0.99")
    assert "best evaluation was 1.0000 at 2016 env steps" in low
    fell = end_warning(_hist((0, 0.3), (50_000, 1.0), (200_000, 0.9850)))  # low and fell
    assert "0.0150 below its best" in fell and "at 50000 env steps" in fell
    drift = end_warning(_hist((0, 0.3), (50_000, 1.0), (200_000, 0.9950)))  # within the slack
    assert drift is None
    many = end_warning(_hist((0, 0.5), (10, 1.0)) + _hist((0, 0.5), (10, 0.5), learner=1))
    assert many.startswith("warning: 1 of 2 learners end badly") and "learner 1:" in many
    # twenty learners below: one short line each for five, then a count
    twenty = end_warning([r for i in range(20) for r in _hist((0, 0.5), (10, 0.5), learner=i)])
    lines = twenty.splitlines()
    assert len(lines) == 7 and max(map(len, lines)) < 120, lines
    assert lines[-1] == "  … and 15 more (learners.csv, metrics.csv)"


def test_a_run_below_the_threshold_is_told_the_override_to_try():
    """DQN's warning ends with the one override most likely to help; a run that ends well gets
    no line, advice or not."""
    from irdrc.runs.report import ADVICE

    line = end_warning(_hist((0, 0.3), (50_000, 0.97)), ADVICE["dqn"])
    assert line.startswith("warning: the final greedy policy is 0.9700")
    assert line.endswith("; try " + ADVICE["dqn"]) and "algo.total_frames=" in line
    assert end_warning(_hist((0, 0.3), (50_000, 0.999)), ADVICE["dqn"]) is None


def test_every_profile_a_learner_recipe_runs_is_told_an_override_that_exists():
    """Each profile of ``irdrc/conf/algo`` that ends through the learner report (all but the
    constrained recipe's) has advice, and the advice starts with an override its recipe accepts:
    a profile that exists, or a key of the profile's config."""
    from dataclasses import fields
    from pathlib import Path

    import yaml

    from irdrc.agents.configs import DQNConfig, QLearningConfig
    from irdrc.runs.report import ADVICE

    conf = Path(__file__).resolve().parents[1] / "irdrc" / "conf" / "algo"
    profiles = (yaml.safe_load(f.read_text()) for f in conf.glob("*.yaml"))
    names = {(data.get("algo") or data)["name"] for data in profiles}
    names.remove("dqn_lagrangian")  # the constrained recipe scores it against the LP, not here
    assert names <= set(ADVICE), names - set(ADVICE)
    for name in names:
        override = ADVICE[name].split()[0]
        key, value = override.split("=", 1)
        if key in ("algo", "network"):  # a config group's option
            assert (conf.parent / key / f"{value}.yaml").is_file(), (name, override)
        else:
            config = QLearningConfig if name.startswith("qlearning") else DQNConfig
            assert key.startswith("algo.") and key[5:] in {f.name for f in fields(config)}, override


def test_a_resumed_run_starts_from_its_last_evaluation(capsys):
    from irdrc.runs.progress import RunProgress

    p = RunProgress(1000, True, None, "ppo")
    p.resumed(_hist((0, 0.3), (400, 0.97)))
    p.on_batch({"env_steps": 500})
    p.close()
    assert "ratio 0.9700 at 400" in capsys.readouterr().out


def test_a_busy_machine_is_named_in_the_progress_line(monkeypatch):
    from irdrc.runs import progress

    monkeypatch.setattr(progress.os, "cpu_count", lambda: 2)
    monkeypatch.setattr(progress.os, "getloadavg", lambda: (4.2, 3.0, 2.0))
    assert progress.busy() == ", machine busy: load 4.2 on 2 cores"
    monkeypatch.setattr(progress.os, "getloadavg", lambda: (1.9, 1.0, 1.0))
    assert progress.busy() == ""


def test_the_advice_to_train_longer_is_twice_the_runs_own_env_steps():
    """A run of 10⁷ env steps is not told to train 8 × 10⁶ (fewer than it ran): the advice is
    fitted to the run that gets it."""
    from types import SimpleNamespace

    from irdrc.runs.report import LearnerRun

    def advice(name: str, env_steps: int) -> str:
        record = SimpleNamespace(env_steps=env_steps)
        return LearnerRun(name, record, [], [], [{}], 1, None, 0).advice

    assert advice("dqn", 10_000_000).startswith("algo.total_frames=20000000 ")
    assert advice("dqn", 4_000_000).startswith("algo.total_frames=8000000 ")
    assert advice("dqn_levels", 1_000_000).startswith("algo.total_frames=2000000 ")
    assert advice("qlearning", 10**6).startswith("algo.episodes=2400")


def test_a_long_lp_is_announced_before_it_starts(tmp_path, capsys, monkeypatch):
    """The constrained optimum's LP is one solver call with no progress of its own (minutes at a
    few thousand states): beyond ``LP_NOTICE_STATES`` a line says it started, before the result,
    and where the miss target is the only constraint that the dual is faster."""
    from irdrc.recipes.constrained import recipe
    from irdrc.runs import app, progress

    args = ["target_miss=0.1", f"hydra.run.dir={tmp_path / 'a'}"]
    assert app.execute(recipe, args) == 0
    assert "[lp]" not in capsys.readouterr().out  # 352 states: no notice
    monkeypatch.setattr(progress, "LP_NOTICE_STATES", 300)
    assert app.execute(recipe, ["target_miss=0.1", f"hydra.run.dir={tmp_path / 'b'}"]) == 0
    out = capsys.readouterr().out
    assert "[lp] solving the constrained optimum over 352 states" in out
    assert out.index("[lp]") < out.index("constrained optimum (LP)")
    assert "learner=dual finds the same optimum" in out  # the miss target alone: the dual's hint
    args = ["target_miss=0.1", "max_drop=0.5", f"hydra.run.dir={tmp_path / 'c'}"]
    assert app.execute(recipe, args) == 0
    assert "learner=dual" not in capsys.readouterr().out  # the dual takes the miss target alone
