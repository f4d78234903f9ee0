"""The umpire's rules (play/umpire.py) on hand-built contact sequences.

Frame: x < 0 is the robot's court, x > 0 the human's; the table is 2.74 x 1.525 m, so the end lines
are at x = -/+1.37 m and the side lines at y = -/+0.7625 m; the ball's radius is 0.02 m.
"""

import numpy as np
import pytest

from ace_drake.physics.params import BallPhysicsParams
from ace_drake.physics.propagate import ContactEvent, ContactKind, simulate
from ace_drake.play.scoring import HUMAN, ROBOT
from ace_drake.play.umpire import Court, RallyEvent, Toss, Umpire, judge_rally

TABLE, NET, FLOOR, RACKET = ContactKind.TABLE, ContactKind.NET, ContactKind.FLOOR, ContactKind.RACKET


def table(t, x, y=0.0):
    return RallyEvent(TABLE, t, [x, y, 0.02], [0.0, 0.0, -2.0])


def net(t, z=0.17):
    """A net-cord touch: the ball's centre 1.75 cm above the cord (0.1525 m)."""
    return RallyEvent(NET, t, [0.0, 0.0, z], [4.0, 0.0, -1.0])


def floor(t, x):
    return RallyEvent(FLOOR, t, [x, 0.0, -0.74], [0.0, 0.0, -3.0])


def hit(t, striker, x, v_z=-1.0):
    return RallyEvent(RACKET, t, [x, 0.0, 0.2], [0.0, 0.0, v_z], striker)


def robot_serve():
    """A good service by the robot: struck behind its end line, once on each court."""
    return [hit(0.0, ROBOT, -1.5), table(0.2, -0.6), table(0.5, 0.7)]


def human_return():
    """After ``robot_serve``: the human strikes it back onto the robot's court."""
    return [hit(0.7, HUMAN, 1.6), table(1.0, -0.5)]


@pytest.mark.parametrize("miss", [table(0.8, 1.2), floor(1.0, 2.2)], ids=["double bounce", "floor"])
def test_a_good_service_the_receiver_misses(miss):
    decision = judge_rally(ROBOT, robot_serve() + [miss])
    assert decision.winner == ROBOT and decision.loser == HUMAN and not decision.let
    assert decision.shots == 1 and decision.law == "2.10.1.3" and decision.event is miss


def test_a_service_touching_the_net_then_good_is_a_let():
    decision = judge_rally(ROBOT, [hit(0.0, ROBOT, -1.5), table(0.2, -0.6), net(0.35), table(0.5, 0.3)])
    assert decision.let and decision.winner is None and decision.law == "2.9.1.1"


def test_a_service_obstructed_after_touching_the_net_is_a_let():
    decision = judge_rally(ROBOT, [hit(0.0, ROBOT, -1.5), table(0.2, -0.6), net(0.35), hit(0.45, HUMAN, 0.3)])
    assert decision.let


@pytest.mark.parametrize(
    "after_net", [table(0.5, -0.1), floor(0.6, -0.5)], ids=["falls back on the server's court", "to the floor"]
)
def test_a_service_into_the_net_is_the_receivers_point(after_net):
    decision = judge_rally(ROBOT, [hit(0.0, ROBOT, -1.5), table(0.2, -0.6), net(0.35, z=0.1), after_net])
    assert decision.winner == HUMAN and not decision.let and decision.law == "2.6.3"


def test_a_service_touching_the_receivers_court_first_is_a_fault():
    decision = judge_rally(HUMAN, [hit(0.0, HUMAN, 1.5), table(0.3, -0.6)])
    assert decision.winner == ROBOT and "first" in decision.reason and decision.law == "2.6.3"


def test_a_service_touching_the_net_before_the_servers_court_is_a_fault():
    assert judge_rally(ROBOT, [hit(0.0, ROBOT, -1.5), net(0.2)]).winner == HUMAN


def good_toss(v_z=2.0, v_x=0.0):
    """Released behind the robot's end line; rises v_z^2 / (2 g): 0.204 m for 2 m/s."""
    return Toss.ballistic(-0.5, [-1.5, 0.0, 0.1], [v_x, 0.0, v_z])


def test_a_good_toss_struck_while_falling_starts_the_rally():
    assert good_toss().apex_height == pytest.approx(0.2039, abs=1e-4)
    umpire = Umpire(ROBOT, good_toss())
    assert umpire.decision is None
    for event in robot_serve():
        assert umpire.observe(event) is None
    assert umpire.to_play == HUMAN and umpire.shots == 1


def test_a_toss_lower_than_16_cm_is_a_fault():
    low = good_toss(v_z=1.7)  # 1.7^2 / 19.62 = 0.147 m
    decision = judge_rally(ROBOT, robot_serve(), toss=low)
    assert decision.winner == HUMAN and decision.law == "2.6.2" and "0.147" in decision.reason
    assert decision.shots == 0 and decision.event is None


def test_a_toss_not_near_vertical_is_a_fault():
    decision = judge_rally(ROBOT, robot_serve(), toss=good_toss(v_z=2.0, v_x=1.0))  # atan(1/2) = 26.6 deg
    assert decision.winner == HUMAN and "26.6 deg" in decision.reason
    assert judge_rally(ROBOT, robot_serve(), toss=good_toss(v_z=2.0, v_x=0.3)) is None  # 8.5 deg


def test_a_toss_struck_while_rising_is_a_fault():
    events = [hit(0.0, ROBOT, -1.5, v_z=0.5)] + robot_serve()[1:]
    decision = judge_rally(ROBOT, events, toss=good_toss())
    assert decision.winner == HUMAN and "rising" in decision.reason and decision.shots == 1


def test_a_service_struck_over_the_table_is_a_fault():
    events = [hit(0.0, ROBOT, -1.2)] + robot_serve()[1:]
    assert judge_rally(ROBOT, events, toss=good_toss()).law == "2.6.4"


def test_a_tossed_ball_touching_the_table_before_the_strike_is_a_fault():
    assert judge_rally(ROBOT, [table(0.0, -0.6)] + robot_serve()).winner == HUMAN


def test_a_net_cord_return_that_lands_is_good():
    events = robot_serve() + [hit(0.7, HUMAN, 1.6), net(0.9), table(1.0, -0.2)]
    umpire = Umpire(ROBOT)
    assert [umpire.observe(e) for e in events] == [None] * len(events)
    assert umpire.to_play == ROBOT and umpire.shots == 2
    assert judge_rally(ROBOT, events + [floor(1.5, -2.0)]).winner == HUMAN


@pytest.mark.parametrize("x, y", [(-1.37 - 0.015, 0.0), (-1.0, -0.7625 - 0.019), (-1.385, 0.775)])
def test_an_edge_ball_is_good(x, y):
    """The ball's centre within a radius (0.02 m) beyond an end or side line: it touches the edge."""
    assert judge_rally(ROBOT, robot_serve() + [hit(0.7, HUMAN, 1.6), table(1.0, x, y)]) is None


def test_a_side_ball_is_a_fault():
    """A TABLE contact 3 cm beyond the side line, or with the centre below the surface: the side."""
    beside = RallyEvent(TABLE, 1.0, [-1.0, 0.7925, 0.02], [0.0, 0.0, -2.0])
    below = RallyEvent(TABLE, 1.0, [-1.0, 0.775, -0.01], [0.0, 1.0, 0.0])
    for side_ball in (beside, below):
        decision = judge_rally(ROBOT, robot_serve() + [hit(0.7, HUMAN, 1.6), side_ball])
        assert decision.winner == ROBOT and "side" in decision.reason


def test_a_long_ball_is_the_point_of_its_receiver():
    decision = judge_rally(ROBOT, robot_serve() + [hit(0.7, HUMAN, 1.6), floor(1.2, -2.0)])
    assert decision.winner == ROBOT and decision.law == "2.10.1.4" and decision.shots == 2


def test_a_return_touching_the_strikers_own_court_is_a_fault():
    decision = judge_rally(ROBOT, robot_serve() + [hit(0.7, HUMAN, 1.6), table(0.9, 0.4)])
    assert decision.winner == ROBOT and "own court" in decision.reason and decision.law == "2.7"


def test_a_double_bounce_after_a_net_cord():
    events = robot_serve() + human_return() + [hit(1.2, ROBOT, -1.6), net(1.4), table(1.45, 0.1), table(1.6, 0.3)]
    decision = judge_rally(ROBOT, events)
    assert decision.winner == ROBOT and "second bounce" in decision.reason and decision.shots == 3


def test_a_double_hit():
    decision = judge_rally(ROBOT, robot_serve() + [hit(0.7, HUMAN, 1.6), hit(0.72, HUMAN, 1.55)])
    assert decision.winner == ROBOT and decision.law == "2.10.1.7" and decision.shots == 3


def test_a_volley_before_the_bounce():
    decision = judge_rally(ROBOT, robot_serve() + [hit(0.7, HUMAN, 1.6), hit(0.9, ROBOT, -0.3)])
    assert decision.winner == HUMAN and "volley" in decision.reason and decision.law == "2.10.1.6"


def test_a_ball_through_the_net_is_a_fault():
    under = RallyEvent(NET, 0.9, [0.0, 0.9, -0.05], [4.0, 0.0, 0.0])  # under the net's overhang
    decision = judge_rally(ROBOT, robot_serve() + [hit(0.7, HUMAN, 1.6), under])
    assert decision.winner == ROBOT and decision.law == "2.10.1.5"
    assert Court().on_net_assembly([0.0, 0.0, 0.17]) and not Court().on_net_assembly([0.0, 0.0, 0.18])


def test_a_six_shot_rally_ending_in_a_miss():
    events = robot_serve()
    t = 0.5
    for shot in range(5):  # the human, robot, human, robot, human strike in turn
        striker, sign = (HUMAN, 1.0) if shot % 2 == 0 else (ROBOT, -1.0)
        events += [hit(t + 0.2, striker, 1.6 * sign), table(t + 0.5, -0.5 * sign)]
        t += 0.5
    events.append(table(t + 0.3, -1.0))  # the robot lets it bounce twice
    decision = judge_rally(ROBOT, events)
    assert decision.winner == HUMAN and decision.shots == 6 and "robot did not return" in decision.reason


def test_an_unfinished_rally_is_undecided():
    umpire = Umpire(HUMAN)
    assert umpire.to_play == HUMAN
    assert judge_rally(HUMAN, []) is None
    assert judge_rally(ROBOT, robot_serve()) is None


def test_events_must_be_in_time_order_and_racket_contacts_name_the_striker():
    with pytest.raises(ValueError, match="time order"):
        judge_rally(ROBOT, [hit(0.0, ROBOT, -1.5), table(0.2, -0.6), table(0.1, 0.7)])
    with pytest.raises(ValueError, match="striker"):
        RallyEvent(RACKET, 0.0, [0.0, 0.0, 0.0], [0.0, 0.0, 0.0])
    with pytest.raises(ValueError, match="striker"):
        RallyEvent(TABLE, 0.0, [0.0, 0.0, 0.0], [0.0, 0.0, 0.0], ROBOT)
    with pytest.raises(ValueError, match="server"):
        Umpire("referee")


def test_the_propagators_contacts_judge_a_service_the_receiver_misses():
    """A service simulated with the project's ball model from behind the robot's end line: it
    bounces on the robot's court, then on the human's, and reaches the floor unplayed."""
    state = np.array([-1.5, 0.0, 0.25, 6.0, 0.0, -2.0, 0.0, 0.0, 0.0])
    contacts = simulate(state, BallPhysicsParams(), 2.0).events[0]
    strike = RallyEvent.from_contact(ContactEvent(RACKET, 0.0, state, state), ROBOT)
    events = [strike] + [RallyEvent.from_contact(contact) for contact in contacts]
    assert [e.kind for e in events[:4]] == [RACKET, TABLE, TABLE, FLOOR]
    np.testing.assert_array_equal(events[1].position, contacts[0].state_pre[:3])
    decision = judge_rally(ROBOT, events, court=Court.from_physics(BallPhysicsParams()))
    assert decision.winner == ROBOT and decision.event is events[3] and decision.shots == 1


def test_a_good_return_that_comes_back_under_the_net_untouched_is_the_strikers_point():
    """After the human's good return bounced on the robot's court, the ball (heavy backspin) goes
    back under the net untouched: the robot failed to return it (Law 2.10.1.2)."""
    back_under = RallyEvent(NET, 1.3, [0.0, 0.9, -0.05], [-2.0, 0.0, 0.0])
    decision = judge_rally(ROBOT, [*robot_serve(), *human_return(), back_under])
    assert decision.winner == HUMAN and decision.law == "2.10.1.2"
