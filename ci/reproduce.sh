#!/usr/bin/env bash
# Regenerates docs/figures/ and the generated blocks of docs/REPRODUCTION.md: runs recipes/figure2.py,
# recipes/tradeoff.py, recipes/constrained.py frontier=true, recipes/bench_constrained.py and
# recipes/study.py with their defaults (extra arguments go to figure2.py) into outputs/reproduction/, then writes the report. The
# recipes that start Ray run in a loopback-only network namespace where `unshare -n` works.
set -euo pipefail
cd "$(dirname "$0")/.."
bash ci/setup.sh sweep
out=${IRDRC_REPRODUCTION_DIR:-outputs/reproduction}
rm -rf "$out"
py=.venv/bin/python
netns() {
  if unshare -n true 2>/dev/null; then
    unshare -n sh -c 'ip link set lo up; exec "$@"' sh "$@"
  else
    "$@"
  fi
}
netns "$py" recipes/figure2.py hydra.run.dir="$out/figure2" "$@"
netns "$py" recipes/tradeoff.py hydra.run.dir="$out/tradeoff"
"$py" recipes/constrained.py frontier=true hydra.run.dir="$out/constrained"
netns "$py" recipes/bench_constrained.py hydra.run.dir="$out/bench_constrained"
"$py" recipes/study.py hydra.run.dir="$out/study"
cmd="bash ci/reproduce.sh${*:+ $*}"
"$py" -c "import sys; from irdrc.paper.report import write_report; write_report(sys.argv[1], sys.argv[2], 'docs', sys.argv[3], sys.argv[4], sys.argv[5], sys.argv[6])" \
  "$out/figure2" "$out/tradeoff" "$cmd" "$out/constrained" "$out/bench_constrained" "$out/study"
echo "[reproduce] wrote docs/REPRODUCTION.md and docs/figures/ from $out"
