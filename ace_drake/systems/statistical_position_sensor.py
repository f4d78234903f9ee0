"""StatisticalPositionSensor: the training path's ball positions, in place of cameras + triangulator."""

from __future__ import annotations

import dataclasses

import numpy as np
from pydrake.common.value import AbstractValue
from pydrake.systems.framework import BasicVector, LeafSystem

from ace_drake.perception.measurements import MeasurementHistory, MeasurementHistoryBatch
from ace_drake.perception.params import PositionSensorParams
from ace_drake.perception.sensor_models import (
    PendingBatch,
    PendingMeasurement,
    due_mask,
    insert_pending,
    insert_pending_batch,
    release_due,
    release_due_batch,
    sample_position_measurements,
)
from ace_drake.systems.random_seed import declare_seed_port, episode_seed

POSITION_STREAM = 1  # random stream of this sensor under its seed (the spin sensor has its own)


@dataclasses.dataclass(frozen=True)
class SensorQueue:
    """A sensor's per-episode state: what it has released and what it has sampled but not yet.
    Immutable (it memoises ``released``, a function of its fields)."""

    history: MeasurementHistory
    pending: tuple[PendingMeasurement, ...] = ()
    _released: dict = dataclasses.field(default_factory=dict, init=False, repr=False, compare=False)

    def __deepcopy__(self, memo):  # immutable: Drake's state copies may share it
        return self

    def released(self, now: float) -> tuple[MeasurementHistory, tuple[PendingMeasurement, ...]]:
        """``release_due`` at ``now`` (s): the history with the pending measurements released by
        then, and the rest. Memoised per number released: the output port asks at every step,
        and each ask would otherwise number and validate the same Measurements again."""
        due = 0
        while due < len(self.pending) and self.pending[due].release_time <= now:
            due += 1
        if due not in self._released:
            self._released[due] = release_due(self.history, self.pending, now)
        return self._released[due]

    def sampled(self, new: tuple[PendingMeasurement, ...], now: float) -> SensorQueue:
        """The queue at ``now`` (s) with ``new`` measurements sampled and what is due released."""
        if not new:
            return SensorQueue(*self.released(now))
        return SensorQueue(*release_due(self.history, insert_pending(self.pending, new), now))


@dataclasses.dataclass(frozen=True)
class SensorQueueBatch:
    """The SensorQueues of B sensors (one per environment) in one: their released ``histories``
    (MeasurementHistoryBatch; ``histories[b]`` is sensor b's MeasurementHistory) and all their
    ``pending`` measurements in flat arrays, released by array operations
    (``sensor_models.release_due_batch``). Immutable (it memoises ``released``)."""

    histories: MeasurementHistoryBatch
    pending: PendingBatch
    _released: dict = dataclasses.field(default_factory=dict, init=False, repr=False, compare=False)

    @classmethod
    def empty(cls, batch: int, capacity: int) -> SensorQueueBatch:
        """B empty queues whose histories keep ``capacity`` measurements."""
        return cls(MeasurementHistoryBatch.empty(batch, capacity), PendingBatch.empty())

    def __deepcopy__(self, memo):  # immutable: Drake's state copies may share it
        return self

    def row(self, b: int) -> SensorQueue:
        """Sensor ``b``'s queue as the continuous-time sensor keeps it."""
        return SensorQueue(self.histories[b], self.pending.row_pending(b))

    def released(self, now: np.ndarray) -> tuple[MeasurementHistoryBatch, PendingBatch]:
        """``SensorQueue.released`` of every sensor, sensor b at ``now[b]`` (s). Memoised per
        set released, as SensorQueue's."""
        due = due_mask(self.pending, now)
        key = due.tobytes()
        if key not in self._released:
            self._released[key] = release_due_batch(self.histories, self.pending, now)
        return self._released[key]

    def sampled(self, new: PendingBatch, now: np.ndarray) -> SensorQueueBatch:
        """``SensorQueue.sampled`` of every sensor: ``new`` measurements sampled and what is due
        at ``now`` (B,), s, released."""
        if new.row.size == 0:
            return SensorQueueBatch(*self.released(now))
        return SensorQueueBatch(*release_due_batch(self.histories, insert_pending_batch(self.pending, new), now))

    def restarted(self, rows, empty: MeasurementHistory) -> SensorQueueBatch:
        """Sensors ``rows`` back to ``empty`` histories with nothing pending (new episodes).
        ``empty``: an empty MeasurementHistory of the batch's capacity (the per-sensor queue's
        start, checked)."""
        if empty.measurements or empty.capacity != self.histories.capacity:
            raise ValueError(f"SensorQueueBatch.restarted: expected an empty history of capacity {self.histories.capacity}, "
                             f"got {len(empty.measurements)} measurements and capacity {empty.capacity}")
        return SensorQueueBatch(self.histories.restarted(rows), self.pending.without_rows(rows))


def trigger_position_sensor(params: PositionSensorParams, queue: SensorQueue, seed: int, now: float, p_WB: np.ndarray) -> SensorQueue:
    """One camera trigger at ``now`` (s; a multiple of ``trigger_period``): the ball at ``p_WB``
    (3,) m sampled (drawn from [seed, POSITION_STREAM, trigger index]) and what is due released
    (the StatisticalPositionSensor's rule; the segment-stepped sensor runs the same triggers)."""
    rng = np.random.default_rng([seed, POSITION_STREAM, round(now / params.trigger_period)])
    sampled = sample_position_measurements(np.asarray(p_WB, dtype=float)[None, :3], np.array([now]), params, rng)
    return queue.sampled(sampled, now)


class StatisticalPositionSensor(LeafSystem):
    """Triangulated ball positions as the paper's statistical sensor model (paper, Methods *Sensor
    modelling*): at each 200 Hz camera trigger the true ball centre, with zero-mean Gaussian noise,
    dropped with a fixed probability, released after a latency uniform on [latency_min,
    latency_max] (``perception.sensor_models.sample_position_measurements``; numbers in
    ``PositionSensorParams``). Same output port, name and type as the Triangulator's, so that the
    cameras + triangulator path and this one are interchangeable in one wiring.

    Input ports:
        ball_state (9,): [p_WB (m), v_WB (m/s), w_WB (rad/s)] in world (BallPlant).
        random_seed (1,), random uniform: the seed, drawn by Drake's random context
            (``systems.random_seed``). Unconnected: the seed parameter.
    Output ports:
        position_measurements (abstract MeasurementHistory): positions p_WB (m) with covariance
            noise_std^2 I (m^2), capture time = the trigger (s) and release time = capture +
            latency (s); the port shows every measurement released at or before the context's
            time (exactly, not at the next trigger), the last ``history_capacity`` of them.
    State:
        abstract SensorQueue: the released history and the sampled, not yet released measurements.
    Parameters:
        numeric (1,): the seed while random_seed is unconnected. The draws at trigger k come
        from the generator seeded with [seed, POSITION_STREAM, k], so a seed gives the same
        measurements bit for bit.
    Events:
        initialization: clears the queue (a new episode).
        periodic unrestricted update every trigger_period (5 ms, 200 Hz, offset 0): samples the
        ball and releases what is due.
    """

    def __init__(self, params: PositionSensorParams | None = None, seed: int = 0):
        """Args: params, the sensor model; seed, the default seed parameter."""
        super().__init__()
        self.params = params or PositionSensorParams()
        self._empty = SensorQueue(MeasurementHistory(capacity=self.params.history_capacity))
        self._queue_index = self.DeclareAbstractState(AbstractValue.Make(self._empty))
        self._seed_index = self.DeclareNumericParameter(BasicVector([float(seed)]))
        self.ball_state_port = self.DeclareVectorInputPort("ball_state", 9)
        self.random_seed_port = declare_seed_port(self)
        self.position_measurements_port = self.DeclareAbstractOutputPort(
            "position_measurements",
            lambda: AbstractValue.Make(MeasurementHistory()),
            self.CalcPositionMeasurements,
            prerequisites_of_calc={self.time_ticket(), self.abstract_state_ticket(self._queue_index)},
        )
        self.DeclareInitializationUnrestrictedUpdateEvent(self.ClearQueue)
        self.DeclarePeriodicUnrestrictedUpdateEvent(self.params.trigger_period, 0.0, self.Trigger)

    # ------------------------------------------------------------------------------ set-up
    def SetSeed(self, context, seed: int) -> None:
        """Sets this context's seed parameter (used while random_seed is unconnected)."""
        context.get_mutable_numeric_parameter(self._seed_index).SetAtIndex(0, float(seed))

    # ------------------------------------------------------------------------------ events
    def ClearQueue(self, context, state):
        state.get_mutable_abstract_state(self._queue_index).set_value(self._empty)

    def Trigger(self, context, state):
        """Samples the ball now (a camera trigger) and releases the measurements that are due."""
        now = context.get_time()
        queue = self._queue(context)
        p_WB = self.ball_state_port.Eval(context)[:3]
        state.get_mutable_abstract_state(self._queue_index).set_value(trigger_position_sensor(self.params, queue, self._seed(context), now, p_WB))

    # ------------------------------------------------------------------------------ outputs
    def CalcPositionMeasurements(self, context, output):
        queue = self._queue(context)
        output.set_value(queue.released(context.get_time())[0])

    # ------------------------------------------------------------------------------ helpers
    def _queue(self, context) -> SensorQueue:
        return context.get_abstract_state(self._queue_index).get_value()

    def _seed(self, context) -> int:
        return episode_seed(self.random_seed_port, context, context.get_numeric_parameter(self._seed_index).GetAtIndex(0))
