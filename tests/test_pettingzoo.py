"""The fleet as a PettingZoo ``ParallelEnv`` (``irdrc.fleet.parallel_env``): PettingZoo's own API
test, the same steps as ``FleetEnv`` for a seed, the exact fleet model by χ², misuse, and TorchRL's
``PettingZooWrapper`` over it."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
import torch
from pettingzoo.test import parallel_api_test

from irdrc.fleet import parallel_env
from irdrc.fleet.model import FleetModel
from irdrc.fleet.spec import FleetSpec


@pytest.mark.parametrize("vehicles", [2, 4])
@pytest.mark.parametrize("observe", ["own", "full"])
def test_pettingzoo_parallel_api_test_passes(vehicles, observe, capsys):
    """PettingZoo's ``parallel_api_test`` (whole episodes: truncation at the horizon empties
    ``agents``) passes with its warnings turned into errors, at N = 2 and 4, both observations."""
    env = parallel_env(**{"env.vehicles": vehicles, "env.observe": observe}, seed=0)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        parallel_api_test(env, num_cycles=1000)
    assert "Passed Parallel API test" in capsys.readouterr().out
    width = 6 if observe == "own" else 6 + 4 * (vehicles - 1)
    assert env.observation_space("vehicle_1").shape == (width,)
    assert env.state_space.shape == (2 + 4 * vehicles,)
    obs, _ = env.reset(seed=1)
    assert all(env.observation_space(a).contains(obs[a]) for a in env.agents)
    assert env.state_space.contains(env.state())


def test_same_steps_as_fleet_env_for_a_seed():
    """One fleet through ``parallel_env`` and ``FleetEnv(batch_size=1)`` with the same seed and
    actions: the same observations, rewards, signals and critic state at every step (one simulator,
    one generator, the same draws) — and the team reward is the fleet's sum."""
    from irdrc.fleet.env import FleetEnv

    spec = FleetSpec(vehicles=3, channels=1, share=0.5)
    model = FleetModel(spec)
    pz = parallel_env(model, rewards="own", seed=5)
    team = parallel_env(model, rewards="team", seed=5)
    tr = FleetEnv(model, batch_size=1, seed=5)
    obs, _ = pz.reset()
    team.reset()
    td = tr.reset()
    gen = torch.Generator().manual_seed(0)
    for _ in range(60):
        assert np.array_equal(np.stack(list(obs.values())), td["agents", "observation"][0].numpy())
        assert np.array_equal(pz.state(), td["state"][0].numpy())
        a = torch.randint(0, 2, (3,), generator=gen)
        obs, rew, _, _, info = pz.step({f"vehicle_{i + 1}": int(a[i]) for i in range(3)})
        _, rew_team, _, _, _ = team.step({f"vehicle_{i + 1}": int(a[i]) for i in range(3)})
        td["agents", "action"] = a.reshape(1, 3)
        td = tr.step(td)
        nxt = td["next"]
        want = nxt["agents", "reward"][0, :, 0].numpy()
        assert np.allclose(list(rew.values()), want, atol=1e-6)
        assert np.allclose(list(rew_team.values()), want.sum(), atol=1e-4)
        for key in ("event", "missed", "granted", "denied", "sent", "dropped"):
            assert [info[f"vehicle_{i + 1}"][key] for i in range(3)] == nxt["agents", key][
                0
            ].long().tolist(), key
        td = td["next"]


def test_parallel_env_matches_the_exact_fleet_model_chi2():
    """From 4 joint states, each under its own joint action, 1 500 steps each through
    ``reset(options={"state": s})`` and ``step``, at N = 2 with every feature of § C on (imperfect
    radar, radar reaction, cooperative perception, one channel) and D = 1: the next joint state's
    counts pass Pearson's χ² (``assert_chi2``: 5 sd above the mean) and each mean fleet reward is
    within 5 standard errors of the model's expectation (seeded; 5 SE keeps the 4 comparisons
    from failing by chance at about 6e-7 each)."""
    from conftest import assert_chi2

    overrides = {
        "env.vehicles": 2,
        "env.queue_capacity": 1,
        "env.detection_prob": 0.8,
        "env.false_alarm_prob": 0.1,
        "reward.r5": 7.0,
        "env.p1.speed": 0.6,
    }
    env = parallel_env(**overrides, seed=11)
    m = env.model
    gen = torch.Generator().manual_seed(3)
    starts = torch.randperm(m.num_states, generator=gen)[:4].tolist()
    n = 1500
    counts = torch.zeros(4, m.num_states, dtype=torch.float64)
    expected = torch.zeros_like(counts)
    for k, s in enumerate(starts):
        a = k % 4  # joint action: vehicle i's action is bit i
        act = {"vehicle_1": a & 1, "vehicle_2": (a >> 1) & 1}
        rewards = []
        for _ in range(n):
            env.reset(options={"state": s})
            _, rew, _, _, info = env.step(act)
            counts[k, info["vehicle_1"]["joint_index"]] += 1
            rewards.append(sum(rew.values()))
        delta = torch.zeros(m.num_states, dtype=torch.float64)
        delta[s] = 1.0
        delta = delta.reshape(m.shape())
        for p, names, _ in m.joint[a]:
            expected[k] += p * n * m.push(delta, names).reshape(-1)
        r = torch.tensor(rewards, dtype=torch.float64)
        want = float(m.reward(a).reshape(-1)[s])
        assert abs(float(r.mean()) - want) <= 5 * float(r.std()) / n**0.5 + 1e-9, (s, a, want)
    assert_chi2(counts, expected)


def test_parallel_env_misuse_is_refused_clearly():
    """Steps before reset or after the last one, a missing or bad action, a bad start state, a key
    without its section and spec with overrides each get a clear error."""
    env = parallel_env(seed=0)
    with pytest.raises(RuntimeError, match="reset"):
        env.step({"vehicle_1": 0, "vehicle_2": 0})
    with pytest.raises(RuntimeError, match="reset"):
        env.state()
    env.reset()
    with pytest.raises(ValueError, match="no action for vehicle_2"):
        env.step({"vehicle_1": 0})
    with pytest.raises(ValueError, match="unknown agent"):
        env.step({"vehicle_1": 0, "vehicle_2": 0, "vehicle_9": 1})
    # a misspelt agent is named, not the agent it leaves without an action
    with pytest.raises(
        ValueError, match=r"unknown agent.*vehicle_0: this env's agents are vehicle_1"
    ):
        env.step({"vehicle_0": 0, "vehicle_2": 0})
    # an action that is not 0 or 1 is refused naming its agent (0.5 was taken as 0, True as 1)
    for bad in (2, 0.5, True, "a", None, [0, 1]):
        with pytest.raises(ValueError, match=r"^vehicle_1's action"):
            env.step({"vehicle_1": bad, "vehicle_2": 0})
    for good in (1, 1.0, np.int64(1), np.array(1), np.array([1.0])):
        env.step({"vehicle_1": good, "vehicle_2": 0})
    with pytest.raises(ValueError, match="joint state index"):
        env.reset(options={"state": env.model.num_states})
    with pytest.raises(ValueError, match=r"env\.vehicles"):
        parallel_env(**{"vehicles": 3})
    with pytest.raises(ValueError, match="spec or overrides"):
        parallel_env(FleetSpec(), **{"env.share": 0.2})
    with pytest.raises(ValueError, match="rewards"):
        parallel_env(rewards="sum")
    env = parallel_env(**{"env.horizon": 3}, seed=0)
    env.reset()
    for _ in range(3):
        _, _, term, trunc, _ = env.step({"vehicle_1": 1, "vehicle_2": 1})
    assert all(trunc.values()) and not any(term.values()) and env.agents == []
    with pytest.raises(RuntimeError, match="reset"):
        env.step({"vehicle_1": 1, "vehicle_2": 1})


def test_torchrl_pettingzoo_wrapper_reads_it():
    """TorchRL's ``PettingZooWrapper`` over it, grouped as ``FleetEnv`` is (``"agents"``), with the
    centralised ``state``: its specs check out and a random rollout runs to the horizon's
    truncation."""
    from torchrl.envs import PettingZooWrapper
    from torchrl.envs.utils import check_env_specs

    pz = parallel_env(**{"env.horizon": 20}, seed=0)
    env = PettingZooWrapper(
        pz, group_map={"agents": pz.possible_agents}, return_state=True, categorical_actions=True
    )
    check_env_specs(env)
    td = env.rollout(25, break_when_any_done=True)
    assert td.batch_size == (20,)
    assert td["next", "agents", "observation"].shape == (20, 2, 6)
    assert td["next", "state"].shape == (20, 10)
    assert bool(td["next", "truncated"][-1]) and not bool(td["next", "truncated"][:-1].any())


def test_without_pettingzoo_the_error_says_how_to_install_it(monkeypatch):
    """The fleet's PettingZoo door names the extra that brings PettingZoo (it was Python's bare
    "No module named 'pettingzoo'")."""
    import sys

    import irdrc.fleet

    monkeypatch.setitem(sys.modules, "pettingzoo", None)  # an import of it now fails
    monkeypatch.delitem(sys.modules, "irdrc.fleet.parallel", raising=False)
    with pytest.raises(ModuleNotFoundError, match=r"pip install 'irdrc\[pettingzoo\]'"):
        irdrc.fleet.parallel_env()


@pytest.mark.parametrize("seed", ["a", -1, 2.5])
def test_a_seed_that_is_not_one_is_refused_by_name(seed):
    """``parallel_env(seed="a")`` was "invalid literal for int() with base 10: 'a'"; ``seed=-1``
    was taken, and ``reset(seed=-1)`` failed in gymnasium's seeding of the action spaces ("Seed
    must be greater or equal to zero")."""
    with pytest.raises(ValueError, match=r"^seed="):
        parallel_env(seed=seed)
    env = parallel_env(seed=np.int64(3))  # a NumPy integer is a seed
    with pytest.raises(ValueError, match=r"^seed="):
        env.reset(seed=seed)
