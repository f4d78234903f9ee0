"""ekf_evaluation: simulated truth and sensor streams, the replay, the figures."""

import dataclasses

import numpy as np
import pytest

from ace_drake.perception.ball_ekf import BallEkf
from ace_drake.perception.ekf_evaluation import evaluate, replay, simulate_shots
from ace_drake.perception.params import PositionSensorParams, SpinSensorParams
from ace_drake.physics.flight import make_state
from ace_drake.physics.params import BallPhysicsParams
from ace_drake.physics.propagate import simulate

PHYSICS = BallPhysicsParams()
STARTS = np.array([
    make_state([1.2, 0.1, 0.3], [-7.0, -0.2, 1.0], [30.0, -200.0, 15.0]),
    make_state([1.5, -0.3, 0.2], [-9.0, 0.4, 1.5], [-50.0, 150.0, 0.0]),
])


def test_shots_sample_the_truth_with_the_sensor_models():
    exact_position = PositionSensorParams(noise_std=0.0, dropout_probability=0.0)
    exact_spin = SpinSensorParams(dropout_probability=0.0, magnitude_noise_std=0.0, axis_noise_std=0.0, magnitude_bias_std=0.0, axis_bias_std=0.0)
    shots = simulate_shots(STARTS, 0.4, position=exact_position, spin=exact_spin, perturb=False)
    reference = simulate(STARTS, PHYSICS, 0.4, dt=1e-3)
    for index, shot in enumerate(shots):
        np.testing.assert_array_equal(shot.states, reference.states[:, index])
        captures = np.array([m.capture_time for m in shot.positions])
        np.testing.assert_allclose(captures, np.arange(0.0, 0.4001, 0.005), atol=1e-12)
        np.testing.assert_array_equal([m.value for m in shot.positions], [shot.true_state(t)[:3] for t in captures])
        # Spin is constant between contacts: each sample equals the state's spin on its interval.
        for measurement in shot.spins:
            step = int(np.floor(measurement.capture_time / 1e-3))
            if all(abs(e.time - measurement.capture_time) > 1e-3 for e in shot.events):
                np.testing.assert_allclose(measurement.value, shot.states[step, 6:], atol=1e-9)
        assert [m.release_time for m in shot.spins] == sorted(m.release_time for m in shot.spins)


def test_same_seed_same_shots_and_perturbations_need_a_bounce():
    one, two = simulate_shots(STARTS, 0.4, seed=3), simulate_shots(STARTS, 0.4, seed=3)
    np.testing.assert_array_equal([m.value for m in one[0].spins], [m.value for m in two[0].spins])
    unperturbed = simulate_shots(STARTS, 0.4, seed=3, perturb=False)
    bounce = one[0].events[0].time
    before = int(bounce / 1e-3)
    np.testing.assert_array_equal(one[0].states[:before], unperturbed[0].states[:before])
    assert not np.array_equal(one[0].states[-1], unperturbed[0].states[-1])


def test_replay_and_evaluate():
    shots = simulate_shots(STARTS, 0.2, seed=1)
    result = replay(BallEkf(), shots[0], [0.005, 0.1])
    assert result.estimates[0.005] is None  # no position released yet
    assert result.estimates[0.1].time == 0.1
    assert result.updates > 0 and result.update_seconds > 0
    figures = evaluate(BallEkf(), shots, report_times=(0.1,))
    row = figures["report_times"][0.1]
    assert row["valid_fraction"] == 1.0
    assert 0 < row["velocity_error_mean_m_s"] < 0.3
    assert np.isfinite(row["nees_mean"]) and row["nees_mean"] > 0
    assert figures["updates"] > 0 and figures["resets"] == 0


def test_bad_arguments_are_named():
    shot = simulate_shots(STARTS[:1], 0.05)[0]
    with pytest.raises(ValueError, match="grid"):
        shot.true_state(0.0105)
    with pytest.raises(ValueError, match="trigger period"):
        simulate_shots(STARTS, 0.05, position=dataclasses.replace(PositionSensorParams(), trigger_period=0.0045), dt=1e-3)
