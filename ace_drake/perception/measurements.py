"""The messages every ball sensor emits and every consumer reads: the estimator, the policy's
observation histories and analysis.

A sensor's output port carries a ``MeasurementHistory``: its most recent measurements (oldest
first), each stamped with its capture time (when the world looked like this) and its release time
(when the sensor published it, capture time + latency), and numbered in release order. A consumer
that updates at any rate takes the measurements numbered above the last one it has seen
(``MeasurementHistory.since``), so it never misses one as long as the history is longer than the
number released between two of its updates. The frame-camera path (ApsCameraArray ->
Triangulator), the statistical training sensors and the spin sensors all emit this type, which is
what lets sensor fidelity be a config choice in one wiring (DESIGN.md).
"""

from __future__ import annotations

import dataclasses

import numba
import numpy as np


@dataclasses.dataclass(frozen=True)
class Measurement:
    """One measurement of the ball.

    sequence: release order, 1, 2, ... per sensor (0 is never used).
    capture_time: s, simulation time the measured state refers to.
    release_time: s, when the sensor published it (capture_time + latency).
    value (3,): a position p_WB (m) or a spin w_WB (rad/s) in world.
    covariance (3, 3): of ``value``, m^2 or (rad/s)^2.
    """

    sequence: int
    capture_time: float
    release_time: float
    value: np.ndarray
    covariance: np.ndarray

    def __post_init__(self) -> None:
        value = np.array(self.value, dtype=float)  # own copies, made read-only below
        covariance = np.array(self.covariance, dtype=float)
        if value.shape != (3,) or covariance.shape != (3, 3):
            raise ValueError(f"Measurement: value must be (3,) and covariance (3, 3), got {value.shape} and {covariance.shape}")
        if not (np.isfinite(value).all() and np.isfinite(covariance).all()):
            raise ValueError(f"Measurement {self.sequence}: value and covariance must be finite, got {value} and {covariance}")
        if self.release_time < self.capture_time:
            raise ValueError(f"Measurement {self.sequence}: released at {self.release_time} s before its capture at {self.capture_time} s")
        value.flags.writeable = False
        covariance.flags.writeable = False
        object.__setattr__(self, "value", value)
        object.__setattr__(self, "covariance", covariance)

    @classmethod
    def from_model(cls, sequence: int, capture_time: float, release_time: float, value: np.ndarray, covariance: np.ndarray) -> Measurement:
        """A Measurement built without ``__post_init__``'s copies and checks, for a sensor model's
        own output (``sensor_models.release_due_batch``), which meets them by construction:
        ``value`` (3,) and ``covariance`` (3, 3) finite float arrays that nothing else holds
        writable (they are made read-only here, not copied), capture_time <= release_time (s).
        Anything else (a measurement built by hand, a triangulation) goes through the checks."""
        measurement = object.__new__(cls)
        value.flags.writeable = False
        covariance.flags.writeable = False
        # the fields straight into the instance (frozen: no __setattr__)
        measurement.__dict__.update(sequence=sequence, capture_time=capture_time, release_time=release_time, value=value, covariance=covariance)
        return measurement

    def __deepcopy__(self, memo) -> Measurement:
        return self  # immutable: Drake's abstract-state copies need not duplicate it


@dataclasses.dataclass(frozen=True)
class MeasurementHistory:
    """A sensor's most recent measurements, oldest first (at most ``capacity``)."""

    measurements: tuple[Measurement, ...] = ()
    capacity: int = 32

    def __deepcopy__(self, memo) -> MeasurementHistory:
        return self  # immutable: Drake copies abstract values on every state update

    @property
    def latest(self) -> Measurement | None:
        """The most recently released measurement, or None."""
        return self.measurements[-1] if self.measurements else None

    @property
    def last_sequence(self) -> int:
        """The sequence number of the latest measurement (0 if none yet)."""
        return self.measurements[-1].sequence if self.measurements else 0

    def since(self, sequence: int) -> tuple[Measurement, ...]:
        """The measurements numbered above ``sequence``, oldest first."""
        start = len(self.measurements)  # numbered in order: scan back from the newest
        while start > 0 and self.measurements[start - 1].sequence > sequence:
            start -= 1
        return self.measurements[start:]

    def appended(self, measurement: Measurement) -> MeasurementHistory:
        """A new history with ``measurement`` released last (the oldest dropped beyond capacity)."""
        if measurement.sequence <= self.last_sequence:
            raise ValueError(f"MeasurementHistory: sequence {measurement.sequence} does not follow {self.last_sequence}")
        return MeasurementHistory((*self.measurements, measurement)[-self.capacity :], self.capacity)

    def extended(self, measurements: tuple[Measurement, ...]) -> MeasurementHistory:
        """A new history with ``measurements`` released last, in that order, numbered on from
        ``last_sequence`` by their producer (``sensor_models.release_due``); the oldest dropped
        beyond capacity."""
        return MeasurementHistory((*self.measurements, *measurements)[-self.capacity :], self.capacity)

    def as_array(self, count: int, now: float) -> np.ndarray:
        """The latest ``count`` measurements as an array (count, 4) of [value (3,), age (s)] with
        age = now - capture_time, newest first, zero-padded with age -1 where there are fewer:
        the fixed-size history the policy observes (paper, *States*: position and spin histories
        with their time stamps)."""
        out = np.zeros((count, 4))
        out[:, 3] = -1.0
        for row, measurement in enumerate(reversed(self.measurements[-count:] if count else ())):
            out[row, :3] = measurement.value
            out[row, 3] = now - measurement.capture_time
        return out


@dataclasses.dataclass(frozen=True)
class MeasurementHistoryBatch:
    """The MeasurementHistory of B sensors (one per environment of the segment-stepped diagram)
    as arrays, so that releasing, fusing and observing them are array operations rather than one
    ``Measurement`` object per sample. Immutable: the arrays are read-only and every change makes
    a new batch.

    Each row is a ring of ``capacity`` slots: the row's ``written`` (B,) measurements so far went
    to slots 0, 1, ... modulo capacity, of which the newest ``count`` (B,) (at most capacity) are
    held. Per slot: ``sequence`` (B, C) int64, ``capture_time`` and ``release_time`` (B, C), s,
    ``value`` (B, C, 3), m or rad/s, ``covariance`` (B, C, 3, 3), m^2 or (rad/s)^2.
    ``last_sequence`` (B,): the newest held measurement's number, 0 for none.

    Indexing gives the MeasurementHistory of a row (``batch[b]``, built on demand), so a batch
    stands wherever a tuple of B histories did; consumers of all B rows read the arrays
    (``since_rows``, ``as_array``).
    """

    sequence: np.ndarray
    capture_time: np.ndarray
    release_time: np.ndarray
    value: np.ndarray
    covariance: np.ndarray
    written: np.ndarray
    count: np.ndarray
    last_sequence: np.ndarray

    def __post_init__(self) -> None:
        for array in (self.sequence, self.capture_time, self.release_time, self.value, self.covariance, self.written, self.count, self.last_sequence):
            array.flags.writeable = False

    def __deepcopy__(self, memo) -> MeasurementHistoryBatch:
        return self  # immutable: Drake copies abstract values on every state update

    @classmethod
    def empty(cls, batch: int, capacity: int) -> MeasurementHistoryBatch:
        """B empty histories that keep ``capacity`` measurements each."""
        if capacity < 1:
            raise ValueError(f"MeasurementHistoryBatch: capacity must be >= 1, got {capacity}")
        B, C = int(batch), int(capacity)
        zeros = np.zeros(B, dtype=np.int64)
        return cls(np.zeros((B, C), dtype=np.int64), np.zeros((B, C)), np.zeros((B, C)), np.zeros((B, C, 3)), np.zeros((B, C, 3, 3)),
                   zeros, zeros.copy(), zeros.copy())

    @classmethod
    def from_histories(cls, histories) -> MeasurementHistoryBatch:
        """The batch of B MeasurementHistory (capacity: the largest of theirs, so each keeps what
        it holds and no more is held than it showed)."""
        histories = tuple(histories)
        batch = cls.empty(len(histories), max((h.capacity for h in histories), default=1))
        fields = {name: getattr(batch, name).copy() for name in ("sequence", "capture_time", "release_time", "value", "covariance", "written", "count", "last_sequence")}
        for b, history in enumerate(histories):
            for slot, measurement in enumerate(history.measurements):
                fields["sequence"][b, slot] = measurement.sequence
                fields["capture_time"][b, slot], fields["release_time"][b, slot] = measurement.capture_time, measurement.release_time
                fields["value"][b, slot], fields["covariance"][b, slot] = measurement.value, measurement.covariance
            fields["written"][b] = fields["count"][b] = len(history.measurements)
            fields["last_sequence"][b] = history.last_sequence
        return cls(**fields)

    @property
    def capacity(self) -> int:
        """The measurements each row keeps."""
        return self.sequence.shape[1]

    def __len__(self) -> int:
        return self.sequence.shape[0]

    def __getitem__(self, b: int) -> MeasurementHistory:
        """Row ``b`` as a MeasurementHistory of the same capacity (its Measurements own copies)."""
        b = range(len(self))[b]  # negative indices and bounds as a tuple's
        slots = [(int(self.written[b]) - int(self.count[b]) + k) % self.capacity for k in range(int(self.count[b]))]
        measurements = tuple(
            Measurement.from_model(int(self.sequence[b, s]), float(self.capture_time[b, s]), float(self.release_time[b, s]),
                                   self.value[b, s].copy(), self.covariance[b, s].copy())
            for s in slots
        )
        return MeasurementHistory(measurements, self.capacity)

    def first_sequence(self) -> np.ndarray:
        """The oldest held measurement's number per row (B,), 0 where none is held."""
        slot = (self.written - self.count) % self.capacity
        return np.where(self.count > 0, self.sequence[np.arange(len(self)), slot], 0)

    def extended(self, rows: np.ndarray, capture_time: np.ndarray, release_time: np.ndarray, value: np.ndarray, covariance: np.ndarray) -> MeasurementHistoryBatch:
        """A new batch with measurements (n,) released last: entry i to row ``rows[i]`` (n,),
        entries grouped by row and in release order within it, numbered on from the row's
        ``last_sequence`` in that order (``MeasurementHistory.extended`` of every row).
        capture_time, release_time (n,), s; value (n, 3); covariance (n, 3, 3)."""
        rows = np.asarray(rows, dtype=np.int64)
        if rows.size == 0:
            return self
        if np.any(rows[1:] < rows[:-1]):  # a row in two runs would count its first run only
            raise ValueError("MeasurementHistoryBatch.extended: entries must be grouped by row in ascending order")
        out = [getattr(self, field.name).copy() for field in dataclasses.fields(self)]
        extend_rings(rows, np.asarray(capture_time, dtype=float), np.asarray(release_time, dtype=float), np.asarray(value, dtype=float).reshape(-1, 3),
                      np.asarray(covariance, dtype=float).reshape(-1, 3, 3), *out)
        return MeasurementHistoryBatch(*out)

    def _extended_numpy(self, rows, capture_time, release_time, value, covariance) -> MeasurementHistoryBatch:
        """``extended`` in NumPy array operations: the reference of its compiled kernel."""
        rows = np.asarray(rows, dtype=np.int64)
        C = self.capacity
        starts = np.flatnonzero(np.r_[True, rows[1:] != rows[:-1]])
        counts = np.diff(np.r_[starts, rows.size])
        first = rows[starts]
        rank = np.arange(rows.size) - np.repeat(starts, counts)  # position within its row's entries
        written, count, last = self.written.copy(), self.count.copy(), self.last_sequence.copy()
        # Only the newest C of a row's entries survive; writing just those keeps each slot's last write unique.
        keep = rank >= np.repeat(counts, counts) - C
        slots = (written[rows] + rank)[keep] % C
        target = rows[keep]
        sequence, capture, release, values, covariances = (
            self.sequence.copy(), self.capture_time.copy(), self.release_time.copy(), self.value.copy(), self.covariance.copy()
        )
        sequence[target, slots] = (last[rows] + 1 + rank)[keep]
        capture[target, slots] = np.asarray(capture_time, dtype=float)[keep]
        release[target, slots] = np.asarray(release_time, dtype=float)[keep]
        values[target, slots] = np.asarray(value, dtype=float)[keep]
        covariances[target, slots] = np.asarray(covariance, dtype=float)[keep]
        written[first] += counts
        count[first] = np.minimum(count[first] + counts, C)
        last[first] += counts
        return MeasurementHistoryBatch(sequence, capture, release, values, covariances, written, count, last)

    def restarted(self, rows) -> MeasurementHistoryBatch:
        """A new batch with rows ``rows`` empty (new episodes: numbering starts again at 1)."""
        rows = np.asarray(rows, dtype=np.int64).reshape(-1)
        written, count, last = self.written.copy(), self.count.copy(), self.last_sequence.copy()
        written[rows] = count[rows] = last[rows] = 0
        return dataclasses.replace(self, written=written, count=count, last_sequence=last)

    def since_rows(self, sequence: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The measurements numbered above ``sequence`` (B,) in every row, as (rows (n,), slots
        (n,)) into the arrays: grouped by row, oldest first within it (``MeasurementHistory.since``
        of each row). Compiled (``_since_slots``; the estimator asks for it twice per tick)."""
        after = np.asarray(sequence, dtype=np.int64)
        if after.shape != self.written.shape:
            after = np.broadcast_to(after, self.written.shape)  # one number for every row
        return _since_slots(self.sequence, self.written, self.count, after)

    def first_gap(self, sequence: np.ndarray) -> int:
        """The first row b whose oldest held measurement is numbered above sequence[b] + 1 (B,),
        i.e. that no longer holds every measurement released after sequence[b]; -1 for none."""
        return _first_gap(self.sequence, self.written, self.count, np.asarray(sequence, dtype=np.int64))

    def as_array(self, count: int, now: np.ndarray) -> np.ndarray:
        """``MeasurementHistory.as_array`` of every row, row b at ``now[b]`` (B,), s: (B, count, 4)
        of [value (3,), age (s)], newest first, zero-padded with age -1."""
        B = len(self)
        out = np.zeros((B, count, 4))
        out[:, :, 3] = -1.0
        if count == 0:
            return out
        newest = np.arange(count)
        held = newest[None, :] < self.count[:, None]
        rows, columns = np.nonzero(held)
        slots = (self.written[rows] - 1 - columns) % self.capacity
        out[rows, columns, :3] = self.value[rows, slots]
        out[rows, columns, 3] = np.asarray(now, dtype=float)[rows] - self.capture_time[rows, slots]
        return out


@numba.njit(cache=True)
def extend_rings(rows, capture_time, release_time, value, covariance, sequence, capture, release, values, covariances, written, count, last):
    """``MeasurementHistoryBatch.extended`` in place on copies of the batch's arrays (sequence,
    capture, release (B, C), values (B, C, 3), covariances (B, C, 3, 3), written, count, last (B,)):
    entries (n,) grouped by row in ascending order, the newest ``capacity`` of each row written to
    its ring (also ``sensor_models.release_due_batch``'s)."""
    n, C = rows.size, sequence.shape[1]
    start = 0
    while start < n:
        row = rows[start]
        stop = start
        while stop < n and rows[stop] == row:
            stop += 1
        entries = stop - start
        for i in range(start + max(entries - C, 0), stop):
            rank = i - start
            slot = (written[row] + rank) % C
            sequence[row, slot] = last[row] + 1 + rank
            capture[row, slot] = capture_time[i]
            release[row, slot] = release_time[i]
            for k in range(3):
                values[row, slot, k] = value[i, k]
                for m in range(3):
                    covariances[row, slot, k, m] = covariance[i, k, m]
        written[row] += entries
        count[row] = min(count[row] + entries, C)
        last[row] += entries
        start = stop


@numba.njit(cache=True)
def _since_slots(sequence, written, count, after):
    """``MeasurementHistoryBatch.since_rows``: the held slots of each row b numbered above
    after[b] (B,), as (rows (n,), slots (n,)), grouped by row, oldest first."""
    batch, capacity = sequence.shape
    rows, slots = np.empty(batch * capacity, dtype=np.int64), np.empty(batch * capacity, dtype=np.int64)
    n = 0
    for b in range(batch):
        newer = 0  # numbers grow along a row, so the ones above after[b] are its newest ``newer``
        for age in range(count[b]):  # age 0: the newest slot
            if sequence[b, (written[b] - 1 - age) % capacity] > after[b]:
                newer += 1
        for rank in range(newer):
            rows[n], slots[n] = b, (written[b] - newer + rank) % capacity
            n += 1
    return rows[:n], slots[:n]


@numba.njit(cache=True)
def _first_gap(sequence, written, count, after):
    """``MeasurementHistoryBatch.first_gap``."""
    capacity = sequence.shape[1]
    for b in range(sequence.shape[0]):
        if count[b] > 0 and sequence[b, (written[b] - count[b]) % capacity] > after[b] + 1:
            return b
    return -1
