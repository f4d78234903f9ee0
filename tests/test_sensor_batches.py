"""The batched sensor models of the segment-stepped diagram against the per-sensor ones they
stand for: the same measurements, numbers, states and draws, bit for bit (issue 29); their
compiled kernels against the NumPy forms they replaced."""

import numpy as np
import pytest

from ace_drake.perception.measurements import MeasurementHistory, MeasurementHistoryBatch
from ace_drake.perception.params import SpinSensorParams
from ace_drake.perception.sensor_models import (
    ZERO_SPIN,
    PendingBatch,
    PendingMeasurement,
    draw_spin_variates,
    due_mask,
    insert_pending,
    insert_pending_batch,
    intervals_reached,
    racket_tracking_loss,
    racket_tracking_loss_batch,
    release_due_batch,
    rotate,
    spin_at_times,
    spin_at_times_batch,
    spin_measurements,
    spin_pending_batch,
    spin_precision_covariance,
)
from ace_drake.physics.propagate import ContactEvent, ContactKind
from ace_drake.systems.gaze_spin_sensor import SpinSensorBatchState, SpinSensorState, poll_spin_sensor, poll_spin_sensors, start_spin_sensor
from ace_drake.systems.statistical_position_sensor import SensorQueue, SensorQueueBatch

SPIN = SpinSensorParams()
CAPACITY = 8


def random_pending(rng, count, start=0.0):
    """``count`` pending measurements captured after ``start`` (s), some with equal release times."""
    capture = np.sort(start + rng.uniform(0.0, 0.05, count))
    release = capture + rng.choice([0.005, 0.01, 0.0125], count)
    return insert_pending((), (PendingMeasurement(float(c), float(r), rng.normal(size=3), np.eye(3) * rng.uniform(1, 2)) for c, r in zip(capture, release)))


def assert_same_history(a: MeasurementHistory, b: MeasurementHistory):
    assert a.capacity == b.capacity and a.last_sequence == b.last_sequence and len(a.measurements) == len(b.measurements)
    for x, y in zip(a.measurements, b.measurements):
        assert (x.sequence, x.capture_time, x.release_time) == (y.sequence, y.capture_time, y.release_time)
        assert np.array_equal(x.value, y.value) and np.array_equal(x.covariance, y.covariance)


def assert_same_pending(a, b):
    assert len(a) == len(b)
    for x, y in zip(a, b):
        assert (x.capture_time, x.release_time) == (y.capture_time, y.release_time)
        assert np.array_equal(x.value, y.value) and np.array_equal(x.covariance, y.covariance)


@pytest.mark.parametrize("batch", [1, 5])
def test_queue_batch_releases_as_each_queue_would(batch):
    rng = np.random.default_rng(3)
    queues = [SensorQueue(MeasurementHistory(capacity=CAPACITY)) for _ in range(batch)]
    together = SensorQueueBatch.empty(batch, CAPACITY)
    for tick in range(12):
        now = 0.032 * (tick + 1) + rng.uniform(0, 0.004, batch)
        # some sensors sample nothing this tick (count 0), one never samples at all
        new = [random_pending(rng, int(rng.integers(0, 4)) if b else 0, start=now[b] - 0.05) for b in range(batch)]
        queues = [queue.sampled(new[b], float(now[b])) for b, queue in enumerate(queues)]
        together = together.sampled(PendingBatch.from_rows(new), now)
        if tick == 6:  # a new episode in the middle of the batch
            queues[batch // 2] = SensorQueue(MeasurementHistory(capacity=CAPACITY))
            together = together.restarted([batch // 2], MeasurementHistory(capacity=CAPACITY))
        for b in range(batch):
            row = together.row(b)
            assert_same_history(row.history, queues[b].history)
            assert_same_pending(row.pending, queues[b].pending)
        later = now + 0.02
        released = together.released(later)[0]
        for b in range(batch):
            assert_same_history(released[b], queues[b].released(float(later[b]))[0])


def test_release_due_batch_with_nothing_due_or_nothing_pending_keeps_the_histories():
    histories = (MeasurementHistory(capacity=CAPACITY),) * 3
    assert release_due_batch(histories, PendingBatch.empty(), np.zeros(3))[0] is histories
    pending = PendingBatch.from_rows([random_pending(np.random.default_rng(0), 3, start=1.0), (), ()])
    same, rest = release_due_batch(histories, pending, np.zeros(3))
    assert same is histories and rest is pending


def test_insert_pending_batch_orders_as_insert_pending():
    rng = np.random.default_rng(5)
    old = [random_pending(rng, 3), (), random_pending(rng, 2)]
    new = [random_pending(rng, 2), random_pending(rng, 1), ()]
    merged = insert_pending_batch(PendingBatch.from_rows(old), PendingBatch.from_rows(new))
    for b in range(3):
        assert_same_pending(merged.row_pending(b), insert_pending(old[b], new[b]))


def test_contact_functions_batched_equal_per_ball():
    rng = np.random.default_rng(7)
    contacts = [np.array([0.1, 0.2]), np.array([]), np.array([0.05, 0.12, 0.3])]
    width = max(c.size for c in contacts)
    times = np.full((3, width), np.inf)
    racket = np.full((3, width), np.nan)
    before = np.zeros((3, width, 3))
    w_now = rng.normal(size=(3, 3))
    for b, c in enumerate(contacts):
        times[b, : c.size] = c
        racket[b, : c.size] = c
        before[b, : c.size] = rng.normal(size=(c.size, 3))
    rows = np.array([0, 0, 1, 2, 2, 2, 0])
    captures = np.array([0.05, 0.15, 0.2, 0.01, 0.2, 0.31, 0.25])
    spins, counts = spin_at_times_batch(rows, captures, w_now, times, before)
    loss = racket_tracking_loss_batch(rows, captures, racket, SPIN)
    for i, b in enumerate(rows):
        one_spin, one_count = spin_at_times([captures[i]], w_now[b], contacts[b], before[b, : contacts[b].size])
        assert np.array_equal(spins[i], one_spin[0]) and counts[i] == one_count[0]
        assert loss[i] == racket_tracking_loss([captures[i]], contacts[b], SPIN)[0]


@pytest.mark.parametrize("batch", [1, 4])
def test_spin_sensors_polled_together_equal_each_alone(batch):
    rng = np.random.default_rng(11)
    seeds = rng.integers(0, 2**62, batch)
    empty = MeasurementHistory(capacity=CAPACITY)
    singles = [start_spin_sensor(SPIN, _empty_state(), int(seed), 0.0) for seed in seeds]
    together = SpinSensorBatchState.empty(batch, CAPACITY).started(SPIN, np.arange(batch), seeds, 0.0, empty)
    events = [[] for _ in range(batch)]
    for poll in range(1, 40):
        now = np.full(batch, poll * SPIN.poll_period)
        w_now = rng.normal(scale=50.0, size=(batch, 3))
        if poll in (10, 25):  # a table bounce for the first ball, a racket contact for the last
            events[0].append(ContactEvent(ContactKind.TABLE, float(now[0]) - 1e-4, np.r_[np.zeros(6), w_now[0] + 1.0], np.zeros(9)))
            events[-1].append(ContactEvent(ContactKind.RACKET, float(now[-1]) - 2e-4, np.r_[np.zeros(6), w_now[-1] - 1.0], np.zeros(9)))
        singles = [poll_spin_sensor(SPIN, state, int(seeds[b]), float(now[b]), w_now[b], events[b]) for b, state in enumerate(singles)]
        together = poll_spin_sensors(SPIN, together, seeds, now, w_now, events)
        for b in range(batch):
            row = together.row(b)
            assert row.next_capture_time == singles[b].next_capture_time
            assert len(row.biases) == len(singles[b].biases)
            for x, y in zip(row.biases, singles[b].biases):
                assert x.magnitude == y.magnitude and np.array_equal(x.rotation_vector, y.rotation_vector)
            assert_same_history(row.queue.history, singles[b].queue.history)
            assert_same_pending(row.queue.pending, singles[b].queue.pending)
    assert all(len(state.queue.history.measurements) > 0 for state in singles)


def _empty_state():
    return SpinSensorState(SensorQueue(MeasurementHistory(capacity=CAPACITY)))


# ---------------------------------------------------------------------------------- compiled kernels
# The NumPy forms the kernels of sensor_models replaced, operation for operation: their references.
def perturb_spin_reference(w_W, magnitude_offset, rotation_vectors, fallback_axis):
    rate = np.linalg.norm(w_W, axis=1)
    spinning = rate > ZERO_SPIN
    turned = np.where(spinning[:, None], w_W / np.where(spinning, rate, 1.0)[:, None], fallback_axis)
    for rotation_vector in rotation_vectors:
        turned = rotate(rotation_vector, turned)
    return (rate + magnitude_offset)[:, None] * turned


def spin_measurements_reference(w_W, capture_times, bias_magnitude, bias_rotation_vector, tracking_loss, variates, params):
    kept = variates.dropout >= params.dropout_probability
    kept &= ~(tracking_loss & (variates.tracking_loss < params.racket_dropout_probability))
    magnitude_noise = params.magnitude_noise_std * variates.magnitude
    axis_noise = params.axis_noise_std * variates.axis
    fallback_axis = variates.fallback_axis / np.linalg.norm(variates.fallback_axis, axis=1, keepdims=True)
    values = perturb_spin_reference(w_W, bias_magnitude + magnitude_noise, (bias_rotation_vector, axis_noise), fallback_axis)
    return kept, capture_times + variates.latency, values, spin_precision_covariance(values, params)


def spin_at_times_reference(rows, times, w_now, contact_times, spins_before_contact):
    counts = np.sum(contact_times[rows] <= times[:, None], axis=1)
    spins = w_now[rows]
    later = counts < np.sum(np.isfinite(contact_times), axis=1)[rows]
    spins[later] = spins_before_contact[rows[later], counts[later]]
    return spins, counts


def tracking_loss_reference(rows, capture_times, racket_contact_times, params):
    if racket_contact_times.shape[1] == 0:
        return np.zeros(capture_times.shape, dtype=bool)
    since = capture_times[:, None] - racket_contact_times[rows]
    return np.any((since >= 0.0) & (since <= params.racket_dropout_duration), axis=1)


def pending_arrays(batch: PendingBatch):
    return [getattr(batch, name) for name in ("row", "capture_time", "release_time", "value", "covariance")]


def from_samples_reference(row, capture_time, release_time, value, covariance, kept):
    covariance = np.broadcast_to(covariance, (kept.size, 3, 3))
    row, capture_time, release_time = row[kept], capture_time[kept], release_time[kept]
    order = np.lexsort((capture_time, release_time, row))
    return [row[order], capture_time[order], release_time[order], value[kept][order], covariance[kept][order]]


def insert_reference(pending: PendingBatch, new: PendingBatch):
    arrays = [np.concatenate([a, b]) for a, b in zip(pending_arrays(pending), pending_arrays(new))]
    order = np.lexsort((arrays[1], arrays[2], arrays[0]))
    return [a[order] for a in arrays]


def release_reference(histories: MeasurementHistoryBatch, pending: PendingBatch, now):
    due = pending.release_time <= now[pending.row]
    released = histories._extended_numpy(pending.row[due], pending.capture_time[due], pending.release_time[due], pending.value[due],
                                         pending.covariance[due]) if due.any() else histories
    return released, [a[~due] for a in pending_arrays(pending)]


def assert_arrays_equal(actual, expected):
    assert len(actual) == len(expected)
    for mine, theirs in zip(actual, expected):
        assert mine.shape == theirs.shape and mine.dtype == theirs.dtype
        np.testing.assert_array_equal(mine, theirs)


def test_spin_model_kernels_equal_their_numpy_references():
    rng = np.random.default_rng(12)
    for trial in range(300):
        n = int(rng.integers(0, 30))
        w = rng.normal(scale=rng.choice([1e-12, 1.0, 300.0]), size=(n, 3))
        if n and trial % 4 == 0:
            w[rng.integers(0, n)] = 0.0  # no axis: the fallback
        captures = np.sort(rng.uniform(0.0, 1.0, n))
        bias_magnitude, bias_rotation = rng.normal(scale=11.0, size=n), rng.normal(scale=0.04, size=(n, 3)) * (trial % 5 != 0)
        loss = rng.random(n) < 0.3
        variates = draw_spin_variates(n, SPIN, rng)
        assert_arrays_equal(spin_measurements(w, captures, bias_magnitude, bias_rotation, loss, variates, SPIN),
                            spin_measurements_reference(w, captures, bias_magnitude, bias_rotation, loss, variates, SPIN))
        batch, width = int(rng.integers(1, 5)), int(rng.integers(0, 4))
        contacts = np.sort(rng.uniform(0.0, 1.0, (batch, width)), axis=1)
        for b in range(batch):
            contacts[b, int(rng.integers(0, width + 1)):] = np.inf  # padding
        rows = np.sort(rng.integers(0, batch, n))
        arguments = (rows, captures, rng.normal(size=(batch, 3)), contacts, rng.normal(size=(batch, width, 3)))
        assert_arrays_equal(spin_at_times_batch(*arguments), spin_at_times_reference(*arguments))
        racket = np.where(np.isfinite(contacts), contacts, np.nan)
        assert_arrays_equal([racket_tracking_loss_batch(rows, captures, racket, SPIN)], [tracking_loss_reference(rows, captures, racket, SPIN)])
        # the batch's model in one call: the biases of the samples' intervals, their tracking loss, the model, the kept in order
        intervals = rng.integers(0, 3, n)
        reached = np.zeros(batch, dtype=np.int64)
        np.maximum.at(reached, rows, intervals + 1)
        assert_arrays_equal([intervals_reached(rows, intervals, batch)], [reached])
        magnitudes, rotations = rng.normal(scale=11.0, size=(batch, 3)), rng.normal(scale=0.04, size=(batch, 3, 3))
        loss = racket_tracking_loss_batch(rows, captures, racket, SPIN)
        expected = spin_measurements(w, captures, magnitudes[rows, intervals], rotations[rows, intervals], loss, variates, SPIN)
        assert_arrays_equal(pending_arrays(spin_pending_batch(rows, intervals, captures, w, magnitudes, rotations, racket, variates, SPIN)),
                            pending_arrays(PendingBatch.from_samples(rows, captures, expected[1], expected[2], expected[3], expected[0])))


def test_pending_kernels_equal_their_numpy_references():
    rng = np.random.default_rng(13)
    for trial in range(200):
        batch = int(rng.integers(1, 5))
        histories = MeasurementHistoryBatch.empty(batch, 4)
        pending = PendingBatch.empty()
        for step in range(4):
            n = int(rng.integers(0, 12))
            rows = np.sort(rng.integers(0, batch, n))
            captures = np.sort(rng.uniform(0.0, 0.05, n)) + 0.03 * step
            releases = captures + rng.choice([0.005, 0.01, 0.0125], n)  # ties in release time
            covariance = rng.normal(size=(n, 3, 3)) if trial % 2 else np.eye(3) * 2.0
            arguments = (rows, captures, releases, rng.normal(size=(n, 3)), covariance, rng.random(n) < 0.8)
            new = PendingBatch.from_samples(*arguments)
            assert_arrays_equal(pending_arrays(new), from_samples_reference(*arguments))
            merged = insert_pending_batch(pending, new)
            assert_arrays_equal(pending_arrays(merged), insert_reference(pending, new))
            now = 0.03 * step + rng.uniform(0.0, 0.04, batch)
            assert_arrays_equal([due_mask(merged, now)], [merged.release_time <= now[merged.row]])
            (histories, pending), (expected, rest) = release_due_batch(histories, merged, now), release_reference(histories, merged, now)
            assert_arrays_equal(pending_arrays(pending), rest)
            for name in ("sequence", "capture_time", "release_time", "value", "covariance", "written", "count", "last_sequence"):
                np.testing.assert_array_equal(getattr(histories, name), getattr(expected, name))
