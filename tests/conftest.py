"""Shared helpers: hand-set transitions on the stateless env."""

from __future__ import annotations

import math
import signal

import pytest
import torch
from tensordict import TensorDict

from irdrc import DFRCEnv, Params
from irdrc.core.exact import (
    as_probs,
    build_factored,
    build_model,
    metrics_from_occupancy,
    stationary_distribution_factored,
    stationary_metrics,
    value_iteration,
)

torch.set_num_threads(1)

TIERS = {
    "not slow and not e2e": "the default suite (2–9 min on 2 cores)",
    "slow": "the learning tests (-m slow)",
    "e2e": "the end-to-end tier (-m e2e: whole recipes, sweeps, kills and resumes)",
}


def pytest_report_header(config):
    """Which tier runs, in words, on the first lines of every test run."""
    expr = config.getoption("markexpr") or ""
    return f"irdrc: {TIERS.get(expr, f'tests selected by -m {expr!r}' if expr else 'every test')}"


class _Clock:
    """A line every 30 s while the tests run: how many are done and how long it has been."""

    def __init__(self, config) -> None:
        import time

        self.config, self.time = config, time
        self.t0 = self.last = time.monotonic()
        self.done = 0

    def pytest_runtest_logreport(self, report) -> None:
        if report.when != "teardown":
            return
        self.done += 1
        now = self.time.monotonic()
        if now - self.last >= 30:
            self.last = now
            tr = self.config.pluginmanager.get_plugin("terminalreporter")
            if tr is not None:
                m, sec = divmod(int(now - self.t0), 60)
                tr.write_line(f"  … {self.done} tests done, {m}:{sec:02d} so far")


def pytest_configure(config):
    if not hasattr(config, "workerinput"):  # the controller (or a run without workers)
        config.pluginmanager.register(_Clock(config), "irdrc-clock")


def recipe_module(name: str):
    """The recipe module behind ``recipes/<name>.py``: the one its ``app.main(…)`` runs, by the
    script's own import (``from irdrc.<package> import app, <module>``)."""
    import importlib
    import re
    from pathlib import Path

    script = Path(__file__).resolve().parents[1] / "recipes" / f"{name}.py"
    if not script.is_file():
        raise ValueError(f"no recipe {name}")
    text = script.read_text()
    main = re.search(r"app\.main\((\w+)\)", text)
    if main is None:
        raise ValueError(f"recipes/{name}.py calls no app.main(…)")
    module = main.group(1)
    found = re.search(rf"from (irdrc[\w.]*) import [^\n]*\b{module}\b", text)
    if found is None:
        raise ValueError(f"recipes/{name}.py does not import {module} from irdrc")
    return importlib.import_module(f"{found.group(1)}.{module}")


def default_sigint() -> None:
    """``preexec_fn`` of a child a test sends SIGINT: SIGINT at its default there, even when the
    tests run in a background job, whose commands start with SIGINT ignored (and pass that on)."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def load(recipe: str, *overrides: str):
    """The typed config ``recipes/<recipe>.py`` runs with these overrides (composed once and checked,
    as the recipe does before any work)."""
    from irdrc.runs.app import prepare

    return prepare(recipe_module(recipe), list(overrides)).config


def run_script(*args: str, timeout: int = 300):
    """``python ARGS`` (a script and its arguments) in a fresh interpreter from the repository's
    root, its output captured as text (a ``subprocess.CompletedProcess``)."""
    import subprocess
    import sys
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    return subprocess.run(
        [sys.executable, *args], capture_output=True, text=True, cwd=root, timeout=timeout
    )


def python_as_typed(cwd) -> str:
    """The python running the tests as a go-on command names it for a recipe run from ``cwd``:
    relative to ``cwd`` when below it (the venv's), else its full path."""
    import os
    import sys

    rel = os.path.relpath(sys.executable, cwd)
    return sys.executable if rel.startswith("..") else rel


def run_recipe(recipe: str, run_dir, *overrides: str) -> int:
    """Run ``recipes/<recipe>.py`` in this process with ``overrides``, writing to ``run_dir``;
    returns its exit status."""
    from irdrc.runs.app import execute

    return execute(recipe_module(recipe), [*overrides, f"hydra.run.dir={run_dir}"])


def scenario(*overrides: str) -> Params:
    """The single-vehicle model the command line ``overrides`` names (``env=large`` …)."""
    return load("solve", *overrides).model


EDGES = {
    "env.queue_capacity": 3,
    "env.arrival_rate": 0.3,
    "env.packets_good": 30,
    "env.packets_bad": 0,
    "env.stay_good.channel": 0.0,
    "env.stay_good.road": 1.0,
    "env.stay_bad.weather": 1.0,
    "env.p1.object": 1.0,
}
"""A scenario at the ends of the allowed ranges: a link past the queue and the arrivals' reach
(30 packets, 3 held, λ = 0.3), a bad channel that carries nothing, chains that always or never
stay, a certain event. The simulator, the stream and the exact model are held to each other on it."""

TINY_ALGO = dict(
    num_envs=8,
    frames_per_batch=32,
    total_frames=640,
    init_random_frames=128,
    buffer_size=640,
    batch_size=32,
)
"""``DQNConfig`` keys of a run of 640 env steps in 20 batches: enough to exercise a part, not to
learn."""

TINY_DQN = [
    *(f"algo.{key}={value}" for key, value in TINY_ALGO.items()),
    "eval.every_frames=320",
    "progress=false",
    "logger=none",
]
"""Overrides of a DQN run of a few seconds (640 env steps), for tests that need a run's files."""


def one_step(params: Params, states, actions, seed: int = 0) -> TensorDict:
    """Step a fresh env once from hand-set ``states`` with ``actions``; returns the "next" td."""
    states = torch.as_tensor(states, dtype=torch.int64)
    actions = torch.as_tensor(actions, dtype=torch.int64).expand_as(states)
    n = states.numel()
    env = DFRCEnv(params, batch_size=[n], seed=seed)
    td = TensorDict(
        {"state": states, "action": actions, "step_count": torch.zeros(n, 1, dtype=torch.int64)},
        batch_size=[n],
    )
    return env.step(td)["next"]


@pytest.fixture
def step_from():
    return one_step


@pytest.fixture(scope="module")
def paper_scorer():
    """The paper scenario's exact scorer (its optimum solved once per test module)."""
    from irdrc.core.exact import exact_scorer

    return exact_scorer(Params())


def assert_chi2(counts: torch.Tensor, expected: torch.Tensor) -> None:
    """Pearson χ² of observed transition ``counts`` [rows, S] against ``expected`` counts.

    Cells with expected count ≥ 5 are compared one by one, each row's remaining cells lumped into one
    (kept when its expectation is ≥ 5 too). Under the model the statistic has mean dof and sd
    √(2·dof); 5 sd above the mean is the bound. Cells the model calls impossible must stay empty.
    """
    big = expected >= 5
    stat = float((((counts - expected) ** 2 / expected.clamp(min=1e-300)) * big).sum())
    dof = int(big.sum()) - counts.shape[0]
    rest_e = (expected * ~big).sum(1)
    rest_o = (counts * ~big).sum(1)
    keep = rest_e >= 5
    stat += float(((rest_o - rest_e) ** 2 / rest_e.clamp(min=1e-300))[keep].sum())
    dof += int(keep.sum())
    assert stat < dof + 5 * math.sqrt(2 * dof), (stat, dof)
    assert float(counts[expected == 0].sum()) == 0.0


def assert_factored_equals_dense(params, seed: int) -> None:
    """Every operator and table to 1e-9 (observed: ≤ 1e-11), value iteration's policy and values,
    exact stationary metrics of the optimum and of a randomised policy by every method, and of two
    periodic policies."""
    dense, fac = build_model(params), build_factored(params)
    S = dense.num_states
    gen = torch.Generator().manual_seed(seed)
    V = torch.randn(S, generator=gen, dtype=torch.float64)
    x = torch.rand(S, generator=gen, dtype=torch.float64)
    assert torch.allclose(fac.expect(V), dense.P @ V, rtol=0, atol=1e-9)
    for a in (0, 1):
        assert torch.allclose(fac.push(x, a), x @ dense.P[a], rtol=0, atol=1e-9)
    for key, table in fac.tables().items():
        assert torch.allclose(table, getattr(dense, key), rtol=0, atol=1e-9), key
    opt, fopt = value_iteration(dense), value_iteration(fac, tol=1e-9)
    assert torch.equal(opt.policy, fopt.policy)
    assert torch.allclose(fopt.values, opt.values, rtol=0, atol=1e-8)
    mixed = torch.rand(S, 2, generator=gen, dtype=torch.float64)
    mixed = mixed / mixed.sum(-1, keepdim=True)
    for policy in (opt.policy, mixed):
        want = stationary_metrics(dense, policy).as_dict()
        for method in ("auto", "gmres", "iad", "power"):
            mu, _ = stationary_distribution_factored(fac, policy, method=method)
            assert mu.shape == (S,) and abs(float(mu.sum()) - 1) < 1e-12
            got = metrics_at(fac, policy, mu).as_dict()
            assert set(got) == set(want)  # false_alarm_rate in both, or in neither
            for k in want:
                assert got[k] == pytest.approx(want[k], rel=1e-9, abs=1e-9), (method, k)
    # periodic policies: round robin, and three randomised phases applied in turn
    phases = torch.rand(3, S, 2, generator=gen, dtype=torch.float64)
    for schedule in ("round_robin", list(phases / phases.sum(-1, keepdim=True))):
        want = stationary_metrics(dense, schedule).as_dict()
        got = stationary_metrics(fac, schedule).as_dict()
        for k in want:
            assert got[k] == pytest.approx(want[k], rel=1e-9, abs=1e-9), ("periodic", k)


def metrics_at(model, policy, mu: torch.Tensor):
    """The exact metrics of ``policy`` given its stationary distribution ``mu``."""
    probs = as_probs(policy, model.num_states, model.num_actions)
    return metrics_from_occupancy(model, (mu[:, None] * probs).T.contiguous())
