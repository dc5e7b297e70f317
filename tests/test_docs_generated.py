"""The docs' generated tables: ``python -m irdrc.paper.docs`` fills a block from a run with the
command that made it (quoted for a shell), and no table names a profile, candidate or learner its
command's config no longer has."""

from __future__ import annotations

import subprocess
from pathlib import Path

import pytest
from conftest import recipe_module
from omegaconf import OmegaConf
from test_docs import DOCS, commands

from irdrc.paper.docs import block_names, shell_quote
from irdrc.runs.compose import compose
from irdrc.runs.grid import override_key


def fake_run(tmp_path: Path, name: str = "bench_env", table: str = "| a |\n|---|\n| 1 |") -> Path:
    """A run directory as a recipe leaves it: Hydra's record of the command, and the table."""
    run = tmp_path / "run"
    (run / ".hydra").mkdir(parents=True)
    record = {
        "hydra": {
            "job": {"name": name},
            "overrides": {"task": ["sizes=[64]", "p1_speed=[0.1, 0.5]", "hydra.run.dir=x"]},
        }
    }
    OmegaConf.save(OmegaConf.create(record), run / ".hydra" / "hydra.yaml")
    (run / f"{name}.md").write_text(table + "\n\nMeasured on today.\n")
    return run


def test_refresh_fills_a_block_with_the_command_and_the_table(tmp_path):
    from irdrc.paper.docs import main

    run = fake_run(tmp_path)
    doc = tmp_path / "DOC.md"
    doc.write_text("# t\n\n<!-- generated:bench_env -->\nold\n<!-- /generated:bench_env -->\nend\n")
    assert main([str(doc), str(run)]) == 0
    text = doc.read_text()
    assert "old" not in text and text.endswith("<!-- /generated:bench_env -->\nend\n")
    # the command as the run recorded it (hydra.* left out), then the table and its measured line
    assert "python recipes/bench_env.py 'sizes=[64]' 'p1_speed=[0.1, 0.5]'\n```" in text
    assert "| 1 |\n\nMeasured on today." in text
    # NAME=DIR fills another block from the same kind of run
    doc.write_text("<!-- generated:other -->\n<!-- /generated:other -->\n")
    assert main([str(doc), f"other={run}"]) == 0 and "| 1 |" in doc.read_text()


def test_refresh_refuses_what_it_cannot_do_and_changes_nothing(tmp_path):
    from irdrc.paper.docs import main

    run = fake_run(tmp_path)
    doc = tmp_path / "DOC.md"
    doc.write_text("<!-- generated:bench_env -->\nold\n<!-- /generated:bench_env -->\n")
    before = doc.read_text()
    assert main([str(doc), f"nope={run}"]) == 2  # no such block
    assert main([str(doc), str(tmp_path)]) == 2  # not a run directory
    (run / "second.md").write_text("x")
    assert main([str(doc), str(run)]) == 2  # two tables: which one?
    assert doc.read_text() == before


@pytest.mark.parametrize(
    "arg", ["a=b", "candidates={x: ['algo.n_steps=3']}", "p=[0.1]", "odd\"'$x", "it's"]
)
def test_shell_quote_round_trips_through_a_shell(arg: str) -> None:
    """The command shown above a generated table, pasted into a shell, gives back each argument."""
    out = subprocess.run(
        ["sh", "-c", f"printf %s {shell_quote(arg)}"], capture_output=True, text=True, check=True
    )
    assert out.stdout == arg


NAMED = ("profiles", "candidates", "learners", "paper_learners", "random_learners")
"""Config keys that name a benchmark's rows (its profiles, candidates or learners)."""
ROW_NAMES = ("profile", "candidate", "learner")
"""The header of the column that names a table's rows by those keys."""


def stale_rows(block: str) -> list[str]:
    """The row names of a generated table that its command's config, composed today, no longer
    has (a table made with profiles that are gone); [] when its rows are not named by the config."""
    found = commands(block)
    if not found:
        return []
    recipe, args = found[0]
    module = recipe_module(recipe)
    args = [a for a in args if "=" in a and not override_key(a).startswith("hydra")]
    cfg = compose(module.NAME, args).cfg
    names: set[str] = set()
    for key in NAMED:
        value = cfg.get(key, "absent")
        if key == "candidates" and value is None:
            value = {"dqn": []}  # bench_robust's default: the default profile alone
        if isinstance(value, dict | list):
            names |= set(value)
    if not names:
        return []
    rows, column = [], None
    for line in block.splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if not line.startswith("|"):
            column = None  # a table ended
        elif column is None:  # a table's header: the column naming its rows, if any
            column = next((i for i, c in enumerate(cells) if c in ROW_NAMES), -1)
        elif column >= 0 and not set(cells[0]) <= set("-: "):
            rows.append(cells[column])
    rows = [r for r in rows if r and not r.startswith("**")]  # aggregate rows
    return sorted({r for r in rows if r not in names})


def test_no_generated_table_names_a_profile_that_is_gone():
    bad = []
    for doc in DOCS:
        text = doc.read_text()
        for name in block_names(text):
            body = text.split(f"<!-- generated:{name} -->")[1].split(f"<!-- /generated:{name} -->")[
                0
            ]
            if stale := stale_rows(body):
                bad.append(f"{doc.name} {name}: {stale}")
    assert not bad, bad


def test_the_stale_table_check_can_fail():
    block = "```bash\npython recipes/bench_dqn.py\n```\n\n| profile | x |\n|---|---|\n| dqn | 1 |\n| previous_default | 2 |\n"
    assert stale_rows(block) == ["previous_default"]
