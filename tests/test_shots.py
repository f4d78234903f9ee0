"""The incoming-shot distribution (play/shots.py) and the Launcher opponent (play/opponent.py)."""

from pathlib import Path

import numpy as np
import pytest

from ace_drake.config import ConfigError, from_dict
from ace_drake.match_data import MatchDataError
from ace_drake.physics.flight import make_state
from ace_drake.physics.params import BallPhysicsParams
from ace_drake.physics.propagate import ContactKind, simulate
from ace_drake.play import shots
from ace_drake.play.opponent import Launcher
from ace_drake.play.params import ShotParams

DATA = Path(__file__).resolve().parents[2] / "shared/data/ace_match_events_elite.csv"
MISSING_DATA = f"recorded match data not found at {DATA} (../shared/data beside the repository)"
needs_data = pytest.mark.skipif(not DATA.is_file(), reason=MISSING_DATA)

HEADER = "player_id,rally_id,type,timestamp,ball_pos,ball_vel_out,ball_spin_out\n"


@pytest.fixture(scope="module")
def synthetic():
    return shots.synthetic_distribution(seed=0, candidates=1000)


@pytest.fixture(scope="module")
def synthetic_sample(synthetic):
    return synthetic.draw(np.random.default_rng(1), 600)


@pytest.fixture(scope="module")
def small_synthetic():
    return shots.synthetic_distribution(seed=3, candidates=200)


@pytest.fixture(scope="module")
def human():
    if not DATA.is_file():
        pytest.skip(MISSING_DATA)
    return shots.make_distribution(ShotParams(source=str(DATA), serve_fraction=0.4, bandwidth=0.5))


def speed_and_spin(states):
    """Mean speed (m/s) and mean spin rate (rad/s) of (n, 9) states."""
    return np.linalg.norm(states[:, 3:6], axis=1).mean(), np.linalg.norm(states[:, 6:9], axis=1).mean()


def test_valid_shots_by_hand():
    return_shot = make_state((1.6, 0.25, 0.25), (-6.0, -0.3, 2.2), (0.0, -80.0, 0.0))  # lands at x = -0.64 m
    serve = make_state((1.6, 0.0, 0.25), (-5.0, 0.0, -1.5), (0.0, 100.0, 0.0))  # bounces at x = 1.02, then -0.40 m
    long = make_state((1.6, 0.0, 0.25), (-12.0, 0.0, 3.0))  # over the robot's end line, onto the floor
    into_net = make_state((1.0, 0.0, 0.12), (-10.0, 0.0, 0.3))  # net, then back onto the human's half
    on_robot_side = make_state((-0.5, 0.0, 0.3), (-3.0, 0.0, 0.0))  # starts on the wrong side of the net
    states = np.stack([return_shot, serve, long, into_net, on_robot_side])
    np.testing.assert_array_equal(shots.valid_shots(states, serve=False), [True, False, False, False, False])
    np.testing.assert_array_equal(shots.valid_shots(states, serve=True), [False, True, False, False, False])


def test_serves_and_returns_mix_three_to_seven(synthetic_sample):
    n = len(synthetic_sample.serve)
    # 4 standard deviations of Binomial(600, 0.3): 45 serves.
    assert abs(synthetic_sample.serve.sum() - 0.3 * n) < 4 * np.sqrt(n * 0.3 * 0.7)
    assert 0.3 < synthetic_sample.acceptance_rate <= 1.0


def test_serve_fraction_zero_and_one(synthetic):
    rng = np.random.default_rng(2)
    only_returns = shots.ShotDistribution(synthetic.serves, synthetic.returns, serve_fraction=0.0)
    only_serves = shots.ShotDistribution(synthetic.serves, synthetic.returns, serve_fraction=1.0)
    assert not only_returns.draw(rng, 20).serve.any()
    assert only_serves.draw(rng, 20).serve.all()


def test_every_sampled_shot_lands_on_the_robots_half(synthetic_sample):
    """Re-simulated to the floor, independently of valid_shots: a return's first table contact is
    on the robot's half, a serve's first on the human's and its second on the robot's."""
    states, serve = synthetic_sample.states[:200], synthetic_sample.serve[:200]
    assert np.all(states[:, 0] > 0.0)
    flight = simulate(states, BallPhysicsParams(), 3.0, stop_on=(ContactKind.FLOOR,), record=False)
    for events, is_serve in zip(flight.events, serve):
        kinds = [e.kind for e in events if e.kind != ContactKind.NET]
        table_x = [e.state_pre[0] for e in events if e.kind == ContactKind.TABLE]
        if is_serve:
            assert kinds[:2] == [ContactKind.TABLE, ContactKind.TABLE]
            assert table_x[0] > 0.0 > table_x[1]
        else:
            assert kinds[0] == ContactKind.TABLE and table_x[0] < 0.0


def test_same_seed_same_shots(synthetic, small_synthetic):
    first = synthetic.draw(np.random.default_rng(7), 20)
    again = synthetic.draw(np.random.default_rng(7), 20)
    np.testing.assert_array_equal(first.states, again.states)
    np.testing.assert_array_equal(first.serve, again.serve)
    assert not np.array_equal(first.states, synthetic.sample(np.random.default_rng(8), 20))
    np.testing.assert_array_equal(small_synthetic.serves, shots.synthetic_distribution(seed=3, candidates=200).serves)


def test_shots_are_validated_ball_by_ball_as_the_batched_reference_validates_them(synthetic, monkeypatch):
    # _contacts_to_next_bounce flies each candidate with the compiled one-ball propagator; the
    # NumPy reference flying the whole batch at once gives the same contacts, so the same shots.
    stop_on = (ContactKind.TABLE, ContactKind.FLOOR)
    compiled = synthetic.draw(np.random.default_rng(21), 300)
    monkeypatch.setattr(shots, "_contacts_to_next_bounce",
                        lambda states, physics: simulate(states, physics, shots.FLIGHT_DURATION, stop_on=stop_on, record=False).events)
    reference = synthetic.draw(np.random.default_rng(21), 300)
    np.testing.assert_array_equal(compiled.states, reference.states)
    np.testing.assert_array_equal(compiled.serve, reference.serve)
    assert compiled.acceptance_rate == reference.acceptance_rate < 1.0  # some candidates were rejected


def test_invalid_synthetic_members_are_excluded(small_synthetic):
    assert 10 < len(small_synthetic.serves) < 200 and 10 < len(small_synthetic.returns) < 200
    assert shots.valid_shots(small_synthetic.serves, serve=True).all()
    assert shots.valid_shots(small_synthetic.returns, serve=False).all()


def test_kde_reproduces_mean_speed_and_spin(synthetic, synthetic_sample):
    """Each KDE draw is a fitted state plus Gaussian kernel noise of covariance factor^2 times the
    data's. With Scott's factor (0.64 for ~400 states in 9-D) that noise raises the mean spin rate
    |w| by 10-25 % (speed, dominated by v_x, hardly moves); with a factor of 0.3 both means hold
    within 5 % (speed) and 8 % (spin)."""
    narrow = shots.ShotDistribution(synthetic.serves, synthetic.returns, bandwidth=0.3).draw(np.random.default_rng(4), 500)
    for drawn, spin_tolerance in ((synthetic_sample, 0.25), (narrow, 0.08)):
        for fitted, states in ((synthetic.serves, drawn.states[drawn.serve]), (synthetic.returns, drawn.states[~drawn.serve])):
            fitted_speed, fitted_spin = speed_and_spin(fitted)
            drawn_speed, drawn_spin = speed_and_spin(states)
            assert drawn_speed == pytest.approx(fitted_speed, rel=0.05)
            assert drawn_spin == pytest.approx(fitted_spin, rel=spin_tolerance)


def test_almost_never_valid_raises():
    rng = np.random.default_rng(0)
    behind_the_robot = rng.uniform([-2.0, -0.5, 0.1, -6, -1, 0, -100, -100, -100], [-1.6, 0.5, 0.3, -4, 1, 2, 100, 100, 100], (50, 9))
    hopeless = shots.ShotDistribution(behind_the_robot, behind_the_robot)
    with pytest.raises(shots.ShotDistributionError, match="valid shots"):
        hopeless.sample(rng, 100)


def test_human_shots_label_first_shot_of_rally_as_serve(tmp_path):
    path = tmp_path / "events.csv"
    path.write_text(
        HEADER
        + "P,/game_0/rally_0/event1,shot_p1,1.0,[-1.8 0 0.2],[5 0 0],[0 0 0]\n"  # the robot serves
        "P,/game_0/rally_0/event2,bounce_p1,1.1,[-1 0 0.02],[5 0 1],[0 0 0]\n"
        "P,/game_0/rally_0/event3,bounce_p2,1.3,[1 0 0.02],[5 0 1],[0 0 0]\n"
        "P,/game_0/rally_0/event4,shot_p2,1.5,[1.8 0 0.2],[-6 0 1],[0 -100 0]\n"
        "P,/game_0/rally_1/event1,shot_p2,3.0,[1.7 0.3 0.2],[-5 0 -1],[0 50 0]\n"  # the human serves
        "P,/game_0/rally_1/event2,shot_p1,3.5,[-1.5 0 0.2],[5 0 1],[0 0 0]\n"
        "P,/game_0/rally_1/event3,shot_p2,4.0,[1.9 0 0.2],[-7 0 1],[0 -200 0]\n"
        "Q,/game_0/rally_1/event1,shot_p2,5.0,[1.6 0 0.2],[-5 0 -1],[0 50 0]\n"  # another player's rally
    )
    states, serve = shots.human_shots(path)
    np.testing.assert_array_equal(serve, [False, True, False, True])
    np.testing.assert_array_equal(states[:, 0], [1.8, 1.7, 1.9, 1.6])
    states, serve = shots.human_shots(path, players=("Q",))  # one player's shots, still counted per rally
    np.testing.assert_array_equal(serve, [True])
    np.testing.assert_array_equal(states[:, 0], [1.6])
    np.testing.assert_array_equal(shots.human_shots(path, players=("P",))[0][:, 0], [1.8, 1.7, 1.9])
    with pytest.raises(MatchDataError, match=r"player\(s\) \['R'\]"):
        shots.human_shots(path, players=("P", "R"))
    # A distribution fitted to P's shots has not seen Q's; one fitted to all or elsewhere, everyone's.
    assert shots.held_out_players(ShotParams(source=str(path), players=("P",)), path) == ("Q",)
    assert shots.held_out_players(ShotParams(source=str(path)), path) == ()
    assert shots.held_out_players(ShotParams(), path) == ()


@needs_data
def test_match_data_builder_finds_the_humans_serves_and_returns(human):
    states, serve = shots.human_shots(DATA)
    assert (serve.sum(), (~serve).sum()) == (115, 522)
    assert (human.serve_fraction, human.bandwidth) == (0.4, 0.5)  # from ShotParams
    # The fit keeps the recorded shots that the ball model confirms as shots.
    assert 80 < len(human.serves) <= 115 and 250 < len(human.returns) <= 522
    sample = human.draw(np.random.default_rng(0), 100)
    assert np.all(np.isfinite(sample.states))
    assert speed_and_spin(sample.states)[0] == pytest.approx(speed_and_spin(np.concatenate([human.serves, human.returns]))[0], rel=0.15)


def test_make_distribution_reads_a_match_file_from_source(tmp_path):
    with pytest.raises(MatchDataError, match="not found"):
        shots.make_distribution(ShotParams(source=str(tmp_path / "absent.csv")))


@pytest.mark.parametrize(
    "field, value",
    [("source", ""), ("players", ("Elite A",)), ("serve_fraction", 1.5), ("serve_fraction", -0.1), ("bandwidth", 0.0), ("bandwidth", float("nan")), ("seed", -1)],
)
def test_bad_shot_params_name_the_field(field, value):
    with pytest.raises(ConfigError, match=field):
        ShotParams(**{field: value})
    with pytest.raises(ConfigError, match=field):
        from_dict(ShotParams, {field: value})


def test_launcher_starts_each_rally_with_a_seeded_shot(synthetic):
    launcher = Launcher(synthetic)
    state, kind = launcher.shot(np.random.default_rng(11))
    assert state.shape == (9,) and kind in ("serve", "return")
    again, again_kind = launcher.shot(np.random.default_rng(11))
    np.testing.assert_array_equal(state, again)
    assert kind == again_kind
    assert shots.valid_shots(state, serve=kind == "serve").all()
