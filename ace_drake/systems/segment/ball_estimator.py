"""SegmentBallEstimator: the ball EKF of B environments."""

from __future__ import annotations

import numpy as np
from pydrake.common.value import AbstractValue
from pydrake.systems.framework import LeafSystem, ValueProducer

from ace_drake.control.segment_timing import SegmentTiming
from ace_drake.perception.ball_ekf import BallEkf
from ace_drake.perception.params import EstimatorParams
from ace_drake.physics.params import BallPhysicsParams
from ace_drake.systems.ball_estimator import EstimatorState, estimate_outputs, fuse_measurements


class SegmentBallEstimator(LeafSystem):
    """The continuous-time ``BallEstimator`` for B environments: at each tick every environment's
    filter fuses what its sensors released since the last tick (``ball_estimator.fuse_measurements``,
    the reference's rule; the filter processes observations in capture order whatever batches
    they come in, so fusing once per tick gives the reference's estimate at the tick).

    Input ports:
        position_measurements, spin_measurements (abstract tuple of B MeasurementHistory).
        contact_events (abstract tuple of B tuples of ContactEvent): the ball's contacts up to the
            tick's start (a racket contact restarts the track).
        episode_ticks (abstract int64 (B,)): the EpisodeClock's.
    Output ports:
        ball_state_estimate (abstract float (B, 9)): [p, v, w] predicted to the tick's start.
        estimate_status (abstract float (B, 3)): [valid, spin valid, age of newest measurement (s)].
    State:
        abstract tuple of B EstimatorState.
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
        self._state_index = self.DeclareAbstractState(AbstractValue.Make((EstimatorState(),) * self.batch))
        self.position_measurements_port = self.DeclareAbstractInputPort("position_measurements", AbstractValue.Make(()))
        self.spin_measurements_port = self.DeclareAbstractInputPort("spin_measurements", AbstractValue.Make(()))
        self.contact_events_port = self.DeclareAbstractInputPort("contact_events", AbstractValue.Make(()))
        self.episode_ticks_port = self.DeclareAbstractInputPort("episode_ticks", AbstractValue.Make(np.zeros(self.batch, dtype=np.int64)))
        self._fused_cache = self.DeclareCacheEntry(
            "the filters with everything released by the tick's start",
            ValueProducer(allocate=lambda: AbstractValue.Make(()), calc=self._CalcFused),
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
        """Clears the filters of environments ``rows``."""
        states = list(context.get_abstract_state(self._state_index).get_value())
        for row in np.asarray(rows, dtype=int):
            states[row] = EstimatorState()
        context.SetAbstractState(self._state_index, tuple(states))

    def estimator_states(self, context) -> tuple[EstimatorState, ...]:
        """The B filters at the tick's start, with everything released by then fused."""
        return self._fused_cache.Eval(context)

    def _CalcFused(self, context, value):
        current = context.get_abstract_state(self._state_index).get_value()
        positions, spins = self.position_measurements_port.Eval(context), self.spin_measurements_port.Eval(context)
        events = self.contact_events_port.Eval(context)
        now = self.timing.tick_time(self.episode_ticks_port.Eval(context))
        value.set_value(tuple(
            fuse_measurements(self.ekf, current[row], positions[row], spins[row], events[row], float(now[row])) for row in range(self.batch)
        ))

    def _CalcOutputs(self, context, value):
        now = self.timing.tick_time(self.episode_ticks_port.Eval(context))
        estimates, status = np.zeros((self.batch, 9)), np.zeros((self.batch, 3))
        for row, fused in enumerate(self.estimator_states(context)):
            estimates[row], status[row] = estimate_outputs(self.ekf.estimate(fused.filter, float(now[row])))
        value.set_value((estimates, status))

    def Update(self, context, state):
        state.get_mutable_abstract_state(self._state_index).set_value(self.estimator_states(context))
