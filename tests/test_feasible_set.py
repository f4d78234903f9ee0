"""The feasible sets' compiled kernel against a NumPy reference written from the module
docstring's equations, non-finite starts, and the memo of the last call."""

import dataclasses

import numpy as np
import pytest

from ace_drake.control import feasible_set
from ace_drake.control.feasible_set import FeasibleSets, InfeasibleStartError, feasible_sets, feasible_sets_batch, in_invariant_set, invariance_pad
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


def reference_pad(towards, A, ramp):
    """invariance_pad in NumPy array operations (module docstring, part 2)."""
    ramped = np.maximum(towards + 0.5 * A * ramp, 0.0)
    stopping = np.maximum(towards, 0.0) * ramp + A * ramp * ramp / 3.0 + ramped * CONTROL.reaction_time + ramped**2 / (2.0 * CONTROL.stop_fraction * A)
    turning = np.minimum(towards, 0.0) ** 2 / (2.0 * CONTROL.reach_fraction * A)
    return np.maximum(stopping, turning)


def reference_sets(q0, v0, a0):
    """The sets (B, 8, ...) and feasibility (B, 8) of starts (B, 8) in NumPy array operations, on
    the whole velocity grid: the kernel's reference."""
    sides = np.array([1.0, -1.0])[:, None, None, None]  # the upper bound (+1) and the lower, mirrored (-1)
    A, V = LIMITS.acceleration, LIMITS.velocity
    A_r = CONTROL.reach_fraction * A
    h = CONTROL.knot_samples * PERIOD
    rest = CONTROL.segment_samples * PERIOD - h
    ramp = feasible_set.ramp_time(CONTROL, PERIOD)
    q1 = q0 + v0 * h + a0 * h * h / 3.0
    v1 = np.clip(v0 + 0.5 * a0 * h, -V, V)
    excess = np.maximum(sides * (v0 + 0.5 * a0 * h) - V, 0.0)
    signed_q1, signed_v1 = sides * q1 - 2.0 * h * excess, sides * v1
    signed_limit = np.stack([LIMITS.upper, -LIMITS.lower])[:, None, None, :]

    def bounds(v):
        x = sides * v
        peak = np.minimum(0.5 * (A_r * rest + signed_v1 + x), V)
        reach = signed_q1 - (signed_v1**2 + x**2) / (2.0 * A_r) + peak * rest + peak * (signed_v1 + x) / A_r - peak**2 / A_r - 0.5 * h * np.abs(peak - x)
        side = sides * np.minimum(reach, signed_limit - reference_pad(x, A, ramp))
        return side[1], side[0]

    grid = np.linspace(0.0, 1.0, feasible_set.VELOCITY_GRID)[:, None, None]
    v_low, v_high = np.maximum(-V, v1 - A_r * rest), np.minimum(V, v1 + A_r * rest)
    lo, hi = bounds(v_low + grid * (v_high - v_low))
    open_ = hi >= lo
    feasible = np.any(open_, axis=0)
    first, last = np.argmax(open_, axis=0), open_.shape[0] - 1 - np.argmax(open_[::-1], axis=0)
    v_low, v_high = v_low + grid[first, 0, 0] * (v_high - v_low), v_low + grid[last, 0, 0] * (v_high - v_low)
    K = CONTROL.boundary_samples
    fractions = np.append(np.linspace(0.0, 1.0, K), 0.5)[:, None, None]
    v = v_low + fractions * (v_high - v_low)  # (K + 1, B, 8): the vertices' velocities, then the centre's
    lo, hi = bounds(v)
    hi = np.maximum(hi, lo)
    centre = np.stack([0.5 * (lo[-1] + hi[-1]), v[-1]], axis=-1)
    lo, hi, v = (np.moveaxis(x[:-1], 0, -1) for x in (lo, hi, v))
    vertices = np.concatenate([np.stack([hi, v], axis=-1), np.stack([lo, v], axis=-1)[..., ::-1, :]], axis=-2)
    edges = np.roll(vertices, -1, axis=-2) - vertices
    normals = np.stack([edges[..., 1], -edges[..., 0]], axis=-1)
    offsets = np.einsum("...ek,...ek->...e", normals, vertices)
    scale = np.maximum(np.stack([0.5 * (hi.max(axis=-1) - lo.min(axis=-1)), 0.5 * (v_high - v_low)], axis=-1), 1e-12)
    return FeasibleSets(centre=centre, scale=scale, vertices=vertices, normals=normals, offsets=offsets), feasible


@pytest.mark.parametrize("count", [1, 3, 4, 64])
def test_the_kernel_equals_the_numpy_reference_bit_for_bit(count):
    q, v, a = random_starts(np.random.default_rng(count), count)
    sets, feasible = feasible_set._feasible_sets(q, v, a, LIMITS, CONTROL, PERIOD)
    reference, reference_feasible = reference_sets(q, v, a)
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
    fresh, _ = reference_sets(q[None], v[None], a[None])
    other = feasible_sets(q, v + 0.1, a, LIMITS, CONTROL, PERIOD)  # a different start is computed again
    assert not np.array_equal(other.centre, single.centre)
    np.testing.assert_array_equal(single.vertices, fresh.vertices[0])


def test_the_invariance_pad_equals_its_numpy_form_and_keeps_nan():
    rng = np.random.default_rng(5)
    towards = rng.uniform(-1.2, 1.2, (50, 8)) * LIMITS.velocity
    ramp = feasible_set.ramp_time(CONTROL, PERIOD)
    np.testing.assert_array_equal(invariance_pad(towards, LIMITS, CONTROL, ramp), reference_pad(towards, LIMITS.acceleration, ramp))
    towards[3, 2] = np.nan
    pad = invariance_pad(towards, LIMITS, CONTROL, ramp)
    assert np.isnan(pad[3, 2]) and np.isfinite(np.delete(pad.ravel(), 3 * 8 + 2)).all()
    q = np.array(RobotScenario().ready_pose, dtype=float)
    assert in_invariant_set(q, np.zeros(8), LIMITS, CONTROL, PERIOD).all()
    assert not in_invariant_set(q, np.where(np.arange(8) == 2, np.nan, 0.0), LIMITS, CONTROL, PERIOD)[2]


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_a_non_finite_joint_has_an_empty_set_and_leaves_the_others_alone(bad):
    q, v, a = random_starts(np.random.default_rng(9), 4)
    q[1, 5] = v[2, 0] = a[3, 7] = bad
    sets, feasible = feasible_set._feasible_sets(q, v, a, LIMITS, CONTROL, PERIOD)
    clean, clean_feasible = feasible_set._feasible_sets(*random_starts(np.random.default_rng(9), 4), LIMITS, CONTROL, PERIOD)
    bad_joints = np.zeros((4, 8), dtype=bool)
    bad_joints[1, 5] = bad_joints[2, 0] = bad_joints[3, 7] = True
    assert not feasible[bad_joints].any()
    np.testing.assert_array_equal(feasible[~bad_joints], clean_feasible[~bad_joints])
    for field in dataclasses.fields(sets):
        assert np.isnan(getattr(sets, field.name)[bad_joints]).all()
        np.testing.assert_array_equal(getattr(sets, field.name)[~bad_joints], getattr(clean, field.name)[~bad_joints])
    with pytest.raises(InfeasibleStartError, match="gantry_x"):
        feasible_sets(q[2], v[2], a[2], LIMITS, CONTROL, PERIOD)


def reference_boundary_distance(sets: FeasibleSets, direction: np.ndarray) -> np.ndarray:
    """``FeasibleSets.boundary_distance`` in NumPy (its former form): the reference of the kernel."""
    along = np.einsum("...jek,...jk->...je", sets.normals, direction)  # n_e . d
    room = sets.offsets - np.einsum("...jek,...jk->...je", sets.normals, sets.centre)  # b_e - n_e . c >= 0
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        candidates = np.where(along > 1e-300, room / along, np.inf)
    return np.min(candidates, axis=-1)


@pytest.mark.parametrize("count", [1, 3, 64])
def test_the_boundary_distance_kernel_equals_the_numpy_reference_bit_for_bit(count):
    rng = np.random.default_rng(20 + count)
    q, v, a = random_starts(rng, count)
    q[0, 3] = np.nan  # an empty set with NaN fields
    sets, _ = feasible_set._feasible_sets(q, v, a, LIMITS, CONTROL, PERIOD)
    direction = rng.normal(size=(count, 8, 2)) * sets.scale
    direction[0, 1] = 0.0  # no edge ahead: inf
    direction[-1, 2, 0] = np.nan
    np.testing.assert_array_equal(sets.boundary_distance(direction), reference_boundary_distance(sets, direction))
    # Broadcast: one start's sets against many directions, and many starts' against one.
    one = sets[0]
    np.testing.assert_array_equal(one.boundary_distance(direction), reference_boundary_distance(one, direction))
    np.testing.assert_array_equal(sets.boundary_distance(direction[0]), reference_boundary_distance(sets, direction[0]))
