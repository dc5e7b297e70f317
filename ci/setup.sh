#!/usr/bin/env bash
# Idempotent setup: a virtual env in .venv, torch 2.13.0 first (the CPU wheel on CPU machines),
# then irdrc with its dev extras, torch held at 2.13.0 by ci/constraints.txt. Extra arguments name
# more extras (e.g. "sweep"). Re-runs are instant while pyproject.toml and the constraints are
# unchanged and the extras asked for are installed already, so ci/main.sh (dev) and ci/test.sh
# (dev, sweep) share one .venv without reinstalling when you switch between them.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
stamp=.venv/.setup-stamp
hash="$(cat pyproject.toml ci/constraints.txt | sha256sum | cut -c1-16)"
want="dev${1:+ $1}"
have=""
if [ -x .venv/bin/python ] && [ -f "$stamp" ]; then
  read -r stamp_hash have_extras < "$stamp" || true
  if [ "$stamp_hash" = "$hash" ]; then
    have="${have_extras//,/ }"
    missing=0
    for e in $want; do
      case " $have " in *" $e "*) ;; *) missing=1 ;; esac
    done
    [ "$missing" = 0 ] && exit 0
  fi
fi
# Install what is asked for and what was there before (switching never uninstalls).
extras=$(printf '%s\n' $want $have | sort -u | paste -sd, -)
start=$SECONDS
say() { echo "[setup] $* ($((SECONDS - start)) s)" >&2; }
say "preparing .venv (extras: $extras): three steps, about 90 s the first time"
[ -x .venv/bin/python ] || { "$PY" -m venv .venv; say "1/3 virtual environment created in .venv"; }
pip() { .venv/bin/python -m pip --disable-pip-version-check -q "$@" 2>&1 | grep -v "^WARNING: Location" || true; }
say "2/3 installing torch 2.13.0 (the CPU wheel here)"
pip install -c ci/constraints.txt "torch==2.13.0"
say "3/3 installing irdrc with its extras [$extras] (torchrl, tensordict, hydra, …)"
pip install -c ci/constraints.txt -e ".[$extras]"
.venv/bin/python -c "import torch, torchrl, irdrc; assert torch.__version__.startswith('2.13.0'), torch.__version__" \
  || { echo "[setup] failed: torch 2.13.0 / torchrl / irdrc do not import" >&2; exit 1; }
echo "$hash $extras" > "$stamp"
say "done"
