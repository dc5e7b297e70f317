"""The README and docs/ stay true to the code: every command they give runs its recipe's own
pre-run checks (keys, values, combinations) without an error, every script and linked file exists,
every anchor names a heading, and the model keys the README's table lists are keys of the config."""

from __future__ import annotations

import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest
from conftest import TINY_DQN
from omegaconf import OmegaConf

from irdrc.experiments.config import compose, rename_overrides
from irdrc.experiments.grid import override_key
from irdrc.experiments.validate import GENERAL_MODEL_KEYS, check_overrides, flat_keys, validate
from irdrc.paper.docs import shell_quote

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
DOCS = sorted((ROOT / "docs").glob("*.md"))
STUDIES = {p for p in DOCS if p.name.startswith("STUDY_")}
"""Study documents record what was measured on the commit they name; their commands run there."""

COMMAND = re.compile(
    r"(?:python|\.venv/bin/python) recipes/(\w+)\.py([^`\n]*)|`irdrc (\w+)([^`\n]*)"
)
PLACEHOLDER = re.compile(r"DATE|TIME|…|\.\.\.")


def commands(text: str) -> list[tuple[str, list[str]]]:
    """(recipe, arguments) of every ``python recipes/NAME.py …`` and ``irdrc NAME …`` in ``text``,
    comments after ``#`` dropped."""
    out = []
    for m in COMMAND.finditer(text):
        recipe = m.group(1) or m.group(3)
        rest = (m.group(2) if m.group(1) else m.group(4)) or ""
        rest = re.split(r"\s+#\s", rest)[0]
        try:
            args = shlex.split(rest)
        except ValueError:
            args = rest.split()
        out.append((recipe, args))
    return out


def config_name(recipe: str) -> str:
    """The config a recipe composes: the name its ``recipe("…", …)`` call gives."""
    source = (ROOT / "recipes" / f"{recipe}.py").read_text()
    return re.search(r'recipe\(\s*"(\w+)"', source).group(1)


def check_command(recipe: str, args: list[str], files: dict[str, Path] | None = None) -> None:
    """What a recipe checks before any work, on ``args``; an argument holding a placeholder
    (``outputs/DATE/TIME/…``) has its key checked, and its value replaced by a real file of that
    kind where ``files`` has one (``checkpoint`` / ``resume``: a DQN checkpoint, ``policy``: a
    policy table), else left out."""
    assert (ROOT / "recipes" / f"{recipe}.py").is_file(), f"recipes/{recipe}.py does not exist"
    name = config_name(recipe)
    args, _ = rename_overrides(name, [a for a in args if not a.startswith("-")])
    check_overrides(name, args)
    files = files or {}
    args = [
        f"{override_key(a)}={files[override_key(a)]}"
        if PLACEHOLDER.search(a) and override_key(a) in files
        else a
        for a in args
    ]
    concrete = [a for a in args if not PLACEHOLDER.search(a)]
    plain = [a for a in concrete if not override_key(a).startswith("hydra")]
    validate(name, compose(name, plain), concrete)


def readme_commands() -> list[tuple[str, list[str]]]:
    return commands(README.read_text())


@pytest.mark.parametrize(
    "recipe,args",
    readme_commands(),
    ids=[f"{r} {' '.join(a)}"[:80] for r, a in readme_commands()],
)
def test_readme_command_passes_its_checks(recipe, args, example_files):
    check_command(recipe, args, example_files)


@pytest.fixture(scope="module")
def example_files(tmp_path_factory) -> dict[str, Path]:
    """Real files for the README's placeholders: a short DQN run's checkpoint and policy table."""
    out = tmp_path_factory.mktemp("example_run")
    tiny = [*TINY_DQN, "eval.mc_episodes=0"]
    r = subprocess.run(
        [sys.executable, str(ROOT / "recipes" / "dqn.py"), *tiny, f"hydra.run.dir={out}"],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert r.returncode == 0, r.stderr[-2000:]
    ckpt = out / "checkpoint.pt"
    return {"checkpoint": ckpt, "resume": ckpt, "policy": out / "policy.csv"}


def test_readme_has_the_commands_it_promises():
    found = {r for r, _ in readme_commands()}
    recipes = {p.stem for p in (ROOT / "recipes").glob("*.py")}
    assert recipes <= found | {"demo"}, f"recipes missing from the README: {recipes - found}"
    text = README.read_text()
    for script in re.findall(r"bash (ci/\w+\.sh)", text):
        assert (ROOT / script).is_file(), script


@pytest.mark.parametrize("doc", [p for p in DOCS if p not in STUDIES], ids=lambda p: p.name)
def test_docs_commands_name_existing_recipes_and_keys(doc):
    for recipe, args in commands(doc.read_text()):
        assert (ROOT / "recipes" / f"{recipe}.py").is_file(), f"{doc.name}: recipes/{recipe}.py"
        name = config_name(recipe)
        args = [a for a in args if not a.startswith("-") and "=" in a]
        args, _ = rename_overrides(name, [a for a in args if not PLACEHOLDER.search(a)])
        check_overrides(name, args)


def expand(key: str) -> list[str]:
    """``env.p0.{road,weather}`` → ``env.p0.road``, ``env.p0.weather``."""
    m = re.search(r"\{([^}]*)\}", key)
    if not m:
        return [key]
    return [key[: m.start()] + part + key[m.end() :] for part in m.group(1).split(",")]


def test_readme_model_keys_exist():
    keys = flat_keys(OmegaConf.to_container(compose("solve"), resolve=False))
    table = README.read_text().split("### Configuration names")[1].split("**One name per idea")[0]
    first = [row.split("|")[1] for row in table.splitlines() if row.startswith("| `")]
    listed = [k for cell in first for t in re.findall(r"`([^`]+)`", cell) for k in expand(t)]
    listed = [k for k in listed if "…" not in k]
    assert len(listed) >= 20
    for key in listed:
        general = any(key == g or key.startswith(g + ".") for g in GENERAL_MODEL_KEYS)
        assert key in keys or general, f"README lists {key}, which the config does not have"


def slug(heading: str) -> str:
    """GitHub's anchor for a heading: lower case, punctuation dropped, spaces to hyphens."""
    text = re.sub(r"[^\w\- ]", "", heading.strip().lower())
    return text.replace(" ", "-")


def anchors(path: Path) -> set[str]:
    return {slug(h) for h in re.findall(r"^#+ (.+)$", path.read_text(), flags=re.M)}


@pytest.mark.parametrize("doc", [README, *DOCS], ids=lambda p: p.name)
def test_links_point_at_files_and_headings_that_exist(doc):
    text = re.sub(r"```.*?```", "", doc.read_text(), flags=re.S)
    for target in re.findall(r"\]\(([^)\s]+)\)", text):
        if target.startswith(("http://", "https://", "mailto:")):
            continue
        path, _, anchor = target.partition("#")
        file = (doc.parent / path).resolve() if path else doc
        assert file.exists(), f"{doc.name} links to {target}: no such file"
        if anchor and file.suffix == ".md":
            assert anchor in anchors(file), f"{doc.name} links to {target}: no such heading"


def test_readme_is_a_door():
    text = README.read_text()
    assert len(text.splitlines()) <= 350
    results = text.split("## Results")[1].split("\n## ")[0]
    assert len(results.strip().splitlines()) <= 20 + 2  # 20 lines of results, and the links line


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


@pytest.mark.parametrize(
    "override, says",
    [
        ("algo=qlearning", "use python recipes/qlearning.py"),
        ("algo=qlearning_paper", "use python recipes/qlearning.py algo=qlearning_paper"),
        ("algo=dqn_lagrangian", "use python recipes/constrained.py learner=dqn_lagrangian"),
        ("executor=ray", "executor= is for python recipes/sweep.py"),
    ],
)
def test_a_choice_of_another_recipe_names_that_recipe(override: str, says: str) -> None:
    """``dqn.py --help`` lists every group option; one that belongs elsewhere says where (it gave
    ~10 unknown-key errors, or Hydra's raw 'Could not override')."""
    with pytest.raises(ValueError, match=re.escape(says)):
        check_overrides("dqn", [override])


def test_citation_license_and_the_files_docs_name_exist() -> None:
    """CITATION.cff names the letter's four authors; LICENSE matches pyproject's MIT; the README
    carries the BibTeX entry."""
    cff = OmegaConf.load(ROOT / "CITATION.cff")
    names = [a["family-names"] for a in cff["preferred-citation"].authors]
    assert names == ["Hieu", "Hoang", "Luong", "Niyato"]
    assert cff.license == "MIT" and (ROOT / "LICENSE").read_text().startswith("MIT License")
    assert 'license = { text = "MIT" }' in (ROOT / "pyproject.toml").read_text()
    assert "@article{hieu2020irdrc" in (ROOT / "README.md").read_text()
