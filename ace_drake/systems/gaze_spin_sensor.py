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
    SpinBias,
    draw_spin_bias,
    first_spin_capture_time,
    racket_tracking_loss,
    sample_spin_measurements,
    spin_at_times,
    spin_capture_times,
)
from ace_drake.physics.propagate import ContactKind
from ace_drake.systems.random_seed import declare_seed_port, episode_seed
from ace_drake.systems.statistical_position_sensor import SensorQueue

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


def start_spin_sensor(params: SpinSensorParams, empty: SpinSensorState, seed: int, now: float) -> SpinSensorState:
    """A new episode's state at time ``now`` (s): ``empty``, its first sample one random interval
    later (drawn from [seed, START_STREAM])."""
    rng = np.random.default_rng([seed, START_STREAM])
    return dataclasses.replace(empty, next_capture_time=first_spin_capture_time(now, params, rng))


def poll_spin_sensor(params: SpinSensorParams, current: SpinSensorState, seed: int, now: float, w_now: np.ndarray, events) -> SpinSensorState:
    """One poll at ``now`` (s; a multiple of ``poll_period``): samples every capture time reached
    since the last poll, with the ball's spin ``w_now`` (3,) rad/s and its contact ``events`` up to
    now, and releases what is due (the GazeSpinSensor's rule; the segment-stepped sensor runs the
    same polls). Draws from [seed, SPIN_STREAM, poll index] and [seed, BIAS_STREAM, interval]."""
    rng = np.random.default_rng([seed, SPIN_STREAM, round(now / params.poll_period)])
    captures, next_capture_time = spin_capture_times(current.next_capture_time, now, params, rng)
    sampled, biases = (), current.biases
    if captures.size:
        contact_times = np.array([event.time for event in events])
        spins_before = np.array([event.state_pre[6:9] for event in events]).reshape(-1, 3)
        w_WB, intervals = spin_at_times(captures, w_now, contact_times, spins_before)
        # paper: "accuracy is sampled once per contact event"
        biases = biases + tuple(
            draw_spin_bias(params, np.random.default_rng([seed, BIAS_STREAM, index]))
            for index in range(len(biases), int(intervals.max()) + 1)
        )
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
