"""DQN's distributional option (``algo.distributional``): the support, the actor's mean values
and greedy actions, the loss and priorities, validation, and a run that checkpoints and resumes."""

from __future__ import annotations

import pytest
import torch
from conftest import assert_dqn_trains_and_resumes

from irdrc import DFRCEnv, Params
from irdrc.agents.dqn import DQNConfig, NetworkConfig
from irdrc.agents.dqn_variants import make_distributional, priority
from irdrc.agents.dqn_variants import values as action_values
from irdrc.agents.offpolicy import clip_and_step, greedy_table, make_buffer


def make_distributional_qnet(env, net, atoms, span):
    cfg = DQNConfig(distributional=True, atoms=atoms, support_span=span, network=net)
    return make_distributional(env, cfg)[0]


def learn(cfg, rb, loss, optimizer, seen):
    """``updates_per_batch`` of DQN's updates (as ``irdrc.agents.dqn.train`` makes them)."""
    for _ in range(cfg.updates_per_batch):
        sample = rb.sample()
        clip_and_step(loss, optimizer, cfg.max_grad_norm, loss(sample)["loss"])
        seen.append(priority(sample, cfg).clone())
        rb.update_priority(sample["index"], seen[-1])


def test_support_spans_the_reward_table_and_values_are_its_means():
    torch.manual_seed(0)
    env = DFRCEnv(Params(), batch_size=[4])
    qnet = make_distributional_qnet(env, NetworkConfig(hidden=(16,)), 11, 2.0)
    # the paper's largest |reward| is the missed-event penalty r3 = 50
    torch.testing.assert_close(qnet.support, torch.linspace(-100.0, 100.0, 11))
    big = DFRCEnv(Params.from_overrides({"reward.r4": 50, "env.p1.speed": 1.0}), batch_size=[4])
    assert make_distributional_qnet(big, NetworkConfig(), 5, 1.0).support.max() == 250.0
    logp = qnet(env.reset().clone())["action_value"]
    assert logp.shape == (4, 11, 2)
    torch.testing.assert_close(logp.exp().sum(-2), torch.ones(4, 2))
    values = action_values(qnet, env)
    assert values.shape == (env.num_states, 2)
    obs = env.dynamics.obs
    from tensordict import TensorDict

    td = qnet(TensorDict({"observation": obs}, batch_size=[obs.shape[0]]))
    expected = (td["action_value"].exp() * qnet.support[:, None]).sum(-2)
    torch.testing.assert_close(values, expected.detach())
    assert torch.equal(greedy_table(qnet, env), expected.argmax(-1))


def test_updates_move_the_mean_towards_the_reward_and_set_priorities():
    """A constant reward of +10 in every transition, γ = 0.5: each update's cross-entropy to the
    projected target pulls the means up from ≈ 0 (one-step returns from a near-zero start)."""
    torch.manual_seed(0)
    env = DFRCEnv(Params(), batch_size=[8])
    cfg = DQNConfig(
        distributional=True,
        gamma=0.5,
        atoms=21,
        support_span=1.0,
        batch_size=32,
        buffer_size=64,
        updates_per_batch=20,
        lr=1e-2,
        network=NetworkConfig(hidden=(16,)),
    )
    qnet, loss = make_distributional(env, cfg)
    rb, _ = make_buffer(cfg)
    td = env.rollout(8, break_when_any_done=False).reshape(-1)
    td["next", "reward"] = torch.full_like(td["next", "reward"], 10.0)
    rb.extend(td)
    before = action_values(qnet, env).mean()
    optimizer = torch.optim.Adam(loss.parameters(), lr=cfg.lr)
    seen = []
    learn(cfg, rb, loss, optimizer, seen)
    after = action_values(qnet, env).mean()
    assert after > before + 2.0
    assert len(seen) == cfg.updates_per_batch and all(p.shape == (32,) for p in seen)
    # the priorities are the per-sample cross-entropies the loss writes, not their square roots
    fixed = rb.sample()
    rb.sample = lambda *args, **kwargs: fixed
    seen.clear()
    one = DQNConfig(**{**cfg.__dict__, "updates_per_batch": 1})
    learn(one, rb, loss, optimizer, seen)
    torch.testing.assert_close(seen[0], fixed["td_error"].reshape(-1))
    assert bool((seen[0] > 0).all())


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"distributional": True, "n_steps": 3}, r"algo\.n_steps=3"),
        ({"distributional": True, "double_dqn": False}, r"algo\.double_dqn"),
        ({"atoms": 1}, r"algo\.atoms"),
        ({"support_span": 0.0}, r"algo\.support_span"),
        ({"distributional": "yes"}, r"algo\.distributional"),
    ],
)
def test_invalid_distributional_config(kwargs, match):
    with pytest.raises(ValueError, match=match):
        DQNConfig(**kwargs)


def test_distributional_trains_checkpoints_and_resumes():
    assert_dqn_trains_and_resumes(distributional=True, atoms=11)


def test_the_lagrangian_learner_refuses_distributional():
    from irdrc.agents.lagrangian import LagrangianConfig

    with pytest.raises(ValueError, match=r"algo\.distributional"):
        LagrangianConfig.from_dict({"distributional": True})


def test_the_distributional_learner_is_opt_in_everywhere():
    """``algo=dqn`` (yaml and dataclass), the paper profile and the Lagrangian learner all learn
    expected values unless ``algo.distributional=true`` is set."""
    from pathlib import Path

    from omegaconf import OmegaConf

    from irdrc.agents.lagrangian import LagrangianConfig

    conf = Path(__file__).resolve().parents[1] / "recipes" / "conf" / "algo"
    assert DQNConfig().distributional is False
    assert DQNConfig.from_dict(OmegaConf.load(conf / "dqn.yaml")).distributional is False
    assert OmegaConf.load(conf / "dqn_paper.yaml").algo.distributional is False
    assert not hasattr(LagrangianConfig().dqn, "distributional")  # refused there (test above)
