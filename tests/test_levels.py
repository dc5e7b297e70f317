"""``DistinctRows``: one pass per distinct observation gives the plain network's outputs bit for
bit and its gradients up to the order of a sum, and falls back to the plain pass wherever it
cannot apply."""

from __future__ import annotations

import json

import pytest
import torch

from irdrc import Params
from irdrc.agents.configs import DQNConfig
from irdrc.agents.levels import DistinctRows, mixed_radix
from irdrc.agents.offpolicy import PolyakUpdate, make_mlp, make_qnet, observation_top
from irdrc.core.env import DFRCEnv


def _nets(params: Params) -> tuple[torch.Tensor, torch.nn.Sequential, DistinctRows]:
    env = DFRCEnv(params, batch_size=[2])
    torch.manual_seed(0)
    plain = make_mlp(env, DQNConfig().network, 2)
    distinct = DistinctRows(*plain, high=observation_top(env))
    return env.dynamics.obs.float(), plain, distinct


def _spy_passes(monkeypatch, module: torch.nn.Module) -> list[int]:
    """The rows of every plain ``nn.Sequential`` pass ``module`` makes, as they happen."""
    rows: list[int] = []
    real = torch.nn.Sequential.forward

    def spy(self, x):
        if self is module:
            rows.append(x.shape[0])
        return real(self, x)

    monkeypatch.setattr(torch.nn.Sequential, "forward", spy)
    return rows


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
    from irdrc.bench.random_scenarios import draw_overrides

    params = Params() if draw is None else Params.from_overrides(draw_overrides(draw))
    obs, plain, distinct = _nets(params)
    gen = torch.Generator().manual_seed(1)
    for rows in (distinct.codes + 1, 4 * distinct.codes, 8000):
        x = obs[torch.randint(0, len(obs), (rows,), generator=gen)]
        with torch.no_grad():
            assert torch.equal(distinct(x), plain(x)), rows


def test_distinct_rows_fall_back_where_they_cannot_apply(monkeypatch):
    obs, _plain, distinct = _nets(Params())
    calls = _spy_passes(monkeypatch, distinct)
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
    out = distinct(many)  # gradients on (the loss): the distinct pass too, differentiable
    assert calls == [len(obs)] and out.requires_grad


def test_distinct_rows_reuse_a_split_only_for_the_same_unchanged_input():
    """A loss's two passes over one tensor split it once; a tensor changed in place, or another
    tensor, is split again (a stale split would give row 0 the output of obs[0])."""
    obs, plain, distinct = _nets(Params())
    many = obs[torch.arange(4 * len(obs)) % len(obs)]
    first = distinct._distinct(many)
    assert distinct._distinct(many) is first
    with torch.no_grad():
        assert torch.equal(distinct(many), plain(many))
        many[0] = obs[7]  # in place: a new version of the same tensor
        assert distinct._distinct(many) is not first
        assert torch.equal(distinct(many), plain(many))
        again = many.clone()
        assert distinct._distinct(again) is not distinct._distinct(many)
        assert torch.equal(distinct(again), plain(again))


def test_dqn_q_network_is_distinct_rows_with_the_plain_keys():
    env = DFRCEnv(Params(), batch_size=[2])
    bodies = [
        m for m in make_qnet(env, DQNConfig().network).modules() if isinstance(m, DistinctRows)
    ]
    assert len(bodies) == 1
    plain = make_mlp(env, DQNConfig().network, 2)
    assert list(bodies[0].state_dict()) == list(plain.state_dict())  # checkpoints load as before


def test_a_dqn_loss_through_distinct_rows_is_the_plain_loss(monkeypatch):
    """All three of DQNLoss's passes (the one autograd records, and the two over the next
    observations through detached and target parameters) take the distinct rows; the loss is the
    plain network's bit for bit, and every gradient is the plain one summed in another order."""
    import copy

    from tensordict import TensorDict
    from torchrl.modules import QValueActor
    from torchrl.objectives import DQNLoss

    env = DFRCEnv(Params(), batch_size=[2])
    torch.manual_seed(0)
    fast = make_qnet(env, DQNConfig().network)
    body = next(m for m in fast.modules() if isinstance(m, DistinctRows))
    plain = QValueActor(
        module=torch.nn.Sequential(*copy.deepcopy(list(body))),
        in_keys=["observation"],
        spec=env.action_spec_unbatched,
    )
    obs = env.dynamics.obs.float()
    gen = torch.Generator().manual_seed(2)
    rows = 4 * len(obs)
    batch = TensorDict(
        {
            "observation": obs[torch.randint(0, len(obs), (rows,), generator=gen)],
            "action": torch.randint(0, 2, (rows,), generator=gen),
            ("next", "observation"): obs[torch.randint(0, len(obs), (rows,), generator=gen)],
            ("next", "reward"): torch.randn(rows, 1, generator=gen),
            ("next", "done"): torch.zeros(rows, 1, dtype=torch.bool),
            ("next", "terminated"): torch.zeros(rows, 1, dtype=torch.bool),
        },
        batch_size=[rows],
    )
    passes = _spy_passes(monkeypatch, body)
    losses = []
    for net in (fast, plain):
        loss = DQNLoss(
            net,
            loss_function="l2",
            delay_value=True,
            double_dqn=True,
            action_space=env.action_spec_unbatched,
        )
        loss.make_value_estimator(gamma=0.99)
        PolyakUpdate(loss, tau=0.02)  # as DQN builds it (the loss expects an updater)
        value = loss(batch.clone())["loss"]
        value.backward()
        grads = [p.grad.clone() for p in loss.parameters() if p.grad is not None]
        assert len(grads) == 10  # weight and bias of the three Linear and two LayerNorm layers
        losses.append((value.detach(), grads))
    # three passes, each over the batch's distinct observations (fewer than its rows)
    assert len(passes) == 3 and all(n < rows for n in passes), passes
    assert torch.equal(losses[0][0], losses[1][0])
    for a, b in zip(losses[0][1], losses[1][1], strict=True):
        # float32 sums of 1 408 rows' terms in two orders: they differ in the last bits alone
        # (relative 1e-5 is ~100 float32 ulps; a wrong gradient, e.g. rows not summed, is off by
        # whole multiples)
        assert not torch.equal(a, torch.zeros_like(a))
        torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-7)


def test_solve_plays_the_levels_optimum_by_monte_carlo(tmp_path):
    """``solve.py env.actions=levels`` plays its optimum by Monte-Carlo too (the row was left
    out: the table policy took comm/radar only), and the simulator agrees with the exact episodic
    metrics. Tolerance: 4 of the row's 95 % half-widths (1.96 standard errors each), about 8
    standard errors, which a correct simulator exceeds with probability ~1e-15 per metric; the
    levels table played as comm/radar (radar fraction 0.08 against 0.43) is ~100 half-widths off."""
    from conftest import run_recipe

    args = ["env.actions=levels", "eval.mc_episodes=64", "eval.mc_num_envs=64"]
    assert run_recipe("solve", tmp_path, *args) == 0
    table = json.loads((tmp_path / "summary.json").read_text())["table"]
    mc, exact = table["optimal (Monte-Carlo)"], table["optimal (episodic)"]
    for key in ("avg_reward", "radar_fraction", "miss_detection"):
        assert abs(mc[key] - exact[key]) < 4 * mc["ci95"][key], key
