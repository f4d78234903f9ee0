"""Statistical ball sensor models: the training path's positions and the gaze-control spin sensor.

Paper, Methods *Sensor modelling*: "To model the ball triangulation obtained from APS cameras, we
sample latency from a uniform distribution and noise from a zero-mean Gaussian distribution, and
apply dropout of sensor measurements with a fixed probability. For the spin estimation, latency
and dropout are modelled similarly, with additional dropout applied directly after racket contact
[...]. Both precision (sensor noise) and accuracy (sensor bias) of GCS are modelled using separate
zero-mean Gaussian distributions for spin magnitude and axis. However, accuracy is sampled once per
contact event". The numbers are ``PositionSensorParams`` and ``SpinSensorParams`` in config.py.

Everything here is batched over samples (NumPy, and numba kernels for what the segment-stepped
sensors run every tick: the spin model, the pending queues); randomness comes only from the
``numpy.random.Generator`` passed in, and each function draws a fixed number of variates per sample
whatever the values, so that a seed gives the same stream of measurements bit for bit. A sampled
measurement is a ``PendingMeasurement`` until its release time; ``release_due`` turns the pending
ones into the numbered ``MeasurementHistory`` that sensors put on their ports.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Iterable

import numba
import numpy as np

from ace_drake.perception.measurements import Measurement, MeasurementHistory, MeasurementHistoryBatch, extend_rings
from ace_drake.perception.params import PositionSensorParams, SpinSensorParams

ZERO_SPIN = 1e-9  # rad/s: below this the true spin has no axis, and a random one is measured


@dataclasses.dataclass(frozen=True)
class PendingMeasurement:
    """A measurement sampled at ``capture_time`` (s), to be published at ``release_time`` (s).

    value (3,): position (m) or spin (rad/s) in world; covariance (3, 3) of value.
    """

    capture_time: float
    release_time: float
    value: np.ndarray
    covariance: np.ndarray


# ---------------------------------------------------------------------------------- publishing
def insert_pending(
    pending: tuple[PendingMeasurement, ...], new: Iterable[PendingMeasurement]
) -> tuple[PendingMeasurement, ...]:
    """``pending`` and ``new`` in release order (ties by capture time)."""
    return tuple(sorted((*pending, *new), key=lambda m: (m.release_time, m.capture_time)))


def release_due(
    history: MeasurementHistory, pending: tuple[PendingMeasurement, ...], now: float
) -> tuple[MeasurementHistory, tuple[PendingMeasurement, ...]]:
    """Publishes the pending measurements released at or before ``now`` (s).

    ``pending`` is in release order (``insert_pending``); the released ones are numbered on from
    ``history.last_sequence`` in that order. Returns (the history with them appended, the rest).
    """
    count = 0
    while count < len(pending) and pending[count].release_time <= now:
        count += 1
    if count == 0:
        return history, pending
    sequence = history.last_sequence
    released = []
    for item in pending[:count]:
        sequence += 1
        released.append(Measurement(sequence, item.capture_time, item.release_time, item.value, item.covariance))
    return history.extended(tuple(released)), pending[count:]


@dataclasses.dataclass(frozen=True)
class PendingBatch:
    """The pending measurements of B sensors (one per environment) in flat arrays: entry i was
    sampled by sensor ``row[i]``, and the entries are in order of row, then release time, then
    capture time (``insert_pending``'s order within a row; ties keep the order of insertion).
    Immutable: the arrays are read-only.

    row (n,) int; capture_time, release_time (n,), s; value (n, 3); covariance (n, 3, 3).
    """

    row: np.ndarray
    capture_time: np.ndarray
    release_time: np.ndarray
    value: np.ndarray
    covariance: np.ndarray

    def __post_init__(self) -> None:
        for array in (self.row, self.capture_time, self.release_time, self.value, self.covariance):
            array.flags.writeable = False

    def __deepcopy__(self, memo):  # immutable: Drake's state copies may share it
        return self

    @classmethod
    def empty(cls) -> PendingBatch:
        """No pending measurement."""
        return cls(np.zeros(0, dtype=np.int64), np.zeros(0), np.zeros(0), np.zeros((0, 3)), np.zeros((0, 3, 3)))

    @classmethod
    def from_samples(cls, row, capture_time, release_time, value, covariance, kept) -> PendingBatch:
        """The ``kept`` (n,) samples of a sensor model's output for the sensors ``row`` (n,),
        put in order; the others are dropped. A sensor's samples must come in capture order
        (as ``sample_*_measurements`` make their PendingMeasurements). covariance: (n, 3, 3),
        or (3, 3) for all. Compiled (``_kept_in_order``)."""
        covariance = np.asarray(covariance, dtype=float)
        return cls(*_kept_in_order(np.asarray(row, dtype=np.int64), np.asarray(capture_time, dtype=float), np.asarray(release_time, dtype=float),
                                   np.asarray(value, dtype=float).reshape(-1, 3), covariance.reshape(-1, 3, 3), np.asarray(kept, dtype=np.bool_)))

    @classmethod
    def from_rows(cls, rows) -> PendingBatch:
        """From each sensor's tuple of PendingMeasurements (in ``insert_pending``'s order)."""
        items = [(b, item) for b, pending in enumerate(rows) for item in pending]
        if not items:
            return cls.empty()
        return cls(
            np.array([b for b, _ in items], dtype=np.int64), np.array([item.capture_time for _, item in items], dtype=float),
            np.array([item.release_time for _, item in items], dtype=float), np.array([item.value for _, item in items], dtype=float),
            np.array([item.covariance for _, item in items], dtype=float),
        )

    def row_pending(self, b: int) -> tuple[PendingMeasurement, ...]:
        """Sensor ``b``'s pending measurements, as ``insert_pending`` orders them."""
        return tuple(
            PendingMeasurement(float(self.capture_time[i]), float(self.release_time[i]), self.value[i], self.covariance[i]) for i in np.flatnonzero(self.row == b)
        )

    def without_rows(self, rows) -> PendingBatch:
        """A copy without sensors ``rows``' pending measurements (new episodes)."""
        keep = ~np.isin(self.row, np.asarray(rows, dtype=np.int64))
        return PendingBatch(self.row[keep], self.capture_time[keep], self.release_time[keep], self.value[keep], self.covariance[keep])


def insert_pending_batch(pending: PendingBatch, new: PendingBatch) -> PendingBatch:
    """``insert_pending`` for every sensor of a batch: ``pending`` and ``new`` in order (row,
    release time, capture time; ties: ``pending`` first). Compiled (``_merged``)."""
    if new.row.size == 0:
        return pending
    if pending.row.size == 0:
        return new
    return PendingBatch(*_merged(pending.row, pending.capture_time, pending.release_time, pending.value, pending.covariance,
                                 new.row, new.capture_time, new.release_time, new.value, new.covariance))


def due_mask(pending: PendingBatch, now: np.ndarray) -> np.ndarray:
    """Whether each pending measurement (n,) is released at or before its sensor's ``now`` (B,), s."""
    return _due_mask(pending.row, pending.release_time, np.asarray(now, dtype=float))


def release_due_batch(
    histories: MeasurementHistoryBatch, pending: PendingBatch, now: np.ndarray
) -> tuple[MeasurementHistoryBatch, PendingBatch]:
    """``release_due`` for every sensor of a batch: sensor b's pending measurements released at
    or before ``now[b]`` (s) numbered on from ``histories.last_sequence[b]`` in release order and
    appended to its row. ``histories``: a MeasurementHistoryBatch (a sequence of B
    MeasurementHistory is converted). Returns (the histories, the rest of ``pending``); the same
    objects when nothing is due. The measurements stay in arrays: no Measurement is built.
    Compiled (``_released``, with ``MeasurementHistoryBatch.extended``'s kernel)."""
    due = due_mask(pending, now)
    if not due.any():
        return histories, pending
    if not isinstance(histories, MeasurementHistoryBatch):
        histories = MeasurementHistoryBatch.from_histories(histories)
    # A sensor's entries are in release order, so its due ones come first and in order.
    h = histories
    released = _released(pending.row, pending.capture_time, pending.release_time, pending.value, pending.covariance, due,
                         h.sequence, h.capture_time, h.release_time, h.value, h.covariance, h.written, h.count, h.last_sequence)
    return MeasurementHistoryBatch(*released[:8]), PendingBatch(*released[8:])


@numba.njit(cache=True)
def _stable_order(row, release_time, capture_time):
    """The order (n,) of entries by row, then release time, then capture time, ties keeping their
    order (np.lexsort((capture_time, release_time, row)): stable sorts by the last key first)."""
    order = np.argsort(capture_time, kind="mergesort")
    order = order[np.argsort(release_time[order], kind="mergesort")]
    return order[np.argsort(row[order], kind="mergesort")]


@numba.njit(cache=True)
def _gathered(order, row, capture_time, release_time, value, covariance):
    """PendingBatch's arrays of the entries ``order`` (m,) of arrays (n,); covariance (n, 3, 3),
    or (1, 3, 3) for every entry."""
    m = order.shape[0]
    out_row, out_capture, out_release = np.empty(m, dtype=np.int64), np.empty(m), np.empty(m)
    out_value, out_covariance = np.empty((m, 3)), np.empty((m, 3, 3))
    for k in range(m):
        i = order[k]
        out_row[k], out_capture[k], out_release[k] = row[i], capture_time[i], release_time[i]
        out_value[k] = value[i]
        out_covariance[k] = covariance[i if covariance.shape[0] > 1 else 0]
    return out_row, out_capture, out_release, out_value, out_covariance


@numba.njit(cache=True)
def _kept_in_order(row, capture_time, release_time, value, covariance, kept):
    """``PendingBatch.from_samples``: the kept entries, in ``_stable_order``."""
    index = np.flatnonzero(kept)
    order = _stable_order(row[index], release_time[index], capture_time[index])
    return _gathered(index[order], row, capture_time, release_time, value, covariance)


@numba.njit(cache=True)
def _merged(row, capture_time, release_time, value, covariance, new_row, new_capture_time, new_release_time, new_value, new_covariance):
    """``insert_pending_batch``: the entries of both PendingBatches (the first's before the
    second's), in ``_stable_order``."""
    n, m = row.shape[0], new_row.shape[0]
    rows, captures, releases = np.empty(n + m, dtype=np.int64), np.empty(n + m), np.empty(n + m)
    values, covariances = np.empty((n + m, 3)), np.empty((n + m, 3, 3))
    rows[:n], captures[:n], releases[:n], values[:n], covariances[:n] = row, capture_time, release_time, value, covariance
    rows[n:], captures[n:], releases[n:], values[n:], covariances[n:] = new_row, new_capture_time, new_release_time, new_value, new_covariance
    return _gathered(_stable_order(rows, releases, captures), rows, captures, releases, values, covariances)


@numba.njit(cache=True)
def _due_mask(row, release_time, now):
    """``due_mask``: release_time (n,) <= now[row] (now (B,), s)."""
    due = np.empty(row.shape[0], dtype=np.bool_)
    for i in range(row.shape[0]):
        due[i] = release_time[i] <= now[row[i]]
    return due


@numba.njit(cache=True)
def _released(row, capture_time, release_time, value, covariance, due, sequence, capture, release, values, covariances, written, count, last):
    """``release_due_batch``: the pending entries ``due`` (n,) appended to copies of the
    histories' arrays (``extend_rings``), and the rest. Returns the histories' 8 arrays, then the
    rest's 5 PendingBatch arrays."""
    rings = (sequence.copy(), capture.copy(), release.copy(), values.copy(), covariances.copy(), written.copy(), count.copy(), last.copy())
    chosen = np.flatnonzero(due)
    extend_rings(row[chosen], capture_time[chosen], release_time[chosen], value[chosen], covariance[chosen], *rings)
    rest = np.flatnonzero(~due)
    return (*rings, row[rest], capture_time[rest], release_time[rest], value[rest], covariance[rest])


# ---------------------------------------------------------------------------------- positions
def sample_position_measurements(
    p_W: np.ndarray, capture_times: np.ndarray, params: PositionSensorParams, rng: np.random.Generator
) -> tuple[PendingMeasurement, ...]:
    """The position sensor's output for true ball positions ``p_W`` (n, 3), m, at ``capture_times``
    (n,), s (paper, Methods *Sensor modelling*): each sample is dropped with probability
    ``dropout_probability``, else released after a latency uniform on [latency_min, latency_max] s
    with zero-mean Gaussian noise of ``noise_std`` m per axis and that covariance.

    Draws, in this order: n uniforms (dropout), n uniforms (latency), 3n normals (noise).
    """
    p_W = np.asarray(p_W, dtype=float).reshape(-1, 3)
    capture_times = np.asarray(capture_times, dtype=float).reshape(-1)
    kept, release_times, values, covariance = position_measurements(p_W, capture_times, draw_position_variates(p_W.shape[0], params, rng), params)
    return tuple(
        PendingMeasurement(float(capture_times[i]), float(release_times[i]), values[i], covariance)
        for i in np.flatnonzero(kept)
    )


@dataclasses.dataclass(frozen=True)
class PositionVariates:
    """The random variates of n position samples: ``dropout`` (n,) and ``latency`` (n,) uniforms,
    ``noise`` (n, 3) standard normals (``draw_position_variates``)."""

    dropout: np.ndarray
    latency: np.ndarray
    noise: np.ndarray

    @classmethod
    def concatenate(cls, parts) -> PositionVariates:
        """The variates of several sample sets, one after the other."""
        return cls(*(np.concatenate([getattr(part, name) for part in parts]) for name in ("dropout", "latency", "noise")))


def draw_position_variates(count: int, params: PositionSensorParams, rng: np.random.Generator) -> PositionVariates:
    """The variates of ``count`` position samples. Draws, in this order: n uniforms (dropout), n
    uniforms on [latency_min, latency_max] s (latency), 3n standard normals (noise)."""
    return PositionVariates(rng.random(count), rng.uniform(params.latency_min, params.latency_max, count), rng.standard_normal((count, 3)))


def position_measurements(
    p_W: np.ndarray, capture_times: np.ndarray, variates: PositionVariates, params: PositionSensorParams
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The position model (``sample_position_measurements``) of n samples, true positions ``p_W``
    (n, 3), m, at ``capture_times`` (n,), s, with their ``variates``, sample by sample (any n:
    one sensor's samples or a batch's). Returns (kept (n,) bool, release times (n,) s, values
    (n, 3) m, covariance (3, 3) m^2)."""
    kept = variates.dropout >= params.dropout_probability
    values = p_W + params.noise_std * variates.noise
    return kept, capture_times + variates.latency, values, np.eye(3) * params.noise_std**2


# ---------------------------------------------------------------------------------- spin
@dataclasses.dataclass(frozen=True)
class SpinBias:
    """The gaze-control system's accuracy error until the next contact event (paper: "accuracy is
    sampled once per contact event"): ``magnitude`` (rad/s) added to the spin rate and
    ``rotation_vector`` (3,) (rad, world) that turns the spin axis."""

    magnitude: float
    rotation_vector: np.ndarray


def draw_spin_bias(params: SpinSensorParams, rng: np.random.Generator) -> SpinBias:
    """A new accuracy bias: magnitude ~ N(0, magnitude_bias_std^2), each component of the axis's
    rotation vector ~ N(0, axis_bias_std^2). Draws 1 then 3 normals."""
    magnitude = params.magnitude_bias_std * rng.standard_normal()
    rotation_vector = params.axis_bias_std * rng.standard_normal(3)
    return SpinBias(float(magnitude), rotation_vector)


def spin_capture_times(
    first_time: float, until: float, params: SpinSensorParams, rng: np.random.Generator
) -> tuple[np.ndarray, float]:
    """The spin sensor's variable-rate sample times from ``first_time`` up to ``until`` (s).

    Each next interval is uniform on [1 / rate_max, 1 / rate_min] (400-700 Hz, paper). Returns
    (the times <= until, starting with first_time if it is; the first time after until). Draws one
    uniform per interval.
    """
    time = float(first_time)
    if not time <= until:  # NaN included: no sample, no draw
        return np.zeros(0), time
    low, high = 1.0 / params.rate_max, 1.0 / params.rate_min
    # Vectorised: draw more intervals than can fit (each is at least ``low``), sum them in order
    # (cumsum adds one after another, as the loop did), then rewind the generator and draw again
    # exactly as many as the loop would have, so that the stream goes on as before.
    state = rng.bit_generator.state
    bound = int((until - time) / low) + 2
    times, count = _times_until(time, rng.uniform(low, high, bound), until)
    rng.bit_generator.state = state
    if count > bound:  # rounding left the bound short: the loop itself
        times, next_time = [], time
        while next_time <= until:
            times.append(next_time)
            next_time += rng.uniform(low, high)
        return np.asarray(times, dtype=float), next_time
    rng.uniform(low, high, count)
    return times[:count], float(times[count])


@numba.njit(cache=True)
def _times_until(time, intervals, until):
    """``spin_capture_times``' sums: (time, then each interval (n,) added in turn, (n + 1,) s; how
    many of them are <= until)."""
    times = np.empty(intervals.shape[0] + 1)
    times[0] = time
    for k in range(intervals.shape[0]):
        times[k + 1] = times[k] + intervals[k]
    count = 0
    while count < times.shape[0] and times[count] <= until:
        count += 1
    return times, count


def first_spin_capture_time(start_time: float, params: SpinSensorParams, rng: np.random.Generator) -> float:
    """The first sample after ``start_time`` (s): one interval later, so the phase is random."""
    return float(start_time + rng.uniform(1.0 / params.rate_max, 1.0 / params.rate_min))


def racket_tracking_loss(capture_times: np.ndarray, racket_contact_times: np.ndarray, params: SpinSensorParams) -> np.ndarray:
    """Whether each capture time (n,) lies in [t_c, t_c + racket_dropout_duration] after some
    racket contact time t_c (k,) (paper: "additional dropout applied directly after racket
    contact to reflect tracking loss of GCS")."""
    capture_times = np.asarray(capture_times, dtype=float).reshape(-1)
    racket_contact_times = np.asarray(racket_contact_times, dtype=float).reshape(1, -1)
    return racket_tracking_loss_batch(np.zeros(capture_times.size, dtype=np.int64), capture_times, racket_contact_times, params)


def racket_tracking_loss_batch(rows: np.ndarray, capture_times: np.ndarray, racket_contact_times: np.ndarray, params: SpinSensorParams) -> np.ndarray:
    """``racket_tracking_loss`` of captures (n,), s, by the sensors ``rows`` (n,) of a batch
    whose racket contact times are ``racket_contact_times`` (B, k), s, each row padded with NaN."""
    return _tracking_loss_rows(np.asarray(rows, dtype=np.int64), np.asarray(capture_times, dtype=float).reshape(-1),
                               np.asarray(racket_contact_times, dtype=float), float(params.racket_dropout_duration))


@numba.njit(cache=True)
def _tracking_loss_rows(rows, capture_times, racket_contact_times, duration):
    """``racket_tracking_loss_batch``: capture i lies in [t_c, t_c + duration] of a racket
    contact t_c of its sensor (NaN padding never)."""
    lost = np.zeros(capture_times.shape[0], dtype=np.bool_)
    for i in range(capture_times.shape[0]):
        for t_c in racket_contact_times[rows[i]]:
            since = capture_times[i] - t_c
            if since >= 0.0 and since <= duration:
                lost[i] = True
    return lost


def rotate(rotation_vectors: np.ndarray, vectors: np.ndarray) -> np.ndarray:
    """R(r) v for rotation vectors r (n, 3), rad, and vectors v (n, 3) (Rodrigues' formula:
    v cos a + (k x v) sin a + k (k . v) (1 - cos a), a = |r|, k = r / a), per sample: a few
    samples per call, where scipy's Rotation objects cost ten times more. Compiled (numba), with
    the arithmetic of the NumPy form it replaced, operation for operation."""
    r = np.ascontiguousarray(rotation_vectors, dtype=float).reshape(-1, 3)
    v = np.ascontiguousarray(vectors, dtype=float).reshape(-1, 3)
    out = np.empty_like(v)
    _rotate_rows(r, v, out)
    return out


@numba.njit(cache=True)
def _rotate_rows(r, v, out):
    """``rotate`` into ``out`` (n, 3), one sample at a time."""
    for i in range(v.shape[0]):
        out[i, 0], out[i, 1], out[i, 2] = _rotate_one(r[i, 0], r[i, 1], r[i, 2], v[i, 0], v[i, 1], v[i, 2])


@numba.njit(cache=True)
def _rotate_one(rx, ry, rz, vx, vy, vz):
    """``rotate`` of one vector (vx, vy, vz) by the rotation vector (rx, ry, rz), rad: 3 floats."""
    angle = math.sqrt(rx * rx + ry * ry + rz * rz)
    safe = angle if angle > 0.0 else 1.0
    kx, ky, kz = rx / safe, ry / safe, rz / safe
    cosine, sine = math.cos(angle), math.sin(angle)
    along = (kx * vx + ky * vy + kz * vz) * (1.0 - cosine)
    return (vx * cosine + (ky * vz - kz * vy) * sine + kx * along,
            vy * cosine + (kz * vx - kx * vz) * sine + ky * along,
            vz * cosine + (kx * vy - ky * vx) * sine + kz * along)


def spin_precision_covariance(w_measured: np.ndarray, params: SpinSensorParams) -> np.ndarray:
    """The covariance (n, 3, 3), (rad/s)^2, of the precision noise around a measured spin (n, 3):
    magnitude_noise_std^2 along the axis, (|w| axis_noise_std)^2 across it (a small rotation of
    the axis by a vector with per-component std s moves the spin by |w| s in each perpendicular
    direction). The per-contact bias is not in it: it is the same for every sample until the next
    contact, so a consumer must model it as such (``BallEkf``'s ``spin_bias_std``). Without an
    axis (|w| <= ZERO_SPIN) the direction is unknown: the magnitude noise in every direction.
    Compiled (numba; the sensor asks for a few samples 200 times per simulated second)."""
    w_measured = np.ascontiguousarray(w_measured, dtype=float).reshape(-1, 3)
    covariance = np.empty((w_measured.shape[0], 3, 3))
    _precision_covariance_rows(w_measured, params.magnitude_noise_std**2, params.axis_noise_std, covariance)
    return covariance


@numba.njit(cache=True)
def _precision_covariance_rows(w, radial_variance, axis_noise_std, out):
    """``spin_precision_covariance`` into ``out`` (n, 3, 3), one sample at a time."""
    for n in range(w.shape[0]):
        _precision_covariance_one(w[n], radial_variance, axis_noise_std, out[n])


@numba.njit(cache=True)
def _precision_covariance_one(w, radial_variance, axis_noise_std, out):
    """``spin_precision_covariance`` of one measured spin w (3,) into out (3, 3)."""
    rate = math.sqrt(w[0] * w[0] + w[1] * w[1] + w[2] * w[2])
    if not rate > ZERO_SPIN:
        for i in range(3):
            for j in range(3):
                out[i, j] = radial_variance if i == j else 0.0
        return
    tangential_variance = (rate * axis_noise_std) ** 2
    for i in range(3):
        for j in range(3):
            along = (w[i] / rate) * (w[j] / rate)
            across = (1.0 if i == j else 0.0) - along
            out[i, j] = radial_variance * along + tangential_variance * across


def sample_spin_measurements(
    w_W: np.ndarray,
    capture_times: np.ndarray,
    bias_magnitude: np.ndarray,
    bias_rotation_vector: np.ndarray,
    tracking_loss: np.ndarray,
    params: SpinSensorParams,
    rng: np.random.Generator,
) -> tuple[PendingMeasurement, ...]:
    """The gaze-control spin sensor's output for true spins ``w_W`` (n, 3), rad/s, at
    ``capture_times`` (n,), s (paper, Methods *Sensor modelling*).

    Each sample is dropped with probability ``dropout_probability``, and also with probability
    ``racket_dropout_probability`` where ``tracking_loss`` (n,) is set (``racket_tracking_loss``);
    the others are released after a latency uniform on [latency_min, latency_max] with
    magnitude offset bias + N(0, magnitude_noise_std^2) and axis rotated by the rotation vector of
    the noise, N(0, axis_noise_std^2) per component, composed with that of the bias. The bias per
    sample, ``bias_magnitude`` (n,) and ``bias_rotation_vector`` (n, 3), is that of the sample's
    contact interval (``draw_spin_bias``). Covariance: ``spin_precision_covariance``.

    Draws, in this order: n uniforms (dropout), n uniforms (tracking loss), n uniforms (latency),
    n normals (magnitude noise), 3n normals (axis noise), 3n normals (axis for a zero spin).
    """
    w_W = np.asarray(w_W, dtype=float).reshape(-1, 3)
    capture_times = np.asarray(capture_times, dtype=float).reshape(-1)
    count = w_W.shape[0]
    if count == 0:
        return ()
    variates = draw_spin_variates(count, params, rng)
    kept, release_times, values, covariances = spin_measurements(w_W, capture_times, bias_magnitude, bias_rotation_vector, tracking_loss, variates, params)
    return tuple(
        PendingMeasurement(float(capture_times[i]), float(release_times[i]), values[i], covariances[i])
        for i in np.flatnonzero(kept)
    )


@dataclasses.dataclass(frozen=True)
class SpinVariates:
    """The random variates of n spin samples (``draw_spin_variates``): uniforms ``dropout``,
    ``tracking_loss`` (n,) and ``latency`` (n,) on [latency_min, latency_max] s; standard normals
    ``magnitude`` (n,), ``axis`` (n, 3) and ``fallback_axis`` (n, 3)."""

    dropout: np.ndarray
    tracking_loss: np.ndarray
    latency: np.ndarray
    magnitude: np.ndarray
    axis: np.ndarray
    fallback_axis: np.ndarray

    @classmethod
    def concatenate(cls, parts) -> SpinVariates:
        """The variates of several sample sets, one after the other."""
        return cls(*(np.concatenate([getattr(part, field.name) for part in parts]) for field in dataclasses.fields(cls)))


def draw_spin_variates(count: int, params: SpinSensorParams, rng: np.random.Generator) -> SpinVariates:
    """The variates of ``count`` spin samples. Draws, in this order: n uniforms (dropout), n
    uniforms (tracking loss), n uniforms (latency), n normals (magnitude noise), 3n normals (axis
    noise), 3n normals (axis for a zero spin)."""
    return SpinVariates(
        rng.random(count), rng.random(count), rng.uniform(params.latency_min, params.latency_max, count),
        rng.standard_normal(count), rng.standard_normal((count, 3)), rng.standard_normal((count, 3)),
    )


def spin_measurements(
    w_W: np.ndarray,
    capture_times: np.ndarray,
    bias_magnitude: np.ndarray,
    bias_rotation_vector: np.ndarray,
    tracking_loss: np.ndarray,
    variates: SpinVariates,
    params: SpinSensorParams,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The spin model (``sample_spin_measurements``) of n samples with their ``variates``, sample
    by sample (any n: one sensor's samples or a batch's). Arguments as
    ``sample_spin_measurements``'. Returns (kept (n,) bool, release times (n,) s, values (n, 3)
    rad/s, covariances (n, 3, 3) (rad/s)^2). Compiled (``_spin_measurement_rows``)."""
    return _spin_measurement_rows(
        np.asarray(w_W, dtype=float).reshape(-1, 3), np.asarray(capture_times, dtype=float).reshape(-1), np.asarray(bias_magnitude, dtype=float).reshape(-1),
        np.asarray(bias_rotation_vector, dtype=float).reshape(-1, 3), np.asarray(tracking_loss, dtype=np.bool_).reshape(-1),
        variates.dropout, variates.tracking_loss, variates.latency, variates.magnitude, variates.axis, variates.fallback_axis,
        float(params.dropout_probability), float(params.racket_dropout_probability), float(params.magnitude_noise_std),
        float(params.axis_noise_std), float(params.magnitude_noise_std**2),
    )


@numba.njit(cache=True)
def _spin_measurement_rows(w, capture_times, bias_magnitude, bias_rotation, tracking_loss, dropout, loss_draw, latency, magnitude, axis,
                           fallback_axis, dropout_probability, racket_dropout_probability, magnitude_std, axis_std, radial_variance):
    """``spin_measurements``, one sample at a time (the parameters' numbers as floats;
    radial_variance: magnitude_std^2, as ``spin_precision_covariance`` squares it).

    The measured spin is (|w| + magnitude offset) R_noise R_bias w / |w|: the bias's rotation of
    the axis, then this sample's noise (rotation vector axis_noise_std times the axis variates),
    the offset the bias's magnitude plus magnitude_noise_std times the magnitude variate; a spin
    below ZERO_SPIN has no axis and the normalised fallback_axis variates stand for it. A
    negative rate flips the axis: the measurement is a vector and that is what an estimator
    would report. Covariance: ``spin_precision_covariance`` of the measured spin."""
    n = w.shape[0]
    kept, release_times, values, covariances = np.empty(n, dtype=np.bool_), np.empty(n), np.empty((n, 3)), np.empty((n, 3, 3))
    for i in range(n):
        kept[i] = dropout[i] >= dropout_probability and not (tracking_loss[i] and loss_draw[i] < racket_dropout_probability)
        release_times[i] = capture_times[i] + latency[i]
        rate = math.sqrt(w[i, 0] * w[i, 0] + w[i, 1] * w[i, 1] + w[i, 2] * w[i, 2])
        if rate > ZERO_SPIN:
            x, y, z = w[i, 0] / rate, w[i, 1] / rate, w[i, 2] / rate
        else:
            f = fallback_axis[i]
            norm = math.sqrt(f[0] * f[0] + f[1] * f[1] + f[2] * f[2])
            x, y, z = f[0] / norm, f[1] / norm, f[2] / norm
        x, y, z = _rotate_one(bias_rotation[i, 0], bias_rotation[i, 1], bias_rotation[i, 2], x, y, z)
        x, y, z = _rotate_one(axis_std * axis[i, 0], axis_std * axis[i, 1], axis_std * axis[i, 2], x, y, z)
        scale = rate + (bias_magnitude[i] + magnitude_std * magnitude[i])
        values[i, 0], values[i, 1], values[i, 2] = scale * x, scale * y, scale * z
        _precision_covariance_one(values[i], radial_variance, axis_std, covariances[i])
    return kept, release_times, values, covariances


def spin_pending_batch(
    rows: np.ndarray,
    intervals: np.ndarray,
    capture_times: np.ndarray,
    w_W: np.ndarray,
    bias_magnitude: np.ndarray,
    bias_rotation_vector: np.ndarray,
    racket_contact_times: np.ndarray,
    variates: SpinVariates,
    params: SpinSensorParams,
) -> PendingBatch:
    """The spin model of n samples by the sensors ``rows`` (n,) of a batch, as the PendingBatch of
    those kept: ``PendingBatch.from_samples`` of ``spin_measurements`` of the true spins ``w_W``
    (n, 3), rad/s, at ``capture_times`` (n,), s, sample i with the bias of its contact interval
    intervals[i] in its sensor's tables ``bias_magnitude`` (B, k), rad/s, and
    ``bias_rotation_vector`` (B, k, 3), rad, and the tracking loss of its sensor's
    ``racket_contact_times`` (B, m), s, NaN-padded (``racket_tracking_loss_batch``). One compiled
    call (the segment-stepped sensor's every tick)."""
    return PendingBatch(*_spin_pending_rows(
        rows, intervals, capture_times, w_W, bias_magnitude, bias_rotation_vector, racket_contact_times, float(params.racket_dropout_duration),
        variates.dropout, variates.tracking_loss, variates.latency, variates.magnitude, variates.axis, variates.fallback_axis,
        float(params.dropout_probability), float(params.racket_dropout_probability), float(params.magnitude_noise_std),
        float(params.axis_noise_std), float(params.magnitude_noise_std**2),
    ))


@numba.njit(cache=True)
def _spin_pending_rows(rows, intervals, capture_times, w, bias_magnitude, bias_rotation, racket_contact_times, racket_dropout_duration,
                       dropout, loss_draw, latency, magnitude, axis, fallback_axis, dropout_probability, racket_dropout_probability,
                       magnitude_std, axis_std, radial_variance):
    """``spin_pending_batch``: the biases looked up, then ``_tracking_loss_rows``,
    ``_spin_measurement_rows`` and ``_kept_in_order``."""
    n = rows.shape[0]
    sample_magnitude, sample_rotation = np.empty(n), np.empty((n, 3))
    for i in range(n):
        sample_magnitude[i] = bias_magnitude[rows[i], intervals[i]]
        sample_rotation[i] = bias_rotation[rows[i], intervals[i]]
    lost = _tracking_loss_rows(rows, capture_times, racket_contact_times, racket_dropout_duration)
    kept, release_times, values, covariances = _spin_measurement_rows(
        w, capture_times, sample_magnitude, sample_rotation, lost, dropout, loss_draw, latency, magnitude, axis, fallback_axis,
        dropout_probability, racket_dropout_probability, magnitude_std, axis_std, radial_variance,
    )
    return _kept_in_order(rows, capture_times, release_times, values, covariances, kept)


def intervals_reached(rows: np.ndarray, intervals: np.ndarray, batch: int) -> np.ndarray:
    """How many contact intervals the samples of each of ``batch`` sensors reach (B,): one more
    than the largest interval index (``spin_at_times``' contact counts, ``intervals`` (n,)) of its
    samples (``rows`` (n,)), 0 without samples."""
    return _intervals_reached(np.asarray(rows, dtype=np.int64), np.asarray(intervals, dtype=np.int64), int(batch))


@numba.njit(cache=True)
def _intervals_reached(rows, intervals, batch):
    """``intervals_reached``."""
    reached = np.zeros(batch, dtype=np.int64)
    for i in range(rows.shape[0]):
        reached[rows[i]] = max(reached[rows[i]], intervals[i] + 1)
    return reached


def spin_at_times(
    times: np.ndarray, w_now: np.ndarray, contact_times: np.ndarray, spins_before_contact: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """The true spin (n, 3), rad/s, at past ``times`` (n,), s, and how many contacts precede each.

    Spin is constant in flight (paper eq. (1)) and changes only at contacts, so the spin at time t
    is ``w_now`` unless a contact happened after t; then it is the spin just before the first such
    contact, ``spins_before_contact`` (k, 3) for contacts at ``contact_times`` (k,), ascending.
    Returns (spins, contact counts (n,): the index of the sample's contact interval).
    """
    times = np.asarray(times, dtype=float).reshape(-1)
    contact_times = np.asarray(contact_times, dtype=float).reshape(1, -1)
    spins_before = np.asarray(spins_before_contact, dtype=float).reshape(1, -1, 3)
    return spin_at_times_batch(np.zeros(times.size, dtype=np.int64), times, np.asarray(w_now, dtype=float).reshape(1, 3), contact_times, spins_before)


def spin_at_times_batch(
    rows: np.ndarray, times: np.ndarray, w_now: np.ndarray, contact_times: np.ndarray, spins_before_contact: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """``spin_at_times`` of past ``times`` (n,), s, of the balls ``rows`` (n,) of a batch: their
    spins now ``w_now`` (B, 3), rad/s, contact times ``contact_times`` (B, k), s, ascending,
    each row padded with inf, and the spins just before them ``spins_before_contact`` (B, k, 3)."""
    return _spin_at_times_rows(np.asarray(rows, dtype=np.int64), np.asarray(times, dtype=float).reshape(-1), np.asarray(w_now, dtype=float),
                               np.asarray(contact_times, dtype=float), np.asarray(spins_before_contact, dtype=float))


@numba.njit(cache=True)
def _spin_at_times_rows(rows, times, w_now, contact_times, spins_before_contact):
    """``spin_at_times_batch``: per sample, the contacts of its ball at or before its time, and
    the spin of its contact interval."""
    spins, counts = np.empty((times.shape[0], 3)), np.zeros(times.shape[0], dtype=np.int64)
    for i in range(times.shape[0]):
        r = rows[i]
        contacts = 0
        for t_c in contact_times[r]:
            counts[i] += t_c <= times[i]
            contacts += math.isfinite(t_c)
        if counts[i] < contacts:
            spins[i] = spins_before_contact[r, counts[i]]
        else:
            spins[i] = w_now[r]
    return spins, counts
