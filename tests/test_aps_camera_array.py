"""ApsCameraArray: trigger and release timing, projected detections, noise and dropout statistics,
seeding, occluders, and the rendered mode on Drake images."""

import dataclasses

import numpy as np
import pytest
from pydrake.geometry import MakeRenderEngineVtk, RenderEngineVtkParams
from pydrake.multibody.parsing import Parser
from pydrake.multibody.plant import AddMultibodyPlantSceneGraph
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import DiagramBuilder
from pydrake.systems.primitives import ConstantVectorSource

from ace_drake.config import MODELS_DIR, ConfigError
from ace_drake.perception.cameras import DEFAULT_CALIBRATION, OccluderSphere, load_cameras, project_points, visibility
from ace_drake.perception.params import CameraParams
from ace_drake.systems.aps_camera_array import ApsCameraArray, make_rgbd_sensor
from ace_drake.systems.ball_geometry import BallGeometry

CAMERAS = load_cameras(DEFAULT_CALIBRATION)
EXACT = CameraParams(pixel_noise_sigma=0.0, dropout_probability=0.0)
BALL = np.array([0.4, -0.2, 0.35])
STEP = 1e-7  # s past an event time, so that AdvanceTo has handled it


def build(params, p_WB=BALL, seed=0):
    builder = DiagramBuilder()
    source = builder.AddNamedSystem("ball_state_source", ConstantVectorSource(np.concatenate([p_WB, np.zeros(6)])))
    dut = builder.AddNamedSystem("cameras", ApsCameraArray(CAMERAS, params, seed=seed))
    builder.Connect(source.get_output_port(), dut.ball_state_port)
    diagram = builder.Build()
    simulator = Simulator(diagram)
    return dut, simulator


def detections_at(dut, simulator, time):
    simulator.AdvanceTo(time)
    return dut.detections_port.Eval(dut.GetMyContextFromRoot(simulator.get_context()))


def test_frames_are_released_after_the_latency():
    dut, simulator = build(EXACT)
    assert dut.period == pytest.approx(0.005)
    before = detections_at(dut, simulator, 0.0102 - STEP)
    assert before.sequence == 0 and not before.detected.any()
    for k in range(6):
        frame = detections_at(dut, simulator, 0.005 * k + 0.0102 + STEP)
        assert frame.sequence == k + 1
        assert frame.capture_time == pytest.approx(0.005 * k, abs=1e-12)
        assert frame.release_time == pytest.approx(frame.capture_time + 0.0102, abs=1e-12)
        assert frame.camera_names == tuple(c.name for c in CAMERAS)
    # One period later the next frame has replaced it.
    assert detections_at(dut, simulator, 0.005 * 6 + 0.0102 + STEP).sequence == 7


@pytest.mark.parametrize("latency", [0.0, 0.01])
def test_latency_on_the_trigger_grid(latency):
    dut, simulator = build(dataclasses.replace(EXACT, latency=latency))
    for k in range(4):
        frame = detections_at(dut, simulator, 0.005 * k + latency + STEP)
        assert (frame.sequence, frame.capture_time) == (k + 1, pytest.approx(0.005 * k, abs=1e-12))
        assert frame.release_time == pytest.approx(frame.capture_time + latency, abs=1e-12)


def test_exact_detections_are_the_visible_projections():
    dut, simulator = build(EXACT)
    frame = detections_at(dut, simulator, 0.0102 + STEP)
    pixels, _ = project_points(CAMERAS, BALL[None])
    seen = visibility(CAMERAS, BALL[None])[:, 0]
    assert seen.sum() >= 3
    np.testing.assert_array_equal(frame.detected, seen)
    np.testing.assert_allclose(frame.pixels[seen], pixels[seen, 0], atol=1e-9)
    # Under the table no camera sees the ball.
    dut, simulator = build(EXACT, p_WB=np.array([0.3, 0.1, -0.3]))
    assert not detections_at(dut, simulator, 0.0102 + STEP).detected.any()


def collect_frames(dut, simulator, count, latency=0.0102):
    return [detections_at(dut, simulator, 0.005 * k + latency + STEP) for k in range(count)]


def test_noise_and_dropout_statistics():
    params = CameraParams(pixel_noise_sigma=0.5, dropout_probability=0.3)
    dut, simulator = build(params, seed=5)
    frames = collect_frames(dut, simulator, 120)
    assert [f.sequence for f in frames] == list(range(1, 121))
    pixels = np.array([f.pixels for f in frames])  # (120, 9, 2)
    truth, _ = project_points(CAMERAS, BALL[None])
    visible = visibility(CAMERAS, BALL[None])[:, 0]
    detected = np.isfinite(pixels[..., 0])
    assert not detected[:, ~visible].any()
    # 120 frames x the visible cameras: the dropout fraction within three standard errors of 0.3.
    trials = 120 * visible.sum()
    assert 1 - detected[:, visible].mean() == pytest.approx(0.3, abs=3 * np.sqrt(0.21 / trials))
    errors = (pixels - truth[:, 0])[detected]
    assert errors.std() == pytest.approx(0.5, rel=0.08)


def test_same_seed_same_detections_bit_for_bit():
    params = CameraParams(pixel_noise_sigma=0.5, dropout_probability=0.2)
    first = collect_frames(*build(params, seed=11), 10)
    second = collect_frames(*build(params, seed=11), 10)
    other_dut, other_simulator = build(params, seed=11)
    other_dut.SetSeed(other_dut.GetMyMutableContextFromRoot(other_simulator.get_mutable_context()), 12)
    other = collect_frames(other_dut, other_simulator, 10)
    assert all(np.array_equal(a.pixels, b.pixels, equal_nan=True) for a, b in zip(first, second))
    assert not all(np.array_equal(a.pixels, b.pixels, equal_nan=True) for a, b in zip(first, other))


def test_occluders_input_hides_the_ball_from_one_camera():
    dut, simulator = build(EXACT)
    context = dut.GetMyMutableContextFromRoot(simulator.get_mutable_context())
    seen = visibility(CAMERAS, BALL[None])[:, 0]
    index = int(np.flatnonzero(seen)[0])
    midpoint = 0.5 * (CAMERAS[index].p_WC + BALL)
    dut.occluders_port.FixValue(context, (OccluderSphere(midpoint, 0.1),))
    frame = detections_at(dut, simulator, 0.0102 + STEP)
    expected = seen.copy()
    expected[index] = False
    np.testing.assert_array_equal(frame.detected, expected)


def test_params_are_validated():
    with pytest.raises(ConfigError, match="mode"):
        CameraParams(mode="photographic")
    with pytest.raises(ConfigError, match="dropout_probability"):
        CameraParams(dropout_probability=1.5)
    with pytest.raises(ConfigError, match="min_views"):
        CameraParams(min_views=1)
    with pytest.raises(ValueError, match="at least one camera"):
        ApsCameraArray([], EXACT)


def build_rendered(p_WB, scale=0.25):
    params = CameraParams(mode="rendered", render_scale=scale, pixel_noise_sigma=0.0, dropout_probability=0.0)
    builder = DiagramBuilder()
    plant, scene_graph = AddMultibodyPlantSceneGraph(builder, 0.0)
    Parser(plant).AddModels(str(MODELS_DIR / "table.sdf"))
    plant.Finalize()
    scene_graph.AddRenderer("vtk", MakeRenderEngineVtk(RenderEngineVtkParams()))
    source = builder.AddNamedSystem("ball_state_source", ConstantVectorSource(np.concatenate([p_WB, np.zeros(6)])))
    geometry = builder.AddNamedSystem("ball_geometry", BallGeometry(scene_graph))
    builder.Connect(source.get_output_port(), geometry.ball_state_port)
    builder.Connect(geometry.geometry_pose_port, scene_graph.get_source_pose_port(geometry.source_id))
    dut = builder.AddNamedSystem("cameras", ApsCameraArray(CAMERAS, params))
    builder.Connect(source.get_output_port(), dut.ball_state_port)
    for camera in CAMERAS:
        sensor = builder.AddNamedSystem(f"sensor_{camera.name}", make_rgbd_sensor(camera, scale, "vtk", scene_graph.world_frame_id()))
        builder.Connect(scene_graph.get_query_output_port(), sensor.query_object_input_port())
        builder.Connect(sensor.color_image_output_port(), dut.image_ports[camera.name])
    return dut, Simulator(builder.Build())


def test_rendered_mode_detects_the_ball_in_drake_images():
    dut, simulator = build_rendered(BALL)
    assert set(dut.image_ports) == {c.name for c in CAMERAS}
    assert dut.GetInputPort(f"color_image_{CAMERAS[0].name}") is dut.image_ports[CAMERAS[0].name]
    frame = detections_at(dut, simulator, 0.0102 + STEP)
    pixels, _ = project_points(CAMERAS, BALL[None])
    seen = visibility(CAMERAS, BALL[None])[:, 0]
    np.testing.assert_array_equal(frame.detected, seen)
    # At a quarter of the resolution the ball's disc is 1.5-3 px across: centres agree to ~2 full-size px.
    errors = np.linalg.norm(frame.pixels[seen] - pixels[seen, 0], axis=1)
    assert errors.max() < 2.5 and errors.mean() < 1.2
    # A ball high above the hall is in no image.
    dut, simulator = build_rendered(np.array([0.0, 0.0, 8.0]))
    assert not detections_at(dut, simulator, 0.0102 + STEP).detected.any()
