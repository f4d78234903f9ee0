"""GazeSpinSensor: the gaze-control systems' spin measurements as the paper's statistical model."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
from pydrake.common.value import AbstractValue
from pydrake.systems.framework import BasicVector, LeafSystem

from ace_drake.perception.measurements import MeasurementHistory
from ace_drake.perception.params import SpinSensorParams
from ace_drake.perception.sensor_models import (
    PendingBatch,
    SpinBias,
    SpinVariates,
    draw_spin_bias,
    draw_spin_variates,
    first_spin_capture_time,
    intervals_reached,
    racket_tracking_loss,
    sample_spin_measurements,
    spin_at_times,
    spin_at_times_batch,
    spin_capture_times,
    spin_pending_batch,
)
from ace_drake.physics.propagate import ContactKind
from ace_drake.systems.random_seed import declare_seed_port, episode_seed
from ace_drake.systems.statistical_position_sensor import SensorQueue, SensorQueueBatch

SPIN_STREAM = 2  # random streams under the seed (the position sensor uses 1)
BIAS_STREAM = 3
START_STREAM = 4


@dataclasses.dataclass(frozen=True)
class SpinSensorState:
    """The spin sensor's per-episode state.

    queue: the released measurements and those sampled, not yet released; next_capture_time: s,
    the next sample (NaN before the episode starts); biases: the accuracy bias of each contact
    interval drawn so far (index = number of contacts before the sample).
    """

    queue: SensorQueue
    next_capture_time: float = math.nan
    biases: tuple[SpinBias, ...] = ()

    def __deepcopy__(self, memo):  # immutable: Drake's state copies may share it
        return self


def first_capture_time(params: SpinSensorParams, seed: int, now: float) -> float:
    """A new episode's first sample time (s), one random interval after ``now`` (s), drawn from
    [seed, START_STREAM]."""
    return first_spin_capture_time(now, params, np.random.default_rng([seed, START_STREAM]))


def start_spin_sensor(params: SpinSensorParams, empty: SpinSensorState, seed: int, now: float) -> SpinSensorState:
    """A new episode's state at time ``now`` (s): ``empty``, its first sample one random interval
    later (``first_capture_time``)."""
    return dataclasses.replace(empty, next_capture_time=first_capture_time(params, seed, now))


def poll_rng(params: SpinSensorParams, seed: int, now: float) -> np.random.Generator:
    """The generator of the poll at ``now`` (s): [seed, SPIN_STREAM, poll index]."""
    return np.random.default_rng([seed, SPIN_STREAM, round(now / params.poll_period)])


def bias_of_interval(params: SpinSensorParams, seed: int, index: int) -> SpinBias:
    """The accuracy bias of contact interval ``index`` (paper: "accuracy is sampled once per
    contact event"), drawn from [seed, BIAS_STREAM, index]."""
    return draw_spin_bias(params, np.random.default_rng([seed, BIAS_STREAM, index]))


def poll_spin_sensor(params: SpinSensorParams, current: SpinSensorState, seed: int, now: float, w_now: np.ndarray, events) -> SpinSensorState:
    """One poll at ``now`` (s; a multiple of ``poll_period``): samples every capture time reached
    since the last poll, with the ball's spin ``w_now`` (3,) rad/s and its contact ``events`` up to
    now, and releases what is due (the GazeSpinSensor's rule; the segment-stepped sensor runs the
    same polls, ``poll_spin_sensors``). Draws from ``poll_rng`` and ``bias_of_interval``."""
    rng = poll_rng(params, seed, now)
    captures, next_capture_time = spin_capture_times(current.next_capture_time, now, params, rng)
    sampled, biases = (), current.biases
    if captures.size:
        contact_times = np.array([event.time for event in events])
        spins_before = np.array([event.state_pre[6:9] for event in events]).reshape(-1, 3)
        w_WB, intervals = spin_at_times(captures, w_now, contact_times, spins_before)
        biases = biases + tuple(bias_of_interval(params, seed, index) for index in range(len(biases), int(intervals.max()) + 1))
        racket_times = [event.time for event in events if event.kind == ContactKind.RACKET]
        sampled = sample_spin_measurements(
            w_WB,
            captures,
            np.array([biases[i].magnitude for i in intervals]),
            np.array([biases[i].rotation_vector for i in intervals]),
            racket_tracking_loss(captures, racket_times, params),
            params,
            rng,
        )
    return SpinSensorState(current.queue.sampled(sampled, now), next_capture_time, biases)


@dataclasses.dataclass(frozen=True)
class SpinSensorBatchState:
    """The SpinSensorStates of B sensors (one per environment) in arrays.

    queue: their queues; next_capture_time (B,): s, each one's next sample (NaN before its
    episode starts); bias_magnitude (B, k), rad/s, and bias_rotation_vector (B, k, 3), rad: the
    biases of the first ``bias_count`` (B,) contact intervals of each (the rest padding).
    """

    queue: SensorQueueBatch
    next_capture_time: np.ndarray
    bias_magnitude: np.ndarray
    bias_rotation_vector: np.ndarray
    bias_count: np.ndarray

    @classmethod
    def empty(cls, batch: int, capacity: int) -> SpinSensorBatchState:
        """B sensors before their episodes, histories of ``capacity``."""
        return cls(SensorQueueBatch.empty(batch, capacity), np.full(batch, np.nan), np.zeros((batch, 0)), np.zeros((batch, 0, 3)), np.zeros(batch, dtype=np.int64))

    def __deepcopy__(self, memo):  # immutable: Drake's state copies may share it
        return self

    def row(self, b: int) -> SpinSensorState:
        """Sensor ``b``'s state as the continuous-time sensor keeps it."""
        biases = tuple(SpinBias(float(self.bias_magnitude[b, i]), self.bias_rotation_vector[b, i]) for i in range(int(self.bias_count[b])))
        return SpinSensorState(self.queue.row(b), float(self.next_capture_time[b]), biases)

    def started(self, params: SpinSensorParams, rows, seeds, now: float, empty: MeasurementHistory) -> SpinSensorBatchState:
        """Sensors ``rows`` starting episodes at ``now`` (s) with ``seeds`` (k,) (``start_spin_sensor``)."""
        rows = np.asarray(rows, dtype=int).reshape(-1)
        next_capture_time, bias_count = self.next_capture_time.copy(), self.bias_count.copy()
        for b, seed in zip(rows, np.asarray(seeds, dtype=np.int64).reshape(-1)):
            next_capture_time[b] = first_capture_time(params, int(seed), now)
        bias_count[rows] = 0
        return SpinSensorBatchState(self.queue.restarted(rows, empty), next_capture_time, self.bias_magnitude, self.bias_rotation_vector, bias_count)


def _contact_arrays(events, rows: np.ndarray, batch: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The contacts of the balls ``rows`` as padded arrays: (times (B, k), s, inf-padded; spins
    just before (B, k, 3), rad/s; racket contact times (B, k), s, NaN-padded)."""
    width = max((len(events[b]) for b in rows), default=0)
    contact_times, spins_before, racket_times = np.full((batch, width), np.inf), np.zeros((batch, width, 3)), np.full((batch, width), np.nan)
    for b in rows:
        rackets = 0
        for k, event in enumerate(events[b]):
            contact_times[b, k] = event.time
            spins_before[b, k] = event.state_pre[6:9]
            if event.kind == ContactKind.RACKET:
                racket_times[b, rackets] = event.time
                rackets += 1
    return contact_times, spins_before, racket_times


def _with_biases(params: SpinSensorParams, current: SpinSensorBatchState, seeds: np.ndarray, needed: np.ndarray) -> SpinSensorBatchState:
    """``current`` with the biases of the first ``needed`` (B,) contact intervals of every sensor
    (``bias_of_interval``: each drawn once, the first time a sample of its interval is taken)."""
    missing = (needed > current.bias_count).nonzero()[0]
    if missing.size == 0:
        return current
    width = max(current.bias_magnitude.shape[1], int(needed.max()))
    magnitude = np.zeros((needed.size, width))
    rotation = np.zeros((needed.size, width, 3))
    magnitude[:, : current.bias_magnitude.shape[1]] = current.bias_magnitude
    rotation[:, : current.bias_magnitude.shape[1]] = current.bias_rotation_vector
    bias_count = current.bias_count.copy()
    for b in missing:
        for index in range(int(current.bias_count[b]), int(needed[b])):
            bias = bias_of_interval(params, int(seeds[b]), index)
            magnitude[b, index], rotation[b, index] = bias.magnitude, bias.rotation_vector
        bias_count[b] = needed[b]
    return dataclasses.replace(current, bias_magnitude=magnitude, bias_rotation_vector=rotation, bias_count=bias_count)


def poll_spin_sensors(
    params: SpinSensorParams, current: SpinSensorBatchState, seeds: np.ndarray, now: np.ndarray, w_now: np.ndarray, events
) -> SpinSensorBatchState:
    """``poll_spin_sensor`` of B sensors, sensor b at ``now[b]`` (s) with its ball's spin
    ``w_now[b]`` (B, 3), rad/s, and contact events ``events[b]``: the same draws from the same
    streams, sensor b's state that of ``poll_spin_sensor`` on ``current.row(b)``. The variates are
    drawn sensor by sensor (only those with a capture due), the model computed for all at once."""
    now = np.asarray(now, dtype=float)
    next_capture_time = current.next_capture_time.copy()
    polling = (next_capture_time <= now).nonzero()[0]  # NaN (not started): no capture
    captures, variates = [], []
    for b in polling:
        rng = poll_rng(params, int(seeds[b]), float(now[b]))
        times, next_capture_time[b] = spin_capture_times(next_capture_time[b], float(now[b]), params, rng)
        captures.append(times)
        variates.append(draw_spin_variates(times.size, params, rng))
    if polling.size == 0:
        return dataclasses.replace(current, queue=current.queue.sampled(PendingBatch.empty(), now))
    rows = np.repeat(polling, [times.size for times in captures])
    capture_times = captures[0] if polling.size == 1 else np.concatenate(captures)  # one sensor (B = 1): no copy
    contact_times, spins_before, racket_times = _contact_arrays(events, polling, now.size)
    w_WB, intervals = spin_at_times_batch(rows, capture_times, w_now, contact_times, spins_before)
    with_biases = _with_biases(params, current, seeds, intervals_reached(rows, intervals, now.size))
    sampled = spin_pending_batch(
        rows, intervals, capture_times, w_WB, with_biases.bias_magnitude, with_biases.bias_rotation_vector, racket_times,
        variates[0] if polling.size == 1 else SpinVariates.concatenate(variates), params,
    )
    return SpinSensorBatchState(current.queue.sampled(sampled, now), next_capture_time, with_biases.bias_magnitude, with_biases.bias_rotation_vector,
                                with_biases.bias_count)


class GazeSpinSensor(LeafSystem):
    """Spin measurements of the gaze-control systems (GCS) as the paper's statistical model
    (paper, Methods *Sensor modelling*; ``perception.sensor_models``, numbers in
    ``SpinSensorParams``): variable rate in 400-700 Hz, uniform latency, dropout, extra dropout for
    ``racket_dropout_duration`` after each racket contact, precision noise per sample and an
    accuracy bias per contact event, each Gaussian on the magnitude and on the axis. The ports are
    those of the event-camera spin estimator that may replace it: ball state and contact events
    in, spin measurements out.

    Input ports:
        ball_state (9,): [p_WB (m), v_WB (m/s), w_WB (rad/s)] in world (BallPlant).
        contact_events (abstract tuple[ContactEvent]): BallPlant's contacts of the episode; each
            re-draws the bias, a racket contact starts the tracking loss. Unconnected: none.
        random_seed (1,), random uniform: the seed, drawn by Drake's random context
            (``systems.random_seed``). Unconnected: the seed parameter.
    Output ports:
        spin_measurements (abstract MeasurementHistory): spins w_WB (rad/s) with the precision
            noise's covariance ((rad/s)^2; the bias is not in it), capture and release times (s);
            every measurement released at or before the context's time, the last
            ``history_capacity``.
    State:
        abstract SpinSensorState (released and pending measurements, next sample time, biases).
    Parameters:
        numeric (1,): the seed while random_seed is unconnected. Poll k draws from [seed,
        SPIN_STREAM, k] and the bias of contact interval i from [seed, BIAS_STREAM, i], the first
        sample time from [seed, START_STREAM]; a seed (>= 0) gives the same output bit for bit.
    Events:
        initialization: clears the state and draws the first sample time.
        periodic unrestricted update every poll_period (5 ms, offset 0): samples every capture
        time drawn since the last poll, at its exact time, and releases what is due.

    Sampling between polls is exact because spin is constant in flight (paper eq. (1)): the spin
    at a past capture time is the current one, or, if a contact came after it, the spin just
    before the first such contact (``ContactEvent.state_pre``). ``poll_period`` <= latency_min
    (checked by the config) so every measurement exists before its release, and the output
    publishes at the release time itself; the update runs at 200 Hz instead of at the sample rate.
    """

    def __init__(self, params: SpinSensorParams | None = None, seed: int = 0):
        """Args: params, the sensor model; seed, the default seed parameter."""
        super().__init__()
        self.params = params or SpinSensorParams()
        self._empty = SpinSensorState(SensorQueue(MeasurementHistory(capacity=self.params.history_capacity)))
        self._state_index = self.DeclareAbstractState(AbstractValue.Make(self._empty))
        self._seed_index = self.DeclareNumericParameter(BasicVector([float(seed)]))
        self.ball_state_port = self.DeclareVectorInputPort("ball_state", 9)
        self.contact_events_port = self.DeclareAbstractInputPort("contact_events", AbstractValue.Make(()))
        self.random_seed_port = declare_seed_port(self)
        self.spin_measurements_port = self.DeclareAbstractOutputPort(
            "spin_measurements",
            lambda: AbstractValue.Make(MeasurementHistory()),
            self.CalcSpinMeasurements,
            prerequisites_of_calc={self.time_ticket(), self.abstract_state_ticket(self._state_index)},
        )
        self.DeclareInitializationUnrestrictedUpdateEvent(self.Start)
        self.DeclarePeriodicUnrestrictedUpdateEvent(self.params.poll_period, 0.0, self.Poll)

    # ------------------------------------------------------------------------------ set-up
    def SetSeed(self, context, seed: int) -> None:
        """Sets this context's seed parameter (used while random_seed is unconnected)."""
        context.get_mutable_numeric_parameter(self._seed_index).SetAtIndex(0, float(seed))

    # ------------------------------------------------------------------------------ events
    def Start(self, context, state):
        """A new episode: empty history, first sample one random interval after now."""
        state.get_mutable_abstract_state(self._state_index).set_value(self._started(context))

    def Poll(self, context, state):
        """Samples the capture times reached since the last poll; releases what is due."""
        now = context.get_time()
        current = self._sensor_state(context)
        if math.isnan(current.next_capture_time):  # Simulator not initialized: start now
            current = self._started(context)
        events = self.contact_events_port.Eval(context) if self.contact_events_port.HasValue(context) else ()
        updated = poll_spin_sensor(self.params, current, self._seed(context), now, self.ball_state_port.Eval(context)[6:9], events)
        state.get_mutable_abstract_state(self._state_index).set_value(updated)

    # ------------------------------------------------------------------------------ outputs
    def CalcSpinMeasurements(self, context, output):
        current = self._sensor_state(context)
        output.set_value(current.queue.released(context.get_time())[0])

    # ------------------------------------------------------------------------------ helpers
    def _started(self, context) -> SpinSensorState:
        return start_spin_sensor(self.params, self._empty, self._seed(context), context.get_time())

    def _sensor_state(self, context) -> SpinSensorState:
        return context.get_abstract_state(self._state_index).get_value()

    def _seed(self, context) -> int:
        return episode_seed(self.random_seed_port, context, context.get_numeric_parameter(self._seed_index).GetAtIndex(0))
