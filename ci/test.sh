#!/usr/bin/env bash
# Runs the test suite (fast by default). Extra arguments go to pytest: `bash ci/test.sh -m slow`.
# It runs on every core (pytest-xdist) unless the arguments say otherwise (ci/pytest_args.sh), e.g.
# `bash ci/test.sh -n 0` for one process.
set -euo pipefail
cd "$(dirname "$0")/.."
bash ci/setup.sh sweep   # dev and sweep (Ray Tune) extras: the sweep tests run Ray
.venv/bin/ruff check .
.venv/bin/ruff format --check .
.venv/bin/mypy   # the package's annotations ([tool.mypy] in pyproject.toml)
source ci/pytest_args.sh
mapfile -t args < <(pytest_args "$@")
exec .venv/bin/python -m pytest "${args[@]}"
