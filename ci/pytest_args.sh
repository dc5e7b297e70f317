# Sourced by ci/test.sh: `pytest_args ARGS…` prints the arguments pytest gets, one per line. The
# suite runs on every core (pytest-xdist, at most 8 workers; each test process holds torch to one
# thread) beside whatever is given, unless the arguments choose otherwise: `-n N` / `--numprocesses`
# sets the workers (`-n 0`: one process), `-p no:xdist` and `--pdb` run in one process.
pytest_args() {
    local arg parallel=1
    for arg in "$@"; do
        case "$arg" in
            -n | -n[0-9a]* | --numprocesses | --numprocesses=* | no:xdist | --pdb) parallel=0 ;;
        esac
    done
    if [ "$parallel" -eq 1 ]; then
        set -- -n auto --maxprocesses 8 "$@"
    fi
    [ $# -eq 0 ] || printf '%s\n' "$@"
}
