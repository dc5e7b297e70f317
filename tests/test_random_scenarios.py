"""The random scenario distribution (``irdrc.bench.random_scenarios``): every draw is a valid
scenario a user can type, reproducible from its index, and the contested filter keeps exactly the
draws where neither always-radar nor always-comm is within 0.9 of the optimum."""

from __future__ import annotations

import pytest
from conftest import load

from irdrc.bench.random_scenarios import (
    CONTESTED,
    command_line,
    contested,
    contested_draws,
    draw_overrides,
)
from irdrc.core.exact import build_model, stationary_metrics, value_iteration
from irdrc.core.params import Params


def test_draws_are_reproducible_valid_and_cover_every_kind_of_key():
    """200 draws: each builds a Params (every check passes), the same index gives the same draw,
    and the kinds a user might pick all occur: three-level factors, bursty arrivals, an imperfect
    radar, the sum event model, no radar reaction, rewards across 0.1 … 100."""
    draws = [draw_overrides(i) for i in range(200)]
    assert draws[17] == draw_overrides(17) and draws[17] != draws[18]
    for d in draws:
        Params.from_overrides(d)
    assert sum("env.factors" in d for d in draws) > 20
    assert sum("env.bursty" in d for d in draws) > 20
    assert sum("env.detection_prob" in d for d in draws) > 20
    assert sum(d["env.event_model"] == "sum" for d in draws) > 50
    assert sum(not d["env.radar_reaction"] for d in draws) > 10
    r3 = [d["reward.r3"] for d in draws]
    assert min(r3) < 0.3 and max(r3) > 30
    with pytest.raises(ValueError, match="whole number"):
        draw_overrides(-1)


@pytest.mark.parametrize("kind", ["env.factors", "env.bursty", "env.detection_prob"])
def test_a_draw_on_the_command_line_is_the_same_scenario(kind):
    """The overrides a benchmark gives a run (``command_line``) compose through the recipe's own
    config into the very scenario of the draw."""
    index = next(i for i in range(200) if kind in draw_overrides(i))
    cfg = load("dqn", *command_line(draw_overrides(index)))
    assert cfg.params == Params.from_overrides(draw_overrides(index))


def test_the_contested_filter_keeps_exactly_the_contested_draws():
    """Over draws 0–29: a kept draw's baselines both earn < 0.9 of a positive optimum; a dropped
    one has a baseline ≥ 0.9 of it or an optimum ≤ 0 (recomputed here from the exact model)."""
    kept = {d.index: d for d in contested_draws(0, 5)}
    last = max(kept)
    for i in range(last + 1):
        model = build_model(Params.from_overrides(draw_overrides(i)))
        best = stationary_metrics(model, value_iteration(model).policy).avg_reward
        base = [stationary_metrics(model, p).avg_reward for p in ("always_radar", "always_comm")]
        fair = best > 0 and max(base) < CONTESTED * best
        assert (i in kept) == fair, i
        if fair:
            assert kept[i].always_radar == pytest.approx(base[0] / best)
    assert contested(max(i for i in range(last) if i not in kept)) is None


def test_bench_robust_plans_one_run_per_draw_and_seed():
    cfg = load("bench_robust", "scenarios=random", "draws=2", "first_draw=0", "executor=local")
    assert len(cfg.planned) == 2 and cfg.seeds == (5,)
    draws = [p["point"]["draw"] for p in cfg.planned]
    assert draws == [d.index for d in contested_draws(0, 2)]
    first = cfg.planned[0]["config"].params
    assert first == Params.from_overrides(draw_overrides(draws[0]))
    grid = load("bench_robust", "executor=local", "p1_speed=[0.1]", "r4=[5]")
    assert grid.seeds == tuple(range(5, 25)) and len(grid.planned) == 20


def test_time_sharing_draws_keep_exactly_where_sharing_gains_two_percent():
    """Time-sharing draws add the sensing curve, κ and the levels to every model key, reproducibly;
    up to the second kept draw a kept draw's optimum over ρ earns ≥ 1.02 × a positive binary optimum and a
    dropped one does not (recomputed here from both exact solvers); the planned run composes into
    the draw's scenario with SAC's continuous actions."""
    from irdrc.bench.random_scenarios import SHARE_GAIN, share_draws, share_overrides
    from irdrc.core.exact import exact_scorer
    from irdrc.core.exact.continuum import ContinuumScorer

    assert share_overrides(3) == share_overrides(3) and share_overrides(3) != share_overrides(4)
    draws = [share_overrides(i) for i in range(60)]
    assert {d["env.sensing"] for d in draws} == {"dwell", "linear"}
    assert {d["env.levels"] for d in draws} == {3, 5, 9}
    kept = {d.index: d for d in share_draws(0, 2)}
    for i in range(max(kept) + 1):
        o = share_overrides(i)
        binary = exact_scorer(Params.from_overrides(o)).optimal_metrics.avg_reward
        cont = Params.from_overrides({**o, "env.actions": "continuous"})
        best = ContinuumScorer(cont).optimal_metrics.avg_reward
        assert (i in kept) == (binary > 0 and best >= SHARE_GAIN * binary), i
        if i in kept:
            assert kept[i].optimum == pytest.approx(best) and kept[i].binary == pytest.approx(
                binary
            )
    cfg = load("bench_timeshare", "scenarios=random", "draws=1", "learners=[sac]", "executor=local")
    assert cfg.seeds == (5,) and len(cfg.planned) == 1
    first = min(kept)
    assert list(cfg.scenario_overrides) == [f"draw {first}"]
    want = Params.from_overrides({**share_overrides(first), "env.actions": "continuous"})
    assert cfg.planned[0]["config"].params == want
    with pytest.raises(ValueError, match="random or a mapping"):
        load("bench_timeshare", "scenarios=grid", "executor=local")
