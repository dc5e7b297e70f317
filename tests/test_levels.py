"""``DistinctRows``: one pass per distinct observation gives the plain network's numbers bit for
bit, and falls back to the plain pass wherever it cannot apply."""

from __future__ import annotations

import pytest
import torch

from irdrc import Params
from irdrc.agents.configs import DQNConfig
from irdrc.agents.levels import DistinctRows, mixed_radix
from irdrc.agents.offpolicy import make_mlp, make_qnet, observation_top
from irdrc.core.env import DFRCEnv


def _nets(params: Params) -> tuple[torch.Tensor, torch.nn.Sequential, DistinctRows]:
    env = DFRCEnv(params, batch_size=[2])
    torch.manual_seed(0)
    plain = make_mlp(env, DQNConfig().network, 2)
    distinct = DistinctRows(*plain, high=observation_top(env))
    return env.dynamics.obs.float(), plain, distinct


def test_mixed_radix_codes_every_observation_once():
    env = DFRCEnv(Params(), batch_size=[2])
    radix, codes = mixed_radix(observation_top(env))
    code = (env.dynamics.obs.long() * radix).sum(-1)
    assert code.unique().numel() == len(env.dynamics.obs)
    assert int(code.min()) >= 0 and int(code.max()) < codes
    with pytest.raises(ValueError, match="must be >= 0"):
        mixed_radix(torch.tensor([2.0, -1.0]))


@pytest.mark.parametrize("draw", [None, 1167, 3888, 4061])
def test_distinct_rows_equal_the_plain_network_bit_for_bit(draw):
    from irdrc.experiments.random_scenarios import draw_overrides

    params = Params() if draw is None else Params.from_overrides(draw_overrides(draw))
    obs, plain, distinct = _nets(params)
    gen = torch.Generator().manual_seed(1)
    for rows in (distinct.codes + 1, 4 * distinct.codes, 8000):
        x = obs[torch.randint(0, len(obs), (rows,), generator=gen)]
        with torch.no_grad():
            assert torch.equal(distinct(x), plain(x)), rows


def test_distinct_rows_fall_back_where_they_cannot_apply(monkeypatch):
    obs, _plain, distinct = _nets(Params())
    calls = []
    real = torch.nn.Sequential.forward

    def spy(self, x):
        if self is distinct:
            calls.append(x.shape[0])
        return real(self, x)

    monkeypatch.setattr(torch.nn.Sequential, "forward", spy)
    many = obs[torch.arange(4 * len(obs)) % len(obs)]
    with torch.no_grad():
        distinct(many)  # applies: one pass over the distinct observations
        assert calls == [len(obs)]
        calls.clear()
        distinct(obs)  # no more rows than codes: the plain pass
        distinct(many + 0.5)  # not integer levels
        distinct(many + 100)  # above high
        assert calls == [len(obs), len(many), len(many)]
    calls.clear()
    out = distinct(many)  # gradients on (the loss): the plain pass, differentiable
    assert calls == [len(many)] and out.requires_grad


def test_dqn_q_network_is_distinct_rows_with_the_plain_keys():
    env = DFRCEnv(Params(), batch_size=[2])
    bodies = [
        m for m in make_qnet(env, DQNConfig().network).modules() if isinstance(m, DistinctRows)
    ]
    assert len(bodies) == 1
    plain = make_mlp(env, DQNConfig().network, 2)
    assert list(bodies[0].state_dict()) == list(plain.state_dict())  # checkpoints load as before
