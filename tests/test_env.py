"""DFRCEnv: specs, seeding, resets, and every rule of MODEL.md's step on hand-set states."""

from __future__ import annotations

import itertools

import pytest
import torch
from tensordict import TensorDict
from torchrl.envs.utils import check_env_specs

from irdrc import DFRCEnv, Params, decode_state, state_index
from irdrc.core.dynamics import queue_update


@pytest.mark.parametrize("batch_size", [[], [1], [4], [1024], [2, 3]])
def test_check_env_specs(batch_size):
    env = DFRCEnv(Params(), batch_size=batch_size, seed=0)
    check_env_specs(env, seed=0)
    td = env.reset()
    assert td["observation"].shape == (*batch_size, 6)
    assert td["state"].shape == tuple(batch_size)
    assert env.action_spec_unbatched.shape == ()


def test_bad_batch_size():
    with pytest.raises(ValueError, match="batch_size"):
        DFRCEnv(Params(), batch_size=[0])


def test_state_index_round_trip():
    s = torch.arange(352)
    cols = decode_state(s)
    assert torch.equal(state_index(*cols.unbind(-1)), s)
    assert cols[:, 0].max() == 10 and bool(((cols[:, 1:] == 0) | (cols[:, 1:] == 1)).all())
    assert state_index(3, 1, 0, 1, 0, 1) == 3 * 32 + 16 + 4 + 1


def _rollout(seed, steps=50):
    env = DFRCEnv(Params(), batch_size=[8], seed=seed)
    gen = torch.Generator().manual_seed(123)  # the same actions for both rollouts
    td = env.reset()
    out = []
    for _ in range(steps):
        td["action"] = torch.randint(0, 2, (8,), generator=gen)
        td = env.step(td)
        out.append(torch.cat([td["next", "observation"], td["next", "reward"]], -1))
        td = td["next"]
    return torch.stack(out)


def test_seeding():
    assert torch.equal(_rollout(1), _rollout(1))
    assert not torch.equal(_rollout(1), _rollout(2))
    # set_seed reseeds: two resets after the same seed start from the same states.
    env = DFRCEnv(Params(), batch_size=[8], seed=5)
    env.set_seed(9)
    s1 = env.reset()["state"].clone()
    env.set_seed(9)
    assert torch.equal(env.reset()["state"], s1)


def test_partial_reset_keeps_untouched_rows():
    env = DFRCEnv(Params(), batch_size=[4], seed=0)
    td = env.rollout(7, break_when_any_done=False)[..., -1]["next"].clone()
    before = td.clone()
    td["_reset"] = torch.tensor([[True], [False], [False], [True]])
    after = env.reset(td)
    keep = torch.tensor([False, True, True, False])
    assert torch.equal(after["state"][keep], before["state"][keep])
    assert torch.equal(after["step_count"][keep], before["step_count"][keep])
    assert bool((after["step_count"][~keep] == 0).all())
    assert bool((before["step_count"] == 7).all())


def test_truncation_not_termination():
    env = DFRCEnv(Params.from_overrides({"env.horizon": 3}), batch_size=[5], seed=0)
    td = env.rollout(3, break_when_any_done=False)
    trunc = td["next", "truncated"].squeeze(-1)
    assert torch.equal(trunc[:, :2], torch.zeros(5, 2, dtype=torch.bool))
    assert bool(trunc[:, 2].all())
    assert torch.equal(td["next", "done"], td["next", "truncated"])
    assert not bool(td["next", "terminated"].any())
    # the auto-reset after truncation starts a new episode
    long = env.rollout(7, break_when_any_done=False)
    assert long["step_count"][0, :7].squeeze(-1).tolist() == [0, 1, 2, 0, 1, 2, 0]


def _certain(event: bool) -> Params:
    p = 1.0 if event else 0.0
    probs = dict.fromkeys(("road", "weather", "speed", "object"), p)
    # distinct weights so that a swapped row cannot pass
    return Params.from_overrides(
        {"env.p0": probs, "env.p1": probs, "reward": {"r1": 3, "r2": 7, "r3": 11, "r4": 13}}
    )


ALL_FACTORS = list(itertools.product((0, 1), repeat=5))


@pytest.mark.parametrize("event", [False, True])
@pytest.mark.parametrize("action", [0, 1])
def test_reward_table_every_row(step_from, event, action):
    """Every row of eq. (3), in every factor configuration."""
    states = torch.tensor([state_index(5, *f) for f in ALL_FACTORS])
    nxt = step_from(_certain(event), states, action)
    c = torch.tensor([f[0] for f in ALL_FACTORS])
    b = torch.tensor([sum(f[1:]) for f in ALL_FACTORS], dtype=torch.float32)
    if action == 0 and not event:
        expected = torch.where(c == 0, 3.0, 7.0)
    elif action == 0 and event:
        expected = torch.full((32,), -11.0)
    elif action == 1 and event:
        expected = 13.0 * (b + 1)
    else:
        expected = torch.zeros(32)
    assert torch.equal(nxt["reward"].squeeze(-1), expected)
    assert bool((nxt["event"] == event).all())
    assert bool((nxt["missed"] == (event and action == 0)).all())


def test_queue_arithmetic_hand_cases():
    #            d   A  ν  D   sent d′ dropped
    cases = [
        (0, 0, 4, 10, 0, 0, 0),
        (3, 0, 4, 10, 3, 0, 0),
        (3, 2, 4, 10, 4, 1, 0),
        (0, 3, 4, 10, 3, 0, 0),  # arrivals may leave in the same step
        (9, 5, 2, 10, 2, 10, 2),
        (10, 1, 0, 10, 0, 10, 1),
        (10, 7, 4, 10, 4, 10, 3),
        (2, 1, 0, 10, 0, 3, 0),
    ]
    for d, a, nu, cap, sent, d2, drop in cases:
        out = queue_update(torch.tensor([d]), torch.tensor([a]), torch.tensor([nu]), cap)
        assert [int(x) for x in out] == [sent, d2, drop], (d, a, nu)


@pytest.mark.parametrize(("action", "c", "nu"), [(0, 0, 4), (0, 1, 2), (1, 0, 0), (1, 1, 0)])
def test_queue_in_env_without_arrivals(step_from, action, c, nu):
    params = Params.from_overrides({"env.arrival_rate": 0.0})
    d = torch.arange(11)
    nxt = step_from(params, state_index(d, c, 0, 0, 0, 0), action)
    got_d = nxt["observation"][:, 0].long()
    assert torch.equal(nxt["capacity"], torch.full((11,), nu))
    assert torch.equal(nxt["sent"], d.clamp(max=nu))
    assert torch.equal(got_d, (d - nu).clamp(min=0))
    assert torch.equal(nxt["dropped"], torch.zeros(11, dtype=torch.long))
    assert torch.equal(nxt["state"] >> 5, got_d)


def test_observation_matches_state(step_from):
    nxt = step_from(Params(), torch.arange(352), 0)
    assert torch.equal(nxt["observation"].long(), decode_state(nxt["state"]))


def test_reset_info_is_zero():
    td = DFRCEnv(Params(), batch_size=[16], seed=0).reset()
    for k in ("sent", "dropped", "capacity"):
        assert not bool(td[k].any())
    assert not bool(td["event"].any() | td["missed"].any())


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device on this machine")
def test_cuda_device():
    env = DFRCEnv(Params(), batch_size=[64], device="cuda", seed=0)
    check_env_specs(env, seed=0)


def test_unseeded_env_leaves_global_rng_alone():
    from irdrc.core import policies

    torch.manual_seed(123)
    expected = torch.rand(3)
    torch.manual_seed(123)
    DFRCEnv(Params(), batch_size=[2]).set_seed(None)
    policies.uniform_random()
    assert torch.equal(torch.rand(3), expected)


def test_grouped_dynamics_match_each_scenario_row_by_row():
    """Several scenarios in one batch: every row steps exactly as its own scenario's Dynamics.

    All rows draw the same uniforms in both runs (same generator seed, same batch size), so rows of
    group k must equal, bit for bit, the rows of a batch stepped with scenario k alone. The scenarios
    differ in every table (event probabilities, rewards, chains, link rates, arrival rate).
    """
    from irdrc.core.dynamics import Dynamics

    scenarios = [
        Params(),
        Params.from_overrides({"env.p1.speed": 1.0, "reward.r4": 50, "env.packets_good": 3}),
        Params.from_overrides(
            {"env.arrival_rate": 3.0, "env.stay_good.channel": 0.5, "reward.r1": 7}
        ),
    ]
    n = 3000
    state = torch.randint(0, 352, (n,), generator=torch.Generator().manual_seed(1))
    action = torch.randint(0, 2, (n,), generator=torch.Generator().manual_seed(2))
    group = torch.arange(n) % 3
    multi = Dynamics(scenarios).step(state, action, torch.Generator().manual_seed(3), group)
    for k, p in enumerate(scenarios):
        alone = Dynamics(p).step(state, action, torch.Generator().manual_seed(3))
        rows = group == k
        for field in (
            "state",
            "reward",
            "event",
            "missed",
            "sent",
            "dropped",
            "capacity",
            "arrivals",
        ):
            assert torch.equal(getattr(multi, field)[rows], getattr(alone, field)[rows]), (k, field)
    # Scenario 0 alone, with or without a group tensor, is the plain single-scenario step.
    a = Dynamics(scenarios[:1]).step(state, action, torch.Generator().manual_seed(4), group * 0)
    b = Dynamics(scenarios[0]).step(state, action, torch.Generator().manual_seed(4))
    assert torch.equal(a.state, b.state) and torch.equal(a.reward, b.reward)


def test_grouped_dynamics_reject_different_state_spaces():
    from irdrc.core.dynamics import Dynamics

    with pytest.raises(ValueError, match="queue_capacity"):
        Dynamics([Params(), Params.from_overrides({"env.queue_capacity": 5})])


# -- misused: each mistake answered by name --------------------------------------------------------


def _td(state, action, n=1):
    return TensorDict(
        {
            "state": torch.as_tensor(state).reshape(n),
            "action": torch.as_tensor(action).reshape(n),
            "step_count": torch.zeros(n, 1, dtype=torch.int64),
        },
        batch_size=[n],
    )


@pytest.mark.parametrize("action", [-1, 2, 0.5, 1.7])
def test_torchrl_env_refuses_actions_other_than_0_and_1(action):
    env = DFRCEnv(Params(), batch_size=[1], seed=0)
    with pytest.raises(ValueError, match=r"^action -?[\d.]+ must be 0 \(communication\)"):
        env.step(_td(0, action))


def test_torchrl_env_accepts_float_zero_and_one():
    env = DFRCEnv(Params(), batch_size=[2], seed=0)
    out = env.step(_td([0, 0], torch.tensor([0.0, 1.0]), n=2))["next"]
    assert out["capacity"].tolist() == [4, 0]


@pytest.mark.parametrize("state", [-1, 352, 10**6])
def test_torchrl_env_refuses_out_of_range_states(state):
    env = DFRCEnv(Params(), batch_size=[1], seed=0)
    with pytest.raises(ValueError, match=r"state must hold integer state indices in \[0, 352\)"):
        env.step(_td(state, 0))


def test_torchrl_env_step_before_reset_is_explained():
    env = DFRCEnv(Params(), batch_size=[1], seed=0)
    td = TensorDict({"action": torch.zeros(1, dtype=torch.int64)}, batch_size=[1])
    with pytest.raises(ValueError, match=r"call env\.reset\(\) first"):
        env.step(td)
