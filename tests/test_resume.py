"""Every learner checkpoints and goes on from its checkpoint (the one loop's ``state`` /
``restore``, Q-learning's own tables): counts, history and the learner's own state continue where
they stopped; a checkpoint of something else is refused naming what it lacks. The recipes' kill -9
and SIGTERM runs are in ``tests/test_durability.py``."""

from __future__ import annotations

import pytest
import torch

from irdrc import Params
from irdrc.agents import lagrangian, marl, qlearning
from irdrc.agents.base import Hooks
from irdrc.agents.configs import (
    DQNConfig,
    FleetLearnerConfig,
    LagrangianConfig,
    NetworkConfig,
    QLearningConfig,
    SearchConfig,
)
from irdrc.agents.dqn import train as train_dqn
from irdrc.fleet.model import FleetModel
from irdrc.fleet.scorer import FleetScorer
from irdrc.fleet.spec import FleetSpec

TINY = dict(
    num_envs=8,
    frames_per_batch=32,
    total_frames=320,
    init_random_frames=64,
    buffer_size=320,
    batch_size=16,
    updates_per_batch=2,
    network=NetworkConfig(hidden=(16,)),
)
"""A DQN of 320 env steps: learning from 64, so (320 − 32)/32 = 9 batches × 2 updates."""


def steps(record) -> list[int]:
    return [e["env_steps"] for e in record.history]


def scored(history: list[dict]) -> list[dict]:
    """An evaluation history without its wall times (which differ from run to run)."""
    return [{k: v for k, v in e.items() if k != "wall_seconds"} for e in history]


def test_dqn_resumes_to_a_longer_run():
    run = train_dqn(Params(), DQNConfig(**TINY), seed=0, eval_every_frames=160)
    assert run.updates == 18 and run.greedy.shape == (1, 352) and run.q.shape == (1, 352, 2)
    assert steps(run) == [0, 160, 320]
    longer = DQNConfig(**{**TINY, "total_frames": 480})
    resumed = train_dqn(Params(), longer, seed=0, eval_every_frames=160, resume=run.state)
    # the replay is not checkpointed: the resumed run learns from its first full batch on
    assert resumed.env_steps == 480 and resumed.updates == 18 + 5 * 2
    assert steps(resumed) == [0, 160, 320, 480]
    assert scored(resumed.history[:3]) == scored(run.history)


def test_lagrangian_resumes_with_its_multiplier():
    search = SearchConfig(measure_envs=4, measure_steps=20, measure_burn_in=0, mix_steps=2)
    dq = DQNConfig(
        **{**TINY, "reward_centering": 0.0, "reward_means": False, "name": "dqn_lagrangian"}
    )
    cfg = LagrangianConfig(dqn=dq, search=search)
    saved = []
    hooks = Hooks(on_checkpoint=saved.append, checkpoint_every_frames=160)
    first = lagrangian.train(Params(), cfg, seed=0, eval_every_frames=160, hooks=hooks)
    (mid,) = saved  # at 160 (none at the end: that is the record's state)
    assert mid["frames"] == 160 and len(mid["mu_trace"]) == 160 // 32
    seen = []
    resumed = lagrangian.train(
        Params(), cfg, seed=0, eval_every_frames=160, resume=mid, hooks=Hooks(on_batch=seen.append)
    )
    assert resumed.training_env_steps == 320 and steps(resumed) == [0, 160, 320]
    assert scored(resumed.history[:2]) == scored(first.history[:2])
    assert len(resumed.info["mu_trace"]) == 320 // 32
    assert resumed.info["mu_trace"][:5] == first.info["mu_trace"][:5]
    assert seen[0]["env_steps"] == 192  # the first batch after the checkpoint
    with pytest.raises(ValueError, match="resume: the checkpoint has no frames"):
        lagrangian.train(Params(), cfg, resume={})


def test_qlearning_resumed_is_the_uninterrupted_run():
    """Tables, visit counts and both random streams are checkpointed: the resumed run's tables
    equal the uninterrupted run's exactly."""
    cfg = QLearningConfig(episodes=4)
    whole = qlearning.train(Params(), cfg, num_learners=2, seed=3, eval_every_frames=400)
    saved = []
    hooks = Hooks(on_checkpoint=saved.append, checkpoint_every_frames=800)
    qlearning.train(Params(), cfg, num_learners=2, seed=3, eval_every_frames=400, hooks=hooks)
    (mid,) = saved
    assert mid["frames"] == 800
    resumed = qlearning.train(
        Params(), cfg, num_learners=2, seed=3, eval_every_frames=400, resume=mid
    )
    assert torch.equal(resumed.q, whole.q)
    assert scored(resumed.history) == scored(whole.history)
    assert [r["reward"] for r in resumed.episode_rewards] == [
        r["reward"] for r in whole.episode_rewards
    ]
    with pytest.raises(ValueError, match="not a Q-learning checkpoint"):
        qlearning.train(Params(), cfg, resume={"frames": 0})
    with pytest.raises(ValueError, match="2 learners"):
        qlearning.train(Params(), cfg, num_learners=3, resume=mid)


@pytest.mark.parametrize("learner", ["vdn", "idqn", "mappo"])
def test_fleet_learners_resume_in_fleet_steps(learner):
    """The fleet's learners checkpoint through the same loop; idqn's rows (N per fleet step) are
    counted in fleet steps in its history and its checkpoint's ``env_steps``."""
    model = FleetModel(FleetSpec(vehicles=2))
    scorer = FleetScorer(model)
    small = {"num_envs": 8, "frames_per_batch": 32, "total_frames": 320, "batch_size": 16}
    cfg = FleetLearnerConfig.from_sections(learner, small, None, small)
    saved = []
    hooks = Hooks(on_checkpoint=saved.append, checkpoint_every_frames=160)
    first = marl.train(model, cfg, seed=0, scorer=scorer, eval_every_frames=160, hooks=hooks)
    (mid,) = saved
    assert steps(first) == [0, 160, 320] and [e["env_steps"] for e in mid["history"]] == [0, 160]
    if learner == "idqn":
        assert mid["env_steps"] == 160 and mid["frames"] == 2 * 160  # rows: 2 per fleet step
    resumed = marl.train(model, cfg, seed=0, scorer=scorer, eval_every_frames=160, resume=mid)
    assert steps(resumed) == [0, 160, 320] and resumed.env_steps == 320
    assert scored(resumed.history[:2]) == scored(first.history[:2])


def test_sac_resumes_to_a_longer_run():
    from irdrc.agents.configs.continuous import SACConfig
    from irdrc.agents.sac import train as train_sac

    p = Params.from_overrides({"env.actions": "continuous"})
    run = train_sac(p, SACConfig(**TINY), seed=0, eval_every_frames=160)
    assert steps(run) == [0, 160, 320] and run.greedy.shape == (1, 352)
    longer = SACConfig(**{**TINY, "total_frames": 480})
    resumed = train_sac(p, longer, seed=0, eval_every_frames=160, resume=run.state)
    assert resumed.env_steps == 480 and steps(resumed) == [0, 160, 320, 480]
    assert scored(resumed.history[:3]) == scored(run.history)
    # the actor goes on with its checkpoint's margin: one written without it spanned [0, 1]
    from irdrc.agents.sac import SHARE_MARGIN

    assert run.state["share_margin"] == resumed.state["share_margin"] == SHARE_MARGIN
    older = {k: v for k, v in run.state.items() if k != "share_margin"}
    assert train_sac(p, longer, seed=0, resume=older).state["share_margin"] == 0.0


def test_ppo_resumes_to_a_longer_run():
    """PPO learns on the same loop without a replay: its checkpoint holds the networks, the
    optimiser and the reward centre, and a resumed run keeps its history."""
    from irdrc.agents.configs.continuous import PPOConfig
    from irdrc.agents.ppo import train as train_ppo

    p = Params.from_overrides({"env.actions": "continuous"})
    small = {"num_envs": 8, "frames_per_batch": 80, "total_frames": 320, "batch_size": 40}
    run = train_ppo(p, PPOConfig(**small), seed=0, eval_every_frames=160)
    assert steps(run) == [0, 160, 320] and run.greedy.shape == (1, 352)
    assert run.updates == 4 * 2 * 4  # 4 rollouts × 2 minibatches × 4 epochs
    assert run.state["reward_center"] is not None
    longer = PPOConfig(**{**small, "total_frames": 480})
    resumed = train_ppo(p, longer, seed=0, eval_every_frames=160, resume=run.state)
    assert resumed.env_steps == 480 and steps(resumed) == [0, 160, 320, 480]
    assert scored(resumed.history[:3]) == scored(run.history)
