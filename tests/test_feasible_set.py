"""The feasible sets' compiled kernel against its NumPy reference, and the memo of the last call."""

import dataclasses

import numpy as np
import pytest

from ace_drake.control import feasible_set
from ace_drake.control.feasible_set import feasible_sets, feasible_sets_batch
from ace_drake.control.params import ControlParams
from ace_drake.control.trajectory import CommandLimits
from ace_drake.robot.params import RobotLimits, RobotScenario

CONTROL = ControlParams()
LIMITS = CommandLimits.from_config(RobotLimits(), CONTROL)
PERIOD = 0.001


def random_starts(rng, count):
    """Starts (count, 8) each across the limits, a third of them within 5 cm or rad of a limit
    (narrow and empty sets), velocities up to 10% beyond the limit."""
    q = rng.uniform(LIMITS.lower, LIMITS.upper, (count, 8))
    edge = count // 3
    near_upper = rng.random((edge, 8)) < 0.5
    q[:edge] = np.where(near_upper, LIMITS.upper - rng.uniform(0, 0.05, (edge, 8)), LIMITS.lower + rng.uniform(0, 0.05, (edge, 8)))
    v = rng.uniform(-1.1, 1.1, (count, 8)) * LIMITS.velocity
    a = rng.uniform(-1.0, 1.0, (count, 8)) * LIMITS.acceleration
    return q, v, a


@pytest.mark.parametrize("count", [1, 3, 4, 64])
def test_the_kernel_equals_the_numpy_reference_bit_for_bit(count):
    q, v, a = random_starts(np.random.default_rng(count), count)
    sets, feasible = feasible_set._feasible_sets(q, v, a, LIMITS, CONTROL, PERIOD)
    reference, reference_feasible = feasible_set._feasible_sets_numpy(q, v, a, LIMITS, CONTROL, PERIOD)
    np.testing.assert_array_equal(feasible, reference_feasible)
    for field in dataclasses.fields(sets):
        np.testing.assert_array_equal(getattr(sets, field.name), getattr(reference, field.name))


def test_the_last_sets_are_reused_read_only_whatever_the_batch_shape():
    q, v, a = np.array(RobotScenario().ready_pose, dtype=float), np.full(8, 0.3), np.zeros(8)
    single = feasible_sets(q, v, a, LIMITS, CONTROL, PERIOD)
    batch, feasible, reasons = feasible_sets_batch(q[None], v[None], a[None], LIMITS, CONTROL, PERIOD)
    assert feasible.shape == (1,) and reasons == [""]
    for field in dataclasses.fields(single):
        assert np.shares_memory(getattr(batch, field.name), getattr(single, field.name))  # the first call's sets
        np.testing.assert_array_equal(getattr(batch, field.name)[0], getattr(single, field.name))
        assert not getattr(single, field.name).flags.writeable
    fresh, _ = feasible_set._feasible_sets_numpy(q[None], v[None], a[None], LIMITS, CONTROL, PERIOD)
    other = feasible_sets(q, v + 0.1, a, LIMITS, CONTROL, PERIOD)  # a different start is computed again
    assert not np.array_equal(other.centre, single.centre)
    np.testing.assert_array_equal(single.vertices, fresh.vertices[0])
