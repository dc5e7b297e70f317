"""What every recipe does around its run: scenarios registered, renamed keys mapped, errors clear.

A recipe is ``main = recipe("dqn", run_dqn)`` plus ``if __name__ == "__main__": main()``: the run
function gets the composed config and the run directory, and its return value (an exit code or a
summary) decides the exit status.
"""

from __future__ import annotations

import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

from irdrc.experiments.config import CONF_DIR, register_scenarios, rename_overrides


def recipe(config_name: str, run: Callable[..., Any], *, scenario_overrides: bool = False):
    """A Hydra entry point for ``recipes/conf/<config_name>.yaml`` calling ``run(cfg, out)``.

    Args:
        config_name: the recipe's config.
        run: ``run(cfg, out)`` (or ``run(cfg, out, overrides)`` with ``scenario_overrides``); an
            int return value is the exit status.
        scenario_overrides: pass the command line's scenario (``env=…``, ``env.*``, ``reward.*``) as
            a third argument, for recipes that plan runs of their own.
    """
    import hydra
    from hydra.core.hydra_config import HydraConfig

    register_scenarios()

    @hydra.main(config_path=str(CONF_DIR), config_name=config_name, version_base=None)
    def _main(cfg) -> None:
        out = Path(HydraConfig.get().runtime.output_dir)
        if scenario_overrides:
            from irdrc.experiments.config import scenario_overrides as current

            code = run(cfg, out, current())
        else:
            code = run(cfg, out)
        if isinstance(code, int) and code:
            sys.exit(code)  # Hydra's wrapper drops return values, so exit from inside the task

    def main() -> None:
        try:
            sys.argv[1:], notes = rename_overrides(config_name, sys.argv[1:])
        except ValueError as err:
            print(f"error: {err}", file=sys.stderr)
            sys.exit(2)
        for note in notes:
            print(note, file=sys.stderr)
        if not any(a.startswith("hydra.job.name=") for a in sys.argv[1:]):
            sys.argv.append(f"hydra.job.name={config_name}")  # the log file is <recipe>.log
        _main()

    return main
