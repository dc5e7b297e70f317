"""``recipes/bench_online.py``: its tables (``irdrc.bench.online_tables``) on hand-made runs, and the
recipe end to end on a tiny grid."""

from __future__ import annotations

import csv
import re
from pathlib import Path

import pytest
from conftest import load, python_as_typed, run_recipe

from irdrc.bench.online_jobs import Job
from irdrc.bench.online_tables import (
    calibration_note,
    lagrangian_row,
    learner_table,
    run_row,
    safe_table,
)


def history(ratios: list[float], regret_step: float = 10.0, cum: float = 0.04) -> list[dict]:
    return [
        {
            "episodes": e,
            "env_steps": 400 * e,
            "optimality_ratio": r,
            "regret": regret_step * e,
            "expected_missed": 2.0 * e,
            "expected_events": 100.0 * e,
            "floor_missed": 1.0 * e,
            "realised_regret": regret_step * e,
            "realised_missed": 2.0 * e,
            "cumulative_miss_detection": cum if e else None,
            "lp_ratio": 0.9,
            "meets_target": 1.0,
            "miss_detection": 0.045,
        }
        for e, r in enumerate(ratios)
    ]


def test_a_run_row_reads_convergence_and_the_ledger_at_the_window():
    """0.99 first at episode 2; 2 of the 3 later evaluations stay there; the ledger is read at the
    window (episode 3), not at the run's end."""
    hist = history([0.5, 0.96, 0.995, 0.98, 0.991, 0.999])
    row = run_row(Job("dqn", "paper", 10, 5), {"history": hist, "wall_seconds": 1.0}, 3)
    assert (row["episodes_to_95"], row["episodes_to_99"]) == (1, 2)
    assert row["stay_99"] == 2 / 3 and row["within_window"]
    assert row["regret"] == 30.0 and row["expected_missed"] == 6.0


def test_the_learner_table_pools_random_draws_and_reports_medians_and_worst():
    runs = [
        run_row(
            Job("posterior", f"draw {i}", 10, 4),
            {"history": history(r, s), "wall_seconds": w, "slowest_decision": d},
            3,
        )
        for i, (r, s, w, d) in enumerate(
            [([0.5, 0.995, 1, 1], 10.0, 2.0, 0.002), ([0.5, 0.9, 0.9, 0.9], 30.0, 5.0, 0.032)]
        )
    ]
    table = learner_table(runs, 3)
    assert "| posterior | random draws | 1/2 | 1 (1) |" in table
    assert "| 60 (90) |" in table  # regret at episode 3: 30 and 90, median 60, worst 90
    assert "slowest decision, ms, median (worst) | wall time" in table.splitlines()[0]
    # slowest decisions 2 and 32 ms: median 17, worst 32; wall seconds 2 and 5: median 3.5
    assert table.splitlines()[2].endswith("| 17 (32) | 3.5 |")


def test_the_lagrangian_row_counts_evaluations_over_the_target_and_its_end():
    """Read at the first batch past each 400 env steps: 0.5 and 0.2 are over 0.1, 0.08 is not."""
    trace = [
        {"env_steps": 100, "cumulative_miss": 1.0},  # before the first episode's end: not read
        {"env_steps": 400, "cumulative_miss": 0.5},
        {"env_steps": 500, "cumulative_miss": 0.4},
        {"env_steps": 800, "cumulative_miss": 0.2},
        {"env_steps": 1200, "cumulative_miss": 0.08},
    ]
    row = lagrangian_row(Job("dqn_lagrangian", "paper", 10, 3, 0.1), {"trace": trace}, 400)
    assert row["violations"] == 2 and row["points"] == 3
    assert row["worst_cumulative_miss"] == 0.5 and row["final_cumulative_miss"] == 0.08


def test_the_safe_table_puts_the_lagrangian_training_beside_the_safe_learner():
    job = Job("safe", "paper", 10, 3, 0.05)
    conf = {"miss_mean": 0.05, "miss_sd": 0.001, "p_within_target": 0.4, "draws": 50}
    # the target's own cost, 0.02 per step: 24 of the regret of 30 at the window (1 200 steps)
    within = run_row(
        job,
        {
            "history": history([0, 0.5, 0.9, 0.95]),
            "wall_seconds": 1,
            "plan_confidence": conf,
            "lp_cost": 0.02,
        },
        3,
    )
    over = run_row(
        job,
        {"history": history([0, 0.5, 0.9, 0.95], 20.0, cum=0.06), "wall_seconds": 1, "lp_cost": 0},
        3,
    )
    assert within["learning_regret"] == pytest.approx(6.0) and over["learning_regret"] == 60.0
    trace = [{"env_steps": 400, "cumulative_miss": 0.3}, {"env_steps": 800, "cumulative_miss": 0.2}]
    lag = [lagrangian_row(Job("dqn_lagrangian", "paper", 10, 3, 0.05), {"trace": trace}, 400)]
    table = safe_table([within, over], lag, 3)
    assert "| 0.05 | paper | 1/2 | 0.0600 |" in table
    assert "0/1, worst 0.3000, at the end 0.2 |" in table
    assert "| 0.9 (0.9000) | 33 (60) |" in table  # beyond the LP's own: 6 and 60
    # the one run with a stated confidence: P 0.4, sd 0.001 = 2 % of the target; then the safe
    # runs' slowest decisions and wall time, 1 s each, before the Lagrangian DQN
    assert "| 2/2 | 0.40; 2.0 % | — | 1 | 0/1, worst" in table  # no decision timed: —


def test_with_both_safe_profiles_the_safe_table_names_each_in_a_first_column():
    """``safe_learners=[safe,safe_anytime]``: a row per profile and cell, named; one profile alone
    keeps the table as it was (no learner column)."""
    res = {"history": history([0, 0.5, 0.9, 0.95]), "wall_seconds": 1, "lp_cost": 0}
    rows = [run_row(Job(n, "paper", 10, 3, 0.05), res, 3) for n in ("safe", "safe_anytime")]
    both = safe_table(rows, [], 3)
    assert both.splitlines()[0].startswith("| learner | target_miss | scenario |")
    assert (
        "| safe | 0.05 | paper | 1/1 |" in both and "| safe_anytime | 0.05 | paper | 1/1 |" in both
    )
    assert safe_table(rows[:1], [], 3).splitlines()[0].startswith("| target_miss | scenario |")


def test_a_failed_run_stops_the_benchmark_at_once_naming_it(tmp_path, monkeypatch):
    """A run that raises ends the benchmark with its name, and the runs not begun are cancelled
    (before, the pool ran every queued run and then raised). The pool is a stand-in that finishes
    the first run with an error and leaves the others queued."""
    import concurrent.futures as cf

    from irdrc.bench.online_jobs import execute

    calls = []

    class Pool:
        def __init__(self, *args, **kwargs):
            self.futures = []

        def __enter__(self):
            return self

        def __exit__(self, *exc):
            self.shutdown()

        def submit(self, fn, job, gamma):
            fut = cf.Future()
            if not self.futures:
                fut.set_exception(ValueError("no such scenario"))
            self.futures.append(fut)
            return fut

        def shutdown(self, wait=True, cancel_futures=False):
            calls.append(cancel_futures)
            if cancel_futures:
                for fut in self.futures:
                    fut.cancel()

    monkeypatch.setattr(cf, "ProcessPoolExecutor", Pool)
    jobs = [Job("posterior", "paper", s, 2) for s in range(10, 14)]
    with pytest.raises(RuntimeError, match="run posterior__paper__10 failed: no such scenario"):
        execute(jobs, tmp_path, workers=1, resume=False, gamma=0.99)
    assert calls[0] is True and list((tmp_path / "runs").iterdir()) == []


def test_a_kept_run_with_other_keys_is_refused_before_any_work(tmp_path, monkeypatch):
    """``resume=true`` keeps a finished run only if it ran the job this invocation plans: a
    result of 3 episodes is not read as one of 2 (before, its file name alone matched). One
    written before results recorded their job is kept as it is."""
    import concurrent.futures as cf
    import json

    from irdrc.bench.online_jobs import execute, ran

    class Pool:  # nothing may run
        def __init__(self, *args, **kwargs):
            pass

        def submit(self, *args):
            raise AssertionError("a run began")

        def shutdown(self, wait=True, cancel_futures=False):
            pass

    monkeypatch.setattr(cf, "ProcessPoolExecutor", Pool)
    job = Job("posterior", "paper", 10, 3)
    (tmp_path / "runs").mkdir()
    path = tmp_path / "runs" / f"{job.name}.json"
    path.write_text(json.dumps({"history": [], "job": ran(job, 0.99)}))
    with pytest.raises(ValueError, match=r"ran with other keys \(episodes 3 → 2\); resume with"):
        execute([Job("posterior", "paper", 10, 2)], tmp_path, workers=1, resume=True, gamma=0.99)
    with pytest.raises(ValueError, match=r"\(optimum_gamma 0.99 → 0.9\)"):
        execute([job], tmp_path, workers=1, resume=True, gamma=0.9)
    assert execute([job], tmp_path, workers=1, resume=True, gamma=0.99) == (
        {job.name: {"history": [], "job": ran(job, 0.99)}},
        1,
    )
    path.write_text(json.dumps({"history": []}))  # an earlier version's result
    assert (
        execute([Job("posterior", "paper", 10, 2)], tmp_path, workers=1, resume=True, gamma=0.99)[1]
        == 1
    )


def test_a_signal_ends_every_worker_and_says_how_to_go_on(tmp_path, monkeypatch):
    """SIGINT or SIGTERM while the runs go on cancels the runs not begun, ends the running ones
    and says how to go on (before, the pool's exit waited for every queued run, silently). The
    stand-in pool finishes one run and is interrupted while it waits for the next."""
    import concurrent.futures as cf
    import signal

    from irdrc.bench.online_jobs import execute
    from irdrc.runs.compose import recipe_call
    from irdrc.runs.signals import RunInterrupted, Signalled

    calls = []

    class Pool:
        def __init__(self, *args, **kwargs):
            self.futures = []

        def submit(self, fn, job, gamma):
            fut = cf.Future()
            if not self.futures:
                fut.set_result({"history": [], "seconds": 1.0})
            elif len(self.futures) == 1:
                fut.set_exception(Signalled(signal.SIGINT))
            self.futures.append(fut)
            return fut

        def __enter__(self):
            return self

        def __exit__(self, *exc):
            self.shutdown()

        def shutdown(self, wait=True, cancel_futures=False):
            calls.append(cancel_futures)

    monkeypatch.setattr(cf, "ProcessPoolExecutor", Pool)
    monkeypatch.setattr(cf, "as_completed", list)  # in the order submitted
    jobs = [Job("posterior", "paper", s, 2) for s in range(10, 14)]
    with pytest.raises(RunInterrupted) as err:
        execute(jobs, tmp_path, workers=1, resume=False, gamma=0.99)
    assert err.value.code == 130 and calls == [True]
    assert str(err.value) == (
        f"stopped by SIGINT: 1 of 4 runs are kept in {tmp_path / 'runs'}; go on with: "
        f"{python_as_typed(Path.cwd())} "
        f"{recipe_call('bench_online')} resume=true hydra.run.dir={tmp_path}"
    )
    assert [p.name for p in (tmp_path / "runs").iterdir()] == ["posterior__paper__10.json"]


@pytest.mark.e2e
def test_ctrl_c_stops_the_benchmark_at_once_and_the_printed_command_finishes_it(tmp_path):
    """Ctrl-C (SIGINT to the process group) while two runs go on: the benchmark and every worker
    end within seconds, the finished runs are kept, and the command it prints runs the rest."""
    import os
    import signal
    import subprocess
    import sys
    import time

    root = Path(__file__).resolve().parent.parent
    grid = (
        "scenarios=[paper]",
        "learners=[dqn]",
        "paper_learners=[]",
        "seeds=[10,11,12,13]",
        "random_draws=0",
        "episodes=40",
        "window=5",
        "safe_targets=[]",
        "workers=2",
    )
    proc = subprocess.Popen(
        [sys.executable, "recipes/bench_online.py", *grid, f"hydra.run.dir={tmp_path}"],
        cwd=root,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,
    )
    t0 = time.monotonic()
    while not list((tmp_path / "runs").glob("*.json")):
        assert proc.poll() is None, proc.communicate()
        assert time.monotonic() - t0 < 240, "no run finished in time"
        time.sleep(0.2)
    os.killpg(proc.pid, signal.SIGINT)
    t1 = time.monotonic()
    stdout, stderr = proc.communicate(timeout=60)
    assert proc.returncode == 130 and "Traceback" not in stderr, (stdout, stderr)
    assert time.monotonic() - t1 < 20  # a run takes ~10 s here; none is waited for
    for _ in range(50):  # the workers and the resource tracker leave with it
        try:
            os.killpg(proc.pid, 0)
        except ProcessLookupError:
            break
        time.sleep(0.1)
    else:
        raise AssertionError("a process of the benchmark outlived it")
    assert "leaked" not in stderr
    kept = len(list((tmp_path / "runs").glob("*.json")))
    assert 1 <= kept < 4 and f"{kept} of 4 runs are kept" in stderr
    printed = stderr.split("go on with: ", 1)[1].splitlines()[0]
    here = python_as_typed(root)  # the benchmark's python (the venv's: relative to its cwd)
    assert printed == f"{here} recipes/bench_online.py resume=true hydra.run.dir={tmp_path}"
    assert run_recipe("bench_online", tmp_path, "resume=true") == 0
    assert len(list(csv.DictReader((tmp_path / "bench_online.csv").open()))) == 4
    assert (
        f"{kept} more were kept from an earlier one" in (tmp_path / "bench_online.md").read_text()
    )


def test_the_calibration_note_holds_each_plans_stated_spread_against_its_true_miss():
    """Every hand-made plan's exact miss is 0.045 (``history``): posterior means 0.0445, 0.048
    and 0.06 with sd 0.001 put it 0.5, 3 and 15 sds away; a radar-everywhere plan (sd 0, its mean
    the truth) is within; the truth is below the posterior mean in two (0.045 < 0.048 and 0.06,
    not 0.0445 nor 0.045); a run without a stated confidence is left out."""
    job = Job("safe", "paper", 10, 3, 0.05)
    rows = [
        run_row(
            job,
            {
                "history": history([0, 0.5, 0.9, 0.95]),
                "wall_seconds": 1,
                "plan_confidence": {"miss_mean": m, "miss_sd": sd, "p_within_target": p},
            },
            3,
        )
        for m, sd, p in [
            (0.0445, 0.001, 0.6),
            (0.048, 0.001, 1.0),
            (0.06, 0.001, 0.0),
            (0.045, 0.0, 1.0),
        ]
    ]
    rows.append(run_row(job, {"history": history([0, 0.5, 0.9, 0.95]), "wall_seconds": 1}, 3))
    note = calibration_note(rows)
    assert "over the 4 safe runs" in note
    assert "within one posterior sd of the posterior mean in 2 (50 %" in note
    assert "within two in 2 (50 %" in note
    assert (
        "below the posterior mean (fewer misses than the posterior expects) in 2 of the 4" in note
    )
    assert "average 0.65; 4 of the 4 plans meet it" in note
    assert calibration_note(rows[-1:]) == ""


@pytest.mark.e2e
def test_the_benchmark_runs_every_kind_of_job_writes_its_files_and_resumes(tmp_path):
    """A learner on every named scenario, one on `paper` alone and the safe learner, 3 episodes
    each (the safe learner's stop at the window, 2): a row per run, the tables, the calibration
    note and the figure; then ``resume=true`` runs nothing again and remakes the same rows, its
    time line saying that the runs were kept."""
    grid = (
        "scenarios=[paper]",
        "learners=[posterior]",
        "paper_learners=[qlearning]",
        "seeds=[10]",
        "paper_seeds=[11]",
        "random_draws=0",
        "episodes=3",
        "window=2",
        "safe_targets=[0.1]",
        "safe_scenarios=[paper]",
        "safe_seeds=[12]",
        "lagrangian_seeds=[]",
        "workers=1",
    )
    assert run_recipe("bench_online", tmp_path, *grid) == 0
    rows = list(csv.DictReader((tmp_path / "bench_online.csv").open()))
    assert [(r["learner"], r["scenario"], r["seed"]) for r in rows] == [
        ("posterior", "paper", "10"),
        ("qlearning", "paper", "11"),
        ("safe", "paper", "12"),
    ]
    for r in rows:
        assert -2 < float(r["final_ratio"]) <= 1 + 1e-9 and float(r["regret"]) > -1e-6
    safe = rows[-1]
    # P_d = 1 on `paper`: the budget holds the vehicle's count under the target at every step
    assert safe["violations"] == "0" and float(safe["worst_cumulative_miss"]) <= 0.1
    assert 0 <= float(safe["plan_p_within_target"]) <= 1 and float(safe["plan_miss_sd"]) >= 0
    table = (tmp_path / "bench_online.md").read_text()
    assert "| posterior | paper | " in table and "| qlearning | paper | " in table
    assert "| 0.1 | paper | 1/1 | " in table
    assert "over the 1 safe run:" in table
    assert "1 seed per named scenario (10; qlearning: 11); 3 episodes per run;" in table
    assert (tmp_path / "bench_online_paper.png").stat().st_size > 0
    kept = {p.name: p.stat().st_mtime_ns for p in (tmp_path / "runs").iterdir()}
    assert len(kept) == 3
    before = (tmp_path / "bench_online.csv").read_text()
    assert run_recipe("bench_online", tmp_path, *grid, "resume=true") == 0
    assert {p.name: p.stat().st_mtime_ns for p in (tmp_path / "runs").iterdir()} == kept
    assert (tmp_path / "bench_online.csv").read_text() == before
    # its time line counts this invocation's runs only, and says so
    assert "3 more were kept from an earlier one" in (tmp_path / "bench_online.md").read_text()
    assert "kept from" not in table


@pytest.mark.parametrize(
    "override, message",
    [
        ("learners=[nobody]", "learners: 'nobody' must be one of"),
        ("scenarios=[nowhere]", "scenarios[0]='nowhere' must be one of"),
        ("window=300", "window=300 must be <= episodes=200"),
        ("safe_targets=[1.5]", "safe_targets"),
        ("safe_learners=[dqn]", "safe_learners: 'dqn' must be one of safe, safe_anytime"),
    ],
)
def test_the_benchmark_refuses_a_bad_grid_before_any_work(override, message):
    with pytest.raises(ValueError, match=re.escape(message)):
        load("bench_online", override)
