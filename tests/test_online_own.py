"""A learner of one's own on ``recipes/online.py`` (``learner=PATH.py:Class`` or
``package.module:Class``, ``irdrc.online.own``): ONLINE.md's example as a file runs on the recipe
with the figures the page prints, its keys are its constructor's, a resumed run from another
directory is the uninterrupted one, a sweep's points find it, and every mistake is one line."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import pytest
from omegaconf import OmegaConf

from irdrc.core.params import Params
from irdrc.online import configs, recipe
from irdrc.online.learners import make_learner
from irdrc.runs import app

PAGE = Path(__file__).parents[1] / "docs" / "ONLINE.md"
QUIET = ["logger=none", "progress=false"]

RESUMABLE = """
    def state_dict(self):
        return {"rng": self.rng.getstate()}

    def load_state_dict(self, state):
        self.rng.setstate(state["rng"])
"""


def page_learner(directory: Path, resumable: bool = False) -> Path:
    """ONLINE.md's *Your own learner on one stream* code, saved as ``watchful.py`` (with
    ``state_dict`` added when ``resumable``)."""
    section = PAGE.read_text().split("## Your own learner on one stream\n", 1)[1]
    code = section.split("```python\n", 1)[1].split("```", 1)[0]
    if resumable:
        head, main = code.split('\n\nif __name__ == "__main__":', 1)
        code = f'{head}\n{RESUMABLE}\n\nif __name__ == "__main__":{main}'
    path = directory / "watchful.py"
    path.write_text(code)
    return path


def ledger(run_dir: Path) -> dict:
    return json.loads((run_dir / "summary.json").read_text())["ledger"]


def test_the_pages_learner_runs_on_the_recipe_with_the_pages_figures(tmp_path, monkeypatch):
    """The page's class as a file: the recipe's run over 20 episodes has the ledger the page's own
    loop prints (regret 709.8, missed 111.2), the file's ``__main__`` part does not run on import,
    and config.yaml names the file by its absolute path with the constructor's defaults."""
    page_learner(tmp_path)
    monkeypatch.chdir(tmp_path)
    args = ["learner=watchful.py:Watchful", "algo.episodes=20", "hydra.run.dir=run", *QUIET]
    assert app.execute(recipe, args) == 0
    row = ledger(tmp_path / "run")
    assert (round(row["regret"], 1), round(row["expected_missed"], 1)) == (709.8, 111.2)
    summary = json.loads((tmp_path / "run" / "summary.json").read_text())
    assert summary["learner"] == f"{tmp_path / 'watchful.py'}:Watchful"
    cfg = OmegaConf.to_container(OmegaConf.load(tmp_path / "run" / "config.yaml"))
    assert cfg["learner"] == summary["learner"] and cfg["algo"] == {"episodes": 20, "eps": 0.1}
    # its keyword is its algo key; the run records the value given
    assert app.execute(recipe, [*args[:2], "algo.eps=0.3", "hydra.run.dir=b", *QUIET]) == 0
    assert OmegaConf.load(tmp_path / "b" / "config.yaml")["algo"]["eps"] == 0.3
    assert ledger(tmp_path / "b")["regret"] != row["regret"]


def test_a_resumed_run_of_ones_own_learner_is_the_uninterrupted_one(tmp_path, monkeypatch):
    """3 episodes, then resumed to 5 from another directory: metrics.csv equals a 5-episode run's
    (its state_dict holds its coin). Without state_dict its resume is refused by name."""
    own = tmp_path / "own"
    own.mkdir()
    page_learner(own, resumable=True)
    monkeypatch.chdir(own)
    spec = "learner=watchful.py:Watchful"
    assert app.execute(recipe, [spec, "algo.episodes=5", "hydra.run.dir=whole", *QUIET]) == 0
    assert app.execute(recipe, [spec, "algo.episodes=3", "hydra.run.dir=part", *QUIET]) == 0
    monkeypatch.chdir(tmp_path)
    resume = [f"resume={own / 'part' / 'checkpoint.pt'}", "algo.episodes=5", *QUIET]
    assert app.execute(recipe, resume) == 0
    rows = [list(csv.DictReader((own / d / "metrics.csv").open())) for d in ("whole", "part")]
    for a, b in zip(*rows, strict=True):
        assert {k: a[k] for k in a if "second" not in k} == {
            k: b[k] for k in b if "second" not in k
        }
    page_learner(own)  # the page's own class: no state_dict
    monkeypatch.chdir(own)
    assert app.execute(recipe, [spec, "algo.episodes=1", "hydra.run.dir=plain", *QUIET]) == 0
    with pytest.raises(ValueError, match=r"defines no state_dict\(\).*load_state_dict"):
        app.prepare(recipe, [f"resume={own / 'plain' / 'checkpoint.pt'}", "algo.episodes=2"])


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (
            ["learner=watchful.py:Watchfull"],
            r"watchful.py has no Watchfull \(did you mean Watchful",
        ),
        (["learner=nofile.py:X"], r"learner=nofile.py:X: no such file"),
        (["learner=watchful.py"], r"or one of your own: learner=PATH.py:Class"),
        (["learner=watchful.py:1x"], r"learner=PATH.py:Class or learner=package.module:Class"),
        (["learner=json:JSONDecoder"], r"JSONDecoder is not a subclass of .*StreamLearner"),
        (["learner=nomod.x:Y"], r"cannot import nomod.x .*a file is learner=PATH.py:Y"),
        (["learner=broken.py:B"], r"importing broken.py failed: ZeroDivisionError"),
        (["learner=script.py:S"], r"importing script.py failed: SystemExit: 3"),
        (["learner=seedless.py:S"], r"its constructor must take \(params, seed=…"),
        (["learner=watchful.py:Watchful", "algo.epss=1"], r"algo.epss \(did you mean algo.eps\?\)"),
        (["learner=watchful.py:Watchful", "algo.episodes=0"], r"algo.episodes=0 is outside"),
    ],
)
def test_a_wrong_learner_of_ones_own_is_one_line_before_any_work(
    tmp_path, monkeypatch, capsys, args, message
):
    page_learner(tmp_path)
    (tmp_path / "broken.py").write_text("1 / 0\n")
    (tmp_path / "script.py").write_text("import sys\n\nsys.exit(3)\n")
    (tmp_path / "seedless.py").write_text(
        "from irdrc.online.loop import StreamLearner\n\n\nclass S(StreamLearner):\n"
        "    def __init__(self, params):\n        pass\n"
    )
    monkeypatch.chdir(tmp_path)
    assert app.execute(recipe, [*args, "hydra.run.dir=run"]) == 2
    assert __import__("re").search(message, capsys.readouterr().err)
    assert not (tmp_path / "run").exists()


def test_a_module_learner_a_sweeps_points_and_make_learner(tmp_path, monkeypatch):
    """``package.module:Class`` imports the module; a sweep's point records the file's absolute
    path (its trial runs elsewhere); ``make_learner`` builds one from its spec and keys."""
    from irdrc.sweeps.trials import plan

    page_learner(tmp_path)
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.chdir(tmp_path)
    assert app.prepare(recipe, ["learner=watchful:Watchful"]).config.algo.name == "watchful"
    # a file imports its neighbours, as under python PATH.py
    elsewhere = tmp_path / "lab"
    elsewhere.mkdir()
    (elsewhere / "rules.py").write_text("EPS = 0.25\n")
    (elsewhere / "mine.py").write_text(
        "from rules import EPS\nfrom watchful import Watchful\n\n\n"
        "class Mine(Watchful):\n    def __init__(self, params, seed=0):\n"
        "        super().__init__(params, EPS, seed)\n"
    )
    assert make_learner(f"{elsewhere / 'mine.py'}:Mine", None, Params()).eps == 0.25
    (point,) = plan(recipe, [{"learner": "watchful.py:Watchful"}], ["algo.eps=0.2"])
    assert point["config"].learner == f"{tmp_path / 'watchful.py'}:Watchful"
    assert point["composed"].cfg["algo"] == {"episodes": 300, "eps": 0.2}
    learner = make_learner("watchful.py:Watchful", {"eps": 0.5}, Params(), seed=3)
    assert learner.eps == 0.5 and learner.name == "watchful"
    with pytest.raises(ValueError, match="takes its constructor's keys"):
        make_learner("watchful.py:Watchful", configs.POSTERIOR, Params())


def test_the_benchmark_names_the_sweep_for_a_learner_of_ones_own():
    from conftest import load

    with pytest.raises(ValueError, match=r"a learner of your own runs beside them in a sweep"):
        load("bench_online", "learners=[watchful.py:Watchful]")
