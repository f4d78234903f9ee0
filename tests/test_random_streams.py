"""random_streams: numpy's default_rng seeded from short integer lists, and its random, uniform and
standard_normal draws, compiled bit for bit; the batched position variates equal
draw_position_variates row by row."""

import numba
import numpy as np
import pytest

from ace_drake.perception import random_streams
from ace_drake.perception.params import PositionSensorParams
from ace_drake.perception.sensor_models import draw_position_variates


@numba.njit
def _draws(values, counts, normals, uniforms):
    """Per row: the generator of values[row, :counts[row]], then len(normals[row]) standard normals,
    then uniforms on [0.25, 1.75) (the first half) and doubles (the rest)."""
    generator, scratch = np.empty(4, np.uint64), np.empty(random_streams.GENERATOR_SCRATCH, np.uint64)
    for row in range(values.shape[0]):
        random_streams.seed_generator(values[row], counts[row], generator, scratch)
        for i in range(normals.shape[1]):
            normals[row, i] = random_streams.standard_normal(generator)
        half = uniforms.shape[1] // 2
        for i in range(half):
            uniforms[row, i] = random_streams.uniform(generator, 0.25, 1.5)
        for i in range(half, uniforms.shape[1]):
            uniforms[row, i] = random_streams.random(generator)


def test_generators_and_draws_are_default_rng_bit_for_bit():
    rng = np.random.default_rng(1)
    entropies = [[0], [1, 2], [2**64 - 1, 2], [2**32, 0, 7], [2**32 - 1, 1, 2**32 - 1], [5, 1, 3, 4], [2**63 + 11, 1, 40]]
    entropies += [[int(seed), 1, int(tick)] for seed, tick in zip(rng.integers(0, 2**64, 300, dtype=np.uint64), rng.integers(0, 5000, 300))]
    values = np.zeros((len(entropies), 4), dtype=np.uint64)
    for row, entropy in enumerate(entropies):
        values[row, : len(entropy)] = entropy
    counts = np.array([len(entropy) for entropy in entropies])
    normals, uniforms = np.empty((len(entropies), 200)), np.empty((len(entropies), 20))
    _draws(values, counts, normals, uniforms)
    for row, entropy in enumerate(entropies):
        generator = np.random.default_rng(entropy)
        assert np.array_equal(normals[row].view(np.uint64), generator.standard_normal(200).view(np.uint64)), entropy
        assert np.array_equal(uniforms[row, :10].view(np.uint64), generator.uniform(0.25, 1.75, 10).view(np.uint64)), entropy
        assert np.array_equal(uniforms[row, 10:].view(np.uint64), generator.random(10).view(np.uint64)), entropy
    assert np.sum(np.abs(normals) > 3.6541528853610087) >= 3  # the ziggurat's tail was drawn
    with pytest.raises(ValueError, match="more than 4"):
        _draws(np.array([[2**40, 2**40, 1, 0]], dtype=np.uint64), np.array([3]), normals[:1], uniforms[:1])


def test_position_variates_are_draw_position_variates_row_by_row():
    params = PositionSensorParams()
    rng = np.random.default_rng(2)
    seeds = np.concatenate([rng.integers(0, 2**63, 40), [0, 2**63 - 1]])
    ticks = np.concatenate([rng.integers(0, 3000, 40), [0, 12]])
    counts = np.concatenate([rng.integers(0, 8, 40), [7, 0]])
    ticks[counts == 0] = -1  # not drawn: any tick
    variates = random_streams.position_variates(seeds, 1, ticks, counts, params.latency_min, params.latency_max)
    start = 0
    for seed, tick, count in zip(seeds.tolist(), ticks.tolist(), counts.tolist()):
        if count:
            expected = draw_position_variates(count, params, np.random.default_rng([seed, 1, tick]))
            for name in ("dropout", "latency", "noise"):
                assert np.array_equal(getattr(variates, name)[start : start + count], getattr(expected, name)), (seed, tick, name)
        start += count
    assert start == len(variates.dropout) == len(variates.latency) == len(variates.noise)
    with pytest.raises(ValueError, match="non-negative"):
        random_streams.position_variates(np.array([-1]), 1, np.array([0]), np.array([1]), params.latency_min, params.latency_max)
