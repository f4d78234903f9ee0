"""Loading match data and building event pairs."""

import numpy as np
import pytest

from ace_drake.match_data import MatchDataError, event_pairs, load_match_events

HEADER = "player_id,rally_id,type,timestamp,ball_pos,ball_vel_out,ball_spin_out\n"


def write(tmp_path, body):
    path = tmp_path / "events.csv"
    path.write_text(HEADER + body)
    return path


def test_parses_vectors_and_builds_pairs(tmp_path):
    path = write(
        tmp_path,
        "P,/game_0/rally_0/event1,shot_p2,1.0,[ 1.5 0.1 0.2],[-5 0 1],[0 -100 0]\n"
        "P,/game_0/rally_0/event2,bounce_p1,1.3,[-0.5 0.2 0.02],[-4 0 2],[0 -50 0]\n"
        "P,/game_0/rally_0/event3,net,1.5,[0 0.2 0.1],[nan nan nan],[nan nan nan]\n"
        "P,/game_0/rally_0/event4,bounce_p2,1.7,[0.5 0.2 0.02],[3 0 2],[0 50 0]\n"
        "P,/game_0/rally_1/event1,bounce_p1,2.0,[-0.5 0.2 0.02],[-4 0 2],[0 -50 0]\n",
    )
    events = load_match_events(path)
    assert [e.type for e in events] == ["shot_p2", "bounce_p1", "net", "bounce_p2", "bounce_p1"]
    np.testing.assert_array_equal(events[0].state, [1.5, 0.1, 0.2, -5, 0, 1, 0, -100, 0])
    assert np.isnan(events[2].state[3:]).all()
    pairs = event_pairs(events)
    # shot->bounce only: net->bounce starts at a net event, and rallies do not join.
    assert list(pairs.transitions) == ["shot_p2->bounce_p1"]
    assert pairs.durations[0] == pytest.approx(0.3)


def test_errors_name_file_line_and_problem(tmp_path):
    with pytest.raises(MatchDataError, match="not found"):
        load_match_events(tmp_path / "absent.csv")
    bad = tmp_path / "bad.csv"
    bad.write_text("player_id,type\nP,shot_p1\n")
    with pytest.raises(MatchDataError, match="missing column"):
        load_match_events(bad)
    path = write(tmp_path, "P,/g/r/e1,shot_p2,1.0,[1 2],[0 0 0],[0 0 0]\n")
    with pytest.raises(MatchDataError, match="line 2.*3-vector"):
        load_match_events(path)
    path = write(tmp_path, "P,/g/r/e1,serve_p2,1.0,[1 2 3],[0 0 0],[0 0 0]\n")
    with pytest.raises(MatchDataError, match="unknown event type"):
        load_match_events(path)


def test_a_short_row_names_the_file_line_and_the_columns_without_a_value(tmp_path):
    path = write(tmp_path, "P,/g/r/e1,shot_p2,1.0,[1 2 3],[0 0 0],[0 0 0]\n"
                           "P,/g/r/e2,bounce_p2,1.3,[1 2 0.02]\n")
    with pytest.raises(MatchDataError, match=r"events\.csv, line 3: no value in column\(s\) \['ball_vel_out', 'ball_spin_out'\] "
                                             r"\(the row has 5 fields; expected 7\)"):
        load_match_events(path)
