"""``learn_on_stream(stream=…)``: a learner on a stream of one's own (a vehicle's own steps, or a
world the model does not describe), held to what the loop reads, scored by the same ledger."""

from __future__ import annotations

import math
import re

import gymnasium
import pytest

import irdrc  # noqa: F401  (registers the gymnasium id)
from irdrc.core.exact import exact_scorer
from irdrc.core.params import Params
from irdrc.core.stream import Step, VehicleStream
from irdrc.online.learners import make_learner
from irdrc.online.loop import learn_on_stream

PARAMS = Params()
SCORER = exact_scorer(PARAMS)


class Wrapped:
    """The simulator's stream behind a stream of one's own, recording what it produced."""

    def __init__(self, params: Params, seed: int) -> None:
        self.inner = VehicleStream(params, seed)
        self.horizon = self.inner.horizon
        self.steps: list[Step] = []

    def reset(self) -> int:
        return self.inner.reset()

    def step(self, action: int) -> Step:
        out = self.inner.step(action)
        self.steps.append(out)
        return out

    def state_dict(self) -> dict:
        return self.inner.state_dict()

    def load_state_dict(self, state: dict) -> None:
        self.inner.load_state_dict(state)


def _run(stream=None, episodes=3, resume=None, learner="qlearning", seed=5):
    return learn_on_stream(
        make_learner(learner, None, PARAMS, 0),
        PARAMS,
        SCORER,
        episodes=episodes,
        seed=seed,
        stream=stream,
        resume=resume,
    )


def _same(a: list[dict], b: list[dict]) -> None:
    """Two histories equal in every column but the wall time."""
    assert len(a) == len(b)
    for x, y in zip(a, b, strict=True):
        x, y = dict(x), dict(y)
        x.pop("wall_seconds"), y.pop("wall_seconds")
        assert x.keys() == y.keys()
        for k in x:
            assert x[k] == y[k] or (math.isnan(x[k]) and math.isnan(y[k])), k


def test_the_simulator_behind_a_stream_of_ones_own_gives_the_same_run_and_resumes():
    """The loop reads a stream of one's own as it reads its simulator: the same steps give the
    same history, row for row; with ``state_dict`` / ``load_state_dict`` it resumes exactly."""
    plain = _run()
    _same(_run(Wrapped(PARAMS, 5), seed=0).history, plain.history)  # seed= is the stream's
    half = _run(Wrapped(PARAMS, 5), episodes=2)
    _same(_run(Wrapped(PARAMS, 0), resume=half.state).history, plain.history)


def test_on_a_world_the_model_does_not_describe_the_realised_columns_are_the_worlds():
    """A learner told the paper scenario on a world where speed is always risky: the ledger's
    exact columns score its behaviour on the paper's model, and the realised ones count exactly
    what the world produced."""
    world = Wrapped(Params.from_overrides({"env.p1.speed": 1.0}), 3)
    row = _run(world, learner="posterior").history[-1]
    steps = world.steps
    assert len(steps) == 3 * PARAMS.env.horizon
    assert row["realised_missed"] == sum(s.missed for s in steps)
    assert row["realised_events"] == sum(s.event for s in steps)
    assert row["realised_sent"] == sum(s.sent for s in steps)
    g_star = SCORER.optimal_metrics.avg_reward
    assert row["realised_regret"] == pytest.approx(
        g_star * len(steps) - sum(s.reward for s in steps)
    )


class GymStream:
    """A stream over the gymnasium env (any wrapper of it works the same way)."""

    def __init__(self, seed: int) -> None:
        self.env = gymnasium.make("irdrc/DFRC-v0")
        self.seed: int | None = seed

    def reset(self) -> int:
        _, info = self.env.reset(seed=self.seed)
        self.seed = None
        return info["state"]

    def step(self, action: int) -> Step:
        _, reward, _, _, info = self.env.step(action)
        return Step(reward=reward, **{k: info[k] for k in Step._fields if k != "reward"})


def test_a_stream_over_the_gymnasium_env_feeds_a_learner():
    """The gym env's ``info`` holds every field of a ``Step``; a stream over it runs a learner
    and the ledger counts its steps."""
    row = _run(GymStream(7), episodes=2).history[-1]
    assert row["episodes"] == 2 and row["realised_events"] > 0
    assert math.isfinite(row["regret"]) and row["regret"] > 0


class NoStep:
    def reset(self) -> int:
        return 0


class Short(Wrapped):
    def __init__(self, params: Params, seed: int) -> None:
        super().__init__(params, seed)
        self.horizon = 10


class Tuples(Wrapped):
    def step(self, action: int):
        return tuple(super().step(action))


class Far(Wrapped):
    def reset(self) -> int:
        return PARAMS.env.num_states


class Unsaved:
    horizon = PARAMS.env.horizon

    def __init__(self) -> None:
        self.inner = Wrapped(PARAMS, 0)

    def reset(self) -> int:
        return self.inner.reset()

    def step(self, action: int) -> Step:
        return self.inner.step(action)


@pytest.mark.parametrize(
    "stream, error, message",
    [
        (NoStep(), TypeError, "stream=NoStep has no step(): a stream has reset() -> state index"),
        (Short(PARAMS, 0), ValueError, "horizon=10: its episodes must be env.horizon=400"),
        (Tuples(PARAMS, 0), TypeError, "Tuples.step() returned tuple: a step is"),
        (Far(PARAMS, 0), ValueError, "Far.reset() gave state 352: a state is an index in [0, 352)"),
    ],
)
def test_a_stream_that_breaks_the_contract_is_refused_by_name(stream, error, message):
    with pytest.raises(error, match=re.escape(message)):
        _run(stream, episodes=1)


def test_a_stream_without_load_state_dict_runs_and_its_resume_is_refused():
    record = _run(Unsaved(), episodes=1)
    assert record.state["stream"] == {}
    with pytest.raises(ValueError, match="the stream Unsaved has no load_state_dict"):
        _run(Unsaved(), episodes=2, resume=record.state)
