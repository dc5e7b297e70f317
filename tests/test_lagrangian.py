"""The Lagrangian DQN (irdrc.agents.lagrangian): its config, the greedy path over μ, its loss, the
dual step, and learning."""

from __future__ import annotations

import itertools
import math

import pytest
import torch
from conftest import load
from tensordict import TensorDict
from torchrl.objectives import SoftUpdate

from irdrc.agents import lagrangian as L
from irdrc.agents.base import Hooks
from irdrc.agents.configs import LagrangianConfig, OffPolicyConfig
from irdrc.agents.offpolicy import RewardCenter
from irdrc.agents.policy_search import (
    SearchConfig,
    greedy_path,
    path_index,
)
from irdrc.core.cmdp import solve_cmdp
from irdrc.core.env import DFRCEnv
from irdrc.core.exact import build_model, stationary_metrics
from irdrc.core.params import Params


@pytest.fixture(scope="module")
def paper():
    return build_model(Params())


def test_yaml_profile_equals_the_dataclass_defaults():
    """The composed profile (DQN's YAML and the differences stated over it) is the code's."""
    got = load("constrained", "learner=dqn_lagrangian").algo
    assert got == LagrangianConfig() and got.name == "dqn_lagrangian"
    assert LagrangianConfig().dqn.total_frames == 80_000


@pytest.mark.parametrize(
    ("key", "value"),
    [
        ("mu_lr", -1.0),
        ("mu_max", 0.0),
        ("mu_init", 0.0),
        ("search_span", 0.5),
        ("measure_envs", 1),
        ("measure_max_blocks", 0),
        ("bogus", 1),
        ("average_tau", 0.01),  # a DQN option the Lagrangian loop does not implement
        ("confirm", "maybe"),
    ],
)
def test_bad_settings_named(key, value):
    with pytest.raises(ValueError, match=key):
        LagrangianConfig.from_sections({key: value})


def test_bad_target_and_objective_named():
    with pytest.raises(ValueError, match="target_miss"):
        LagrangianConfig(target_miss=1.5)
    with pytest.raises(ValueError, match="objective"):
        LagrangianConfig(objective="packets")


def test_greedy_path_is_greedy_at_every_multiplier():
    """Every table of the path is the argmax of Q_J − μ·Q_C on its interval of μ, and neighbours
    differ in exactly one state."""
    gen = torch.Generator().manual_seed(0)
    q = torch.randn(40, 2, 2, generator=gen, dtype=torch.float64)
    breaks, tables = greedy_path(q)
    assert len(tables) == len(breaks) + 1
    assert breaks == sorted(breaks) and all(b > 0 for b in breaks)
    for a, b in itertools.pairwise(tables):
        assert int((a != b).sum()) == 1
    edges = [0.0, *breaks, breaks[-1] * 2 + 1]
    for k, table in enumerate(tables):
        mu = 0.5 * (edges[k] + edges[k + 1])
        greedy = ((q[:, 0] - mu * q[:, 1]).argmax(-1) == 1).long()
        assert torch.equal(table, greedy), k
        assert path_index(breaks, mu) == k


def _batch(obs, action, nobs, sent, missed, event):
    n = len(action)
    return TensorDict(
        {
            "observation": obs,
            "action": torch.tensor(action),
            "next": {
                "observation": nobs,
                "sent": torch.tensor(sent),
                "missed": torch.tensor(missed),
                "event": torch.tensor(event),
                "terminated": torch.zeros(n, 1, dtype=torch.bool),
            },
        },
        batch_size=[n],
    )


def test_loss_is_double_dqn_on_both_heads():
    """The TD targets by hand: next action greedy on Q_J − μ·Q_C of the online network, valued by
    the target network's heads; the cost signal is missed − m*·event."""
    torch.manual_seed(0)
    heads = L.TwoHeads(torch.nn.Linear(3, 4))
    mu = torch.tensor(2.0)
    loss = L.LagrangianDQNLoss(heads, mu, gamma=0.9, objective_key="sent", target_miss=0.1)
    SoftUpdate(loss, tau=0.01)  # the learner's target updater (the loss warns without one)
    with torch.no_grad():  # make the target network differ from the online one
        for p in loss.target_value_network_params.values(True, True):
            p.add_(0.3)
    obs, nobs = torch.randn(5, 3), torch.randn(5, 3)
    td = _batch(obs, [0, 1, 0, 1, 1], nobs, [2, 0, 1, 0, 3], [1, 0, 0, 0, 0], [1, 1, 0, 0, 1])
    out = loss(td)
    q, qn = heads(obs), heads(nobs)
    with loss.target_value_network_params.to_module(loss.value_network):
        qt = loss.value_network(nobs)
    best = (qn[:, 0] - 2.0 * qn[:, 1]).argmax(-1)
    r = torch.tensor([[2.0, 0.9], [0.0, -0.1], [1.0, 0.0], [0.0, 0.0], [3.0, -0.1]])
    target = r + 0.9 * qt[torch.arange(5), :, best]
    taken = q[torch.arange(5), :, td["action"]]
    want = (taken - target).pow(2).sum(-1).mean()
    assert float(out["loss"].detach()) == pytest.approx(float(want.detach()), rel=1e-5)
    assert td["td_error"].shape == (5,)
    # algo.double_dqn=false: the next action is greedy in the target network itself
    loss.double_dqn = False
    with torch.no_grad():  # a target network that ranks the actions the other way round
        for p in loss.target_value_network_params.values(True, True):
            p.mul_(-1.0)
    with loss.target_value_network_params.to_module(loss.value_network):
        qt = loss.value_network(nobs)
    best_t = (qt[:, 0] - 2.0 * qt[:, 1]).argmax(-1)
    assert not torch.equal(best, best_t)  # the case tells the two apart
    target_t = r + 0.9 * qt[torch.arange(5), :, best_t]
    want_t = (taken - target_t).pow(2).sum(-1).mean()
    assert float(loss(td)["loss"].detach()) == pytest.approx(float(want_t.detach()), rel=1e-5)


def test_dual_step_is_relative_and_bounded():
    cfg = LagrangianConfig(target_miss=0.05, mu_lr=1.0, mu_min=1e-3, mu_max=1e3)
    assert L.dual_step(10.0, 0.05, 1000, cfg) == pytest.approx(10.0)
    assert L.dual_step(10.0, 1.0, 1000, cfg) == pytest.approx(10.0 * math.e)  # error clipped at 1
    assert L.dual_step(10.0, 0.0, 500, cfg) == pytest.approx(10.0 * math.exp(-0.5))
    assert L.dual_step(100.0, 0.075, 1000, cfg) == pytest.approx(100.0 * math.exp(0.5))
    assert L.dual_step(999.0, 1.0, 10_000, cfg) == 1e3
    assert L.dual_step(2e-3, 0.0, 10_000, cfg) == 1e-3


def tiny(total_frames: int = 1024) -> LagrangianConfig:
    """A run of ``total_frames`` env steps on 8 envs with a short final search."""
    return LagrangianConfig(
        dqn=OffPolicyConfig(
            num_envs=8,
            frames_per_batch=32,
            total_frames=total_frames,
            init_random_frames=total_frames // 4,
            batch_size=1000,
            updates_per_batch=4,
            reward_means=False,
            name="dqn_lagrangian",
        ),
        search=SearchConfig(measure_envs=8, measure_steps=50, measure_burn_in=10, mix_steps=2),
    )


def test_short_run_reports_mu_measured_miss_and_a_probability_policy():
    cfg = tiny()
    seen = []
    rec = L.train(Params(), cfg, seed=0, eval_every_frames=512, hooks=Hooks(on_batch=seen.append))
    assert {"mu", "measured_miss", "loss"} <= set(seen[-1])
    assert rec.policy.shape == (1, 352, 2)
    assert torch.allclose(rec.policy.sum(-1), torch.ones(1, 352, dtype=torch.float64))
    assert rec.env_steps == rec.training_env_steps + rec.measurement_env_steps
    assert (
        rec.measurement_env_steps == rec.info["measure_env_steps"]
        and rec.training_env_steps == 1024
    )
    assert len(rec.info["mu_trace"]) == 1024 // 32
    assert math.isfinite(rec.info["mu"]) and rec.info["mu"] >= 0
    with pytest.raises(ValueError, match="resume"):
        L.train(Params(), cfg, resume={})


@pytest.mark.slow
def test_meets_a_loose_target():
    """p^v_1 = 1, target 0.15: the LP sends everything (throughput 1.0) with miss 0.15. The
    learner must end with exact miss ≤ 0.16 and throughput ≥ 0.95 of the LP's (the benchmark's
    criteria), on two seeds."""
    params = Params.from_overrides({"env.p1.speed": 1.0})
    model = build_model(params)
    lp = solve_cmdp(model, 0.15)
    for seed in (0, 1):
        rec = L.train(params, LagrangianConfig(target_miss=0.15), seed=seed)
        m = stationary_metrics(model, rec.policy[0])
        assert m.miss_detection <= 0.16, (seed, m.miss_detection)
        assert m.throughput >= 0.95 * lp.value, (seed, m.throughput)


@pytest.mark.slow
def test_meets_the_binding_target_on_unseen_seeds():
    """p^v_1 = 0.1, target 0.05, where the LP communicates only in the all-favourable long-queue
    states (0.413 packets per step): on two seeds beyond both benchmarks' (0–19), the learner must
    meet the benchmark's criteria (exact miss ≤ 0.06, throughput ≥ 0.95 of the LP's) within 20 M env
    steps. Without the ranked family (the heads' path alone) seed 21 ends at 0.81 of the LP's
    throughput (measured when this was written)."""
    params = Params()
    model = build_model(params)
    lp = solve_cmdp(model, 0.05)
    for seed in (20, 21):
        rec = L.train(params, LagrangianConfig(target_miss=0.05), seed=seed)
        m = stationary_metrics(model, rec.policy[0])
        assert m.miss_detection <= 0.06, (seed, m.miss_detection, rec.info)
        assert m.throughput >= 0.95 * lp.value, (seed, m.throughput / lp.value, rec.info)
        assert rec.env_steps <= 20_000_000, (seed, rec.env_steps)


def test_objective_centering_shifts_the_objective_signal_only():
    params = Params()
    env = DFRCEnv(params, batch_size=[1])
    heads, _, _ = L.make_network(env, LagrangianConfig())
    loss = L.LagrangianDQNLoss(
        heads, torch.tensor(1.0), gamma=0.99, objective_key="sent", target_miss=0.05
    )
    SoftUpdate(loss, tau=0.01)
    td = TensorDict(
        {
            ("next", "sent"): torch.tensor([[3.0], [0.0]]),
            ("next", "missed"): torch.tensor([[False], [True]]),
            ("next", "event"): torch.tensor([[False], [True]]),
        },
        batch_size=[2],
    )
    plain = loss.signals(td)
    # the shared loop centres the objective's key in every sample (``TrainingLoop.center_key``)
    center = RewardCenter(0.01, value=0.75)
    centred = loss.signals(center.center(td.clone(), ("next", "sent")))
    assert torch.allclose(centred[:, 0], plain[:, 0] - 0.75)
    assert torch.equal(centred[:, 1], plain[:, 1])  # the cost signal is untouched


def test_centering_runs_and_tracks_the_objective_mean(monkeypatch):
    seen = []
    original = RewardCenter.update

    def spy(self, reward):
        original(self, reward)
        seen.append(self.value)

    monkeypatch.setattr(RewardCenter, "update", spy)
    dqn = OffPolicyConfig(
        num_envs=8,
        frames_per_batch=32,
        total_frames=256,
        init_random_frames=64,
        buffer_size=256,
        batch_size=32,
        updates_per_batch=4,
        reward_means=False,
        reward_centering=0.01,
        name="dqn_lagrangian",
    )
    cfg = LagrangianConfig(
        dqn=dqn, search=SearchConfig(measure_envs=4, measure_steps=20, measure_burn_in=0)
    )
    L.train(Params(), cfg, seed=0, eval_every_frames=128)
    assert len(seen) == 256 // 32 and all(0.0 <= v <= 4.0 for v in seen)  # packets sent per step


def test_the_final_search_counts_in_the_runs_wall_time(monkeypatch):
    """The final policy's measurements are counted in env_steps and so in the wall time: a search
    made to last 3 s more shows in ``wall_seconds`` (it ended before the search, a run reporting
    10.8 M env steps in 0 s)."""
    import time

    cfg = tiny(256)
    search = L.final_policy
    monkeypatch.setattr(L, "final_policy", lambda *a: time.sleep(3.0) or search(*a))
    start = time.perf_counter()
    rec = L.train(Params(), cfg, seed=0, eval_every_frames=256)
    assert rec.wall_seconds >= 3.0 and rec.wall_seconds <= time.perf_counter() - start
