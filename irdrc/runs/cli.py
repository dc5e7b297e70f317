"""``irdrc`` command: ``irdrc RECIPE [overrides…]`` runs ``recipes/RECIPE.py``; ``irdrc`` lists the
recipes, each with the summary of what it does."""

from __future__ import annotations

import ast
import subprocess
import sys

from irdrc.core.checks import closest
from irdrc.runs.compose import ROOT, list_scenarios


def recipes() -> dict[str, str]:
    """The runnable recipes, each with its docstring's summary (its first paragraph, on one line)."""
    out = {}
    for path in sorted((ROOT / "recipes").glob("*.py")):
        if path.stem.startswith("_"):
            continue
        doc = ast.get_docstring(ast.parse(path.read_text())) or ""
        out[path.stem] = " ".join(doc.strip().split("\n\n")[0].split())
    return out


def main(argv: list[str] | None = None) -> int:
    """Entry point of the console script."""
    args = sys.argv[1:] if argv is None else argv
    known = recipes()
    if not args or args[0] in ("-h", "--help", "list"):
        print("usage: irdrc RECIPE [overrides ...]   e.g. irdrc solve env.p1.speed=1.0")
        print("       irdrc RECIPE --help            what it does, with examples")
        print("       irdrc --version\n")
        width = max(map(len, known))
        for name, what in known.items():
            print(f"  {name:<{width}}  {what}")
        print(f"\nscenarios: {', '.join(list_scenarios())}  (env=NAME)")
        return 0
    if args[0] in ("-V", "--version"):
        from importlib.metadata import PackageNotFoundError, version

        try:
            print(f"irdrc {version('irdrc')}")
        except PackageNotFoundError:  # run from a checkout that pip never installed
            print("irdrc (not installed: pip install -e . installs it)")
        return 0
    name = args[0].replace("-", "_")
    if name not in known:
        near = closest(name, known)
        hint = f"did you mean {near}? " if near else ""
        print(
            f"irdrc: unknown recipe {args[0]!r}; {hint}recipes: {', '.join(known)}",
            file=sys.stderr,
        )
        return 2
    return subprocess.call([sys.executable, str(ROOT / "recipes" / f"{name}.py"), *args[1:]])


if __name__ == "__main__":
    sys.exit(main())
