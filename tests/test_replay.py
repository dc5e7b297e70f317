"""The pure-torch prioritised sampler against PER's formulas, and end to end in a TorchRL buffer."""

from __future__ import annotations

import math

import pytest
import torch
from tensordict import TensorDict
from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer
from torchrl.data.replay_buffers.samplers import RandomSampler

from irdrc.agents.replay import PackedStorage, TorchPrioritizedSampler, make_prioritized_sampler


def buffer(n=10, alpha=0.7, beta=0.5, batch=64):
    s = TorchPrioritizedSampler(100, alpha=alpha, beta=beta)
    rb = TensorDictReplayBuffer(storage=LazyTensorStorage(100), sampler=s, batch_size=batch)
    rb.extend(TensorDict({"x": torch.arange(float(n))}, [n]))
    return rb, s


def test_sampling_frequencies_follow_priorities():
    rb, s = buffer(n=4, alpha=0.7)
    raw = torch.tensor([1.0, 2.0, 4.0, 0.5])
    rb.update_priority(torch.arange(4), raw)
    rb._sampler._rng = torch.Generator().manual_seed(0)
    n = 200_000
    idx, _ = s.sample(rb.storage, n)
    freq = torch.bincount(idx, minlength=4).double() / n
    p = (raw.double() + 1e-8) ** 0.7
    p /= p.sum()
    # binomial 5σ per item
    assert bool(((freq - p).abs() <= 5 * torch.sqrt(p * (1 - p) / n)).all()), (freq, p)


def test_importance_weights_formula():
    rb, s = buffer(n=3, alpha=0.5, beta=0.6)
    raw = torch.tensor([1.0, 9.0, 4.0])
    rb.update_priority(torch.arange(3), raw)
    idx, info = s.sample(rb.storage, 50)
    w = (raw.double() + 1e-8) ** 0.5
    P = w / w.sum()
    expected = (3 * P[idx]) ** -0.6 / ((3 * P) ** -0.6).max()
    assert torch.allclose(info["priority_weight"].double(), expected, rtol=1e-5)
    assert float(info["priority_weight"].max()) <= 1.0 + 1e-6


def test_new_items_get_max_priority_and_updates_by_index():
    rb, s = buffer(n=5)
    assert torch.equal(s._raw[:5], torch.ones(5, dtype=torch.float64))
    rb.update_priority(torch.tensor([1, 3]), torch.tensor([7.0, 0.25]))
    rb.extend(TensorDict({"x": torch.tensor([10.0, 11.0])}, [2]))
    assert s._raw[:7].tolist() == [1, 7, 1, 0.25, 1, 7, 7]
    with pytest.raises(ValueError):
        rb.update_priority(torch.tensor([0]), torch.tensor([float("nan")]))


def test_buffer_end_to_end_and_the_importance_exponent():
    """Through TorchRL's buffer: a sample carries its indices (pointing at the data) and its
    importance weights; priorities steer the draws; a β set on the sampler is the exponent of the
    next draw's weights (β = 0: all 1; β = 1: the full correction, (N·P(i))⁻¹ normalised)."""
    rb, s = buffer(n=10)
    sample = rb.sample()
    assert sample.shape == (64,) and {"priority_weight", "index"} <= set(sample.keys())
    assert torch.equal(sample["x"], sample["index"].float())  # the index points at the data
    # a zero-priority item is (almost) never drawn; a dominant one mostly is
    raw = torch.tensor([0.0] * 9 + [100.0])
    rb.update_priority(torch.arange(10), raw)
    s.alpha = 1.0
    draws = torch.cat([rb.sample()["index"] for _ in range(20)])
    assert (draws == 9).double().mean() > 0.99
    P = (raw.double() + 1e-8) / (raw.double() + 1e-8).sum()
    for beta in (0.0, 1.0):
        s.beta = beta
        sample = rb.sample()
        want = (10 * P[sample["index"]]) ** -beta / ((10 * P) ** -beta).max()
        assert torch.allclose(sample["priority_weight"].double(), want, rtol=1e-5)
    assert bool((sample["priority_weight"] < 1e-3).any()) or bool((sample["index"] == 9).all())
    with pytest.raises(ValueError):
        s.beta = -1


def test_state_dict_round_trip(tmp_path):
    rb, s = buffer(n=6)
    rb.update_priority(torch.arange(6), torch.arange(6.0))
    s2 = TorchPrioritizedSampler(100, alpha=0.1, beta=0.1)
    s.dumps(tmp_path)
    s2.loads(tmp_path)
    assert torch.equal(s2._raw, s._raw) and s2.alpha == s.alpha and s2.default_priority == 5.0


def test_factory_choice():
    """``prefer="torch"`` is always ours; ``auto`` is TorchRL's sampler exactly when its compiled
    extension loads (here it does not: torch 2.13 against TorchRL's 2.14 build), else ours; asking
    for TorchRL's where it cannot load fails."""
    from irdrc.agents.replay import torchrl_segment_trees_available

    assert isinstance(
        make_prioritized_sampler(10, 0.6, 0.4, prefer="torch"), TorchPrioritizedSampler
    )
    s = make_prioritized_sampler(10, 0.6, 0.4)
    expected = (
        "PrioritizedSampler" if torchrl_segment_trees_available() else "TorchPrioritizedSampler"
    )
    assert type(s).__name__ == expected
    assert math.isclose(s.beta, 0.4)
    with pytest.raises(ValueError):
        make_prioritized_sampler(10, 0.6, 0.4, prefer="gpu")
    if not torchrl_segment_trees_available():
        with pytest.raises(RuntimeError, match="not available"):
            make_prioritized_sampler(10, 0.6, 0.4, prefer="torchrl")


def multinomial_draw(s, n, batch, seed):
    """What the sampler drew before its cumulative sums: ``torch.multinomial`` over the stored
    items, and the weights from a minimum over the buffer."""
    w = (s._raw[:n] + s._eps) ** s.alpha
    g = torch.Generator().manual_seed(seed)
    index = torch.multinomial(w, batch, replacement=True, generator=g)
    return index, (w[index] / w.min()) ** (-s.beta)


@pytest.mark.parametrize("capacity", [1000, 1024, 777])
def test_draws_what_multinomial_draws(capacity):
    """The cumulative sum picks the item ``torch.multinomial`` picks from the same uniforms, and the
    kept minimum gives the same importance weights, through partial fills, wrap-around writes,
    priority updates that lower and raise the least item (with repeated indices) and an α change.
    The two normalise their sums differently, so float rounding could split a draw that lands
    within ~1e-16 (relative) of a boundary: none of these 24 000 does."""
    s = TorchPrioritizedSampler(capacity, alpha=0.6, beta=0.7)
    storage = LazyTensorStorage(capacity)
    rb = TensorDictReplayBuffer(storage=storage, sampler=s, batch_size=500)
    gen = torch.Generator().manual_seed(1)
    for step in range(12):
        rb.extend(TensorDict({"x": torch.zeros(170)}, [170]))  # fills, then wraps
        n = len(rb)
        index = torch.randint(0, n, (400,), generator=gen)  # repeats on purpose
        rb.update_priority(index, torch.rand(400, generator=gen) * 10 ** (step % 4))
        if step == 6:
            s.alpha = 0.9
        s._rng = torch.Generator().manual_seed(step)
        got, info = s.sample(rb.storage, 2000)
        want, weight = multinomial_draw(s, n, 2000, step)
        assert torch.equal(got, want), (step, (got != want).sum())
        assert torch.equal(info["priority_weight"], weight.to(torch.float32))
        assert int(got.max()) < n  # nothing beyond the stored items


def test_draws_follow_a_load_and_a_smaller_storage(tmp_path):
    rb, s = buffer(n=30)
    rb.update_priority(torch.arange(30), torch.arange(30.0))
    s.dumps(tmp_path)
    s2 = TorchPrioritizedSampler(100, alpha=0.7, beta=0.5)
    s2.loads(tmp_path)
    rb2 = TensorDictReplayBuffer(storage=LazyTensorStorage(100), sampler=s2, batch_size=64)
    rb2.extend(TensorDict({"x": torch.arange(10.0)}, [10]))  # fewer items than the state's
    s2._rng = torch.Generator().manual_seed(0)
    got, _ = s2.sample(rb2.storage, 4000)
    want, _ = multinomial_draw(s2, 10, 4000, 0)
    assert torch.equal(got, want) and int(got.max()) < 10


def _transitions(n: int, gen: torch.Generator) -> TensorDict:
    """Leaves of every kind a learner stores: floats, integers, flags, nested keys, doubles."""
    return TensorDict(
        {
            "observation": torch.randn(n, 3, generator=gen),
            "action": torch.randint(0, 5, (n,), generator=gen),
            ("next", "observation"): torch.randn(n, 3, generator=gen),
            ("next", "reward"): torch.randn(n, 1, generator=gen).double(),
            ("next", "done"): torch.rand(n, 1, generator=gen) < 0.5,
            "code": torch.randint(-(2**40), 2**40, (n, 2), generator=gen),
        },
        [n],
    )


def test_packed_storage_gives_back_what_was_written_bit_for_bit():
    """Against TorchRL's LazyTensorStorage given the same writes (through a wrap-around): the
    same keys, dtypes, shapes and values for an index tensor, a mask, a slice and one item."""
    gen = torch.Generator().manual_seed(0)
    packed = TensorDictReplayBuffer(storage=PackedStorage(50), sampler=RandomSampler())
    plain = TensorDictReplayBuffer(storage=LazyTensorStorage(50), sampler=RandomSampler())
    for _ in range(4):  # 80 rows into 50
        batch = _transitions(20, gen)
        packed.extend(batch.clone())
        plain.extend(batch.clone())
    assert len(packed) == len(plain) == 50
    index = torch.randint(0, 50, (200,), generator=gen)
    for at in (index, torch.arange(50) % 3 == 0, slice(5, 17), 7):
        got, want = packed.storage.get(at), plain.storage.get(at)
        assert set(got.keys(True, True)) == set(want.keys(True, True))
        for key in want.keys(True, True):
            assert got.get(key).dtype == want.get(key).dtype, key
            assert torch.equal(got.get(key), want.get(key)), (key, at)
    sample = packed.sample(64)
    assert torch.equal(sample["action"], plain.storage.get(sample["index"])["action"])


def test_packed_storage_rejects_a_batch_of_another_layout():
    packed = TensorDictReplayBuffer(storage=PackedStorage(10), sampler=RandomSampler())
    packed.extend(TensorDict({"x": torch.zeros(4, 2)}, [4]))
    with pytest.raises(ValueError, match="replay holds"):
        packed.extend(TensorDict({"x": torch.zeros(4, 2, dtype=torch.float64)}, [4]))
    with pytest.raises(ValueError, match="replay holds"):
        packed.extend(TensorDict({"x": torch.zeros(4, 3)}, [4]))
    with pytest.raises(ValueError, match="replay holds the keys"):
        packed.extend(TensorDict({"y": torch.zeros(4, 2)}, [4]))
    with pytest.raises(ValueError, match="replay holds the keys"):
        packed.extend(TensorDict({"x": torch.zeros(4, 2), "y": torch.zeros(4)}, [4]))
