"""Parameters: defaults, config names, and validation messages naming the key."""

from __future__ import annotations

import pytest
from omegaconf import OmegaConf

from irdrc import EnvParams, Params, RewardParams
from irdrc.core.params import as_dict
from irdrc.runs.scenarios import list_scenarios, load_scenario


def test_defaults_are_model_md():
    p = Params()
    e = p.env
    assert (e.queue_capacity, e.arrival_rate, e.packets_good, e.packets_bad) == (10, 1.0, 4, 2)
    assert e.p0.as_tuple() == (0.005,) * 4
    assert e.p1.as_tuple() == (0.05, 0.046, 0.1, 0.05)
    assert e.stay_good.as_tuple() == (0.9,) * 5 and e.stay_bad.as_tuple() == (0.1,) * 5
    assert (e.event_model, e.radar_reaction, e.horizon) == ("noisy_or", True, 400)
    assert (p.reward.r1, p.reward.r2, p.reward.r3, p.reward.r4) == (2, 1, 50, 5)
    assert e.num_states == 352


def test_round_trip_dict_and_omegaconf():
    d = Params().to_dict()
    assert Params.from_config(d) == Params()
    assert Params.from_config(OmegaConf.create(d)) == Params()


def test_overrides_nested_or_dotted_and_a_key_without_its_section_is_named():
    """One key style, the command line's: nested or dotted, each key with its section; a bare
    key is refused with its full name."""
    a = Params.from_overrides({"env": {"p1": {"speed": 0.5}}, "reward": {"r4": 50}})
    b = Params.from_overrides({"env.p1.speed": 0.5, "reward.r4": 50})
    assert a == b
    assert a.env.p1.speed == 0.5 and a.env.p1.road == 0.05 and a.reward.r4 == 50
    with pytest.raises(ValueError, match=r"'r4' needs its section: write 'reward\.r4'"):
        Params.from_overrides({"r4": 50})
    with pytest.raises(ValueError, match=r"write 'env\.p1\.speed'"):
        Params().with_overrides({"p1.speed": 0.5})


def test_scenario_files():
    assert {"paper", "ref_impl"} <= set(list_scenarios())
    paper = EnvParams.from_dict(load_scenario("paper"))
    assert paper == EnvParams()
    ref = as_dict(EnvParams.from_dict(load_scenario("ref_impl")))
    expected = as_dict(EnvParams())
    expected["p1"].update(speed=0.5, weather=0.05)
    assert ref == expected
    with pytest.raises(ValueError, match="not a scenario"):
        load_scenario("nope")


def test_a_scenario_file_that_is_a_list_is_refused_by_name(tmp_path):
    """A scenario file holding a YAML list (not a mapping of env keys) is refused with its path
    (it failed inside OmegaConf, asking a list for its ``defaults``)."""
    (tmp_path / "listed.yaml").write_text("# a list\n- queue_capacity: 5\n")
    with pytest.raises(ValueError, match=r"listed\.yaml: a scenario file holds a mapping"):
        load_scenario("listed", tmp_path)


def test_a_scenario_file_of_the_users_is_a_scenario(tmp_path, monkeypatch):
    """``env=PATH.yaml``: a file of the user's, anywhere, in the named scenarios' form — the same
    model as the command line's keys; without ``defaults`` it starts from paper; its ``defaults``
    name scenarios of irdrc or files beside it. Runs name it by its file name and store its
    absolute path, so a sweep or a resumed run finds it from any directory."""
    from conftest import load

    import irdrc
    from irdrc.runs.compose import compose

    (tmp_path / "city.yaml").write_text(
        "# a city\np1: {object: 0.2, speed: 0.3}\narrival_rate: 1.5\n"
    )
    (tmp_path / "rush.yaml").write_text("# rush hour\ndefaults: [city.yaml]\np1: {speed: 0.9}\n")
    (tmp_path / "town.yaml").write_text("# a town\ndefaults: multilevel\nqueue_capacity: 5\n")
    monkeypatch.chdir(tmp_path)
    keys = ["env.p1.object=0.2", "env.p1.speed=0.3", "env.arrival_rate=1.5"]
    assert load("solve", "env=city.yaml").model == load("solve", *keys).model
    rush = load("solve", "env=rush.yaml", "reward.r4=50").model
    assert rush == load("solve", *keys, "env.p1.speed=0.9", "reward.r4=50").model
    town = load("solve", f"env={tmp_path / 'town.yaml'}").model
    assert town == load("solve", "env=multilevel", "env.queue_capacity=5").model
    assert irdrc.scenario("rush.yaml", {"reward.r4": 50}) == rush
    composed = compose("solve", ["env=rush.yaml", "env.p1.road=0.2"])
    assert composed.scenario == "rush.yaml[env.p1.road=0.2]"
    assert f"env={tmp_path / 'rush.yaml'}" in composed.task
    assert composed.scenario_overrides[0] == f"env={tmp_path / 'rush.yaml'}"
    # what is wrong with a file is said in one line, naming it
    (tmp_path / "typo.yaml").write_text("# typo\np1: {sped: 0.5}\n")
    (tmp_path / "broken.yaml").write_text("p1: [\n")
    (tmp_path / "loop.yaml").write_text("# loop\ndefaults: [loop.yaml]\n")
    for value, says in (
        ("nope.yaml", r"env=nope\.yaml: no such scenario file"),
        ("typo.yaml", r"env\.p1\.sped \(did you mean env\.p1\.speed\?\)"),
        ("broken.yaml", r"broken\.yaml: not a YAML file"),
        ("loop.yaml", r"scenario defaults form a cycle"),
        ("nope", r"env='nope' is not a choice of env: .*a scenario file of your own"),
    ):
        with pytest.raises(ValueError, match=says):
            load("solve", f"env={value}")


BAD = [
    ("env.queue_capacity", 0),
    ("env.queue_capacity", 2.5),
    ("env.arrival_rate", -0.1),
    ("env.arrival_rate", float("nan")),
    ("env.packets_good", -1),
    ("env.packets_bad", -1),
    ("env.horizon", 0),
    ("env.event_model", "max"),
    ("env.radar_reaction", "yes"),
    ("env.reaction_clear", 1.2),
    ("reward.r1", -1.0),
    ("reward.r2", "two"),
    ("reward.r3", float("inf")),
    ("reward.r4", True),
    *[
        (f"env.{g}.{f}", v)
        for g in ("p0", "p1")
        for f in ("road", "weather", "speed", "object")
        for v in (-0.01, 1.01)
    ],
    *[
        (f"env.{g}.{f}", 1.5)
        for g in ("stay_good", "stay_bad")
        for f in ("channel", "road", "weather", "speed", "object")
    ],
]


@pytest.mark.parametrize(("key", "value"), BAD)
def test_invalid_value_names_key(key, value):
    with pytest.raises(ValueError) as err:
        Params.from_overrides({key: value})
    msg = str(err.value)
    assert key in msg and repr(value) in msg


def test_unknown_and_missing_keys():
    with pytest.raises(ValueError, match=r"env\.p1\.sped"):
        Params.from_overrides({"env.p1.sped": 0.2})
    with pytest.raises(ValueError, match=r"env\.bogus"):
        Params.from_overrides({"env.bogus": 1})
    with pytest.raises(ValueError, match=r"reward\.r6"):
        Params.from_overrides({"reward.r6": 1})
    full = Params().to_dict()
    del full["env"]["p1"]["road"]
    with pytest.raises(ValueError, match=r"missing key\(s\) env\.p1\.road"):
        Params.from_config(full)
    full = Params().to_dict()
    del full["reward"]["r3"]
    with pytest.raises(ValueError, match=r"missing key\(s\) reward\.r3"):
        Params.from_config(full)
    with pytest.raises(ValueError, match="missing key"):
        Params.from_config({"env": Params().to_dict()["env"]})
    with pytest.raises(ValueError, match=r"env\.p0 must be a mapping"):
        Params.from_overrides({"env.p0": 0.1})


def test_frozen():
    with pytest.raises(AttributeError):
        RewardParams().r1 = 3.0  # type: ignore[misc]


def test_with_overrides_keeps_the_rest_and_validates():
    base = Params.from_overrides({"env.p1.road": 0.2, "reward.r1": 3})
    p = base.with_overrides({"env.p1.speed": 0.5, "reward.r4": 50})
    assert (p.env.p1.speed, p.reward.r4) == (0.5, 50) and (p.env.p1.road, p.reward.r1) == (0.2, 3)
    assert base.env.p1.speed == 0.1  # frozen: the original is untouched
    with pytest.raises(ValueError, match=r"env\.p1\.sped"):
        base.with_overrides({"env.p1.sped": 0.5})
    with pytest.raises(ValueError, match=r"env\.p1\.speed=1\.5"):
        base.with_overrides({"env.p1.speed": 1.5})
