"""Counter-based random numbers keyed per world (marl_render/keyed_random.py): the same key gives the
same draws in any slot and batch size, the hash is splitmix64's bit for bit, and the numbers pass
basic statistical checks."""
from __future__ import annotations

import math

import pytest
import torch

from marl_render.keyed_random import KeyedRandom, derive_keys, label_id, mix64, shift_right

U64 = (1 << 64) - 1


def reference_mix64(x: int) -> int:
    """splitmix64's finaliser on Python ints (unsigned 64-bit), as published."""
    x &= U64
    x = ((x ^ (x >> 30)) * 0xBF58476D1CE4E5B9) & U64
    x = ((x ^ (x >> 27)) * 0x94D049BB133111EB) & U64
    return x ^ (x >> 31)


def signed(x: int) -> int:
    return x - (1 << 64) if x >= 1 << 63 else x


def test_mix64_is_splitmix64_bit_for_bit_including_negative_words():
    words = [0, 1, 2, 12345, 2 ** 62, 2 ** 63 - 1, -1, -(2 ** 63), -987654321, 0x9E3779B97F4A7C15 - 2 ** 64]
    got = mix64(torch.tensor(words, dtype=torch.int64)).tolist()
    assert got == [signed(reference_mix64(w)) for w in words]


def test_shift_right_is_logical():
    x = torch.tensor([-1, -(2 ** 63), 5], dtype=torch.int64)
    assert shift_right(x, 1).tolist() == [2 ** 63 - 1, 2 ** 62, 2]
    assert shift_right(x, 60).tolist() == [15, 8, 0]


def test_bits_follow_the_documented_construction():
    """Element i of stream s of key k: mix64(seed + (i + 1) * golden), seed = mix64(mix64(k + golden) ^ mix64(s))."""
    golden = 0x9E3779B97F4A7C15
    key, stream = 42, 7
    seed = reference_mix64(reference_mix64(key + golden) ^ reference_mix64(stream))
    expected = [signed(reference_mix64(seed + (i + 1) * golden)) for i in range(5)]
    assert KeyedRandom(torch.tensor([key])).bits(stream, 5)[0].tolist() == expected


DRAWS = {
    "uniform": lambda r: r.uniform("u", (3, 2)),
    "uniform64": lambda r: r.uniform("u", (4,), dtype=torch.float64, low=-2.0, high=3.0),
    "randint": lambda r: r.randint("i", -5, 17, (6,)),
    "normal": lambda r: r.normal("n", (5,)),
    "bernoulli": lambda r: r.bernoulli("b", 0.3, (7,)),
    "permutation": lambda r: r.permutation("p", 9),
    "choice": lambda r: r.choice("c", 12, 4),
}


@pytest.mark.parametrize("kind", sorted(DRAWS))
def test_a_key_draws_the_same_numbers_in_any_slot_and_batch_size(kind):
    key = 0x5EED
    reference = DRAWS[kind](KeyedRandom(torch.tensor([key])))[0]
    for batch, slot in ((1, 0), (8, 5), (64, 37), (64, 0)):
        keys = torch.arange(batch, dtype=torch.int64) * 7919 + 3  # other worlds, other keys
        keys[slot] = key
        rng = KeyedRandom(keys)
        DRAWS[kind](rng)  # history: a draw before makes no difference
        got = DRAWS[kind](rng)[slot]
        assert torch.equal(got, reference), (kind, batch, slot)
        assert got.dtype == reference.dtype


def test_shapes_dtypes_and_ranges():
    rng = KeyedRandom(torch.arange(16))
    u = rng.uniform(0, (1000,))
    assert u.shape == (16, 1000) and u.dtype == torch.float32
    assert float(u.min()) >= 0.0 and float(u.max()) < 1.0
    u64 = rng.uniform(1, (1000,), dtype=torch.float64)
    assert u64.dtype == torch.float64 and float(u64.min()) >= 0.0 and float(u64.max()) < 1.0
    scaled = rng.uniform(2, (100,), low=-3.0, high=-1.0)
    assert float(scaled.min()) >= -3.0 and float(scaled.max()) < -1.0
    i = rng.randint(3, 10, 13, (500,))
    assert i.dtype == torch.int64 and set(i.unique().tolist()) == {10, 11, 12}
    assert rng.bernoulli(4, 0.5, (3, 4)).dtype == torch.bool
    perm = rng.permutation(5, 11)
    assert torch.equal(perm.sort(-1).values, torch.arange(11).expand(16, 11))
    picks = rng.choice(6, 11, 3)
    assert picks.shape == (16, 3) and all(len(set(row)) == 3 for row in picks.tolist())
    assert rng.uniform(7).shape == (16,)
    assert KeyedRandom(torch.tensor(5)).uniform(0, 2).shape == (1, 2)  # a 0-d key is one world


def test_uniform_mean_and_variance_on_1e5_draws():
    u = KeyedRandom(torch.arange(100)).uniform("stats", (1000,), dtype=torch.float64).reshape(-1)
    assert abs(float(u.mean()) - 0.5) < 0.005  # the mean's sd is 0.0009
    assert abs(float(u.var()) - 1 / 12) < 0.002


def test_randint_passes_a_chi_square_test():
    draws = KeyedRandom(torch.arange(100)).randint("chi", 0, 10, (1000,)).reshape(-1)
    counts = torch.bincount(draws, minlength=10).double()
    chi2 = float(((counts - 1e4) ** 2 / 1e4).sum())
    assert chi2 < 27.88, counts.tolist()  # the 0.999 quantile at 9 degrees of freedom


def test_normal_moments():
    n = KeyedRandom(torch.arange(100)).normal("gauss", (1000,), dtype=torch.float64).reshape(-1)
    assert abs(float(n.mean())) < 0.02 and abs(float(n.std()) - 1) < 0.02
    assert abs(float((n.abs() < 1).double().mean()) - 0.6827) < 0.01


def correlation(a: torch.Tensor, b: torch.Tensor) -> float:
    return float(torch.corrcoef(torch.stack((a.double(), b.double())))[0, 1])


def test_no_correlation_between_adjacent_keys_streams_or_elements():
    keys = torch.arange(100_000, dtype=torch.int64)
    first = KeyedRandom(keys).uniform("s", (2,), dtype=torch.float64)
    neighbour = KeyedRandom(keys + 1).uniform("s", (2,), dtype=torch.float64)
    other_stream = KeyedRandom(keys).uniform("t", (2,), dtype=torch.float64)
    next_stream = KeyedRandom(keys).uniform(1, dtype=torch.float64), KeyedRandom(keys).uniform(2, dtype=torch.float64)
    bound = 0.015  # the coefficient's sd is 0.0032 at 1e5 pairs
    assert abs(correlation(first[:, 0], neighbour[:, 0])) < bound
    assert abs(correlation(first[:, 0], other_stream[:, 0])) < bound
    assert abs(correlation(first[:, 0], first[:, 1])) < bound
    assert abs(correlation(*next_stream)) < bound
    # Each bit of the raw words is set about half the time.
    bits = KeyedRandom(keys).bits("bits")
    rate = torch.stack([(shift_right(bits, b) & 1).double().mean() for b in range(64)])
    assert float((rate - 0.5).abs().max()) < 0.01


def test_permutations_are_uniform():
    perms = KeyedRandom(torch.arange(60_000)).permutation("perm", 3)
    codes = perms[:, 0] * 3 + perms[:, 1]
    counts = torch.bincount(codes, minlength=9)[[1, 2, 3, 5, 6, 7]].double()  # the 6 orders of 3
    chi2 = float(((counts - 1e4) ** 2 / 1e4).sum())
    assert chi2 < 20.5, counts.tolist()  # the 0.999 quantile at 5 degrees of freedom


def test_derive_keys_is_pure_and_separates_labels():
    ids = torch.tensor([0, 1, 2, 3])
    a = derive_keys(ids, "appearance")
    assert torch.equal(a, derive_keys(ids.clone(), "appearance"))
    assert torch.equal(derive_keys(ids[2:], "appearance"), a[2:])
    assert not bool((a == derive_keys(ids, "layout")).any())
    assert not bool((a == ids).any()) and len(set(a.tolist())) == 4
    assert torch.equal(derive_keys(ids, "a", 3), derive_keys(derive_keys(ids, "a"), 3))
    # A derived key's numbers are not the parent's stream of the same name.
    assert not torch.equal(KeyedRandom(a).bits(0, 4), KeyedRandom(ids).bits("appearance", 4))


def test_labels_hash_stably():
    assert label_id(5) == 5
    assert label_id("appearance") == label_id("appearance") < 0  # str ids have the top bit set
    assert label_id("a") != label_id("b") and label_id(b"a") == label_id("a")


@pytest.mark.parametrize("call, error, words", [
    (lambda: KeyedRandom([1, 2]), TypeError, "keys must be an int64 tensor"),
    (lambda: KeyedRandom(torch.zeros(3)), TypeError, "keys must be an integer tensor"),
    (lambda: KeyedRandom(torch.zeros(2, 2, dtype=torch.int64)), ValueError, r"keys must have shape \[W\]"),
    (lambda: KeyedRandom(torch.arange(2)).uniform(-1), ValueError, "stream must be an int in"),
    (lambda: KeyedRandom(torch.arange(2)).uniform(1.5), TypeError, "stream must be an int"),
    (lambda: KeyedRandom(torch.arange(2)).uniform("s", (2, -1)), ValueError, "shape must be non-negative"),
    (lambda: KeyedRandom(torch.arange(2)).uniform("s", "ab"), TypeError, "shape must be an int"),
    (lambda: KeyedRandom(torch.arange(2)).uniform("s", (2 ** 30, 2 ** 30)), ValueError, "at most"),
    (lambda: KeyedRandom(torch.arange(2)).uniform("s", low=1.0, high=0.0), ValueError, "low <= high"),
    (lambda: KeyedRandom(torch.arange(2)).uniform("s", dtype=torch.float16), ValueError, "dtype must be"),
    (lambda: KeyedRandom(torch.arange(2)).randint("s", 3, 3), ValueError, "low < high"),
    (lambda: KeyedRandom(torch.arange(2)).randint("s", 0.0, 3), TypeError, "integer low and high"),
    (lambda: KeyedRandom(torch.arange(2)).bernoulli("s", 1.5), ValueError, r"p in \[0, 1\]"),
    (lambda: KeyedRandom(torch.arange(2)).permutation("s", -1), ValueError, "n must be an int"),
    (lambda: KeyedRandom(torch.arange(2)).choice("s", 3, 4), ValueError, "0 <= k <= n"),
])
def test_bad_input_names_the_argument(call, error, words):
    with pytest.raises(error, match=words):
        call()


def test_a_large_batch_draws_all_of_its_worlds():
    keys = torch.arange(100_000)
    u = KeyedRandom(keys).uniform("fast", (4,))
    assert u.shape == (100_000, 4) and math.isclose(float(u.mean()), 0.5, abs_tol=0.01)
