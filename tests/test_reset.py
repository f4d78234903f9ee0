"""Reset trajectories and protective stops (Ruckig): the sampler, hand-worked durations and
distances, and position/velocity/acceleration safety from the controller's set (property tests)."""

import math

import numpy as np
import pytest
import ruckig
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st

from ace_drake.control.params import ControlParams
from ace_drake.control.reset import ResetPlanner, is_reset_safe, plan_reset, plan_stop, sample_profiles, stop_pad
from ace_drake.control.trajectory import CommandLimits
from ace_drake.robot.params import JOINT_NAMES, RobotLimits, RobotScenario
from ace_drake.robot.trajectory import JointTrajectory

CONTROL = ControlParams()
LIMITS = CommandLimits.from_config(RobotLimits(), CONTROL)
PERIOD = 0.001
A, V, J = LIMITS.acceleration, LIMITS.velocity, LIMITS.jerk
JERK_TIME = CONTROL.jerk_time
GANTRY_Y, WRIST_3 = JOINT_NAMES.index("gantry_y"), JOINT_NAMES.index("wrist_3")
PLANNER = ResetPlanner(LIMITS, PERIOD)
PROPERTY = settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])

# A number in [0, 1], often exactly at an end or the middle, so that states land on the set's boundary.
fraction = st.one_of(st.sampled_from([0.0, 1.0, 0.5]), st.floats(0.0, 1.0))
joint_fractions = st.lists(fraction, min_size=8, max_size=8).map(np.array)


def lerp(low, high, f):
    """low + f (high - low), exactly low at f = 0 and high at f = 1, never outside [low, high]."""
    return np.clip((1.0 - f) * low + f * high, low, high)


def safe_state(fa: np.ndarray, fv: np.ndarray, fq: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The state of is_reset_safe at fractions (8,) of each bound, nested: a across [-A, A], then
    v across the velocities whose jerk-limited ramp stays within [-V, V], then q across
    [lower + stop_pad(-v, -a), upper - stop_pad(v, a)]. Fractions 0 and 1 are on the boundary."""
    a = lerp(-A, A, fa)
    v_low = -V + np.maximum(-a, 0.0) ** 2 / (2.0 * J)
    v_high = V - np.maximum(a, 0.0) ** 2 / (2.0 * J)
    v = lerp(v_low, v_high, fv)
    q_low = LIMITS.lower + stop_pad(-v, -a, LIMITS, CONTROL)
    q_high = LIMITS.upper - stop_pad(v, a, LIMITS, CONTROL)
    assert np.all(q_low <= q_high), "every joint's range is wide enough to stop from full speed"
    return lerp(q_low, q_high, fq), v, a


def check_samples(trajectory: JointTrajectory, q0, v0, a0) -> None:
    """Row 0 is the start exactly; every sample within the limits; the samples consistent."""
    assert trajectory.period == PERIOD
    assert np.array_equal(trajectory.q[0], q0) and np.array_equal(trajectory.v[0], v0) and np.array_equal(trajectory.a[0], a0)
    assert LIMITS.violations(trajectory) == {"position": 0, "velocity": 0, "acceleration": 0}
    # Finite differences against v and a, by the trapezoid rule and its end-corrected (Hermite)
    # form: exact over a constant-jerk piece (a linear, q cubic); for any jerk |j| <= J within a
    # period their errors are at most J h^2 / 4 (a tent of slope J) and 0.032 J h^3 (Peano
    # kernel), so J h^3 / 12 keeps a margin. The 1e-8 covers Ruckig's precision on the end state.
    h = PERIOD
    dv = np.diff(trajectory.v, axis=0) - h * (trajectory.a[1:] + trajectory.a[:-1]) / 2.0
    dq = np.diff(trajectory.q, axis=0) - h * (trajectory.v[1:] + trajectory.v[:-1]) / 2.0 + h * h * np.diff(trajectory.a, axis=0) / 12.0
    assert np.all(np.abs(dv) <= J * h * h / 4.0 + 1e-8)
    assert np.all(np.abs(dq) <= J * h**3 / 12.0 + 1e-8)


def single_joint_duration(q, v, a, target, dof) -> float:
    """Ruckig's time-optimal duration of one joint on its own, s."""
    otg, inp, trajectory = ruckig.Ruckig(1), ruckig.InputParameter(1), ruckig.Trajectory(1)
    inp.current_position, inp.current_velocity, inp.current_acceleration = [q[dof]], [v[dof]], [a[dof]]
    inp.target_position, inp.target_velocity, inp.target_acceleration = [target[dof]], [0.0], [0.0]
    inp.max_velocity, inp.max_acceleration, inp.max_jerk = [V[dof]], [A[dof]], [J[dof]]
    assert otg.calculate(inp, trajectory) == ruckig.Result.Working
    return trajectory.duration


def reference_sample_numbers(numbers, brakes, n, times, lengths, at_rest, shift):
    """``reset._sample_numbers`` in NumPy (its former form): the reference of the compiled
    ``_sample_pieces``."""
    from ace_drake.control import reset

    flat = np.array(numbers, dtype=float)
    rows = reset._ROW * np.arange(n)
    piece_map = reset._PIECE_MAP_REST if at_rest else reset._PIECE_MAP
    pieces = flat.take((piece_map[:, None, :] + rows[None, :, None]).reshape(len(piece_map), n * reset._PIECES))  # (5 fields, n * 10 pieces)
    durations = flat.take(reset._DURATION_MAP[None, :] + rows[:, None])  # (n, 11)
    for dof, brake in brakes:
        durations[dof, 1:3] = brake.t
        row = slice(dof * reset._PIECES, dof * reset._PIECES + 2)
        pieces[1, row], pieces[2, row], pieces[3, row], pieces[4, row] = brake.p, brake.v, brake.a, brake.j
    starts = np.cumsum(durations, axis=1)
    pieces[0] = starts[:, :-1].ravel()
    first = np.minimum(np.searchsorted(times, starts), lengths[:, None])
    counts = (first[:, 1:] - first[:, :-1]).ravel()
    start, p0, v0, a0, j = np.repeat(pieces, counts, axis=1)
    t = times[np.arange(start.size) - np.repeat(np.cumsum(lengths) - lengths, lengths)]
    dt = t - start
    jerk_dt = dt * j
    a = a0 + jerk_dt
    v = v0 + dt * (a0 + 0.5 * jerk_dt)
    q = p0 + dt * (v0 + dt * (0.5 * a0 + jerk_dt * (1.0 / 6.0)))
    if shift:
        shortfall = flat[reset._END :: reset._ROW] - flat[reset._PROFILE_END :: reset._ROW]
        offsets = np.cumsum(lengths) - lengths
        for dof in np.flatnonzero(np.abs(shortfall) > 1e-12):
            end = starts[dof, 9]
            rows = slice(offsets[dof], offsets[dof] + lengths[dof])
            joint_times = t[rows]
            progress = np.minimum(joint_times / (end if end > 0.0 else 1.0), 1.0)
            q[rows] += shortfall[dof] * np.where(joint_times < end, progress, 0.0)
    return q, v, a


@pytest.mark.parametrize("seed", range(6))
def test_the_compiled_sampler_equals_the_numpy_reference_bit_for_bit(seed):
    """Resets and stops of several joint sets with brakes (beyond the limits), targets Ruckig
    ends short of (shifted), and joints sampled over different lengths."""
    from ace_drake.control import reset

    rng = np.random.default_rng(seed)
    numbers, brakes, lengths = [], [], []
    planner = ResetPlanner(LIMITS, PERIOD)
    for trajectory in range(3):
        q, v, a = rng.uniform(LIMITS.lower, LIMITS.upper), rng.uniform(-1.2, 1.2, 8) * V, rng.uniform(-1.2, 1.2, 8) * A
        target = rng.uniform(LIMITS.lower, LIMITS.upper)
        if (seed + trajectory) % 2:
            planner.plan_stop(q, v, a)
            ends = None
        else:
            planner.plan_reset(q, v, a, target)
            ends = (target + rng.choice([0.0, 1e-9], 8)).tolist()  # some a little off the profiles' ends
        reset._profile_numbers(planner._trajectory.profiles[0], ends, numbers, brakes, 8 * trajectory)
        lengths += [int(planner.duration / PERIOD) + rng.integers(-20, 20)] * 8
    assert brakes
    lengths = np.maximum(np.array(lengths), 1)
    times = np.arange(lengths.max()) * PERIOD
    for at_rest, shift in ((False, False), (True, False), (True, True)):
        got = reset._sample_numbers(numbers, brakes, len(lengths), times, lengths, at_rest, shift)
        for x, y in zip(got, reference_sample_numbers(numbers, brakes, len(lengths), times, lengths, at_rest, shift)):
            np.testing.assert_array_equal(x, y)


# ----------------------------------------------------------------------------------------------
# The vectorised sampler
# ----------------------------------------------------------------------------------------------


@PROPERTY
@given(fq=joint_fractions, fv=joint_fractions, fa=joint_fractions, ft=joint_fractions, stop=st.booleans())
def test_sampler_matches_ruckig_at_time(fq, fv, fa, ft, stop):
    # Anywhere within the position, velocity and acceleration limits, including v = V with a = A,
    # where Ruckig prepends a brake pre-trajectory.
    q, v, a = lerp(LIMITS.lower, LIMITS.upper, fq), lerp(-V, V, fv), lerp(-A, A, fa)
    target = lerp(LIMITS.lower, LIMITS.upper, ft)
    planner = ResetPlanner(LIMITS, PERIOD)
    if stop:
        planner.plan_stop(q, v, a)
    else:
        planner.plan_reset(q, v, a, target)
    trajectory = planner._trajectory  # the last Ruckig trajectory
    times = np.sort(np.r_[np.linspace(0.0, 1.2 * trajectory.duration + 0.01, 97), trajectory.duration])
    q_s, v_s, a_s = sample_profiles(trajectory.profiles[0], times)
    expected = np.array([trajectory.at_time(t) for t in times])  # (k, 3, 8)
    np.testing.assert_allclose(q_s, expected[:, 0], rtol=0, atol=1e-9)
    np.testing.assert_allclose(v_s, expected[:, 1], rtol=0, atol=1e-9)
    np.testing.assert_allclose(a_s, expected[:, 2], rtol=0, atol=1e-9)


@pytest.mark.parametrize("stop", [False, True])
def test_sampler_follows_the_brake_pre_trajectory(stop):
    # At the velocity limit and still accelerating (position interface), or beyond the
    # acceleration limit (velocity interface), Ruckig brakes first: the sampler must follow.
    q = np.zeros(8)
    v = V.copy() if not stop else 0.5 * V
    a = A.copy() if not stop else 1.5 * A
    planner = ResetPlanner(LIMITS, PERIOD)
    if stop:
        planner.plan_stop(q, v, a)
    else:
        planner.plan_reset(q, v, a, np.zeros(8))
    trajectory = planner._trajectory
    assert all(profile.brake.duration > 0.0 for profile in trajectory.profiles[0])
    times = np.linspace(0.0, trajectory.duration, 301)
    expected = np.array([trajectory.at_time(t) for t in times])
    for sampled, column in zip(sample_profiles(trajectory.profiles[0], times), range(3)):
        np.testing.assert_allclose(sampled, expected[:, column], rtol=0, atol=1e-9)


def test_sampler_holds_at_rest_past_the_end():
    PLANNER.plan_stop(np.zeros(8), 0.3 * V, np.zeros(8))
    profiles = PLANNER._trajectory.profiles[0]
    ends = np.array([profile.p[7] for profile in profiles])
    q, v, a = sample_profiles(profiles, np.array([0.0, 10.0]), at_rest=True)
    assert np.array_equal(q[1], ends) and np.all(v[1] == 0.0) and np.all(a[1] == 0.0)
    q, v, a = sample_profiles(profiles, np.array([0.0, 10.0]), at_rest=True, final=np.ones(8))
    assert np.all(q[1] == 1.0)
    with pytest.raises(ValueError, match="at_rest"):
        sample_profiles(profiles, np.array([0.0]), final=np.ones(8))


# ----------------------------------------------------------------------------------------------
# Hand-worked numbers
# ----------------------------------------------------------------------------------------------


def test_rest_to_rest_duration_is_the_analytic_time_optimum():
    # gantry_y from rest at 0 to -1.0 m, the other joints already at rest at their targets. With
    # V = 4.25 m/s, A = 34 m/s^2, J = A / 0.002 s = 17000 m/s^3 it reaches V (the distance to reach
    # it and stop again, V (V / A + A / J) = 0.540 m, is < 1 m), so the time-optimal jerk-limited
    # profile is jerk up/down to A, cruise at V, and back: T = D / V + V / A + A / J = 0.3623 s.
    start, target = np.zeros(8), np.zeros(8)
    target[GANTRY_Y] = -1.0
    D, v_max, a_max, j_max = 1.0, V[GANTRY_Y], A[GANTRY_Y], J[GANTRY_Y]
    assert D > v_max * (v_max / a_max + a_max / j_max)
    T = D / v_max + v_max / a_max + a_max / j_max
    assert T == pytest.approx(1.0 / 4.25 + 0.125 + 0.002)
    trajectory = PLANNER.plan_reset(start, np.zeros(8), np.zeros(8), target)
    assert PLANNER.duration == pytest.approx(T, abs=1e-12)
    assert trajectory.samples == math.ceil(T / PERIOD) == 363
    check_samples(trajectory, start, np.zeros(8), np.zeros(8))
    assert np.array_equal(trajectory.state(-1)[0], target) and not np.any(trajectory.v[-1]) and not np.any(trajectory.a[-1])
    assert np.max(-trajectory.v[:, GANTRY_Y]) == pytest.approx(v_max, abs=1e-12)  # the cruise is sampled
    assert np.max(np.abs(trajectory.a[:, GANTRY_Y])) == pytest.approx(a_max, abs=1e-9)
    others = np.arange(8) != GANTRY_Y
    assert not np.any(trajectory.q[:, others]) and not np.any(trajectory.v[:, others]) and not np.any(trajectory.a[:, others])


def test_short_rest_to_rest_move_reaches_neither_limit():
    # wrist_3 by 1 mrad: four jerk phases of t = (D / (2 J))^(1/3) = 1.2516 ms each (peak
    # acceleration J t = 319 < 510 rad/s^2), T = 4 t = 5.0065 ms: 6 samples after the start.
    target = np.zeros(8)
    target[WRIST_3] = 1e-3
    t = (1e-3 / (2.0 * J[WRIST_3])) ** (1.0 / 3.0)
    assert J[WRIST_3] * t < A[WRIST_3] and J[WRIST_3] * t * t < V[WRIST_3]
    trajectory = PLANNER.plan_reset(np.zeros(8), np.zeros(8), np.zeros(8), target)
    assert PLANNER.duration == pytest.approx(4.0 * t, abs=1e-12)
    assert trajectory.samples == math.ceil(4.0 * t / PERIOD) == 6
    check_samples(trajectory, np.zeros(8), np.zeros(8), np.zeros(8))


@pytest.mark.parametrize(
    "v0",
    [
        3.0,  # >= A^2 / J = 0.068 m/s: jerk down to -A, hold, jerk back up
        0.01,  # < A^2 / J: a triangular acceleration that never reaches A
    ],
)
def test_stop_travels_the_analytic_braking_distance(v0):
    a_max, j_max = A[GANTRY_Y], J[GANTRY_Y]
    if v0 >= a_max**2 / j_max:
        distance, T = v0**2 / (2.0 * a_max) + v0 * a_max / (2.0 * j_max), v0 / a_max + a_max / j_max
    else:
        distance, T = v0 * math.sqrt(v0 / j_max), 2.0 * math.sqrt(v0 / j_max)
    q0, v = np.full(8, 0.1), np.zeros(8)
    v[GANTRY_Y] = v0
    trajectory = PLANNER.plan_stop(q0, v, np.zeros(8))
    assert PLANNER.duration == pytest.approx(T, abs=1e-12)
    assert trajectory.samples == math.ceil(T / PERIOD - 1e-9)
    check_samples(trajectory, q0, v, np.zeros(8))
    assert trajectory.q[-1, GANTRY_Y] - q0[GANTRY_Y] == pytest.approx(distance, abs=1e-12)
    assert np.all(np.diff(trajectory.q[:, GANTRY_Y]) >= 0.0)  # no reversal
    assert not np.any(trajectory.v[-1]) and not np.any(trajectory.a[-1])
    others = np.arange(8) != GANTRY_Y
    assert np.all(trajectory.q[:, others] == 0.1)


def test_already_at_target_and_at_rest_is_a_single_sample():
    ready = np.array(RobotScenario().ready_pose)
    trajectory = plan_reset(ready, np.zeros(8), np.zeros(8), ready, LIMITS, PERIOD)
    assert trajectory.samples == 0 and np.array_equal(trajectory.q[0], ready)
    assert plan_stop(ready, np.zeros(8), np.zeros(8), LIMITS, PERIOD).samples == 0


def test_module_functions_match_the_planner():
    q, v, a, target = np.full(8, 0.2), 0.3 * V, -0.2 * A, np.full(8, -0.1)
    for mine, theirs in ((plan_reset(q, v, a, target, LIMITS, PERIOD), PLANNER.plan_reset(q, v, a, target)), (plan_stop(q, v, a, LIMITS, PERIOD), PLANNER.plan_stop(q, v, a))):
        assert np.array_equal(mine.q, theirs.q) and np.array_equal(mine.v, theirs.v) and np.array_equal(mine.a, theirs.a)


# ----------------------------------------------------------------------------------------------
# Safety: position, velocity and acceleration limits from the controller's set
# ----------------------------------------------------------------------------------------------


def test_set_without_the_jerk_ramp_lets_the_stop_overshoot():
    # The controller's set as first stated bounds q + v tau + v^2 / (2 A_s) <= upper for v > 0 only,
    # with |v| <= V and |a| <= A. Two of its states a jerk-limited motion cannot keep within limits:
    # 1. wrist_3 at rest at its upper limit with a = +A: ramping a to 0 at -J takes jerk_time t_j
    #    and travels A t_j^2 / 3 while reaching A t_j / 2, then braking (a triangle peaking at
    #    A / sqrt 2) adds A t_j^2 / (2 sqrt 2): 0.687 A t_j^2 = 1.40 mrad past the limit.
    q, v, a = np.zeros(8), np.zeros(8), np.zeros(8)
    q[WRIST_3], a[WRIST_3] = LIMITS.upper[WRIST_3], A[WRIST_3]
    overshoot = A[WRIST_3] * JERK_TIME**2 * (1.0 / 3.0 + 1.0 / (2.0 * math.sqrt(2.0)))
    assert overshoot == pytest.approx(1.401e-3, abs=1e-6)
    stop = PLANNER.plan_stop(q, v, a)
    assert np.max(stop.q[:, WRIST_3]) - LIMITS.upper[WRIST_3] == pytest.approx(overshoot, abs=1e-9)
    assert LIMITS.violations(stop)["position"] > 0
    assert LIMITS.violations(PLANNER.plan_reset(q, v, a, np.zeros(8)))["position"] > 0
    assert not is_reset_safe(q, v, a, LIMITS, CONTROL)[WRIST_3]
    # 2. wrist_3 at the velocity limit with a = +A: v keeps rising by A^2 / (2 J) = 0.51 rad/s.
    q[WRIST_3], v[WRIST_3] = 0.0, V[WRIST_3]
    stop = PLANNER.plan_stop(q, v, a)
    assert np.max(stop.v[:, WRIST_3]) - V[WRIST_3] == pytest.approx(A[WRIST_3] ** 2 / (2.0 * J[WRIST_3]), abs=1e-9)
    assert LIMITS.violations(stop)["velocity"] > 0
    assert not is_reset_safe(q, v, a, LIMITS, CONTROL)[WRIST_3]
    # The jerk-aware set (stop_pad) needs exactly this much more room at v = 0, a = A.
    assert stop_pad(0.0, A, LIMITS, CONTROL)[WRIST_3] >= overshoot


def test_stop_pad_is_the_original_set_without_acceleration_towards_the_limit():
    v = np.linspace(-1.0, 1.0, 8) * V
    tau, braking = CONTROL.reaction_time, CONTROL.stop_fraction * A
    original = np.maximum(v, 0.0) * tau + np.maximum(v, 0.0) ** 2 / (2.0 * braking)
    for a in (np.zeros(8), -A, -0.3 * A):
        np.testing.assert_allclose(stop_pad(v, a, LIMITS, CONTROL), original, rtol=1e-15, atol=0)
    assert np.all(stop_pad(v, A, LIMITS, CONTROL) > original)


def test_feasible_set_bounds_with_a_jerk_time_knot_lie_in_the_safe_set():
    # The proposed fix on the controller's side: feasible_set.invariant_bounds pads for any terminal
    # acceleration |a| <= A ramped out over its knot period h; with h >= jerk_time that covers the
    # jerk-limited ramp, so its (q, v) bounds, with any |a| <= A and the linear velocity condition
    # |v + a jerk_time / 2| <= V (which implies |v + a |a| / (2 J)| <= V), are in is_reset_safe.
    from ace_drake.control.feasible_set import invariant_bounds

    v = np.linspace(-1.0, 1.0, 201)[:, None] * V
    lo, hi = invariant_bounds(v, LIMITS, CONTROL, JERK_TIME)
    for a in np.linspace(-1.0, 1.0, 21)[:, None, None] * A:
        a = np.broadcast_to(a, v.shape)
        ok = (lo <= hi) & (np.abs(v + a * JERK_TIME / 2.0) <= V)
        for q in (lo, hi):
            assert np.all(is_reset_safe(q, v, a, LIMITS, CONTROL, tolerance=1e-12)[ok])


@PROPERTY
@example(fa=np.ones(8), fv=np.ones(8), fq=np.ones(8))  # at the upper bounds: a = A, fastest v, q on the boundary
@example(fa=np.ones(8), fv=np.full(8, 0.5), fq=np.ones(8))  # a = A towards the limit at v ~ 0
@example(fa=np.zeros(8), fv=np.zeros(8), fq=np.zeros(8))  # the mirror image at the lower limits
@given(fa=joint_fractions, fv=joint_fractions, fq=joint_fractions)
def test_stop_from_the_safe_set_stays_within_limits(fa, fv, fq):
    q, v, a = safe_state(fa, fv, fq)
    assert np.all(is_reset_safe(q, v, a, LIMITS, CONTROL))
    trajectory = PLANNER.plan_stop(q, v, a)
    check_samples(trajectory, q, v, a)
    assert not np.any(trajectory.v[-1]) and not np.any(trajectory.a[-1])
    assert trajectory.samples == math.ceil(PLANNER.duration / PERIOD - 1e-9)  # no padding beyond rounding
    # Each joint stops within its pad (stop_pad bounds the travel towards either limit).
    travel = trajectory.q - q
    assert np.all(travel <= stop_pad(v, a, LIMITS, CONTROL) + 1e-9)
    assert np.all(-travel <= stop_pad(-v, -a, LIMITS, CONTROL) + 1e-9)


@PROPERTY
@example(fa=np.ones(8), fv=np.ones(8), fq=np.ones(8), ft=np.zeros(8))
@example(fa=np.ones(8), fv=np.full(8, 0.5), fq=np.ones(8), ft=np.ones(8))
@example(fa=np.zeros(8), fv=np.zeros(8), fq=np.zeros(8), ft=np.zeros(8))
# shoulder_pitch creeps for 1.2 s to a target on its lower limit, where Ruckig's profile ends 7e-9
# rad short of it (sample_profiles shifts it onto the target); duration 0.221 s, a whole number of
# periods up to round-off.
@example(fa=np.r_[0, 0, 1, 1, 0, 0, 0, 0.0], fv=np.r_[0, 0, 1, 0.5, 0, 0, 0, 0], fq=np.r_[0, 0, 2.0**-9, 2.0**-5, 0, 0, 0, 0], ft=np.r_[0, 0, 1, 0, 0, 0, 0, 0.0])
@example(fa=np.r_[1 / 3, 0, 0, 0, 0, 0, 0, 0], fv=np.zeros(8), fq=np.r_[0, 0.5, 0, 0, 1, 0, 0, 0], ft=np.r_[0, 0.5, 0, 0, 1, 0, 0, 0])
@given(fa=joint_fractions, fv=joint_fractions, fq=joint_fractions, ft=joint_fractions)
def test_reset_from_the_safe_set_stays_within_limits(fa, fv, fq, ft):
    q, v, a = safe_state(fa, fv, fq)
    target = lerp(LIMITS.lower, LIMITS.upper, ft)
    trajectory = PLANNER.plan_reset(q, v, a, target)
    check_samples(trajectory, q, v, a)
    assert np.array_equal(trajectory.q[-1], target) and not np.any(trajectory.v[-1]) and not np.any(trajectory.a[-1])
    if PLANNER.fell_back:  # Ruckig failed on the direct reset (nearly degenerate joints): see below
        with pytest.raises(ruckig.RuckigError):
            [single_joint_duration(q, v, a, target, dof) for dof in range(8)]
        return
    # Time-optimal: as long as the slowest joint needs on its own, rounded up to whole periods.
    optimum = max(single_joint_duration(q, v, a, target, dof) for dof in range(8))
    assert PLANNER.duration == pytest.approx(optimum, abs=1e-9)
    assert -1e-12 <= trajectory.duration - PLANNER.duration < PERIOD  # (1e-9 periods count as whole)


@PROPERTY
@example(fa=np.ones(8), fv=np.ones(8), fq=np.ones(8), ft=np.zeros(8))
@example(fa=np.zeros(8), fv=np.zeros(8), fq=np.zeros(8), ft=np.ones(8))
@given(fa=joint_fractions, fv=joint_fractions, fq=joint_fractions, ft=joint_fractions)
def test_stop_then_reset_from_the_safe_set_stays_within_limits(fa, fv, fq, ft):
    q, v, a = safe_state(fa, fv, fq)
    target = lerp(LIMITS.lower, LIMITS.upper, ft)
    trajectory = PLANNER.plan_stop_then_reset(q, v, a, target)
    assert PLANNER.fell_back
    check_samples(trajectory, q, v, a)
    assert np.array_equal(trajectory.q[-1], target) and not np.any(trajectory.v[-1]) and not np.any(trajectory.a[-1])
    stop = PLANNER.plan_stop(q, v, a)
    assert np.array_equal(trajectory.q[: stop.samples + 1], stop.q)  # the stop, then from rest
    assert -1e-12 <= trajectory.duration - stop.duration - max(single_joint_duration(stop.q[-1], np.zeros(8), np.zeros(8), target, dof) for dof in range(8)) < PERIOD


def test_reset_falls_back_to_a_stop_where_ruckig_fails():
    # Ruckig 0.19 finds no profile for shoulder_pitch at its target, at rest but still accelerating
    # at 4.98 rad/s^2 (step 1 fails); the reset stops first, then returns to the target from rest.
    q, v, a = np.full(8, 0.1), np.zeros(8), np.zeros(8)
    a[3] = 4.98046875
    with pytest.raises(ruckig.RuckigError, match="step 1"):
        single_joint_duration(q, v, a, q, 3)
    trajectory = PLANNER.plan_reset(q, v, a, q)
    assert PLANNER.fell_back
    check_samples(trajectory, q, v, a)
    assert np.array_equal(trajectory.q[-1], q) and not np.any(trajectory.v[-1]) and not np.any(trajectory.a[-1])
    assert trajectory.duration < 0.01  # the 4.98 rad/s^2 ramp-out and the way back take milliseconds


# ----------------------------------------------------------------------------------------------
# Errors
# ----------------------------------------------------------------------------------------------


def test_bad_inputs_raise_value_errors_naming_them():
    zeros = np.zeros(8)
    with pytest.raises(ValueError, match=r"plan_reset: v must have shape \(8,\)"):
        PLANNER.plan_reset(zeros, np.zeros(7), zeros, zeros)
    with pytest.raises(ValueError, match="plan_stop: a must be finite"):
        PLANNER.plan_stop(zeros, zeros, np.r_[np.zeros(7), np.nan])
    with pytest.raises(ValueError, match="q_target must be finite"):
        PLANNER.plan_reset(zeros, zeros, zeros, np.r_[np.inf, np.zeros(7)])
    with pytest.raises(ValueError, match="q_target outside the position limits: elbow=3.0"):
        PLANNER.plan_reset(zeros, zeros, zeros, np.r_[np.zeros(4), 3.0, np.zeros(3)])
    with pytest.raises(ValueError, match="period"):
        ResetPlanner(LIMITS, 0.0)


def test_a_start_far_outside_the_limits_raises_instead_of_filling_memory():
    far = np.r_[1e4, np.zeros(7)]
    with pytest.raises(RuntimeError, match="max_duration"):
        PLANNER.plan_reset(far, np.zeros(8), np.zeros(8), np.zeros(8))


def test_ruckig_errors_become_runtime_errors_naming_the_result():
    planner = ResetPlanner(LIMITS, PERIOD)
    zeros = np.zeros(8)
    planner._stop_input.max_jerk = np.r_[-1.0, J[1:]]  # corrupted inputs Ruckig rejects
    with pytest.raises(RuntimeError, match=r"plan_stop: Ruckig rejected the input \(\[ruckig\] maximum jerk limit -1"):
        planner.plan_stop(zeros, np.full(8, 0.1), zeros)
    planner = ResetPlanner(LIMITS, PERIOD)
    planner._reset_input.max_jerk = np.r_[-1.0, J[1:]]
    with pytest.raises(RuntimeError, match=r"plan_reset \(from rest, after a stop\): Ruckig rejected the input \(\[ruckig\] maximum jerk"):
        planner.plan_reset(zeros, zeros, zeros, np.full(8, 0.1))


def test_a_batch_of_resets_is_each_row_planned_alone():
    """plan_reset_batch equals plan_reset row by row, exactly: moving starts, a nearly degenerate
    one (Ruckig's failure, the stop-then-reset fallback) and, with a short max_duration, plans
    refused with plan_reset's message."""
    rng = np.random.default_rng(4)
    target = np.asarray(RobotScenario().ready_pose, dtype=float)
    q = rng.uniform(LIMITS.lower + 0.3 * (LIMITS.upper - LIMITS.lower), LIMITS.upper - 0.3 * (LIMITS.upper - LIMITS.lower), (12, 8))
    v = rng.uniform(-0.3, 0.3, (12, 8)) * V
    a = rng.uniform(-0.3, 0.3, (12, 8)) * A
    q[3], v[3], a[3] = target + 1e-9, 1e-8, 0.0  # at the target: Ruckig may fail, the fallback plans
    q[5], v[5], a[5] = target, 0.0, 0.0  # already there
    planner = ResetPlanner(LIMITS, PERIOD)
    for max_duration in (ResetPlanner.max_duration, 0.3):
        planner.max_duration = max_duration
        plans, errors = planner.plan_reset_batch(q, v, a, target)
        for row in range(12):
            try:
                expected = planner.plan_reset(q[row], v[row], a[row], target)
            except RuntimeError as error:
                assert plans[row] is None and errors[row] == str(error)
                continue
            assert errors[row] == ""
            for field in ("q", "v", "a"):
                np.testing.assert_array_equal(getattr(plans[row], field), getattr(expected, field))
    assert any(errors) and not all(errors)
    with pytest.raises(ValueError, match="q_target outside"):
        planner.plan_reset_batch(q, v, a, LIMITS.upper + 1.0)
