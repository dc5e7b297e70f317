"""What every recipe does around its run: scenarios registered, renamed keys mapped, the command line
and the composed config checked before any work, and errors reported in a line, not a traceback.

A recipe is ``main = recipe("dqn", run_dqn)`` plus ``if __name__ == "__main__": main()``: the run
function gets the composed config and the run directory, and its return value (an exit code or a
summary) decides the exit status.
"""

from __future__ import annotations

import os
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

from irdrc.experiments.config import CONF_DIR, compose, register_scenarios, rename_overrides
from irdrc.experiments.grid import override_key
from irdrc.experiments.guard import RunInterrupted

EXIT_USAGE = 2
"""Exit status of a run refused before any work (a bad key or value)."""


def fail(message: str, code: int = EXIT_USAGE) -> None:
    """Print ``error: message`` (no traceback) and exit with ``code``."""
    print(f"error: {message}", file=sys.stderr, flush=True)
    sys.exit(code)


class _Tee:
    """``sys.stdout`` for the length of a run: what is printed also goes to the run's log."""

    def __init__(self, stream: Any, log: Any) -> None:
        self.stream, self.log = stream, log

    def write(self, text: str) -> int:
        self.log.write(text)
        return self.stream.write(text)

    def flush(self) -> None:
        self.log.flush()
        self.stream.flush()

    def __getattr__(self, name: str) -> Any:  # isatty, fileno, encoding: the terminal's
        return getattr(self.stream, name)


def _quoted_path(path: Path) -> str:
    """A path as a Hydra override value (quoted when it holds more than plain characters)."""
    text = str(path)
    plain = all(c.isalnum() or c in "_-./" for c in text)
    return text if plain else "'" + text.replace("\\", "\\\\").replace("'", "\\'") + "'"


def stored_overrides(args: list[str]) -> tuple[list[str], list[str]]:
    """With ``resume=true hydra.run.dir=DIR``, the command line completed by the overrides the run
    in DIR was started with (its ``.hydra/overrides.yaml``; what the command line sets wins), so a
    sweep, a figure or a benchmark goes on with its own grid; and the overrides taken from there."""
    from omegaconf import OmegaConf

    values = {override_key(a): a.split("=", 1)[1] for a in args if "=" in a}
    run_dir = values.get("hydra.run.dir")
    if str(values.get("resume", "")).lower() != "true" or not run_dir:
        return args, []
    record = Path(run_dir.strip("'\"")).expanduser() / ".hydra" / "overrides.yaml"
    if not record.is_file():
        return args, []
    taken = [
        str(o)
        for o in OmegaConf.load(record)
        if override_key(str(o)) not in values and not override_key(str(o)).startswith("hydra")
    ]
    return [*taken, *args], taken


def _remove_if_empty(out: Path, log_name: str) -> None:
    """Remove a run directory a refused run made: one holding only Hydra's record and the log
    (and its date folder under ``outputs/`` when that is left empty)."""
    if not out.is_dir() or {p.name for p in out.iterdir()} - {".hydra", log_name}:
        return
    import shutil

    shutil.rmtree(out / ".hydra", ignore_errors=True)
    (out / log_name).unlink(missing_ok=True)
    for d in (out, out.parent):
        if d == out or d.parent.name == "outputs":
            try:
                d.rmdir()
            except OSError:
                return


def recipe(
    config_name: str,
    run: Callable[..., Any],
    *,
    scenario_overrides: bool = False,
    check: Callable[[Any], None] | None = None,
):
    """A Hydra entry point for ``recipes/conf/<config_name>.yaml`` calling ``run(cfg, out)``.

    Args:
        config_name: the recipe's config.
        run: ``run(cfg, out)`` (or ``run(cfg, out, overrides)`` with ``scenario_overrides``); an
            int return value is the exit status.
        scenario_overrides: pass the command line's scenario (``env=…``, ``env.*``, ``reward.*``) as
            a third argument, for recipes that plan runs of their own.
        check: validates the composed config before ``run`` (default: the recipe's own checks in
            ``irdrc.experiments.validate``).

    Set ``IRDRC_TRACEBACK=1`` to see the traceback of an error instead of its one line.
    """
    import hydra
    from hydra.core.hydra_config import HydraConfig

    from irdrc.experiments.validate import check_overrides, validate

    register_scenarios()
    full = bool(os.environ.get("IRDRC_TRACEBACK"))

    @hydra.main(config_path=str(CONF_DIR), config_name=config_name, version_base=None)
    def _main(cfg) -> None:
        out = Path(HydraConfig.get().runtime.output_dir)
        log_name = f"{HydraConfig.get().job.name}.log"
        stdout = sys.stdout
        with open(out / log_name, "a", encoding="utf-8") as log:
            sys.stdout = _Tee(stdout, log)  # the run's printed lines are kept in its log
            try:
                if scenario_overrides:
                    from irdrc.experiments.config import scenario_overrides as current

                    code = run(cfg, out, current())
                else:
                    code = run(cfg, out)
            except RunInterrupted as err:
                print(f"error: {err}", file=log)
                fail(str(err), err.code)
            except (ValueError, OSError) as err:
                if full:
                    raise
                print(f"error: {err}", file=log)
                refused: str | None = str(err)
            else:
                refused = None
            finally:
                sys.stdout = stdout
        if refused is not None:
            _remove_if_empty(out, log_name)  # a refused run leaves no trace
            fail(refused)
        if isinstance(code, int) and code:
            sys.exit(code)  # Hydra's wrapper drops return values, so exit from inside the task

    def main() -> None:
        args = sys.argv[1:]
        try:
            args, notes = rename_overrides(config_name, args)
            args, stored = stored_overrides(args)
            overrides = [a for a in args if not a.startswith("-")]
            check_overrides(config_name, overrides)
            # Checked before Hydra starts, which creates (or, when it exists, rewrites) the run
            # directory: a refused run leaves no trace.
            cfg = compose(
                config_name, [o for o in overrides if not override_key(o).startswith("hydra")]
            )
            (check or (lambda c: validate(config_name, c, overrides)))(cfg)
        except (ValueError, OSError) as err:
            if full:
                raise
            fail(str(err))
        except Exception as err:  # Hydra's own parse errors: one line, not a traceback
            if full:
                raise
            fail(f"{type(err).__name__}: {str(err).strip().splitlines()[0]}")
        for note in notes:
            print(note, file=sys.stderr)
        if stored:
            print(f"resume: with the run's stored overrides {' '.join(stored)}", file=sys.stderr)
        resume = cfg.get("resume")
        if (
            isinstance(resume, str)
            and resume
            and not any(a.startswith("hydra.run.dir=") for a in args)
        ):
            # a resumed run goes on in its own directory: one run, one directory
            run_dir = Path(resume).expanduser().resolve().parent
            args.append(f"hydra.run.dir={_quoted_path(run_dir)}")
        if not any(a.startswith("hydra.job.name=") for a in args):
            args.append(f"hydra.job.name={config_name}")  # the log file is <recipe>.log
        sys.argv[1:] = args
        _main()

    return main
