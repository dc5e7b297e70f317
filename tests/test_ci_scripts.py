"""The CI scripts' choices (``ci/pytest_args.sh``): what pytest is given for each command line."""

from __future__ import annotations

import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
XDIST = ["-n", "auto", "--maxprocesses", "8"]


def pytest_args(*args: str) -> list[str]:
    out = subprocess.run(
        ["bash", "-c", 'source ci/pytest_args.sh && pytest_args "$@"', "bash", *args],
        cwd=ROOT,
        capture_output=True,
        text=True,
        check=True,
    ).stdout
    return out.splitlines()


@pytest.mark.parametrize(
    ("given", "expected"),
    [
        ((), XDIST),
        (("-m", "slow"), [*XDIST, "-m", "slow"]),  # a tier keeps every core
        (("tests/test_online.py", "-k", "safe"), [*XDIST, "tests/test_online.py", "-k", "safe"]),
        (("-n", "0"), ["-n", "0"]),  # the workers chosen: nothing added
        (("-m", "e2e", "-n", "2"), ["-m", "e2e", "-n", "2"]),
        (("-n2",), ["-n2"]),
        (("--numprocesses=3",), ["--numprocesses=3"]),
        (("-p", "no:xdist"), ["-p", "no:xdist"]),
        (("--pdb", "tests/test_env.py"), ["--pdb", "tests/test_env.py"]),  # pdb needs one process
    ],
)
def test_the_suite_runs_on_every_core_unless_the_arguments_choose(given, expected):
    assert pytest_args(*given) == expected
