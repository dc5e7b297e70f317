"""What a resume refuses before anything is read into a run or written: a checkpoint changed since
its run wrote it (its digest), a ``config.yaml`` edited since, a checkpoint of another recipe; and
a refused run leaves no directory behind, the logger's included."""

from __future__ import annotations

from pathlib import Path

import pytest

from irdrc.recipes import dqn
from irdrc.recipes.shares import sac
from irdrc.runs.app import prepare
from irdrc.runs.compose import compose_recipe
from irdrc.runs.scaffold import Run
from irdrc.runs.sections import Logger


def write_checkpoint(directory: Path, module=dqn, args=()) -> Path:
    """A run directory as ``module``'s recipe leaves it: config files and a checkpoint."""
    run = Run(module.NAME, compose_recipe(module, list(args)), directory).open()
    try:
        run.checkpoint({"frames": 64, "updates": 1, "wall_seconds": 0.1, "history": []})
    finally:
        run.close()
    return directory / "checkpoint.pt"


def files(directory: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in directory.iterdir() if p.is_file()}


def test_a_checkpoint_changed_since_its_run_wrote_it_is_refused_before_anything(tmp_path):
    path = write_checkpoint(tmp_path / "run")
    data = bytearray(path.read_bytes())
    data[len(data) // 2] ^= 0xFF  # one byte inside, the zip still readable
    path.write_bytes(bytes(data))
    before = files(path.parent)
    with pytest.raises(ValueError, match="differs from the one its run wrote"):
        prepare(dqn, [f"resume={path}"])
    assert files(path.parent) == before
    # the untouched checkpoint passes its check
    good = write_checkpoint(tmp_path / "good")
    prepare(dqn, [f"resume={good}", "algo.total_frames=32000"])


def test_the_digest_accepts_the_previous_checkpoint_while_a_new_one_replaces_it(tmp_path):
    path = write_checkpoint(tmp_path / "run")
    first = path.read_bytes()
    run = Run("dqn", compose_recipe(dqn, []), tmp_path / "run").open()
    try:
        run.checkpoint({"frames": 128, "updates": 2, "wall_seconds": 0.2, "history": []})
    finally:
        run.close()
    assert path.read_bytes() != first
    assert len(path.with_suffix(".sha256").read_text().split()) == 1  # the new one's alone


def test_an_edited_config_yaml_is_refused_naming_the_key(tmp_path):
    path = write_checkpoint(tmp_path / "run")
    config = path.parent / "config.yaml"
    config.write_text(config.read_text().replace("r4: 5.0", "r4: 50.0"))
    with pytest.raises(
        ValueError, match=r"edited after its run wrote it \(reward\.r4: 5\.0 → 50\.0\)"
    ):
        prepare(dqn, [f"resume={path}", "algo.total_frames=32000"])
    assert "r4: 50.0" in config.read_text()  # left as the user wrote it


def test_a_checkpoint_of_another_recipe_names_it_and_the_command(tmp_path):
    path = write_checkpoint(tmp_path / "run", sac, ["env.actions=continuous"])
    with pytest.raises(
        ValueError,
        match=r"is a checkpoint of the sac recipe; go on with it with: .*recipes/sac\.py resume=",
    ):
        prepare(dqn, [f"resume={path}"])


def test_a_refused_run_leaves_no_directory_the_logger_included(tmp_path):
    out = tmp_path / "a" / "run"
    run = Run("dqn", compose_recipe(dqn, []), out).open()
    run.make_logger(Logger(backend="csv"), "dqn")
    assert (out / "logs").exists()
    run.close(refused=True)
    assert not (tmp_path / "a").exists()


def test_checkpoints_are_paced_by_env_steps_or_wall_time_whichever_first():
    import time

    from irdrc.agents.base import Hooks

    def hooks(**kw) -> Hooks:
        return Hooks(on_checkpoint=lambda state: None, **kw)

    by_time = hooks(checkpoint_every_frames=10**9, checkpoint_every_seconds=0.05)
    assert not by_time.checkpoint_due(0, 100)
    time.sleep(0.06)
    assert by_time.checkpoint_due(100, 200)  # the time is up, far from the step mark
    assert not by_time.checkpoint_due(200, 300)  # … and it counts again from there
    by_steps = hooks(checkpoint_every_frames=100, checkpoint_every_seconds=3600)
    assert not by_steps.checkpoint_due(0, 99) and by_steps.checkpoint_due(99, 100)
    assert not hooks().checkpoint_due(0, 10**9)  # neither: at the end only


def test_a_scenario_changed_on_resume_is_named_in_a_few_keys():
    """``env=multilevel`` on a paper checkpoint changes dozens of keys; the refusal names three
    and counts the rest under the key the command line set (it listed every one, 659
    characters for a posterior-sampling run)."""
    from irdrc.runs.resume import CLASHES_SHOWN, resumed_config

    saved = {"env": {f"k{i}": i for i in range(8)}, "seed": 0}
    current = {"env": {f"k{i}": i + 1 for i in range(8)}, "seed": 0}
    with pytest.raises(
        ValueError, match=r"env\.k0: 0 → 1; env\.k1: 1 → 2; env\.k2: 2 → 3; … 5 more under env\."
    ):
        resumed_config(Path("c.pt"), saved, current, frozenset({"env"}))
    assert CLASHES_SHOWN == 3


@pytest.mark.parametrize("verbatim", [False, True])
def test_a_resumed_run_says_whether_it_is_the_uninterrupted_one(tmp_path, capsys, verbatim):
    """A learner of the shared loop checkpoints no replay and no env rows, so its resumed run
    differs from an uninterrupted one and says so; Q-learning and the one-stream learners, whose
    checkpoints hold every random stream (``tests/test_resume.py``,
    ``tests/test_online_learners.py``), resume verbatim and do not."""
    path = write_checkpoint(tmp_path / "run")
    state = {"frames": 64, "updates": 1, "wall_seconds": 0.1, "history": []}
    composed = compose_recipe(dqn, [f"resume={path}", "progress=false"])
    run = Run("dqn", composed, tmp_path / "run", resume_state=state)
    with run.training(128, "dqn", verbatim=verbatim):
        pass
    out = capsys.readouterr().out
    assert "resumed from" in out and "at 64 env steps" in out
    assert ("differ from an uninterrupted run's" in out) is not verbatim


def test_a_run_directory_given_for_its_file_is_answered_with_the_files_path(tmp_path):
    """``resume=DIR`` (and evaluate's ``checkpoint=DIR``, ``policy=DIR``) said "no such file" of
    a directory that exists; the answer now names the file inside it, or says it holds none."""
    from irdrc.core.checks import check_file

    path = write_checkpoint(tmp_path / "run")
    with pytest.raises(ValueError, match=rf"^resume={path.parent} is a directory: its checkpoint"):
        prepare(dqn, [f"resume={path.parent}"])
    (tmp_path / "empty").mkdir()
    with pytest.raises(ValueError, match=r"is a directory, and it holds no policy\.csv"):
        check_file("policy", tmp_path / "empty", "policy.csv")
    with pytest.raises(ValueError, match=r"^policy=.*/none\.csv: no such file$"):
        check_file("policy", tmp_path / "none.csv", "policy.csv")
    # a path that exists but is not a file (it said "no such file" of /dev/null)
    with pytest.raises(ValueError, match=r"^policy=/dev/null is not a regular file$"):
        check_file("policy", Path("/dev/null"), "policy.csv")
    assert check_file("checkpoint", path, "checkpoint.pt") == path


def test_a_resumed_run_may_choose_another_logger(tmp_path):
    """The logger may differ on resume (``RESUME_MAY_DIFFER``), whether set key by key or as the
    group: ``logger=none`` on a run that logged to csv goes on, logging nowhere."""
    path = write_checkpoint(tmp_path / "run")
    for choice, backend in (("logger=none", "none"), ("logger=tensorboard", "tensorboard")):
        resumed = prepare(dqn, [f"resume={path}", choice])
        assert resumed.composed.cfg["logger"]["backend"] == backend
    with pytest.raises(ValueError, match=r"algo\.lr: 0\.006 → 0\.1"):  # what it learns may not
        prepare(dqn, [f"resume={path}", "logger=none", "algo.lr=0.1"])
