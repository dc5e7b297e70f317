"""Third-party trainers on our envs, scored exactly: a policy's table from the gym env and the
fleet's PettingZoo view (``score``, ``policy_table``); in the e2e tier, Stable-Baselines3's DQN and
SAC through ``examples/sb3_train.py`` with ``recipes/evaluate.py`` reading their tables, and MAPPO
through TorchRL's ``PettingZooWrapper`` (``examples/fleet_mappo_pettingzoo.py``)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import gymnasium
import numpy as np
import pytest
import torch

import irdrc  # noqa: F401 - registers irdrc/DFRC-v0
from irdrc.core.exact import exact_scorer
from irdrc.core.exact.continuum import ContinuumScorer
from irdrc.core.params import Params

ROOT = Path(__file__).resolve().parents[1]


def test_gym_score_is_the_exact_scorers():
    """``score`` of a predict function equals the exact scorer on the table it acts by: the
    optimum's own actions score 1, always-radar its exact ratio; radar shares are scored against the
    optimum over ρ (the optimum's ρ scores 1); a wrong number of actions or an action outside the
    space is refused."""
    env = gymnasium.make("irdrc/DFRC-v0").unwrapped
    scorer = exact_scorer(env.params)
    best = scorer.optimal.policy
    assert env.score(lambda obs: best.numpy())["ratio"] == pytest.approx(1.0, abs=1e-12)
    radar = env.score(lambda obs: np.ones(len(obs), dtype=np.int64))
    assert radar["ratio"] == pytest.approx(scorer.ratio(torch.ones_like(best)), abs=1e-12)
    assert radar["radar_fraction"] == pytest.approx(1.0)
    assert torch.equal(
        env.policy_table(lambda obs: (obs[:, 0] > 0).astype(int)),
        env.dynamics.obs[:, 0].gt(0).long(),
    )
    with pytest.raises(ValueError, match="actions for the"):
        env.score(lambda obs: np.ones(3))
    with pytest.raises(ValueError, match="action"):
        env.score(lambda obs: np.full(len(obs), 2))
    # 0.5 (a probability) was scored as 0, "x" was torch's TypeError: each is refused by name
    for bad in (0.5, "x"):
        with pytest.raises(ValueError, match=r"^predict's actions \[.*\] must be 0"):
            env.score(lambda obs, bad=bad: np.full(len(obs), bad))
    assert env.score(lambda obs: np.ones(len(obs)))["ratio"] == radar["ratio"]  # 1.0 is radar
    cont = gymnasium.make("irdrc/DFRC-v0", **{"env.actions": "continuous"}).unwrapped
    rho = ContinuumScorer(Params.from_overrides({"env.actions": "continuous"})).optimal.rho
    assert cont.score(lambda obs: rho.numpy()[:, None])["ratio"] == pytest.approx(1.0, abs=1e-9)
    with pytest.raises(ValueError, match=r"\[0, 1\]|share"):
        cont.score(lambda obs: np.full((len(obs), 1), 1.5))


def test_fleet_score_is_the_fleet_scorers():
    """The fleet's ``score`` equals ``FleetScorer`` on the table the policy acts by: every vehicle
    on its single-vehicle optimum (``own``), and the centralised optimum's joint actions shown
    through ``full`` observations (ratio 1)."""
    from irdrc.fleet import parallel_env
    from irdrc.fleet.policies import single_optima
    from irdrc.fleet.scorer import FleetScorer

    env = parallel_env(seed=0)
    scorer = FleetScorer(env.model)
    single = single_optima(env.model)[0]
    obs_table = env.sim.dyn.obs

    def copies(obs):  # each vehicle looks its observation up in the single optimum
        rows = [
            int((obs_table == torch.as_tensor(o)).all(1).nonzero()[0]) for o in obs["vehicle_1"]
        ]
        return {a: single[rows].numpy() for a in env.possible_agents}

    assert env.score(copies)["ratio"] == pytest.approx(scorer.ratio(single), abs=1e-12)
    full = parallel_env(**{"env.observe": "full"}, seed=0)
    joint = scorer.optimal.policy
    got = full.score(
        lambda obs: {a: (joint.numpy() >> i) & 1 for i, a in enumerate(full.possible_agents)}
    )
    assert got["ratio"] == pytest.approx(1.0, abs=1e-12)
    with pytest.raises(ValueError, match="actions per agent"):
        env.score(lambda obs: {a: np.zeros(3) for a in env.possible_agents})
    # a policy's 0.5 (a probability, a share) was scored as 0: it is refused, naming the agent
    half = {a: np.full(env.model.single.num_states, 0.5) for a in env.possible_agents}
    with pytest.raises(ValueError, match=r"^vehicle_1's actions \[0\.5, 0\.5, 0\.5\] must be"):
        env.score(lambda obs: half)


def _run(args: list[str], cwd: Path, tmp: Path | None = None) -> str:
    env = None if tmp is None else {**os.environ, "TMPDIR": str(tmp)}
    done = subprocess.run(
        [sys.executable, *args], cwd=cwd, capture_output=True, text=True, timeout=900, env=env
    )
    assert done.returncode == 0, done.stdout[-2000:] + done.stderr[-2000:]
    return done.stdout


@pytest.mark.e2e
@pytest.mark.parametrize(
    ("algo", "steps", "train", "scenario"),
    [
        ("dqn", 3000, [], []),
        ("sac", 1200, [], ["env.actions=continuous"]),
        ("dqn", 1000, ["env.actions=levels"], ["env.actions=levels"]),
        ("dqn", 1000, ["env=multilevel", "reward.r4=50"], ["env=multilevel", "reward.r4=50"]),
    ],
)
def test_sb3_trains_and_evaluate_scores_its_table(algo, steps, train, scenario, tmp_path):
    """SB3's DQN (binary, radar-share levels) and SAC (radar share) train on ``irdrc/DFRC-v0``
    for a short budget (the plumbing, not SB3's tuning: no learning threshold), on a named
    scenario too (``env=multilevel``: ``irdrc.scenario``); ``recipes/evaluate.py policy=…`` reads
    the written table and finds the same exact ratio as ``score`` (a levels table was written as
    comm/radar actions, its shares truncated to 0). SB3's own log is its ``progress.csv`` in the
    output folder, not a folder of its own under the temporary directory."""
    out, tmp = tmp_path / algo, tmp_path / "tmp"
    tmp.mkdir()
    printed = _run(
        ["examples/sb3_train.py", "--algo", algo, "--steps", str(steps), "--out", str(out), *train],
        ROOT,
        tmp,
    )
    assert f"SB3 {algo}:" in printed
    assert (out / "progress.csv").is_file()
    assert not [p.name for p in tmp.iterdir() if p.name.startswith("SB3-")]
    score = json.loads((out / "score.json").read_text())
    _run(
        [
            "recipes/evaluate.py",
            f"policy={out / 'policy.csv'}",
            *scenario,
            "eval.mc_episodes=0",
            f"hydra.run.dir={tmp_path / 'eval'}",
        ],
        ROOT,
    )
    summary = json.loads((tmp_path / "eval" / "summary.json").read_text())
    assert summary["optimality_ratio"] == pytest.approx(score["ratio"], abs=1e-9)


@pytest.mark.e2e
def test_mappo_through_torchrl_pettingzoo_wrapper_is_scored_exactly(tmp_path):
    """TorchRL's ``PettingZooWrapper`` over ``parallel_env`` trains MAPPO (a short run); the greedy
    table it writes, rescored here by ``FleetScorer``, gives the ratio it printed."""
    from irdrc.fleet import parallel_env
    from irdrc.fleet.scorer import FleetScorer

    out = tmp_path / "mappo.json"
    printed = _run(
        [
            "examples/fleet_mappo_pettingzoo.py",
            "--frames",
            "3000",
            "--out",
            str(out),
            "env.share=0.5",
        ],
        ROOT,
    )
    assert "rollout 3:" in printed and "exact ratio" in printed
    result = json.loads(out.read_text())
    model = parallel_env(**{"env.share": 0.5}).model
    ratio = FleetScorer(model).ratio(torch.tensor(result["table"]))
    assert ratio == pytest.approx(result["ratio"], abs=1e-9)
    assert len(result["table"]) == 2 * model.single.num_states


@pytest.mark.e2e
def test_readme_sb3_lines_run(tmp_path):
    """The README's Stable-Baselines3 lines run as printed (with a budget of 500 steps) and print
    the exact score (SB3's log folder goes to this test's temporary directory)."""
    readme = (ROOT / "README.md").read_text()
    block = readme.split("### Other libraries", 1)[1].split("```python\n", 1)[1].split("```")[0]
    assert "stable_baselines3" in block and ".learn(50_000)" in block
    printed = _run(["-c", block.replace(".learn(50_000)", ".learn(500)")], ROOT, tmp_path)
    assert "'ratio':" in printed


@pytest.mark.e2e
@pytest.mark.parametrize(
    ("args", "message"),
    [
        # TorchRL's collector reads a negative budget as "run for ever": it never stopped
        (["examples/fleet_mappo_pettingzoo.py", "--frames", "-3"], "-3 is not an integer >= 1"),
        (["examples/fleet_mappo_pettingzoo.py", "--frames", "500"], "less than one rollout"),
        (["examples/sb3_train.py", "--steps", "-5"], "-5 is not an integer >= 0"),
    ],
)
def test_the_examples_refuse_a_budget_that_is_not_one(args, message):
    done = subprocess.run(
        [sys.executable, *args], cwd=ROOT, capture_output=True, text=True, timeout=120
    )
    assert done.returncode == 2 and message in done.stderr, done.stderr[-2000:]


def built_wheel(tmp_path: Path, site: Path) -> None:
    """Build a wheel of irdrc from its sources alone (``pip wheel``, what ``pip install`` builds;
    no build/ left by an earlier build can bring files back) and unpack it into ``site``."""
    import shutil
    import zipfile

    src, wheel_dir = tmp_path / "src", tmp_path / "wheel"
    shutil.copytree(ROOT / "irdrc", src / "irdrc", ignore=shutil.ignore_patterns("__pycache__"))
    for name in ("pyproject.toml", "README.md", "LICENSE"):
        shutil.copy(ROOT / name, src / name)
    build = subprocess.run(
        [sys.executable, "-m", "pip", "wheel", str(src), "--no-deps", "-q", "-w", str(wheel_dir)],
        capture_output=True,
        text=True,
        timeout=300,
        cwd=tmp_path,
    )
    assert build.returncode == 0, build.stderr
    (wheel,) = wheel_dir.glob("irdrc-*.whl")
    with zipfile.ZipFile(wheel) as z:
        z.extractall(site)


@pytest.mark.e2e
def test_the_built_wheel_runs_away_from_the_checkout(tmp_path):
    """A wheel of irdrc (``pip wheel .``, what ``pip install`` builds) carries the named scenarios
    and the recipes' configs: unpacked alone and run from another directory, ``irdrc.scenario``,
    the gym id's ``params=`` and ``python -m irdrc solve`` work, and a recipe's resume hint names
    ``-m irdrc``."""
    site, work = tmp_path / "site", tmp_path / "work"
    built_wheel(tmp_path, site)
    work.mkdir()
    env = {**os.environ, "PYTHONPATH": str(site)}  # ahead of the checkout's editable install
    code = (
        "import gymnasium, irdrc\n"
        f"assert irdrc.__file__.startswith({str(site)!r}), irdrc.__file__\n"
        "p = irdrc.scenario('multilevel')\n"
        "env = gymnasium.make('irdrc/DFRC-v0', params=p)\n"
        "print(p.env.num_states, env.unwrapped.params.env.num_states)\n"
    )

    def python(*args: str) -> subprocess.CompletedProcess:
        return subprocess.run(
            [sys.executable, *args], capture_output=True, text=True, cwd=work, env=env, timeout=300
        )

    lib = python("-c", code)
    assert lib.returncode == 0, lib.stderr
    assert lib.stdout.split() == ["792", "792"]
    listing = python("-m", "irdrc")
    assert listing.returncode == 0 and "bench_online" in listing.stdout, listing.stderr
    solve = python("-m", "irdrc", "solve", "env=multilevel", "eval.mc_episodes=0")
    assert solve.returncode == 0, solve.stderr
    (summary,) = work.glob("outputs/*/*/summary.json")
    assert json.loads(summary.read_text())["optimal"]["avg_reward"] > 0
    ql = python(
        "-m", "irdrc", "qlearning", "algo.episodes=2", "eval.mc_episodes=0", "hydra.run.dir=q"
    )
    assert ql.returncode == 0, ql.stderr
    wrong = python("-m", "irdrc", "dqn", "resume=q/checkpoint.pt")
    assert wrong.returncode == 2
    assert wrong.stderr.strip().endswith("-m irdrc qlearning resume=q/checkpoint.pt"), wrong.stderr


TYPED_USE = """\
import irdrc
from irdrc.core.exact import build_model, stationary_metrics, value_iteration

params = irdrc.scenario("multilevel")
states: int = params.env.num_states
model = build_model(params)
ratio: float = stationary_metrics(model, value_iteration(model).policy).avg_reward
"""


@pytest.mark.e2e
def test_a_type_checker_reads_the_installed_wheel(tmp_path):
    """Installed from its wheel, irdrc's annotations reach a user's type checker (``py.typed``):
    mypy accepts a correct use, flags a wrong one by irdrc's own signature, and without the
    marker finds no types at all."""
    pytest.importorskip("mypy")
    import venv

    env_dir = tmp_path / "v"
    venv.create(env_dir, with_pip=False)
    (site,) = env_dir.glob("lib/python*/site-packages")
    built_wheel(tmp_path, site)
    (tmp_path / "ok.py").write_text(TYPED_USE)
    bad_use = TYPED_USE.replace("ratio: float", "ratio: str").replace("states: int", "states: str")
    (tmp_path / "bad.py").write_text(bad_use)
    (tmp_path / "mypy.ini").write_text("[mypy]\n")  # a user's own settings, not irdrc's

    def mypy(*files: str) -> subprocess.CompletedProcess:
        # torch, gymnasium, … are not in that environment: their names are Any there
        args = ["--python-executable", str(env_dir / "bin" / "python"), "--no-incremental"]
        return subprocess.run(
            [sys.executable, "-m", "mypy", *args, "--config-file", "mypy.ini", *files],
            capture_output=True,
            text=True,
            cwd=tmp_path,
            timeout=300,
        )

    ok = mypy("ok.py")
    assert ok.returncode == 0, ok.stdout
    bad = mypy("bad.py")
    assert 'expression has type "float", variable has type "str"' in bad.stdout, bad.stdout
    assert 'expression has type "int", variable has type "str"' in bad.stdout, bad.stdout
    (site / "irdrc" / "py.typed").unlink()
    untyped = mypy("ok.py")
    assert "module is installed, but missing library stubs or py.typed marker" in untyped.stdout
