"""Statistical ball sensor models: the training path's positions and the gaze-control spin sensor.

Paper, Methods *Sensor modelling*: "To model the ball triangulation obtained from APS cameras, we
sample latency from a uniform distribution and noise from a zero-mean Gaussian distribution, and
apply dropout of sensor measurements with a fixed probability. For the spin estimation, latency
and dropout are modelled similarly, with additional dropout applied directly after racket contact
[...]. Both precision (sensor noise) and accuracy (sensor bias) of GCS are modelled using separate
zero-mean Gaussian distributions for spin magnitude and axis. However, accuracy is sampled once per
contact event". The numbers are ``PositionSensorParams`` and ``SpinSensorParams`` in config.py.

Everything here is pure NumPy and batched over samples; randomness comes only from the
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

from ace_drake.perception.measurements import Measurement, MeasurementHistory
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
    measurements = (*history.measurements, *released)[-history.capacity :]
    return MeasurementHistory(measurements, history.capacity), pending[count:]


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
    count = p_W.shape[0]
    kept = rng.random(count) >= params.dropout_probability
    latencies = rng.uniform(params.latency_min, params.latency_max, count)
    values = p_W + params.noise_std * rng.standard_normal((count, 3))
    covariance = np.eye(3) * params.noise_std**2
    return tuple(
        PendingMeasurement(float(capture_times[i]), float(capture_times[i] + latencies[i]), values[i], covariance)
        for i in np.flatnonzero(kept)
    )


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
    times = []
    time = float(first_time)
    while time <= until:
        times.append(time)
        time += rng.uniform(1.0 / params.rate_max, 1.0 / params.rate_min)
    return np.asarray(times, dtype=float), time


def first_spin_capture_time(start_time: float, params: SpinSensorParams, rng: np.random.Generator) -> float:
    """The first sample after ``start_time`` (s): one interval later, so the phase is random."""
    return float(start_time + rng.uniform(1.0 / params.rate_max, 1.0 / params.rate_min))


def racket_tracking_loss(capture_times: np.ndarray, racket_contact_times: np.ndarray, params: SpinSensorParams) -> np.ndarray:
    """Whether each capture time (n,) lies in [t_c, t_c + racket_dropout_duration] after some
    racket contact time t_c (k,) (paper: "additional dropout applied directly after racket
    contact to reflect tracking loss of GCS")."""
    capture_times = np.asarray(capture_times, dtype=float).reshape(-1)
    racket_contact_times = np.asarray(racket_contact_times, dtype=float).reshape(-1)
    if racket_contact_times.size == 0:
        return np.zeros(capture_times.shape, dtype=bool)
    since = capture_times[:, None] - racket_contact_times[None, :]
    return np.any((since >= 0.0) & (since <= params.racket_dropout_duration), axis=1)


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
        angle = math.sqrt(r[i, 0] * r[i, 0] + r[i, 1] * r[i, 1] + r[i, 2] * r[i, 2])
        safe = angle if angle > 0.0 else 1.0
        kx, ky, kz = r[i, 0] / safe, r[i, 1] / safe, r[i, 2] / safe
        vx, vy, vz = v[i, 0], v[i, 1], v[i, 2]
        cosine, sine = math.cos(angle), math.sin(angle)
        along = (kx * vx + ky * vy + kz * vz) * (1.0 - cosine)
        out[i, 0] = vx * cosine + (ky * vz - kz * vy) * sine + kx * along
        out[i, 1] = vy * cosine + (kz * vx - kx * vz) * sine + ky * along
        out[i, 2] = vz * cosine + (kx * vy - ky * vx) * sine + kz * along


def perturb_spin(
    w_W: np.ndarray, magnitude_offset: np.ndarray, rotation_vectors: tuple[np.ndarray, ...], fallback_axis: np.ndarray
) -> np.ndarray:
    """(|w| + magnitude_offset) R_m ... R_1 w / |w| for spins ``w_W`` (n, 3), rad/s.

    magnitude_offset (n,), rad/s; rotation_vectors: the rotations R_1, ..., R_m applied to the
    axis in that order, each (n, 3), rad; a spin below ZERO_SPIN has no axis and
    ``fallback_axis`` (n, 3), a unit vector, is used instead. A negative rate flips the axis: the
    measurement is a vector and that is what an estimator would report.
    """
    w_W = np.asarray(w_W, dtype=float).reshape(-1, 3)
    rate = np.linalg.norm(w_W, axis=1)
    spinning = rate > ZERO_SPIN
    turned = np.where(spinning[:, None], w_W / np.where(spinning, rate, 1.0)[:, None], fallback_axis)
    for rotation_vector in rotation_vectors:
        turned = rotate(rotation_vector, turned)
    return (rate + magnitude_offset)[:, None] * turned


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
        rate = math.sqrt(w[n, 0] * w[n, 0] + w[n, 1] * w[n, 1] + w[n, 2] * w[n, 2])
        if not rate > ZERO_SPIN:
            for i in range(3):
                for j in range(3):
                    out[n, i, j] = radial_variance if i == j else 0.0
            continue
        tangential_variance = (rate * axis_noise_std) ** 2
        for i in range(3):
            for j in range(3):
                along = (w[n, i] / rate) * (w[n, j] / rate)
                across = (1.0 if i == j else 0.0) - along
                out[n, i, j] = radial_variance * along + tangential_variance * across


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
    kept = rng.random(count) >= params.dropout_probability
    lost = np.asarray(tracking_loss, dtype=bool) & (rng.random(count) < params.racket_dropout_probability)
    kept &= ~lost
    latencies = rng.uniform(params.latency_min, params.latency_max, count)
    magnitude_noise = params.magnitude_noise_std * rng.standard_normal(count)
    axis_noise = params.axis_noise_std * rng.standard_normal((count, 3))
    fallback_axis = rng.standard_normal((count, 3))
    fallback_axis /= np.linalg.norm(fallback_axis, axis=1, keepdims=True)
    # The measured axis: the bias's rotation, then this sample's noise.
    bias_rotation = np.asarray(bias_rotation_vector, dtype=float).reshape(-1, 3)
    values = perturb_spin(w_W, np.asarray(bias_magnitude, dtype=float) + magnitude_noise, (bias_rotation, axis_noise), fallback_axis)
    covariances = spin_precision_covariance(values, params)
    return tuple(
        PendingMeasurement(float(capture_times[i]), float(capture_times[i] + latencies[i]), values[i], covariances[i])
        for i in np.flatnonzero(kept)
    )


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
    contact_times = np.asarray(contact_times, dtype=float).reshape(-1)
    counts = np.searchsorted(contact_times, times, side="right")
    spins = np.broadcast_to(np.asarray(w_now, dtype=float), (times.size, 3)).copy()
    later = counts < contact_times.size
    if np.any(later):
        spins[later] = np.asarray(spins_before_contact, dtype=float).reshape(-1, 3)[counts[later]]
    return spins, counts
