"""The gymnasium entry point: checker, overrides, and the very same dynamics as DFRCEnv."""

from __future__ import annotations

import subprocess
import sys

import gymnasium
import numpy as np
import pytest
import torch
from conftest import assert_chi2
from gymnasium.utils.env_checker import check_env

import irdrc  # registers irdrc/DFRC-v0
from irdrc.core.exact import build_model
from irdrc.core.gym import DFRCGymEnv
from irdrc.core.params import Params


def test_env_checker_passes():
    env = gymnasium.make("irdrc/DFRC-v0")
    check_env(env.unwrapped, skip_render_check=True)


def test_overrides():
    env = gymnasium.make(
        "irdrc/DFRC-v0", env={"p1": {"speed": 0.5}, "horizon": 7}, reward={"r4": 50}
    )
    p = env.unwrapped.params
    assert p.env.p1.speed == 0.5 and p.reward.r4 == 50 and p.env.horizon == 7
    env2 = gymnasium.make(
        "irdrc/DFRC-v0", **{"env.p1.speed": 0.5, "reward.r4": 50, "env.horizon": 7}
    )
    assert env2.unwrapped.params == p
    with pytest.raises(ValueError, match=r"env\.p1\.speed"):
        gymnasium.make("irdrc/DFRC-v0", env={"p1": {"speed": 2.0}})
    # a keyword without its section: the error names what the constructor takes and the fix
    with pytest.raises(ValueError, match=r"takes params, env, reward.*r4 → 'reward\.r4'"):
        gymnasium.make("irdrc/DFRC-v0", r4=50)


def test_a_radar_share_key_for_whole_step_modes_is_refused():
    """``env.levels=9`` (or κ, the sensing curve) without ``env.actions`` made a Discrete(2) env
    that never read it; the same keys with a shared step still make their env."""
    import irdrc.fleet

    refusal = r"with env\.actions=binary each step is all comm or all radar; env\.{}"
    for key, value in (("levels", 9), ("dwell_gain", 2.0), ("sensing", "linear")):
        with pytest.raises(ValueError, match=refusal.format(key)):
            gymnasium.make("irdrc/DFRC-v0", **{f"env.{key}": value})
        with pytest.raises(ValueError, match=refusal.format(key)):
            gymnasium.make_vec("irdrc/DFRC-v0", num_envs=2, env={key: value})
        with pytest.raises(ValueError, match=refusal.format(key)):
            irdrc.fleet.parallel_env(**{f"env.{key}": value})
    env = gymnasium.make("irdrc/DFRC-v0", **{"env.actions": "levels", "env.levels": 9})
    assert env.action_space.n == 9
    env = gymnasium.make("irdrc/DFRC-v0", env={"actions": "continuous", "dwell_gain": 2.0})
    assert env.unwrapped.params.env.dwell_gain == 2.0


def test_a_named_scenario_is_irdrc_scenario():
    """``irdrc.scenario(NAME, overrides)`` is the ``Params`` the recipes compose for ``env=NAME``
    (every single-vehicle scenario of irdrc/scenarios/), for the gym id's ``params=``. A
    scenario's name given as a section (``env="multilevel"``) is answered with that call (it was
    "env must be a mapping, got 'multilevel'"); the fleet's PettingZoo env, which is
    irdrc/scenarios/fleet.yaml's fleet, says so (it was "dictionary update sequence element #0 has length 1; 2 is required"); a fleet is
    not one vehicle."""
    from irdrc.fleet import parallel_env
    from irdrc.recipes import solve
    from irdrc.runs.compose import compose
    from irdrc.runs.scenarios import fleet_scenarios, list_scenarios

    assert fleet_scenarios() == ["fleet"]
    for name in list_scenarios():
        if name != "fleet":
            want = solve.load(compose("solve", [f"env={name}", "reward.r4=50"])).model
            assert irdrc.scenario(name, {"reward.r4": 50}) == want, name
    env = gymnasium.make("irdrc/DFRC-v0", params=irdrc.scenario("multilevel"))
    assert env.unwrapped.params.env.num_states == 792
    with pytest.raises(ValueError, match=r"env='multilevel': .*irdrc\.scenario\('multilevel'\)"):
        gymnasium.make("irdrc/DFRC-v0", env="multilevel")
    # scenario= was answered "name each key with its section (scenario → 'env.scenario')"
    with pytest.raises(
        ValueError, match=r"no scenario=: .* params=irdrc\.scenario\('multilevel'\)"
    ):
        gymnasium.make("irdrc/DFRC-v0", scenario="multilevel")
    # params= of another type was "'int' object is not iterable"
    with pytest.raises(TypeError, match=r"params=3 must be a Params \(irdrc\.scenario\(name\)"):
        gymnasium.make("irdrc/DFRC-v0", params=3)
    # overrides as keywords, as gymnasium.make and parallel_env take them (was a TypeError)
    fast = irdrc.scenario("imperfect_radar", **{"env.p1.speed": 0.5, "reward.r4": 50})
    assert fast == irdrc.scenario("imperfect_radar", {"env.p1.speed": 0.5, "reward.r4": 50})
    assert fast.env.p1.speed == 0.5 and fast.reward.r4 == 50
    with pytest.raises(
        ValueError, match=r"env='paper': parallel_env is the fleet of irdrc/scenarios/fleet"
    ):
        parallel_env(env="paper")
    with pytest.raises(ValueError, match=r"'fleet' is a fleet of vehicles: irdrc\.fleet"):
        irdrc.scenario("fleet")


def test_a_bare_import_reaches_the_layers_and_loads_none_of_them():
    """``import irdrc`` then ``irdrc.fleet.parallel_env`` (as the README names it) works, loading
    the fleet only then (it was "module 'irdrc' has no attribute 'fleet'")."""
    code = (
        "import sys, irdrc\n"
        "assert 'irdrc.fleet' not in sys.modules and 'torch' not in sys.modules\n"
        "assert irdrc.fleet.parallel_env.__module__ == 'irdrc.fleet'\n"
        "assert irdrc.online is sys.modules['irdrc.online']\n"
        "print(irdrc.fleet.__name__)"
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=False)
    assert done.returncode == 0 and done.stdout == "irdrc.fleet\n", done.stderr
    with pytest.raises(AttributeError, match="has no attribute 'nope'"):
        irdrc.nope  # noqa: B018 - the attribute access is the test


def test_episode_and_info():
    env = gymnasium.make("irdrc/DFRC-v0", env={"horizon": 5})
    obs, info = env.reset(seed=0)
    assert obs.dtype == np.float32 and obs.shape == (6,)
    for t in range(5):
        obs, _reward, terminated, truncated, info = env.step(t % 2)
        assert not terminated and truncated == (t == 4)
    assert set(info) >= {"state", "event", "missed", "sent", "dropped", "capacity"}
    with pytest.raises(ValueError, match="action"):
        env.step(2)


def test_transitions_and_rewards_match_the_exact_model():
    """From every (state, action), K steps of the single env: χ² on next states against the exact
    model; mean reward, sent, dropped and capacity within 5 standard errors."""
    params = Params.from_overrides(
        {"env.p1.speed": 0.6, "env.arrival_rate": 1.7, "env.stay_good.road": 0.7}
    )
    m = build_model(params)
    # every factor configuration at queue lengths 0, 1, 5 and 10 (empty, nearly empty, half, full)
    starts = [d * 32 + f for d in (0, 1, 5, 10) for f in range(32)]
    S, K = m.num_states, 500
    env = DFRCGymEnv(params)
    env.reset(seed=3)
    # tallied in NumPy (a torch element update costs ~10 µs, each of 128 000 steps makes nine)
    counts = np.zeros((2 * S, S))
    keys = ("reward", "sent", "dropped", "capacity")
    sums, sq = np.zeros((len(keys), 2 * S)), np.zeros((len(keys), 2 * S))
    for a in (0, 1):
        for s in starts:
            row = a * S + s
            for _ in range(K):
                env.reset(options={"state": s})
                _, reward, _, _, info = env.step(a)
                counts[row, info["state"]] += 1
                x = np.array((reward, info["sent"], info["dropped"], info["capacity"]))
                sums[:, row] += x
                sq[:, row] += x * x
    rows = torch.tensor([a * S + s for a in (0, 1) for s in starts])
    assert_chi2(torch.from_numpy(counts)[rows], m.P.reshape(2 * S, S)[rows] * K)
    sums_of = dict(zip(keys, torch.from_numpy(sums), strict=True))
    sq_of = dict(zip(keys, torch.from_numpy(sq), strict=True))
    for key, exact in (
        ("reward", m.R),
        ("sent", m.sent),
        ("dropped", m.dropped),
        ("capacity", m.capacity),
    ):
        mean = sums_of[key] / K
        se = torch.sqrt((sq_of[key] / K - mean**2).clamp(min=0) / (K - 1))
        mu = exact.reshape(-1)
        if key == "reward":
            # The reward takes two values, with the event probability e: its exact variance is
            # e(1 − e)·(gap)². Rare events make the sample variance too small in some of the 704
            # rows, so the exact one is the bound.
            dyn = env.dynamics
            f = torch.arange(S) % 32
            e = dyn.event_prob[f % 16].double()
            gap = torch.stack(
                [dyn.reward[a * 64 + 32 + f] - dyn.reward[a * 64 + f] for a in (0, 1)]
            ).double()
            se = torch.sqrt((e * (1 - e) * gap**2).reshape(-1) / K)
        else:
            # an integer count X ≥ 0 has Var X ≥ μ − μ²: a floor when every sample was 0
            se = torch.maximum(se, torch.sqrt((mu - mu**2).clamp(min=0) / K))
        bad = ((mean - mu).abs() > 5 * se + 1e-6)[rows]  # 1e-6: float32 rewards, samples agree
        assert not bool(bad.any()), (key, mean[rows][bad][:5].tolist(), mu[rows][bad][:5].tolist())


def test_vector_env_matches_the_batched_dynamics_and_autoresets():
    venv = gymnasium.make_vec("irdrc/DFRC-v0", num_envs=3, env={"horizon": 2})
    obs, info = venv.reset(seed=0)
    assert obs.shape == (3, 6) and obs.dtype == np.float32
    _, _, term, trunc, _ = venv.step(np.array([0, 1, 0]))
    assert not trunc.any() and not term.any()
    _, _, _, trunc, _ = venv.step(np.array([0, 1, 0]))
    assert trunc.all()  # horizon 2
    obs, reward, _, trunc, info = venv.step(np.array([1, 1, 1]))  # the autoreset step
    assert not trunc.any() and (reward == 0).all() and not info["event"].any()
    # what is not 0 or 1 is refused by value (a bool and a string were taken, or torch's TypeError)
    for bad in ([0, 2, 0], [0, 0.5, 0], [True, False, True], ["0", "1", "0"]):
        with pytest.raises(ValueError, match=r"^actions? \S.* must be 0 \(communication\)"):
            venv.step(np.array(bad))


# -- misused: each mistake answered by name --------------------------------------------------------


@pytest.mark.parametrize("action", [0.5, 1.7, "1", 1.0, 2, -1, True, np.array([1])])
def test_gym_env_refuses_anything_but_0_and_1(action):
    """Discrete(2)'s actions are integers: 1.0 or [1] is refused saying so (it read "action=1.0
    must be 0 (communication) or 1 (radar)", which 1.0 seems to be)."""
    env = gymnasium.make("irdrc/DFRC-v0")
    env.reset(seed=0)
    with pytest.raises(ValueError, match=r"must be 0 \(communication\) or 1 \(radar\)") as err:
        env.unwrapped.step(action)
    integer = isinstance(action, int | np.integer) and not isinstance(action, bool)
    assert ("as an integer" in str(err.value)) == (not integer and action is not True), err.value


def test_gym_env_accepts_integer_scalars():
    """Python ints, NumPy integers and 0-d arrays are actions: comm carries packets, radar none."""
    env = gymnasium.make("irdrc/DFRC-v0").unwrapped
    env.reset(seed=0)
    for a in (0, 1, np.int64(1), np.array(0)):
        obs, _, terminated, _, info = env.step(a)
        assert env.observation_space.contains(obs) and not terminated
        assert (info["capacity"] > 0) == (int(a) == 0)


def test_gym_env_step_before_reset_is_refused():
    with pytest.raises(gymnasium.error.ResetNeeded):
        DFRCGymEnv().step(0)
    with pytest.raises(gymnasium.error.ResetNeeded):
        gymnasium.make_vec("irdrc/DFRC-v0", num_envs=2).step(np.array([0, 1]))


def test_reset_options_are_read_or_refused_never_ignored():
    """``reset(options=…)``: the single env and the vector env start from ``options["state"]``
    (the vector env from one index for all or one per env); a misspelt or unknown option is
    refused naming the closest (it was ignored, and the episode started from a random state)."""
    env = DFRCGymEnv()
    assert env.reset(options={"state": 5})[1]["state"] == 5
    vec = gymnasium.make_vec("irdrc/DFRC-v0", num_envs=3)
    assert vec.reset(options={"state": 7})[1]["state"].tolist() == [7, 7, 7]
    obs, info = vec.reset(options={"state": [1, 2, 3]})
    assert info["state"].tolist() == [1, 2, 3]
    assert (obs == vec.unwrapped.dynamics.obs[[1, 2, 3]].numpy()).all()
    for target in (env, vec):
        with pytest.raises(ValueError, match=r"options\.stat \(did you mean options\.state\?\)"):
            target.reset(options={"stat": 5})
        with pytest.raises(ValueError, match="must be a dict"):
            target.reset(options=5)
    for bad in ([1, 2], 1.5, [0, 1, 352]):
        with pytest.raises(ValueError, match=r"one per env"):
            vec.reset(options={"state": bad})
