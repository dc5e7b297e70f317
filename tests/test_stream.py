"""One vehicle's stream (``irdrc.core.stream``) against the simulator it replaces at batch size one."""

from __future__ import annotations

import math

import pytest
import torch
from conftest import EDGES

from irdrc.bench.random_scenarios import draw_overrides
from irdrc.core.dynamics import Dynamics
from irdrc.core.params import Params
from irdrc.core.stream import VehicleStream

SCENARIOS = {
    "paper": {},
    "imperfect radar": {
        "env.detection_prob": 0.9,
        "env.false_alarm_prob": 0.05,
        "reward.r5": 10.0,
    },
    # three-level factors, bursty arrivals (a phase factor), an imperfect radar: draws of every key
    "draw 3": draw_overrides(3),
    "draw 11": draw_overrides(11),
    "draw 17": draw_overrides(17),
    "edges": EDGES,
}


@pytest.mark.parametrize("name", list(SCENARIOS))
def test_a_step_is_dynamics_step_given_the_same_uniforms(name):
    """Every state × action, three draws of uniforms each: the same next state, reward, event,
    miss, packets and false alarm as ``Dynamics.step`` — equality, not a statistical match."""
    params = Params.from_overrides(SCENARIOS[name])
    dyn, stream = Dynamics(params), VehicleStream(params)
    S = dyn.num_states
    states, actions = torch.arange(S).repeat(2), torch.arange(2).repeat_interleave(S)
    g = torch.Generator().manual_seed(1)
    for _ in range(3):
        u = torch.rand(2 * S, dyn.num_uniforms, generator=g, dtype=torch.float64)
        ref = dyn.step(states, actions, g, uniforms=u)
        for i in range(2 * S):
            got = stream.transition(int(states[i]), int(actions[i]), u[i].tolist())
            want = (
                int(ref.state[i]),
                float(ref.reward[i]),
                bool(ref.event[i]),
                bool(ref.missed[i]),
                int(ref.sent[i]),
                int(ref.dropped[i]),
                bool(ref.false_alarm[i]),
                int(ref.arrivals[i]),
            )
            assert tuple(got) == want, (name, int(states[i]), int(actions[i]))


def test_a_mutated_step_is_caught():
    """The equality test can fail: a stream whose reward table is off in one entry differs."""
    params = Params()
    dyn, stream = Dynamics(params), VehicleStream(params)
    stream.steps._reward[0] += 1.0  # comm, no event, configuration 0
    u = torch.zeros(1, dyn.num_uniforms, dtype=torch.float64) + 0.99  # no event
    ref = dyn.step(torch.tensor([0]), torch.tensor([0]), None, uniforms=u)
    assert stream.transition(0, 0, u[0].tolist()).reward != float(ref.reward[0])


def test_episodes_reset_uniformly_and_end_by_truncation():
    """Resets are uniform over the S states (χ² over 20 000 episodes' first states, 5-sigma bound on
    the statistic's normal approximation: df + 5·√(2·df)); an episode lasts ``env.horizon`` steps."""
    params = Params.from_overrides({"env.horizon": 3})
    stream = VehicleStream(params, seed=4)
    S, n = stream.num_states, 20_000
    counts = torch.zeros(S)
    for _ in range(n):
        counts[stream.reset()] += 1
        for _ in range(3):
            stream.step(1)
        with pytest.raises(RuntimeError, match="episode is over"):
            stream.step(1)
    chi2 = float(((counts - n / S) ** 2 / (n / S)).sum())
    df = S - 1
    assert chi2 < df + 5 * math.sqrt(2 * df)


def test_a_restored_stream_goes_on_as_the_original():
    """Checkpointed between episodes (its generator alone), a stream replays the same steps."""
    params = Params()
    a, b = VehicleStream(params, seed=7), VehicleStream(params, seed=0)
    a.reset()
    for _ in range(params.env.horizon):
        a.step(0)
    b.load_state_dict(a.state_dict())
    for stream in (a, b):
        stream.reset()
    assert [tuple(a.step(t % 2)) for t in range(50)] == [tuple(b.step(t % 2)) for t in range(50)]
    with pytest.raises(RuntimeError, match="between episodes"):
        a.state_dict()


def test_other_action_spaces_are_refused():
    with pytest.raises(ValueError, match="binary"):
        VehicleStream(Params.from_overrides({"env.actions": "continuous"}))
