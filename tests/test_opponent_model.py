"""The opponent fitted to recorded matches (play/opponent_model.py)."""

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from ace_drake.config import InputError
from ace_drake.match_data import MatchEvent
from ace_drake.physics.params import BallPhysicsParams
from ace_drake.physics.propagate import simulate
from ace_drake.play import opponent_model
from ace_drake.play.opponent_model import OpponentModel, OpponentModelError, OpponentParams, human_responses

DATA = Path(__file__).resolve().parents[2] / "shared/data/ace_match_events_elite.csv"
MISSING_DATA = f"recorded match data not found at {DATA} (../shared/data beside the repository)"
needs_data = pytest.mark.skipif(not DATA.is_file(), reason=MISSING_DATA)

HEADER = "player_id,rally_id,type,timestamp,ball_pos,ball_vel_out,ball_spin_out\n"
NO_JITTER = OpponentParams(position_jitter=0.0, velocity_jitter=0.0, spin_jitter=0.0)


def ball(x=1.0, y=0.0, v_x=5.0, v_y=0.0, v_z=2.0, w_y=100.0, w_z=0.0):
    """A (9,) ball state; w_x is 0."""
    return np.array([x, y, 0.02, v_x, v_y, v_z, 0.0, w_y, w_z])


def rally(player, name, steps):
    """MatchEvents of one rally from (type, state) steps, 0.1 s apart."""
    events = []
    for i, (kind_side, state) in enumerate(steps):
        kind, _, side = kind_side.partition("_")
        events.append(MatchEvent(player, name, kind, side, 10.0 + 0.1 * i, np.asarray(state, dtype=float)))
    return events


def planted_events(incoming, returned, returns=None, player="P"):
    """One robot-served rally per incoming ball: shot_p1, bounce_p1, bounce_p2 (the incoming
    state), then the human's shot (``returns[i]``, default a fixed return) where returned."""
    events = []
    for i, (state, hit) in enumerate(zip(incoming, returned)):
        steps = [("shot_p1", ball(-1.5, v_x=6.0)), ("bounce_p1", ball(-0.5)), ("bounce_p2", state)]
        if hit:
            steps.append(("shot_p2", ball(1.6, v_x=-9.0) if returns is None else returns[i]))
        events += rally(player, f"/game_0/rally_{i}", steps)
    return events


# ------------------------------------------------------------------------------ extraction


def hand_built_events():
    a, b, c, d, z = (ball(x) for x in (0.5, 0.6, 0.7, 0.8, 0.9))
    return_a, return_c, return_z = ball(1.5, v_x=-8.0), ball(1.6, v_x=-9.0), ball(1.7, v_x=-10.0)
    serve_1, serve_2, serve_3 = ball(1.4, v_x=-4.0), ball(1.41, v_x=-4.0), ball(1.42, v_x=-4.0)
    events = (
        # The robot serves; the human returns (landing), later misses the robot's next ball.
        rally("P", "/game_0/rally_0", [("shot_p1", ball(-1.4)), ("bounce_p1", ball(-0.5)), ("bounce_p2", a),
                                       ("shot_p2", return_a), ("bounce_p1", ball(-0.6)), ("shot_p1", ball(-1.5)),
                                       ("bounce_p2", b)])
        # The human serves; the robot's return touches the net; the human's return goes into the net.
        + rally("P", "/game_0/rally_1", [("shot_p2", serve_1), ("bounce_p2", ball(0.5)), ("bounce_p1", ball(-0.5)),
                                         ("shot_p1", ball(-1.5)), ("net", ball(0.0)), ("bounce_p2", c),
                                         ("shot_p2", return_c), ("net", ball(0.0))])
        # The robot's return goes out: no incoming ball.
        + rally("P", "/game_0/rally_2", [("shot_p2", serve_2), ("bounce_p2", ball(0.5)), ("bounce_p1", ball(-0.5)),
                                         ("shot_p1", ball(-1.5))])
        # The robot serves; the ball bounces twice on the human's half: a miss.
        + rally("P", "/game_0/rally_3", [("shot_p1", ball(-1.4)), ("bounce_p1", ball(-0.5)), ("bounce_p2", d),
                                         ("bounce_p2", ball(1.3))])
        # The robot's return bounces on its own half first (a fault): no incoming ball.
        + rally("P", "/game_0/rally_4", [("shot_p2", serve_3), ("bounce_p2", ball(0.5)), ("bounce_p1", ball(-0.5)),
                                         ("shot_p1", ball(-1.5)), ("bounce_p1", ball(-0.3)), ("bounce_p2", ball(0.4))])
        # Another player: a return that touches the net and lands.
        + rally("Q", "/game_0/rally_0", [("shot_p1", ball(-1.4)), ("bounce_p1", ball(-0.5)), ("bounce_p2", z),
                                         ("shot_p2", return_z), ("net", ball(0.0)), ("bounce_p1", ball(-0.4))])
    )
    return events, dict(a=a, b=b, c=c, d=d, z=z, return_a=return_a, return_c=return_c, return_z=return_z,
                        serves=[serve_1, serve_2, serve_3])


def test_extraction_finds_the_incoming_balls_returns_misses_and_serves():
    events, s = hand_built_events()
    dut = human_responses(events, ["P"])
    np.testing.assert_array_equal(dut.incoming, [s["a"], s["b"], s["c"], s["d"]])
    np.testing.assert_array_equal(dut.returned, [True, False, True, False])
    np.testing.assert_array_equal(dut.returns[[0, 2]], [s["return_a"], s["return_c"]])
    assert np.all(np.isnan(dut.returns[[1, 3]]))
    np.testing.assert_allclose(dut.hit_delays[[0, 2]], [0.1, 0.1])
    np.testing.assert_array_equal(dut.return_landed, [True, False, False, False])
    # Return a landed at x = -0.6, y = 0, 0.1 s after the hit; the others did not land.
    np.testing.assert_allclose(dut.return_landings[0], [-0.6, 0.0, 0.1])
    assert np.all(np.isnan(dut.return_landings[1:]))
    np.testing.assert_array_equal(dut.robot_serve, [True, False, False, True])
    np.testing.assert_array_equal(dut.via_net, [False, False, True, False])
    np.testing.assert_array_equal(dut.serves, s["serves"])
    assert dut.return_rate == 0.5

    everyone = human_responses(events)
    assert len(everyone) == 5 and list(everyone.players).count("Q") == 1
    q = everyone.of_players(["Q"])
    np.testing.assert_array_equal(q.returns, [s["return_z"]])
    assert q.return_landed.tolist() == [True] and len(q.serves) == 0
    np.testing.assert_allclose(q.return_landings, [[-0.4, 0.0, 0.2]])  # after a net touch


def test_unknown_player_raises_naming_the_recorded_players(tmp_path):
    events, _ = hand_built_events()
    with pytest.raises(InputError, match=r"'Elite X'.*\['P', 'Q'\]"):
        OpponentModel.fit(events, ["Elite X"])
    path = tmp_path / "match.csv"
    path.write_text(HEADER + "\n".join(
        f"{e.player},{e.rally}/event{i},{e.type},{e.time},"
        + ",".join("[ " + " ".join(repr(float(v)) for v in e.state[j:j + 3]) + " ]" for j in (0, 3, 6))
        for i, e in enumerate(events, start=1)) + "\n")
    with pytest.raises(InputError, match=r"match\.csv.*'Elite X'.*\['P', 'Q'\]"):
        OpponentModel.from_match_data(path, players=("Elite X",))
    from_file = OpponentModel.from_match_data(path, players=("P",))
    np.testing.assert_array_equal(from_file.data.incoming, human_responses(events, ["P"]).incoming)
    assert set(opponent_model.profiles(path)) == {"P", "Q"}


# ------------------------------------------------------------------------------ the model


def test_return_probability_is_the_smoothed_neighbour_count():
    """Three balls along y, the middle one missed; k = 2, m = 1: p0 = (2 + 1) / (3 + 2) = 0.6."""
    incoming = [ball(y=-0.5), ball(y=0.0), ball(y=0.5)]
    dut = OpponentModel.fit(planted_events(incoming, [True, False, True]), params=OpponentParams(k=2, prior_weight=1.0))
    assert dut.overall_return_rate == pytest.approx(0.6)
    # At y = -0.6 the two nearest are y = -0.5 (returned) and y = 0 (missed): (1 + 0.6) / 3.
    np.testing.assert_allclose(dut.return_probability(np.array([ball(y=-0.6), ball(y=0.6)])), [1.6 / 3, 1.6 / 3])


def test_return_probability_follows_a_planted_dependence():
    """Balls to the human's left (y < 0) missed, to the right returned, otherwise identical."""
    y = np.linspace(-0.7, 0.7, 60)
    dut = OpponentModel.fit(planted_events([ball(y=v) for v in y], y > 0.0))
    probability = dut.return_probability(np.array([ball(y=v) for v in np.linspace(-0.6, 0.6, 13)]))
    assert np.all(np.diff(probability) >= 0.0)
    assert probability[0] < 0.2 and probability[-1] > 0.8


def test_the_reaction_limit_refuses_balls_faster_than_any_returned():
    speeds = np.linspace(2.0, 6.0, 30)
    returned = np.arange(30) != 5  # one slow ball missed
    dut = OpponentModel.fit(planted_events([ball(v_x=v, v_z=0.0) for v in speeds], returned))
    assert dut.max_return_speed == pytest.approx(6.0)
    probability = dut.return_probability(np.array([ball(v_x=5.9, v_z=0.0), ball(v_x=6.1, v_z=0.0)]))
    assert probability[0] > 0.9 and probability[1] == 0.0
    too_fast = ball(v_x=6.1, v_z=0.0)
    assert all(dut.sample_return(too_fast, np.random.default_rng(seed)) is None for seed in range(20))


def test_a_sampled_return_is_a_neighbours_recorded_return():
    """Without jitter, the return of a ball near the planted ones is the recorded return of one of
    its k nearest returned neighbours, and its hit delay comes with it."""
    y = np.linspace(-0.7, 0.7, 30)
    returns = [ball(1.6, y=v, v_x=-9.0) for v in y]
    dut = OpponentModel.fit(planted_events([ball(y=v) for v in y], np.ones(30, bool), returns),
                            params=dataclasses.replace(NO_JITTER, k=3))
    states, hit_delays = dut.draw_returns(np.array([ball(y=0.0)] * 50), np.random.default_rng(0))
    nearest_three = np.argsort(np.abs(y))[:3]
    assert {round(v, 9) for v in states[:, 1]} == {round(y[i], 9) for i in nearest_three}
    np.testing.assert_array_equal(states[:, [0, 3]], np.tile([1.6, -9.0], (50, 1)))
    np.testing.assert_allclose(hit_delays, 0.1)


def test_sampling_is_reproducible_with_a_seeded_rng():
    y = np.linspace(-0.7, 0.7, 40)
    dut = OpponentModel.fit(planted_events([ball(y=v) for v in y], np.abs(y) < 0.5))
    incoming = np.array([ball(y=v) for v in np.linspace(-0.7, 0.7, 25)])
    first, again = (dut.sample_returns(incoming, np.random.default_rng(3)) for _ in range(2))
    np.testing.assert_array_equal(first.returned, again.returned)
    np.testing.assert_array_equal(first.states, again.states)
    other = dut.sample_returns(incoming, np.random.default_rng(4))
    assert not np.array_equal(first.states, other.states, equal_nan=True)
    assert np.all(np.isnan(first.states[~first.returned])) and np.all(np.isfinite(first.states[first.returned]))
    events, s = hand_built_events()
    serving = OpponentModel.fit(events, ["P"])
    serve = serving.sample_serve(np.random.default_rng(5))
    np.testing.assert_array_equal(serve, serving.sample_serve(np.random.default_rng(5)))
    assert np.min(np.abs(serve - np.array(s["serves"])).max(axis=1)) < 5 * serving.params.spin_jitter


def test_a_player_without_serves_or_returns_is_refused():
    events, _ = hand_built_events()
    with pytest.raises(OpponentModelError, match="no serves"):
        OpponentModel.fit(events, ["Q"]).sample_serve(np.random.default_rng(0))
    with pytest.raises(OpponentModelError, match="no recorded returns"):
        OpponentModel.fit(planted_events([ball()], [False]))
    with pytest.raises(OpponentModelError, match="k must be >= 1"):
        OpponentParams(k=0)


def test_ball_at_hit_flies_the_incoming_ball_for_the_hit_delay():
    incoming = np.array([ball(0.9, v_x=5.0, v_z=2.0), ball(1.1, y=0.3, v_x=7.0, v_z=1.5)])
    physics = BallPhysicsParams()
    flight = simulate(incoming, physics, 0.2)
    at_hit = opponent_model.ball_at_hit(incoming, [0.2, 0.1005], physics)
    np.testing.assert_allclose(at_hit[0], flight.final_state[0], atol=1e-9)
    # Half way between the 1 ms steps at 100 and 101 ms: the mean of the two states.
    np.testing.assert_allclose(at_hit[1], flight.states[[100, 101], 1].mean(axis=0), atol=1e-9)
    np.testing.assert_allclose(opponent_model.ball_at_hit(incoming, 0.0, physics), incoming)


def test_a_return_struck_from_elsewhere_lands_where_it_was_recorded_landing():
    """``retarget_returns``: returns struck 10-20 cm away from where they were recorded land (ball
    model, table and net included) within 2 mm of the recorded landing point, at its time, with
    their spin kept; a return with no recorded landing keeps its velocity."""
    physics = BallPhysicsParams()
    recorded = np.array([ball(1.6, 0.2, v_x=-9.0, v_y=-1.0, v_z=1.5, w_y=-150.0), ball(1.8, -0.3, v_x=-7.0, v_y=0.8, v_z=2.2, w_y=60.0, w_z=40.0),
                         ball(1.5, 0.0, v_x=-8.0, v_z=1.0)])
    recorded[:, 2] = [0.25, 0.30, 0.20]
    landings = np.array([[-0.8, -0.1, 0.40], [-0.5, 0.2, 0.55], [np.nan, np.nan, np.nan]])
    moved = recorded[:, :3] + np.array([[0.15, -0.1, -0.05], [-0.2, 0.1, 0.08], [0.1, 0.1, 0.0]])
    out = opponent_model.retarget_returns(recorded, moved, physics, landings)
    np.testing.assert_array_equal(out[:, :3], moved)
    np.testing.assert_array_equal(out[:, 6:], recorded[:, 6:])
    points, times = opponent_model.first_landings(out[:2], physics)
    np.testing.assert_allclose(points, landings[:2, :2], atol=2e-3)
    np.testing.assert_allclose(times, landings[:2, 2], atol=2e-3)
    np.testing.assert_array_equal(out[2, 3:6], recorded[2, 3:6])


def test_wilson_interval_matches_hand_worked_values():
    z2 = opponent_model.WILSON_Z**2
    assert opponent_model.wilson_interval(0, 10) == pytest.approx((0.0, z2 / (10 + z2)))
    assert opponent_model.wilson_interval(5, 10) == pytest.approx((0.2366, 0.7634), abs=1e-4)


# ------------------------------------------------------------------------------ the recorded matches


@pytest.fixture(scope="module")
def elite_profiles():
    return opponent_model.profiles(DATA)


@needs_data
def test_every_recorded_player_has_a_profile(elite_profiles):
    assert list(elite_profiles) == [f"Elite {c}" for c in "ABCDE"]
    counts = {player: (len(m.data), int(m.data.returned.sum()), len(m.data.serves)) for player, m in elite_profiles.items()}
    assert counts == {"Elite A": (117, 114, 27), "Elite B": (73, 73, 15), "Elite C": (101, 99, 24),
                      "Elite D": (117, 110, 28), "Elite E": (128, 126, 21)}
    for model in elite_profiles.values():
        assert 0.9 < model.overall_return_rate < 1.0 and 8.0 < model.max_return_speed < 11.0


@needs_data
def test_held_out_players_are_predicted_within_their_interval():
    """Fit on Elite A-C, test on D-E (245 incoming balls, 236 returned, Wilson 95% [0.932, 0.981];
    the model predicts 0.975 on average)."""
    report = opponent_model.heldout_check(DATA, ["Elite A", "Elite B", "Elite C"], ["Elite D", "Elite E"], np.random.default_rng(0))
    rate = report["return_rate"]
    assert report["n_test_incoming"] == 245 and report["n_test_returned"] == 236
    assert rate["wilson_95"][0] <= rate["predicted_mean"] <= rate["wilson_95"][1]
    speed = report["returns"]["speed"]
    assert speed["sampled_median"] == pytest.approx(speed["recorded_median"], rel=0.15)
