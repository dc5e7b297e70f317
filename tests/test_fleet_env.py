"""The fleet's simulator and TorchRL envs (MODEL.md § C): held to the exact fleet model by χ², their
specs, seeding and misuse, and the single-agent rows view the shared learners train on."""

from __future__ import annotations

import pytest
import torch

from irdrc.core.exact import value_iteration
from irdrc.core.params import Params
from irdrc.fleet.model import FleetModel
from irdrc.fleet.policies import joint_from_single
from irdrc.fleet.scorer import FleetScorer, fleet_metrics
from irdrc.fleet.spec import FleetSpec


@pytest.mark.parametrize(
    ("access", "differ"), [("scheduled", False), ("collision", False), ("scheduled", True)]
)
def test_simulator_matches_the_exact_fleet_model_chi2(access, differ):
    """The fleet simulator (single-vehicle ``Dynamics`` per vehicle, shared road and weather,
    uplink grants, cooperative perception) against the exact fleet model, every feature of § C on
    (imperfect radar, radar reaction, sharing, one channel; vehicles alike, and differing in
    probabilities, arrivals, radar and rewards) at D = 1: from 12 joint states under
    each of the 4 joint actions, 4 000 steps each, the next joint state's counts pass Pearson's χ²
    (``assert_chi2``: 5 sd above the mean) and the fleet reward's mean is within 5 standard errors
    of the model's expectation (a seeded run; 5 SE keeps the 48 comparisons from failing by
    chance at about 6e-7 each)."""
    from conftest import assert_chi2

    from irdrc.fleet.sim import FleetDynamics

    params = Params.from_overrides(
        {
            "env.queue_capacity": 1,
            "env.detection_prob": 0.8,
            "env.false_alarm_prob": 0.1,
            "reward.r5": 7.0,
            "env.p1.speed": 0.6,
        }
    )
    per = None
    if differ:  # vehicle 2 differs in its event probability, arrivals, radar and reward weights
        other = params.with_overrides(
            {
                "env.p1.speed": 0.2,
                "env.arrival_rate": 0.5,
                "env.detection_prob": 0.95,
                "env.false_alarm_prob": 0.02,
                "reward.r4": 9.0,
                "reward.r3": 30.0,
            }
        )
        per = (params, other)
    m = FleetModel(
        FleetSpec(vehicle=params, vehicles=2, channels=1, access=access, share=0.5, per_vehicle=per)
    )
    sim = FleetDynamics(m)
    gen = torch.Generator().manual_seed(7)
    starts = torch.randperm(m.num_states, generator=gen)[:12]
    n, X = 4000, m.X
    rows = [(int(s), a) for s in starts for a in range(4)]
    states, actions = [], []
    for s, a in rows:
        rw, x1, x2 = s // (X * X), (s // X) % X, s % X
        states.append(torch.tensor([[m.index[rw, x1], m.index[rw, x2]]]).expand(n, 2))
        actions.append(torch.tensor([[a & 1, (a >> 1) & 1]]).expand(n, 2))
    out = sim.step(torch.cat(states), torch.cat(actions), gen)
    nxt = sim.fleet_index(out.state).reshape(len(rows), n)
    counts = torch.zeros(len(rows), m.num_states, dtype=torch.float64)
    counts.scatter_add_(1, nxt, torch.ones_like(nxt, dtype=torch.float64))
    expected = torch.zeros_like(counts)
    reward = out.reward.sum(1).reshape(len(rows), n)
    for k, (s, a) in enumerate(rows):
        delta = torch.zeros(m.num_states, dtype=torch.float64)
        delta[s] = 1.0
        delta = delta.reshape(m.shape())
        for p, names, _ in m.joint[a]:
            expected[k] += p * n * m.push(delta, names).reshape(-1)
        want = float(m.reward(a).reshape(-1)[s])
        se = float(reward[k].std()) / n**0.5
        assert abs(float(reward[k].mean()) - want) <= 5 * se + 1e-9, (s, a, want)
    assert_chi2(counts, expected)


def test_fleet_env_specs_seeding_and_misuse():
    """``FleetEnv`` follows TorchRL's multi-agent layout (``check_env_specs`` at N = 1 and 2),
    the same seed gives the same steps, its joint ``state`` is the exact model's index of the
    vehicles' states, and misuse gets a clear error."""
    from tensordict import TensorDict
    from torchrl.envs.utils import check_env_specs, step_mdp

    from irdrc.fleet.env import FleetEnv

    for n in (1, 2):
        env = FleetEnv(FleetSpec(vehicles=n), batch_size=4, seed=0)
        check_env_specs(env)
        assert env.group_map == {"agents": [f"vehicle_{i + 1}" for i in range(n)]}

    def run(seed: int) -> torch.Tensor:
        env = FleetEnv(FleetSpec(vehicles=2), batch_size=16, seed=seed)
        td = env.reset()
        out = []
        for t in range(20):
            td["agents", "action"] = torch.tensor([[t % 2, 1 - t % 2]]).expand(16, 2).clone()
            td = env.step(td)
            out.append(td["next", "agents", "reward"].clone())
            nxt = td["next"]
            assert torch.equal(nxt["joint_index"], env.sim.fleet_index(nxt["vehicle_state"]))
            td = step_mdp(td)
        return torch.stack(out)

    assert torch.equal(run(3), run(3)) and not torch.equal(run(3), run(4))
    env = FleetEnv(FleetSpec(vehicles=2), batch_size=2, seed=0)
    with pytest.raises(ValueError, match=r"call env\.reset"):
        env.step(TensorDict({"agents": {"action": torch.zeros(2, 2, dtype=torch.int64)}}, [2]))
    td = env.reset()
    td["agents", "action"] = torch.full((2, 2), 2, dtype=torch.int64)
    with pytest.raises(ValueError, match="action"):
        env.step(td)


def test_fleet_rows_and_independent_dqn_with_parameter_sharing():
    """``FleetRowsEnv`` gives each vehicle a row with the fleet's team reward (both rows of a fleet
    get the same sum); ``FleetScorer`` scores a shared single-vehicle table as N copies of it on
    the fleet; ``marl.train_idqn`` runs DQN's learner on the rows and records exact fleet ratios."""
    from torchrl.envs.utils import check_env_specs

    from irdrc.agents import marl
    from irdrc.agents.configs import FleetLearnerConfig
    from irdrc.fleet.views import FleetRowsEnv

    model = FleetModel(FleetSpec(vehicles=2))
    env = FleetRowsEnv(model, fleets=3, seed=0)
    check_env_specs(env)
    td = env.rollout(4)
    r = td["next", "reward"]  # [rows, steps, 1]: rows 2b and 2b + 1 are fleet b
    assert torch.equal(r[0::2], r[1::2])
    scorer = FleetScorer(model)
    single = value_iteration(model.single).policy
    copies, _ = fleet_metrics(model, joint_from_single(model, single))
    assert scorer.metrics(single).avg_reward == pytest.approx(copies.avg_reward, abs=1e-12)
    assert scorer.optimal_metrics.avg_reward > copies.avg_reward
    cfg = FleetLearnerConfig.from_sections(
        "idqn", {"num_envs": 32, "frames_per_batch": 64, "total_frames": 1024, "batch_size": 64}
    )
    rec = marl.train(model, cfg, seed=0, scorer=scorer, eval_every_frames=512)
    assert [h["env_steps"] for h in rec.history] == [0, 512, 1024]  # fleet steps
    assert all(-5 < h["optimality_ratio"] <= 1 + 1e-9 for h in rec.history)


def test_agent_index_gives_each_vehicle_its_own_table():
    """With ``agent_index`` each row also sees its vehicle's one-hot index, the observation table
    has a row per (vehicle, state), and ``FleetScorer`` reads a [N·S] greedy table as vehicle i's
    own table: vehicle 1 radar always and vehicle 2 the single optimum scores as that joint
    policy."""
    from irdrc.fleet.views import FleetRowsEnv

    model = FleetModel(FleetSpec(vehicles=2))
    S = model.single.num_states
    env = FleetRowsEnv(model, fleets=2, seed=0, agent_index=True)
    assert env.observation_table.shape == (2 * S, 8) and env.num_states == 2 * S
    obs = env.reset()["observation"]
    assert obs[:, 6:].tolist() == [[1, 0], [0, 1], [1, 0], [0, 1]]
    single = value_iteration(model.single).policy
    tables = torch.cat([torch.ones(S, dtype=torch.int64), single])
    joint = joint_from_single(model, single) | 1  # vehicle 1's bit set: radar
    want, _ = fleet_metrics(model, joint)
    got = FleetScorer(model).metrics(tables)
    assert got.avg_reward == pytest.approx(want.avg_reward, abs=1e-12)
