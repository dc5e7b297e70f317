"""The Q-network (scaled inputs, LayerNorm) and the exploration ladder: an ε per env row,
random actions held for several steps (εz-greedy), greedy when exploration is off."""

from __future__ import annotations

import math

import pytest
import torch
from tensordict import TensorDict
from torchrl.envs.utils import ExplorationType, set_exploration_type

from irdrc import DFRCEnv, Params
from irdrc.agents.dqn import DQNConfig
from irdrc.agents.offpolicy import (
    LadderExploration,
    NetworkConfig,
    Scale,
    eps_ladder,
    make_exploration,
    make_qnet,
)


def test_inputs_are_scaled_to_the_unit_range_and_hidden_layers_normalised():
    env = DFRCEnv(Params(), batch_size=[1])
    qnet = make_qnet(env, NetworkConfig())
    scale = next(m for m in qnet.modules() if isinstance(m, Scale))
    x = scale(env.dynamics.obs)
    assert x.shape == env.dynamics.obs.shape and float(x.min()) == 0.0 and float(x.max()) == 1.0
    norms = [m for m in qnet.modules() if isinstance(m, torch.nn.LayerNorm)]
    assert [n.normalized_shape for n in norms] == [(64,), (64,)]
    plain = make_qnet(env, NetworkConfig(hidden=(32, 16), layer_norm=False))
    assert not any(isinstance(m, torch.nn.LayerNorm) for m in plain.modules())


def test_ladder_is_log_uniform_from_eps_max_to_eps_min():
    eps = eps_ladder(5, 1.0, 0.01)
    assert torch.allclose(eps, torch.tensor([1.0, 10**-0.5, 0.1, 10**-1.5, 0.01]))
    assert torch.equal(eps_ladder(1, 0.1, 0.1), torch.tensor([0.1]))  # one row: eps_max
    assert torch.equal(eps_ladder(3, 0.5, 0.5), torch.full((3,), 0.5))
    assert torch.allclose(eps_ladder(3, 1.0, 0.0), torch.tensor([1.0, 0.5, 0.0]))
    with pytest.raises(ValueError, match=r"algo\.eps_min=0\.5 must be <= algo\.eps_max=0\.1"):
        DQNConfig(eps_max=0.1, eps_min=0.5)


def _explorer(eps: float | torch.Tensor, max_duration: int, rows: int = 64):
    eps = torch.full((rows,), eps) if isinstance(eps, float) else eps
    return LadderExploration(eps, max_duration)


def _greedy(rows: int) -> TensorDict:
    return TensorDict({"action": torch.zeros(rows, dtype=torch.long)}, [rows])


def test_hold_durations_follow_the_truncated_zeta_law():
    """With ε = 1 every row starts a new hold as soon as the last ends; the drawn lengths n must
    follow P(n) ∝ n^−2 on 1..N. 20 000+ holds: the standard error of P(n = 1) (≈ 0.63) is
    ≈ 0.0034 and of the mean (≈ 2.3, sd ≈ 3.5) ≈ 0.025, so 5σ bounds of 0.02 and 0.15 hold."""
    torch.manual_seed(0)
    n_max, rows = 20, 64
    m = _explorer(1.0, n_max, rows)
    lengths = []
    for _ in range(800):
        before = m.remaining.clone() if m.remaining is not None else torch.zeros(rows).long()
        m(_greedy(rows))
        started = before == 0
        lengths += (m.remaining[started] + 1).tolist()
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
        act, rem = td["action"].clone(), m.remaining.clone()
        if prev_remaining is not None:
            continuing = prev_remaining > 0
            assert torch.equal(act[continuing], prev_action[continuing])
        prev_action, prev_remaining = act, rem


@pytest.mark.parametrize("max_duration", [1, 8])
def test_share_of_random_actions_per_row(max_duration):
    """A greedy action of 0 is replaced by radar only by exploration: the share of radar in a row
    is half its share of exploring steps, ε / 2 for ε-greedy and ε·E[n] / (1 + ε·(E[n] − 1)) / 2
    when holds last E[n] steps on average (a renewal argument). Two halves of 64 rows at ε = 0.1 and
    0.4, 1 000 steps: 32 000 draws per half, sd < 0.003 (holds correlate draws, at most by E[n]
    ≈ 1.9 in variance), bound 0.015."""
    torch.manual_seed(2)
    eps = torch.cat([torch.full((32,), 0.1), torch.full((32,), 0.4)])
    m = _explorer(eps, max_duration, 64)
    radar = torch.stack([m(_greedy(64))["action"] for _ in range(1000)]).double()
    n = torch.arange(1, max_duration + 1, dtype=torch.float64)
    mean_n = float((n**-1).sum() / (n**-2).sum())
    for rows, e in ((slice(0, 32), 0.1), (slice(32, 64), 0.4)):
        expected = e * mean_n / (1 + e * (mean_n - 1)) / 2
        assert math.isclose(float(radar[:, rows].mean()), expected, abs_tol=0.015)


def test_a_row_explores_at_its_own_rate_in_a_collector_batch_shape():
    """The env's rows are the ladder's rows; a [rows, 1] action (one step) uses each row's ε."""
    env = DFRCEnv(Params(), batch_size=[4])
    m = make_exploration(env, DQNConfig(num_envs=4, frames_per_batch=4, eps_min=0.0))
    assert torch.allclose(m.eps, torch.tensor([1.0, 2 / 3, 1 / 3, 0.0]))
    torch.manual_seed(3)
    td = TensorDict({"action": torch.zeros(4, 1, dtype=torch.long)}, [4, 1])
    radar = torch.stack([m(td.clone())["action"] for _ in range(2000)]).double().mean(0)
    assert float(radar[3]) == 0.0 and float(radar[0]) > 0.4  # ε = 0 never explores


def test_greedy_when_exploration_is_off():
    m = _explorer(1.0, 8, 16)
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        assert int(m(_greedy(16))["action"].sum()) == 0


def test_duration_checked():
    with pytest.raises(ValueError, match=r"algo\.eps_duration_max"):
        DQNConfig(eps_duration_max=0)
