"""The README and docs/ stay true to the code: every command they give runs its recipe's own
pre-run checks (keys, values, combinations) without an error, every config key they name exists,
every script and linked file exists, every anchor names a heading, and the model keys the README's
table lists are keys of the config."""

from __future__ import annotations

import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest
from conftest import TINY_DQN, load, recipe_module
from omegaconf import OmegaConf

from irdrc.runs.compose import (
    CONF_DIR,
    OPTIONAL_KEYS,
    _flat_keys,
    compose,
    config_groups,
)
from irdrc.runs.grid import override_key

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
DOCS = sorted((ROOT / "docs").glob("*.md"))
LAB = sorted((ROOT / "docs" / "lab").glob("*.md"))

COMMAND = re.compile(
    r"(?:python|\.venv/bin/python) recipes/(\w+)\.py([^`\n]*)|`irdrc (\w+)([^`\n]*)"
)
PLACEHOLDER = re.compile(r"DATE|TIME|…|\.\.\.")


AT_TAG = re.compile(r"<!-- at-tag: ([\w.-]+) -->.*?<!-- /at-tag -->", re.S)
"""A region of a doc about an earlier commit (its keys and commands run at that tag only)."""


def current(text: str) -> str:
    """``text`` without its ``at-tag`` regions."""
    return AT_TAG.sub("", text)


def test_at_tag_regions_are_closed_and_cut():
    text = "a `algo.lr`\n<!-- at-tag: v1 -->`algo.n_steps=3`\n<!-- /at-tag -->\nb"
    assert current(text) == "a `algo.lr`\n\nb"
    for doc in [README, *DOCS, *LAB]:
        body = doc.read_text()
        assert body.count("<!-- at-tag:") == body.count("<!-- /at-tag -->"), doc.relative_to(ROOT)


TAG_NAME = re.compile(r"(?:tag|tagged|at-tag:) `?([a-z0-9]+(?:-[a-z0-9]+)*-v\d+)`?")
TAG_ROW = re.compile(r"^\| `([\w.-]+)` \| ([0-9a-f]{7,40}) \|", re.M)


REGISTER = ROOT / "docs" / "lab" / "removed-options.md"
"""The register of removed options: each tag that runs one, with its commit."""


def test_every_tag_a_doc_names_has_its_commit_in_the_register():
    """A clone may lack the tags: the register's table names each one's commit, and that commit is
    in this history. The lab notes are read too: they name the tags of what they measured."""
    table = dict(TAG_ROW.findall(REGISTER.read_text()))
    named = {t for doc in [README, *DOCS, *LAB] for t in TAG_NAME.findall(doc.read_text())}
    assert named, "the pattern finds no tag: it no longer matches how the docs name tags"
    assert named <= set(table), (
        f"tags without a commit in {REGISTER.name}: {sorted(named - set(table))}"
    )
    shallow = subprocess.run(
        ["git", "rev-parse", "--is-shallow-repository"], cwd=ROOT, capture_output=True, text=True
    )
    if shallow.returncode != 0 or shallow.stdout.strip() != "false":
        return  # not a full clone: the commits' presence cannot be checked here
    for tag, commit in table.items():
        ok = subprocess.run(
            ["git", "cat-file", "-e", f"{commit}^{{commit}}"], cwd=ROOT, capture_output=True
        )
        assert ok.returncode == 0, f"{tag}: commit {commit} is not in this history"


def commands(text: str) -> list[tuple[str, list[str]]]:
    """(recipe, arguments) of every ``python recipes/NAME.py …`` and ``irdrc NAME …`` in ``text``
    outside its ``at-tag`` regions, comments after ``#`` dropped."""
    out = []
    for m in COMMAND.finditer(current(text)):
        recipe = m.group(1) or m.group(3)
        rest = (m.group(2) if m.group(1) else m.group(4)) or ""
        rest = re.split(r"\s+#\s", rest)[0]
        try:
            args = shlex.split(rest)
        except ValueError:
            args = rest.split()
        out.append((recipe, args))
    return out


def check_command(recipe: str, args: list[str], files: dict[str, Path] | None = None) -> None:
    """What a recipe checks before any work, on ``args``; an argument holding a placeholder
    (``outputs/DATE/TIME/…``) has its key checked, and its value replaced by a real file of that
    kind where ``files`` has one (``checkpoint`` / ``resume``: a DQN checkpoint, ``policy``: a
    policy table), else left out."""
    assert (ROOT / "recipes" / f"{recipe}.py").is_file(), f"recipes/{recipe}.py does not exist"
    files = files or {}
    args = [
        f"{override_key(a)}={files[override_key(a)]}"
        if PLACEHOLDER.search(a) and override_key(a) in files
        else a
        for a in args
        if not a.startswith("-")
    ]
    concrete = [a for a in args if not PLACEHOLDER.search(a) or override_key(a) == "hydra.run.dir"]
    load(recipe, *(a for a in concrete if not override_key(a).startswith("hydra")))


def readme_commands() -> list[tuple[str, list[str]]]:
    return commands(README.read_text())


@pytest.mark.e2e
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


@pytest.mark.e2e
def test_readme_python_api_runs():
    """The README's Python example runs as printed (about 6 s: a 10⁶-state factored solve)."""
    code = README.read_text().split("```python\n", 1)[1].split("```", 1)[0]
    r = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=300, cwd=ROOT
    )
    assert r.returncode == 0, r.stderr[-2000:]


def test_readme_has_the_commands_it_promises():
    found = {r for r, _ in readme_commands()}
    recipes = {p.stem for p in (ROOT / "recipes").glob("*.py")}
    assert recipes <= found | {"demo"}, f"recipes missing from the README: {recipes - found}"
    text = README.read_text()
    for script in re.findall(r"bash (ci/\w+\.sh)", text):
        assert (ROOT / script).is_file(), script


@pytest.mark.parametrize("doc", DOCS, ids=lambda p: p.name)
def test_docs_commands_name_existing_recipes_and_keys(doc):
    """Every command in docs/ composes (its keys and group choices exist); the ones a doc gives
    for a whole benchmark are not run, only composed."""
    for recipe, args in commands(doc.read_text()):
        assert (ROOT / "recipes" / f"{recipe}.py").is_file(), f"{doc.name}: recipes/{recipe}.py"
        module = recipe_module(recipe)
        args = [a for a in args if not a.startswith("-") and "=" in a]
        args = [a for a in args if not PLACEHOLDER.search(a)]
        compose(module.NAME, [a for a in args if not override_key(a).startswith("hydra")])


def every_key() -> set[str]:
    """Every dotted key any recipe's config has or any option of its groups sets, the groups, the
    general model's optional keys, and every ``algo.*`` key a recipe's learner reads
    (``ALGO_KEYS``: a profile's file lists only those that act on its run)."""
    keys = set(OPTIONAL_KEYS) | set(config_groups())
    for path in (ROOT / "recipes").glob("*.py"):
        module = recipe_module(path.stem)
        keys |= {f"algo.{k}" for k in getattr(module, "ALGO_KEYS", ())}
    for path in CONF_DIR.glob("*.yaml"):
        keys |= _flat_keys(compose(path.stem, []).cfg)
    for path in CONF_DIR.glob("*/*.yaml"):
        node = OmegaConf.to_container(OmegaConf.load(path), resolve=False)
        node.pop("defaults", None)
        top = path.read_text().startswith("# @package _global_")
        keys |= _flat_keys(node if top else {path.parent.name: node})
    return keys


KEY_IN_TEXT = re.compile(
    r"`((?:algo|env|reward|eval|logger|network|checkpoint|plot|compare|sweep|frontier_grid|"
    r"search|dqn|ray|learners)\.[a-z0-9_.{},]+)(?:=[^`]*)?`"
)
"""A config key a document names: in backquotes, with its section."""
FILES = (".csv", ".pt", ".log", ".md", ".json", ".png", ".yaml", ".py")
"""… not a file name (``learners.csv``, ``checkpoint.pt``)."""


def test_every_config_key_docs_name_exists():
    """A key named in README.md or docs/ (in backquotes, with its section: ``algo.lr``,
    ``env.p1.speed=…``) is a key of some recipe's config — a doc naming a key that is gone fails."""
    keys = every_key()
    missing = []
    for doc in [README, *DOCS]:
        for match in KEY_IN_TEXT.finditer(current(doc.read_text())):
            for key in expand(match.group(1).rstrip(".")):
                if key.endswith(FILES):
                    continue
                known = key in keys or any(k.startswith(key + ".") for k in keys)
                general = any(key == g or key.startswith(g + ".") for g in OPTIONAL_KEYS)
                if not (known or general or "*" in key or key.startswith("env.factors.")):
                    missing.append(f"{doc.name}: {key}")
    assert not missing, missing


def expand(key: str) -> list[str]:
    """``env.p0.{road,weather}`` → ``env.p0.road``, ``env.p0.weather``."""
    m = re.search(r"\{([^}]*)\}", key)
    if not m:
        return [key]
    return [key[: m.start()] + part + key[m.end() :] for part in m.group(1).split(",")]


def test_readme_model_keys_exist():
    keys = _flat_keys(compose("solve", []).cfg)
    table = README.read_text().split("### Configuration names")[1].split("**One name per idea")[0]
    first = [row.split("|")[1] for row in table.splitlines() if row.startswith("| `")]
    listed = [k for cell in first for t in re.findall(r"`([^`]+)`", cell) for k in expand(t)]
    listed = [k for k in listed if "…" not in k]
    assert len(listed) >= 20
    for key in listed:
        general = any(key == g or key.startswith(g + ".") for g in OPTIONAL_KEYS)
        assert key in keys or general, f"README lists {key}, which the config does not have"


def slug(heading: str) -> str:
    """GitHub's anchor for a heading: lower case, punctuation dropped, spaces to hyphens."""
    text = re.sub(r"[^\w\- ]", "", heading.strip().lower())
    return text.replace(" ", "-")


def anchors(path: Path) -> set[str]:
    return {slug(h) for h in re.findall(r"^#+ (.+)$", path.read_text(), flags=re.M)}


@pytest.mark.parametrize("doc", [README, *DOCS, *LAB], ids=lambda p: f"{p.parent.name}/{p.name}")
def test_links_point_at_files_and_headings_that_exist(doc):
    text = re.sub(r"```.*?```", "", doc.read_text(), flags=re.S)
    for target in re.findall(r"\]\(([^)\s]+)\)", text):
        if target.startswith(("http://", "https://", "mailto:")):
            continue
        path, _, anchor = target.partition("#")
        file = (doc.parent / path).resolve() if path else doc
        assert file.exists(), f"{doc.relative_to(ROOT)} links to {target}: no such file"
        if anchor and file.suffix == ".md":
            assert anchor in anchors(file), (
                f"{doc.relative_to(ROOT)} links to {target}: no such heading"
            )


def test_readme_is_a_door():
    text = README.read_text()
    assert len(text.splitlines()) <= 350
    results = text.split("## Results")[1].split("\n## ")[0]
    assert len(results.strip().splitlines()) <= 20 + 2  # 20 lines of results, and the links line


@pytest.mark.parametrize(
    "override, says",
    [
        ("algo=qlearning", "use python recipes/qlearning.py"),
        ("algo=qlearning_paper", "use python recipes/qlearning.py algo=qlearning_paper"),
        ("algo=dqn_lagrangian", "use python recipes/constrained.py learner=dqn_lagrangian"),
        ("algo=posterior", "use python recipes/online.py learner=posterior"),
        ("algo=safe", "use python recipes/online.py learner=safe"),
        ("executor=ray", "executor= is for python recipes/bench_constrained.py"),
    ],
)
def test_a_choice_of_another_recipe_names_that_recipe(override: str, says: str) -> None:
    """A group option that belongs to another recipe says where (it gave ~10 unknown-key errors,
    or Hydra's raw 'Could not override')."""
    with pytest.raises(ValueError, match=re.escape(says)):
        load("dqn", override)


@pytest.mark.parametrize("recipe", ["bench_online", "study", "bench_scale"])
def test_a_group_a_recipe_without_groups_has_not_is_named(recipe: str) -> None:
    """A recipe whose defaults choose no group answers a group's option as every recipe does (it
    said "unknown key 'executor' …; did you mean executor?", the key it refused)."""
    from irdrc.runs.compose import unknown_key

    with pytest.raises(ValueError, match=f"{recipe} has no executor: executor= is for python "):
        load(recipe, "executor=local")
    assert "did you mean" not in unknown_key(recipe, "executor", {"executor", "seeds"})


def test_citation_license_and_the_files_docs_name_exist() -> None:
    """CITATION.cff names the letter's four authors; LICENSE matches pyproject's MIT; the README
    carries the BibTeX entry."""
    cff = OmegaConf.load(ROOT / "CITATION.cff")
    names = [a["family-names"] for a in cff["preferred-citation"].authors]
    assert names == ["Hieu", "Hoang", "Luong", "Niyato"]
    assert cff.license == "MIT" and (ROOT / "LICENSE").read_text().startswith("MIT License")
    assert 'license = { text = "MIT" }' in (ROOT / "pyproject.toml").read_text()
    assert "@article{hieu2020irdrc" in (ROOT / "README.md").read_text()


DOTTED = re.compile(r"`(irdrc(?:\.\w+)+)")
"""A Python name a document gives (``irdrc.core.exact.value_iteration``), in backquotes."""


def resolve(name: str) -> bool:
    """Whether ``name`` is an importable module or an attribute of one."""
    import importlib

    parts = name.split(".")
    for i in range(len(parts), 0, -1):
        try:
            obj = importlib.import_module(".".join(parts[:i]))
        except ModuleNotFoundError:
            continue
        for attr in parts[i:]:
            if not hasattr(obj, attr):
                return False
            obj = getattr(obj, attr)
        return True
    return False


def test_every_python_name_docs_give_exists():
    """A module, class or function named in README.md or docs/ exists — a doc naming one that
    moved fails (the test itself: ``resolve`` refuses a made-up name)."""
    assert resolve("irdrc.core.exact.value_iteration") and not resolve("irdrc.core.solve")
    missing = [
        f"{doc.name}: {m.group(1)}"
        for doc in [README, *DOCS]
        for m in DOTTED.finditer(current(doc.read_text()))
        if not resolve(m.group(1))
    ]
    assert not missing, missing


PAGE_LIMITS = {"DQN.md": 250, "BENCHMARKS.md": 250}
"""Lines a user page may hold (the rest: ``PAGE_LIMIT``); how defaults were chosen is in docs/lab."""
PAGE_LIMIT = 420


@pytest.mark.parametrize("doc", DOCS, ids=lambda p: p.name)
def test_user_pages_stay_short(doc):
    assert len(doc.read_text().splitlines()) <= PAGE_LIMITS.get(doc.name, PAGE_LIMIT)
