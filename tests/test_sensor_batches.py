"""The batched sensor models of the segment-stepped diagram against the per-sensor ones they
stand for: the same measurements, numbers, states and draws, bit for bit (issue 29)."""

import numpy as np
import pytest

from ace_drake.perception.measurements import MeasurementHistory
from ace_drake.perception.params import SpinSensorParams
from ace_drake.perception.sensor_models import (
    PendingBatch,
    PendingMeasurement,
    insert_pending,
    insert_pending_batch,
    racket_tracking_loss,
    racket_tracking_loss_batch,
    release_due_batch,
    spin_at_times,
    spin_at_times_batch,
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
