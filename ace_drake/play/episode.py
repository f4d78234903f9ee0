"""When a rally episode is over and how it ended, from the BallPlant's contact events.

An episode (paper, *Rally*; DESIGN.md) runs from the opponent's hit to the robot's response. Its
ball events decide it, in table-tennis terms (ITTF Laws 2.5-2.10, for the striker's side):

- the opponent's shot must bounce on the robot's half first (a serve: on the server's half, then
  the robot's); if it does not, the shot was a fault and the episode is ``INVALID`` (no play for
  the robot to make);
- the robot must hit it after that bounce and before a second contact with its half or the floor:
  otherwise ``MISSED`` (also a hit before the bounce counts against the robot: ``NOT_RETURNED``);
- the hit must make the ball's next table contact one on the opponent's half (touching the net on
  the way is allowed): ``RETURNED``; the robot's half, the floor or a second racket touch first is
  ``NOT_RETURNED``.

The classification reads only the ordered contact events; the caller ends episodes that never
resolve (a time limit) with ``timed_out``.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

from ace_drake.contracts import EpisodeResult, Outcome
from ace_drake.physics.propagate import ContactEvent, ContactKind


def _robot_half(event: ContactEvent) -> bool:
    return event.state_pre[0] < 0.0


def classify(events: Sequence[ContactEvent], serve: bool = False) -> EpisodeResult:
    """The episode's state after ``events`` (BallPlant's contacts since the opponent's hit, in
    order); ``serve``: the shot is a serve (it bounces on the server's half first)."""
    needed = [False, True] if serve else [True]  # the halves (robot's?) the incoming must bounce on
    bounce = None
    for index, event in enumerate(events):
        if event.kind == ContactKind.RACKET:
            if needed:
                return EpisodeResult(Outcome.NOT_RETURNED, "hit before the bounce", bounce, event)
            return _after_hit(events[index + 1 :], bounce, event)
        if event.kind == ContactKind.NET:
            continue  # the ball may touch the net and go on
        if event.kind == ContactKind.FLOOR:
            outcome = Outcome.INVALID if needed else Outcome.MISSED
            return EpisodeResult(outcome, "the shot missed the table" if needed else "not hit: the ball reached the floor", bounce)
        if event.kind == ContactKind.TABLE:
            if not needed:
                return EpisodeResult(Outcome.MISSED, "not hit: second bounce on the robot's half", bounce)
            if _robot_half(event) != needed[0]:
                return EpisodeResult(Outcome.INVALID, "the shot bounced on the wrong half", bounce)
            needed.pop(0)
            if not needed:
                bounce = event
    return EpisodeResult(Outcome.IN_PLAY, "", bounce)


def _after_hit(events: Sequence[ContactEvent], bounce: ContactEvent, hit: ContactEvent) -> EpisodeResult:
    for event in events:
        if event.kind == ContactKind.NET:
            continue
        if event.kind == ContactKind.TABLE:
            if _robot_half(event):
                return EpisodeResult(Outcome.NOT_RETURNED, "the return bounced on the robot's half", bounce, hit, event)
            return EpisodeResult(Outcome.RETURNED, "", bounce, hit, event)
        if event.kind == ContactKind.FLOOR:
            return EpisodeResult(Outcome.NOT_RETURNED, "the return missed the table", bounce, hit, event)
        if event.kind == ContactKind.RACKET:
            return EpisodeResult(Outcome.NOT_RETURNED, "the racket touched the ball twice", bounce, hit, event)
    return EpisodeResult(Outcome.IN_PLAY, "", bounce, hit)


def timed_out(result: EpisodeResult) -> EpisodeResult:
    """The final result of an episode stopped by its time limit while still in play."""
    if result.done:
        return result
    reason = "time limit after the hit" if result.hit is not None else "time limit: not hit"
    return dataclasses.replace(result, outcome=Outcome.NOT_RETURNED if result.hit is not None else Outcome.MISSED, reason=reason)
