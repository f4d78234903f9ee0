"""The hit predictor shared by the returner and the observation's ``hit_prediction`` part."""

import numpy as np
import pytest

from ace_drake.analysis.scripted_swing import INCOMING_BALL
from ace_drake.config import MODELS_DIR
from ace_drake.contracts import HIT_PREDICTION_SIZE
from ace_drake.control.hit_prediction import HitPredictor, joint_lag
from ace_drake.control.params import ControlParams, ReturnerParams
from ace_drake.physics.params import BallPhysicsParams
from ace_drake.physics.propagate import ContactKind, simulate
from ace_drake.robot.model import load_scenario

PARAMS = BallPhysicsParams()


@pytest.fixture(scope="module")
def predictor():
    return HitPredictor.for_robot(load_scenario(MODELS_DIR / "scenario.yaml"), ControlParams(), PARAMS)


def test_the_predictor_takes_segment_lead_and_lag_from_the_robot(predictor):
    scenario = load_scenario(MODELS_DIR / "scenario.yaml")
    assert predictor.segment == pytest.approx(ControlParams().segment_samples * scenario.dynamics.command_period)
    assert predictor.lead == ControlParams().observation_lead
    assert predictor.lag == pytest.approx(joint_lag(scenario)) and 0.0 < predictor.lag < 0.02
    assert HitPredictor.for_robot(scenario, ControlParams(), PARAMS, ReturnerParams(joint_lag=0.01)).lag == 0.01
    with pytest.raises(ValueError, match="lead < segment"):
        HitPredictor(PARAMS, ReturnerParams(), 0.032, 0.04, 0.0)


def test_the_preferred_hit_is_after_the_bounce_in_the_window_nearest_its_top(predictor):
    estimate = simulate(INCOMING_BALL, PARAMS, 0.1).final_state[0]
    time, state = predictor.preferred_hit(estimate)
    # A hit instant: lead + lag + k T after the observation.
    k = (time - predictor.lead - predictor.lag) / predictor.segment
    assert k == pytest.approx(round(k), abs=1e-9) and round(k) >= 0
    # The predicted state is the ball's (a finer simulation of the same flight: the prediction
    # takes one RK4 step per segment) ...
    truth = simulate(estimate, PARAMS, time, dt=0.001).final_state[0]
    np.testing.assert_allclose(state[:3], truth[:3], atol=5e-3)
    np.testing.assert_allclose(state[3:6], truth[3:6], atol=5e-2)
    # ... after the bounce on the robot's half, within the hit window, and within half a segment
    # of the top of the bounce.
    bounce = simulate(estimate, PARAMS, 1.0, stop_on=(ContactKind.TABLE,)).stop_events[0]
    assert bounce.state_pre[0] < 0.0 and time > bounce.time
    window = ReturnerParams()
    assert window.hit_height_min <= state[2] <= window.hit_height_max and state[3] < 0.0
    flight = simulate(estimate, PARAMS, 1.0, dt=0.001)
    after = flight.times > bounce.time
    apex = flight.times[after][np.argmax(flight.states[after, 0, 2])]
    assert abs(time - apex) <= 0.5 * predictor.segment + 1e-9
    # Later along the same flight, the same hit instant (on the ball's clock) stays preferred.
    later_time, _ = predictor.preferred_hit(simulate(INCOMING_BALL, PARAMS, 0.1 + predictor.segment).final_state[0])
    assert later_time == pytest.approx(time - predictor.segment, abs=1e-9)


def test_the_features_are_the_preferred_hit_or_zeros(predictor):
    estimate = simulate(INCOMING_BALL, PARAMS, 0.1).final_state[0]
    features = predictor.features(estimate, valid=True)
    time, state = predictor.preferred_hit(estimate)
    assert features.shape == (HIT_PREDICTION_SIZE,)
    np.testing.assert_array_equal(features, np.concatenate([[1.0, time], state]))
    np.testing.assert_array_equal(predictor.features(estimate, valid=False), np.zeros(HIT_PREDICTION_SIZE))
    going_away = estimate * np.r_[1, 1, 1, -1, 1, 1, 1, 1, 1]  # v_x > 0: after the robot's hit
    np.testing.assert_array_equal(predictor.features(going_away, valid=True), np.zeros(HIT_PREDICTION_SIZE))
    # A ball that lands long (no bounce on the robot's half) has no hit.
    long_ball = np.array([1.0, 0.0, 0.4, -12.0, 0.0, 1.0, 0.0, 0.0, 0.0])
    assert predictor.preferred_hit(long_ball) is None


def test_a_kept_hit_comes_first_while_it_is_a_candidate(predictor):
    estimate = simulate(INCOMING_BALL, PARAMS, 0.1).final_state[0]
    time, state = predictor.preferred_hit(estimate)
    later = time + predictor.segment  # the next segment boundary: a hit too, just past the top
    kept_time, kept_state = predictor.preferred_hit(estimate, keep=later)
    assert kept_time == pytest.approx(later, abs=1e-9) and kept_state[2] < state[2] + 0.05
    np.testing.assert_array_equal(predictor.features(estimate, True, keep=later), np.concatenate([[1.0, kept_time], kept_state]))
    # A kept time that is no candidate (between boundaries, or past the ball's reach) changes nothing.
    for keep in (time + 0.5 * predictor.segment, 5.0, None):
        assert predictor.preferred_hit(estimate, keep=keep)[0] == time
