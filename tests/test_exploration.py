"""The Q-network's input encodings and temporally extended ε-greedy (εz-greedy)."""

from __future__ import annotations

import math

import pytest
import torch
from tensordict import TensorDict

from irdrc import DFRCEnv, Params
from irdrc.agents.dqn import DQNConfig, NetworkConfig, make_exploration, make_qnet


def _encoder(net: NetworkConfig):
    env = DFRCEnv(Params(), batch_size=[1])
    qnet = make_qnet(env, net)
    return env, next(m for m in qnet.modules() if type(m).__name__ in ("_OneHot", "_Scale"))


def test_onehot_encoding_one_input_per_level():
    env, enc = _encoder(NetworkConfig(encoding="onehot"))
    obs = env.dynamics.obs  # [S, 6]: d in 0..10, then five binary factors
    x = enc(obs)
    assert x.shape == (obs.shape[0], 11 + 5 * 2)
    assert torch.equal(x.sum(-1), torch.full((obs.shape[0],), 6.0))
    # the level of each entry is recovered from its block of inputs
    blocks = torch.split(x, [11, 2, 2, 2, 2, 2], dim=-1)
    recovered = torch.stack([b.argmax(-1) for b in blocks], -1).float()
    assert torch.equal(recovered, obs)


def test_scale_encoding_is_the_default_and_in_unit_range():
    env, enc = _encoder(NetworkConfig())
    x = enc(env.dynamics.obs)
    assert x.shape == env.dynamics.obs.shape and float(x.min()) == 0.0 and float(x.max()) == 1.0


def test_bad_encoding_named():
    with pytest.raises(ValueError, match=r"network\.encoding"):
        NetworkConfig(encoding="binary")


def _explorer(eps: float, max_duration: int, n_envs: int = 64):
    env = DFRCEnv(Params(), batch_size=[n_envs])
    cfg = DQNConfig(eps_start=eps, eps_end=eps, eps_duration_max=max_duration)
    return make_exploration(env, cfg)


def _greedy(n_envs: int) -> TensorDict:
    return TensorDict({"action": torch.zeros(n_envs, dtype=torch.long)}, [n_envs])


def test_hold_durations_follow_the_truncated_zeta_law():
    """With ε = 1 every env starts a new hold as soon as the last ends; the drawn lengths n must
    follow P(n) ∝ n^−2 on 1..N. 20 000+ holds: the standard error of P(n = 1) (≈ 0.63) is
    ≈ 0.0034 and of the mean (≈ 2.3, sd ≈ 3.5) ≈ 0.025, so 5σ bounds of 0.02 and 0.15 hold."""
    torch.manual_seed(0)
    n_max, n_envs = 20, 64
    m = _explorer(1.0, n_max, n_envs)
    lengths = []
    for _ in range(800):
        before = (
            m._remaining.clone()
            if m._remaining is not None
            else torch.zeros(n_envs, dtype=torch.long)
        )
        m(_greedy(n_envs))
        started = before == 0
        lengths += (m._remaining[started] + 1).tolist()
    lengths = torch.tensor(lengths, dtype=torch.float64)
    n = torch.arange(1, n_max + 1, dtype=torch.float64)
    p = n**-2 / (n**-2).sum()
    assert len(lengths) > 20_000
    assert abs(float((lengths == 1).double().mean()) - float(p[0])) < 0.02
    assert abs(float(lengths.mean()) - float((n * p).sum())) < 0.15
    assert int(lengths.max()) <= n_max


def test_held_action_is_constant_through_a_hold():
    torch.manual_seed(1)
    m = _explorer(0.2, 16, 32)
    prev_action, prev_remaining = None, None
    for _ in range(500):
        td = m(_greedy(32))
        act, rem = td["action"].clone(), m._remaining.clone()
        if prev_remaining is not None:
            continuing = prev_remaining > 0
            assert torch.equal(act[continuing], prev_action[continuing])
        prev_action, prev_remaining = act, rem


@pytest.mark.parametrize("max_duration", [1, 8])
def test_share_of_random_actions(max_duration):
    """A greedy action of 0 is replaced by radar only by exploration: the share of radar is half
    the share of exploring steps, ε / 2 for ε-greedy and ε·E[n] / (1 + ε·(E[n] − 1)) / 2 when
    holds last E[n] steps on average (a renewal argument). 64 000 draws: sd < 0.002, bound 0.01."""
    torch.manual_seed(2)
    eps = 0.1
    m = _explorer(eps, max_duration, 64)
    radar = torch.stack([m(_greedy(64))["action"] for _ in range(1000)]).double().mean()
    n = torch.arange(1, max_duration + 1, dtype=torch.float64)
    mean_n = float((n**-1).sum() / (n**-2).sum())
    expected = eps * mean_n / (1 + eps * (mean_n - 1)) / 2
    assert math.isclose(float(radar), expected, abs_tol=0.01)


def test_duration_checked():
    with pytest.raises(ValueError, match=r"algo\.eps_duration_max"):
        DQNConfig(eps_duration_max=0)


def test_policy_average_is_a_polyak_average_of_the_online_network():
    from irdrc.agents.dqn import _make_average, _update_average

    env = DFRCEnv(Params(), batch_size=[1])
    qnet = make_qnet(env, NetworkConfig())
    assert _make_average(qnet, DQNConfig()) is None  # average_tau = 0: off
    average = _make_average(qnet, DQNConfig(average_tau=0.25))
    before = [p.detach().clone() for p in average.parameters()]
    with torch.no_grad():
        for p in qnet.parameters():
            p.add_(1.0)
    _update_average(average, qnet, 0.25)
    for b, a, o in zip(before, average.parameters(), qnet.parameters(), strict=True):
        assert torch.allclose(a, 0.75 * b + 0.25 * o)
        assert not a.requires_grad


def test_policy_average_is_checkpointed_and_resumed():
    from irdrc.agents.dqn import train

    cfg = DQNConfig(total_frames=640, init_random_frames=128, buffer_size=640, batch_size=32)
    avg = DQNConfig(**{**cfg.__dict__, "average_tau": 0.01})
    first = train(Params(), avg, seed=0, eval_every_frames=320)
    assert "average" in first.state
    longer = DQNConfig(**{**avg.__dict__, "total_frames": 960})
    resumed = train(Params(), longer, seed=0, eval_every_frames=320, resume=first.state)
    assert resumed.env_steps >= 960
    # without the average the greedy policy comes from another network: the checkpoints differ
    plain = train(Params(), cfg, seed=0, eval_every_frames=320)
    assert "average" not in plain.state
