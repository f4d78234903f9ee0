"""The selectable drag and Magnus models of eq. (1) (``AeroParams.drag_model``, ``magnus_model``):
hand-worked coefficients, continuity in spin, configs, and every compiled user of the flight
constants (hit prediction, EKF) running the selected models."""

import dataclasses

import numpy as np
import pytest

from ace_drake.config import ConfigError, from_dict
from ace_drake.control.hit_prediction import _PREDICTION_KINDS, HitPredictor
from ace_drake.control.params import ReturnerParams
from ace_drake.perception import ekf_kernels
from ace_drake.perception.ball_ekf import BallEkf
from ace_drake.physics.flight import (
    FLIGHT_CONSTANT_COUNT,
    REFINED_MAGNUS,
    SPIN_RATIO_DRAG,
    drag_coefficient,
    flight_acceleration,
    flight_constants,
    magnus_coefficient,
    make_state,
)
from ace_drake.physics.params import AeroParams, BallPhysicsParams, load_ball_params
from ace_drake.physics.propagate import ContactKind, simulate, simulate_ball

SPIN_RATIO = AeroParams(drag_model="spin_ratio")
REFINED = AeroParams(magnus_model="refined")
BOTH = AeroParams(drag_model="spin_ratio", magnus_model="refined")
MODELS = [AeroParams(), SPIN_RATIO, REFINED, BOTH]
MODEL_IDS = ["constant-ratio", "spin_ratio-ratio", "constant-refined", "spin_ratio-refined"]
R = AeroParams().ball_radius
DENSITY_RATIO = 1.204 / 81.2


def spin_for_ratio(speed, spin_ratio):
    """|w| (rad/s) giving the spin ratio S = |w| r / |v|."""
    return spin_ratio * speed / R


# ---------------------------------------------------------------------------------- drag


@pytest.mark.parametrize("speed, spin_ratio, expected", [
    (7.5, 0.75, 0.55),  # the 7.5 m/s curve's peak, at its breakpoint S_2
    (7.5, 0.2, 0.49),  # below S_1: the first value
    (7.5, 1.5, 0.53),  # beyond S_4: the last value
    (7.5, 0.925, 0.515),  # midway between S_2 = 0.75 (0.55) and S_3 = 1.1 (0.48)
    (10.0, 0.2, 0.48),  # midway between the 7.5 and 12.5 m/s curves: (0.49 + 0.47) / 2
    # At 10 m/s the blended curve has S_1 = 0.4, S_2 = 0.685 with values 0.48, 0.54.
    (10.0, 0.5425, 0.51),
    (17.5, 0.84, 0.37),  # the lowest value of the tables
    (30.0, 0.84, 0.37),  # above 17.5 m/s: the 17.5 m/s curve (the authors extrapolate)
    (30.0, 0.5, 0.51),
    (2.0, 0.84, 0.55),  # at or below 2.5 m/s: 0.55
    (12.5, 0.0, 0.47),  # no spin: S = 0
])
def test_spin_ratio_drag_hand_worked(speed, spin_ratio, expected):
    c_d = drag_coefficient(speed, spin_for_ratio(speed, spin_ratio), SPIN_RATIO)
    assert c_d == pytest.approx(expected, abs=1e-12)


def test_spin_ratio_drag_at_rest_and_its_range_and_scale():
    assert drag_coefficient(0.0, 300.0, SPIN_RATIO) == 0.55  # S undefined, no division
    speeds, rates = np.meshgrid(np.linspace(0.0, 40.0, 161), np.linspace(0.0, 1500.0, 151))
    c_d = drag_coefficient(speeds, rates, SPIN_RATIO)
    assert c_d.shape == speeds.shape
    assert c_d.min() == pytest.approx(0.37) and c_d.max() == pytest.approx(0.55)
    # physics-fit scales the table through drag_coefficient (relative to 0.55).
    scaled = drag_coefficient(speeds, rates, dataclasses.replace(SPIN_RATIO, drag_coefficient=0.44))
    np.testing.assert_allclose(scaled, 0.8 * c_d, rtol=1e-15)
    assert drag_coefficient(10.0, 300.0, AeroParams(drag_coefficient=0.44)) == 0.44  # "constant"


def test_spin_ratio_drag_is_continuous_in_speed_and_spin():
    speeds = np.linspace(2.5, 25.0, 4501)
    for spin_ratio in [0.0, 0.45, 0.7, 1.0, 1.25, 3.0]:
        c_d = drag_coefficient(speeds, spin_for_ratio(speeds, spin_ratio), SPIN_RATIO)
        assert np.abs(np.diff(c_d)).max() < 2e-4
    rates = np.linspace(0.0, 1500.0, 15001)
    for speed in [3.0, 7.5, 9.0, 12.5, 16.0, 17.5, 20.0]:
        assert np.abs(np.diff(drag_coefficient(speed, rates, SPIN_RATIO))).max() < 1e-3


# ---------------------------------------------------------------------------------- Magnus


@pytest.mark.parametrize("speed, spin_rate, expected", [
    (7.5, 100.0, -0.000775 * 100 + 0.366),  # linear part, w <= w_break = 350
    (7.5, 400.0, -2.0e-7 * 400**2 + 1.7e-4 * 400 + 0.05875),  # quadratic part
    (9.0, 100.0, -0.0007165 * 100 + 0.3705),  # midway between 7.5 and 10.5 m/s
    (2.0, 100.0, 0.08),
    (1.0, 100.0, 0.08),  # below 2 m/s: the 2 m/s values
    (1.0, 1000.0, 0.0),  # ... (the authors extrapolate) and no negative c_M
    (17.0, 600.0, -0.000448 * 600 + 0.371),
    (30.0, 600.0, -0.000448 * 600 + 0.371),  # above 17 m/s: the 17 m/s values
    (17.0, 3000.0, 0.0),  # -0.9 - ... < 0: clipped
    (12.0, 0.0, 0.379),  # finite at w = 0 (where v x w = 0)
])
def test_refined_magnus_hand_worked(speed, spin_rate, expected):
    assert magnus_coefficient(speed, spin_rate, REFINED) == pytest.approx(expected, abs=1e-12)


def test_refined_magnus_is_nonnegative_and_scaled():
    speeds, rates = np.meshgrid(np.linspace(0.0, 40.0, 161), np.linspace(0.0, 3000.0, 301))
    c_m = magnus_coefficient(speeds, rates, REFINED)
    assert c_m.min() == 0.0 and c_m.max() < 0.4
    doubled = dataclasses.replace(REFINED, magnus_scale=2.0)
    np.testing.assert_array_equal(magnus_coefficient(speeds, rates, doubled), 2.0 * c_m)
    ratio_doubled = AeroParams(magnus_scale=2.0)  # the scale acts on "refined" only
    np.testing.assert_array_equal(magnus_coefficient(speeds, rates, ratio_doubled), magnus_coefficient(speeds, rates, AeroParams()))


# ---------------------------------------------------------------------------------- eq. (1)


def test_flight_acceleration_with_both_models_hand_worked():
    # v = (10, 0, 0), w = (0, 200, 0): S = 200 * 0.02 / 10 = 0.4, on the blended S_1 at 10 m/s:
    # c_d = 0.48. Refined at 10 m/s, 5/6 of the way from 7.5 to 10.5 m/s: w_break = 425 > 200,
    # c_M = m1 w + c1 with m1 = -0.000775 + (5/6) 0.000117, c1 = 0.366 + (5/6) 0.009.
    a = flight_acceleration(np.array([10.0, 0.0, 0.0]), np.array([0.0, 200.0, 0.0]), BOTH)
    c_m = (-0.000775 + 5 / 6 * 0.000117) * 200 + 0.366 + 5 / 6 * 0.009
    assert a[0] == pytest.approx(-3 / (8 * 0.02) * 0.48 * DENSITY_RATIO * 10 * 10, rel=1e-12)
    assert a[1] == 0.0
    assert a[2] == pytest.approx(-c_m * DENSITY_RATIO * 10 * 200 - (1 - DENSITY_RATIO) * 9.81, rel=1e-12)


@pytest.mark.parametrize("aero", MODELS, ids=MODEL_IDS)
def test_trajectory_is_continuous_as_spin_goes_to_zero(aero):
    physics = BallPhysicsParams(aero=aero)
    start = make_state([-1.2, 0.1, 0.25], [6.0, -0.5, 1.0], [0.0, 0.0, 0.0])
    reference = simulate(start, physics, 0.4, kinds=()).final_state[0]
    previous_error = np.inf
    for scale in [10.0, 1.0, 0.1, 0.01, 0.001]:
        spun = start.copy()
        spun[6:] = scale * np.array([0.3, -1.0, 0.2]) / np.sqrt(1.13)
        error = np.linalg.norm(simulate(spun, physics, 0.4, kinds=()).final_state[0][:3] - reference[:3])
        assert error < previous_error
        previous_error = error
    assert previous_error < 1e-4  # 1 mrad/s of spin moves the ball by less than 0.1 mm


def test_the_models_change_the_flight():
    start = make_state([1.2, 0.1, 0.3], [-12.0, 0.5, 1.5], [0.0, 250.0, 0.0])
    landing = {aero: simulate(start, BallPhysicsParams(aero=aero), 0.3, kinds=()).final_state[0] for aero in MODELS}
    for aero in MODELS[1:]:
        assert np.linalg.norm(landing[aero][:3] - landing[MODELS[0]][:3]) > 1e-3


# ---------------------------------------------------------------------------------- configs


def test_flight_constants_carry_the_selection():
    assert len(flight_constants(AeroParams())) == FLIGHT_CONSTANT_COUNT == ekf_kernels.CONFIG_SIZE - ekf_kernels.F_FLIGHT
    assert flight_constants(AeroParams())[7:] == (0.0, 0.0, 1.0, 1.0)
    scaled = AeroParams(drag_model="spin_ratio", magnus_model="refined", drag_coefficient=0.44, magnus_scale=0.5)
    assert flight_constants(scaled)[7:] == (SPIN_RATIO_DRAG, REFINED_MAGNUS, 0.44 / 0.55, 0.5)


def test_bad_model_names_the_field():
    with pytest.raises(ConfigError, match="aero.*drag_model.*constant, spin_ratio.*'quadratic'"):
        from_dict(BallPhysicsParams, {"aero": {"drag_model": "quadratic"}})
    with pytest.raises(ConfigError, match="aero.*magnus_model.*ratio, refined.*'v2'"):
        from_dict(BallPhysicsParams, {"aero": {"magnus_model": "v2"}})
    with pytest.raises(ConfigError, match="magnus_scale"):
        AeroParams(magnus_scale=-1.0)


def test_load_ball_params_selects_the_models(tmp_path):
    path = tmp_path / "ball.yaml"
    path.write_text("aero: {drag_model: spin_ratio, magnus_model: refined}\n")
    params = load_ball_params(path)
    assert params.aero == BOTH
    assert load_ball_params().aero.drag_model == "constant" and load_ball_params().aero.magnus_model == "ratio"


# ---------------------------------------------------------------------------------- compiled users


@pytest.mark.parametrize("aero", MODELS[1:], ids=MODEL_IDS[1:])
def test_hit_prediction_legs_are_simulate_with_the_models(aero):
    physics = BallPhysicsParams(aero=aero)
    starts = np.stack([
        make_state([1.2, 0.1, 0.15], [-9.0, 0.5, -1.0], [40.0, -300.0, 20.0]),  # lands on the table
        make_state([1.0, -0.2, 0.6], [-4.0, 0.3, 2.0], [0.0, 150.0, -60.0]),
    ])
    durations, dts = np.array([0.25, 0.2]), np.array([0.008, 0.01])
    stops = (ContactKind.TABLE_PLANE, ContactKind.FLOOR)
    for n in range(2):  # the predictor's legs (simulate_ball's compiled loop)
        reference = simulate(starts[n], physics, durations[n], dt=dts[n], kinds=_PREDICTION_KINDS, stop_on=stops)
        leg = simulate_ball(starts[n], physics, durations[n], dt=dts[n], kinds=_PREDICTION_KINDS, stop_on=stops)
        np.testing.assert_array_equal(leg.final_state, reference.final_state)
        assert (leg.stop_events[0] is not None) == (n == 0)
    # The compiled predictor flies the selected models.
    predictor, default = (HitPredictor(p, ReturnerParams(), 0.032, 0.005, 0.01) for p in (physics, BallPhysicsParams()))
    assert not np.array_equal(predictor.predict(starts[1]).states, default.predict(starts[1]).states)


@pytest.mark.parametrize("aero", MODELS[1:], ids=MODEL_IDS[1:])
def test_ekf_prediction_is_simulate_with_the_models(aero):
    physics = BallPhysicsParams(aero=aero)
    dut = BallEkf(physics=physics)
    np.testing.assert_array_equal(dut._config[ekf_kernels.F_FLIGHT:], flight_constants(aero))
    free = make_state([1.0, 0.2, 0.3], [-9.0, 0.5, 1.0], [40.0, -300.0, 20.0]) + np.random.default_rng(1).normal(0, 1e-3, (10, 9))
    batch = free.copy()
    assert ekf_kernels._flight_without_contact(batch, 0.013, 0.013 / 3, dut._config)
    np.testing.assert_array_equal(batch, simulate(free, physics, 0.013, dt=0.013 / 3, record=False).final_state)
    mean, _, _ = dut.predict(free[0], np.eye(12), 0.012)
    reference = simulate(free[0], physics, 0.012, dt=0.012 / np.ceil(0.012 / 0.005)).final_state[0]
    np.testing.assert_allclose(mean, reference, rtol=0, atol=1e-12)
