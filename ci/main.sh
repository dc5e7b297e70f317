#!/usr/bin/env bash
# Runs the main job (DQN). Extra arguments are Hydra overrides: `bash ci/main.sh reward.r4=50 network=large`.
set -euo pipefail
cd "$(dirname "$0")/.."
bash ci/setup.sh
exec .venv/bin/python recipes/dqn.py "$@"
