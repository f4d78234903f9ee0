"""SegmentUmpire: the umpire of B environments' points (ITTF Laws, ``play.umpire``), once per segment."""

from __future__ import annotations

import dataclasses

import numpy as np
from pydrake.common.value import AbstractValue
from pydrake.systems.framework import LeafSystem, ValueProducer

from ace_drake.physics.propagate import ContactKind
from ace_drake.play.scoring import HUMAN, ROBOT, require_player
from ace_drake.play.umpire import Court, RallyEvent, Toss, umpire_after


@dataclasses.dataclass(frozen=True)
class PointRecord:
    """One environment's point so far: who served, the robot's or the human's toss (None: not
    judged), the rally's events in point time (s from the point's start), the point time of the
    current episode's time 0 (s) and how many of the episode's ball contacts are already in
    ``events``. Immutable."""

    server: str
    toss: Toss | None
    events: tuple[RallyEvent, ...]
    offset: float
    seen: int

    def __deepcopy__(self, memo):  # immutable: Drake's state copies may share it
        return self


class SegmentUmpire(LeafSystem):
    """Judges the points of B environments from the BallPlant's contacts: each tick, the contacts
    the ball made in it join the point's rally events (a racket contact in the diagram is the
    robot's: the human's strokes are told by the match runner, ``HumanStrikes``), and the point's
    umpire (``play.umpire.Umpire``) decides. An environment with no point open is not judged
    (training and evaluation episodes).

    Input ports:
        ball_flight (abstract BallSegment): the SegmentBallPlant's (each episode's contacts through
            the tick's end, episode times).
    Output ports:
        umpires (abstract tuple of B Umpire or None): each open point's umpire after the contacts
            through the last tick's end (its ``decision``, ``to_play``, ``bounced``; state only).
    State:
        abstract tuple of B PointRecord or None.
    Events:
        periodic unrestricted update every T (offset 0): adds the tick's contacts.
    """

    def __init__(self, batch: int, period: float, court: Court | None = None):
        """Args: batch, B; period, the tick T (s); court, the table's geometry (default the
        project's)."""
        super().__init__()
        self.batch = int(batch)
        self.court = Court() if court is None else court
        self._state_index = self.DeclareAbstractState(AbstractValue.Make((None,) * self.batch))
        self.ball_flight_port = self.DeclareAbstractInputPort("ball_flight", AbstractValue.Make(None))
        self._umpires_cache = self.DeclareCacheEntry(
            "the points' umpires", ValueProducer(allocate=lambda: AbstractValue.Make(()), calc=self._CalcUmpires),
            {self.abstract_state_ticket(self._state_index)},
        )
        self.umpires_port = self.DeclareAbstractOutputPort(
            "umpires", lambda: AbstractValue.Make(()), lambda context, output: output.set_value(self._umpires_cache.Eval(context)),
            prerequisites_of_calc={self._umpires_cache.ticket()},
        )
        self.DeclarePeriodicUnrestrictedUpdateEvent(period, 0.0, self.Update)

    # ------------------------------------------------------------------------------ set-up
    def records(self, context) -> tuple[PointRecord | None, ...]:
        """The B PointRecords (None: no point open) in this system's ``context``."""
        return context.get_abstract_state(self._state_index).get_value()

    def StartPoints(self, context, rows, servers, tosses=None) -> None:
        """Opens a point in environments ``rows`` (k,) served by ``servers`` (k,) (ROBOT or HUMAN)
        with their tosses (k,) (Toss, in the episode's time, or None), at the episode's time 0;
        call it with the episode's start (``diagrams.start_segment_episodes``)."""
        records = list(self.records(context))
        for k, row in enumerate(np.asarray(rows, dtype=int)):
            records[row] = PointRecord(require_player(servers[k], "SegmentUmpire server"), None if tosses is None else tosses[k], (), 0.0, 0)
        context.SetAbstractState(self._state_index, tuple(records))

    def HumanStrikes(self, context, rows, times, states_pre) -> None:
        """The human struck the ball in environments ``rows`` (k,) at point times ``times`` (k,) s,
        the ball's state just before being [p, v, ...] (k, >= 6); each row's new episode starts
        there (its time 0 is that strike): call it with that episode's start."""
        records = list(self.records(context))
        for row, time, state in zip(np.asarray(rows, dtype=int), np.asarray(times, dtype=float), np.asarray(states_pre, dtype=float)):
            record = records[row]
            if record is None:
                raise ValueError(f"SegmentUmpire.HumanStrikes: environment {row} has no point open")
            strike = RallyEvent(ContactKind.RACKET, float(time), state[:3], state[3:6], HUMAN)
            records[row] = PointRecord(record.server, record.toss, record.events + (strike,), float(time), 0)
        context.SetAbstractState(self._state_index, tuple(records))

    def ClosePoints(self, context, rows) -> None:
        """Stops judging environments ``rows``."""
        records = list(self.records(context))
        for row in np.asarray(rows, dtype=int):
            records[row] = None
        context.SetAbstractState(self._state_index, tuple(records))

    # ------------------------------------------------------------------------------ judging
    def _CalcUmpires(self, context, value):
        value.set_value(tuple(None if r is None else umpire_after(r.server, r.events, r.toss, self.court) for r in self.records(context)))

    def Update(self, context, state):
        records = self.records(context)
        if all(record is None for record in records):
            return
        events = self.ball_flight_port.Eval(context).events
        updated = list(records)
        for row, record in enumerate(records):
            if record is None or len(events[row]) == record.seen:
                continue
            new = tuple(RallyEvent.from_contact(e, ROBOT if ContactKind(e.kind) == ContactKind.RACKET else None) for e in events[row][record.seen:])
            new = tuple(dataclasses.replace(e, time=record.offset + e.time) for e in new)
            updated[row] = dataclasses.replace(record, events=record.events + new, seen=len(events[row]))
        state.get_mutable_abstract_state(self._state_index).set_value(tuple(updated))

