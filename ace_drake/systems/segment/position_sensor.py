"""SegmentPositionSensor: the statistical triangulated-position sensor of B environments."""

from __future__ import annotations

import numpy as np
from pydrake.common.value import AbstractValue
from pydrake.systems.framework import LeafSystem

from ace_drake.control.segment_timing import SegmentTiming
from ace_drake.perception.measurements import MeasurementHistory
from ace_drake.perception.params import PositionSensorParams
from ace_drake.perception.random_streams import position_variates
from ace_drake.perception.sensor_models import PendingBatch, position_measurements
from ace_drake.systems.statistical_position_sensor import POSITION_STREAM, SensorQueueBatch


def trigger_samples(period: float, timing: SegmentTiming, name: str) -> int:
    """A sensor period (s) in command samples; it must be a whole number of them."""
    samples = period / timing.period
    if abs(samples - round(samples)) > 1e-9 or round(samples) < 1:
        raise ValueError(f"{name}: its period ({period} s) must be a whole number of command periods ({timing.period} s)")
    return int(round(samples))


class SegmentPositionSensor(LeafSystem):
    """The continuous-time ``StatisticalPositionSensor`` for B environments: at each 200 Hz
    trigger inside a tick, the true ball centre with Gaussian noise, dropout and latency
    (``perception.sensor_models.sample_position_measurements``, the reference's model). The draws
    of a tick's triggers come at once from the stream [seed, POSITION_STREAM, tick] (the
    reference draws per trigger), so the statistics are the reference's and a seed gives the
    same measurements whatever the batch.

    Input ports:
        ball_flight (abstract BallSegment): the SegmentBallPlant's samples over the tick.
        episode_ticks (abstract int64 (B,)): the EpisodeClock's.
    Output ports:
        position_measurements (abstract MeasurementHistoryBatch, B rows): positions p_WB (m) with
            covariance, everything released at or before the tick's start (state only).
    State:
        abstract SensorQueueBatch (the B queues); abstract int64 (B,): each episode's seed.
    Events:
        periodic unrestricted update every T (offset 0): the tick's triggers, their measurements
        queued until their release.
    """

    def __init__(self, params: PositionSensorParams, batch: int, timing: SegmentTiming):
        """Args: params, the sensor model; batch, B; timing, the segment time line."""
        super().__init__()
        self.params = params
        self.batch = int(batch)
        self.timing = timing
        self._trigger = trigger_samples(self._trigger_period(), timing, type(self).__name__)
        self._empty = MeasurementHistory(capacity=params.history_capacity)
        self._queue_index = self.DeclareAbstractState(AbstractValue.Make(SensorQueueBatch.empty(self.batch, params.history_capacity)))
        self._seed_index = self.DeclareAbstractState(AbstractValue.Make(np.zeros(self.batch, dtype=np.int64)))
        self.ball_flight_port = self.DeclareAbstractInputPort("ball_flight", AbstractValue.Make(None))
        self.episode_ticks_port = self.DeclareAbstractInputPort("episode_ticks", AbstractValue.Make(np.zeros(self.batch, dtype=np.int64)))
        self.position_measurements_port = self.DeclareAbstractOutputPort(
            "position_measurements", lambda: AbstractValue.Make(()), self.CalcPositionMeasurements,
            prerequisites_of_calc={self.abstract_state_ticket(self._queue_index), self.input_port_ticket(self.episode_ticks_port.get_index())},
        )
        self.DeclarePeriodicUnrestrictedUpdateEvent(timing.duration, 0.0, self.Trigger)

    def _trigger_period(self) -> float:
        return self.params.trigger_period

    def StartEpisodes(self, context, rows, seeds) -> None:
        """Empties the queues of environments ``rows`` and sets their episode seeds (k,)."""
        all_seeds = self._seeds(context).copy()
        all_seeds[np.asarray(rows, dtype=int)] = np.asarray(seeds, dtype=np.int64)
        context.SetAbstractState(self._queue_index, self.queues(context).restarted(rows, self._empty))
        context.SetAbstractState(self._seed_index, all_seeds)

    def queues(self, context) -> SensorQueueBatch:
        """The B queues in this system's ``context`` (``.row(b)`` is environment b's SensorQueue)."""
        return context.get_abstract_state(self._queue_index).get_value()

    def CalcPositionMeasurements(self, context, output):
        now = self.timing.tick_time(self.episode_ticks_port.Eval(context))
        output.set_value(self.queues(context).released(now)[0])

    def Trigger(self, context, state):
        flight = self.ball_flight_port.Eval(context)
        ticks = self.episode_ticks_port.Eval(context)
        first = self.timing.first_sample(ticks)
        sampled = self._sample(flight, ticks, first, self._seeds(context))
        end = self.timing.seconds(first + self.timing.samples)
        state.get_mutable_abstract_state(self._queue_index).set_value(self.queues(context).sampled(sampled, end))

    def _triggers(self, first: int) -> np.ndarray:
        """The episode samples of the triggers in the tick starting at episode sample ``first``
        (those at or after the episode's time 0)."""
        start = max(int(first), 0)
        return np.arange(-(-start // self._trigger) * self._trigger, int(first) + self.timing.samples, self._trigger)

    def _trigger_grid(self, first: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``_triggers`` of every environment at once: (the episode samples (B, m) of the m
        possible triggers of a tick, whether each is one (B, m))."""
        start = np.maximum(first, 0)
        count = -(-self.timing.samples // self._trigger) + 1
        triggers = (-(-start // self._trigger) * self._trigger)[:, None] + self._trigger * np.arange(count)
        return triggers, triggers < (first + self.timing.samples)[:, None]

    def _sample(self, flight, ticks: np.ndarray, first: np.ndarray, seeds: np.ndarray) -> PendingBatch:
        """Every environment's PendingMeasurements of the tick's triggers: the model's variates
        drawn environment by environment, each from its stream (``draw_position_variates`` with
        ``default_rng([seed, POSITION_STREAM, tick])``, compiled: ``random_streams``), the model
        of all at once."""
        triggers, valid = self._trigger_grid(first)
        counts = valid.sum(axis=1)
        if not counts.any():
            return PendingBatch.empty()
        variates = position_variates(seeds, POSITION_STREAM, ticks, counts, self.params.latency_min, self.params.latency_max)
        sample_rows, columns = np.nonzero(valid)  # row by row, in trigger order
        sample_triggers = triggers[sample_rows, columns]
        capture_times = self.timing.seconds(sample_triggers)
        p_W = flight.samples[sample_rows, sample_triggers - first[sample_rows], :3]
        kept, release_times, values, covariance = position_measurements(p_W, capture_times, variates, self.params)
        return PendingBatch.from_samples(sample_rows, capture_times, release_times, values, covariance, kept)

    def _seeds(self, context) -> np.ndarray:
        return context.get_abstract_state(self._seed_index).get_value()
