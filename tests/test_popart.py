"""PopArt in DQN (``algo.popart``): the TD targets it normalises, the output-preserving rescale,
the statistics, the loss in normalised units, the checkpoint and the refusals."""

from __future__ import annotations

import math
from pathlib import Path

import pytest
import torch
from omegaconf import OmegaConf
from tensordict import TensorDict

from irdrc import Params
from irdrc.agents import dqn as D
from irdrc.agents.lagrangian import LagrangianConfig
from irdrc.core.env import DFRCEnv

ROOT = Path(__file__).resolve().parents[1]


def _setup(seed: int = 0) -> tuple[DFRCEnv, D.QValueActor, D.DQNLoss]:
    torch.manual_seed(seed)
    env = DFRCEnv(Params(), batch_size=[2], seed=seed)
    cfg = D.DQNConfig(popart=0.1, network=D.NetworkConfig(hidden=(16, 16)))
    qnet, _ = D.make_qnets(env, cfg.network, 1, popart=True)
    loss = D.make_loss(qnet, env, cfg)
    # A target network that differs from the online one, as it does during training.
    with torch.no_grad():
        for p in loss.target_value_network_params.values(True, True):
            if p.dtype.is_floating_point and p.dim() > 0:
                p.add_(0.3 * torch.randn_like(p))
    return env, qnet, loss


def _sample(env: DFRCEnv, n: int = 64, seed: int = 1) -> TensorDict:
    """n transitions between random states of the env's table, rewards on the paper's scale."""
    g = torch.Generator().manual_seed(seed)
    obs = env.dynamics.obs
    i = torch.randint(obs.shape[0], (n,), generator=g)
    j = torch.randint(obs.shape[0], (n,), generator=g)
    return TensorDict(
        {
            "observation": obs[i],
            "action": torch.randint(2, (n,), generator=g),
            ("next", "observation"): obs[j],
            ("next", "reward"): 20.0 * torch.randn(n, 1, generator=g) - 3.0,
            ("next", "terminated"): torch.zeros(n, 1, dtype=torch.bool),
            ("next", "truncated"): torch.zeros(n, 1, dtype=torch.bool),
            ("next", "done"): torch.zeros(n, 1, dtype=torch.bool),
        },
        batch_size=[n],
    )


def _values(loss: D.DQNLoss, env: DFRCEnv, target: bool = False) -> torch.Tensor:
    params = loss.target_value_network_params if target else loss.value_network_params.data
    with torch.no_grad(), params.to_module(loss.value_network):
        return D.action_values(loss.value_network, env)


def test_td_targets_are_the_ones_torchrl_s_dqn_loss_regresses_on():
    """DQNLoss writes (Q(s, a) − y)² as its td_error; our targets must give the same numbers."""
    env, qnet, loss = _setup()
    sample = _sample(env)
    y = D.td_targets(loss, sample, 0.99)
    loss(sample)
    with torch.no_grad():
        pred = qnet(sample.select("observation").clone())["action_value"]
    pred = pred.gather(-1, sample["action"].unsqueeze(-1)).squeeze(-1)
    torch.testing.assert_close((pred - y).pow(2), sample["td_error"].reshape(-1))


def test_art_preserves_every_output_and_the_statistics_follow_the_targets():
    env, _, loss = _setup()
    before_online, before_target = _values(loss, env), _values(loss, env, target=True)
    first = _sample(env, seed=1)
    y1 = D.td_targets(loss, first, 0.99)
    w = torch.rand(y1.shape[0], generator=torch.Generator().manual_seed(3)) + 0.5
    sigma1 = D.popart_update(loss, y1, 0.1, w)
    # The first update averages with step 1: the weighted mean and standard deviation of the batch.
    wn = (w / w.sum()).double()
    mean1 = float((wn * y1.double()).sum())
    second1 = float((wn * y1.double().pow(2)).sum())
    assert sigma1 == pytest.approx(math.sqrt(second1 - mean1**2), rel=1e-6)
    assert sigma1 > 5  # the rewards' spread is 20, far from the initial σ = 1
    # Every Q-value of both networks is unchanged (to float32 rounding of σ·n + μ).
    torch.testing.assert_close(_values(loss, env), before_online, atol=1e-4, rtol=1e-5)
    torch.testing.assert_close(_values(loss, env, target=True), before_target, atol=1e-4, rtol=1e-5)
    # The second update: step max(0.1, 1/2) = 0.5, unweighted.
    second = _sample(env, seed=2)
    y2 = D.td_targets(loss, second, 0.99).double()
    sigma2 = D.popart_update(loss, y2, 0.1)
    mean2 = 0.5 * mean1 + 0.5 * float(y2.mean())
    nu2 = 0.5 * second1 + 0.5 * float(y2.pow(2).mean())
    assert sigma2 == pytest.approx(math.sqrt(nu2 - mean2**2), rel=1e-6)
    online = loss.value_network_params.flatten_keys(".")
    target = loss.target_value_network_params.flatten_keys(".")
    keys = list(online.keys())
    for key in [k for k in keys if k.endswith(("mu", "nu", "sigma", "count"))]:
        assert float(online[key]) == float(target[key])
    assert float(online[next(k for k in keys if k.endswith("mu"))]) == pytest.approx(
        mean2, rel=1e-6
    )
    assert float(online[next(k for k in keys if k.endswith("count"))]) == 2.0
    torch.testing.assert_close(_values(loss, env), before_online, atol=1e-4, rtol=1e-5)
    # After 1/rate updates the step is the rate itself (an exponential average).
    for k in range(20):
        D.popart_update(loss, D.td_targets(loss, _sample(env, seed=10 + k), 0.99), 0.1)
    torch.testing.assert_close(_values(loss, env), before_online, atol=1e-3, rtol=1e-4)


def test_the_gradient_step_is_the_loss_divided_by_sigma_squared(monkeypatch):
    """With plain SGD (lr 1), the change of every parameter in one update equals the gradient of
    DQNLoss's loss (in the values' units) divided by σ², where σ is the one set before the loss."""
    records: list[dict] = []
    original = D.DQNLoss.forward

    def spy(self, sample):
        out = original(self, sample)
        params = [p for p in self.value_network_params.values(True, True) if p.requires_grad]
        grads = torch.autograd.grad(out["loss"], params, retain_graph=True)
        flat = self.value_network_params.flatten_keys(".")
        keys = list(flat.keys())
        sigma = float(flat[next(k for k in keys if k.endswith("sigma"))])
        records.append(
            {
                "before": [p.detach().clone() for p in params],
                "params": params,
                "grads": grads,
                "sigma": sigma,
            }
        )
        return out

    monkeypatch.setattr(D.DQNLoss, "forward", spy)
    env, _, loss = _setup()
    cfg = D.DQNConfig(
        popart=0.1, updates_per_batch=1, batch_size=32, max_grad_norm=0.0, prioritized=False
    )
    rb, _ = D.make_buffer(cfg)
    rb.extend(_sample(env, n=64))
    optimizer = torch.optim.SGD(loss.parameters(), lr=1.0)
    target = D.make_target_updater(loss, cfg)
    D._learn(cfg, rb, loss, optimizer, target)
    (rec,) = records
    assert rec["sigma"] > 5  # the statistics moved before the loss was taken
    for before, p, g in zip(rec["before"], rec["params"], rec["grads"], strict=True):
        torch.testing.assert_close(before - p.detach(), g / rec["sigma"] ** 2)


def test_training_keeps_the_statistics_in_the_checkpoint_and_resumes_them():
    base = dict(
        total_frames=320,
        init_random_frames=64,
        buffer_size=480,
        batch_size=32,
        popart=0.01,
        network=D.NetworkConfig(hidden=(16,)),
    )
    run = D.train(Params(), D.DQNConfig(**base), seed=0, eval_every_frames=160)
    state = {k: v for k, v in run.state["loss"].items() if k.endswith(("sigma", "count"))}
    counts = [float(v) for k, v in state.items() if k.endswith("count")]
    assert counts == [run.updates, run.updates]  # one statistics update per gradient update
    assert all(float(v) > 1.5 for k, v in state.items() if k.endswith("sigma"))
    longer = D.DQNConfig(**{**base, "total_frames": 480})
    resumed = D.train(Params(), longer, seed=0, eval_every_frames=160, resume=run.state)
    counts = [float(v) for k, v in resumed.state["loss"].items() if k.endswith("count")]
    assert counts == [resumed.updates, resumed.updates] and resumed.updates > run.updates
    plain = D.train(Params(), D.DQNConfig(**{**base, "popart": 0.0}), seed=0)
    assert not [k for k in plain.state["loss"] if k.endswith("sigma")]


def test_off_by_default_and_listed_in_the_config():
    conf = ROOT / "recipes" / "conf" / "algo"
    assert D.DQNConfig().popart == 0.0
    assert OmegaConf.load(conf / "dqn.yaml").popart == 0.0
    assert D.DQNConfig.from_dict({"popart": 0.001}).popart == 0.001


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"popart": -0.1}, r"algo\.popart"),
        ({"popart": 1.0}, r"algo\.popart"),
        ({"popart": 0.01, "distributional": True}, r"algo\.distributional"),
        ({"popart": 0.01, "ensemble": 3}, r"algo\.ensemble"),
        ({"popart": 0.01, "average_tau": 0.01}, r"algo\.average_tau"),
        ({"popart": 0.01, "reward_scale": 0.5}, r"algo\.reward_scale"),
    ],
)
def test_popart_checked(kwargs, match):
    with pytest.raises(ValueError, match=match):
        D.DQNConfig(**kwargs)


def test_the_lagrangian_learner_refuses_popart():
    with pytest.raises(ValueError, match=r"algo\.popart"):
        LagrangianConfig.from_dict({"popart": 0.001})
