"""numpy's default random generator, compiled: ``numpy.random.default_rng(entropy)`` seeded from a
short list of integers and its uniform and standard-normal draws, bit for bit, so that batched
sensors can seed and draw a generator per (environment, trigger) inside one compiled loop instead
of one Python Generator each (tests/test_random_streams.py checks them against numpy).

Written out from numpy (2.x): SeedSequence's pool mixing and ``generate_state``
(numpy/random/bit_generator.pyx), PCG64's seeding and XSL-RR output of its 128-bit LCG
(pcg64.h), and Generator's ``random`` (the top 53 bits), ``uniform`` (low + (high - low) u) and
``standard_normal`` (the ziggurat of distributions.c, with numpy's tables as numba ships them).

A generator is a uint64 array (4,): [state high, state low, increment high, increment low].
"""

from __future__ import annotations

import math

import numba
import numba.np.random._constants as ziggurat
import numpy as np

from ace_drake.perception.sensor_models import PositionVariates

MAX_ENTROPY_WORDS = 4  # SeedSequence's pool: longer entropy is mixed in differently (not written here)
GENERATOR_SCRATCH = 24  # uint64 work space of ``seed_generator``

MASK32 = 0xFFFFFFFF  # a 32-bit word (SeedSequence works in them; camera_segment checks its seed words against it)
_HASH_INIT_A, _HASH_MULT_A = 0x43B0D7E5, 0x931E8875
_HASH_INIT_B, _HASH_MULT_B = 0x8B51F9DD, 0x58F38DED
_MIX_MULT_L, _MIX_MULT_R = 0xCA01F9DD, 0x4973F715
_PCG64_MULTIPLIER = 0x2360ED051FC65DA44385DF649FCCF645
_PCG64_MULTIPLIER_HIGH = np.uint64(_PCG64_MULTIPLIER >> 64)
_PCG64_MULTIPLIER_LOW = np.uint64(_PCG64_MULTIPLIER & 0xFFFFFFFFFFFFFFFF)
_ZIGGURAT_KI = np.ascontiguousarray(ziggurat.ki_double, dtype=np.uint64)  # (256,) each
_ZIGGURAT_WI = np.ascontiguousarray(ziggurat.wi_double, dtype=np.float64)
_ZIGGURAT_FI = np.ascontiguousarray(ziggurat.fi_double, dtype=np.float64)
_ZIGGURAT_R = float(ziggurat.ziggurat_nor_r)
_ZIGGURAT_INV_R = float(ziggurat.ziggurat_nor_inv_r)


def _hash_constants(init: int, mult: int, count: int) -> list[tuple[int, int]]:
    """The data-independent (xor, multiplier) pairs of SeedSequence's successive hashes."""
    pairs, value = [], init
    for _ in range(count):
        following = (value * mult) & MASK32
        pairs.append((value, following))
        value = following
    return pairs


_MIX_HASHES = np.array(_hash_constants(_HASH_INIT_A, _HASH_MULT_A, MAX_ENTROPY_WORDS * MAX_ENTROPY_WORDS), dtype=np.uint64)  # (16, 2)
_STATE_HASHES = np.array(_hash_constants(_HASH_INIT_B, _HASH_MULT_B, 2 * MAX_ENTROPY_WORDS), dtype=np.uint64)  # (8, 2)


@numba.njit(cache=True)
def _hash(value, xor, mult):
    """SeedSequence's hashmix of a 32-bit word held in a uint64."""
    value = ((value ^ xor) * mult) & np.uint64(MASK32)
    return value ^ (value >> np.uint64(16))


@numba.njit(cache=True)
def _seed_words(entropy, pool, words, out):
    """SeedSequence(entropy words)'s pool mixing and ``generate_state(4, uint64)``: entropy (4,)
    uint64, the 32-bit entropy words padded with zeros (shorter entropy hashes zeros into the
    pool); out (4,) uint64, the 64-bit halves [high, low] of PCG64's initstate, then of its
    initseq; pool (4,) and words (8,) uint64 are scratch."""
    mask, shift = np.uint64(MASK32), np.uint64(32)
    left, right = np.uint64(_MIX_MULT_L), np.uint64(_MIX_MULT_R)
    constant = 0
    for i in range(MAX_ENTROPY_WORDS):
        pool[i] = _hash(entropy[i], _MIX_HASHES[constant, 0], _MIX_HASHES[constant, 1])
        constant += 1
    for source in range(MAX_ENTROPY_WORDS):
        for target in range(MAX_ENTROPY_WORDS):
            if source != target:
                hashed = _hash(pool[source], _MIX_HASHES[constant, 0], _MIX_HASHES[constant, 1])
                constant += 1
                mixed = (left * pool[target] - right * hashed) & mask
                pool[target] = mixed ^ (mixed >> np.uint64(16))
    for i in range(8):
        words[i] = _hash(pool[i % MAX_ENTROPY_WORDS], _STATE_HASHES[i, 0], _STATE_HASHES[i, 1])
    for i in range(4):  # little-endian pairs of 32-bit words
        out[i] = words[2 * i] | (words[2 * i + 1] << shift)


@numba.njit(cache=True, inline="always")
def _multiply_high(a, b):
    """The high 64 bits of the 128-bit product of uint64 a and b."""
    mask, shift = np.uint64(MASK32), np.uint64(32)
    a_low, a_high, b_low, b_high = a & mask, a >> shift, b & mask, b >> shift
    low_low, low_high, high_low = a_low * b_low, a_low * b_high, a_high * b_low
    middle = (low_low >> shift) + (low_high & mask) + (high_low & mask)
    return a_high * b_high + (low_high >> shift) + (high_low >> shift) + (middle >> shift)


@numba.njit(cache=True, inline="always")
def next_uint64(generator):
    """PCG64's next 64-bit output: the state steps (state <- state * multiplier + increment, mod
    2**128), then XSL-RR of it."""
    high, low = generator[0], generator[1]
    product_high = _multiply_high(low, _PCG64_MULTIPLIER_LOW) + high * _PCG64_MULTIPLIER_LOW + low * _PCG64_MULTIPLIER_HIGH
    product_low = low * _PCG64_MULTIPLIER_LOW
    low = product_low + generator[3]
    high = product_high + generator[2] + (np.uint64(1) if low < product_low else np.uint64(0))
    generator[0], generator[1] = high, low
    rotation = high >> np.uint64(58)
    value = high ^ low
    return (value >> rotation) | (value << ((np.uint64(64) - rotation) & np.uint64(63)))


@numba.njit(cache=True)
def seed_generator(values, count, generator, scratch):
    """generator (4,) <- ``numpy.random.default_rng([values[0], ..., values[count - 1]])``'s PCG64,
    values uint64 (each coerced to 32-bit words, at least one, as SeedSequence does; at most
    ``MAX_ENTROPY_WORDS`` words in all); scratch (``GENERATOR_SCRATCH``,) uint64. PCG64's seeding:
    state 0, increment 2 initseq + 1, step, add initstate, step."""
    entropy, pool, words, state = scratch[:4], scratch[4:8], scratch[8:16], scratch[16:20]
    entropy[:] = 0
    length = 0
    for i in range(count):
        value = values[i]
        while True:
            if length == MAX_ENTROPY_WORDS:
                raise ValueError("seed_generator: the entropy needs more than 4 32-bit words")
            entropy[length] = value & np.uint64(MASK32)
            length += 1
            value >>= np.uint64(32)
            if value == 0:
                break
    _seed_words(entropy, pool, words, state)
    one = np.uint64(1)
    increment_high = (state[2] << one) | (state[3] >> np.uint64(63))
    increment_low = (state[3] << one) | one
    low = increment_low + state[1]  # the first step from state 0 gives the increment
    generator[0] = increment_high + state[0] + (one if low < increment_low else np.uint64(0))
    generator[1] = low
    generator[2], generator[3] = increment_high, increment_low
    next_uint64(generator)


@numba.njit(cache=True, inline="always")
def random(generator):
    """Generator.random's double in [0, 1): the top 53 bits of the next output."""
    return np.float64(next_uint64(generator) >> np.uint64(11)) * (1.0 / 9007199254740992.0)


@numba.njit(cache=True, inline="always")
def uniform(generator, low, width):
    """Generator.uniform(low, low + width)'s draw (numpy computes width = high - low first)."""
    return low + width * random(generator)


@numba.njit(cache=True)
def standard_normal(generator):
    """Generator.standard_normal's draw (numpy's ziggurat, ``random_standard_normal``)."""
    while True:
        r = next_uint64(generator)
        index = np.intp(r & np.uint64(0xFF))
        r >>= np.uint64(8)
        sign = r & np.uint64(1)
        magnitude = (r >> np.uint64(1)) & np.uint64(0x000FFFFFFFFFFFFF)
        x = np.float64(magnitude) * _ZIGGURAT_WI[index]
        if sign:
            x = -x
        if magnitude < _ZIGGURAT_KI[index]:
            return x  # 99.3 % of draws
        if index == 0:  # the tail
            while True:
                xx = -_ZIGGURAT_INV_R * math.log1p(-random(generator))
                yy = -math.log1p(-random(generator))
                if yy + yy > xx * xx:
                    return -(_ZIGGURAT_R + xx) if (magnitude >> np.uint64(8)) & np.uint64(1) else _ZIGGURAT_R + xx
        elif (_ZIGGURAT_FI[index - 1] - _ZIGGURAT_FI[index]) * random(generator) + _ZIGGURAT_FI[index] < math.exp(-0.5 * x * x):
            return x


# ---------------------------------------------------------------------------------- batched draws


@numba.njit(cache=True)
def _position_variates(seeds, stream, ticks, counts, latency_min, latency_width, dropout, latency, noise):
    """``position_variates``' draws into dropout, latency (n,) and noise (n, 3)."""
    generator, scratch, values = np.empty(4, np.uint64), np.empty(GENERATOR_SCRATCH, np.uint64), np.empty(3, np.uint64)
    start = 0
    for b in range(seeds.shape[0]):
        count = counts[b]
        if count == 0:
            continue
        values[0], values[1], values[2] = seeds[b], stream, ticks[b]
        seed_generator(values, 3, generator, scratch)
        for i in range(start, start + count):
            dropout[i] = random(generator)
        for i in range(start, start + count):
            latency[i] = uniform(generator, latency_min, latency_width)
        for i in range(start, start + count):
            for axis in range(3):
                noise[i, axis] = standard_normal(generator)
        start += count


def position_variates(seeds: np.ndarray, stream: int, ticks: np.ndarray, counts: np.ndarray, latency_min: float, latency_max: float) -> PositionVariates:
    """``sensor_models.draw_position_variates`` of B sensors in one compiled pass, concatenated in
    row order: sensor b's counts[b] samples drawn from ``numpy.random.default_rng([seeds[b],
    stream, ticks[b]])`` (n uniforms (dropout), n uniforms on [latency_min, latency_max] s, 3n
    standard normals), bit for bit. seeds, ticks, counts (B,) integers, non-negative where
    counts are positive (the seed, stream and tick take 4 32-bit words at most)."""
    seeds, ticks, counts = np.asarray(seeds), np.asarray(ticks), np.asarray(counts, dtype=np.int64)
    active = counts > 0
    if stream < 0 or (counts < 0).any() or (seeds[active] < 0).any() or (ticks[active] < 0).any():
        raise ValueError("position_variates: seeds, stream, ticks and counts must be non-negative")
    total = int(counts.sum())
    dropout, latency, noise = np.empty(total), np.empty(total), np.empty((total, 3))
    width = float(latency_max) - float(latency_min)
    if not math.isfinite(width):
        raise OverflowError("position_variates: latency_max - latency_min exceeds the float range")
    _position_variates(seeds.astype(np.uint64), np.uint64(stream), ticks.astype(np.uint64), counts, float(latency_min), width, dropout, latency, noise)
    return PositionVariates(dropout, latency, noise)
