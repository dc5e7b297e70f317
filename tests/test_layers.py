"""The package's layers: no import cycle (function-local imports included), no upward import."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

PKG = Path(__file__).resolve().parents[1] / "irdrc"
LAYERS = {
    "core": 0,
    "fleet": 1,
    "agents": 2,
    "runs": 3,
    "sweeps": 4,
    "recipes": 5,
    "online": 5,
    "bench": 6,
    "paper": 7,
}
"""Each layer may import only the layers before it (and itself)."""


def module_name(path: Path) -> str:
    rel = path.relative_to(PKG.parent).with_suffix("")
    parts = list(rel.parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def all_modules() -> dict[str, Path]:
    return {module_name(p): p for p in PKG.rglob("*.py")}


def _type_checking_only(tree: ast.AST) -> set[int]:
    """ids of the nodes under ``if TYPE_CHECKING:`` (type hints only: never run)."""
    out: set[int] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.If) and getattr(node.test, "id", None) == "TYPE_CHECKING":
            out |= {id(n) for stmt in node.body for n in ast.walk(stmt)}
    return out


def imports_of(path: Path, modules: dict[str, Path]) -> set[str]:
    """Every irdrc module ``path`` imports, anywhere in the file (top level or inside functions),
    but for type hints under ``if TYPE_CHECKING:``."""
    out = set()
    tree = ast.parse(path.read_text())
    hints = _type_checking_only(tree)
    for node in ast.walk(tree):
        if id(node) in hints:
            continue
        if isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            # ``from irdrc.agents import dqn`` imports the module irdrc.agents.dqn
            names = [node.module] + [f"{node.module}.{a.name}" for a in node.names]
        else:
            continue
        out |= {n for n in names if n in modules}
    return out


def layer(module: str) -> int | None:
    parts = module.split(".")
    return LAYERS.get(parts[1]) if len(parts) > 1 else None


def graph() -> dict[str, set[str]]:
    modules = all_modules()
    return {m: imports_of(p, modules) - {m} for m, p in modules.items()}


def upward_imports(g: dict[str, set[str]]) -> list[str]:
    """Every import of a higher layer (or of the package's top) by a module of a layer."""
    bad = []
    for mod, deps in g.items():
        mine = layer(mod)
        if mine is None:  # irdrc/__init__.py and __main__.py sit above every layer
            continue
        for dep in deps:
            theirs = layer(dep)
            if theirs is None or theirs > mine:
                bad.append(f"{mod} imports {dep}")
    return bad


def test_no_upward_import():
    bad = upward_imports(graph())
    assert not bad, bad


def find_cycle(g: dict[str, set[str]]) -> list[str] | None:
    """A cycle of module imports (a package's own ``__init__`` counts as a module), or None."""
    state: dict[str, int] = {}
    stack: list[str] = []

    def visit(m: str) -> list[str] | None:
        state[m] = 1
        stack.append(m)
        for d in sorted(g.get(m, ())):
            if state.get(d) == 1:
                return [*stack[stack.index(d) :], d]
            if d not in state and (c := visit(d)):
                return c
        stack.pop()
        state[m] = 2
        return None

    for m in sorted(g):
        if m not in state and (c := visit(m)):
            return c
    return None


def test_no_import_cycle():
    assert find_cycle(graph()) is None, find_cycle(graph())


def test_the_checks_can_fail():
    """The cycle finder and the layer rule catch what they are for (on a made-up graph)."""
    g = {"irdrc.core.a": {"irdrc.agents.b"}, "irdrc.agents.b": {"irdrc.core.a"}}
    cycle = find_cycle(g)
    assert cycle is not None and cycle[0] == cycle[-1] and set(cycle) == set(g)
    assert find_cycle({"irdrc.core.a": set(), "irdrc.agents.b": {"irdrc.core.a"}}) is None
    assert layer("irdrc.agents.b") > layer("irdrc.core.a")
    # the fleet is a layer of its own, below the learners: an arrow from it to agents is refused
    up = {"irdrc.fleet.x": {"irdrc.agents.y", "irdrc.core.a"}, "irdrc.agents.y": {"irdrc.fleet.x"}}
    assert upward_imports(up) == ["irdrc.fleet.x imports irdrc.agents.y"]
    assert upward_imports({"irdrc.core.a": {"irdrc.fleet.x"}}) == [
        "irdrc.core.a imports irdrc.fleet.x"
    ]
    tree = ast.parse(
        "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    import irdrc.agents\n"
    )
    assert len(_type_checking_only(tree)) > 0


@pytest.mark.parametrize("package", sorted(LAYERS))
def test_every_layer_says_what_it_holds_and_may_import(package):
    doc = ast.get_docstring(ast.parse((PKG / package / "__init__.py").read_text())) or ""
    assert "May import" in doc, package


def recipe_modules():
    from conftest import recipe_module

    names = [p.stem for p in (PKG.parent / "recipes").glob("*.py")]
    return names, {name: recipe_module(name) for name in sorted(names)}


def test_every_recipe_is_one_module_with_a_typed_config():
    """Each ``recipes/<name>.py`` runs one module's ``run`` on its own frozen ``Config``, built by
    its own ``load`` from the config file ``irdrc/conf/<NAME>.yaml``; no central module knows
    every recipe's keys."""
    import dataclasses
    import inspect

    names, modules = recipe_modules()
    assert set(modules) == set(names), set(names) - set(modules)
    for name, m in modules.items():
        assert name == m.NAME and (PKG / "conf" / f"{name}.yaml").is_file()
        assert dataclasses.is_dataclass(m.Config) and m.Config.__dataclass_params__.frozen, name
        assert list(inspect.signature(m.load).parameters) == ["composed", "resume"], name
        assert list(inspect.signature(m.run).parameters) == ["cfg", "run"], name
        script = (PKG.parent / "recipes" / f"{name}.py").read_text()
        assert f"app.main({m.__name__.rsplit('.', 1)[1]})" in script, name


def test_every_off_policy_learner_runs_on_the_one_loop():
    """DQN, the Lagrangian DQN and the fleet's mixers hand their parts to ``TrainingLoop``; none
    of them has its own evaluate / stop / checkpoint code."""
    for name in ("dqn", "lagrangian", "marl"):
        text = (PKG / "agents" / f"{name}.py").read_text()
        assert "TrainingLoop(" in text or "dqn.train(" in text, name
        for own in ("stop_requested", "checkpoint_due", "scorer.metrics(", "progress_record("):
            assert own not in text, (name, own)


def test_a_run_composes_its_config_once_and_builds_it_once(tmp_path, monkeypatch):
    """One DQN run, start to finish, in this process: Hydra composes the config once, the typed
    config is built once, and a resumed run reads its checkpoint once."""
    import hydra
    from conftest import TINY_DQN, run_recipe

    from irdrc.agents import base
    from irdrc.recipes import dqn

    counts = {"compose": 0, "load": 0, "checkpoint": 0}

    def counting(name, real):
        def wrapper(*args, **kwargs):
            counts[name] += 1
            return real(*args, **kwargs)

        return wrapper

    monkeypatch.setattr(hydra, "compose", counting("compose", hydra.compose))
    monkeypatch.setattr(dqn, "load", counting("load", dqn.load))
    monkeypatch.setattr(base, "load_checkpoint", counting("checkpoint", base.load_checkpoint))
    assert run_recipe("dqn", tmp_path / "a", *TINY_DQN, "eval.mc_episodes=0") == 0
    assert counts == {"compose": 1, "load": 1, "checkpoint": 0}
    ckpt = tmp_path / "a" / "checkpoint.pt"
    more = ["algo.total_frames=960", "eval.mc_episodes=0"]
    assert run_recipe("dqn", tmp_path / "b", *TINY_DQN, f"resume={ckpt}", *more) == 0
    assert counts == {"compose": 2, "load": 2, "checkpoint": 1}
