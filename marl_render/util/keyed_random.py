"""Counter-based random numbers keyed per world: draws that depend on a world's key, not on its batch.

A ``torch.Generator`` hands out one stream of numbers, so what world w draws depends on how
many worlds came before it in the batch and on everything drawn before. Here every number
is a pure function of three things:

    (key of the world [W] int64, stream id, index of the element within the draw)

hashed with splitmix64's finaliser in torch int64 ops, vectorised over worlds (no Python
loop over worlds or elements). The same key gives bit-identical numbers in any world slot,
at any batch size, after any history, on any device.

    keys = derive_keys(level_ids, "rooms", repr(params))    # [W] int64, one key per world
    rng = KeyedRandom(keys)
    xy = rng.uniform("spawn", (A, 2), low=-1.5, high=1.5)   # [W, A, 2] float32 in [low, high)
    order = rng.permutation("cells", 9)                     # [W, 9] int64, a permutation per world
    doors = rng.randint("doors", 0, 3, (4,))                # [W, 4] int64 in [0, 3)
    noise = rng.normal("jitter", (A,), std=0.1)             # [W, A]
    open_ = rng.bernoulli("open", 0.3, (12,))               # [W, 12] bool
    picks = rng.choice("goals", 9, 2)                       # [W, 2]: 2 of range(9) without replacement

Streams: every call names its stream (an int in [0, 2**63) or a str); calls with different
streams are independent, and a call repeated with the same stream and shape returns the same
numbers (the object keeps no counter: reordering code never changes a draw). Use one stream
per purpose. Element i of a draw of shape S is the flat (row-major) index i of S, so draws of
shape (A, 2) and (A + 1, 2) share their first 2A numbers: keep the shape fixed per stream if
that matters (it is a feature for "first k of n" draws).

For levels (envs): key = derive_keys(level_ids, task name, repr(task params)), then draw every
part of a reset from ``KeyedRandom(key)`` with its own stream name; the reset is then a pure
function of (task params, level id). ``derive_keys`` also makes sub-keys for independent
consumers (the appearance of a world uses ``derive_keys(ids, "appearance")``).

Quality: splitmix64 (Steele, Lea & Flood 2014; its finaliser is Stafford's Mix13), seeded per
(key, stream) by two further rounds of the finaliser, which is a bijection of 64-bit words
with full avalanche. Floats take the top 24 (float32) or 53 (float64) bits, so they lie in
[0, 1) exactly; randint takes 63 bits modulo the range (bias at most range / 2**63);
normal is Box-Muller on two float64 uniforms. Not for cryptography.

torch has no unsigned 64-bit arithmetic, so the hash runs on int64: multiplication wraps
modulo 2**64 as unsigned would, and right shifts are made logical with a mask (torch's
``>>`` on int64 is arithmetic).
"""
from __future__ import annotations

import hashlib
import math

import torch

from .validation import describe


def _int64(constant: int) -> int:
    """An unsigned 64-bit constant as the int64 with the same bits."""
    return constant - (1 << 64) if constant >= 1 << 63 else constant


GOLDEN = _int64(0x9E3779B97F4A7C15)  # 2**64 / golden ratio: splitmix64's Weyl increment
MIX_1 = _int64(0xBF58476D1CE4E5B9)
MIX_2 = _int64(0x94D049BB133111EB)
DERIVE = _int64(0xD1B54A32D192ED03)  # derive_keys' offset: its keys share no seed with the streams of KeyedRandom
STREAM_LIMIT = 2 ** 63  # integer stream ids lie in [0, STREAM_LIMIT)
MAX_ELEMENTS = 2 ** 40  # elements of one draw per world (a guard against absurd shapes)


def shift_right(x: torch.Tensor, bits: int) -> torch.Tensor:
    """Logical right shift of int64 words (torch's >> is arithmetic: it copies the sign bit)."""
    return (x >> bits) & ((1 << (64 - bits)) - 1)


def mix64(x: torch.Tensor) -> torch.Tensor:
    """splitmix64's finaliser: a bijection of 64-bit words (int64) in which every input bit
    flips every output bit with probability about 1/2."""
    x = (x ^ shift_right(x, 30)) * MIX_1
    x = (x ^ shift_right(x, 27)) * MIX_2
    return x ^ shift_right(x, 31)


def label_id(label) -> int:
    """A stream id or key label as an int64 constant: an int in [0, 2**63) as it is, a str or bytes
    by its BLAKE2b hash (stable across processes and Python versions, unlike hash())."""
    if isinstance(label, bool) or not isinstance(label, (int, str, bytes)):
        raise TypeError(f"stream must be an int in [0, 2**63) or a str, got {describe(label)}")
    if isinstance(label, int):
        if not 0 <= label < STREAM_LIMIT:
            raise ValueError(f"stream must be an int in [0, 2**63) or a str, got {label}")
        return label
    data = label.encode() if isinstance(label, str) else label
    # The top bit set keeps hashed labels apart from every integer id.
    return _int64(int.from_bytes(hashlib.blake2b(data, digest_size=8).digest(), "little") | 1 << 63)


def as_keys(keys, name: str = "keys") -> torch.Tensor:
    """keys [W] as int64 (any integer dtype; 0-d is one world), else TypeError / ValueError naming `name`."""
    if not isinstance(keys, torch.Tensor):
        raise TypeError(f"{name} must be an int64 tensor of shape [W] (one key per world), got {describe(keys)}")
    if keys.is_floating_point() or keys.is_complex() or keys.dtype == torch.bool:
        raise TypeError(f"{name} must be an integer tensor of shape [W] (one key per world), got dtype {keys.dtype}")
    if keys.dtype in (torch.uint16, torch.uint32, torch.uint64):
        raise TypeError(f"{name} must be a signed integer tensor (int64) of shape [W], got dtype {keys.dtype}")
    keys = keys.detach().reshape(1) if keys.ndim == 0 else keys.detach()
    if keys.ndim != 1:
        raise ValueError(f"{name} must have shape [W] (one key per world), got shape {list(keys.shape)}")
    return keys.to(torch.int64)


def derive_keys(keys, *labels) -> torch.Tensor:
    """[W] int64 keys made from `keys` [W] and each label in turn (ints in [0, 2**63) or strs):
    a pure function, so derive_keys(ids, "appearance") names the same keys wherever it runs."""
    keys = as_keys(keys)
    for label in labels:
        keys = mix64(mix64(keys + DERIVE) ^ mix64(torch.tensor(label_id(label), dtype=torch.int64)))
    return keys


def _shape(shape) -> tuple:
    if isinstance(shape, bool) or not isinstance(shape, (int, tuple, list, torch.Size)):
        raise TypeError(f"shape must be an int or a tuple of ints (the shape per world), got {describe(shape)}")
    shape = (shape,) if isinstance(shape, int) else tuple(shape)
    if any(isinstance(n, bool) or not isinstance(n, int) or n < 0 for n in shape):
        raise ValueError(f"shape must be non-negative ints (the shape per world), got {shape}")
    if math.prod(shape) > MAX_ELEMENTS:
        raise ValueError(f"shape must have at most {MAX_ELEMENTS} elements per world, got {shape}")
    return shape


class KeyedRandom:
    """Random numbers of W worlds, each a pure function of its world's key; see the module docstring.

    keys: [W] integer tensor (its device is the device of every draw). Every method takes the
    stream first and returns [W, *shape]."""

    def __init__(self, keys):
        self.keys = as_keys(keys)
        self._base = mix64(self.keys + GOLDEN)  # [W]: the per-world half of every stream's seed

    @property
    def num_worlds(self) -> int:
        return self.keys.shape[0]

    def bits(self, stream, shape=()) -> torch.Tensor:
        """[W, *shape] int64: 64 random bits per element (all 2**64 words equally likely)."""
        shape = _shape(shape)
        seed = mix64(self._base ^ mix64(torch.tensor(label_id(stream), dtype=torch.int64, device=self.keys.device)))
        index = torch.arange(1, math.prod(shape) + 1, dtype=torch.int64, device=self.keys.device)
        return mix64(seed[:, None] + index * GOLDEN).reshape(self.num_worlds, *shape)

    def uniform(self, stream, shape=(), *, low=0.0, high=1.0, dtype=torch.float32) -> torch.Tensor:
        """[W, *shape] floats in [low, high) (low / high: numbers or tensors broadcastable to
        [W, *shape]); with the defaults exactly in [0, 1), from 24 (float32) or 53 (float64) bits."""
        if dtype not in (torch.float32, torch.float64):
            raise ValueError(f"dtype must be torch.float32 or torch.float64, got {dtype}")
        mantissa = 24 if dtype == torch.float32 else 53
        unit = shift_right(self.bits(stream, shape), 64 - mantissa).to(dtype) * 2.0 ** -mantissa
        if isinstance(low, (int, float)) and isinstance(high, (int, float)) and (low, high) == (0.0, 1.0):
            return unit
        low_t, high_t = (torch.as_tensor(v, dtype=dtype, device=self.keys.device) for v in (low, high))
        if not bool((high_t >= low_t).all()) or not bool(torch.isfinite(high_t - low_t).all()):
            raise ValueError(f"uniform needs finite low <= high, got low={describe(low)}, high={describe(high)}")
        return low_t + unit * (high_t - low_t)

    def randint(self, stream, low, high, shape=()) -> torch.Tensor:
        """[W, *shape] int64 in [low, high) (ints, or int tensors broadcastable to [W, *shape]);
        high - low in [1, 2**62]."""
        low_t, high_t = (torch.as_tensor(v, device=self.keys.device) for v in (low, high))
        if low_t.is_floating_point() or high_t.is_floating_point() or low_t.dtype == torch.bool:
            raise TypeError(f"randint needs integer low and high, got low={describe(low)}, high={describe(high)}")
        low_t, high_t = low_t.to(torch.int64), high_t.to(torch.int64)
        span = high_t - low_t
        if not bool(((span >= 1) & (span <= 2 ** 62) & (high_t > low_t)).all()):
            raise ValueError(f"randint needs low < high with high - low <= 2**62, got low={describe(low)}, "
                             f"high={describe(high)}")
        return low_t + torch.remainder(shift_right(self.bits(stream, shape), 1), span)

    def normal(self, stream, shape=(), *, mean=0.0, std=1.0, dtype=torch.float32) -> torch.Tensor:
        """[W, *shape] normal numbers (Box-Muller on two float64 uniforms per element)."""
        shape = _shape(shape)
        pair = self.uniform(stream, (*shape, 2), dtype=torch.float64)
        radius = torch.sqrt(-2.0 * torch.log1p(-pair[..., 0]))  # 1 - u lies in (0, 1]: the log is finite
        value = radius * torch.cos(2 * math.pi * pair[..., 1])
        return (mean + std * value).to(dtype)

    def bernoulli(self, stream, p, shape=()) -> torch.Tensor:
        """[W, *shape] bool, True with probability p (a number or a tensor broadcastable to [W, *shape])."""
        p_t = torch.as_tensor(p, dtype=torch.float64, device=self.keys.device)
        if not bool(((p_t >= 0) & (p_t <= 1)).all()):
            raise ValueError(f"bernoulli needs probabilities p in [0, 1], got {describe(p)}")
        return self.uniform(stream, shape, dtype=torch.float64) < p_t

    def permutation(self, stream, n: int) -> torch.Tensor:
        """[W, n] int64: a uniformly random permutation of range(n) per world."""
        if isinstance(n, bool) or not isinstance(n, int) or n < 0:
            raise ValueError(f"n must be an int >= 0, got {describe(n)}")
        # Sorting independent 64-bit words: every order is equally likely (ties have odds ~n**2 / 2**64).
        return torch.argsort(self.bits(stream, (n,)), dim=-1, stable=True)

    def choice(self, stream, n: int, k: int) -> torch.Tensor:
        """[W, k] int64: k distinct values of range(n) per world, in random order (without replacement)."""
        if isinstance(k, bool) or not isinstance(k, int) or not isinstance(n, int) or not 0 <= k <= n:
            raise ValueError(f"choice needs ints 0 <= k <= n, got n={describe(n)}, k={describe(k)}")
        return self.permutation(stream, n)[:, :k]
