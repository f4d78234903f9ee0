"""Measurement, MeasurementHistory and MeasurementHistoryBatch: validation, numbering, what a
consumer reads since, and the batch row by row as the histories it stands for."""

import numpy as np
import pytest

from ace_drake.perception.measurements import Measurement, MeasurementHistory, MeasurementHistoryBatch


def measurement(sequence: int) -> Measurement:
    return Measurement(sequence, 0.005 * sequence, 0.005 * sequence + 0.01, np.full(3, float(sequence)), np.eye(3))


def test_since_gives_the_measurements_numbered_above_oldest_first():
    history = MeasurementHistory(capacity=4)
    for sequence in range(1, 7):  # 1 and 2 drop out beyond the capacity
        history = history.appended(measurement(sequence))
    assert [m.sequence for m in history.measurements] == [3, 4, 5, 6]
    assert [m.sequence for m in history.since(0)] == [3, 4, 5, 6]
    assert [m.sequence for m in history.since(4)] == [5, 6]
    assert history.since(6) == () and history.since(9) == ()
    assert MeasurementHistory().since(0) == ()


def test_a_measurement_owns_read_only_copies_and_refuses_bad_values():
    value = np.array([1.0, 2.0, 3.0])
    dut = Measurement(1, 0.0, 0.01, value, np.eye(3))
    value[0] = 9.0
    assert dut.value[0] == 1.0 and not dut.value.flags.writeable
    with pytest.raises(ValueError, match="finite"):
        Measurement(1, 0.0, 0.01, [np.nan, 0.0, 0.0], np.eye(3))
    with pytest.raises(ValueError, match="before its capture"):
        Measurement(1, 0.02, 0.01, np.zeros(3), np.eye(3))
    with pytest.raises(ValueError, match="sequence 1 does not follow 1"):
        MeasurementHistory().appended(dut).appended(dut)


def assert_same_history(a: MeasurementHistory, b: MeasurementHistory):
    assert a.capacity == b.capacity and a.last_sequence == b.last_sequence and len(a.measurements) == len(b.measurements)
    for x, y in zip(a.measurements, b.measurements):
        assert (x.sequence, x.capture_time, x.release_time) == (y.sequence, y.capture_time, y.release_time)
        assert np.array_equal(x.value, y.value) and np.array_equal(x.covariance, y.covariance)


def test_history_batch_rows_are_the_histories_through_wraps_overflows_and_restarts():
    rng = np.random.default_rng(2)
    capacity, batch = 4, 3
    dut = MeasurementHistoryBatch.empty(batch, capacity)
    expected = [MeasurementHistory(capacity=capacity)] * batch
    for step in range(40):
        # 0 to 6 new measurements per row: more than the capacity at once sometimes, none at others
        counts = rng.integers(0, 7, batch)
        rows = np.repeat(np.arange(batch), counts)
        capture = np.sort(rng.uniform(0.0, 1.0, rows.size)) + step
        release, value, covariance = capture + 0.01, rng.normal(size=(rows.size, 3)), rng.normal(size=(rows.size, 3, 3))
        dut = dut.extended(rows, capture, release, value, covariance)
        for b in range(batch):
            chosen = np.flatnonzero(rows == b)
            first = expected[b].last_sequence + 1
            expected[b] = expected[b].extended(tuple(
                Measurement(first + k, capture[i], release[i], value[i], covariance[i]) for k, i in enumerate(chosen)
            ))
        if step % 7 == 6:  # a new episode in row 1
            dut, expected[1] = dut.restarted([1]), MeasurementHistory(capacity=capacity)
        now = step + 1.5 + rng.uniform(0.0, 0.1, batch)
        observed = dut.as_array(3, now)
        read = rng.integers(0, 2 + max(h.last_sequence for h in expected), batch)
        since_rows, since_slots = dut.since_rows(read)
        for b in range(batch):
            assert_same_history(dut[b], expected[b])
            assert dut.last_sequence[b] == expected[b].last_sequence
            assert dut.first_sequence()[b] == (expected[b].measurements[0].sequence if expected[b].measurements else 0)
            np.testing.assert_array_equal(observed[b], expected[b].as_array(3, float(now[b])))
            mine = since_slots[since_rows == b]
            assert dut.sequence[b, mine].tolist() == [m.sequence for m in expected[b].since(int(read[b]))]
    assert_same_history(MeasurementHistoryBatch.from_histories(expected)[2], expected[2])


def test_history_batch_is_read_only():
    dut = MeasurementHistoryBatch.empty(2, 4).extended(np.array([0]), np.array([0.0]), np.array([0.01]), np.zeros((1, 3)), np.zeros((1, 3, 3)))
    with pytest.raises(ValueError, match="read-only"):
        dut.value[0, 0, 0] = 1.0
    assert len(dut) == 2 and dut.capacity == 4 and dut[-1].measurements == ()


def test_history_batch_extended_kernel_equals_its_numpy_reference():
    rng = np.random.default_rng(5)
    capacity, batch = 4, 5
    dut = reference = MeasurementHistoryBatch.empty(batch, capacity)
    for step in range(30):
        counts = rng.integers(0, 7, batch)  # beyond the capacity at once sometimes
        rows = np.repeat(np.arange(batch), counts)
        capture = np.sort(rng.uniform(0.0, 1.0, rows.size)) + step
        arguments = (rows, capture, capture + 0.01, rng.normal(size=(rows.size, 3)), rng.normal(size=(rows.size, 3, 3)))
        dut, reference = dut.extended(*arguments), reference._extended_numpy(*arguments)
        for name in ("sequence", "capture_time", "release_time", "value", "covariance", "written", "count", "last_sequence"):
            np.testing.assert_array_equal(getattr(dut, name), getattr(reference, name))


def since_rows_reference(batch: MeasurementHistoryBatch, sequence) -> tuple[np.ndarray, np.ndarray]:
    """``MeasurementHistoryBatch.since_rows`` in NumPy array operations: the reference of its kernel."""
    age = (batch.written[:, None] - 1 - np.arange(batch.capacity)[None, :]) % batch.capacity  # 0: newest slot
    held = age < batch.count[:, None]
    newer = np.count_nonzero(held & (batch.sequence > np.asarray(sequence, dtype=np.int64).reshape(-1, 1)), axis=1)
    rows = np.repeat(np.arange(len(batch)), newer)
    starts = np.cumsum(newer) - newer
    rank = np.arange(rows.size) - np.repeat(starts, newer)
    return rows, (batch.written[rows] - newer[rows] + rank) % batch.capacity


def test_since_rows_and_first_gap_kernels_equal_their_numpy_references():
    rng = np.random.default_rng(8)
    capacity, batch = 4, 5
    dut = MeasurementHistoryBatch.empty(batch, capacity)
    for step in range(60):
        counts = rng.integers(0, 7, batch)  # beyond the capacity at once sometimes
        rows = np.repeat(np.arange(batch), counts)
        capture = np.sort(rng.uniform(0.0, 1.0, rows.size)) + step
        dut = dut.extended(rows, capture, capture + 0.01, rng.normal(size=(rows.size, 3)), rng.normal(size=(rows.size, 3, 3)))
        if step % 9 == 8:
            dut = dut.restarted([int(rng.integers(0, batch))])
        read = rng.integers(0, dut.last_sequence.max() + 3, batch)
        for actual, expected in zip(dut.since_rows(read), since_rows_reference(dut, read)):
            assert actual.dtype == np.int64
            np.testing.assert_array_equal(actual, expected)
        gaps = np.flatnonzero((dut.count > 0) & (dut.first_sequence() > read + 1))
        assert dut.first_gap(read) == (gaps[0] if gaps.size else -1)
