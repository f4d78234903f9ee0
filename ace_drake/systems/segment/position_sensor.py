"""SegmentPositionSensor: the statistical triangulated-position sensor of B environments."""

from __future__ import annotations

import numpy as np
from pydrake.common.value import AbstractValue
from pydrake.systems.framework import LeafSystem

from ace_drake.control.segment_timing import SegmentTiming
from ace_drake.perception.measurements import MeasurementHistory
from ace_drake.perception.params import PositionSensorParams
from ace_drake.perception.sensor_models import sample_position_measurements
from ace_drake.systems.statistical_position_sensor import POSITION_STREAM, SensorQueue


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
        position_measurements (abstract tuple of B MeasurementHistory): positions p_WB (m) with
            covariance, everything released at or before the tick's start (state only).
    State:
        abstract tuple of B SensorQueue; abstract int64 (B,): each episode's seed.
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
        self._empty = SensorQueue(MeasurementHistory(capacity=params.history_capacity))
        self._queue_index = self.DeclareAbstractState(AbstractValue.Make((self._empty,) * self.batch))
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
        queues, all_seeds = list(self._queues(context)), self._seeds(context).copy()
        for row, seed in zip(np.asarray(rows, dtype=int), np.asarray(seeds, dtype=np.int64)):
            queues[row] = self._empty
            all_seeds[row] = seed
        context.SetAbstractState(self._queue_index, tuple(queues))
        context.SetAbstractState(self._seed_index, all_seeds)

    def CalcPositionMeasurements(self, context, output):
        now = self.timing.tick_time(self.episode_ticks_port.Eval(context))
        output.set_value(tuple(queue.released(float(now[row]))[0] for row, queue in enumerate(self._queues(context))))

    def Trigger(self, context, state):
        flight = self.ball_flight_port.Eval(context)
        ticks = self.episode_ticks_port.Eval(context)
        first = self.timing.first_sample(ticks)
        sampled = self._sample(flight, ticks, first, self._seeds(context))
        end = self.timing.seconds(first + self.timing.samples)
        queues = tuple(queue.sampled(sampled[row], float(end[row])) for row, queue in enumerate(self._queues(context)))
        state.get_mutable_abstract_state(self._queue_index).set_value(queues)

    def _triggers(self, first: int) -> np.ndarray:
        """The episode samples of the triggers in the tick starting at episode sample ``first``
        (those at or after the episode's time 0)."""
        start = max(int(first), 0)
        return np.arange(-(-start // self._trigger) * self._trigger, int(first) + self.timing.samples, self._trigger)

    def _sample(self, flight, ticks: np.ndarray, first: np.ndarray, seeds: np.ndarray) -> list[tuple]:
        """Each environment's PendingMeasurements of the tick's triggers."""
        sampled = []
        for row in range(self.batch):
            triggers = self._triggers(first[row])
            rng = np.random.default_rng([int(seeds[row]), POSITION_STREAM, int(ticks[row])])
            sampled.append(sample_position_measurements(flight.samples[row, triggers - first[row], :3], self.timing.seconds(triggers), self.params, rng))
        return sampled

    def _queues(self, context) -> tuple[SensorQueue, ...]:
        return context.get_abstract_state(self._queue_index).get_value()

    def _seeds(self, context) -> np.ndarray:
        return context.get_abstract_state(self._seed_index).get_value()
