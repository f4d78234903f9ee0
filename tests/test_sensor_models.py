"""Statistical sensor models: publishing order, and the configured rate, latency, noise, bias and
dropout statistics (paper, Methods *Sensor modelling*)."""

import dataclasses

import numpy as np
import pytest
from scipy import stats

from ace_drake.config import ConfigError, from_dict
from ace_drake.perception.measurements import MeasurementHistory
from ace_drake.perception.params import PositionSensorParams, SpinSensorParams
from ace_drake.perception.sensor_models import (
    PendingMeasurement,
    draw_spin_bias,
    first_spin_capture_time,
    insert_pending,
    racket_tracking_loss,
    release_due,
    rotate,
    sample_position_measurements,
    sample_spin_measurements,
    spin_at_times,
    spin_capture_times,
    spin_precision_covariance,
)

POSITION = PositionSensorParams()
SPIN = SpinSensorParams()
N = 20000


def pending(capture, release, value=0.0):
    return PendingMeasurement(capture, release, np.full(3, value), np.eye(3))


def binomial_band(p, n, sigmas=4.0):
    half = sigmas * np.sqrt(p * (1 - p) / n)
    return p - half, p + half


# ---------------------------------------------------------------------------------- publishing
def test_release_numbers_in_release_order_and_keeps_the_rest():
    queue = insert_pending((), [pending(0.0, 0.012, 1), pending(0.002, 0.010, 2), pending(0.004, 0.020, 3)])
    assert [m.release_time for m in queue] == [0.010, 0.012, 0.020]
    history, rest = release_due(MeasurementHistory(capacity=2), queue, 0.015)
    assert [(m.sequence, m.capture_time) for m in history.measurements] == [(1, 0.002), (2, 0.0)]
    assert rest == queue[2:]
    history, rest = release_due(history, rest, 0.020)  # released exactly at its release time
    assert rest == ()
    assert [m.sequence for m in history.measurements] == [2, 3]  # capacity 2 keeps the newest
    same_history, same_rest = release_due(history, rest, 1.0)
    assert same_history is history and same_rest == ()


# ---------------------------------------------------------------------------------- positions
def test_position_model_statistics_match_the_config_and_the_paper():
    rng = np.random.default_rng(1)
    truth = rng.uniform(-1.0, 1.0, (N, 3))
    captures = np.arange(N) * POSITION.trigger_period
    sampled = sample_position_measurements(truth, captures, POSITION, rng)
    kept = np.searchsorted(captures, [m.capture_time for m in sampled])
    low, high = binomial_band(1 - POSITION.dropout_probability, N)
    assert low < len(sampled) / N < high
    latencies = np.array([m.release_time - m.capture_time for m in sampled])
    assert latencies.min() >= POSITION.latency_min and latencies.max() <= POSITION.latency_max
    assert stats.kstest(latencies, stats.uniform(POSITION.latency_min, POSITION.latency_max - POSITION.latency_min).cdf).pvalue > 1e-3
    assert latencies.mean() == pytest.approx(0.0102, abs=1e-4)  # paper: 10.2 ms
    errors = np.array([m.value for m in sampled]) - truth[kept]
    np.testing.assert_allclose(errors.mean(axis=0), 0.0, atol=4 * POSITION.noise_std / np.sqrt(len(sampled)))
    np.testing.assert_allclose(errors.std(axis=0), POSITION.noise_std, rtol=0.03)
    assert np.linalg.norm(errors, axis=1).mean() == pytest.approx(0.0030, rel=0.03)  # paper: 3.0 mm
    np.testing.assert_array_equal(sampled[0].covariance, POSITION.noise_std**2 * np.eye(3))


def test_position_draws_do_not_depend_on_the_values():
    a, b = np.random.default_rng(5), np.random.default_rng(5)
    first = sample_position_measurements(np.zeros((4, 3)), np.arange(4.0), POSITION, a)
    second = sample_position_measurements(np.ones((4, 3)), np.arange(4.0), POSITION, b)
    assert a.random() == b.random()  # same number of draws
    for x, y in zip(first, second):
        np.testing.assert_allclose(y.value - x.value, 1.0)
        assert x.release_time == y.release_time


# ---------------------------------------------------------------------------------- spin rate
def test_spin_sample_intervals_are_uniform_in_the_400_to_700_hz_band():
    rng = np.random.default_rng(2)
    start = first_spin_capture_time(0.3, SPIN, rng)
    assert 0.3 + 1 / 700 <= start <= 0.3 + 1 / 400
    times, next_time = spin_capture_times(start, start + 20.0, SPIN, rng)
    intervals = np.diff(times)
    assert times[0] == start and next_time > start + 20.0 >= times[-1]
    assert intervals.min() >= 1 / 700 - 1e-12 and intervals.max() <= 1 / 400 + 1e-12
    assert stats.kstest(intervals, stats.uniform(1 / 700, 1 / 400 - 1 / 700).cdf).pvalue > 1e-3
    assert 400 < len(times) / 20.0 < 700


def test_spin_capture_times_continue_where_they_stopped():
    one, two = np.random.default_rng(3), np.random.default_rng(3)
    whole, _ = spin_capture_times(0.0, 0.1, SPIN, one)
    first, resume = spin_capture_times(0.0, 0.05, SPIN, two)
    second, _ = spin_capture_times(resume, 0.1, SPIN, two)
    np.testing.assert_array_equal(whole, np.concatenate([first, second]))


# ---------------------------------------------------------------------------------- spin noise
def angle_between(a, b):
    cosine = np.sum(a * b, axis=1) / (np.linalg.norm(a, axis=1) * np.linalg.norm(b, axis=1))
    return np.arccos(np.clip(cosine, -1.0, 1.0))


def sample_spins(params, w, bias_magnitude=0.0, bias_rotation=(0.0, 0.0, 0.0), loss=False, seed=4, n=N):
    rng = np.random.default_rng(seed)
    truth = np.broadcast_to(np.asarray(w, dtype=float), (n, 3))
    sampled = sample_spin_measurements(
        truth, np.arange(n) * 1e-3, np.full(n, bias_magnitude), np.broadcast_to(bias_rotation, (n, 3)), np.full(n, loss), params, rng
    )
    kept = np.rint(np.array([m.capture_time for m in sampled]) / 1e-3).astype(int)
    return sampled, truth[kept]


def test_spin_precision_noise_is_gaussian_on_magnitude_and_axis():
    params = dataclasses.replace(SPIN, dropout_probability=0.0)
    sampled, truth = sample_spins(params, [120.0, -250.0, 60.0])
    values = np.array([m.value for m in sampled])
    magnitude_error = np.linalg.norm(values, axis=1) - np.linalg.norm(truth, axis=1)
    assert magnitude_error.mean() == pytest.approx(0.0, abs=4 * params.magnitude_noise_std / np.sqrt(N))
    assert magnitude_error.std() == pytest.approx(params.magnitude_noise_std, rel=0.03)
    # The axis turns by a rotation vector with per-component std s: the tilt is Rayleigh(s).
    tilt = angle_between(values, truth)
    assert tilt.mean() == pytest.approx(params.axis_noise_std * np.sqrt(np.pi / 2), rel=0.03)
    assert stats.kstest(tilt, stats.rayleigh(scale=params.axis_noise_std).cdf).pvalue > 1e-3


def test_spin_bias_shifts_every_sample_by_the_same_amount():
    params = dataclasses.replace(SPIN, dropout_probability=0.0, magnitude_noise_std=0.0, axis_noise_std=0.0)
    w = np.array([0.0, 300.0, 0.0])
    turn = np.array([0.0, 0.0, 0.05])  # 0.05 rad about z
    sampled, _ = sample_spins(params, w, bias_magnitude=-20.0, bias_rotation=turn, n=50)
    expected = 280.0 * np.array([-np.sin(0.05), np.cos(0.05), 0.0])
    for measurement in sampled:
        np.testing.assert_allclose(measurement.value, expected, atol=1e-9)


def test_bias_draws_have_the_configured_spread():
    rng = np.random.default_rng(6)
    biases = [draw_spin_bias(SPIN, rng) for _ in range(N)]
    assert np.std([b.magnitude for b in biases]) == pytest.approx(SPIN.magnitude_bias_std, rel=0.03)
    np.testing.assert_allclose(np.std([b.rotation_vector for b in biases], axis=0), SPIN.axis_bias_std, rtol=0.03)


def test_default_spin_error_is_the_papers_24_8_rad_s_at_the_median_incoming_spin():
    # One bias per sample, as over many contact events; 289 rad/s is the match data's median.
    params = dataclasses.replace(SPIN, dropout_probability=0.0)
    rng = np.random.default_rng(7)
    biases = [draw_spin_bias(params, rng) for _ in range(N)]
    truth = np.tile([0.0, 0.0, 289.0], (N, 1)) @ stats.special_ortho_group.rvs(3, random_state=8)
    sampled = sample_spin_measurements(
        truth, np.zeros(N), np.array([b.magnitude for b in biases]), np.array([b.rotation_vector for b in biases]),
        np.zeros(N, dtype=bool), params, rng,
    )
    errors = np.linalg.norm(np.array([m.value for m in sampled]) - truth, axis=1)
    assert errors.mean() == pytest.approx(24.8, rel=0.03)


def test_spin_dropout_and_tracking_loss_fractions():
    sampled, _ = sample_spins(SPIN, [0.0, 200.0, 0.0])
    low, high = binomial_band(1 - SPIN.dropout_probability, N)
    assert low < len(sampled) / N < high
    lost, _ = sample_spins(SPIN, [0.0, 200.0, 0.0], loss=True)
    assert lost == ()
    half = dataclasses.replace(SPIN, racket_dropout_probability=0.5)
    partly, _ = sample_spins(half, [0.0, 200.0, 0.0], loss=True)
    low, high = binomial_band((1 - SPIN.dropout_probability) * 0.5, N)
    assert low < len(partly) / N < high


def test_spin_latency_is_uniform_in_its_interval():
    sampled, _ = sample_spins(SPIN, [0.0, 200.0, 0.0])
    latencies = np.array([m.release_time - m.capture_time for m in sampled])
    assert latencies.min() >= SPIN.latency_min and latencies.max() <= SPIN.latency_max
    assert stats.kstest(latencies, stats.uniform(SPIN.latency_min, SPIN.latency_max - SPIN.latency_min).cdf).pvalue > 1e-3


def test_zero_spin_is_measured_along_a_random_axis_with_the_magnitude_noise():
    params = dataclasses.replace(SPIN, dropout_probability=0.0)
    sampled, _ = sample_spins(params, [0.0, 0.0, 0.0], n=5000)
    values = np.array([m.value for m in sampled])
    assert np.all(np.isfinite(values))
    # |N(0, s^2)| has mean s sqrt(2 / pi); directions spread over the sphere (mean near zero).
    assert np.linalg.norm(values, axis=1).mean() == pytest.approx(params.magnitude_noise_std * np.sqrt(2 / np.pi), rel=0.05)
    assert np.linalg.norm(values.mean(axis=0)) < 1.0
    # The covariance is the model's around what was measured (the sensor does not know the truth).
    np.testing.assert_allclose(sampled[0].covariance, spin_precision_covariance(values[:1], params)[0])


def test_precision_covariance_by_hand():
    covariance = spin_precision_covariance(np.array([[0.0, 0.0, -100.0]]), SPIN)[0]
    across = (100.0 * SPIN.axis_noise_std) ** 2
    np.testing.assert_allclose(covariance, np.diag([across, across, SPIN.magnitude_noise_std**2]), atol=1e-12)


# ---------------------------------------------------------------------------------- contacts
def test_tracking_loss_window_after_racket_contacts():
    captures = np.array([0.099, 0.1, 0.115, 0.13, 0.1301, 0.3, 0.31])
    loss = racket_tracking_loss(captures, [0.1, 0.3], SPIN)
    np.testing.assert_array_equal(loss, [False, True, True, True, False, True, True])
    assert not racket_tracking_loss(captures, [], SPIN).any()


def test_spin_at_past_times_from_contact_events():
    w_now = np.array([0.0, 0.0, 3.0])
    before = np.array([[1.0, 0.0, 0.0], [0.0, 2.0, 0.0]])  # spins just before contacts at 0.1 and 0.2 s
    spins, intervals = spin_at_times([0.05, 0.1, 0.15, 0.25], w_now, [0.1, 0.2], before)
    np.testing.assert_array_equal(spins, [[1, 0, 0], [0, 2, 0], [0, 2, 0], [0, 0, 3]])
    np.testing.assert_array_equal(intervals, [0, 1, 1, 2])
    spins, intervals = spin_at_times([0.05], w_now, [], np.zeros((0, 3)))
    np.testing.assert_array_equal(spins, [w_now])
    np.testing.assert_array_equal(intervals, [0])


# ---------------------------------------------------------------------------------- config
@pytest.mark.parametrize(
    "cls, data, field",
    [
        (PositionSensorParams, {"dropout_probability": 1.0}, "dropout_probability"),
        (PositionSensorParams, {"latency_min": 0.02}, "latency_min"),
        (PositionSensorParams, {"noise_std": -1.0}, "noise_std"),
        (SpinSensorParams, {"rate_min": 800.0}, "rate_min"),
        (SpinSensorParams, {"poll_period": 0.01}, "poll_period"),
        (SpinSensorParams, {"racket_dropout_probability": 1.5}, "racket_dropout_probability"),
        (SpinSensorParams, {"axis_bias_std": "wide"}, "axis_bias_std"),
    ],
)
def test_bad_sensor_config_names_the_field(cls, data, field):
    with pytest.raises(ConfigError, match=field):
        from_dict(cls, data)


def test_rotate_is_rodrigues_formula_as_scipy_has_it():
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(11)
    r, v = rng.normal(size=(40, 3)), rng.normal(size=(40, 3))
    r[0] = 0.0  # no rotation
    r[1] = [0.0, 0.0, np.pi]  # half a turn
    np.testing.assert_allclose(rotate(r, v), Rotation.from_rotvec(r).apply(v), atol=1e-14)
    np.testing.assert_array_equal(rotate(r[:1], v[:1]), v[:1])
