"""``irdrc`` command: ``irdrc RECIPE [hydra overrides…]`` runs ``recipes/RECIPE.py``; ``irdrc`` lists them."""

from __future__ import annotations

import subprocess
import sys

from irdrc.experiments.config import ROOT, list_scenarios


def recipes() -> list[str]:
    """Names of the runnable recipes."""
    return sorted(p.stem for p in (ROOT / "recipes").glob("*.py") if not p.stem.startswith("_"))


def main(argv: list[str] | None = None) -> int:
    """Entry point of the console script."""
    args = sys.argv[1:] if argv is None else argv
    if not args or args[0] in ("-h", "--help", "list"):
        print("usage: irdrc RECIPE [overrides ...]   e.g. irdrc solve env.p1.speed=1.0")
        print(f"recipes:   {', '.join(recipes())}")
        print(f"scenarios: {', '.join(list_scenarios())}  (env=NAME)")
        return 0
    name = args[0].replace("-", "_")
    if name not in recipes():
        print(
            f"irdrc: unknown recipe {args[0]!r}; recipes: {', '.join(recipes())}", file=sys.stderr
        )
        return 2
    return subprocess.call([sys.executable, str(ROOT / "recipes" / f"{name}.py"), *args[1:]])


if __name__ == "__main__":
    sys.exit(main())
