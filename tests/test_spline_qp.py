"""The jerk-minimising spline QP: exact on hand-worked cases, within the limits, agreeing across
solvers, and recursively feasible from every state the action mapping produces."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from ace_drake.control.action_mapping import ACTION_SIZE, map_action
from ace_drake.control.feasible_set import feasible_sets, feasible_sets_batch, in_invariant_set
from ace_drake.control.spline_qp import SegmentQp
from tests.test_action_mapping import CONTROL, LIMITS, PERIOD, READY, invariant_state

QP = SegmentQp(LIMITS, CONTROL.segment_samples, PERIOD, CONTROL.knot_samples)
T = CONTROL.segment_samples * PERIOD


def test_constant_acceleration_is_the_jerk_free_solution():
    v0 = np.linspace(-1.0, 1.0, 8)
    a0 = 0.3 * LIMITS.acceleration * np.linspace(1.0, -1.0, 8)
    solution = QP.solve(READY, v0, a0, READY + v0 * T + 0.5 * a0 * T**2, v0 + a0 * T)
    assert solution.success, solution.status
    trajectory = solution.trajectory
    assert trajectory.samples == 32 and trajectory.period == PERIOD
    assert np.all(np.abs(trajectory.a - a0) <= 1e-6 * LIMITS.acceleration)
    times = PERIOD * np.arange(33)[:, None]
    np.testing.assert_allclose(trajectory.q, READY + v0 * times + 0.5 * a0 * times**2, atol=1e-9)


def test_a_rest_to_rest_move_is_symmetric_and_ends_exactly():
    target = READY + 0.005  # the gantry needs 4 * 0.005 / T^2 = 20 m/s^2 of its 34
    solution = QP.solve(READY, np.zeros(8), np.zeros(8), target, np.zeros(8))
    assert solution.success, solution.status
    q, v, a = solution.trajectory.q, solution.trajectory.v, solution.trajectory.a
    np.testing.assert_allclose(q[-1], target, atol=1e-9)
    np.testing.assert_allclose(v[-1], 0.0, atol=1e-9)
    # Minimum jerk between rest states with a free end acceleration: the velocity profile is
    # symmetric in time about the middle of the segment... up to the free end acceleration.
    assert np.all(v[1:-1] > 0.0)
    assert np.all(np.abs(a) <= LIMITS.acceleration + 1e-9)


def test_an_unreachable_target_fails_without_a_trajectory():
    target = READY.copy()
    target[0] += 1.0  # a metre in 32 ms
    solution = QP.solve(READY, np.zeros(8), np.zeros(8), target, np.zeros(8))
    assert not solution.success and solution.trajectory is None
    assert "daqp" in solution.status


def test_bad_input_raises():
    with pytest.raises(ValueError, match="8 finite values"):
        QP.solve(READY, np.zeros(8), np.zeros(8), READY, np.full(8, np.nan))
    with pytest.raises(ValueError, match="solver"):
        SegmentQp(LIMITS, solver="gurobi")


def test_mathematical_program_solves_the_same_problem():
    sets = feasible_sets(READY, np.zeros(8), np.zeros(8), LIMITS, CONTROL, PERIOD)
    q_terminal, v_terminal = map_action(np.tile([0.5, -0.5], 8), sets)
    reference = QP.solve(READY, np.zeros(8), np.zeros(8), q_terminal, v_terminal)
    other = SegmentQp(LIMITS, CONTROL.segment_samples, PERIOD, CONTROL.knot_samples, solver="clarabel")
    solution = other.solve(READY, np.zeros(8), np.zeros(8), q_terminal, v_terminal)
    assert reference.success and solution.success, solution.status
    np.testing.assert_allclose(solution.trajectory.q, reference.trajectory.q, atol=1e-7)


step_actions = st.one_of(
    st.lists(st.floats(-1.0, 1.0, allow_nan=False), min_size=ACTION_SIZE, max_size=ACTION_SIZE),
    st.lists(st.sampled_from([-1.0, 1.0]), min_size=ACTION_SIZE, max_size=ACTION_SIZE),
    st.sampled_from([[1.0] * ACTION_SIZE, [-1.0] * ACTION_SIZE, [1.0, -1.0] * 8, [-1.0, 1.0] * 8]),
).map(np.array)


@settings(max_examples=400, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), edge=st.booleans(), actions=st.lists(step_actions, min_size=1, max_size=6))
def test_recursive_feasibility(seed, edge, actions):
    """From any invariant state, any action sequence maps to targets the QP reaches within the
    limits, ending in invariant states again."""
    q, v, a = invariant_state(seed, edge)
    for action in actions:
        sets = feasible_sets(q, v, a, LIMITS, CONTROL, PERIOD)
        q_terminal, v_terminal = map_action(action, sets)
        solution = QP.solve(q, v, a, q_terminal, v_terminal)
        assert solution.success, solution.status
        trajectory = solution.trajectory
        assert LIMITS.violations(trajectory, tolerance=1e-6) == {"position": 0, "velocity": 0, "acceleration": 0}
        np.testing.assert_allclose(trajectory.state(0)[0], q, atol=1e-12)
        np.testing.assert_allclose(trajectory.q[-1], q_terminal, atol=1e-7)
        np.testing.assert_allclose(trajectory.v[-1], v_terminal, atol=1e-6)
        q, v, a = trajectory.state(-1)
        # The target is inside; the QP lands on it to its tolerance.
        assert np.all(in_invariant_set(q_terminal, v_terminal, LIMITS, CONTROL, PERIOD, tolerance=1e-9))
        assert np.all(in_invariant_set(q, v, LIMITS, CONTROL, PERIOD, tolerance=1e-6))


def cruising_state(seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A state with every joint at its velocity limit, not accelerating, inside the invariant set:
    where a policy steering at full speed spends its time (the rally bench found the polygon's
    corners unreachable here before the feasible set accounted for the spline's ramps)."""
    rng = np.random.default_rng(seed)
    v = rng.choice([-1.0, 1.0], 8) * LIMITS.velocity
    while True:
        q = rng.uniform(LIMITS.lower, LIMITS.upper)
        inside = in_invariant_set(q, v, LIMITS, CONTROL, PERIOD)
        if np.all(inside):
            return q, v, np.zeros(8)
        v = np.where(inside, v, -v)  # turn the joints that are too close to the limit ahead


@settings(max_examples=150, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), kind=st.sampled_from(["random", "edge", "cruising"]))
def test_every_corner_of_the_feasible_set_is_reachable(seed, kind):
    """The QP reaches every vertex of every joint's feasible polygon; both sets are convex, so it
    reaches every point of the polygon (the mapping's image)."""
    q, v, a = cruising_state(seed) if kind == "cruising" else invariant_state(seed, edge=kind == "edge")
    sets = feasible_sets(q, v, a, LIMITS, CONTROL, PERIOD)
    for vertex in range(sets.vertices.shape[1]):
        target = sets.vertices[:, vertex]
        solution = QP.solve(q, v, a, target[:, 0], target[:, 1])
        assert solution.success, f"vertex {vertex}: {solution.status}"


def test_a_batch_solves_each_row_as_solve_does():
    """Rows whose bounds bind (DAQP), rows where none does, and unreachable targets (failures):
    solve_batch equals solve row by row, exactly (the solver keeps no state between solves)."""
    from tests.test_action_mapping import batch_of_starts

    q, v, a = batch_of_starts(48)
    sets, feasible, _ = feasible_sets_batch(q, v, a, LIMITS, CONTROL, PERIOD)
    q, v, a = q[feasible], v[feasible], a[feasible]
    actions = np.random.default_rng(1).uniform(-1.0, 1.0, (len(q), ACTION_SIZE))
    actions[::2] = np.sign(actions[::2])
    q_terminal, v_terminal = map_action(actions, sets[feasible])
    q_terminal[::5, 0] += 0.05  # out of reach
    batch = QP.solve_batch(q, v, a, q_terminal, v_terminal)
    assert len(batch) == len(q) and 0 < np.sum(~batch.success) < len(q)
    for row in range(len(q)):
        expected, got = QP.solve(q[row], v[row], a[row], q_terminal[row], v_terminal[row]), batch.solution(row)
        assert (got.success, got.status, got.worst_violation) == (expected.success, expected.status, expected.worst_violation)
        if expected.success:
            for field in ("q", "v", "a"):
                np.testing.assert_array_equal(getattr(got.trajectory, field), getattr(expected.trajectory, field))
    with pytest.raises(ValueError, match="solve_batch"):
        QP.solve_batch(q[0], v[0], a[0], q_terminal[0], v_terminal[0])


def reference_acceleration_bounds(limits, v):
    """``CommandLimits.acceleration_bounds`` in NumPy (its former form)."""
    upper = np.sqrt(2.0 * limits.jerk * np.maximum(limits.velocity - v, 0.0))
    lower = np.sqrt(2.0 * limits.jerk * np.maximum(limits.velocity + v, 0.0))
    return -np.minimum(limits.acceleration, lower), np.minimum(limits.acceleration, upper)


def reference_row_bounds(qp, q0, v0, a0, q_terminal, v_terminal):
    """The QP's bounds (B, 8, M + rows) of [x; rows x] and linear term (B, 8, M) in NumPy (the
    former ``SegmentQp._row_bounds``): the reference of the compiled ``_row_bounds``."""
    N, M, limits = qp.samples, qp.knots, qp.limits
    inner = qp._times[1:N]
    start_v = v0[..., None] + a0[..., None] * qp._rows_start[: N - 1]
    start_q = q0[..., None] + v0[..., None] * inner + a0[..., None] * qp._rows_start[N - 1 : 2 * N - 2]
    end_v = v0 + a0 * qp._rows_start[-2]
    end_q = q0 + v0 * qp._times[N] + a0 * qp._rows_start[-1]
    box = np.repeat(np.broadcast_to(limits.acceleration, q0.shape)[..., None], M, axis=-1)
    low_box = -box
    low_box[..., -1], box[..., -1] = reference_acceleration_bounds(limits, v_terminal)
    speed = np.broadcast_to(limits.velocity[:, None], start_v.shape)
    upper_q, lower_q = (np.broadcast_to(x[:, None], start_q.shape) for x in (limits.upper, limits.lower))
    v_gap, q_gap = (v_terminal - end_v)[..., None], (q_terminal - end_q)[..., None]
    upper = np.concatenate([box, speed - start_v, upper_q - start_q, v_gap, q_gap], axis=-1)
    lower = np.concatenate([low_box, -speed - start_v, lower_q - start_q, v_gap, q_gap], axis=-1)
    return lower, upper, a0[..., None] * qp._hessian_cross


def reference_samples(qp, q0, v0, knots, q_terminal, v_terminal):
    """The splines' samples (B, N + 1, 8) and worst violations (B,) in NumPy (the former body of
    ``SegmentQp._checked``): the reference of the compiled ``_samples``."""
    from ace_drake.control.spline_qp import _product

    rows, N, limits = q0.shape[0], qp.samples, qp.limits
    v = (v0.reshape(-1, 1) + _product(knots, qp._velocity_map.T)).reshape(rows, 8, N + 1)
    q = (q0.reshape(-1, 1) + v0.reshape(-1, 1) * qp._times + _product(knots, qp._position_map.T)).reshape(rows, 8, N + 1)
    a = _product(knots, qp._interpolation.T).reshape(rows, 8, N + 1)
    knots = knots.reshape(rows, 8, -1)
    worst = np.max(np.stack([
        np.max(np.abs(knots[..., 1:]) - limits.acceleration[:, None], axis=(1, 2)),
        np.max(np.abs(v) - limits.velocity[:, None], axis=(1, 2)),
        np.max(np.maximum(q - limits.upper[:, None], limits.lower[:, None] - q), axis=(1, 2)),
        np.max(np.abs(v[..., -1] - v_terminal), axis=1),
        np.max(np.abs(q[..., -1] - q_terminal), axis=1),
    ]), axis=0)
    return [np.ascontiguousarray(np.swapaxes(x, 1, 2)) for x in (q, v, a)], np.maximum(worst, 0.0)


@pytest.mark.parametrize("count", [1, 5, 40])
def test_the_compiled_bounds_and_samples_equal_the_numpy_reference_bit_for_bit(count):
    from ace_drake.control import spline_qp
    from tests.test_action_mapping import batch_of_starts

    rng = np.random.default_rng(count)
    q0, v0, a0 = batch_of_starts(count)
    q_terminal = q0 + rng.normal(0.0, 0.01, q0.shape)
    v_terminal = rng.uniform(-1.1, 1.1, q0.shape) * LIMITS.velocity  # some beyond the limit: the bound closes
    rows, M = count, QP.knots
    lower, upper = np.empty((rows, 8, QP._sense.size)), np.empty((rows, 8, QP._sense.size))
    linear, right = np.empty((rows, 8, M)), np.empty((rows * 8, M + 2))
    assert spline_qp._row_bounds(q0, v0, a0, q_terminal, v_terminal, QP._times, QP._rows_start, QP._hessian_cross, LIMITS.acceleration,
                                 LIMITS.velocity, LIMITS.jerk, LIMITS.lower, LIMITS.upper, lower, upper, linear, right)
    expected = reference_row_bounds(QP, q0, v0, a0, q_terminal, v_terminal)
    for got, reference in zip((lower, upper, linear), expected):
        np.testing.assert_array_equal(got, reference)
    np.testing.assert_array_equal(right, np.concatenate([-expected[2], expected[1][..., -2:]], axis=-1).reshape(rows * 8, M + 2))
    v_terminal[0, 0] = np.nan
    assert not spline_qp._row_bounds(q0, v0, a0, q_terminal, v_terminal, QP._times, QP._rows_start, QP._hessian_cross, LIMITS.acceleration,
                                     LIMITS.velocity, LIMITS.jerk, LIMITS.lower, LIMITS.upper, lower, upper, linear, right)
    np.testing.assert_array_equal(LIMITS.acceleration_bounds(v_terminal), reference_acceleration_bounds(LIMITS, v_terminal))
    # Samples: knots within and beyond the limits, and a NaN in the last row.
    knots = np.concatenate([a0[..., None], rng.uniform(-1.05, 1.05, (rows, 8, M)) * LIMITS.acceleration[:, None]], axis=-1).reshape(rows * 8, M + 1)
    knots[-1, 3] = np.nan
    q, v, a = (np.empty((rows, QP.samples + 1, 8)) for _ in range(3))
    worst = np.empty(rows)
    spline_qp._samples(q0, v0, knots, spline_qp._product(knots, QP._velocity_map.T), spline_qp._product(knots, QP._position_map.T),
                       spline_qp._product(knots, QP._interpolation.T), QP._times, q_terminal, v_terminal, LIMITS.acceleration,
                       LIMITS.velocity, LIMITS.lower, LIMITS.upper, q, v, a, worst)
    (q_ref, v_ref, a_ref), worst_ref = reference_samples(QP, q0, v0, knots, q_terminal, v_terminal)
    for got, reference in ((q, q_ref), (v, v_ref), (a, a_ref), (worst, worst_ref)):
        np.testing.assert_array_equal(got, reference)
    assert np.isnan(worst[-1])
