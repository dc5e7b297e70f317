"""The gymnasium entry point: checker, overrides, and the very same dynamics as DFRCEnv."""

from __future__ import annotations

import gymnasium
import numpy as np
import pytest
import torch
from gymnasium.utils.env_checker import check_env

import irdrc  # noqa: F401 - registers irdrc/DFRC-v0
from irdrc import DFRCEnv, Params


def test_env_checker_passes():
    env = gymnasium.make("irdrc/DFRC-v0")
    check_env(env.unwrapped, skip_render_check=True)


def test_overrides():
    env = gymnasium.make("irdrc/DFRC-v0", env={"p1": {"speed": 0.5}}, reward={"r4": 50}, horizon=7)
    p = env.unwrapped.params
    assert p.env.p1.speed == 0.5 and p.reward.r4 == 50 and p.env.horizon == 7
    env2 = gymnasium.make("irdrc/DFRC-v0", **{"env.p1.speed": 0.5, "r4": 50, "horizon": 7})
    assert env2.unwrapped.params == p
    with pytest.raises(ValueError, match=r"env\.p1\.speed"):
        gymnasium.make("irdrc/DFRC-v0", p1={"speed": 2.0})


def test_episode_and_info():
    env = gymnasium.make("irdrc/DFRC-v0", horizon=5)
    obs, info = env.reset(seed=0)
    assert obs.dtype == np.float32 and obs.shape == (6,)
    for t in range(5):
        obs, _reward, terminated, truncated, info = env.step(t % 2)
        assert not terminated and truncated == (t == 4)
    assert set(info) >= {"state", "event", "missed", "sent", "dropped", "capacity"}
    with pytest.raises(ValueError, match="action"):
        env.step(2)


def test_same_dynamics_as_torchrl_env():
    params = Params.from_overrides(horizon=1000)
    genv = gymnasium.make("irdrc/DFRC-v0", horizon=1000).unwrapped
    obs, _ = genv.reset(seed=42)
    tenv = DFRCEnv(params, batch_size=[], seed=42)
    td = tenv.reset()
    assert np.array_equal(obs, td["observation"].numpy())
    actions = torch.randint(0, 2, (300,), generator=torch.Generator().manual_seed(0))
    for a in actions:
        obs, reward, _, _, info = genv.step(int(a))
        td["action"] = a
        td = tenv.step(td)["next"]
        assert np.array_equal(obs, td["observation"].numpy())
        assert reward == pytest.approx(float(td["reward"]))
        assert info["sent"] == int(td["sent"]) and info["event"] == bool(td["event"])
