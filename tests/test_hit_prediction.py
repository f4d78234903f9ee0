"""The hit predictor shared by the returner and the observation's ``hit_prediction`` part."""

import numpy as np
import pytest

from ace_drake.analysis.scripted_swing import INCOMING_BALL
from ace_drake.config import MODELS_DIR
from ace_drake.contracts import HIT_PREDICTION_SIZE
from ace_drake.control.hit_prediction import KEEP_TOLERANCE, Flight, HitPredictor, Prediction, joint_lag
from ace_drake.control.params import ControlParams, ReturnerParams
from ace_drake.physics.params import BallPhysicsParams
from ace_drake.physics.flight import rk4_step
from ace_drake.physics.propagate import ContactKind, simulate, simulate_ball
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


def _estimates_along_flights():
    """Estimates of incoming balls before and after their bounce, balls going away, balls that
    hit the net or land long or wide (no bounce on the robot's half), one that drops off the
    table's end, and ones still on the human's side: true states of ``simulate`` flights."""
    shots = np.array([
        INCOMING_BALL,
        [1.4, -0.3, 0.3, -7.0, 0.6, 1.5, -30.0, 60.0, 5.0],     # a topspin return, crossing
        [1.2, 0.2, 0.2, -5.0, -0.2, 2.5, 0.0, -150.0, 0.0],    # backspin, high
        [1.3, 0.0, 0.05, -6.0, 0.0, 0.3, 0.0, 0.0, 0.0],       # into the net
        [1.0, 0.0, 0.4, -12.0, 0.0, 1.0, 0.0, 0.0, 0.0],       # long (past the robot's end)
        [1.2, 0.1, 0.3, -5.0, -4.0, 1.5, 0.0, 0.0, 0.0],       # wide
        [1.3, 0.1, 0.25, -6.5, 0.1, 1.8, 0.0, 0.0, 40.0],      # bounces near the robot's end line
    ])
    flights = simulate(shots, PARAMS, 1.0, dt=0.008)
    rows = [flights.states[k, i] for i in range(len(shots)) for k in range(0, flights.times.size, 3)]
    away = INCOMING_BALL * np.r_[1, 1, 1, -1, 1, 1, 1, 1, 1]
    return np.array(rows + [away, np.array([-1.0, 0.0, 0.1, -3.0, 0.0, -1.0, 0.0, 0.0, 0.0])])


def test_features_batch_is_features_of_each_row(predictor):
    estimates = _estimates_along_flights()
    count = len(estimates)
    rng = np.random.default_rng(0)
    valid = rng.random(count) < 0.85
    estimates[~valid & (rng.random(count) < 0.5)] = np.nan  # invalid rows may hold anything
    # Kept hits: each row's preferred hit, the next boundary, a time between boundaries, or none.
    keep = np.full(count, np.nan)
    preferred = np.array([predictor.features(e, True)[1] if v else np.nan for e, v in zip(estimates, valid)])
    choice = rng.integers(0, 4, count)
    keep[choice == 1] = preferred[choice == 1]
    keep[choice == 2] = preferred[choice == 2] + predictor.segment
    keep[choice == 3] = preferred[choice == 3] + 0.5 * predictor.segment
    reference = np.array([predictor.features(e, v, None if np.isnan(k) else k) for e, v, k in zip(estimates, valid, keep)])
    batch = predictor.features_batch(estimates, valid, keep)
    np.testing.assert_array_equal(batch, reference)  # bit for bit
    # The cases are all there: hits, kept hits that differ from the preferred, no hit.
    assert 20 < reference[:, 0].sum() < count - 20
    assert np.any((choice == 2) & (reference[:, 0] > 0) & (np.abs(reference[:, 1] - preferred) > 1e-3))
    # B = 1 and the empty batch.
    for b in np.flatnonzero(valid)[:5]:
        np.testing.assert_array_equal(predictor.features_batch(estimates[b : b + 1], valid[b : b + 1], keep[b : b + 1])[0], reference[b])
    assert predictor.features_batch(np.zeros((0, 9)), np.zeros(0, bool), np.zeros(0)).shape == (0, HIT_PREDICTION_SIZE)
    with pytest.raises(ValueError, match=r"\(B, 9\)"):
        predictor.features_batch(np.zeros(9), np.ones(1, bool), np.zeros(1))
    # A valid row that cannot be predicted is named with its numbers.
    broken = estimates[np.flatnonzero(valid)[:3]].copy()
    broken[1, 6] = np.inf
    with pytest.raises(ValueError, match=r"NaN or inf \(environment 1: estimate \[.*inf.*\], kept hit none\)"):
        predictor.features_batch(broken, np.ones(3, bool), np.full(3, np.nan))


def reference_bounce_behind(predictor, estimate, horizon=1.0, dt=0.02):
    """``HitPredictor.bounce_behind`` in Python on ``rk4_step``: the reference the compiled one equals."""
    table, radius = predictor.physics.table, predictor.physics.aero.ball_radius
    state = np.asarray(estimate, dtype=float)
    for step in range(1, int(round(horizon / dt)) + 1):
        before, state = state, rk4_step(state, -dt, predictor.physics.aero)
        if state[0] > 0.0:
            return None  # back over the net first: the ball is still to bounce
        if state[2] < radius:
            fraction = (before[2] - radius) / (before[2] - state[2])
            x, y = before[:2] + fraction * (state[:2] - before[:2])
            on_table = -0.5 * table.length <= x <= 0.0 and abs(y) <= 0.5 * table.width
            return -(step - 1 + fraction) * dt if on_table else None
    return None


def reference_predict(predictor, estimate):
    """``HitPredictor.predict`` in Python, its legs by ``simulate_ball``: the reference the
    compiled one equals."""
    params, table = predictor.params, predictor.physics.table
    kinds = (ContactKind.TABLE_PLANE, ContactKind.NET, ContactKind.FLOOR)
    stops = (ContactKind.TABLE_PLANE, ContactKind.FLOOR)
    first_sample = predictor.lead + predictor.lag
    step = predictor.segment / predictor._samples_per_segment
    times, states, contacts = [], [], []
    now, state = 0.0, np.asarray(estimate, dtype=float)
    while True:
        upcoming = first_sample + step * len(times)
        lead_in = upcoming - now
        duration = lead_in + 8 * predictor.segment
        leg = simulate_ball(state, predictor.physics, lead_in, dt=lead_in, kinds=kinds, stop_on=stops) if lead_in > 1e-9 else None
        if leg is None or leg.stop_events[0] is None:
            if leg is not None:
                state, now = leg.final_state[0], upcoming
                contacts += [(now - lead_in + e.time, e.kind, e.state_pre) for e in leg.events[0]]
                times.append(now)
                states.append(state)
            leg = simulate_ball(state, predictor.physics, duration - lead_in, dt=step, kinds=kinds, stop_on=stops)
            offset = now
            stopped = leg.stop_events[0]
            kept = leg.times[1:] if stopped is None else leg.times[1:][leg.times[1:] < stopped.time]
            times.extend(offset + kept)
            states.extend(leg.states[1 : 1 + kept.size, 0])
        else:
            offset, stopped = now, leg.stop_events[0]
        contacts += [(offset + e.time, e.kind, e.state_pre) for e in leg.events[0] if e is not stopped]
        if stopped is not None:
            now = offset + stopped.time
            on_table = abs(stopped.state_pre[0]) <= 0.5 * table.length and abs(stopped.state_pre[1]) <= 0.5 * table.width
            if stopped.kind == ContactKind.TABLE_PLANE and on_table:
                contacts.append((now, ContactKind.TABLE, stopped.state_pre))
                state = stopped.state_post
            elif stopped.kind == ContactKind.TABLE_PLANE:
                kinds, stops = (ContactKind.NET, ContactKind.FLOOR), (ContactKind.FLOOR,)
                state = stopped.state_pre
            else:
                contacts.append((now, stopped.kind, stopped.state_pre))
                break
        else:
            now, state = times[-1], states[-1]
        robot_bounces = sum(kind == ContactKind.TABLE and pre[0] < 0.0 for _, kind, pre in contacts)
        falling_out = robot_bounces >= 1 and state[5] < 0.0 and state[2] < params.hit_height_min
        if robot_bounces >= 2 or state[0] < params.hit_x_min or falling_out or now - first_sample > params.prediction_horizon:
            break
    return Prediction(np.asarray(times), np.asarray(states).reshape(-1, 9), contacts)


def _random_estimates(count, seed):
    """Balls over and around the table, coming or not, with any spin."""
    rng = np.random.default_rng(seed)
    return np.concatenate([rng.uniform([-1.8, -1.0, -0.1], [1.8, 1.0, 0.8], (count, 3)), rng.uniform([-14.0, -4.0, -4.0], [6.0, 4.0, 5.0], (count, 3)),
                           rng.uniform(-400.0, 400.0, (count, 3))], axis=1)


@pytest.mark.parametrize("lead", [0.005, 0.0])
def test_compiled_predict_and_bounce_behind_are_the_python_reference_bit_for_bit(lead):
    # lead 0 with no lag: the first sample is at the observation (no first leg).
    predictor = HitPredictor.for_robot(load_scenario(MODELS_DIR / "scenario.yaml"), ControlParams(), PARAMS)
    if lead == 0.0:
        predictor = HitPredictor(PARAMS, ReturnerParams(), predictor.segment, 0.0, 0.0)
    kinds, past_the_table, bounces = set(), 0, 0
    for estimate in np.concatenate([_estimates_along_flights(), _random_estimates(300, 3)]):
        expected, actual = reference_predict(predictor, estimate), predictor.predict(estimate)
        np.testing.assert_array_equal(actual.times, expected.times)
        np.testing.assert_array_equal(actual.states, expected.states)
        assert [(t, k) for t, k, _ in actual.contacts] == [(t, k) for t, k, _ in expected.contacts]
        assert all(type(t) is float and type(k) is ContactKind for t, k, _ in actual.contacts)
        for (_, _, a), (_, _, b) in zip(actual.contacts, expected.contacts):
            np.testing.assert_array_equal(a, b)
        kinds |= {k for _, k, _ in expected.contacts}
        robot_bounce = any(k == ContactKind.TABLE and pre[0] < 0.0 for _, k, pre in expected.contacts)
        past_the_table += not robot_bounce and any(k == ContactKind.FLOOR for _, k, _ in expected.contacts)
        behind = reference_bounce_behind(predictor, estimate)
        assert predictor.bounce_behind(estimate) == behind
        bounces += behind is not None
    assert {ContactKind.TABLE, ContactKind.NET, ContactKind.FLOOR} <= kinds and past_the_table > 0 and bounces > 10
    with pytest.raises(ValueError, match="NaN"):
        predictor.predict(np.full(9, np.nan))


def reference_candidates(predictor, flight, prediction, include_current=False, keep=None):
    """``HitPredictor.candidates`` with its ranking in NumPy: the reference the compiled ranking
    (``_hit_order``) equals."""
    params = predictor.params
    window = predictor.bounce_window(flight, prediction)  # the bounce and the contact after it: not part of the ranking
    if window is None:
        return []
    bounce, end = window
    times, states = prediction.times, prediction.states
    first = 0 if include_current else predictor._samples_per_segment
    index = np.arange(first, len(times), predictor._samples_per_segment)
    index = index[(times[index] > bounce) & (times[index] < end)]
    z, x = states[index, 2], states[index, 0]
    index = index[(z >= params.hit_height_min) & (z <= params.hit_height_max) & (x >= params.hit_x_min) & (states[index, 3] < 0.0)]
    if index.size == 0:
        return []
    after_bounce = np.flatnonzero((times > bounce) & (times < end))
    apex = times[after_bounce[np.argmax(states[after_bounce, 2])]]
    order = sorted(index, key=lambda i: abs(times[i] - apex))
    if keep is not None:
        kept = [i for i in order if abs(times[i] - keep) < KEEP_TOLERANCE]
        order = kept + [i for i in order if i not in kept]
    return order


def test_candidates_are_the_numpy_reference(predictor):
    # Fresh and remembered bounces (re-timed, behind, too far ahead), with and without the
    # current segment, kept hits on a candidate, off the grid, or none; a half-segment predictor
    # (samples between the boundaries).
    half = HitPredictor(PARAMS, ReturnerParams(prediction_step=0.016), predictor.segment, predictor.lead, predictor.lag)
    rng = np.random.default_rng(5)
    ranked = 0
    for dut in (predictor, half):
        for estimate in np.concatenate([_estimates_along_flights(), _random_estimates(100, 4)]):
            prediction = dut.predict(estimate)
            bounce = dut.bounce_behind(estimate)
            for include_current in (False, True):
                for bounce_time in (bounce, 0.004, -0.2, 0.3, None):
                    clock = float(rng.choice([0.0, 0.032]))
                    preferred = dut.candidates(Flight(clock=clock, bounce_time=bounce_time), prediction, include_current)
                    keeps = [None, 0.5 * dut.segment] + ([float(prediction.times[preferred[-1]])] if preferred else [])
                    for keep in keeps:
                        mine, theirs = Flight(clock=clock, bounce_time=bounce_time), Flight(clock=clock, bounce_time=bounce_time)
                        actual = dut.candidates(mine, prediction, include_current, keep)
                        expected = reference_candidates(dut, theirs, prediction, include_current, keep)
                        assert actual == expected and mine == theirs
                        assert all(type(i) is np.int64 for i in actual)
                        ranked += len(actual) > 1 and keep is not None and actual[0] != preferred[0]
    assert ranked > 20
