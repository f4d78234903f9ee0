"""Feasible sets and the action mapping of paper eq. (12): centre to centre, boundary to
boundary, inside the feasible set, and inverted exactly."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from ace_drake.control.action_mapping import ACTION_SIZE, inverse_map_action, map_action
from ace_drake.control.feasible_set import InfeasibleStartError, feasible_sets, feasible_sets_batch, in_invariant_set
from ace_drake.control.params import ControlParams
from ace_drake.control.trajectory import CommandLimits
from ace_drake.robot.params import RobotLimits, RobotScenario
from test_feasible_set import reference_boundary_distance

CONTROL = ControlParams()
LIMITS = CommandLimits.from_config(RobotLimits(), CONTROL)
PERIOD = 0.001
READY = np.array(RobotScenario().ready_pose)


def invariant_state(seed: int, edge: bool = False) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A random joint state (q, v, a) in the control-invariant set; with ``edge``, pushed onto its
    boundary towards a position limit (the hardest starts)."""
    rng = np.random.default_rng(seed)
    while True:
        v = rng.uniform(-1, 1, 8) * LIMITS.velocity * rng.choice([0.2, 1.0])
        q = rng.uniform(LIMITS.lower, LIMITS.upper)
        a = rng.uniform(-1, 1, 8) * LIMITS.acceleration
        if edge:
            # Slide q to where the invariant set ends in the direction of motion.
            for _ in range(40):
                step = q + np.sign(v + 1e-9) * 0.02 * (LIMITS.upper - LIMITS.lower)
                inside = in_invariant_set(step, v, LIMITS, CONTROL, PERIOD)
                q = np.where(inside, step, q)
            a = np.sign(v + 1e-9) * LIMITS.acceleration  # accelerating towards the limit
        if np.all(in_invariant_set(q, v, LIMITS, CONTROL, PERIOD)):
            return q, v, a


actions = st.lists(st.floats(-1.0, 1.0, allow_nan=False), min_size=ACTION_SIZE, max_size=ACTION_SIZE).map(np.array)
extreme_actions = st.lists(st.sampled_from([-1.0, 1.0]), min_size=ACTION_SIZE, max_size=ACTION_SIZE).map(np.array)


def test_at_rest_the_centre_is_standing_still():
    sets = feasible_sets(READY, np.zeros(8), np.zeros(8), LIMITS, CONTROL, PERIOD)
    q, v = map_action(np.zeros(ACTION_SIZE), sets)
    np.testing.assert_allclose(q, READY, atol=1e-12)
    np.testing.assert_allclose(v, 0.0, atol=1e-12)
    # Far from the limits the velocity range is what A_r reaches over the segment after the
    # first knot interval, 0.8 * 0.85 * 40 m/s^2 * 31 ms for the gantry, less the fastest corners
    # that the ramp pad of the final acceleration change trims (3%).
    assert 0.95 * 0.8 * 0.85 * 40.0 * 0.031 < sets.scale[0, 1] <= 0.8 * 0.85 * 40.0 * 0.031


@settings(max_examples=300, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), edge=st.booleans(), action=st.one_of(actions, extreme_actions))
def test_every_action_maps_into_the_feasible_and_invariant_sets(seed, edge, action):
    q0, v0, a0 = invariant_state(seed, edge)
    sets = feasible_sets(q0, v0, a0, LIMITS, CONTROL, PERIOD)
    q, v = map_action(action, sets)
    assert np.all(sets.contains(np.stack([q, v], axis=-1)))
    assert np.all(in_invariant_set(q, v, LIMITS, CONTROL, PERIOD, tolerance=1e-9))  # on its boundary up to round-off


@settings(max_examples=300, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), edge=st.booleans(), action=actions)
def test_the_inverse_recovers_the_action(seed, edge, action):
    sets = feasible_sets(*invariant_state(seed, edge), LIMITS, CONTROL, PERIOD)
    np.testing.assert_allclose(inverse_map_action(*map_action(action, sets), sets), action, atol=1e-9)


@settings(max_examples=200, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), edge=st.booleans(), action=actions)
def test_centre_to_centre_and_boundary_to_boundary(seed, edge, action):
    sets = feasible_sets(*invariant_state(seed, edge), LIMITS, CONTROL, PERIOD)
    q, v = map_action(np.zeros(ACTION_SIZE), sets)
    np.testing.assert_allclose(np.stack([q, v], axis=-1), sets.centre, atol=1e-12)
    # Scale the action onto the square's boundary: every joint's pair has infinity-norm 1.
    pairs = action.reshape(2, 8)
    size = np.max(np.abs(pairs), axis=0)
    on_square = np.where(size > 1e-6, pairs / np.maximum(size, 1e-6), 1.0).ravel()
    q, v = map_action(on_square, sets)
    # On the boundary: the ray from the centre through the point leaves the set right there.
    t = sets.boundary_distance(np.stack([q, v], axis=-1) - sets.centre)
    np.testing.assert_allclose(t, 1.0, rtol=1e-9)
    # And the mapping is monotone along a ray: half the action lands half way.
    q_half, v_half = map_action(0.5 * on_square, sets)
    np.testing.assert_allclose(np.stack([q_half, v_half], axis=-1), 0.5 * (sets.centre + np.stack([q, v], axis=-1)), atol=1e-12)


def test_points_outside_the_set_invert_beyond_the_box():
    sets = feasible_sets(READY, np.zeros(8), np.zeros(8), LIMITS, CONTROL, PERIOD)
    q, v = map_action(np.ones(ACTION_SIZE), sets)
    beyond = inverse_map_action(sets.centre[:, 0] + 2.0 * (q - sets.centre[:, 0]), sets.centre[:, 1] + 2.0 * (v - sets.centre[:, 1]), sets)
    np.testing.assert_allclose(beyond, 2.0, rtol=1e-9)


def test_bad_actions_raise():
    sets = feasible_sets(READY, np.zeros(8), np.zeros(8), LIMITS, CONTROL, PERIOD)
    with pytest.raises(ValueError, match="16 values"):
        map_action(np.zeros(8), sets)
    with pytest.raises(ValueError, match=r"\[-1, 1\]"):
        map_action(np.full(ACTION_SIZE, 1.5), sets)
    with pytest.raises(ValueError, match=r"\[-1, 1\]"):
        map_action(np.full(ACTION_SIZE, np.nan), sets)


def test_a_start_outside_the_invariant_set_raises():
    # At the upper limit of gantry_x, moving towards it at full speed: no stop is possible.
    q = READY.copy()
    q[0] = LIMITS.upper[0]
    v = np.zeros(8)
    v[0] = LIMITS.velocity[0]
    with pytest.raises(InfeasibleStartError, match="gantry_x"):
        feasible_sets(q, v, np.zeros(8), LIMITS, CONTROL, PERIOD)


@settings(max_examples=300, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), edge=st.booleans(), action=st.one_of(actions, extreme_actions), fraction=st.floats(-1.0, 1.0))
def test_mapped_states_are_safe_starts_for_a_reset_or_stop(seed, edge, action, fraction):
    """Whatever terminal acceleration the QP ends with (within CommandLimits.acceleration_bounds),
    a jerk-limited reset or protective stop from the mapped state stays within the limits
    (control.reset.is_reset_safe, proven there on its set's boundary)."""
    from ace_drake.control.reset import is_reset_safe

    sets = feasible_sets(*invariant_state(seed, edge), LIMITS, CONTROL, PERIOD)
    q, v = map_action(action, sets)
    low, high = LIMITS.acceleration_bounds(v)
    a = np.where(fraction >= 0, fraction * high, -fraction * low)
    assert np.all(is_reset_safe(q, v, a, LIMITS, CONTROL, tolerance=1e-9))


def batch_of_starts(count: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Random, edge and at-rest invariant starts (count, 8) each; every fourth made infeasible
    (a joint at its upper limit moving towards it at full speed)."""
    q, v, a = (np.array(x) for x in zip(*(invariant_state(seed, edge=seed % 3 == 1) for seed in range(count))))
    v[2::7], a[2::7] = 0.0, 0.0
    for row in range(0, count, 4):
        joint = row % 8
        q[row, joint], v[row, joint] = LIMITS.upper[joint], LIMITS.velocity[joint]
    return q, v, a


def test_a_batch_of_starts_gives_each_start_its_sets_exactly():
    q, v, a = batch_of_starts(60)
    sets, feasible, reasons = feasible_sets_batch(q, v, a, LIMITS, CONTROL, PERIOD)
    actions = np.random.default_rng(0).uniform(-1.0, 1.0, (60, ACTION_SIZE))
    q_batch, v_batch = map_action(actions, sets)
    assert sets.batch_shape == (60,) and feasible.shape == (60,) and len(reasons) == 60
    for row in range(60):
        try:
            expected = feasible_sets(q[row], v[row], a[row], LIMITS, CONTROL, PERIOD)
        except InfeasibleStartError as error:
            assert not feasible[row] and reasons[row] == str(error)
            continue
        assert feasible[row] and reasons[row] == ""
        for field in ("centre", "scale", "vertices", "normals", "offsets"):
            np.testing.assert_array_equal(getattr(sets, field)[row], getattr(expected, field))
        q_row, v_row = map_action(actions[row], expected)
        np.testing.assert_array_equal(q_batch[row], q_row)
        np.testing.assert_array_equal(v_batch[row], v_row)
    assert 10 <= np.sum(~feasible) < 60
    with pytest.raises(InfeasibleStartError, match="gantry_x"):  # the first infeasible start's
        feasible_sets(q, v, a, LIMITS, CONTROL, PERIOD)


def reference_map_action(action, sets):
    """``map_action`` in NumPy (its former form): the reference of the compiled loop."""
    action = np.asarray(action, dtype=float)
    delta = np.swapaxes(action.reshape(*action.shape[:-1], 2, 8), -1, -2)
    size = np.max(np.abs(delta), axis=-1)
    shaped = delta * sets.scale
    beta = reference_boundary_distance(sets, shaped)  # NumPy too: not the kernel under test
    step = np.where(size > 0.0, size * np.where(np.isfinite(beta), beta, 0.0), 0.0)
    y = sets.centre + step[..., None] * shaped
    return y[..., 0], y[..., 1]


def reference_inverse_map_action(q_terminal, v_terminal, sets):
    """``inverse_map_action`` in NumPy (its former form): the reference of the compiled loop."""
    y = np.stack([np.asarray(q_terminal, dtype=float), np.asarray(v_terminal, dtype=float)], axis=-1)
    offset = y - sets.centre
    to_boundary = reference_boundary_distance(sets, offset)
    unscaled = offset / sets.scale
    largest = np.max(np.abs(unscaled), axis=-1)
    with np.errstate(divide="ignore", invalid="ignore"):
        delta = np.where((largest > 0.0)[..., None], unscaled / (largest * to_boundary)[..., None], 0.0)
    pairs = np.swapaxes(delta, -1, -2)
    return pairs.reshape(*pairs.shape[:-2], ACTION_SIZE)


@pytest.mark.parametrize("count", [1, 5, 64])
def test_the_compiled_mapping_and_inverse_equal_the_numpy_reference_bit_for_bit(count):
    rng = np.random.default_rng(count)
    starts = [invariant_state(seed, edge=bool(seed % 2)) for seed in range(count)]
    q0, v0, a0 = (np.array([start[k] for start in starts]) for k in range(3))
    sets, _, _ = feasible_sets_batch(q0, v0, a0, LIMITS, CONTROL, PERIOD)
    action = rng.uniform(-1.0, 1.0, (count, ACTION_SIZE))
    action[0, :3] = 0.0
    action[0, 8] = 0.0  # joint 0 at the centre
    action[-1, 4] = action[-1, 12] = 1.0  # a corner
    for got, expected in zip(map_action(action, sets), reference_map_action(action, sets)):
        np.testing.assert_array_equal(got, expected)
    q, v = reference_map_action(action, sets)
    q, v = q + rng.normal(0.0, 0.05, q.shape), v.copy()  # some beyond the boundary
    q[0, 1], v[-1, 2] = sets.centre[0, 1, 0], np.nan
    v[0, 1] = sets.centre[0, 1, 1]  # at the centre
    np.testing.assert_array_equal(inverse_map_action(q, v, sets), reference_inverse_map_action(q, v, sets))
    # Broadcast: one start's sets for many actions.
    one = sets[0]
    for got, expected in zip(map_action(action, one), reference_map_action(action, one)):
        np.testing.assert_array_equal(got, expected)
    np.testing.assert_array_equal(inverse_map_action(q, v, one), reference_inverse_map_action(q, v, one))
