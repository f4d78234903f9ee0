"""Terminal rewards (paper eq. (10)) on constructed episode results, checked by hand."""

import math

import numpy as np
import pytest

from ace_drake.config import ConfigError
from ace_drake.contracts import EpisodeResult, Outcome
from ace_drake.learning.params import RewardParams
from ace_drake.learning.rewards import position_term, return_reward, terminal_reward, travel_frame_spin
from ace_drake.physics.flight import make_state
from ace_drake.physics.propagate import ContactEvent, ContactKind

PARAMS = RewardParams()
INCOMING = make_state((1.0, 0.0, 0.2), (-6.0, 0.0, -1.0), (0.0, 0.0, 0.0))


def event(kind, time, state):
    return ContactEvent(kind, time, np.asarray(state, dtype=float), np.asarray(state, dtype=float))


BOUNCE = event(ContactKind.TABLE, 0.45, make_state((-0.8, 0.0, 0.02), (-5.0, 0.0, -2.0), (0.0, 0.0, 0.0)))
HIT = event(ContactKind.RACKET, 0.6, make_state((-1.8, 0.0, 0.25), (-4.0, 0.0, 1.0), (0.0, 0.0, 0.0)))


def returned(landing_state):
    landing = event(ContactKind.TABLE, 1.0, landing_state)
    return EpisodeResult(Outcome.RETURNED, "", BOUNCE, HIT, landing)


def test_topspin_is_positive_whichever_way_the_ball_flies():
    # Flying +x, spin about +y turns the top towards +x: topspin.
    assert travel_frame_spin(make_state((0, 0, 0), (5.0, 0.0, -1.0), (0.0, 300.0, 0.0))) == pytest.approx(300.0)
    # Flying -x, the same topspin is about -y.
    assert travel_frame_spin(make_state((0, 0, 0), (-5.0, 0.0, -1.0), (0.0, -300.0, 0.0))) == pytest.approx(300.0)
    # Flying diagonally with backspin about the horizontal axis across the flight; side spin (about
    # z) and corkscrew (about the heading) do not count.
    heading = np.array([3.0, 4.0, 0.0]) / 5.0
    across = np.cross([0.0, 0.0, 1.0], heading)
    w = -200.0 * across + 50.0 * np.array([0.0, 0.0, 1.0]) + 70.0 * heading
    assert travel_frame_spin(make_state((0, 0, 0), 6.0 * heading + [0, 0, -2.0], w)) == pytest.approx(-200.0)
    # No horizontal velocity: no travel frame, no spin term.
    assert travel_frame_spin(make_state((0, 0, 0), (0.0, 0.0, -3.0), (0.0, 100.0, 0.0))) == 0.0


def test_topspin_is_unchanged_by_the_mirror_across_the_xz_plane():
    state = make_state((0.5, 0.3, 0.02), (4.0, -1.5, -2.0), (30.0, 250.0, -40.0))
    mirrored = state * np.array([1, -1, 1, 1, -1, 1, -1, 1, -1])  # positions, velocities; spin a pseudovector
    assert travel_frame_spin(mirrored) == pytest.approx(travel_frame_spin(state))


def test_position_term_by_hand():
    assert position_term(0.2, 0.2, PARAMS) == PARAMS.position_reward
    assert position_term(0.5, 0.2, PARAMS) == pytest.approx(PARAMS.position_reward * math.exp(-0.3 / PARAMS.position_length))
    assert position_term(-0.1, 0.2, PARAMS) == pytest.approx(position_term(0.5, 0.2, PARAMS))


def test_return_reward_weights_position_and_spin_by_the_skill():
    params = RewardParams(return_base=1.0, position_reward=2.0, position_length=0.5, spin_gain=0.01)
    landing = make_state((0.9, 0.4, 0.02), (5.0, 0.0, -2.0), (0.0, 100.0, 0.0))  # topspin 100 rad/s
    result = returned(landing)
    # w_p = 1, w_s = 0: base + position.
    assert terminal_reward(result, (0.4, 1.0, 0.0), params) == pytest.approx(3.0)
    assert terminal_reward(result, (-0.1, 1.0, 0.0), params) == pytest.approx(1.0 + 2.0 * math.exp(-1.0))
    # w_p = 0.5, w_s = +1 (topspin wanted): base + half the position term + 0.01 * 100.
    assert terminal_reward(result, (0.4, 0.5, 1.0), params) == pytest.approx(1.0 + 1.0 + 1.0)
    # w_s = -1 (backspin wanted) and no position weight: topspin is penalised.
    assert terminal_reward(result, (0.4, 0.0, -1.0), params) == pytest.approx(0.0)
    # Batches: (n, 9) landings with (n, 3) skills.
    batch = return_reward(np.stack([landing, landing]), np.array([[0.4, 1.0, 0.0], [0.4, 0.0, -1.0]]), params)
    np.testing.assert_allclose(batch, [3.0, 0.0])


def test_miss_hit_collision_and_invalid():
    skill = (0.0, 1.0, 1.0)
    missed = EpisodeResult(Outcome.MISSED, "not hit", BOUNCE)
    assert terminal_reward(missed, skill, PARAMS) == PARAMS.miss
    not_returned = EpisodeResult(Outcome.NOT_RETURNED, "the return missed the table", BOUNCE, HIT)
    assert terminal_reward(not_returned, skill, PARAMS) == PARAMS.hit
    params = RewardParams(collision=-3.0)
    assert terminal_reward(EpisodeResult(Outcome.IN_PLAY, "", BOUNCE), skill, params, collided=True) == -3.0
    assert terminal_reward(EpisodeResult(Outcome.INVALID, "fault"), skill, PARAMS) == PARAMS.invalid
    with pytest.raises(ValueError, match="still in play"):
        terminal_reward(EpisodeResult(Outcome.IN_PLAY, "", BOUNCE), skill, PARAMS)
    # The defaults order the outcomes: a miss < a hit < the base of a return.
    assert PARAMS.miss < PARAMS.hit < PARAMS.return_base


def test_bad_reward_params_name_the_field():
    with pytest.raises(ConfigError, match="position_length"):
        RewardParams(position_length=0.0)
