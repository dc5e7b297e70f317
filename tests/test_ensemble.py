"""DQN's ensemble of Q-heads (``algo.ensemble``): shapes, the mean that acts, per-head targets,
bootstrap masks, priorities, validation, and a run that checkpoints and resumes."""

from __future__ import annotations

import pytest
import torch
from conftest import assert_dqn_trains_and_resumes
from tensordict import TensorDict

from irdrc import DFRCEnv, Params
from irdrc.agents.dqn import (
    DQNConfig,
    NetworkConfig,
    _per_head,
    action_values,
    greedy_table,
    make_loss,
    make_qnets,
)

SMALL = Params.from_overrides(queue_capacity=5)


def test_one_head_is_the_plain_q_network():
    env = DFRCEnv(SMALL, batch_size=[4])
    acting, trained = make_qnets(env, NetworkConfig(hidden=(16,)), 1)
    assert acting is trained


def test_acting_values_are_the_mean_of_independent_heads():
    torch.manual_seed(0)
    env = DFRCEnv(SMALL, batch_size=[4])
    acting, trained = make_qnets(env, NetworkConfig(hidden=(16,)), 3)
    # the two actors share one set of parameters
    assert {id(p) for p in acting.parameters()} == {id(p) for p in trained.parameters()}
    obs = env.dynamics.obs
    per_head = trained(
        TensorDict({"observation": obs[:, None].expand(-1, 3, -1)}, batch_size=[obs.shape[0], 3])
    )["action_value"]
    assert per_head.shape == (env.num_states, 3, 2)
    # independently initialised heads disagree
    assert not torch.allclose(per_head[:, 0], per_head[:, 1])
    mean = action_values(acting, env)
    torch.testing.assert_close(mean, per_head.mean(1).detach())
    table = greedy_table(acting, env)
    assert torch.equal(table, mean.argmax(-1))


def test_loss_trains_each_head_against_its_own_target():
    """With distinct per-head predictions on one transition the loss is the mean of the heads'
    own squared TD errors (each head's double-DQN target from its own networks)."""
    torch.manual_seed(1)
    env = DFRCEnv(SMALL, batch_size=[2])
    cfg = DQNConfig(ensemble=3, gamma=0.9)
    _, trained = make_qnets(env, NetworkConfig(hidden=(8,)), 3)
    loss = make_loss(trained, env, cfg)
    obs = env.dynamics.obs
    td = TensorDict(
        {
            "observation": obs[:2],
            "action": torch.tensor([0, 1]),
            "next": {
                "observation": obs[2:4],
                "reward": torch.tensor([[1.0], [-2.0]]),
                "done": torch.zeros(2, 1, dtype=torch.bool),
                "terminated": torch.zeros(2, 1, dtype=torch.bool),
            },
        },
        batch_size=[2],
    )
    sample = _per_head(td, cfg)
    assert sample.batch_size == (2, 3)
    out = loss(sample)
    with torch.no_grad():
        q = trained(sample.clone())["action_value"]  # [2, 3, 2]
        q_next = trained(sample["next"].clone())["action_value"]
    # the target copy equals the online network at the start
    pred = q.gather(-1, sample["action"][..., None])[..., 0]
    target = sample["next", "reward"][..., 0] + 0.9 * q_next.max(-1).values
    expected = ((pred - target) ** 2).mean()
    torch.testing.assert_close(out["loss"], expected)
    torch.testing.assert_close(sample["td_error"][..., 0], (pred - target) ** 2)


def test_bootstrap_mask_keeps_the_set_fraction():
    cfg = DQNConfig(ensemble=4, ensemble_mask=0.3)
    td = TensorDict({"priority_weight": torch.full((5000,), 2.0)}, batch_size=[5000])
    out = _per_head(td, cfg)
    weight = out["priority_weight"]
    assert set(weight.unique().tolist()) <= {0.0, 2.0}
    kept = (weight > 0).float().mean().item()
    # 20 000 Bernoulli(0.3) draws: standard error √(0.3·0.7/20 000) ≈ 0.0032; 0.02 is > 6 of them.
    assert abs(kept - 0.3) < 0.02
    # without a priority weight (uniform replay) the mask alone is the weight
    out = _per_head(TensorDict({}, batch_size=[100]), cfg)
    assert set(out["priority_weight"].unique().tolist()) <= {0.0, 1.0}
    # mask 1: no weight key is added
    assert "priority_weight" not in _per_head(TensorDict({}, batch_size=[3]), DQNConfig(ensemble=2))


@pytest.mark.parametrize(
    ("kwargs", "key"),
    [({"ensemble": 0}, "algo.ensemble"), ({"ensemble_mask": 0.0}, "algo.ensemble_mask")],
)
def test_invalid_ensemble_config(kwargs, key):
    with pytest.raises(ValueError, match=key.replace(".", r"\.")):
        DQNConfig(**kwargs)


def test_ensemble_trains_checkpoints_and_resumes():
    assert_dqn_trains_and_resumes(ensemble=3, ensemble_mask=0.5)


def test_the_lagrangian_learner_refuses_an_ensemble():
    from irdrc.agents.lagrangian import LagrangianConfig

    with pytest.raises(ValueError, match=r"algo\.ensemble=3"):
        LagrangianConfig.from_dict({"ensemble": 3})
    assert LagrangianConfig.from_dict({"ensemble": 1}).dqn.ensemble == 1
