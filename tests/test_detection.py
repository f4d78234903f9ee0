"""Ball detection: sub-pixel centres on synthetic discs (cv2.circle) and on Drake-rendered images,
and rejection of what is not a ball."""

import cv2
import numpy as np
import pytest
from pydrake.geometry import MakeRenderEngineVtk, RenderEngineVtkParams, SceneGraph
from pydrake.systems.framework import DiagramBuilder
from pydrake.systems.primitives import ConstantVectorSource

from ace_drake.perception.cameras import camera_looking_at
from ace_drake.perception.detection import BallColorThreshold, ball_mask, detect_ball
from ace_drake.systems.aps_camera_array import make_rgbd_sensor
from ace_drake.systems.ball_geometry import BallGeometry

TABLE_BLUE = (13, 64, 140)
BALL_ORANGE = (255, 140, 0)
ROBOT_ORANGE = (242, 115, 13)  # the robot's links, (0.95, 0.45, 0.05)
SHIFT_BITS = 8  # cv2.circle's fixed-point fraction bits: centres to 1/256 px


def draw_disc(image, center, radius, color, line_type=cv2.LINE_AA):
    scale = 2**SHIFT_BITS
    cv2.circle(image, (round(center[0] * scale), round(center[1] * scale)), round(radius * scale), color, -1, line_type, SHIFT_BITS)


def background(width=360, height=270):
    image = np.empty((height, width, 3), np.uint8)
    image[:] = TABLE_BLUE
    return image


@pytest.mark.parametrize(("radius", "max_error", "mean_error"), [(2.5, 0.35, 0.2), (5.0, 0.25, 0.12), (12.0, 0.15, 0.07)])
def test_sub_pixel_centres_of_synthetic_discs(radius, max_error, mean_error):
    rng = np.random.default_rng(int(radius * 10))
    errors = []
    for _ in range(25):
        center = rng.uniform([30, 30], [330, 240])
        image = background()
        draw_disc(image, center, radius, BALL_ORANGE)
        detection = detect_ball(image, min_radius_px=0.5 * radius)
        assert detection is not None
        assert detection.radius == pytest.approx(radius, abs=0.6)  # anti-aliased rims count as ball
        errors.append(np.linalg.norm(detection.center - center))
    assert max(errors) < max_error and np.mean(errors) < mean_error


def test_rgba_images_and_the_mask():
    image = background()
    draw_disc(image, (100.25, 80.5), 6.0, BALL_ORANGE, cv2.LINE_8)
    rgba = np.dstack([image, np.full(image.shape[:2], 255, np.uint8)])
    detection = detect_ball(rgba)
    np.testing.assert_allclose(detection.center, (100.25, 80.5), atol=0.15)
    mask = ball_mask(rgba)
    assert mask.dtype == np.uint8 and set(np.unique(mask)) == {0, 255}
    with pytest.raises(ValueError, match="RGB"):
        ball_mask(image.astype(float))


def test_nothing_ball_like_gives_none():
    assert detect_ball(background()) is None
    wrong_colour = background()
    draw_disc(wrong_colour, (150, 100), 6.0, (240, 240, 240))  # a white disc: a table line's colour
    assert detect_ball(wrong_colour) is None
    robot = background()
    draw_disc(robot, (150, 100), 6.0, ROBOT_ORANGE)  # the robot's orange, hue 13, is not the ball's
    assert detect_ball(robot) is None
    bar = background()
    cv2.rectangle(bar, (50, 50), (120, 56), BALL_ORANGE, -1)  # ball-coloured but long and thin
    assert detect_ball(bar) is None
    small = background()
    draw_disc(small, (150, 100), 1.0, BALL_ORANGE)
    assert detect_ball(small, min_radius_px=3.0) is None


def test_the_ball_is_chosen_among_other_blobs():
    image = background()
    draw_disc(image, (60.0, 60.0), 2.0, BALL_ORANGE)  # a smaller ball-coloured speck
    cv2.rectangle(image, (200, 30), (300, 38), BALL_ORANGE, -1)  # a bar
    draw_disc(image, (150.4, 180.7), 7.0, BALL_ORANGE)
    detection = detect_ball(image)
    np.testing.assert_allclose(detection.center, (150.4, 180.7), atol=0.15)


def test_threshold_validation():
    with pytest.raises(ValueError, match="hue_low"):
        BallColorThreshold(hue_low=30, hue_high=20)
    # A custom threshold finds a white ball.
    image = background()
    draw_disc(image, (120.0, 90.0), 5.0, (250, 250, 250))
    white = BallColorThreshold(hue_low=0, hue_high=179, saturation_min=0, value_min=230)
    np.testing.assert_allclose(detect_ball(image, color=white).center, (120.0, 90.0), atol=0.2)


def render_ball(camera, p_WB, scale):
    builder = DiagramBuilder()
    scene_graph = builder.AddSystem(SceneGraph())
    scene_graph.AddRenderer("vtk", MakeRenderEngineVtk(RenderEngineVtkParams()))
    source = builder.AddSystem(ConstantVectorSource(np.concatenate([p_WB, np.zeros(6)])))
    ball = builder.AddSystem(BallGeometry(scene_graph))
    builder.Connect(source.get_output_port(), ball.ball_state_port)
    builder.Connect(ball.geometry_pose_port, scene_graph.get_source_pose_port(ball.source_id))
    sensor = builder.AddSystem(make_rgbd_sensor(camera, scale, "vtk", scene_graph.world_frame_id()))
    builder.Connect(scene_graph.get_query_output_port(), sensor.query_object_input_port())
    diagram = builder.Build()
    context = diagram.CreateDefaultContext()
    return np.array(sensor.color_image_output_port().Eval(sensor.GetMyContextFromRoot(context)).data)


def test_drake_rendered_ball_is_found_where_the_camera_model_projects_it():
    camera = camera_looking_at("c", [0.0, -2.0, 0.5], [0.0, 0.0, 0.5], 2300.0)
    # On the optical axis the rendered disc is centred on the principal point (the renderer's
    # half-pixel convention is compensated by make_rgbd_sensor).
    for scale in (1.0, 0.25):
        image = render_ball(camera, np.array([0.0, 0.0, 0.5]), scale)
        assert image.shape == (round(1080 * scale), round(1440 * scale), 4)
        detection = detect_ball(image, max_radius_px=100)
        expected = camera.scaled(scale).project(np.array([[0.0, 0.0, 0.5]]))[0]
        np.testing.assert_allclose(detection.center, expected, atol=0.02)
        assert detection.radius == pytest.approx(scale * 2300 * 0.02 / 2.0, rel=0.05)
    # Off axis the sphere's tessellation moves the centroid by a fraction of a pixel.
    p_WB = np.array([0.25, 0.1, 0.45])
    detection = detect_ball(render_ball(camera, p_WB, 1.0), max_radius_px=100)
    assert np.linalg.norm(detection.center - camera.project(p_WB[None])[0]) < 0.7
