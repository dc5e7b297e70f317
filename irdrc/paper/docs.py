"""Generated tables in docs/: each lies between ``<!-- generated:NAME -->`` and
``<!-- /generated:NAME -->`` and is refreshed from a run directory, never typed by hand.

A benchmark writes its table as ``<name>.md`` in its run directory (``write_table_md``: the table and
one line saying when, where and how long it was measured). ``refresh`` puts that file's text
between the markers of the block it names, with the command that made the run directory above it
(read from Hydra's record of the run: the recipe and its command-line overrides)::

    python -m irdrc.paper.docs docs/BENCHMARKS.md outputs/2026-11-25/10-00-00
    python -m irdrc.paper.docs docs/BENCHMARKS.md bench_robust:multilevel=outputs/…/…

A run directory alone fills the block named after the one ``*.md`` table in it; ``NAME=DIR``
names the block (several runs of one benchmark fill several blocks).
"""

from __future__ import annotations

import sys
from collections.abc import Sequence
from pathlib import Path

from omegaconf import OmegaConf

from irdrc.runs.grid import shell_quote
from irdrc.runs.results import atomic_write_text

TABLE_FILES_IGNORED = ("claims.md",)
"""``*.md`` files of a run directory that are not its benchmark table (Figure 2's claims go into
docs/REPRODUCTION.md through ``irdrc.paper.report``)."""


def replace_block(text: str, name: str, body: str) -> str:
    """``text`` with the body between ``<!-- generated:NAME -->`` and ``<!-- /generated:NAME -->``
    replaced by ``body``.

    Raises:
        ValueError: the markers are missing or out of order.
    """
    start, end = f"<!-- generated:{name} -->", f"<!-- /generated:{name} -->"
    i, j = text.find(start), text.find(end)
    if i < 0 or j < i:
        raise ValueError(f"no block {start} … {end}")
    return text[: i + len(start)] + "\n" + body.rstrip() + "\n" + text[j:]


def block_names(text: str) -> list[str]:
    """The names of the generated blocks of a document, in order."""
    out, tag = [], "<!-- generated:"
    i = text.find(tag)
    while i >= 0:
        j = text.find(" -->", i)
        out.append(text[i + len(tag) : j])
        i = text.find(tag, j)
    return out


def run_command(run_dir: Path) -> str:
    """The command that made ``run_dir``: ``python recipes/<recipe>.py <overrides>`` from Hydra's
    record of the run (``.hydra/hydra.yaml``: the job name every recipe sets to its own name, and
    the task overrides), ``hydra.*`` and ``resume=…`` overrides left out.

    Raises:
        ValueError: ``run_dir`` holds no Hydra record.
    """
    record = Path(run_dir) / ".hydra" / "hydra.yaml"
    if not record.is_file():
        raise ValueError(f"{run_dir} is not a recipe's run directory (no .hydra/hydra.yaml)")
    hydra = OmegaConf.load(record).hydra
    # a resumed run's table is the original command's: resume=… is left out with hydra.*
    overrides = [o for o in hydra.overrides.task if not o.startswith(("hydra.", "resume="))]
    return " ".join(["python", f"recipes/{hydra.job.name}.py", *map(shell_quote, overrides)])


def table_file(run_dir: Path) -> Path:
    """The one benchmark table (``*.md``) of a run directory."""
    found = sorted(p for p in Path(run_dir).glob("*.md") if p.name not in TABLE_FILES_IGNORED)
    if len(found) != 1:
        names = ", ".join(p.name for p in found) or "none"
        raise ValueError(f"{run_dir} must hold one *.md table; it holds {names}")
    return found[0]


def block_body(run_dir: Path) -> str:
    """What a block holds: the command in a code block, then the run's table file."""
    return (
        f"```bash\n{run_command(run_dir)}\n```\n\n" + table_file(run_dir).read_text().strip() + "\n"
    )


def refresh(doc: Path, runs: Sequence[str]) -> list[str]:
    """Refresh the blocks of ``doc`` from run directories (``DIR`` or ``NAME=DIR``); returns the
    names of the blocks written. Every run is read before the document is written, so a bad one
    changes nothing."""
    doc = Path(doc)
    text = doc.read_text()
    names = []
    for arg in runs:
        name, _, path = arg.rpartition("=") if "=" in arg else ("", "", arg)
        run_dir = Path(path)
        name = name or table_file(run_dir).stem
        if name not in block_names(text):
            raise ValueError(
                f"{doc} has no block {name!r}; its blocks: {', '.join(block_names(text)) or 'none'}"
            )
        text = replace_block(text, name, block_body(run_dir))
        names.append(name)
    atomic_write_text(doc, text)
    return names


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m irdrc.paper.docs DOC RUN [RUN …]``: refresh DOC's blocks from the runs."""
    args = list(sys.argv[1:] if argv is None else argv)
    if len(args) < 2 or args[0] in ("-h", "--help"):
        print(__doc__.strip().split("\n\n")[0])
        print("usage: python -m irdrc.paper.docs DOC RUN_DIR|NAME=RUN_DIR [...]")
        return 0 if args[:1] in (["-h"], ["--help"]) else 2
    try:
        names = refresh(Path(args[0]), args[1:])
    except (ValueError, OSError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    print(f"refreshed {', '.join(names)} in {args[0]}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
