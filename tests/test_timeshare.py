"""Time-sharing within a step (MODEL.md § D): the config, the exact model over radar shares, the
optimum over the continuum and the facts § D states at the paper's defaults; the simulator and the
gymnasium env held to that model; DQN over levels (SAC: ``test_sac.py``, PPO: ``test_ppo.py``)."""

from __future__ import annotations

import csv
import dataclasses
import json
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from conftest import run_script

from irdrc.core.exact import build_model, stationary_metrics, value_iteration
from irdrc.core.exact.continuum import policy_model, solve_continuum
from irdrc.core.params import Params
from irdrc.core.share import breakpoints, capacity_split, reaction
from irdrc.core.states import decode_state

ROOT = Path(__file__).resolve().parents[1]


def params(**over) -> Params:
    return Params.from_overrides(over)


def optimum(p: Params, shares=None) -> float:
    m = build_model(p, shares=shares)
    return stationary_metrics(m, value_iteration(m, gamma=0.99, tol=1e-9).policy).avg_reward


@pytest.fixture(scope="module")
def paper():
    """The continuum's optimum and the binary optimum at the paper's defaults."""
    p = params(**{"env.actions": "continuous"})
    sol = solve_continuum(p)
    still = torch.zeros(p.env.num_states, dtype=torch.int64)
    binary = build_model(p, shares=(0.0, 1.0))
    best = value_iteration(binary, gamma=0.99, tol=1e-9).policy
    return p, sol, stationary_metrics(sol.model, still), stationary_metrics(binary, best)


def test_the_sensing_curve_ends_where_v1_is():
    rho = torch.tensor([0.0, 0.5, 1.0])
    assert reaction(rho, "dwell", 3.0).tolist() == pytest.approx([0.0, 0.8175744761936437, 1.0])
    assert reaction(rho, "linear", 3.0).tolist() == [0.0, 0.5, 1.0]
    k, p = capacity_split(torch.tensor(4.0), torch.tensor([0.0, 0.25, 0.3, 1.0]))
    assert k.tolist() == [4.0, 3.0, 2.0, 0.0] and p.tolist() == pytest.approx([0, 0, 0.8, 0])
    assert breakpoints(Params()) == (0.0, 0.25, 0.5, 0.75, 1.0)


@pytest.mark.parametrize(
    "scenario", [{}, {"env.detection_prob": 0.8, "env.false_alarm_prob": 0.05, "reward.r5": 3.0}]
)
def test_shares_zero_and_one_are_v1_bit_for_bit(scenario):
    """ρ ∈ {0, 1} through the time-sharing tables gives v1's (and § B's imperfect radar's) model
    exactly, not approximately."""
    p = params(**scenario)
    v1 = build_model(p)
    two = build_model(params(**scenario, **{"env.actions": "levels", "env.levels": 2}))
    for name in ("P", "R", "missed", "false_alarms", "sent", "dropped", "capacity"):
        assert torch.equal(getattr(v1, name), getattr(two, name)), name


def test_a_binary_policy_as_shares_scores_as_it_does_in_v1():
    p = Params()
    m = build_model(p)
    policy = value_iteration(m, gamma=0.99, tol=1e-9).policy
    as_rho = stationary_metrics(policy_model(p, policy.double()), torch.zeros_like(policy))
    assert as_rho.as_dict() == pytest.approx(stationary_metrics(m, policy).as_dict(), abs=1e-10)


def test_section_d_facts_at_the_paper_defaults(paper):
    """MODEL.md § D: 1.0586 against 0.8985 per step; misses 20.9 % against 28.9 %; throughput 1.000,
    radar time 0.383; ρ* ≈ 0.19 in all-favourable states on a good channel, 0.42 on a bad one."""
    p, sol, cont, binary = paper
    assert cont.avg_reward == pytest.approx(1.0586, abs=5e-5)
    assert binary.avg_reward == pytest.approx(0.8985, abs=5e-5)
    assert (round(cont.miss_detection, 3), round(binary.miss_detection, 3)) == (0.209, 0.289)
    assert round(cont.throughput, 3) == 1.0 and round(cont.radar_fraction, 3) == 0.383
    cols = decode_state(torch.arange(p.env.num_states))
    calm = cols[:, 2:].sum(1) == 0
    good, bad = sol.rho[calm & (cols[:, 1] == 0)], sol.rho[calm & (cols[:, 1] == 1)]
    assert (
        float(good.min()) == pytest.approx(0.19, abs=0.005)
        and float(good.max() - good.min()) < 1e-9
    )
    assert (
        float(bad.min()) == pytest.approx(0.42, abs=0.005) and float(bad.max() - bad.min()) < 1e-9
    )
    assert sol.value_bound < 1e-4  # the grid's bound on how far the values are below the optimum


def test_section_d_facts_elsewhere():
    """p^v_1 = 1.0: 1.9657 against 1.7993; linear sensing: the binary optimum (no gain); G levels
    reach 0.914, 0.985, 0.993, 0.9995 of the continuum's optimum (G = 3, 5, 9, 21)."""
    fast = params(**{"env.actions": "continuous", "env.p1.speed": 1.0})
    sol = solve_continuum(fast)
    still = torch.zeros(fast.env.num_states, dtype=torch.int64)
    assert stationary_metrics(sol.model, still).avg_reward == pytest.approx(1.9657, abs=5e-5)
    assert optimum(fast, (0.0, 1.0)) == pytest.approx(1.7993, abs=5e-5)
    linear = params(**{"env.actions": "continuous", "env.sensing": "linear"})
    sol = solve_continuum(linear)
    got = stationary_metrics(sol.model, still).avg_reward
    assert got == pytest.approx(0.8985, abs=5e-5)
    best = 1.058606  # the paper scenario's continuum optimum (above)
    for G, share in ((3, 0.914), (5, 0.985), (9, 0.993), (21, 0.9995)):
        got = optimum(params(**{"env.actions": "levels", "env.levels": G})) / best
        assert round(got, 4 if G == 21 else 3) == share, G


@pytest.mark.parametrize(
    "override, message",
    [
        ("env.actions=both", "env.actions='both' must be one of binary, levels, continuous"),
        ("env.levels=1", "env.levels=1 is outside the allowed range [2, 1001]"),
        ("env.sensing=cubic", "env.sensing='cubic' must be one of dwell, linear"),
        ("env.dwell_gain=-1", "env.dwell_gain=-1 is outside the allowed range (0.0, 100.0]"),
    ],
)
def test_bad_time_sharing_keys_are_one_line(override, message, tmp_path):
    shared = [] if override.startswith("env.actions") else ["env.actions=levels"]
    r = subprocess.run(
        [sys.executable, "recipes/solve.py", *shared, override, f"hydra.run.dir={tmp_path / 'r'}"],
        capture_output=True,
        text=True,
        cwd=ROOT,
    )
    assert r.returncode == 2 and r.stderr == f"error: {message}\n", r.stderr
    assert not (tmp_path / "r").exists()


def test_a_fleet_does_not_time_share():
    from irdrc.fleet.spec import FleetSpec

    with pytest.raises(ValueError, match=r"time-sharing .* is for one vehicle"):
        FleetSpec(vehicle=params(**{"env.actions": "levels"}))


def test_solve_prints_the_continuum_beside_binary_and_writes_rho(tmp_path):
    out = tmp_path / "run"
    r = subprocess.run(
        [sys.executable, "recipes/solve.py", "env.actions=continuous", f"hydra.run.dir={out}"],
        capture_output=True,
        text=True,
        cwd=ROOT,
    )
    assert r.returncode == 0, r.stderr
    assert r.stdout.startswith(
        "scenario=paper[env.actions=continuous]: optimum over the radar share"
    )
    assert "time-sharing earns 1.0586 per step against the binary optimum's 0.8985" in r.stdout
    rows = list(csv.DictReader((out / "policy.csv").open()))
    assert list(rows[0]) == ["d", "c", "r", "w", "v", "m", "rho"] and len(rows) == 352
    summary = json.loads((out / "summary.json").read_text())
    assert summary["metrics"]["avg_reward"] == pytest.approx(1.0586, abs=5e-5)
    assert summary["binary_optimum"]["avg_reward"] == pytest.approx(0.8985, abs=5e-5)


TIMESHARE_SCENARIOS = {
    "paper": {},
    "imperfect": {"env.detection_prob": 0.8, "env.false_alarm_prob": 0.05, "reward.r5": 3.0},
    "busy_linear": {"env.arrival_rate": 2.5, "env.queue_capacity": 4, "env.sensing": "linear"},
}


@pytest.mark.parametrize("actions", ["continuous", "levels"])
@pytest.mark.parametrize("name", list(TIMESHARE_SCENARIOS))
def test_simulator_matches_the_exact_model_under_a_random_share_policy(name, actions):
    """One step from every state under a random ρ policy (continuous: ρ uniform per state; levels:
    a random level), K times each: χ² on the next states against the policy's exact rows (5 sd
    above the χ² mean, ``assert_chi2``), and the mean reward, missed events, capacity and sent
    packets per state within 5 standard errors of their exact expectations."""
    from conftest import assert_chi2
    from tensordict import TensorDict

    from irdrc.core.env import DFRCEnv

    p = params(**TIMESHARE_SCENARIOS[name], **{"env.actions": actions})
    S, K = p.env.num_states, 2000
    g = torch.Generator().manual_seed(3)
    if actions == "continuous":
        rho = torch.rand(S, generator=g, dtype=torch.float64).to(torch.float32).double()
        action = rho.to(torch.float32)[:, None]
    else:
        level = torch.randint(0, p.env.levels, (S,), generator=g)
        rho, action = level.double() / (p.env.levels - 1), level
    exact = policy_model(p, rho)
    states = torch.arange(S).repeat_interleave(K)
    n = states.numel()
    env = DFRCEnv(p, batch_size=[n], seed=11)
    td = TensorDict(
        {
            "state": states,
            "action": action[states],
            "step_count": torch.zeros(n, 1, dtype=torch.long),
        },
        batch_size=[n],
    )
    nxt = env.step(td)["next"]
    counts = torch.zeros(S, S, dtype=torch.float64)
    counts.index_put_((states, nxt["state"]), torch.ones(n, dtype=torch.float64), accumulate=True)
    assert_chi2(counts, exact.P[0] * K)
    for key, mu in (
        ("reward", exact.R[0]),
        ("missed", exact.missed[0]),
        ("capacity", exact.capacity[0]),
        ("sent", exact.sent[0]),
    ):
        x = nxt[key].double().reshape(-1)
        mean = torch.zeros(S, dtype=torch.float64).index_add_(0, states, x) / K
        sq = torch.zeros(S, dtype=torch.float64).index_add_(0, states, x * x) / K
        se = torch.sqrt((sq - mean**2).clamp(min=0) / (K - 1))
        if (
            key != "reward"
        ):  # a 0/1 or count with every sample equal: Var X ≥ μ − μ² (X ≥ 0 integer)
            se = torch.maximum(se, torch.sqrt((mu - mu**2).clamp(min=0) / K))
        bad = (mean - mu).abs() > 5 * se + 1e-6  # 1e-6: float32 rewards where every sample agreed
        assert not bool(bad.any()), (key, mean[bad][:5].tolist(), mu[bad][:5].tolist())


@pytest.mark.parametrize("actions", ["levels", "continuous"])
def test_the_env_specs_hold_and_an_action_out_of_range_is_refused(actions):
    from torchrl.data import Bounded, Categorical
    from torchrl.envs.utils import check_env_specs

    from irdrc.core.env import DFRCEnv

    env = DFRCEnv(params(**{"env.actions": actions}), batch_size=[4], seed=0)
    check_env_specs(env)
    spec = env.action_spec
    if actions == "continuous":
        assert isinstance(spec, Bounded) and spec.shape == (4, 1)
        assert spec.space.low.min() == 0 and spec.space.high.max() == 1
    else:
        assert isinstance(spec, Categorical) and spec.space.n == 5
    bad = (
        torch.tensor([[0.5], [1.5], [0.0], [1.0]])
        if actions == "continuous"
        else torch.tensor([0, 5, 1, 2])
    )
    td = env.reset()
    td["action"] = bad
    with pytest.raises(ValueError, match=r"radar share in \[0, 1\]; got \[1.5\]|level in 0 … 4"):
        env.step(td)


@pytest.mark.e2e
def test_dqn_over_levels_scores_against_both_optima(tmp_path):
    """``recipes/dqn.py env.actions=levels``: G actions, scored against the G-level optimum, read
    against the optimum over ρ; policy.csv gives each state's level and share."""
    from conftest import TINY_DQN

    out = tmp_path / "run"
    r = run_script(
        "recipes/dqn.py",
        *TINY_DQN,
        "env.actions=levels",
        "eval.mc_episodes=8",
        f"hydra.run.dir={out}",
    )
    assert r.returncode == 0, r.stderr[-2000:]
    assert (
        "over ρ ∈ [0, 1] the optimum earns 1.0586 per step: the 5-level optimum is 0.9846"
        in r.stdout
    )
    summary = json.loads((out / "summary.json").read_text())
    assert summary["optimal"]["avg_reward"] == pytest.approx(1.0423, abs=5e-5)  # G = 5
    assert summary["continuum"]["levels_ratio"] == pytest.approx(0.9846, abs=5e-5)
    rows = list(csv.DictReader((out / "policy.csv").open()))
    assert list(rows[0])[-2:] == ["action", "rho"]
    assert all(float(x["rho"]) == int(x["action"]) / 4 for x in rows)
    mc = summary["table"]["dqn (Monte-Carlo, episodic)"]
    assert 0 <= mc["radar_fraction"] <= 1  # the share of each level, not the level


def test_the_levels_profile_is_dqn_over_levels_longer_and_wider():
    """``algo=dqn_levels`` is DQN's defaults over G levels with 1 M env steps, the ``medium``
    network and the shape, learning rate and reward centering it was measured at (1 000 rows,
    4 updates of 1 000 per collection on the sampled rewards, 3e-3, r̄ on the collected rewards
    alone; nothing else); a network chosen on the command line still wins."""
    from conftest import load

    from irdrc.agents.configs.value import NetworkConfig

    levels, dqn = load("dqn", "algo=dqn_levels"), load("dqn")
    assert levels.params.env.actions == "levels" and levels.algo.total_frames == 1_000_000
    medium = NetworkConfig(hidden=(128, 128))
    assert levels.algo == dataclasses.replace(
        dqn.algo,
        lr=3e-3,
        center_on="rewards",
        num_envs=1000,
        frames_per_batch=2000,
        total_frames=1_000_000,
        batch_size=1000,
        updates_per_batch=4,
        reward_means=False,
        network=medium,
    )
    for chosen, hidden in (("network=large", (256, 256)), ("network.hidden=[32,32]", (32, 32))):
        assert load("dqn", "algo=dqn_levels", chosen).algo.network.hidden == hidden


def test_dqn_refuses_continuous_shares(tmp_path):
    r = run_script("recipes/dqn.py", "env.actions=continuous", f"hydra.run.dir={tmp_path / 'r'}")
    assert (
        r.returncode == 2 and "use env.actions=levels" in r.stderr and not (tmp_path / "r").exists()
    )


@pytest.mark.slow
def test_dqn_over_five_levels_reaches_their_optimum_and_fails_without_the_sensing_curve():
    """DQN over G = 5 levels with its profile (``algo=dqn_levels``) ends ≥ 0.99 of the 5-level
    optimum (seed 0); trained where sensing is linear (the curve ignored) and scored on the dwell
    model, it does not."""
    from conftest import load

    from irdrc.agents.dqn import train
    from irdrc.core.exact import Scorer

    cfg = load("dqn", "algo=dqn_levels").algo
    p = params(**{"env.actions": "levels"})
    scorer = Scorer(build_model(p))
    good = train(p, cfg, seed=0, scorer=scorer, eval_every_frames=100_000)
    assert scorer.ratio(good.greedy[0]) >= 0.99, [e["optimality_ratio"] for e in good.history]
    blind = train(params(**{"env.actions": "levels", "env.sensing": "linear"}), cfg, seed=0)
    assert scorer.ratio(blind.greedy[0]) < 0.95


@pytest.mark.parametrize("actions", ["continuous", "levels"])
def test_the_gymnasium_env_steps_shares_as_the_exact_model_says(actions):
    """``gymnasium.make`` with a share action space: a ``Box(0, 1, (1,))`` or ``Discrete(G)`` action,
    gymnasium's env checker passes, and K one-step transitions from each of a few states at a fixed
    share hold to the exact rows (χ², 5 sd above its mean: ``assert_chi2``); a share out of range
    is refused, never clipped."""
    import gymnasium
    import numpy as np
    from conftest import assert_chi2
    from gymnasium.utils.env_checker import check_env

    import irdrc  # noqa: F401  (registers the id)

    env = gymnasium.make("irdrc/DFRC-v0", **{"env.actions": actions})
    p = env.unwrapped.params
    if actions == "continuous":
        assert env.action_space == gymnasium.spaces.Box(0.0, 1.0, (1,), np.float32)
        act, rho, bad = np.array([0.3], np.float32), float(np.float32(0.3)), np.array([1.2])
    else:
        assert env.action_space == gymnasium.spaces.Discrete(5)
        act, rho, bad = 1, 0.25, 5
    check_env(env.unwrapped, skip_render_check=True)
    states, K = [0, 7, 40, 200], 1500
    exact = policy_model(p, torch.full((p.env.num_states,), rho, dtype=torch.float64))
    counts = torch.zeros(len(states), p.env.num_states, dtype=torch.float64)
    env.reset(seed=5)
    for i, s in enumerate(states):
        for _ in range(K):
            env.reset(options={"state": s})
            counts[i, env.step(act)[4]["state"]] += 1
    assert_chi2(counts, exact.P[0][states] * K)
    with pytest.raises(ValueError, match=r"radar share in \[0, 1\]|level in 0 … 4"):
        env.step(bad)


def test_the_gymnasium_vector_env_takes_a_batch_of_shares():
    import gymnasium
    import numpy as np

    import irdrc  # noqa: F401  (registers the id)

    env = gymnasium.make_vec("irdrc/DFRC-v0", num_envs=3, **{"env.actions": "continuous"})
    assert env.single_action_space == gymnasium.spaces.Box(0.0, 1.0, (1,), np.float32)
    env.reset(seed=0)
    obs, reward, _, _, info = env.step(np.array([[0.0], [0.5], [1.0]], np.float32))
    assert obs.shape == (3, 6) and reward.shape == (3,)
    assert info["capacity"][2] == 0  # ρ = 1: the whole step is radar, nothing sent
    with pytest.raises(ValueError, match=r"radar share in \[0, 1\]; got \[-0.5\]"):
        env.step(np.array([[0.0], [-0.5], [1.0]]))
