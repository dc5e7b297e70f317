"""Statistical checks of the simulator against MODEL.md's formulas (written here independently).

Each frequency is compared with its probability at 5 binomial standard deviations: a correct
simulator fails one comparison with probability ~6e-7 (a few hundred comparisons per test keep the
family-wise rate below 1e-3), and seeds are fixed, so the tests are deterministic.
"""

from __future__ import annotations

import itertools
import math

import pytest
import torch

from irdrc import Params, state_index

K = 20_000  # samples per (state, action) cell


def assert_binomial(freq: torch.Tensor, p: torch.Tensor, n: int, what: str) -> None:
    sigma = torch.sqrt(p * (1 - p) / n)
    # the 1e-12 floor only admits exact 0/1 cells, where sigma is 0 and freq must equal p
    bad = (freq - p).abs() > 5 * sigma + 1e-12
    assert not bool(bad.any()), f"{what}: freq {freq[bad][:5].tolist()} vs p {p[bad][:5].tolist()}"


EVENT_CONFIGS = list(itertools.product((0, 1), repeat=4))  # (r, w, v, m)
P0 = {"road": 0.01, "weather": 0.02, "speed": 0.03, "object": 0.04}
P1 = {"road": 0.2, "weather": 0.3, "speed": 0.35, "object": 0.25}


@pytest.mark.parametrize("model", ["noisy_or", "sum"])
def test_event_frequency_per_state(step_from, model):
    params = Params.from_overrides({"env.p0": P0, "env.p1": P1, "env.event_model": model})
    states = torch.tensor([state_index(3, 0, *cfg) for cfg in EVENT_CONFIGS]).repeat_interleave(K)
    nxt = step_from(
        params,
        states,
        torch.randint(0, 2, states.shape, generator=torch.Generator().manual_seed(0)),
        seed=1,
    )
    freq = nxt["event"].float().view(16, K).mean(1).double()
    probs = []
    for cfg in EVENT_CONFIGS:
        ps = [
            (P1 if x else P0)[k]
            for x, k in zip(cfg, ("road", "weather", "speed", "object"), strict=True)
        ]
        probs.append(1 - math.prod(1 - q for q in ps) if model == "noisy_or" else min(1.0, sum(ps)))
    assert_binomial(freq, torch.tensor(probs, dtype=torch.float64), K, f"event ({model})")


def test_sum_model_is_capped_at_one(step_from):
    probs = dict.fromkeys(("road", "weather", "speed", "object"), 0.4)
    params = Params.from_overrides({"env.p1": probs, "env.event_model": "sum"})
    nxt = step_from(params, torch.full((1000,), state_index(0, 0, 1, 1, 1, 1)), 1)
    assert bool(nxt["event"].all())  # Σ p = 1.6 → P = 1


GOOD = {"channel": 0.8, "road": 0.7, "weather": 0.6, "speed": 0.95, "object": 0.85}
BAD = {"channel": 0.3, "road": 0.2, "weather": 0.4, "speed": 0.5, "object": 0.6}
NAMES = ("channel", "road", "weather", "speed", "object")


def expected_next1(cfg, action, reaction, clear):
    """P(factor′ = 1) per factor from MODEL.md step 4, for factors cfg = (c, r, w, v, m)."""
    out = [BAD[k] if x else 1 - GOOD[k] for x, k in zip(cfg, NAMES, strict=True)]
    if reaction and action == 1 and cfg[4] == 1:
        out[3] = 0.0  # v′ = 0
        out[4] = 1 - clear  # m′ = 0 w.p. clear
    return out


@pytest.mark.parametrize("reaction", [True, False])
def test_factor_transitions_and_radar_reaction(step_from, reaction):
    clear = 0.7
    params = Params.from_overrides(
        {
            "env.stay_good": GOOD,
            "env.stay_bad": BAD,
            "env.radar_reaction": reaction,
            "env.reaction_clear": clear,
        }
    )
    cfgs = list(itertools.product((0, 1), repeat=5))
    states = torch.tensor([state_index(4, *c) for c in cfgs])
    for action in (0, 1):
        nxt = step_from(params, states.repeat_interleave(K), action, seed=10 + action)
        bits = torch.stack([(nxt["state"] >> b) & 1 for b in (4, 3, 2, 1, 0)], -1).double()
        freq = bits.view(32, K, 5).mean(1)
        p = torch.tensor(
            [expected_next1(c, action, reaction, clear) for c in cfgs], dtype=torch.float64
        )
        assert_binomial(freq, p, K, f"factor transitions (action {action}, reaction {reaction})")


def poisson_pmf(k: int, lam: float) -> float:
    return math.exp(-lam) * lam**k / math.factorial(k)


@pytest.mark.parametrize("lam", [1.0, 3.5])
def test_arrivals_are_poisson(step_from, lam):
    # radar (ν = 0) from an empty queue that cannot overflow: d′ = A exactly
    params = Params.from_overrides({"env.arrival_rate": lam, "env.queue_capacity": 60})
    n = 1_000_000
    nxt = step_from(params, torch.full((n,), state_index(0, 0, 0, 0, 0, 0)), 1, seed=3)
    a = nxt["state"] >> 5
    assert not bool(nxt["dropped"].any())
    # One cell per count while its expected count is >= 50 (where the 5σ normal bound is sound),
    # then one cell for the whole upper tail.
    k0 = 0
    while n * poisson_pmf(k0, lam) >= 50 or k0 < lam:
        k0 += 1
    p = [poisson_pmf(k, lam) for k in range(k0)]
    p.append(1.0 - sum(p))
    freq = [(a == k).double().mean().item() for k in range(k0)] + [(a >= k0).double().mean().item()]
    assert_binomial(
        torch.tensor(freq), torch.tensor(p, dtype=torch.float64), n, f"arrivals (λ={lam})"
    )
    # mean within 5 standard errors (variance of Poisson = λ)
    assert abs(a.double().mean().item() - lam) < 5 * math.sqrt(lam / n)


def test_overflow_drops_counted(step_from):
    # full queue, radar: every arrival is dropped, so dropped ~ Poisson(λ)
    n = 100_000
    nxt = step_from(Params(), torch.full((n,), state_index(10, 0, 0, 0, 0, 0)), 1, seed=4)
    assert bool(((nxt["state"] >> 5) == 10).all())
    assert abs(nxt["dropped"].double().mean().item() - 1.0) < 5 * math.sqrt(1.0 / n)


def test_reset_is_uniform():
    from irdrc import DFRCEnv

    n = 352 * 300
    s = DFRCEnv(Params(), batch_size=[n], seed=0).reset()["state"]
    counts = torch.bincount(s, minlength=352).double()
    # χ² goodness of fit with 351 dof: mean 351, sd √702 ≈ 26.5; 5 sd above the mean is 484.
    chi2 = float(((counts - 300) ** 2 / 300).sum())
    assert chi2 < 351 + 5 * math.sqrt(2 * 351), chi2
