"""SegmentBallPlant: the ball of B environments, one segment per tick."""

from __future__ import annotations

import dataclasses

import numpy as np
from pydrake.common.value import AbstractValue
from pydrake.systems.framework import LeafSystem, ValueProducer

from ace_drake.control.segment_timing import SegmentTiming
from ace_drake.physics.contact import ResidualModel
from ace_drake.physics.params import BallPhysicsParams
from ace_drake.physics.segment import propagate_segment


@dataclasses.dataclass(frozen=True)
class BallSegment:
    """The balls over one tick: ``samples`` (B, n + 1, 9) [p, v, w] at the tick's 1 kHz samples
    (after any contact at its exact time), and ``events``, each environment's contacts since its
    episode began, through the tick's end (tuples of ContactEvent, episode times)."""

    samples: np.ndarray
    events: tuple


@dataclasses.dataclass(frozen=True)
class BallPlantState:
    """The balls at the tick's start (B, 9), their episodes' contacts so far, and their seeds of the
    post-table perturbations (B,). Immutable."""

    balls: np.ndarray
    events: tuple
    seeds: np.ndarray

    def __deepcopy__(self, memo):  # immutable: Drake's state copies may share it
        return self


class _DelayedRacket:
    """A tick's RacketMotion seen from ``offset`` samples into the tick (an episode's first tick:
    its ball starts flying ``lead`` after the tick's start)."""

    def __init__(self, motion, offset: int, period: float):
        self._motion, self._shift = motion, offset * period
        self.times = motion.times[offset:] - self._shift
        self.p_WR, self.R_WR, self.w_WR, self.v_WR = (getattr(motion, name)[:, offset:] for name in ("p_WR", "R_WR", "w_WR", "v_WR"))

    def state_at(self, env, tau):
        return self._motion.state_at(env, np.asarray(tau, dtype=float) + self._shift)


class SegmentBallPlant(LeafSystem):
    """The continuous-time ``BallPlant`` for B environments (paper, Methods *Simulation*): at each
    tick every ball flies through the segment by fixed-step RK4 (1 ms) with every table, net,
    floor and (moving) racket contact located inside it to 1e-10 s and its impact map applied
    there (``physics.segment.propagate_segment``; the post-table perturbations drawn as the
    reference draws them). An episode's ball starts flying at its episode time 0, ``lead`` into
    its first tick, and holds its state before.

    Input ports:
        racket_motion (abstract RacketMotion): the racket over the tick. Unconnected: no racket.
        episode_ticks (abstract int64 (B,)): the EpisodeClock's.
    Output ports:
        ball_flight (abstract BallSegment): the balls over the tick (feedthrough of the racket).
        ball_state (abstract float (B, 9)): [p_WB (m), v_WB (m/s), w_WB (rad/s)] at the tick's
            start (state only).
        contact_events (abstract tuple of B tuples of ContactEvent): each episode's contacts up to
            the tick's start (state only).
    State:
        abstract BallPlantState.
    Events:
        periodic unrestricted update every T (offset 0): stores the balls at the tick's end.
    """

    def __init__(self, params: BallPhysicsParams, batch: int, timing: SegmentTiming, perturb: bool = False, racket_residual: ResidualModel | None = None):
        """Args: params, the ball model; batch, B; timing; perturb, apply the paper's post-table
        perturbations (seeded per episode, ``StartEpisodes``); racket_residual, an optional
        correction model for racket contacts."""
        super().__init__()
        self.params = params
        self.batch = int(batch)
        self.timing = timing
        self.perturb = perturb
        self.residual = racket_residual
        default = BallPlantState(np.zeros((self.batch, 9)), ((),) * self.batch, np.zeros(self.batch, dtype=np.int64))
        self._state_index = self.DeclareAbstractState(AbstractValue.Make(default))
        self.racket_motion_port = self.DeclareAbstractInputPort("racket_motion", AbstractValue.Make(None))
        self.episode_ticks_port = self.DeclareAbstractInputPort("episode_ticks", AbstractValue.Make(np.zeros(self.batch, dtype=np.int64)))
        self._flight_cache = self.DeclareCacheEntry(
            "the balls over the tick",
            ValueProducer(allocate=lambda: AbstractValue.Make(None), calc=self._CalcFlight),
            {self.abstract_state_ticket(self._state_index), self.all_input_ports_ticket()},
        )
        self.ball_flight_port = self.DeclareAbstractOutputPort(
            "ball_flight", lambda: AbstractValue.Make(None), lambda context, output: output.set_value(self._flight_cache.Eval(context)),
            prerequisites_of_calc={self._flight_cache.ticket()},
        )
        state_only = {self.abstract_state_ticket(self._state_index)}
        self.ball_state_port = self.DeclareAbstractOutputPort(
            "ball_state", lambda: AbstractValue.Make(np.zeros((self.batch, 9))),
            lambda context, output: output.set_value(self.plant_state(context).balls), prerequisites_of_calc=state_only,
        )
        self.contact_events_port = self.DeclareAbstractOutputPort(
            "contact_events", lambda: AbstractValue.Make(()),
            lambda context, output: output.set_value(self.plant_state(context).events), prerequisites_of_calc=state_only,
        )
        self.DeclarePeriodicUnrestrictedUpdateEvent(timing.duration, 0.0, self.Update)

    # ------------------------------------------------------------------------------ set-up
    def plant_state(self, context) -> BallPlantState:
        """The BallPlantState in this system's ``context``."""
        return context.get_abstract_state(self._state_index).get_value()

    def StartEpisodes(self, context, rows, shots, seeds) -> None:
        """Starts environments ``rows`` (k,) with balls ``shots`` (k, 9) [p, v, w] (just after the
        opponent's hit), no contacts, and the perturbations' seeds (k,)."""
        rows = np.asarray(rows, dtype=int)
        shots = np.asarray(shots, dtype=float).reshape(rows.size, -1)
        if shots.shape[1] != 9 or not np.all(np.isfinite(shots)):
            raise ValueError(f"SegmentBallPlant.StartEpisodes: expected ({rows.size}, 9) finite ball states [p, v, w], got {shots.shape}")
        current = self.plant_state(context)
        balls, events, all_seeds = current.balls.copy(), list(current.events), current.seeds.copy()
        balls[rows] = shots
        all_seeds[rows] = np.asarray(seeds, dtype=np.int64)
        for row in rows:
            events[row] = ()
        context.SetAbstractState(self._state_index, BallPlantState(balls, tuple(events), all_seeds))

    # ------------------------------------------------------------------------------ flight
    def _CalcFlight(self, context, value):
        current = self.plant_state(context)
        ticks = self.episode_ticks_port.Eval(context)
        racket = self.racket_motion_port.Eval(context) if self.racket_motion_port.HasValue(context) else None
        samples = np.empty((self.batch, self.timing.samples + 1, 9))
        events = list(current.events)
        first = ticks == 0
        lead = self.timing.lead
        counts = np.array([len(e) for e in current.events], dtype=np.int64)
        seeds = current.seeds if self.perturb else None
        for active, start, duration, offset in (
            (~first, self.timing.tick_time(ticks), self.timing.duration, 0),
            (first, np.zeros(self.batch), self.timing.duration - lead * self.timing.period, lead),
        ):
            if not active.any():
                continue
            moving = racket if racket is None or offset == 0 else _DelayedRacket(racket, offset, self.timing.period)
            flight = propagate_segment(current.balls, start, duration, self.params, moving, active, dt=self.timing.period,
                                       perturb_seeds=seeds, event_counts=counts, residual=self.residual)
            if offset == 0 and active.all():
                samples = flight.samples  # every row flew the whole tick (most ticks): no copy
            else:
                samples[active, offset:] = flight.samples[active]
                samples[active, :offset] = current.balls[active, None, :]
            for row in np.flatnonzero(active):
                if flight.events[row]:
                    events[row] = events[row] + tuple(flight.events[row])
        value.set_value(BallSegment(samples, tuple(events)))

    def Update(self, context, state):
        flight = self._flight_cache.Eval(context)
        current = self.plant_state(context)
        state.get_mutable_abstract_state(self._state_index).set_value(BallPlantState(flight.samples[:, -1].copy(), flight.events, current.seeds))
