"""analysis/replay.py: a recorded rally replayed through the BallPlant diagram."""

from pathlib import Path

import numpy as np
import pytest
from pydrake.geometry import Meshcat

from ace_drake.analysis.ball_demo import run_shots, spin_comparison_shots
from ace_drake.analysis.replay import (
    LOG_PERIOD,
    compare_bounces,
    longest_rallies,
    rally_keys,
    replay_rally,
    select_rally,
)
from ace_drake.match_data import MatchEvent, load_match_events
from ace_drake.physics.flight import make_state
from ace_drake.physics.propagate import ContactEvent, ContactKind

DATA = Path(__file__).resolve().parents[2] / "shared/data/ace_match_events_elite.csv"
# A rally of 17 events (7 shots after the serve, 9 bounces, 5.3 s) on which the paper's model lands
# a median 12 cm from the recorded bounces; without the Magnus force the median is 30 cm.
RALLY = ("Elite D", "/game_0/rally_9")
MEDIAN_DISTANCE_BOUND = 0.25  # m


def event(kind, time, state, side="p1", player="Elite X", rally="/game_0/rally_0"):
    return MatchEvent(player, rally, kind, side if kind != "net" else "", time, np.asarray(state, dtype=float))


def topspin_rally(start_time=10.0):
    """A synthetic rally: the topspin demo shot, its recorded bounce where the model puts it, and a
    net event without velocity."""
    shot = spin_comparison_shots()["topspin"]
    (result,) = run_shots({"topspin": shot})
    bounce = result.first(ContactKind.TABLE)
    nan_state = np.concatenate([[0.0, 0.0, 0.1], np.full(6, np.nan)])
    events = [
        event("shot", start_time, shot),
        event("net", start_time + 0.2, nan_state),
        event("bounce", start_time + bounce.time, bounce.state_post, side="p2"),
    ]
    return events, bounce


# ------------------------------------------------------------------------------ without data


def test_compare_bounces_picks_the_table_contact_nearest_in_time():
    recorded = [
        event("shot", 0.0, make_state([-1.5, 0, 0.2], [5, 0, 1])),
        event("bounce", 0.5, make_state([0.5, 0.1, 0.02], [4, 0, 2]), side="p2"),
    ]
    far = ContactEvent(ContactKind.TABLE, 0.2, make_state([-0.5, 0, 0.02], 0), make_state([-0.5, 0, 0.02], 0))
    net = ContactEvent(ContactKind.NET, 0.49, make_state([0, 0, 0.1], 0), make_state([0, 0, 0.1], 0))
    near = ContactEvent(ContactKind.TABLE, 0.53, make_state([0.8, 0.5, 0.02], 0), make_state([0.8, 0.5, 0.02], 0))
    (comparison,) = compare_bounces(recorded, [far, net, near])
    assert comparison.simulated is near
    assert comparison.distance == pytest.approx(0.5)  # (0.3, 0.4, 0) apart
    assert comparison.time_error == pytest.approx(0.03)
    (unmatched,) = compare_bounces(recorded, [net])
    assert unmatched.simulated is None and np.isnan(unmatched.distance)


def test_replay_of_a_modelled_shot_lands_on_its_recorded_bounce():
    events, bounce = topspin_rally(start_time=10.0)
    dut = replay_rally(events)
    assert [e.kind for e in dut.recorded] == ["shot", "bounce"]  # the NaN net event is skipped
    assert dut.start_time == 10.0
    assert dut.recorded[0].time == 0.0 and dut.recorded[1].time == pytest.approx(bounce.time)
    np.testing.assert_array_equal(dut.states[0], events[0].state)
    assert dut.times[0] == 0.0
    assert bounce.time + 0.5 - LOG_PERIOD < dut.times[-1] <= bounce.time + 0.5  # the tail after the last event
    (comparison,) = dut.bounces
    assert comparison.distance < 1e-4
    assert abs(comparison.time_error) < 1e-4


def test_replay_draws_recorded_bounces_in_meshcat():
    events, _ = topspin_rally()
    meshcat = Meshcat()
    replay_rally(events, meshcat=meshcat)
    assert meshcat.HasPath("/recorded/bounce_0")
    assert not meshcat.HasPath("/recorded/bounce_1")


def test_replay_of_several_rallies_needs_a_rally_id():
    events, _ = topspin_rally()
    other = [event("shot", 30.0, events[0].state, rally="/game_0/rally_1")]
    with pytest.raises(ValueError, match="pass rally="):
        replay_rally(events + other)
    assert len(replay_rally(events + other, rally="/game_0/rally_0").recorded) == 2


# ------------------------------------------------------------------------------ recorded data


@pytest.fixture(scope="module")
def events():
    if not DATA.is_file():
        pytest.skip(f"recorded match data not found at {DATA} (../shared/data beside the repository)")
    return load_match_events(DATA)


@pytest.fixture(scope="module")
def replay(events):
    player, rally = RALLY
    return replay_rally(events, player=player, rally=rally)


def test_replayed_bounces_land_near_the_recorded_ones(replay):
    distances = replay.bounce_distances
    assert len(distances) == 9
    assert np.all(np.isfinite(distances))
    assert np.median(distances) < MEDIAN_DISTANCE_BOUND
    # Matched in time too: the model's bounces come a few tens of ms early, not a flight away.
    assert np.median(np.abs([b.time_error for b in replay.bounces])) < 0.06


def test_replay_is_in_time_order_from_zero(replay):
    contact_times = [e.time for e in replay.contact_events]
    recorded_times = [e.time for e in replay.recorded]
    assert np.all(np.diff(contact_times) >= 0)
    assert np.all(np.diff(recorded_times) >= 0)
    assert np.all(np.diff(replay.times) > 0)
    assert recorded_times[0] == 0.0 and replay.times[0] == 0.0
    assert 0.0 < contact_times[0] and contact_times[-1] <= replay.times[-1]
    assert recorded_times[-1] + 0.5 - LOG_PERIOD < replay.times[-1] <= recorded_times[-1] + 0.5
    np.testing.assert_array_equal(replay.states[0], replay.recorded[0].state)


def test_unknown_or_ambiguous_rally_raises(events):
    with pytest.raises(ValueError, match="no rally '/game_9/rally_99'"):
        replay_rally(events, rally="/game_9/rally_99", player="Elite A")
    with pytest.raises(ValueError, match="no rally '/game_0/rally_0' against 'Nobody'"):
        select_rally(events, "/game_0/rally_0", player="Nobody")
    with pytest.raises(ValueError, match="pass player="):
        select_rally(events, "/game_0/rally_0")


def test_select_and_longest_rallies(events):
    player, rally = RALLY
    selected = select_rally(events, rally, player)
    assert len(selected) == 17
    assert all(e.player == player and e.rally == rally for e in selected)
    longest = longest_rallies(events, 3)
    shots = [sum(e.kind == "shot" for e in select_rally(events, key.rally, key.player)) for key in longest]
    assert shots == sorted(shots, reverse=True)
    all_shots = [sum(e.kind == "shot" for e in select_rally(events, k.rally, k.player)) for k in rally_keys(events)]
    assert shots[0] == max(all_shots)
    assert all(key.player == "Elite B" for key in longest_rallies(events, 2, player="Elite B"))
