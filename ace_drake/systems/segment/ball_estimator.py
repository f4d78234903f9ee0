"""SegmentBallEstimator: the ball EKF of B environments."""

from __future__ import annotations

import numpy as np
from pydrake.common.value import AbstractValue
from pydrake.systems.framework import LeafSystem, ValueProducer

from ace_drake.control.segment_timing import SegmentTiming
from ace_drake.perception.ball_ekf import BallEkf
from ace_drake.perception.params import EstimatorParams
from ace_drake.physics.params import BallPhysicsParams
from ace_drake.systems.ball_estimator import EstimatorBatchState, fuse_measurements_batch


class SegmentBallEstimator(LeafSystem):
    """The continuous-time ``BallEstimator`` for B environments: at each tick every environment's
    filter fuses what its sensors released since the last tick (``ball_estimator.fuse_measurements_batch``,
    the reference's rule for all B at once, equal environment by environment to
    ``fuse_measurements``; the filter processes observations in capture order whatever batches
    they come in, so fusing once per tick gives the reference's estimate at the tick).

    Input ports:
        position_measurements, spin_measurements (abstract MeasurementHistoryBatch, or a tuple of B
            MeasurementHistory).
        contact_events (abstract tuple of B tuples of ContactEvent): the ball's contacts up to the
            tick's start (a racket contact restarts the track).
        episode_ticks (abstract int64 (B,)): the EpisodeClock's.
    Output ports:
        ball_state_estimate (abstract float (B, 9)): [p, v, w] predicted to the tick's start.
        estimate_status (abstract float (B, 3)): [valid, spin valid, age of newest measurement (s)].
    State:
        abstract EstimatorBatchState (the B filters as arrays, ``perception.ball_ekf.EkfBatch``).
    Events:
        periodic unrestricted update every T (offset 0): stores the fused filters.
    """

    def __init__(self, params: EstimatorParams, physics: BallPhysicsParams, batch: int, timing: SegmentTiming):
        """Args: params, the filter's settings; physics, its process model; batch, B; timing."""
        super().__init__()
        self.params = params
        self.ekf = BallEkf(params, physics)
        self.batch = int(batch)
        self.timing = timing
        self._state_index = self.DeclareAbstractState(AbstractValue.Make(EstimatorBatchState.initial(self.ekf, self.batch)))
        self.position_measurements_port = self.DeclareAbstractInputPort("position_measurements", AbstractValue.Make(()))
        self.spin_measurements_port = self.DeclareAbstractInputPort("spin_measurements", AbstractValue.Make(()))
        self.contact_events_port = self.DeclareAbstractInputPort("contact_events", AbstractValue.Make(()))
        self.episode_ticks_port = self.DeclareAbstractInputPort("episode_ticks", AbstractValue.Make(np.zeros(self.batch, dtype=np.int64)))
        self._fused_cache = self.DeclareCacheEntry(
            "the filters with everything released by the tick's start",
            ValueProducer(allocate=lambda: AbstractValue.Make(EstimatorBatchState.initial(self.ekf, self.batch)), calc=self._CalcFused),
            {self.abstract_state_ticket(self._state_index), self.all_input_ports_ticket()},
        )
        self._outputs_cache = self.DeclareCacheEntry(
            "estimates at the tick's start",
            ValueProducer(allocate=lambda: AbstractValue.Make(None), calc=self._CalcOutputs),
            {self._fused_cache.ticket()},
        )
        self.ball_state_estimate_port = self.DeclareAbstractOutputPort(
            "ball_state_estimate", lambda: AbstractValue.Make(np.zeros((self.batch, 9))),
            lambda context, output: output.set_value(self._outputs_cache.Eval(context)[0]), prerequisites_of_calc={self._outputs_cache.ticket()},
        )
        self.estimate_status_port = self.DeclareAbstractOutputPort(
            "estimate_status", lambda: AbstractValue.Make(np.zeros((self.batch, 3))),
            lambda context, output: output.set_value(self._outputs_cache.Eval(context)[1]), prerequisites_of_calc={self._outputs_cache.ticket()},
        )
        self.DeclarePeriodicUnrestrictedUpdateEvent(timing.duration, 0.0, self.Update)

    def StartEpisodes(self, context, rows) -> None:
        """Clears the filters of environments ``rows``. The other environments' filters are
        stored as fused now (``estimator_states``; at a tick's start it is the cached fusion that
        the tick's observation read), so that the tick's update, whose inputs the new episodes
        change, finds nothing new in them and does not fuse their measurements a second time
        (the filter is the same either way: fusing is idempotent, and environments are
        independent). Call it before the other systems start their episodes, while the cached
        fusion is still valid."""
        rows = np.asarray(rows, dtype=int).reshape(-1)
        if np.unique(rows).size == self.batch:
            states = context.get_abstract_state(self._state_index).get_value()  # every filter starts over
        else:
            states = self.estimator_states(context)
        context.SetAbstractState(self._state_index, states.cleared(rows))

    def estimator_states(self, context) -> EstimatorBatchState:
        """The B filters at the tick's start, with everything released by then fused
        (``.row(b)`` is environment b's EstimatorState)."""
        return self._fused_cache.Eval(context)

    def _CalcFused(self, context, value):
        current = context.get_abstract_state(self._state_index).get_value()
        positions, spins = self.position_measurements_port.Eval(context), self.spin_measurements_port.Eval(context)
        events = self.contact_events_port.Eval(context)
        now = self.timing.tick_time(self.episode_ticks_port.Eval(context))
        value.set_value(fuse_measurements_batch(self.ekf, current, positions, spins, events, now))

    def _CalcOutputs(self, context, value):
        now = np.asarray(self.timing.tick_time(self.episode_ticks_port.Eval(context)), dtype=float)
        means, _, status = self.ekf.estimate_batch(self.estimator_states(context).filters, now)  # zeros where not valid
        # as ``ball_estimator.estimate_outputs``: [valid, spin valid, age of the newest measurement used (-1: none)]
        status[:, 2] = np.where(status[:, 0] == 1.0, now - status[:, 2], -1.0)
        value.set_value((means, status))

    def Update(self, context, state):
        state.get_mutable_abstract_state(self._state_index).set_value(self.estimator_states(context))
