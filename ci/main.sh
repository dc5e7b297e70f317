#!/usr/bin/env bash
# Runs the main job. Extra arguments are Hydra overrides: `bash ci/main.sh env=ref_impl reward.r4=50`.
set -euo pipefail
cd "$(dirname "$0")/.."
bash ci/setup.sh
exec .venv/bin/python recipes/demo.py "$@"
