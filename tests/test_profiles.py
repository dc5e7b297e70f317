"""Every key a learner profile (``irdrc/conf/algo/*.yaml``) sets acts on that profile's own run:
no key is set where another key makes it do nothing (a priority exponent without prioritised
replay, an exploration floor with one row, a schedule's start without a schedule, …)."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import pytest
from conftest import load
from omegaconf import OmegaConf

from irdrc.agents.configs import DQNConfig, QLearningConfig

ALGO = Path(__file__).resolve().parents[1] / "irdrc" / "conf" / "algo"

INERT = {
    DQNConfig: {
        "alpha": lambda a: not a.prioritized,
        "center_on": lambda a: a.reward_centering == 0,
        "init_random_frames": lambda a: a.init_random_frames == 0,
        "eps_min": lambda a: a.num_envs == 1,
        "eps_duration_max": lambda a: a.eps_max == 0,
        "lr_end": lambda a: a.total_frames <= a.frames_per_batch,
    },
    QLearningConfig: {
        "epsilon_start": lambda a: a.epsilon_decay_episodes == 0,
        "epsilon_decay_episodes": lambda a: a.epsilon_start == a.epsilon_end,
        "alpha_power": lambda a: a.alpha_schedule == "constant",
        "alpha_min": lambda a: a.alpha_schedule == "constant" or a.alpha_min == 0,
    },
}
"""When a key does nothing, given the profile's other keys."""

RECIPE = {"dqn_lagrangian": ("constrained", ["learner=dqn_lagrangian"])}
"""Profiles another recipe runs (the rest: ``dqn`` or ``qlearning`` by their name)."""


def own_keys(path: Path) -> set[str]:
    """The ``algo`` keys a profile's file sets itself (not those of the file it extends)."""
    node = OmegaConf.to_container(OmegaConf.load(path), resolve=False)
    node.pop("defaults", None)
    if path.read_text().startswith("# @package _global_"):
        node = node.get("algo", {})
    return {k for k in node if k != "name"}


def profile_config(name: str):
    recipe, extra = RECIPE.get(name, ("qlearning" if name.startswith("qlearning") else "dqn", []))
    algo = load(recipe, *extra, f"algo={name}").algo
    return getattr(algo, "dqn", algo)  # the Lagrangian's machinery is DQN's


def inert_keys(config, keys: set[str]) -> list[str]:
    rules = next(r for cls, r in INERT.items() if isinstance(config, cls))
    return sorted(k for k in keys if k in rules and rules[k](config))


@pytest.mark.parametrize("path", sorted(ALGO.glob("*.yaml")), ids=lambda p: p.stem)
def test_every_key_a_profile_sets_acts_on_its_run(path):
    config = profile_config(path.stem)
    assert not inert_keys(config, own_keys(path)), path.name


def test_the_check_finds_a_key_that_does_nothing():
    """The mutation: a priority exponent on uniform replay, ε's start without a decay."""
    uniform = dataclasses.replace(DQNConfig(), prioritized=False)
    assert inert_keys(uniform, {"alpha", "lr"}) == ["alpha"]
    assert inert_keys(QLearningConfig(), {"epsilon_start", "alpha"}) == ["epsilon_start"]


def test_a_key_a_profile_leaves_out_can_still_be_set():
    """``dqn.yaml`` lists no warm-up (0 does nothing there), yet a command line may ask for one."""
    assert "init_random_frames" not in own_keys(ALGO / "dqn.yaml")
    assert load("dqn", "algo.init_random_frames=1000").algo.init_random_frames == 1000
    assert (
        load("qlearning", "algo.epsilon_decay_episodes=10", "algo.epsilon_start=0.5").algo.epsilon(
            0
        )
        == 0.5
    )
