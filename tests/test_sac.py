"""SAC on the radar share (MODEL.md § D, ``recipes/sac.py``): its run scored exactly, its actor's
span beyond [0, 1], its refusals, and (slow) that it learns — and fails without the sensing curve."""

from __future__ import annotations

import csv
import json

import pytest
import torch
from conftest import run_script

from irdrc.core.exact import stationary_metrics
from irdrc.core.exact.continuum import policy_model
from irdrc.core.params import Params


def params(**over) -> Params:
    return Params.from_overrides(over)


TINY_SAC = [
    "algo.num_envs=50",
    "algo.frames_per_batch=100",
    "algo.total_frames=2000",
    "algo.init_random_frames=200",
    "algo.batch_size=64",
    "algo.updates_per_batch=1",
    "algo.buffer_size=4000",
    "eval.every_frames=1000",
    "checkpoint.every_frames=1000",
    "network=small",
    "progress=false",
]


def run_share_recipe(script: str, tiny: list[str], out) -> dict:
    """Run a radar-share learner's recipe (``recipes/sac.py``, ``ppo.py``) on ``tiny`` settings
    into ``out``: exit 0, the optimum over ρ printed, a share per state in policy.csv, an
    evaluation every 1 000 env steps, and ``summary.json``'s learned metrics the exact metrics of
    the shares policy.csv holds. Returns the summary."""
    r = run_script(script, *tiny, f"hydra.run.dir={out}")
    assert r.returncode == 0, r.stderr[-2000:]
    assert r.stdout.startswith("scenario=paper: optimum over ρ ∈ [0, 1] 1.0586 per step")
    rows = list(csv.DictReader((out / "policy.csv").open()))
    assert list(rows[0])[-1] == "rho" and all(0 <= float(x["rho"]) <= 1 for x in rows)
    metrics = list(csv.DictReader((out / "metrics.csv").open()))
    assert [int(m["env_steps"]) for m in metrics] == [0, 1000, 2000]
    summary = json.loads((out / "summary.json").read_text())
    rho = torch.tensor([float(x["rho"]) for x in rows], dtype=torch.float64)
    p = params(**{"env.actions": "continuous"})
    exact = stationary_metrics(policy_model(p, rho), torch.zeros(352, dtype=torch.int64))
    assert summary["metrics"]["avg_reward"] == pytest.approx(exact.avg_reward, abs=1e-6)
    return summary


@pytest.mark.e2e
def test_sac_runs_scored_exactly_and_writes_its_shares(tmp_path):
    out = tmp_path / "run"
    summary = run_share_recipe("recipes/sac.py", TINY_SAC, out)
    assert summary["optimal"]["avg_reward"] == pytest.approx(1.0586, abs=5e-5)
    assert (out / "checkpoint.pt").is_file() and summary["interrupted"] is False


def test_sacs_actor_reaches_the_ends_unsaturated_and_the_env_sees_shares_in_0_1():
    """The actor's TanhNormal spans [−m, 1 + m] and is clipped to [0, 1]: a location where tanh is
    0.85 (far from its saturation) is already the share 1, where on [0, 1] it is 0.925; the
    critics and the collector see the clipped share; a checkpoint keeps its margin, one without
    it (its actor spanned [0, 1]) is read with 0."""
    from irdrc.agents.configs.continuous import SACConfig
    from irdrc.agents.sac import SHARE_MARGIN, checkpoint_margin, make_actor, make_critic
    from irdrc.agents.shares import ShareLadder, share_table
    from irdrc.core.env import DFRCEnv

    env = DFRCEnv(params(**{"env.actions": "continuous"}), batch_size=[1])
    cfg = SACConfig()
    shares = {}
    for margin in (SHARE_MARGIN, 0.0):
        actor = make_actor(env, cfg, margin)
        last = [m for m in actor.modules() if isinstance(m, torch.nn.Linear)][-1]
        with torch.no_grad():
            last.weight.zero_()
            last.bias.copy_(torch.tensor([float(torch.atanh(torch.tensor(0.85))), -3.0]))
        shares[margin] = share_table(actor, env)
    assert bool((shares[SHARE_MARGIN] == 1.0).all())
    assert torch.allclose(shares[0.0], torch.full((352,), 0.925, dtype=torch.float64), atol=1e-6)
    critic = make_critic(env, cfg)
    obs = env.dynamics.obs[:4]
    q = [critic(observation=obs, action=torch.full((4, 1), a)) for a in (1.0, 1.08, 0.0, -0.05)]
    assert torch.equal(q[0], q[1]) and torch.equal(q[2], q[3])
    out = ShareLadder(2, 0.0, 0.0)(torch.tensor([[1.07], [-0.02]]))
    assert out.tolist() == [[1.0], [0.0]]
    assert checkpoint_margin(None) == SHARE_MARGIN
    assert checkpoint_margin({"share_margin": 0.1}) == 0.1 and checkpoint_margin({}) == 0.0


def test_sac_refuses_a_discrete_action_space(tmp_path):
    r = run_script("recipes/sac.py", "env.actions=binary", f"hydra.run.dir={tmp_path / 'r'}")
    assert r.returncode == 2
    assert r.stderr.startswith("error: env.actions=binary: SAC acts on")
    assert len(r.stderr.splitlines()) == 1 and not (tmp_path / "r").exists()


@pytest.mark.slow
def test_sac_reaches_the_continuum_optimum_and_fails_without_the_sensing_curve():
    """The default SAC ends ≥ 0.99 of the optimum over ρ (seed 0, the paper scenario). The
    same learner trained where sensing is linear (the curve q(ρ) ignored: time-sharing then pays
    nothing) and scored on the real, dwell-sensing model stays well below: the test can fail."""
    from irdrc.agents.sac import train
    from irdrc.core.exact.continuum import ContinuumScorer

    p = params(**{"env.actions": "continuous"})
    scorer = ContinuumScorer(p)
    good = train(p, seed=0, scorer=scorer, eval_every_frames=200_000)
    assert scorer.ratio(good.greedy[0]) >= 0.99, [e["optimality_ratio"] for e in good.history]
    blind = train(params(**{"env.actions": "continuous", "env.sensing": "linear"}), seed=0)
    assert scorer.ratio(blind.greedy[0]) < 0.95
