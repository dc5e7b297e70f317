#!/usr/bin/env bash
# Idempotent setup: a virtual env in .venv, torch 2.13.0 first (the CPU wheel on CPU machines),
# then irdrc with its dev extras, torch held at 2.13.0 by ci/constraints.txt. Re-runs are instant
# unless pyproject.toml or the constraints changed. Extra arguments name extras (e.g. "sweep").
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
extras="dev${1:+,$1}"
stamp=.venv/.setup-stamp
want="$(cat pyproject.toml ci/constraints.txt | sha256sum | cut -c1-16) $extras"
if [ -x .venv/bin/python ] && [ -f "$stamp" ] && [ "$(cat "$stamp")" = "$want" ]; then
  exit 0
fi
echo "[setup] preparing .venv (extras: $extras)" >&2
[ -x .venv/bin/python ] || "$PY" -m venv .venv
pip() { .venv/bin/python -m pip --disable-pip-version-check -q "$@" 2>&1 | grep -v "^WARNING: Location" || true; }
pip install -c ci/constraints.txt "torch==2.13.0"
pip install -c ci/constraints.txt -e ".[$extras]"
.venv/bin/python -c "import torch, torchrl, irdrc; assert torch.__version__.startswith('2.13.0'), torch.__version__" \
  || { echo "[setup] failed: torch 2.13.0 / torchrl / irdrc do not import" >&2; exit 1; }
echo "$want" > "$stamp"
echo "[setup] done" >&2
