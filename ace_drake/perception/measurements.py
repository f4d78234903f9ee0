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
