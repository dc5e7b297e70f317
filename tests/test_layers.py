"""The package's layers: no import cycle (function-local imports included), no upward import."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

PKG = Path(__file__).resolve().parents[1] / "irdrc"
LAYERS = {"core": 0, "fleet": 1, "agents": 1, "experiments": 2, "paper": 3}
"""Each layer may import only the layers before it (and itself)."""


def module_name(path: Path) -> str:
    rel = path.relative_to(PKG.parent).with_suffix("")
    parts = list(rel.parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def all_modules() -> dict[str, Path]:
    return {module_name(p): p for p in PKG.rglob("*.py")}


def imports_of(path: Path, modules: dict[str, Path]) -> set[str]:
    """Every irdrc module ``path`` imports, anywhere in the file (top level or inside functions)."""
    out = set()
    for node in ast.walk(ast.parse(path.read_text())):
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


def test_no_upward_import():
    bad = []
    for mod, deps in graph().items():
        mine = layer(mod)
        if mine is None:  # irdrc/__init__.py and __main__.py sit above every layer
            continue
        for dep in deps:
            theirs = layer(dep)
            if theirs is None or theirs > mine:
                bad.append(f"{mod} imports {dep}")
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


@pytest.mark.parametrize("package", sorted(LAYERS))
def test_every_layer_says_what_it_holds_and_may_import(package):
    doc = ast.get_docstring(ast.parse((PKG / package / "__init__.py").read_text())) or ""
    assert "May import" in doc, package


def test_every_learner_is_registered_with_one_train_signature():
    """DQN, Q-learning and the Lagrangian DQN: one interface (``irdrc.agents.base``)."""
    import inspect

    from irdrc.agents.registry import LEARNERS

    assert set(LEARNERS) == {"dqn", "qlearning", "dqn_lagrangian"}
    signatures = {name: inspect.signature(m.train) for name, m in LEARNERS.items()}
    params = {name: list(s.parameters) for name, s in signatures.items()}
    assert len({tuple(p) for p in params.values()}) == 1, params
    assert params["dqn"] == [
        "params",
        "cfg",
        "num_learners",
        "seed",
        "device",
        "scorers",
        "eval_every_frames",
        "hooks",
        "resume",
    ]
    for m in LEARNERS.values():
        assert hasattr(m.Config, "from_node") and m.NAME
