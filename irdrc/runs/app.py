"""What every recipe does around its run: the command line composed once into the recipe's typed
config and checked before any work, the run scaffold opened, the recipe's run function called, and
every error reported in one line.

A recipe module (``irdrc.recipes.dqn`` …) provides ``NAME`` (its config file), ``load(composed,
resume) -> Config`` (its typed config, checked), ``run(config, run)`` and, for training recipes,
``RESUMABLE = True`` (``resume=PATH`` goes on from a checkpoint); optionally ``ELSEWHERE`` (group
choices that belong to another recipe, and the command to use instead),
``misplaced_override(args)`` (where an override the recipe refused goes instead: the sweep's
method's keys), ``recorded(config, cfg)`` (the composed config as its run records it, with what
the recipe resolves in Python written in: ``compose.recorded``), and ``ALGO_KEYS`` with
``algo_keys(args)`` (the ``algo.*`` keys its learners read: ``compose_recipe``).
``recipes/<name>.py`` is ``app.main(module)``. Set ``IRDRC_TRACEBACK=1`` to see the traceback of an error instead of its
one line.
"""

from __future__ import annotations

import os
import sys
from dataclasses import dataclass, replace
from pathlib import Path
from types import ModuleType
from typing import Any

from irdrc.runs.compose import (
    CONF_DIR,
    Composed,
    _flat_keys,
    compose_recipe,
    recipe_call,
    recorded,
    stored_overrides,
    unknown_key,
)
from irdrc.runs.grid import override_key

EXIT_USAGE = 2
"""Exit status of a run refused before any work (a bad key or value)."""


@dataclass(frozen=True)
class Prepared:
    """A recipe's run before it starts: its typed ``config``, the ``composed`` config, its run
    directory, the checkpoint it resumes from, and notes for the user."""

    config: Any
    composed: Composed
    run_dir: Path
    resume: dict[str, Any] | None
    notes: list[str]


def prepare(module: ModuleType, args: list[str]) -> Prepared:
    """The command line ``args`` of ``module``'s recipe composed once (Hydra), a resumed run's
    checkpoint merged in, turned into the recipe's typed config and checked.

    Raises:
        ValueError: the first bad key or value, naming it (nothing has been written).
    """
    notes: list[str] = []
    args, stored = stored_overrides(args)
    if stored:
        notes.append(f"resume: with the run's stored overrides {' '.join(stored)}")
    for a in args:
        if "=" not in a and not a.startswith("~"):
            many = (
                "; several runs over a grid of values: python recipes/sweep.py method=… "
                "sweep.grid='{seed: [0,1,2]}'"
                if a in ("-m", "--multirun")
                else ""
            )
            raise ValueError(f"{a!r} is not an override: write key=value{many}")
        if a in getattr(module, "ELSEWHERE", {}):
            raise ValueError(f"{a} is not a {module.NAME} profile: use {module.ELSEWHERE[a]}")
    try:
        composed = compose_recipe(module, args)
    except ValueError as err:
        misplaced = getattr(module, "misplaced_override", None)
        where = misplaced(args) if misplaced is not None else None
        if where is None:
            raise
        raise ValueError(where) from err
    resume = None
    if getattr(module, "RESUMABLE", False) and isinstance(composed.cfg.get("resume"), str):
        from irdrc.agents.base import load_checkpoint
        from irdrc.runs.resume import checkpoint_recipe, edited_config, resumed_config
        from irdrc.runs.scaffold import python_command, quoted

        path = Path(composed.cfg["resume"]).expanduser()
        resume = load_checkpoint(path)
        wrote = checkpoint_recipe(path, resume)
        if wrote is not None and wrote != module.NAME:
            raise ValueError(
                f"resume={path} is a checkpoint of the {wrote} recipe; go on with it with: "
                f"{python_command()} {recipe_call(wrote)} resume={quoted(path)}"
            )
        if edited := edited_config(path, resume["config"]):
            raise ValueError(
                f"{path.parent / 'config.yaml'} was edited after its run wrote it "
                f"({'; '.join(edited)}); a resumed run keeps its checkpoint's configuration: "
                "restore the file, and set what a resumed run may change on the command line"
            )
        merged = resumed_config(path, resume["config"], composed.cfg, composed.explicit)
        composed = replace(composed, cfg=merged)
    try:
        config = module.load(composed, resume)
    except ValueError as err:
        raise ValueError(_added_key(module.NAME, composed, args, err)) from None
    composed = recorded(module, config, composed)
    run_dir = Path(composed.run_dir)
    if resume is not None and not any(a.startswith("hydra.run.dir=") for a in args):
        run_dir = Path(composed.cfg["resume"]).expanduser().resolve().parent  # one run, one dir
    return Prepared(config, composed, run_dir.expanduser(), resume, notes)


def _added_key(name: str, composed: Composed, args: list[str], err: ValueError) -> str:
    """A key the command line added with ``+`` that the recipe does not read, named in full with
    the closest valid key; any other error as it is."""
    if not str(err).startswith("unknown key"):
        return str(err)
    for a in args:
        if a.startswith("+") and not a.startswith("++"):
            key = override_key(a)
            known = {k for k in _flat_keys(composed.cfg) if not k.startswith(key)}
            return unknown_key(name, key, known)
    return str(err)


CONFIG_FLAG = "--cfg"
"""Print the run's configuration, checked, and run nothing (Hydra's flag; ``--cfg job`` too)."""


def _config_flag(args: list[str]) -> tuple[list[str], bool]:
    """``args`` without ``--cfg`` (and a ``job`` after it, as Hydra writes it), and whether it
    was there."""
    if CONFIG_FLAG not in args:
        return args, False
    i = args.index(CONFIG_FLAG)
    rest = args[i + 1 :]
    if rest[:1] == ["job"]:
        rest = rest[1:]
    return [*args[:i], *rest], True


def _help(module: ModuleType) -> None:
    print((module.__doc__ or module.NAME).strip())
    print(
        f"\nkeys and their defaults: {CONF_DIR / module.NAME}.yaml (every key: docs/CONFIG.md); "
        "override any as key=value, the run directory as hydra.run.dir=DIR; "
        f"{CONFIG_FLAG} prints the run's config.yaml, checked, and runs nothing"
    )


def execute(module: ModuleType, args: list[str]) -> int:
    """Run ``module``'s recipe with the command line ``args``; returns the exit status."""
    from irdrc.runs.scaffold import Run, resume_hint
    from irdrc.runs.signals import RunInterrupted, Signalled

    if args and args[0] in ("-h", "--help"):
        _help(module)
        return 0
    args, show = _config_flag(args)
    full = bool(os.environ.get("IRDRC_TRACEBACK"))
    try:
        prepared = prepare(module, args)
    except (ValueError, OSError) as err:
        if full:
            raise
        return fail(str(err))
    except KeyboardInterrupt:
        return fail("interrupted (Ctrl-C) before the run started; nothing was written", 130)
    if show:
        from omegaconf import OmegaConf

        print(OmegaConf.to_yaml(prepared.composed.cfg), end="")
        return 0
    for note in prepared.notes:
        print(note, file=sys.stderr)
    run = Run(module.NAME, prepared.composed, prepared.run_dir, prepared.resume)
    try:
        run.open()
    except ValueError as err:
        return fail(str(err))
    refused = False
    try:
        result = module.run(prepared.config, run)
    except RunInterrupted as err:
        run.log_line(f"error: {err}")
        return fail(str(err), err.code)
    except (ValueError, OSError) as err:
        if full:
            raise
        message = str(err)
        if isinstance(err, OSError):  # a full disk, a lost mount: the checkpoint, if any, goes on
            message += resume_hint(module.NAME, run.dir)
        run.log_line(f"error: {message}")
        refused = True
        return fail(message)
    except Signalled as sig:
        message = f"stopped by {sig}; what the run wrote is in {run.dir}" + resume_hint(
            module.NAME, run.dir
        )
        run.log_line(f"error: {message}")
        return fail(message, 128 + sig.signum)
    except KeyboardInterrupt:
        run.log_line("error: interrupted (Ctrl-C)")
        return fail(f"interrupted (Ctrl-C); what the run wrote is in {run.dir}", 130)
    finally:
        run.close(refused=refused)
    return result if isinstance(result, int) else 0


def fail(message: str, code: int = EXIT_USAGE) -> int:
    """Print ``error: message`` (no traceback); returns ``code``."""
    print(f"error: {message}", file=sys.stderr, flush=True)
    return code


def main(module: ModuleType, args: list[str] | None = None) -> None:
    """The entry point of ``recipes/<name>.py`` and of ``irdrc NAME``: run the recipe on the
    command line (``args``, default ``sys.argv[1:]``), exit with its status (by ``os._exit``
    where an interrupted solver call still runs: ``solver_running``)."""
    code = execute(module, sys.argv[1:] if args is None else args)
    cmdp = sys.modules.get("irdrc.core.cmdp")
    if cmdp is not None and cmdp.solver_running():
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(code)
    sys.exit(code)
