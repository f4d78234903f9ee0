"""BallEkf: prediction = the project's physics, start of a track, convergence on noisy shots,
NEES consistency, bounces, late and out-of-order measurements, resets, the spin sensor's bias."""

import dataclasses
import functools

import numpy as np
import pytest
from scipy import stats

from ace_drake.analysis.bench import sample_incoming_balls
from ace_drake.config import ConfigError, from_dict
from ace_drake.perception import ball_ekf, ekf_kernels
from ace_drake.perception.ball_ekf import POSITION, SPIN, BallEkf, Observation
from ace_drake.perception.ekf_evaluation import evaluate, replay, simulate_shots
from ace_drake.perception.measurements import Measurement, MeasurementHistoryBatch
from ace_drake.perception.params import EstimatorParams
from ace_drake.physics.flight import make_state
from ace_drake.physics.params import BallPhysicsParams
from ace_drake.physics.propagate import ContactKind, simulate

PHYSICS = BallPhysicsParams()
SHOT_COUNT = 20
# The truth has no in-flight process noise: with (almost) none in the filter it is matched.
MATCHED = EstimatorParams(acceleration_noise_density=1e-4, spin_noise_density=1e-2)


@functools.cache
def incoming_shots():
    """Shots from the human side that first land on the robot's half, simulated 0.4 s with both
    sensors' default models (and the post-bounce perturbations); all land before 0.3 s."""
    candidates = sample_incoming_balls(3 * SHOT_COUNT, seed=0)
    trajectory = simulate(candidates, PHYSICS, 0.5, record=False)
    landing = [
        i for i, events in enumerate(trajectory.events)
        if events and events[0].kind == ContactKind.TABLE and events[0].state_pre[0] < 0.0 and events[0].time < 0.3
    ]
    return simulate_shots(candidates[landing[:SHOT_COUNT]], 0.4, seed=0)


def measurement(sequence, time, value, variance=1e-6, latency=0.01):
    return Measurement(sequence, time, time + latency, np.asarray(value, dtype=float), variance * np.eye(3))


def positions_along(states_at, times, start_sequence=1, **kwargs):
    return [measurement(start_sequence + i, t, states_at(t)[:3], **kwargs) for i, t in enumerate(times)]


def trajectory(start, duration=0.25):
    """The noise-free state (9,) at any time t (s) on a 0.1 ms grid, as a function of t."""
    states = simulate(start, PHYSICS, duration, dt=1e-4).states[:, 0]
    return lambda t: states[int(round(t / 1e-4))]


# ---------------------------------------------------------------------------------- prediction
def test_prediction_is_the_physics_in_flight_and_through_a_bounce():
    dut = BallEkf(dataclasses.replace(MATCHED, acceleration_noise_density=0.0, spin_noise_density=0.0, bounce_velocity_std=0.0, bounce_spin_std=0.0))
    covariance = np.eye(12)
    for start, duration, bounces in [
        (make_state([1.0, 0.2, 0.3], [-9.0, 0.5, 1.0], [40.0, -300.0, 20.0]), 0.012, False),
        (make_state([-0.8, 0.1, 0.05], [-5.0, 0.3, -3.0], [0.0, 200.0, 50.0]), 0.03, True),
    ]:
        mean, predicted, last_contact = dut.predict(start, covariance, duration)
        assert (last_contact is not None) == bounces
        reference = simulate(start, PHYSICS, duration, dt=duration / np.ceil(duration / 0.005)).final_state[0]
        np.testing.assert_allclose(mean, reference, rtol=0, atol=1e-12)
        # F by central differences of the propagator (bounce included): P = F I F^T.
        step = 1e-5
        columns = [
            (simulate(start + step * e, PHYSICS, duration, dt=1e-3, record=False).final_state[0]
             - simulate(start - step * e, PHYSICS, duration, dt=1e-3, record=False).final_state[0]) / (2 * step)
            for e in np.eye(9)
        ]
        jacobian = np.column_stack(columns)
        np.testing.assert_allclose(predicted[:9, :9], jacobian @ jacobian.T, rtol=1e-3, atol=1e-6)


def test_estimate_is_not_defined_before_the_posterior():
    dut = BallEkf()
    start = make_state([1.5, 0.0, 0.3], [-8.0, 0.0, 1.0])
    state = dut.update(dut.initial_state(), positions_along(trajectory(start, 0.02), [0.0, 0.005, 0.01]))
    with pytest.raises(ValueError, match="before the posterior"):
        dut.estimate(state, 0.009)


# ---------------------------------------------------------------------------------- start
def test_track_starts_from_three_positions_with_drag_in_the_fit():
    start = make_state([1.6, -0.2, 0.3], [-20.0, 1.0, 0.5])  # fast: drag ~60 m/s^2
    truth_at = trajectory(start, 0.02)
    dut = BallEkf()
    state = dut.update(dut.initial_state(), positions_along(truth_at, [0.0, 0.005]))
    assert dut.estimate(state, 0.005) is None
    state = dut.update(state, positions_along(truth_at, [0.010], start_sequence=3))
    estimate = dut.estimate(state, 0.010)
    truth = truth_at(0.010)
    np.testing.assert_allclose(estimate.mean[:3], truth[:3], atol=1e-5)
    np.testing.assert_allclose(estimate.mean[3:6], truth[3:6], atol=0.01)  # gravity alone: ~0.3 m/s off
    assert not estimate.spin_valid
    np.testing.assert_array_equal(estimate.mean[6:], 0.0)
    np.testing.assert_allclose(np.diag(estimate.covariance)[:6], [0.01] * 3 + [0.1] * 3)  # notes.md
    assert np.diag(estimate.covariance)[6] == MATCHED.initial_spin_variance


def test_a_bounce_inside_the_first_positions_waits_for_a_clean_fit():
    start = make_state([-0.5, 0.0, 0.04], [-4.0, 0.0, -3.0])  # lands after 6.6 ms
    bounce_time = simulate(start, PHYSICS, 0.1).events[0][0].time
    times = [0.0, 0.005, 0.010, 0.015]
    assert times[1] < bounce_time < times[2]
    truth_at = trajectory(start, 0.06)
    dut = BallEkf()
    state = dut.update(dut.initial_state(), positions_along(truth_at, times[:3]))
    assert dut.estimate(state, 0.010) is None
    # The next window (5, 10, 15 ms) still holds the bounce but fits within the noise: the track
    # starts off by about 1 m/s and the following positions pull it in.
    later = np.arange(0.015, 0.06, 0.005)
    state = dut.update(state, positions_along(truth_at, later, start_sequence=4))
    estimate = dut.estimate(state, later[-1])
    np.testing.assert_allclose(estimate.mean[3:6], truth_at(later[-1])[3:6], atol=0.05)
    assert state.latest.resets == 0


# ---------------------------------------------------------------------------------- accuracy
def test_converges_on_noisy_shots():
    figures = evaluate(BallEkf(), incoming_shots(), report_times=(0.05, 0.15))
    early, late = figures["report_times"][0.05], figures["report_times"][0.15]
    assert early["valid_fraction"] == late["valid_fraction"] == 1.0
    assert early["velocity_error_mean_m_s"] < 0.25
    assert late["velocity_error_mean_m_s"] < 0.08
    assert late["position_error_mean_m"] < 0.004
    # The spin sensor's per-contact bias (about 18 rad/s mean at these spins) cannot be averaged out.
    assert late["spin_error_mean_rad_s"] < 30.0
    assert figures["resets"] == 0 and figures["discarded"] == 0


def test_nees_is_within_its_chi_square_band():
    figures = evaluate(BallEkf(MATCHED), incoming_shots(), report_times=(0.05, 0.15))
    low, high = stats.chi2.ppf([0.005, 0.995], 9 * SHOT_COUNT) / SHOT_COUNT
    for time in (0.05, 0.15):
        assert low < figures["report_times"][time]["nees_mean"] < high, (time, figures["report_times"][time])


def test_tracks_through_the_bounce_on_the_robots_half():
    dut = BallEkf()
    for shot in incoming_shots()[:8]:
        bounce_time = shot.events[0].time
        report_time = round(bounce_time + 0.03, 3)
        result = replay(dut, shot, [report_time], duration=report_time)
        estimate = result.estimates[report_time]
        error = estimate.mean - shot.true_state(report_time)
        assert result.final.latest.resets == 0
        assert np.linalg.norm(error[:3]) < 0.01
        assert np.linalg.norm(error[3:6]) < 0.3


# ---------------------------------------------------------------------------------- late data
def final_core(dut, batches):
    state = dut.initial_state()
    for positions, spins in batches:
        state = dut.update(state, positions, spins)
    return state


def test_late_and_out_of_order_measurements_give_the_in_order_result():
    shot = incoming_shots()[0]
    positions = [Measurement(i + 1, m.capture_time, m.release_time, m.value, m.covariance) for i, m in enumerate(shot.positions)]
    spins = [Measurement(i + 1, m.capture_time, m.release_time, m.value, m.covariance) for i, m in enumerate(shot.spins)]
    # What the replay below sees: released by the end of the shot.
    positions = [m for m in positions if m.release_time <= shot.times[-1]]
    spins = [m for m in spins if m.release_time <= shot.times[-1]]
    by_release = sorted(positions + spins, key=lambda m: m.release_time)
    latest_capture = np.maximum.accumulate([m.capture_time for m in by_release])
    assert np.sum(np.array([m.capture_time for m in by_release[1:]]) < latest_capture[:-1]) > 20  # late ones
    dut = BallEkf()
    # Reference: one measurement at a time, in capture order.
    ordered = sorted([(m.capture_time, [m], []) for m in positions] + [(m.capture_time, [], [m]) for m in spins], key=lambda x: x[0])
    reference = final_core(dut, [(p, s) for _, p, s in ordered]).latest
    # As released (spins overtake positions and each other), in 1 ms batches.
    released = replay(dut, shot, []).final.latest
    # Backwards within 20 ms blocks: every block arrives newest first.
    blocks = {}
    for _, p, s in ordered:
        blocks.setdefault(int((p or s)[0].capture_time / 0.02), []).append((p, s))
    scrambled = final_core(dut, [batch for block in blocks.values() for batch in reversed(block)]).latest
    for core in (released, scrambled):
        assert core.time == reference.time
        np.testing.assert_array_equal(core.mean, reference.mean)
        np.testing.assert_array_equal(core.covariance, reference.covariance)


def test_a_measurement_older_than_the_history_is_discarded():
    start = make_state([1.5, 0.0, 0.3], [-8.0, 0.0, 1.5])
    dut = BallEkf()
    times = np.arange(0.0, 0.2, 0.005)
    state = dut.update(dut.initial_state(), positions_along(trajectory(start), times))
    before = state.latest
    state = dut.update(state, positions_along(trajectory(start), [0.0525], start_sequence=100))
    assert state.discarded == 1
    assert state.latest is before


# ---------------------------------------------------------------------------------- resets
def test_a_gap_restarts_the_track():
    first = make_state([1.5, 0.0, 0.3], [-8.0, 0.0, 1.5])
    second = make_state([1.4, 0.3, 0.25], [-6.0, -0.5, 2.0])
    dut = BallEkf()
    state = dut.update(dut.initial_state(), positions_along(trajectory(first), np.arange(0.0, 0.1, 0.005)))
    later = [0.35, 0.355, 0.36]  # 0.255 s after the last capture
    second_at = trajectory(second, 0.02)
    state = dut.update(state, positions_along(lambda t: second_at(t - 0.35), later, start_sequence=30))
    assert state.latest.resets == 1
    estimate = dut.estimate(state, 0.36)
    np.testing.assert_allclose(estimate.mean[:6], second_at(0.01)[:6], atol=0.02)


def test_a_jump_restarts_the_track():
    first = make_state([1.5, 0.0, 0.3], [-8.0, 0.0, 1.5])
    other = make_state([1.5, -1.0, 0.3], [-8.0, 0.0, 1.5])  # a second ball 1 m to the side
    dut = BallEkf()
    state = dut.update(dut.initial_state(), positions_along(trajectory(first), np.arange(0.0, 0.1, 0.005)))
    other_at = trajectory(other, 0.12)
    state = dut.update(state, positions_along(other_at, [0.1, 0.105, 0.11], start_sequence=30))
    assert state.latest.resets == 1
    np.testing.assert_allclose(dut.estimate(state, 0.11).mean[:3], other_at(0.11)[:3], atol=1e-3)


def test_a_position_the_prediction_cannot_explain_restarts_the_track():
    # 5 cm off is far below the 0.4 m jump, but hundreds of standard deviations: the prediction
    # missed a contact (a net-cord ball that went the other way). 3 mm off is just noise.
    start = make_state([1.5, 0.0, 0.3], [-8.0, 0.0, 1.5])
    truth_at = trajectory(start, 0.12)
    dut = BallEkf()
    state = dut.update(dut.initial_state(), positions_along(truth_at, np.arange(0.0, 0.1, 0.005)))
    for offset, resets in ((0.003, 0), (0.05, 1)):
        moved = [measurement(100, 0.1, truth_at(0.1)[:3] + [0.0, 0.0, offset])]
        assert dut.update(state, moved).latest.resets == resets


def test_a_diverged_track_gives_no_estimate_and_its_next_position_restarts_it():
    """A track whose velocity diverged (an absurd fit) predicts inf and NaN through the quadratic
    drag: it must give no estimate rather than a NaN one, and the next position must restart it
    (NaN fails every comparison, so a bound written as "reset if above" would fuse it)."""
    start = make_state([1.5, 0.0, 0.3], [-8.0, 0.0, 1.5])
    truth_at = trajectory(start, 0.2)
    dut = BallEkf()
    tracked = dut.update(dut.initial_state(), positions_along(truth_at, np.arange(0.0, 0.1, 0.005)))
    # -1e100 m/s: the mean itself becomes NaN; -1e6 m/s: the mean stays finite (if absurd) while
    # the covariance, through the finite-difference Jacobian, overflows
    for speed, mean_finite in ((-1e100, False), (-1e6, True)):
        state = dut.update(dut.initial_state(), positions_along(truth_at, np.arange(0.0, 0.1, 0.005)))
        index = state.batch.index[0]
        latest = int(index[ekf_kernels.X_CORE0] + index[ekf_kernels.X_N] - index[ekf_kernels.X_FIRST])
        state.batch.core_f[0, latest, ekf_kernels.C_MEAN + 3] = speed  # the diverged velocity, m/s
        mean, covariance, _ = dut.predict(state.latest.mean, state.latest.covariance, 0.005)
        assert np.all(np.isfinite(mean)) == mean_finite and not np.all(np.isfinite(covariance))
        assert dut.estimate(state, 0.1) is None and dut.estimate(tracked, 0.1) is not None
        state = dut.update(state, positions_along(truth_at, [0.1, 0.105, 0.11, 0.115], start_sequence=30))
        assert state.latest.resets == 1
        np.testing.assert_allclose(dut.estimate(state, 0.115).mean[:3], truth_at(0.115)[:3], atol=1e-3)
    # Diverged to absurd finite values, which no finiteness check catches (a velocity of 1e24 m/s
    # reached a training run's observations and turned its networks into NaN): faster or spinning
    # faster than any ball (EstimatorParams.max_speed, max_spin), no estimate either.
    for column, value in ((ekf_kernels.C_MEAN + 3, -500.0), (ekf_kernels.C_MEAN + 7, 1e5)):
        state = dut.update(dut.initial_state(), positions_along(truth_at, np.arange(0.0, 0.1, 0.005)))
        index = state.batch.index[0]
        latest = int(index[ekf_kernels.X_CORE0] + index[ekf_kernels.X_N] - index[ekf_kernels.X_FIRST])
        state.batch.core_f[0, latest, column] = value
        mean, covariance, _ = dut.predict(state.latest.mean, state.latest.covariance, 0.005)
        assert np.all(np.isfinite(mean)) and np.all(np.isfinite(covariance))
        assert dut.estimate(state, 0.1) is None
        state = dut.update(state, positions_along(truth_at, [0.1, 0.105, 0.11, 0.115], start_sequence=30))
        assert state.latest.resets == 1  # the next position restarts it
        np.testing.assert_allclose(dut.estimate(state, 0.115).mean[:3], truth_at(0.115)[:3], atol=1e-3)
    with pytest.raises(ConfigError, match="max_speed"):
        EstimatorParams(max_speed=0.0)


def test_a_racket_contact_restarts_from_the_measurements_after_it():
    incoming = make_state([1.5, 0.0, 0.3], [-8.0, 0.0, 1.5], [0.0, -200.0, 0.0])
    incoming_at = trajectory(incoming, 0.1)
    dut = BallEkf()
    state = dut.update(dut.initial_state(), positions_along(incoming_at, np.arange(0.0, 0.1, 0.005)))
    state = dut.update(state, racket_contact_times=[0.1])
    assert dut.estimate(state, 0.1) is None and state.latest.resets == 1
    returned_at = trajectory(incoming_at(0.1) * np.r_[1, 1, 1, -1, 1, 1, 1, -1, 1], 0.02)  # sent back
    after = lambda t: returned_at(t - 0.1)
    # Late measurements from before the contact do not start a track.
    state = dut.update(state, positions_along(incoming_at, [0.098], start_sequence=50))
    state = dut.update(state, positions_along(after, [0.1025, 0.1075], start_sequence=60))
    assert dut.estimate(state, 0.11) is None
    state = dut.update(state, positions_along(after, [0.1125], start_sequence=62))
    np.testing.assert_allclose(dut.estimate(state, 0.1125).mean[3:6], after(0.1125)[3:6], atol=0.05)


# ---------------------------------------------------------------------------------- spin
def spin_track(params, spin_count):
    """A track of positions, then ``spin_count`` spin measurements of the same constant spin with
    1 (rad/s)^2 precision: returns the spin covariance of the estimate."""
    start = make_state([1.5, 0.0, 0.3], [-8.0, 0.0, 1.5], [0.0, -300.0, 0.0])
    dut = BallEkf(params)
    state = dut.update(dut.initial_state(), positions_along(trajectory(start, 0.02), [0.0, 0.005, 0.01]))
    spins = [measurement(i + 1, 0.01 + 1e-5 * i, start[6:], variance=1.0) for i in range(spin_count)]
    state = dut.update(state, spins=spins)
    estimate = dut.estimate(state, 0.01)  # the posterior's time: spins are fused there
    assert estimate.spin_valid
    np.testing.assert_allclose(estimate.mean[6:], start[6:], rtol=1e-4)  # the zero prior pulls a little
    return estimate.covariance[6:, 6:]


def test_the_spin_sensors_bias_bounds_the_spin_variance():
    axis_variance = spin_track(EstimatorParams(), 200)[1, 1]  # the spin is along y
    across_variance = spin_track(EstimatorParams(), 200)[0, 0]
    assert axis_variance == pytest.approx(EstimatorParams().spin_bias_magnitude_std**2, rel=0.02)
    assert across_variance == pytest.approx((300 * EstimatorParams().spin_bias_axis_std) ** 2, rel=0.02)
    unbiased = spin_track(EstimatorParams(spin_bias_magnitude_std=0.0, spin_bias_axis_std=0.0), 200)
    assert np.max(np.diag(unbiased)) < 1.0 / 200 * 1.1  # averaging: R / n


# ---------------------------------------------------------------------------------- config
@pytest.mark.parametrize(
    "data, field",
    [
        ({"initial_position_count": 2}, "initial_position_count"),
        ({"position_observation_variance": 0.0}, "position_observation_variance"),
        ({"max_position_jump": -0.4}, "max_position_jump"),
        ({"update_offset": -0.001}, "update_offset"),
    ],
)
def test_bad_estimator_config_names_the_field(data, field):
    with pytest.raises(ConfigError, match=field):
        from_dict(EstimatorParams, data)


def test_observation_orders_contacts_first_at_equal_times():
    contact = Observation.contact(0.1)
    position = Observation.of(measurement(1, 0.1, [0, 0, 0]), 1)
    assert contact.key < position.key


# ---------------------------------------------------------------------------------- B environments
TICK = 0.032
RACKET_ROW, GAP_ROW, SILENT_ROW = 1, 3, 5


@functools.cache
def batch_streams():
    """Seven environments' inputs tick by tick: returns from ``play.shots`` through both statistical
    sensors (20 % position dropout) for 0.6 s (a bounce on the robot's half, the floor); a racket
    contact at 0.2 s in RACKET_ROW, nothing captured in 0.12-0.4 s in GAP_ROW (a gap reset), no
    measurement at all in SILENT_ROW. Returns per row a list of (positions, spins, racket times)."""
    from ace_drake.perception.params import PositionSensorParams
    from ace_drake.play.shots import RETURN_RANGES, synthetic_candidates, valid_shots

    candidates = synthetic_candidates(np.random.default_rng(3), RETURN_RANGES, 60)
    starts = candidates[valid_shots(candidates, False)][:7]
    shots = simulate_shots(starts, 0.6, seed=3, position=PositionSensorParams(dropout_probability=0.2))
    ticks = int(0.6 / TICK)
    rows = []
    for row, shot in enumerate(shots):
        keep = lambda m: row != SILENT_ROW and not (row == GAP_ROW and 0.12 < m.capture_time < 0.4)
        numbered = [
            [Measurement(i + 1, m.capture_time, m.release_time, m.value, m.covariance) for i, m in enumerate(filter(keep, pending))]
            for pending in (shot.positions, shot.spins)
        ]
        due = lambda ms, k: [m for m in ms if k * TICK < m.release_time <= (k + 1) * TICK]
        rows.append([
            (due(numbered[0], k), due(numbered[1], k), [0.2] if row == RACKET_ROW and k * TICK < 0.2 <= (k + 1) * TICK else [])
            for k in range(ticks)
        ])
    return rows


def assert_same_filter(actual, expected):
    a, e = actual.latest, expected.latest
    assert (a.time, a.tracking, a.resets, a.last_capture, a.spin_fused, a.not_before) == (e.time, e.tracking, e.resets, e.last_capture, e.spin_fused, e.not_before)
    assert (actual.discarded, actual.history_length) == (expected.discarded, expected.history_length)
    assert len(a.start_positions) == len(e.start_positions) and len(a.start_spins) == len(e.start_spins)
    if e.tracking:
        np.testing.assert_array_equal(a.mean, e.mean)
        np.testing.assert_array_equal(a.covariance, e.covariance)


def test_the_batch_is_each_environments_filter():
    # Bit for bit: the kernels run each environment's steps alone, whatever the others do.
    streams = batch_streams()
    dut = BallEkf()
    states = [dut.initial_state()] * len(streams)
    batch = tuple(states)
    resets, bounced = np.zeros(len(streams), dtype=int), False
    for k in range(len(streams[0])):
        now = (k + 1) * TICK
        batch = dut.update_batch(batch, *zip(*(rows[k] for rows in streams)))
        states = [dut.update(state, *rows[k]) for state, rows in zip(states, streams)]
        means, covariances, status = dut.estimate_batch(batch, np.full(len(streams), now))
        for row, state in enumerate(states):
            assert_same_filter(batch[row], state)
            expected = dut.estimate(state, now)
            assert status[row, 0] == float(expected is not None)
            if expected is not None:
                np.testing.assert_array_equal(means[row], expected.mean)
                np.testing.assert_array_equal(covariances[row], expected.covariance)
                assert (status[row, 1], status[row, 2]) == (float(expected.spin_valid), expected.last_capture_time)
            else:
                np.testing.assert_array_equal(means[row], 0.0)
        resets = np.array([state.latest.resets for state in states])
        bounced = bounced or any(np.isfinite(state.latest.segment_start) for state in states)
    # The streams exercise what they are for: predictions through a bounce (``simulate``), the
    # racket contact and the gap restart tracks.
    assert bounced
    assert resets[RACKET_ROW] >= 1 and resets[GAP_ROW] >= 1
    assert not batch[SILENT_ROW].latest.tracking and batch[SILENT_ROW].history_length == 0
    assert sum(state.latest.tracking for state in states) >= 4


def test_one_environment_is_update():
    dut = BallEkf()
    state = single = dut.initial_state()
    for positions, spins, racket in batch_streams()[RACKET_ROW]:
        (state,) = dut.update_batch([state], [positions], [spins], [racket])
        single = dut.update(single, positions, spins, racket)
        assert_same_filter(state, single)


def test_empty_inputs_change_nothing():
    dut = BallEkf()
    batch = dut.initial_batch(3)
    assert dut.update_arrays(batch, dut.observations([(), (), ()], [(), (), ()])).row(2).latest == dut.initial_state().latest
    means, covariances, status = dut.estimate_batch(batch, [0.1, 0.2, 0.3])
    np.testing.assert_array_equal(status[:, 0], 0.0)
    np.testing.assert_array_equal(means, 0.0)
    state = dut.update(dut.initial_state())
    assert dut.estimate(state, 0.1) is None
    tracked = dut.update(dut.initial_state(), positions_along(trajectory(make_state([1.5, 0.0, 0.3], [-8.0, 0.0, 1.0]), 0.02), [0.0, 0.005, 0.01]))
    assert dut.update(tracked) is tracked
    with pytest.raises(ValueError, match="environments"):
        dut.update_arrays(batch, dut.observations([()], [()]))


def test_a_cleared_environment_starts_again():
    dut = BallEkf()
    streams = batch_streams()
    batch = dut.initial_batch(2)
    for k in range(5):
        batch = dut.update_arrays(batch, dut.observations(*zip(*(rows[k][:2] for rows in streams[:2]))))
    assert batch.row(0).latest.tracking and batch.row(1).latest.tracking
    cleared = batch.cleared([1])
    assert not cleared.row(1).latest.tracking and cleared.row(1).history_length == 0
    assert_same_filter(cleared.row(0), batch.row(0))
    assert batch.row(1).latest.tracking  # the original is untouched


def observation_arrays_reference(ekf: BallEkf, positions, spins, racket_contact_times):
    """``BallEkf.observation_arrays`` in NumPy array operations: the reference of its kernel
    (``ekf_kernels.place_observations``)."""
    count = len(racket_contact_times)
    position_rows, spin_rows = np.asarray(positions[0], dtype=np.int64), np.asarray(spins[0], dtype=np.int64)
    contact_rows = np.repeat(np.arange(count, dtype=np.int64), [len(times) for times in racket_contact_times])
    contact_times = np.array([float(time) for times in racket_contact_times for time in times], dtype=float)
    position_counts, spin_counts = np.bincount(position_rows, minlength=count), np.bincount(spin_rows, minlength=count)
    contact_counts = np.bincount(contact_rows, minlength=count)
    start = np.zeros(count + 1, dtype=np.int64)
    start[1:] = np.cumsum(position_counts + spin_counts + contact_counts)
    values = np.zeros((int(start[-1]), ekf_kernels.OBS_F))
    kinds_out = np.zeros((int(start[-1]), ekf_kernels.OBS_I), dtype=np.int64)

    def place(rows, counts, offset):
        first = np.cumsum(counts) - counts
        return start[rows] + offset[rows] + np.arange(rows.size) - first[rows]

    for (rows, sequence, capture, value, covariance), counts, offset, kind, lag in (
        (positions, position_counts, np.zeros(count, dtype=np.int64), POSITION, 0.0),
        (spins, spin_counts, position_counts, SPIN, ekf.params.spin_fusion_lag),
    ):
        at = place(np.asarray(rows, dtype=np.int64), counts, offset)
        values[at, ekf_kernels.O_KEY] = capture + lag
        values[at, ekf_kernels.O_CAPTURE] = capture
        values[at, ekf_kernels.O_VALUE:ekf_kernels.O_VALUE + 3] = value
        values[at, ekf_kernels.O_COVARIANCE:] = np.reshape(covariance, (-1, 9))
        kinds_out[at, ekf_kernels.O_KIND] = kind
        kinds_out[at, ekf_kernels.O_SEQUENCE] = sequence
    at = place(contact_rows, contact_counts, position_counts + spin_counts)
    values[at, ekf_kernels.O_KEY] = contact_times
    values[at, ekf_kernels.O_CAPTURE] = contact_times
    return values, kinds_out, start


def test_observation_kernel_equals_its_numpy_reference_from_arrays_and_from_rings():
    rng = np.random.default_rng(6)
    ekf = BallEkf()
    for trial in range(40):
        batch = int(rng.integers(1, 5))
        histories = MeasurementHistoryBatch.empty(batch, 6)
        counts = rng.integers(0, 9, batch)
        rows = np.repeat(np.arange(batch), counts)
        capture = np.sort(rng.uniform(0.0, 1.0, rows.size))
        histories = histories.extended(rows, capture, capture + 0.01, rng.normal(size=(rows.size, 3)), rng.normal(size=(rows.size, 3, 3)))
        contacts = [list(rng.uniform(0.0, 1.0, int(rng.integers(0, 3)))) for _ in range(batch)]
        read = [histories.since_rows(rng.integers(0, 9, batch)) for _ in range(2)]  # positions, spins
        flat = [(r, histories.sequence[r, s], histories.capture_time[r, s], histories.value[r, s], histories.covariance[r, s]) for r, s in read]
        expected = observation_arrays_reference(ekf, *flat, contacts)
        h = histories
        for actual in (ekf.observation_arrays(*flat, contacts),
                       ekf.observations_of_rings(*[(r, r, s, h.sequence, h.capture_time, h.value, h.covariance) for r, s in read], contacts)):
            for mine, theirs in zip((actual.values, actual.kinds, actual.start), expected):
                np.testing.assert_array_equal(mine, theirs)


def test_predictions_simulated_ball_by_ball_or_together_are_the_same():
    # A bounce inside the prediction: the few requests of one duration take simulate_ball, many simulate.
    ekf = BallEkf(physics=PHYSICS)
    start = make_state([-0.8, 0.1, 0.03], [-5.0, 0.3, -3.0], [0.0, 200.0, 50.0])
    for count in (1, ball_ekf.SIMULATED_TOGETHER):
        requests, results = np.zeros((count, ball_ekf.REQUEST_SIZE)), np.zeros((count, ball_ekf.REQUEST_SIZE))
        for b in range(count):
            requests[b, :90] = (start + 1e-4 * b + np.eye(10, 9) * 1e-6).ravel()
            requests[b, 90:] = 0.006, 0.003
        ekf._simulate_requests(requests, results, np.arange(count))
        for b in range(count):
            trajectory = simulate(requests[b, :90].reshape(10, 9), PHYSICS, 0.006, dt=0.003, record=False)
            np.testing.assert_array_equal(results[b, :90], trajectory.final_state.ravel())
            assert results[b, 90] == 1.0 and results[b, 91] == trajectory.events[0][-1].time
