"""Triangulator: measurements from released camera frames, in the smallest diagrams (a constant
ball, a thrown ball) and on hand-made frames (outliers, too few views, capacity, bad wiring)."""

import numpy as np
import pytest
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import DiagramBuilder
from pydrake.systems.primitives import ConstantVectorSource, VectorLogSink

from ace_drake.diagrams import add_ball, make_simulator
from ace_drake.perception.cameras import DEFAULT_CALIBRATION, DetectionFrame, load_cameras, project_points
from ace_drake.perception.measurements import MeasurementHistory
from ace_drake.perception.params import CameraParams
from ace_drake.physics.flight import make_state
from ace_drake.physics.params import BallPhysicsParams
from ace_drake.systems.aps_camera_array import ApsCameraArray
from ace_drake.systems.triangulator import Triangulator

CAMERAS = load_cameras(DEFAULT_CALIBRATION)
NAMES = tuple(camera.name for camera in CAMERAS)
BALL = np.array([-0.6, 0.3, 0.25])


def constant_ball_diagram(params, capacity=32):
    builder = DiagramBuilder()
    source = builder.AddNamedSystem("ball_state_source", ConstantVectorSource(np.concatenate([BALL, np.zeros(6)])))
    cameras = builder.AddNamedSystem("cameras", ApsCameraArray(CAMERAS, params, seed=2))
    dut = builder.AddNamedSystem("triangulator", Triangulator(CAMERAS, params, history_capacity=capacity))
    builder.Connect(source.get_output_port(), cameras.ball_state_port)
    builder.Connect(cameras.detections_port, dut.detections_port)
    return cameras, dut, builder.Build()


def measurements(dut, simulator) -> MeasurementHistory:
    return dut.position_measurements_port.Eval(dut.GetMyContextFromRoot(simulator.get_context()))


def test_every_released_frame_becomes_a_measurement():
    params = CameraParams(pixel_noise_sigma=0.5, dropout_probability=0.0)
    cameras, dut, diagram = constant_ball_diagram(params)
    simulator = Simulator(diagram)
    simulator.AdvanceTo(0.1 + 1e-7)  # frames captured at 0, 5, ..., 85 ms are released by 95.2 ms
    history = measurements(dut, simulator)
    frame = cameras.detections_port.Eval(cameras.GetMyContextFromRoot(simulator.get_context()))
    assert frame.sequence == 18
    assert [m.sequence for m in history.measurements] == list(range(1, 19))
    for k, measurement in enumerate(history.measurements):
        assert measurement.capture_time == pytest.approx(0.005 * k, abs=1e-12)
        assert measurement.release_time == pytest.approx(0.005 * k + 0.0102, abs=1e-12)
        error = measurement.value - BALL
        assert error @ np.linalg.solve(measurement.covariance, error) < 20.0  # chi-square(3): p < 2e-4
        np.testing.assert_allclose(measurement.covariance, measurement.covariance.T)
        assert np.all(np.linalg.eigvalsh(measurement.covariance) > 0)


def test_each_frame_is_triangulated_once_and_absorbed_at_the_next_trigger(monkeypatch):
    import ace_drake.systems.triangulator as module

    calls = []
    original = module.triangulate
    monkeypatch.setattr(module, "triangulate", lambda *args: calls.append(args) or original(*args))
    cameras, dut, diagram = constant_ball_diagram(CameraParams(dropout_probability=0.0))
    simulator = Simulator(diagram)
    context = dut.GetMyContextFromRoot(simulator.get_context())
    shown_before = 0
    for millisecond in range(1, 101):  # a consumer reading the output every 1 ms, as the estimator
        simulator.AdvanceTo(millisecond * 1e-3 + 1e-7)
        frame = cameras.detections_port.Eval(cameras.GetMyContextFromRoot(simulator.get_context()))
        assert measurements(dut, simulator).last_sequence == frame.sequence  # shown from its release on
        absorbed = context.get_abstract_state(0).get_value().last_frame_sequence
        if millisecond % 5 == 0:  # a trigger: the frame shown before it is absorbed
            assert absorbed == shown_before
        assert frame.sequence - 1 <= absorbed <= frame.sequence
        shown_before = frame.sequence
    assert frame.sequence == 18 and len(calls) == 18  # each released frame triangulated once


def test_exact_detections_give_the_ball_and_a_zero_covariance():
    cameras, dut, diagram = constant_ball_diagram(CameraParams(pixel_noise_sigma=0.0, dropout_probability=0.0))
    simulator = Simulator(diagram)
    simulator.AdvanceTo(0.0102 + 1e-7)
    (measurement,) = measurements(dut, simulator).measurements
    assert np.linalg.norm(measurement.value - BALL) < 1e-6
    np.testing.assert_array_equal(measurement.covariance, np.zeros((3, 3)))
    # Resetting the context starts the next episode with no measurements.
    diagram.SetDefaultContext(simulator.get_mutable_context())
    assert measurements(dut, simulator).measurements == ()


def test_history_keeps_the_latest_measurements():
    _, dut, diagram = constant_ball_diagram(CameraParams(dropout_probability=0.0), capacity=5)
    simulator = Simulator(diagram)
    simulator.AdvanceTo(0.07 + 1e-7)
    assert [m.sequence for m in measurements(dut, simulator).measurements] == [8, 9, 10, 11, 12]


def test_a_thrown_ball_is_tracked_through_its_bounce():
    params = CameraParams()  # 1.5 px noise, 2 % dropout
    builder = DiagramBuilder()
    ball = add_ball(builder, BallPhysicsParams())
    cameras = builder.AddNamedSystem("cameras", ApsCameraArray(CAMERAS, params, seed=4))
    dut = builder.AddNamedSystem("triangulator", Triangulator(CAMERAS, params, history_capacity=100))
    truth = builder.AddNamedSystem("truth_logger", VectorLogSink(9, publish_period=1.0 / params.trigger_rate))
    builder.Connect(ball.ball_state_port, cameras.ball_state_port)
    builder.Connect(ball.ball_state_port, truth.get_input_port())
    builder.Connect(cameras.detections_port, dut.detections_port)
    diagram = builder.Build()
    simulator = make_simulator(diagram)
    context = simulator.get_mutable_context()
    ball.SetBallState(ball.GetMyMutableContextFromRoot(context), make_state([1.6, -0.3, 0.3], [-5.5, 0.5, 1.0], [0.0, -80.0, 0.0]))
    simulator.AdvanceTo(0.4)
    assert ball.contact_events_port.Eval(ball.GetMyContextFromRoot(context))  # it bounced
    log = truth.FindLog(context)
    history = measurements(dut, simulator)
    assert len(history.measurements) >= 70  # 78 frames released by 0.4 s, all in view
    errors = []
    for measurement in history.measurements:
        (row,) = np.flatnonzero(np.isclose(log.sample_times(), measurement.capture_time, atol=1e-9))
        errors.append(np.linalg.norm(measurement.value - log.data()[:3, row]))
    assert np.mean(errors) < 0.004 and np.max(errors) < 0.012  # m; the paper reports a mean of 3.0 mm


def fixed_frame_simulator(capacity=32):
    dut = Triangulator(CAMERAS, CameraParams(pixel_noise_sigma=0.5), history_capacity=capacity)
    simulator = Simulator(dut)
    return dut, simulator


def release(dut, simulator, frame):
    """Puts ``frame`` on the input and advances one trigger period (the trigger's update absorbs it)."""
    dut.detections_port.FixValue(simulator.get_mutable_context(), frame)
    simulator.AdvanceTo(simulator.get_context().get_time() + 0.005)
    return measurements(dut, simulator)


def test_outliers_and_frames_without_enough_views():
    dut, simulator = fixed_frame_simulator()
    truth, _ = project_points(CAMERAS, BALL[None])
    corrupted = truth[:, 0].copy()
    corrupted[1] += [15.0, 15.0]
    history = release(dut, simulator, DetectionFrame(1, 0.0, 0.0102, NAMES, corrupted))
    (measurement,) = history.measurements
    assert np.linalg.norm(measurement.value - BALL) < 1e-6  # the corrupted view was dropped
    one_view = np.full_like(corrupted, np.nan)
    one_view[0] = truth[0, 0]
    assert release(dut, simulator, DetectionFrame(2, 0.005, 0.0152, NAMES, one_view)).last_sequence == 1
    # The same frame seen again adds nothing; a new good frame is measurement 2.
    assert release(dut, simulator, DetectionFrame(2, 0.005, 0.0152, NAMES, one_view)).last_sequence == 1
    history = release(dut, simulator, DetectionFrame(3, 0.01, 0.0202, NAMES, truth[:, 0]))
    assert history.last_sequence == 2 and history.latest.capture_time == 0.01


def test_detections_from_other_cameras_are_refused():
    dut, simulator = fixed_frame_simulator()
    frame = DetectionFrame(1, 0.0, 0.0102, tuple(reversed(NAMES)), np.zeros((len(NAMES), 2)))
    dut.detections_port.FixValue(simulator.get_mutable_context(), frame)
    with pytest.raises(ValueError, match="was built for"):
        dut.position_measurements_port.Eval(simulator.get_context())
