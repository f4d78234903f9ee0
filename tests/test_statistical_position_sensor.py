"""StatisticalPositionSensor: 200 Hz captures of the true ball, release at capture + latency,
noise and dropout of the model, seeding."""

import dataclasses

import numpy as np
import pytest
from pydrake.systems.framework import DiagramBuilder

from ace_drake.diagrams import add_ball, make_simulator
from ace_drake.perception.params import PositionSensorParams
from ace_drake.physics.flight import make_state
from ace_drake.physics.params import BallPhysicsParams
from ace_drake.physics.propagate import simulate
from ace_drake.systems.statistical_position_sensor import StatisticalPositionSensor

PHYSICS = BallPhysicsParams()
START = make_state([1.5, 0.1, 0.3], [-8.0, -0.3, 1.5], [20.0, -150.0, 10.0])
EXACT = PositionSensorParams(latency_min=0.01, latency_max=0.01, noise_std=0.0, dropout_probability=0.0, history_capacity=200)


def measurements_after(duration, params=PositionSensorParams(), seed=0, start=START):
    builder = DiagramBuilder()
    ball = add_ball(builder, PHYSICS)
    dut = builder.AddNamedSystem("position_sensor", StatisticalPositionSensor(params))
    builder.Connect(ball.ball_state_port, dut.ball_state_port)
    diagram = builder.Build()
    simulator = make_simulator(diagram)
    context = simulator.get_mutable_context()
    ball.SetBallState(ball.GetMyMutableContextFromRoot(context), start)
    dut.SetSeed(dut.GetMyMutableContextFromRoot(context), seed)
    simulator.Initialize()
    simulator.AdvanceTo(duration)
    return dut.position_measurements_port.Eval(dut.GetMyContextFromRoot(context))


def truth_at(times):
    trajectory = simulate(START, PHYSICS, max(times) + 1e-3, dt=1e-4)
    return trajectory.states[np.rint(np.asarray(times) / 1e-4).astype(int), 0]


def test_noise_free_sensor_reports_the_ball_at_each_trigger_after_its_latency():
    history = measurements_after(0.3, EXACT)
    captures = np.array([m.capture_time for m in history.measurements])
    np.testing.assert_allclose(captures, np.arange(0.0, 0.2901, 0.005), atol=1e-12)  # released by 0.3 s
    assert [m.sequence for m in history.measurements] == list(range(1, len(captures) + 1))
    np.testing.assert_allclose([m.release_time for m in history.measurements], captures + 0.01, atol=1e-12)
    values = np.array([m.value for m in history.measurements])
    np.testing.assert_allclose(values, truth_at(captures)[:, :3], atol=1e-6)  # the plant agrees to ~1e-6
    np.testing.assert_array_equal(history.measurements[0].covariance, np.zeros((3, 3)))


def test_the_port_publishes_at_the_release_time_not_at_the_next_trigger():
    history = measurements_after(0.1123, EXACT)
    assert history.latest.release_time == pytest.approx(0.110)
    assert history.latest.capture_time == pytest.approx(0.100)
    assert all(m.release_time <= 0.1123 for m in history.measurements)


def test_default_model_noise_latency_and_dropout():
    params = dataclasses.replace(PositionSensorParams(), history_capacity=400)
    history = measurements_after(0.8, params)
    captures = np.array([m.capture_time for m in history.measurements])
    triggers = int(round((0.8 - params.latency_max) / params.trigger_period))
    assert 0.85 * triggers < len(captures) < triggers  # 5 % dropout of about 158 triggers
    latencies = np.array([m.release_time for m in history.measurements]) - captures
    assert latencies.min() >= params.latency_min and latencies.max() <= params.latency_max
    errors = np.array([m.value for m in history.measurements]) - truth_at(captures)[:, :3]
    assert errors.std() == pytest.approx(params.noise_std, rel=0.15)
    np.testing.assert_array_equal(history.latest.covariance, params.noise_std**2 * np.eye(3))


def test_a_seed_gives_the_same_measurements_bit_for_bit():
    first, again, other = (measurements_after(0.2, seed=seed) for seed in (4, 4, 5))
    values = lambda h: np.array([np.r_[m.capture_time, m.release_time, m.value] for m in h.measurements])
    np.testing.assert_array_equal(values(first), values(again))
    assert values(first).shape != values(other).shape or not np.array_equal(values(first), values(other))
