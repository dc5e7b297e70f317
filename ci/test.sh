#!/usr/bin/env bash
# Runs the test suite (fast by default). Extra arguments go to pytest: `bash ci/test.sh -m slow`.
# Without arguments the default suite runs on every core (pytest-xdist, at most 8 workers; each test
# process holds torch to one thread); any argument given replaces that, e.g. `bash ci/test.sh -n 0`.
set -euo pipefail
cd "$(dirname "$0")/.."
bash ci/setup.sh sweep   # dev and sweep (Ray Tune) extras: the sweep tests run Ray
.venv/bin/ruff check .
.venv/bin/ruff format --check .
[ $# -eq 0 ] && set -- -n auto --maxprocesses 8
exec .venv/bin/python -m pytest "$@"
