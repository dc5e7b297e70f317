"""DQN's growing batch (``algo.batch_size_end``): the schedule, validation, and a run whose updates
sample the scheduled sizes, then checkpoint and resume."""

from __future__ import annotations

import pytest

from irdrc.agents import dqn as D


def test_schedule_is_linear_in_env_steps_and_constant_when_off():
    cfg = D.DQNConfig(total_frames=20_000, batch_size=256, batch_size_end=1024)
    assert [D.batch_size_at(cfg, f) for f in (0, 5_000, 10_000, 20_000, 30_000)] == [
        256,
        448,
        640,
        1024,
        1024,
    ]
    assert D.batch_size_at(D.DQNConfig(), 10_000) == 256  # the default: constant
    assert D.DQNConfig().batch_size_end == 0


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"batch_size_end": -1}, r"algo\.batch_size_end"),
        ({"batch_size_end": 2.5}, r"algo\.batch_size_end"),
        ({"buffer_size": 1000, "batch_size_end": 2000}, r"algo\.batch_size_end=2000"),
    ],
)
def test_invalid_batch_growth(kwargs, match):
    with pytest.raises(ValueError, match=match):
        D.DQNConfig(**kwargs)


def test_updates_sample_the_scheduled_sizes_and_resume(monkeypatch):
    from irdrc import Params

    seen: list[int] = []
    original = D.TensorDictReplayBuffer.sample

    def spy(self, batch_size=None, *args, **kwargs):
        seen.append(batch_size)
        return original(self, batch_size, *args, **kwargs)

    monkeypatch.setattr(D.TensorDictReplayBuffer, "sample", spy)
    base = dict(
        total_frames=320,
        init_random_frames=64,
        buffer_size=480,
        batch_size=16,
        batch_size_end=48,
        updates_per_batch=2,
        network=D.NetworkConfig(hidden=(16,)),
    )
    run = D.train(Params(), D.DQNConfig(**base), seed=0, eval_every_frames=160)
    # learning from 64 frames: after each batch of 32, 2 updates of the size due at that frame
    cfg = D.DQNConfig(**base)
    want = [D.batch_size_at(cfg, f) for f in range(64, 321, 32) for _ in range(2)]
    assert seen == want and want[0] == 22 and want[-1] == 48 and run.updates == 18
    # Resumed to 480 frames the schedule is the longer run's, and the refilled buffer (no replay is
    # checkpointed) must hold a whole batch first: at 352 frames it holds 32 < 40, so the resumed
    # run learns from 384 frames on.
    seen.clear()
    longer = D.DQNConfig(**{**base, "total_frames": 480})
    resumed = D.train(Params(), longer, seed=0, eval_every_frames=160, resume=run.state)
    assert seen == [D.batch_size_at(longer, f) for f in range(384, 481, 32) for _ in range(2)]
    assert resumed.env_steps == 480 and resumed.updates == 18 + 4 * 2 and seen[-1] == 48


def test_the_lagrangian_learner_refuses_a_growing_batch():
    from irdrc.agents.lagrangian import LagrangianConfig

    with pytest.raises(ValueError, match=r"algo\.batch_size_end"):
        LagrangianConfig.from_dict({"batch_size_end": 512})
