"""Sweeps: grid parsing and validation, and real Ray Tune runs inside a loopback-only namespace."""

from __future__ import annotations

import csv
import json
import os
import shlex
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import pytest
from conftest import load, python_as_typed

from irdrc.runs.grid import format_value, parse_grid, point_id, point_overrides, scenario_of

ROOT = Path(__file__).resolve().parents[1]


def _unshare_works() -> bool:
    if shutil.which("unshare") is None:
        return False
    return subprocess.run(["unshare", "-n", "true"], capture_output=True).returncode == 0


needs_ray_netns = pytest.mark.skipif(
    not _unshare_works(),
    reason="`unshare -n` is unavailable: Ray may only start in a loopback-only namespace",
)


def sweep(tmp_path: Path, *overrides: str, timeout: int = 400) -> subprocess.CompletedProcess:
    """Run recipes/sweep.py inside `unshare -n` (Ray must not reach beyond loopback)."""
    pytest.importorskip("ray")
    cmd = shlex.join(
        [
            sys.executable,
            str(ROOT / "recipes" / "sweep.py"),
            *overrides,
            "ray.num_cpus=2",
            f"hydra.run.dir={tmp_path}",
        ]
    )
    return subprocess.run(
        ["unshare", "-n", "sh", "-c", f"ip link set lo up; exec {cmd}"],
        capture_output=True,
        text=True,
        timeout=timeout,
        cwd=ROOT,
    )


def rows(path: Path) -> list[dict]:
    return list(csv.DictReader(path.open()))


def test_parse_grid_product_and_ids():
    pts = parse_grid({"env.p1.speed": [0.1, 0.5], "seed": [0, 1, 2]})
    assert len(pts) == 6 and pts[0] == {"env.p1.speed": 0.1, "seed": 0}
    assert point_overrides(pts[-1]) == ["env.p1.speed=0.5", "seed=2"]
    assert len({point_id(p) for p in pts}) == 6
    assert point_id({"a": 1, "b": 2}) == point_id({"b": 2, "a": 1})
    assert (
        format_value([1, "x"]) == "[1,x]"
        and format_value(None) == "null"
        and format_value(True) == "true"
    )
    assert scenario_of(["env=ref_impl", "reward.r4=50", "seed=1"]) == "ref_impl[reward.r4=50]"


@pytest.mark.parametrize(
    ("grid", "match"),
    [
        (None, "empty"),
        ({}, "empty"),
        ({"seed": []}, "non-empty list"),
        ({"seed": 3}, "non-empty list"),
        ("seed", "mapping"),
        ({"seed": [1, 1]}, "repeats"),
        ({"a=b": [1]}, "config key"),
    ],
)
def test_parse_grid_rejects(grid, match):
    with pytest.raises(ValueError, match=match):
        parse_grid(grid)


@pytest.mark.parametrize(
    ("overrides", "msg"),
    [
        (["sweep.grid={}"], "sweep.grid is empty"),
        (["sweep.grid={seed: 3}"], "sweep.grid.seed=3"),
        (["sweep.grid={env.p1.sped: [0.1]}"], "sped"),
        # a misspelt key in the grid or the base gets the closest valid one, as on a command line
        (
            ["sweep.grid={reward.r44: [5,50]}"],
            r"unknown key 'reward.r44' in dqn; did you mean reward.r4\?",
        ),
        (["sweep.grid={seed: [0]}", "sweep.base=['algo.lrr=1']"], r"did you mean algo.lr\?"),
    ],
)
def test_bad_grid_is_refused_before_ray_starts(overrides, msg):
    """The checks a sweep runs before starting Ray (the command line runs the same, see
    tests/test_errors.py for the one-line answer)."""
    with pytest.raises(ValueError, match=msg):
        load("sweep", *overrides)  # plans (composes and checks every point) before any trial


def test_a_cluster_address_that_nothing_answers_at_is_refused_at_once():
    """``ray.address=HOST:PORT`` where nothing listens: Ray retried for minutes, printing warnings,
    and the sweep ended INCOMPLETE without a word of why. The address is checked first (a
    malformed one at load); an address that answers passes."""
    import socket

    from irdrc.sweeps.tune_runner import check_reachable

    with pytest.raises(
        ValueError, match=r"must be local .*, auto .*, HOST:PORT or ray://HOST:PORT"
    ):
        load("sweep", "sweep.grid={seed: [0]}", "ray.address=nowhere")
    with socket.socket() as server:  # a port that listens, then a port that is closed
        server.bind(("127.0.0.1", 0))
        server.listen()
        port = server.getsockname()[1]
        check_reachable(f"127.0.0.1:{port}")
        check_reachable(f"ray://127.0.0.1:{port}")
    with pytest.raises(ValueError, match=rf"ray.address=127.0.0.1:{port}: nothing answers there"):
        check_reachable(f"127.0.0.1:{port}", timeout=2.0)
    check_reachable("local")  # Ray's own: nothing to check
    check_reachable("auto")


TINY_DQN = "sweep.base=['algo.num_envs=8','algo.frames_per_batch=32','algo.total_frames=640','algo.init_random_frames=128','algo.buffer_size=640','algo.batch_size=32','eval.every_frames=320','eval.mc_episodes=0']"


@pytest.mark.e2e
@needs_ray_netns
def test_dqn_grid_2x2(tmp_path):
    r = sweep(tmp_path, "method=dqn", "sweep.grid={reward.r4: [5,50], seed: [0,1]}", TINY_DQN)
    assert r.returncode == 0, (r.stdout[-3000:], r.stderr[-3000:])
    table = rows(tmp_path / "summary.csv")
    assert [(t["reward.r4"], t["seed"], t["status"]) for t in table] == [
        ("5", "0", "DONE"),
        ("5", "1", "DONE"),
        ("50", "0", "DONE"),
        ("50", "1", "DONE"),
    ]
    assert all(
        float(t["optimality_ratio"]) <= 1.0 + 1e-9 and int(t["env_steps"]) == 640 for t in table
    )
    for t in table:
        d = tmp_path / "trials" / t["point_id"]
        assert (d / "summary.json").is_file() and (d / "metrics.csv").read_text().startswith(
            "learner,env_steps"
        )
    assert r.stdout.count("→ DONE") == 4 and "ETA" in r.stdout


@pytest.mark.e2e
@needs_ray_netns
def test_crash_marks_error_and_resume_reruns_only_it(tmp_path):
    grid = "sweep.grid={reward.r4: [5,50], seed: [0,1]}"
    base = "sweep.base=['eval.mc_episodes=0']"
    r = sweep(tmp_path, "method=solve", grid, base, "sweep.fail_on=['seed=1','reward.r4=50']")
    assert r.returncode != 0
    status = {(t["reward.r4"], t["seed"]): t["status"] for t in rows(tmp_path / "summary.csv")}
    assert status == {
        ("5", "0"): "DONE",
        ("5", "1"): "DONE",
        ("50", "0"): "DONE",
        ("50", "1"): "ERROR",
    }
    done_files = {p: p.stat().st_mtime_ns for p in (tmp_path / "trials").glob("*/summary.json")}
    assert len(done_files) == 3
    # the crash removed: resume runs only the point that did not finish
    # the injected crash removed (the stored overrides would bring it back)
    r2 = sweep(tmp_path, "method=solve", grid, base, "resume=true", "sweep.fail_on=[]")
    assert r2.returncode == 0, (r2.stdout[-3000:], r2.stderr[-3000:])
    assert "4 grid points, 1 to run (resume)" in r2.stdout and r2.stdout.count("→ DONE") == 1
    assert {t["status"] for t in rows(tmp_path / "summary.csv")} == {"DONE"}
    assert {p: p.stat().st_mtime_ns for p in done_files} == done_files  # untouched


@pytest.mark.e2e
def test_local_executor_crash_resume_and_mixed_plans(tmp_path):
    """executor=local: same files and statuses as under Ray, without Ray (so no namespace)."""
    grid = "sweep.grid={reward.r4: [5,50]}"
    base = "sweep.base=['eval.mc_episodes=0']"

    def run(*extra):
        return subprocess.run(
            [
                sys.executable,
                str(ROOT / "recipes" / "sweep.py"),
                "method=solve",
                "executor=local",
                grid,
                base,
                *extra,
                f"hydra.run.dir={tmp_path}",
            ],
            capture_output=True,
            text=True,
            timeout=300,
            cwd=ROOT,
        )

    r = run("sweep.fail_on=['reward.r4=50']")
    assert r.returncode == 1, r.stderr[-2000:]
    assert {t["reward.r4"]: t["status"] for t in rows(tmp_path / "summary.csv")} == {
        "5": "DONE",
        "50": "ERROR",
    }
    (done,) = [t for t in rows(tmp_path / "summary.csv") if t["status"] == "DONE"]
    assert abs(float(done["optimality_ratio"]) - 1.0) < 1e-12  # the optimum scored against itself
    assert (
        "injected failure"
        in (
            tmp_path / "trials" / rows(tmp_path / "summary.csv")[1]["point_id"] / "run.log"
        ).read_text()
    )
    # resume as the README gives it: the directory alone; the stored grid and options come back
    # (all but the injected crash, which is removed)
    r = subprocess.run(
        [
            sys.executable,
            str(ROOT / "recipes" / "sweep.py"),
            "resume=true",
            "sweep.fail_on=[]",
            f"hydra.run.dir={tmp_path}",
        ],
        capture_output=True,
        text=True,
        timeout=300,
        cwd=ROOT,
    )
    assert r.returncode == 0 and "2 grid points, 1 to run (resume)" in r.stdout, r.stderr[-2000:]
    assert "resume: with the run's stored overrides" in r.stderr
    assert {t["status"] for t in rows(tmp_path / "summary.csv")} == {"DONE"}


@pytest.mark.parametrize(
    ("args", "says"),
    [
        (["seed=3"], "seed=3 is for the runs of dqn (method), not for the sweep"),
        (["env=multilevel"], "every trial takes it with \"sweep.base=['env=multilevel']\""),
        (["method=online", "algo.episodes=3"], "sweep.grid='{algo.episodes: [...]}'"),
    ],
)
def test_an_override_of_the_method_given_to_the_sweep_says_where_it_goes(args, says):
    """It was "unknown key 'seed' in sweep; did you mean sweep?"; a key neither has is still one."""
    with pytest.raises(ValueError) as err:
        load("sweep", *args)
    assert says in str(err.value)
    with pytest.raises(ValueError, match=r"unknown key 'algo\.episodes' in sweep"):
        load("sweep", "method=solve", "algo.episodes=3")  # solve has no such key either


def test_one_vehicle_learners_sweep_with_the_price_of_their_learning(tmp_path, capsys):
    """method=online: each point one vehicle's run; summary.csv carries its ledger beside its
    final metrics, and summary_by_point.csv their means over seeds."""
    from conftest import run_recipe

    grid = "sweep.grid={learner: [posterior, qlearning], seed: [0, 1]}"
    base = "sweep.base=['algo.episodes=2','env.horizon=50']"
    assert run_recipe("sweep", tmp_path, "method=online", "executor=local", grid, base) == 0
    table = rows(tmp_path / "summary.csv")
    assert [(r["learner"], r["seed"], r["status"]) for r in table] == [
        ("posterior", "0", "DONE"),
        ("posterior", "1", "DONE"),
        ("qlearning", "0", "DONE"),
        ("qlearning", "1", "DONE"),
    ]
    for r in table:
        s = json.loads((tmp_path / "trials" / r["point_id"] / "summary.json").read_text())
        assert s["learner"] == r["learner"] and s["env_steps"] == 100
        for key in ("regret", "expected_missed", "floor_missed", "cumulative_miss_detection"):
            assert float(r[key]) == pytest.approx(s["ledger"][key], rel=1e-12), key
        assert float(r["miss_detection"]) == pytest.approx(s["metrics"]["miss_detection"])
    means = {r["learner"]: r for r in rows(tmp_path / "summary_by_point.csv")}
    want = sum(float(r["regret"]) for r in table if r["learner"] == "qlearning") / 2
    assert float(means["qlearning"]["regret_mean"]) == pytest.approx(want, rel=1e-5)


def test_resume_without_a_directory_says_to_name_it(tmp_path):
    r = subprocess.run(
        [sys.executable, str(ROOT / "recipes" / "sweep.py"), "resume=true"],
        capture_output=True,
        text=True,
        timeout=120,
        cwd=tmp_path,
    )
    assert r.returncode == 2 and "hydra.run.dir" in r.stderr and "Traceback" not in r.stderr


@pytest.mark.e2e
def test_constrained_method_sweeps_targets(tmp_path):
    """method=constrained: one exact LP per grid point; a tighter target never sends more."""
    r = subprocess.run(
        [
            sys.executable,
            str(ROOT / "recipes" / "sweep.py"),
            "method=constrained",
            "executor=local",
            "sweep.grid={target_miss: [0.05, 0.15]}",
            f"hydra.run.dir={tmp_path}",
        ],
        capture_output=True,
        text=True,
        timeout=300,
        cwd=ROOT,
    )
    assert r.returncode == 0, r.stderr[-2000:]
    done = {t["target_miss"]: t for t in rows(tmp_path / "summary.csv")}
    assert {k: v["status"] for k, v in done.items()} == {"0.05": "DONE", "0.15": "DONE"}
    got = {}
    for t in done.values():
        s = json.loads((tmp_path / "trials" / t["point_id"] / "summary.json").read_text())
        assert s["optimal"]["miss_detection"] <= s["target_miss"]
        got[s["target_miss"]] = s["optimal"]["throughput"]
    assert got[0.05] < got[0.15]
    # the LP is the optimum: its progress line says its value, not a ratio to itself
    assert "optimality ratio" not in r.stdout, r.stdout
    assert r.stdout.count("DONE, LP optimum throughput") == 2, r.stdout


def test_point_ids_separate_methods_and_bases():
    from irdrc.recipes import qlearning, solve
    from irdrc.sweeps.trials import plan

    a = plan(solve, [{"seed": 0}], ["eval.mc_episodes=0"])
    b = plan(solve, [{"seed": 0}], ["eval.mc_episodes=0", "reward.r4=50"])
    c = plan(qlearning, [{"seed": 0}], ["eval.mc_episodes=0"])
    ids = {x[0]["point_id"] for x in (a, b, c)}
    assert len(ids) == 3 and all(i.startswith("seed=0__") for i in ids)
    assert b[0]["config"].model.reward.r4 == 50 and c[0]["config"].algo.name == "qlearning"


def _sweep_popen(tmp_path: Path, *overrides: str) -> subprocess.Popen:
    """The sweep driver in its own session (so the test can signal or kill the whole group)."""
    pytest.importorskip("ray")
    cmd = shlex.join(
        [
            sys.executable,
            str(ROOT / "recipes" / "sweep.py"),
            *overrides,
            "ray.num_cpus=1",
            f"hydra.run.dir={tmp_path}",
        ]
    )
    # A killed driver cannot remove its temporary directories (Ray Tune imports wandb, which makes
    # two): they go under the test's own folder. Ray keeps its session under the usual /tmp/ray,
    # whose socket paths must stay short.
    scratch = tmp_path.parent / f"{tmp_path.name}.tmp"
    scratch.mkdir(exist_ok=True)
    env = {**os.environ, "TMPDIR": str(scratch)}
    env.setdefault("RAY_TMPDIR", tempfile.gettempdir())
    return subprocess.Popen(
        ["unshare", "-n", "sh", "-c", f"ip link set lo up; exec {cmd}"],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        cwd=ROOT,
        env=env,
        start_new_session=True,
    )


def _wait_for_done(tmp_path: Path, proc: subprocess.Popen, n: int, timeout: float = 240) -> None:
    """Until ``n`` trials are done: a DONE status beside their summary (the status is written after
    the summary, so a summary alone may still be a trial the driver has not marked done)."""
    import time

    from irdrc.sweeps.trials import read_status

    def done() -> int:
        trials = (tmp_path / "trials").glob("*/summary.json")
        return sum((read_status(s.parent) or {}).get("status") == "DONE" for s in trials)

    t0 = time.monotonic()
    while done() < n:
        assert proc.poll() is None, proc.communicate()
        assert time.monotonic() - t0 < timeout, "no trial finished in time"
        time.sleep(0.2)


SLOW_GRID = (
    "method=qlearning",
    "sweep.grid={seed: [0,1,2]}",
    "sweep.base=['algo.episodes=25','eval.mc_episodes=0','eval.every_frames=8000']",
)


@pytest.mark.e2e
@needs_ray_netns
def test_driver_killed_mid_sweep_keeps_finished_trials_and_resume_runs_the_rest(tmp_path):
    """kill -9 of the driver after the first trial: its files are already stored (they are written
    when each trial finishes), and resume reruns only the others."""
    import signal

    proc = _sweep_popen(tmp_path, *SLOW_GRID)
    _wait_for_done(tmp_path, proc, 1)
    os.killpg(proc.pid, signal.SIGKILL)
    proc.communicate(timeout=60)
    from irdrc.sweeps.trials import read_status

    # Done = a DONE status beside its summary. A trial killed between writing its summary and its
    # status (the other trial runs in parallel) is not done: resume reruns it.
    done = [
        d for d in (tmp_path / "trials").iterdir() if (read_status(d) or {}).get("status") == "DONE"
    ]
    assert 1 <= len(done) < 3
    for d in done:
        assert (d / "summary.json").is_file() and (d / "metrics.csv").is_file()
    r = sweep(tmp_path, *SLOW_GRID, "resume=true")
    assert r.returncode == 0, (r.stdout[-3000:], r.stderr[-3000:])
    assert f"3 grid points, {3 - len(done)} to run (resume)" in r.stdout
    assert {t["status"] for t in rows(tmp_path / "summary.csv")} == {"DONE"}


@pytest.mark.e2e
@needs_ray_netns
def test_ctrl_c_leaves_a_valid_summary_with_incomplete_rows(tmp_path):
    import signal

    proc = _sweep_popen(tmp_path, *SLOW_GRID)
    _wait_for_done(tmp_path, proc, 1)
    os.killpg(proc.pid, signal.SIGINT)
    stdout, stderr = proc.communicate(timeout=180)
    assert proc.returncode == 130 and "Traceback" not in stderr, (stdout[-2000:], stderr[-3000:])
    table = rows(tmp_path / "summary.csv")
    assert len(table) == 3 and "DONE" in {t["status"] for t in table}
    # the trials Ctrl-C stopped are INCOMPLETE, not errors; Tune's own hint is not printed
    assert {t["status"] for t in table} <= {"DONE", "INCOMPLETE"}, table
    assert "Tuner.restore" not in stdout + stderr and "FileNotFoundError" not in stdout + stderr
    printed = stdout.split("go on with: ", 1)[1].splitlines()[0]
    here = python_as_typed(ROOT)  # the sweep's python (the venv's: relative to its cwd)
    assert printed == f"{here} recipes/sweep.py resume=true hydra.run.dir={tmp_path}"
    r = sweep(tmp_path, "resume=true")  # as printed (plus the test's ray.num_cpus), no grid
    assert r.returncode == 0, (r.stdout[-3000:], r.stderr[-3000:])
    assert {t["status"] for t in rows(tmp_path / "summary.csv")} == {"DONE"}


def test_status_files_are_checked(tmp_path, capsys):
    from irdrc.sweeps.trials import read_status

    d = tmp_path / "p"
    d.mkdir()
    (d / "status.json").write_text('{"status": "DONE"}')
    assert read_status(d)["status"] == "INCOMPLETE"  # DONE without its summary is not DONE
    (d / "summary.json").write_text("{}")
    assert read_status(d)["status"] == "DONE"
    (d / "status.json").write_text("{not json")
    assert read_status(d) is None and str(d / "status.json") in capsys.readouterr().out


def test_kept_points_counts_what_a_resumed_run_does_not_run_again(tmp_path):
    """A benchmark's time line leaves out the points a resumed run keeps: DONE ones, and only
    with ``resume`` (an ERROR or INCOMPLETE point runs again; without ``resume`` every one does)."""
    from irdrc.runs.sections import Executor
    from irdrc.sweeps.trials import kept_points

    planned = [{"point_id": name} for name in ("a", "b", "c", "d")]
    for name, status in (("a", "DONE"), ("b", "DONE"), ("c", "ERROR")):
        d = tmp_path / "trials" / name
        d.mkdir(parents=True)
        (d / "status.json").write_text(json.dumps({"status": status}))
        (d / "summary.json").write_text("{}")
    assert kept_points(Executor(executor="local", resume=True), planned, tmp_path) == 2
    assert kept_points(Executor(executor="local"), planned, tmp_path) == 0
    (tmp_path / "trials" / "b" / "summary.json").unlink()  # DONE without its summary: not done
    assert kept_points(Executor(executor="local", resume=True), planned, tmp_path) == 1


def test_a_point_id_reads_as_its_overrides_and_a_resume_keeps_an_earlier_versions_trials(
    tmp_path,
):
    """The readable part of a trial's directory names each key by its last part with its whole
    value, a path by its file (before, ``env.p1.speed=0.5`` read ``5`` and a learner's file
    ``py-Watchful``); a resumed sweep keeps a DONE trial whose directory an earlier version named
    (the same hash), under this version's name."""
    from irdrc.runs.sections import Executor
    from irdrc.sweeps.trials import kept_points

    speed = point_id({"env.p1.speed": 0.5, "reward.r4": 5.0, "seed": 0})
    assert speed.startswith("speed=0.5_r4=5.0_seed=0__")
    own = point_id({"learner": "/home/me/watchful.py:Watchful", "env": "examples/my_city.yaml"})
    assert own.startswith("env=my_city.yaml_learner=watchful.py-Watchful__")
    planned = [{"point_id": speed}, {"point_id": own}]
    earlier = tmp_path / "trials" / f"0_5_seed=0__{speed.rpartition('__')[2]}"
    earlier.mkdir(parents=True)
    (earlier / "status.json").write_text(json.dumps({"status": "DONE"}))
    (earlier / "summary.json").write_text("{}")
    assert kept_points(Executor(executor="local"), planned, tmp_path) == 0
    assert earlier.is_dir()  # without resume nothing is touched
    assert kept_points(Executor(executor="local", resume=True), planned, tmp_path) == 1
    assert [d.name for d in (tmp_path / "trials").iterdir()] == [speed]


def test_points_that_differ_in_their_seed_alone_are_composed_as_fresh_ones():
    """A plan composes runs that differ only in ``seed=`` once and copies the seed in: each copy
    equals a fresh composition (config, choices, task), in the seed's place among the overrides;
    a seed that is not a plain integer, or given twice, is composed afresh."""
    from irdrc.recipes import dqn
    from irdrc.recipes.fleet import recipe as fleet
    from irdrc.runs.compose import SeededCompose, compose_recipe

    for module, base in (
        (dqn, ["env=multilevel", "algo.lr=0.001"]),
        (fleet, ["learner=vdn", "env.vehicles=2"]),
    ):
        shared = SeededCompose(module)
        for seed in (3, 0, 12, -1):
            for args in ([*base, f"seed={seed}"], [f"seed={seed}", *base]):
                got, fresh = shared(args), compose_recipe(module, args)
                assert (got.cfg, got.choices, got.task) == (fresh.cfg, fresh.choices, fresh.task)
                assert got.cfg["seed"] == seed and got.cfg is not fresh.cfg
        assert len(shared._shared) == 2  # one composition per order of the overrides
    shared = SeededCompose(dqn)
    assert shared(["seed=0x10"]).cfg == compose_recipe(dqn, ["seed=0x10"]).cfg
    assert shared(["seed=1", "seed=2"]).cfg["seed"] == 2
    assert not shared._shared
