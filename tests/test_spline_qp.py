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
