"""Episode outcomes from constructed contact sequences (play/episode.py)."""

import numpy as np
import pytest

from ace_drake.contracts import Outcome
from ace_drake.physics.propagate import ContactEvent, ContactKind
from ace_drake.play.episode import classify, timed_out


def event(kind: ContactKind, time: float, x: float) -> ContactEvent:
    state = np.zeros(9)
    state[0] = x
    return ContactEvent(kind, time, state, state)


TABLE, NET, FLOOR, RACKET = ContactKind.TABLE, ContactKind.NET, ContactKind.FLOOR, ContactKind.RACKET


@pytest.mark.parametrize(
    "events, serve, outcome, reason",
    [
        ([], False, Outcome.IN_PLAY, ""),
        ([event(TABLE, 0.4, -0.6)], False, Outcome.IN_PLAY, ""),
        ([event(TABLE, 0.4, -0.6), event(RACKET, 0.6, -1.5)], False, Outcome.IN_PLAY, ""),
        ([event(TABLE, 0.4, -0.6), event(RACKET, 0.6, -1.5), event(TABLE, 1.0, 0.8)], False, Outcome.RETURNED, ""),
        ([event(NET, 0.2, 0.0), event(TABLE, 0.4, -0.3), event(RACKET, 0.6, -1.5), event(NET, 0.8, 0.0), event(TABLE, 0.9, 0.3)], False, Outcome.RETURNED, ""),
        ([event(TABLE, 0.4, -0.6), event(RACKET, 0.6, -1.5), event(TABLE, 0.8, -0.2)], False, Outcome.NOT_RETURNED, "robot's half"),
        ([event(TABLE, 0.4, -0.6), event(RACKET, 0.6, -1.5), event(FLOOR, 1.2, 2.0)], False, Outcome.NOT_RETURNED, "missed the table"),
        ([event(TABLE, 0.4, -0.6), event(RACKET, 0.6, -1.5), event(RACKET, 0.61, -1.5)], False, Outcome.NOT_RETURNED, "twice"),
        ([event(RACKET, 0.3, -1.0)], False, Outcome.NOT_RETURNED, "before the bounce"),
        ([event(TABLE, 0.4, -0.6), event(FLOOR, 0.9, -2.5)], False, Outcome.MISSED, "floor"),
        ([event(TABLE, 0.4, -0.6), event(TABLE, 0.7, -1.2)], False, Outcome.MISSED, "second bounce"),
        ([event(TABLE, 0.4, 0.6)], False, Outcome.INVALID, "wrong half"),
        ([event(FLOOR, 0.6, -2.0)], False, Outcome.INVALID, "missed the table"),
        # A serve bounces on the server's half, then on the robot's.
        ([event(TABLE, 0.2, 0.8), event(TABLE, 0.5, -0.6), event(RACKET, 0.7, -1.5), event(TABLE, 1.0, 0.5)], True, Outcome.RETURNED, ""),
        ([event(TABLE, 0.2, -0.8)], True, Outcome.INVALID, "wrong half"),
        ([event(TABLE, 0.2, 0.8), event(RACKET, 0.4, -1.0)], True, Outcome.NOT_RETURNED, "before the bounce"),
    ],
)
def test_outcomes_follow_the_rules(events, serve, outcome, reason):
    result = classify(events, serve)
    assert result.outcome is outcome
    assert reason in result.reason
    assert result.done == (outcome is not Outcome.IN_PLAY)


def test_result_keeps_the_deciding_events_and_the_bounce_to_hit_time():
    events = [event(TABLE, 0.4, -0.6), event(RACKET, 0.55, -1.5), event(TABLE, 1.0, 0.8)]
    result = classify(events)
    assert result.bounce is events[0] and result.hit is events[1] and result.landing is events[2]
    assert result.bounce_to_hit_time == pytest.approx(0.15)


def test_time_limit_ends_open_episodes_only():
    assert timed_out(classify([event(TABLE, 0.4, -0.6)])).outcome is Outcome.MISSED
    hit = timed_out(classify([event(TABLE, 0.4, -0.6), event(RACKET, 0.6, -1.5)]))
    assert hit.outcome is Outcome.NOT_RETURNED and "after the hit" in hit.reason
    returned = classify([event(TABLE, 0.4, -0.6), event(RACKET, 0.6, -1.5), event(TABLE, 1.0, 0.8)])
    assert timed_out(returned) is returned
