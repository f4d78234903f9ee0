"""BallEstimator: the ball state EKF (perception/ball_ekf.py) as a system."""

from __future__ import annotations

import dataclasses

import numpy as np
from pydrake.common.value import AbstractValue
from pydrake.systems.framework import EventStatus, LeafSystem, ValueProducer

from ace_drake.perception.ball_ekf import BallEkf, BallEstimate, EkfBatch, EkfState
from ace_drake.perception.measurements import MeasurementHistory, MeasurementHistoryBatch
from ace_drake.perception.params import EstimatorParams
from ace_drake.physics.params import BallPhysicsParams
from ace_drake.physics.propagate import ContactKind

STATUS_SIZE = 3


@dataclasses.dataclass(frozen=True)
class EstimatorState:
    """The estimator's per-episode state: the filter, and how far it has read its inputs (the
    last position and spin sequence numbers, the number of contact events)."""

    filter: EkfState = dataclasses.field(default_factory=EkfState)
    last_position_sequence: int = 0
    last_spin_sequence: int = 0
    contacts_seen: int = 0

    def __deepcopy__(self, memo):  # immutable: Drake's state copies may share it
        return self


@dataclasses.dataclass(frozen=True)
class EstimatorBatchState:
    """B estimators' state (``EstimatorState`` of each environment, as arrays): the filters
    (EkfBatch) and, per environment, the last position and spin sequence numbers read and the
    number of contact events seen, (B,) int64 each."""

    filters: EkfBatch
    last_position_sequence: np.ndarray
    last_spin_sequence: np.ndarray
    contacts_seen: np.ndarray

    @staticmethod
    def initial(ekf: BallEkf, batch: int) -> EstimatorBatchState:
        """B estimators with nothing read yet."""
        zeros = np.zeros(int(batch), dtype=np.int64)
        return EstimatorBatchState(ekf.initial_batch(batch), zeros, zeros.copy(), zeros.copy())

    def row(self, b: int) -> EstimatorState:
        """Environment b's EstimatorState (its filter a view of the batch)."""
        return EstimatorState(self.filters.row(b), int(self.last_position_sequence[b]), int(self.last_spin_sequence[b]), int(self.contacts_seen[b]))

    def cleared(self, rows) -> EstimatorBatchState:
        """A copy with environments ``rows`` back to the initial state (a new episode)."""
        rows = np.asarray(rows, dtype=int).reshape(-1)
        sequences = [self.last_position_sequence.copy(), self.last_spin_sequence.copy(), self.contacts_seen.copy()]
        for values in sequences:
            values[rows] = 0
        return EstimatorBatchState(self.filters.cleared(rows), *sequences)

    def __deepcopy__(self, memo):  # immutable: Drake's state copies may share it
        return self


def _new_measurements(last_position: int, last_spin: int, contacts_seen: int, positions_history: MeasurementHistory, spins_history: MeasurementHistory, events, time: float):
    """What one estimator has not read yet: (positions, spins, racket contact times (s), whether
    anything changed). ``fuse_measurements``'s rule, shared with ``fuse_measurements_batch``."""
    # A sensor or plant that started a new episode numbers from the start again.
    last_position = last_position if positions_history.last_sequence >= last_position else 0
    last_spin = last_spin if spins_history.last_sequence >= last_spin else 0
    contacts_seen = contacts_seen if len(events) >= contacts_seen else 0
    for kind, history, last in (("position", positions_history, last_position), ("spin", spins_history, last_spin)):
        if history.measurements and history.measurements[0].sequence > last + 1:
            raise RuntimeError(
                f"BallEstimator: at {time:.4f} s the {kind} sensor's history starts at measurement "
                f"{history.measurements[0].sequence}, but the filter has read only up to {last}: more were released "
                f"since its last update than the history holds ({history.capacity}). Raise the sensor's "
                "history_capacity or shorten EstimatorParams.update_period."
            )
    positions = positions_history.since(last_position)
    spins = spins_history.since(last_spin)
    racket_times = [event.time for event in events[contacts_seen:] if event.kind == ContactKind.RACKET]
    return positions, spins, racket_times, bool(positions or spins or racket_times) or len(events) != contacts_seen


def fuse_measurements(ekf: BallEkf, current: EstimatorState, positions_history: MeasurementHistory, spins_history: MeasurementHistory, events, time: float) -> EstimatorState:
    """``current`` with every measurement the histories show numbered above the last ones read, and
    every new racket contact in ``events``, fused (``BallEkf.update``); ``current`` itself when
    there is nothing new. ``time`` (s) only names the instant in the error raised when a history
    no longer holds what was released since the last fusion. The BallEstimator's rule, shared by
    the segment-stepped estimator (``fuse_measurements_batch``)."""
    positions, spins, racket_times, changed = _new_measurements(
        current.last_position_sequence, current.last_spin_sequence, current.contacts_seen, positions_history, spins_history, events, time
    )
    if not changed:
        return current
    return EstimatorState(ekf.update(current.filter, positions, spins, racket_times), positions_history.last_sequence, spins_history.last_sequence, len(events))


def fuse_measurements_batch(ekf: BallEkf, current: EstimatorBatchState, positions_histories, spins_histories, events, times) -> EstimatorBatchState:
    """``fuse_measurements`` of B estimators at once (one ``BallEkf.update_arrays``): the same
    filters, environment by environment. positions_histories, spins_histories: a
    MeasurementHistoryBatch each (a sequence of B MeasurementHistory is converted); events: B
    tuples of ContactEvent; times (B,) s. ``current`` itself when no environment has anything new."""
    size = current.filters.size
    if not (len(positions_histories) == len(spins_histories) == len(events) == size):
        raise ValueError(f"fuse_measurements_batch: expected {size} position and spin histories and event tuples, got "
                         f"{len(positions_histories)}, {len(spins_histories)} and {len(events)}")
    positions, spins = (h if isinstance(h, MeasurementHistoryBatch) else MeasurementHistoryBatch.from_histories(h) for h in (positions_histories, spins_histories))
    # ``_new_measurements``' rule on arrays: a sensor that started a new episode numbers from the start again.
    last_position = np.where(positions.last_sequence >= current.last_position_sequence, current.last_position_sequence, 0)
    last_spin = np.where(spins.last_sequence >= current.last_spin_sequence, current.last_spin_sequence, 0)
    for kind, history, last in (("position", positions, last_position), ("spin", spins, last_spin)):
        b = history.first_gap(last)
        if b >= 0:
            time = np.broadcast_to(np.asarray(times, dtype=float), (size,))[b]
            raise RuntimeError(
                f"BallEstimator: at {time:.4f} s the {kind} sensor's history starts at measurement "
                f"{history.first_sequence()[b]}, but the filter has read only up to {last[b]}: more were released "
                f"since its last update than the history holds ({history.capacity}). Raise the sensor's "
                "history_capacity or shorten EstimatorParams.update_period."
            )
    position_rows, position_slots = positions.since_rows(last_position)
    spin_rows, spin_slots = spins.since_rows(last_spin)
    racket_times, changed = [], np.zeros(size, dtype=bool)
    for b in range(size):
        seen = int(current.contacts_seen[b]) if len(events[b]) >= current.contacts_seen[b] else 0
        racket_times.append([event.time for event in events[b][seen:] if event.kind == ContactKind.RACKET])
        changed[b] = bool(racket_times[b]) or len(events[b]) != seen
    changed[position_rows] = True
    changed[spin_rows] = True
    if not changed.any():
        return current
    observations = ekf.observations_of_rings(
        (position_rows, position_rows, position_slots, positions.sequence, positions.capture_time, positions.value, positions.covariance),
        (spin_rows, spin_rows, spin_slots, spins.sequence, spins.capture_time, spins.value, spins.covariance),
        racket_times,
    )
    filters = ekf.update_arrays(current.filters, observations)
    return EstimatorBatchState(
        filters,
        np.where(changed, positions.last_sequence, current.last_position_sequence),
        np.where(changed, spins.last_sequence, current.last_spin_sequence),
        np.where(changed, [len(e) for e in events], current.contacts_seen).astype(np.int64),
    )


def estimate_outputs(estimate) -> tuple[np.ndarray, np.ndarray]:
    """The estimator's ball_state_estimate (9,) and estimate_status (3,) for a BallEstimate or
    None (zeros and [0, 0, -1] without a track)."""
    if estimate is None:
        return np.zeros(9), np.array([0.0, 0.0, -1.0])
    return estimate.mean, np.array([1.0, float(estimate.spin_valid), estimate.time - estimate.last_capture_time])


class BallEstimator(LeafSystem):
    """The ball state estimator: an EKF over position, velocity and spin whose process model is the
    project's ball physics (``perception.ball_ekf.BallEkf``; notes.md, *Perception*), fed by any
    position and spin sensors that emit MeasurementHistory.

    Input ports:
        position_measurements (abstract MeasurementHistory): positions p_WB (m) with covariance
            (m^2), from the Triangulator or the StatisticalPositionSensor.
        spin_measurements (abstract MeasurementHistory): spins w_WB (rad/s) with covariance
            ((rad/s)^2), from the GazeSpinSensor or an event-camera spin estimator.
        contact_events (abstract tuple[ContactEvent]): BallPlant's contacts; a racket contact
            restarts the track from the measurements captured after it (the robot knows when it
            hit). Unconnected: tracks restart only on the gap and jump rules.
    Output ports:
        ball_state_estimate (9,): [p_WB (m), v_WB (m/s), w_WB (rad/s)] predicted from the latest
            posterior to the context's time; zeros while there is no track.
        ball_covariance (81,): its 9 x 9 covariance, row-major, SI units squared; zeros while
            there is no track.
        estimate_status (3,): [valid (1 with a track, else 0), spin valid (1 once a spin
            measurement is in the track), age of the newest measurement used (s; -1 without a
            track)].
    State:
        abstract EstimatorState: the filter (posterior, re-filtering history) and the sequence
        numbers read so far, as of the last update.
    Events:
        initialization: clears the state (a new episode).
        periodic unrestricted update every update_period, offset update_offset (by default the
        rally controller's observation instants, 32 ms apart and 5 ms before each segment):
        stores the filter at that time (``estimator_state``).

    Every output reads the filter with every measurement released at or before the context's
    time fused into it (``estimator_state``: the stored state plus what the inputs show numbered
    above the last ones read, ``MeasurementHistory.since``, and new racket contacts; cached per
    context time), so an estimate uses a measurement from its release on, with no polling wait,
    and the update's timing changes only the cost, never a value: the filter processes
    observations in capture order whatever batches they come in (``BallEkf.update``). The update
    is there so that each evaluation fuses only what is new since the last; at the controller's
    instants the fused filter the controller's evaluation computed is stored as it is (both read
    one cache entry). The sensors' histories must hold what they release in one update period
    (checked: a gap is an error).
    """

    def __init__(self, params: EstimatorParams | None = None, physics: BallPhysicsParams | None = None):
        """Args: params, the filter's settings; physics, the ball model the filter predicts with."""
        super().__init__()
        self.params = params or EstimatorParams()
        self.ekf = BallEkf(self.params, physics)
        self._state_index = self.DeclareAbstractState(AbstractValue.Make(EstimatorState()))
        self.position_measurements_port = self.DeclareAbstractInputPort(
            "position_measurements", AbstractValue.Make(MeasurementHistory())
        )
        self.spin_measurements_port = self.DeclareAbstractInputPort("spin_measurements", AbstractValue.Make(MeasurementHistory()))
        self.contact_events_port = self.DeclareAbstractInputPort("contact_events", AbstractValue.Make(()))
        self._fused_cache = self.DeclareCacheEntry(
            "the filter with everything released by the context's time",
            ValueProducer(allocate=lambda: AbstractValue.Make(EstimatorState()), calc=self._CalcFused),
            {self.time_ticket(), self.abstract_state_ticket(self._state_index), self.all_input_ports_ticket()},
        )
        self._estimate_cache = self.DeclareCacheEntry(
            "estimate at the context's time",
            ValueProducer(allocate=lambda: AbstractValue.Make((None,)), calc=self._CalcEstimate),
            {self._fused_cache.ticket()},
        )
        estimate_ticket = {self._estimate_cache.ticket()}
        self.ball_state_estimate_port = self.DeclareVectorOutputPort(
            "ball_state_estimate", 9, self.CalcBallStateEstimate, prerequisites_of_calc=estimate_ticket
        )
        self.ball_covariance_port = self.DeclareVectorOutputPort(
            "ball_covariance", 81, self.CalcBallCovariance, prerequisites_of_calc=estimate_ticket
        )
        self.estimate_status_port = self.DeclareVectorOutputPort(
            "estimate_status", STATUS_SIZE, self.CalcEstimateStatus, prerequisites_of_calc=estimate_ticket
        )
        self.DeclareInitializationUnrestrictedUpdateEvent(self.Clear)
        self.DeclarePeriodicUnrestrictedUpdateEvent(self.params.update_period, self.params.update_offset, self.Update)

    # ------------------------------------------------------------------------------ access
    def estimator_state(self, context) -> EstimatorState:
        """The EstimatorState at the context's time: the filter (history, resets, discarded
        count) with every measurement released by then fused."""
        return self._fused_cache.Eval(context)

    def estimate(self, context) -> BallEstimate | None:
        """The estimate at the context's time, or None without a track."""
        return self._estimate_cache.Eval(context)[0]

    # ------------------------------------------------------------------------------ events
    def Clear(self, context, state):
        state.get_mutable_abstract_state(self._state_index).set_value(EstimatorState())

    def Update(self, context, state):
        """Stores the filter as of now (what the outputs computed here already read)."""
        fused = self.estimator_state(context)
        if fused is context.get_abstract_state(self._state_index).get_value():
            return EventStatus.DidNothing()  # the Simulator skips writing the state back
        state.get_mutable_abstract_state(self._state_index).set_value(fused)
        return EventStatus.Succeeded()

    def _CalcFused(self, context, value):
        """The stored state with what the inputs released since fused (the same object if nothing)."""
        events = self.contact_events_port.Eval(context) if self.contact_events_port.HasValue(context) else ()
        value.set_value(
            fuse_measurements(
                self.ekf, context.get_abstract_state(self._state_index).get_value(), self.position_measurements_port.Eval(context),
                self.spin_measurements_port.Eval(context), events, context.get_time(),
            )
        )

    # ------------------------------------------------------------------------------ outputs
    def _CalcEstimate(self, context, value):
        value.set_value((self.ekf.estimate(self.estimator_state(context).filter, context.get_time()),))

    def CalcBallStateEstimate(self, context, output):
        output.SetFromVector(estimate_outputs(self.estimate(context))[0])

    def CalcBallCovariance(self, context, output):
        estimate = self.estimate(context)
        output.SetFromVector(np.zeros(81) if estimate is None else estimate.covariance.ravel())

    def CalcEstimateStatus(self, context, output):
        output.SetFromVector(estimate_outputs(self.estimate(context))[1])
