"""SegmentSpinSensor: the gaze-control spin sensor of B environments."""

from __future__ import annotations

import numpy as np
from pydrake.common.value import AbstractValue
from pydrake.systems.framework import LeafSystem

from ace_drake.control.segment_timing import SegmentTiming
from ace_drake.perception.measurements import MeasurementHistory
from ace_drake.perception.params import SpinSensorParams
from ace_drake.systems.gaze_spin_sensor import SpinSensorBatchState, poll_spin_sensors


class SegmentSpinSensor(LeafSystem):
    """The continuous-time ``GazeSpinSensor`` for B environments: one poll per tick, at its end,
    samples every capture time of the tick (``gaze_spin_sensor.poll_spin_sensors``, the
    reference's ``poll_spin_sensor`` for every environment at once: variable rate,
    latency, dropout, racket tracking loss, precision noise and per-contact bias). Spin is
    constant in flight, so sampling a capture after its time gives the reference's value; what a
    tick releases is queued until its release time, so the output is the reference's model. The
    draws come per tick (the reference draws per 5 ms poll), so a seed gives the same
    measurements whatever the batch, not the reference's numbers.

    Input ports:
        ball_flight (abstract BallSegment): the SegmentBallPlant's samples and contact events.
        episode_ticks (abstract int64 (B,)): the EpisodeClock's.
    Output ports:
        spin_measurements (abstract MeasurementHistoryBatch, B rows): spins w_WB (rad/s) with the
            precision noise's covariance, everything released at or before the tick's start.
    State:
        abstract SpinSensorBatchState (the B sensors' states); abstract int64 (B,): each episode's seed.
    Events:
        periodic unrestricted update every T (offset 0): the tick's poll.
    """

    def __init__(self, params: SpinSensorParams, batch: int, timing: SegmentTiming):
        """Args: params, the sensor model; batch, B; timing, the segment time line."""
        super().__init__()
        self.params = params
        self.batch = int(batch)
        self.timing = timing
        self._empty = MeasurementHistory(capacity=params.history_capacity)
        self._state_index = self.DeclareAbstractState(AbstractValue.Make(SpinSensorBatchState.empty(self.batch, params.history_capacity)))
        self._seed_index = self.DeclareAbstractState(AbstractValue.Make(np.zeros(self.batch, dtype=np.int64)))
        self.ball_flight_port = self.DeclareAbstractInputPort("ball_flight", AbstractValue.Make(None))
        self.episode_ticks_port = self.DeclareAbstractInputPort("episode_ticks", AbstractValue.Make(np.zeros(self.batch, dtype=np.int64)))
        self.spin_measurements_port = self.DeclareAbstractOutputPort(
            "spin_measurements", lambda: AbstractValue.Make(()), self.CalcSpinMeasurements,
            prerequisites_of_calc={self.abstract_state_ticket(self._state_index), self.input_port_ticket(self.episode_ticks_port.get_index())},
        )
        self.DeclarePeriodicUnrestrictedUpdateEvent(timing.duration, 0.0, self.Poll)

    def StartEpisodes(self, context, rows, seeds) -> None:
        """Starts environments ``rows`` at episode time 0 with their seeds (k,): empty history,
        the first capture one random interval after 0."""
        all_seeds = context.get_abstract_state(self._seed_index).get_value().copy()
        all_seeds[np.asarray(rows, dtype=int)] = np.asarray(seeds, dtype=np.int64)
        context.SetAbstractState(self._state_index, self.sensor_states(context).started(self.params, rows, seeds, 0.0, self._empty))
        context.SetAbstractState(self._seed_index, all_seeds)

    def sensor_states(self, context) -> SpinSensorBatchState:
        """The B sensors' states in this system's ``context`` (``.row(b)`` is environment b's
        SpinSensorState)."""
        return context.get_abstract_state(self._state_index).get_value()

    def CalcSpinMeasurements(self, context, output):
        now = self.timing.tick_time(self.episode_ticks_port.Eval(context))
        output.set_value(self.sensor_states(context).queue.released(now)[0])

    def Poll(self, context, state):
        flight = self.ball_flight_port.Eval(context)
        end = self.timing.seconds(self.timing.first_sample(self.episode_ticks_port.Eval(context)) + self.timing.samples)
        seeds = context.get_abstract_state(self._seed_index).get_value()
        updated = poll_spin_sensors(self.params, self.sensor_states(context), seeds, end, flight.samples[:, -1, 6:9], flight.events)
        state.get_mutable_abstract_state(self._state_index).set_value(updated)
