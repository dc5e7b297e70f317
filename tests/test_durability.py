"""Work is never lost: periodic atomic checkpoints, signals, kills, resume checks, file modes."""

from __future__ import annotations

import csv
import json
import os
import shlex
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch

from irdrc.runs.results import FILE_MODE, atomic_write, atomic_write_text
from irdrc.runs.resume import resumed_config

ROOT = Path(__file__).resolve().parents[1]
# 4 000 env steps, a checkpoint every 640 (about a second apart here)
RUN = [
    "algo.num_envs=8",
    "algo.frames_per_batch=32",
    "algo.total_frames=4000",
    "algo.init_random_frames=128",
    "algo.buffer_size=1000",
    "algo.batch_size=32",
    "eval.every_frames=320",
    "checkpoint.every_frames=640",
    "eval.mc_episodes=0",
    "logger=none",
]


def dqn(out: Path, *overrides: str, wait: bool = True):
    cmd = [
        sys.executable,
        str(ROOT / "recipes" / "dqn.py"),
        *RUN,
        *overrides,
        f"hydra.run.dir={out}",
    ]
    if wait:
        return subprocess.run(cmd, capture_output=True, text=True, timeout=300, cwd=ROOT)
    return subprocess.Popen(
        cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=ROOT
    )


def wait_for(path: Path, proc: subprocess.Popen, timeout: float = 120) -> None:
    t0 = time.monotonic()
    while not path.exists():
        assert proc.poll() is None, proc.communicate()
        assert time.monotonic() - t0 < timeout, f"{path} never appeared"
        time.sleep(0.05)


def steps_of(path: Path) -> list[int]:
    return [int(r["env_steps"]) for r in csv.DictReader(path.open())]


@pytest.mark.e2e
def test_sigterm_saves_and_resume_continues_without_lost_or_duplicated_rows(tmp_path):
    out = tmp_path / "run"
    proc = dqn(out, wait=False)
    wait_for(out / "checkpoint.pt", proc)
    proc.send_signal(signal.SIGTERM)
    _, stderr = proc.communicate(timeout=120)
    assert proc.returncode == 128 + signal.SIGTERM, stderr[-2000:]
    assert "stopped by SIGTERM" in stderr and "resume=" in stderr and "Traceback" not in stderr
    ckpt = torch.load(out / "checkpoint.pt", weights_only=True)
    stopped_at = ckpt["frames"]
    assert 0 < stopped_at < 4000
    summary = json.loads((out / "summary.json").read_text())
    assert summary["interrupted"] is True and summary["env_steps"] == stopped_at
    before = steps_of(out / "metrics.csv")
    assert before[-1] == stopped_at

    # the printed command, run as printed (no overrides: the checkpoint keeps the configuration),
    # goes on in the same directory
    printed = stderr.split("go on with: ", 1)[1].split(" (", 1)[0]
    args = shlex.split(printed)
    # the python that ran the run (the venv's, relative to here), then the recipe
    assert Path(args[0]).name.startswith("python") and args[1] == "recipes/dqn.py"
    assert args[0] == os.path.relpath(sys.executable, ROOT) or args[0] == sys.executable
    r = subprocess.run(
        [sys.executable, *args[1:]], capture_output=True, text=True, timeout=300, cwd=ROOT
    )
    assert r.returncode == 0, r.stderr[-2000:]
    assert f"resumed from {out / 'checkpoint.pt'} at {stopped_at} env steps" in r.stdout
    assert f"training to 4000, files in {out}" in r.stdout
    assert "note: dqn's checkpoint holds" in r.stdout  # no replay: not the uninterrupted run
    after = steps_of(out / "metrics.csv")
    assert after[: len(before)] == before  # nothing lost
    assert len(after) == len(set(after)) and after == sorted(after)  # nothing twice
    assert after[-1] == 4000 and all(s % 320 == 0 or s == 4000 for s in after[len(before) :])
    summary = json.loads((out / "summary.json").read_text())
    assert summary["interrupted"] is False and summary["env_steps"] == 4000
    assert "resumed from" in (out / "dqn.log").read_text()  # the log holds both parts


@pytest.mark.e2e
def test_kill_9_during_training_leaves_a_resumable_checkpoint(tmp_path):
    out = tmp_path / "run"
    proc = dqn(out, wait=False)
    wait_for(out / "checkpoint.pt", proc)
    proc.kill()  # SIGKILL: no handler runs
    proc.communicate(timeout=60)
    frames = torch.load(out / "checkpoint.pt", weights_only=True)["frames"]
    assert frames % 640 == 0 and frames > 0
    assert steps_of(out / "metrics.csv")[-1] >= frames - 320  # files so far were written with it
    r = dqn(tmp_path / "resumed", f"resume={out / 'checkpoint.pt'}")
    assert r.returncode == 0, r.stderr[-2000:]
    assert steps_of(tmp_path / "resumed" / "metrics.csv")[-1] == 4000


def test_kill_9_during_a_checkpoint_write_keeps_the_previous_one(tmp_path):
    """A process killed half-way through writing leaves the old file whole (the write goes to a
    temporary file that is renamed only once complete)."""
    path = tmp_path / "checkpoint.pt"
    atomic_write_text(path, "the previous, good checkpoint")
    code = (
        "import os, signal, sys\n"
        "from irdrc.runs.results import atomic_write\n"
        "def half(f):\n"
        "    f.write(b'x' * 100000); f.flush()\n"
        "    os.kill(os.getpid(), signal.SIGKILL)\n"
        f"atomic_write({str(path)!r}, half)\n"
    )
    r = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True)
    assert r.returncode == -signal.SIGKILL
    assert path.read_text() == "the previous, good checkpoint"


def test_a_failed_write_keeps_the_previous_file_and_leaves_no_temp(tmp_path):
    """Disk full (ENOSPC) in the middle of a write: a clear error, the old content, no litter."""
    path = tmp_path / "metrics.csv"
    atomic_write_text(path, "old")

    def full(f):
        f.write(b"partial")
        raise OSError(28, "No space left on device")

    with pytest.raises(
        OSError,
        match=r"cannot write .*metrics\.csv: No space left on device \(its previous content is intact\)",
    ):
        atomic_write(path, full)
    assert path.read_text() == "old" and [p.name for p in tmp_path.iterdir()] == ["metrics.csv"]
    # a file that did not exist is not said to be intact
    with pytest.raises(
        OSError, match=r"new\.csv: No space left on device \(nothing was written there\)"
    ):
        atomic_write(tmp_path / "new.csv", full)
    assert not (tmp_path / "new.csv").exists()


def test_rows_with_a_metric_some_rows_lack_are_written_with_every_column(tmp_path):
    """A false-alarm rate is defined only where a policy senses: tradeoff.py on a scenario with
    false alarms failed ('dict contains fields not in fieldnames') when its first row, a policy
    that never senses, lacked it. The header is every row's keys; a missing value is blank."""
    import csv

    from irdrc.runs.results import write_rows_csv

    path = tmp_path / "tradeoff.csv"
    write_rows_csv(
        path, [{"r4": 0.5, "miss": 1.0}, {"r4": 5, "miss": 0.2, "false_alarm_rate": 0.9}]
    )
    rows = list(csv.DictReader(path.open()))
    assert list(rows[0]) == ["r4", "miss", "false_alarm_rate"]
    assert rows[0]["false_alarm_rate"] == "" and rows[1]["false_alarm_rate"] == "0.9"


def test_files_follow_the_umask(tmp_path):
    atomic_write_text(tmp_path / "a.txt", "x")
    assert (tmp_path / "a.txt").stat().st_mode & 0o777 == FILE_MODE


@pytest.fixture(scope="module")
def finished_run(tmp_path_factory) -> Path:
    """One short finished DQN run, copied by the tests that damage or resume it."""
    out = tmp_path_factory.mktemp("finished") / "a"
    first = dqn(out, "algo.total_frames=640", "checkpoint.every_frames=0")
    assert first.returncode == 0, first.stderr[-2000:]
    return out


def _copy(run: Path, tmp_path: Path) -> Path:
    import shutil

    return Path(shutil.copytree(run, tmp_path / "a"))


def test_resume_refuses_another_configuration_and_changes_nothing(finished_run, tmp_path):
    run = _copy(finished_run, tmp_path)
    ckpt = run / "checkpoint.pt"
    before = {p.name: p.read_bytes() for p in (tmp_path / "a").iterdir() if p.is_file()}
    r = dqn(
        tmp_path / "a", f"resume={ckpt}", "env.p1.speed=1.0", "reward.r4=50", "env.queue_capacity=5"
    )
    assert r.returncode == 2 and "Traceback" not in r.stderr
    for key in ("env.p1.speed: 0.1 → 1.0", "reward.r4: 5.0 → 50", "env.queue_capacity: 10 → 5"):
        assert key in r.stderr, r.stderr
    after = {p.name: p.read_bytes() for p in (tmp_path / "a").iterdir() if p.is_file()}
    assert after == before  # config.yaml and the rest untouched


def test_resume_of_a_finished_run_says_how_to_train_longer(finished_run, tmp_path):
    """Resuming a finished run with nothing left to train is refused before Hydra makes a run
    directory, and the message names the key that trains it longer."""
    ckpt = _copy(finished_run, tmp_path) / "checkpoint.pt"
    r = dqn(tmp_path / "b", f"resume={ckpt}", "algo.total_frames=640")
    assert r.returncode == 2 and "nothing left to train" in r.stderr
    assert "algo.total_frames" in r.stderr and not (tmp_path / "b").exists()


def test_resumed_config_is_the_checkpoints_but_for_what_the_command_line_sets():
    """``resumed_config``: keys left off the command line come from the checkpoint (its scenario,
    its run length), keys set on purpose that may change (run length, evaluation) are taken, and a
    group chosen to something else (``env=…``) is refused, naming its keys."""
    saved = {"env": {"p1": {"speed": 0.5}, "n": 3}, "algo": {"total_frames": 200}, "eval": {"k": 1}}
    current = {
        "env": {"p1": {"speed": 0.1}, "n": 3},
        "algo": {"total_frames": 500},
        "eval": {"k": 2},
    }
    path = Path("c.pt")
    assert resumed_config(path, saved, current, frozenset()) == saved
    out = resumed_config(path, saved, current, frozenset({"algo.total_frames", "eval.k"}))
    assert out == {**saved, "algo": {"total_frames": 500}, "eval": {"k": 2}}
    with pytest.raises(ValueError, match=r"env\.p1\.speed: 0\.5 → 0\.1"):
        resumed_config(path, saved, current, frozenset({"env"}))


@pytest.mark.parametrize("damage", ["truncate", "garbage", "empty"])
def test_corrupt_checkpoint_is_one_line_naming_the_file(finished_run, tmp_path, damage):
    ckpt = _copy(finished_run, tmp_path) / "checkpoint.pt"
    data = ckpt.read_bytes()
    ckpt.write_bytes(
        {"truncate": data[: len(data) // 2], "garbage": b"\x00junk" * 50, "empty": b""}[damage]
    )
    r = dqn(tmp_path / "b", f"resume={ckpt}")
    assert r.returncode == 2 and "Traceback" not in r.stderr
    errors = [line for line in r.stderr.splitlines() if line.startswith("error:")]
    assert len(errors) == 1 and str(ckpt) in errors[0], r.stderr[-1500:]
    assert not (tmp_path / "b").exists()


def test_umask_is_honoured_by_a_whole_run(tmp_path):
    code = "import os, sys, runpy; os.umask(0o027); sys.argv = sys.argv[1:]; runpy.run_path(sys.argv[0], run_name='__main__')"
    r = subprocess.run(
        [
            sys.executable,
            "-c",
            code,
            str(ROOT / "recipes" / "solve.py"),
            "eval.mc_episodes=0",
            f"hydra.run.dir={tmp_path}",
        ],
        capture_output=True,
        text=True,
        timeout=120,
        cwd=ROOT,
    )
    assert r.returncode == 0, r.stderr[-2000:]
    for name in ("summary.json", "policy.csv"):
        assert (tmp_path / name).stat().st_mode & 0o777 == 0o640, name


LEARNERS = {
    "fleet": (
        "recipes/fleet.py",
        [
            "algo.num_envs=8",
            "algo.frames_per_batch=32",
            "algo.total_frames=3200",
            "algo.batch_size=32",
            "eval.every_frames=320",
            "checkpoint.every_frames=640",
            "logger=none",
        ],
        3200,
    ),
    "constrained": (
        "recipes/constrained.py",
        [
            "learner=dqn_lagrangian",
            "algo.num_envs=8",
            "algo.frames_per_batch=32",
            "algo.total_frames=3200",
            "algo.init_random_frames=128",
            "algo.batch_size=32",
            "algo.measure_envs=4",
            "algo.measure_steps=20",
            "algo.measure_burn_in=0",
            "algo.mix_steps=2",
            "eval.every_frames=320",
            "checkpoint.every_frames=640",
            "logger=none",
        ],
        3200,
    ),
    "sac": (
        "recipes/sac.py",
        [
            "algo.num_envs=8",
            "algo.frames_per_batch=32",
            "algo.total_frames=6400",
            "algo.init_random_frames=64",
            "algo.batch_size=32",
            "algo.updates_per_batch=2",
            "eval.every_frames=320",
            "checkpoint.every_frames=640",
            "logger=none",
        ],
        6400,
    ),
    "ppo": (
        "recipes/ppo.py",
        [
            "algo.num_envs=8",
            "algo.frames_per_batch=64",
            "algo.total_frames=6400",
            "algo.batch_size=32",
            "eval.every_frames=320",
            "checkpoint.every_frames=640",
            "logger=none",
        ],
        6400,
    ),
    "qlearning": (
        "recipes/qlearning.py",
        ["algo.episodes=40", "eval.every_frames=800", "checkpoint.every_frames=800"],
        16000,
    ),
}
"""Every training recipe but DQN (above): its command, its checkpoint period, its length in
env steps (fleet steps for the fleet)."""


def _learner(name: str, out: Path, *extra: str, wait: bool = True):
    script, overrides, _ = LEARNERS[name]
    cmd = [sys.executable, script, *overrides, "progress=false", *extra, f"hydra.run.dir={out}"]
    if wait:
        return subprocess.run(cmd, capture_output=True, text=True, timeout=300, cwd=ROOT)
    return subprocess.Popen(
        cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=ROOT
    )


@pytest.mark.e2e
@pytest.mark.parametrize("name", sorted(LEARNERS))
def test_every_learner_survives_kill_9_and_sigterm(name, tmp_path):
    """kill -9 during training leaves a checkpoint that ``resume=`` finishes, in the same
    directory, every evaluation once; SIGTERM saves, exits 143 and prints the command that goes on.
    (The fleet lost everything on kill -9 and could not resume before.)"""
    total = LEARNERS[name][2]
    out = tmp_path / "killed"
    proc = _learner(name, out, wait=False)
    wait_for(out / "checkpoint.pt", proc)
    proc.kill()
    proc.communicate(timeout=60)
    saved = torch.load(out / "checkpoint.pt", weights_only=True)
    assert saved["frames"] > 0
    r = subprocess.run(
        [sys.executable, LEARNERS[name][0], f"resume={out / 'checkpoint.pt'}", "progress=false"],
        capture_output=True,
        text=True,
        timeout=300,
        cwd=ROOT,
    )
    assert r.returncode == 0, r.stderr[-2000:]
    assert "resumed from" in r.stdout
    # Q-learning's checkpoint holds its random streams: its resume is the uninterrupted run; the
    # shared loop's learners restart their rows and refill their data, and say so
    assert ("differ from an uninterrupted run's" in r.stdout) == (name != "qlearning"), r.stdout
    steps = steps_of(out / "metrics.csv")
    assert steps[-1] == total and len(steps) == len(set(steps)) and steps == sorted(steps)
    assert json.loads((out / "summary.json").read_text())["interrupted"] is False

    out = tmp_path / "stopped"
    proc = _learner(name, out, wait=False)
    wait_for(out / "checkpoint.pt", proc)
    proc.send_signal(signal.SIGTERM)
    _, stderr = proc.communicate(timeout=120)
    assert proc.returncode == 128 + signal.SIGTERM, stderr[-2000:]
    assert "go on with: " in stderr and "resume=" in stderr and "Traceback" not in stderr


def test_threads_are_capped_by_the_cores_and_a_trials_cpus(monkeypatch):
    """``num_threads`` above the machine's cores runs on the cores (a recipe's default of 2 on a
    one-core machine), and a sweep trial given one CPU runs on one thread whatever its recipe says
    (SAC's default is 2: two such trials side by side would fight over the cores)."""
    from irdrc.runs.scaffold import Run

    before = torch.get_num_threads()
    monkeypatch.setattr("os.cpu_count", lambda: 1)
    try:
        Run.threads(2)
        assert torch.get_num_threads() == 1
        monkeypatch.setattr("os.cpu_count", lambda: 8)
        Run.threads(2)
        assert torch.get_num_threads() == 2
        monkeypatch.setattr(Run, "max_threads", 1)
        Run.threads(2)
        assert torch.get_num_threads() == 1
    finally:
        torch.set_num_threads(before)
