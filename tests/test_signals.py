"""A signal in any phase of a run: the files it can write are written, it says so, and it exits
128 + the signal's number; a resumed run whose training is complete but whose files are missing
writes them."""

from __future__ import annotations

import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from conftest import default_sigint

ROOT = Path(__file__).resolve().parents[1]

TINY = [
    "algo.num_envs=8",
    "algo.frames_per_batch=32",
    "algo.total_frames=640",
    "algo.batch_size=32",
    "progress=false",
]
LONG_MC = ["eval.mc_episodes=2400", "eval.mc_num_envs=1"]  # about a minute of Monte-Carlo


def _ignore_sigint() -> None:
    # what a shell does to a job started with '&': SIGINT ignored from the start
    signal.signal(signal.SIGINT, signal.SIG_IGN)


def signal_during_final_evaluation(run_dir: Path, signum: int) -> subprocess.CompletedProcess:
    """Start a tiny DQN run whose Monte-Carlo evaluation lasts about a minute; send ``signum``
    once training is over (``learners.csv`` is written just before the evaluation)."""
    proc = subprocess.Popen(
        [sys.executable, "recipes/dqn.py", *TINY, *LONG_MC, f"hydra.run.dir={run_dir}"],
        cwd=ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        preexec_fn=_ignore_sigint,
    )
    start = time.monotonic()
    while not (run_dir / "learners.csv").exists():
        assert proc.poll() is None, proc.communicate()
        assert time.monotonic() - start < 120
        time.sleep(0.1)
    time.sleep(1.0)
    proc.send_signal(signum)
    out, err = proc.communicate(timeout=60)  # the evaluation alone would take about a minute
    return subprocess.CompletedProcess(proc.args, proc.returncode, out, err)


def resume(run_dir: Path) -> subprocess.CompletedProcess:
    # a resumed run may change its evaluation: a short one here, not the minute-long original
    return subprocess.run(
        [
            sys.executable,
            "recipes/dqn.py",
            f"resume={run_dir / 'checkpoint.pt'}",
            "eval.mc_episodes=8",
            "eval.mc_num_envs=8",
        ],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=300,
    )


@pytest.mark.e2e
@pytest.mark.parametrize("signum", [signal.SIGTERM, signal.SIGINT])
def test_a_signal_during_the_final_evaluation_writes_the_files_and_says_so(tmp_path, signum):
    run_dir = tmp_path / "run"
    out = signal_during_final_evaluation(run_dir, signum)
    name = signal.Signals(signum).name
    assert out.returncode == 128 + signum, out.stderr
    assert f"stopped by {name}" in out.stderr
    assert f"{name}: the Monte-Carlo evaluation is left out" in out.stdout
    for f in ("summary.json", "policy.csv", "metrics.csv", "checkpoint.pt"):
        assert (run_dir / f).is_file(), f
    assert not (run_dir / ".lock").exists()
    # the run is complete: a resume has nothing to do and says so
    again = resume(run_dir)
    assert again.returncode == 2 and "nothing left to train" in again.stderr
    # … unless its files are gone: then the resume writes them, training nothing
    (run_dir / "summary.json").unlink()
    (run_dir / "policy.csv").unlink()
    again = resume(run_dir)
    assert again.returncode == 0, again.stderr
    assert (run_dir / "summary.json").is_file() and (run_dir / "policy.csv").is_file()


@pytest.mark.e2e
def test_ctrl_c_in_a_long_solve_is_one_line(tmp_path):
    """SIGINT while a 10⁶-state solve runs: its estimate and progress were shown, the answer is
    one line, exit 130."""
    import threading

    out = tmp_path / "run"
    proc = subprocess.Popen(
        [
            sys.executable,
            "recipes/solve.py",
            "env=large",
            "env.queue_capacity=6944",
            f"hydra.run.dir={out}",
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        cwd=ROOT,
        preexec_fn=default_sigint,  # Ctrl-C at a terminal
    )
    # wait for the first progress line of the sweeps (a fixed wait raced a slow start)
    seen: list[str] = []
    reader = threading.Thread(target=lambda: seen.extend(proc.stdout), daemon=True)
    reader.start()
    t0 = time.monotonic()
    while not any("value iteration: sweep" in line for line in seen):
        assert proc.poll() is None, proc.stderr.read()
        assert time.monotonic() - t0 < 300, "no sweep progress line"
        time.sleep(0.2)
    proc.send_signal(signal.SIGINT)
    proc.wait(timeout=60)
    reader.join(timeout=60)
    stdout, stderr = "".join(seen), proc.stderr.read()
    assert proc.returncode == 130, stderr
    assert "estimate here" in stdout and "[solve] value iteration: sweep" in stdout
    assert "Traceback" not in stderr
    assert (
        stderr.strip().startswith("error: stopped by SIGINT; what the run wrote is in ")
        and len(stderr.splitlines()) == 1
    )
