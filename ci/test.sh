#!/usr/bin/env bash
# Runs the test suite (fast by default). Extra arguments go to pytest: `bash ci/test.sh -m slow`.
set -euo pipefail
cd "$(dirname "$0")/.."
bash ci/setup.sh sweep   # dev and sweep (Ray Tune) extras: the sweep tests run Ray
.venv/bin/ruff check .
.venv/bin/ruff format --check .
exec .venv/bin/python -m pytest "$@"
