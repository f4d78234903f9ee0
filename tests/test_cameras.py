"""Camera models: projection against hand-worked pixels, ball radius, visibility and occlusion,
the detection noise model, calibration files and their errors."""

import numpy as np
import pytest
import yaml

from ace_drake.config import ConfigError
from ace_drake.perception.cameras import (
    DEFAULT_CALIBRATION,
    Camera,
    DetectionFrame,
    OccluderBox,
    OccluderSphere,
    PlayingArea,
    camera_looking_at,
    load_cameras,
    project_points,
    projected_ball_radius,
    rotation_from_yaw_pitch,
    save_cameras,
    segments_blocked,
    simulate_detections,
    table_occluder,
    validate_camera_array,
    visibility,
)

K = np.array([[1000.0, 0.0, 719.5], [0.0, 1000.0, 539.5], [0.0, 0.0, 1.0]])
# Looking along +x from behind the robot's end: image x (right) is world -y, image y (down) is -z.
R_WC_ALONG_X = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


def camera_along_x(distortion=(0.0, 0.0, 0.0, 0.0, 0.0), name="end"):
    return Camera(name, K, np.array(distortion), R_WC_ALONG_X, np.array([-8.0, 0.0, 1.0]))


def test_projection_matches_hand_worked_pixels():
    # p_C = (-0.5, -0.25, 10) for p_W = (2, 0.5, 1.25): u = 719.5 + 1000 (-0.05), v = 539.5 + 1000 (-0.025).
    point = np.array([[2.0, 0.5, 1.25]])
    np.testing.assert_allclose(camera_along_x().project(point), [[669.5, 514.5]], atol=1e-9)
    # Radial distortion k1 = -0.1: r^2 = 0.003125, so both normalised coordinates shrink by 1 - 0.0003125.
    np.testing.assert_allclose(camera_along_x((-0.1, 0, 0, 0, 0)).project(point), [[669.515625, 514.5078125]], atol=1e-9)


def test_rotation_from_yaw_pitch_and_looking_at():
    np.testing.assert_allclose(rotation_from_yaw_pitch(0.0, 0.0), R_WC_ALONG_X, atol=1e-15)
    camera = camera_looking_at("c", [3.0, -4.0, 2.0], [0.0, 0.0, 0.0], 1500.0)
    np.testing.assert_allclose(camera.project(np.zeros((1, 3))), [[719.5, 539.5]], atol=1e-9)
    assert camera.R_WC[2, 0] == pytest.approx(0.0, abs=1e-15)  # no roll: image x is horizontal
    assert np.linalg.det(camera.R_WC) == pytest.approx(1.0)


def test_jacobian_matches_finite_differences():
    camera = camera_along_x((-0.12, 0.06, 1e-3, -2e-3, 0.01))
    point = np.array([1.0, 0.8, 0.4])
    _, jacobian = camera.project_with_jacobian(point)
    step = 1e-6
    numeric = np.column_stack([(camera.project(point + step * e) - camera.project(point - step * e))[0] / (2 * step) for e in np.eye(3)])
    np.testing.assert_allclose(jacobian[0], numeric, rtol=1e-6, atol=1e-4)


def test_scaled_camera_maps_pixel_centres():
    camera = camera_along_x((-0.1, 0.03, 0, 0, 0))
    points = np.array([[2.0, 0.5, 1.25], [0.0, -1.0, 0.2]])
    quarter = camera.scaled(0.25)
    assert (quarter.width, quarter.height) == (360, 270)
    np.testing.assert_allclose(quarter.project(points), (camera.project(points) + 0.5) * 0.25 - 0.5, atol=1e-9)


def test_projected_ball_radius():
    camera = camera_along_x()
    # On the optical axis 4 m away: f tan(asin(r / d)) = 1000 * 0.02 / sqrt(16 - 0.0004) px.
    radius = projected_ball_radius([camera], np.array([[-4.0, 0.0, 1.0]]))
    assert radius[0, 0] == pytest.approx(1000 * 0.02 / np.sqrt(16 - 0.0004), rel=1e-12)
    assert projected_ball_radius([camera], np.array([[-9.0, 0.0, 1.0]]))[0, 0] == 0.0  # behind


def test_project_points_batches_cameras():
    cameras = [camera_along_x(), camera_looking_at("side", [0.0, -4.0, 1.0], [0.0, 0.0, 0.3], 1200.0)]
    points = np.array([[0.3, 0.2, 0.5], [-0.5, -0.1, 0.2], [1.0, 0.0, 0.1]])
    pixels, depth = project_points(cameras, points)
    assert pixels.shape == (2, 3, 2) and depth.shape == (2, 3)
    for index, camera in enumerate(cameras):
        np.testing.assert_array_equal(pixels[index], camera.project(points))
    np.testing.assert_allclose(depth[0], points[:, 0] + 8.0)


def test_visibility_in_front_and_in_frame():
    camera = camera_along_x()
    points = np.array(
        [
            [0.0, 0.0, 1.0],  # on the optical axis
            [-9.0, 0.0, 1.0],  # behind the camera
            [0.0, 8.0, 1.0],  # left of the image: u = 719.5 - 1000 px
            [0.0, 0.0, 1.0 + 539.5 / 1000 * 8.0 - 0.001],  # centre in the top row (v = 0.125), disc not
        ]
    )
    pixels = camera.project(points)
    assert pixels[2, 0] == pytest.approx(-280.5)
    assert pixels[3, 1] == pytest.approx(0.125)
    seen = visibility([camera], points, occluders=())[0]
    np.testing.assert_array_equal(seen, [True, False, False, False])


def test_table_occludes_low_balls_from_a_low_side_camera():
    # A camera beside the table, 0.3 m below the playing surface, looking at the table's centre.
    camera = camera_looking_at("low", [0.0, -3.8, -0.3], [0.0, 0.0, 0.1], 1200.0)
    points = np.array([[0.0, 0.0, 0.05], [0.0, 0.0, 0.3], [0.0, 0.0, -0.3]])
    np.testing.assert_array_equal(visibility([camera], points)[0], [False, True, False])
    np.testing.assert_array_equal(visibility([camera], points, occluders=())[0], [True, True, True])
    # From high above, a ball on the table is seen and one under it is not.
    high = camera_looking_at("high", [0.0, -3.8, 3.0], [0.0, 0.0, 0.0], 1200.0)
    np.testing.assert_array_equal(visibility([high], np.array([[0.3, 0.2, 0.02], [0.3, 0.2, -0.2]]))[0], [True, False])


def test_extra_occluders():
    camera = camera_along_x()
    ball = np.array([[0.0, 0.0, 1.0]])
    sphere = OccluderSphere(np.array([-2.0, 0.05, 1.0]), 0.1)
    assert not visibility([camera], ball, occluders=(sphere,))[0, 0]
    assert visibility([camera], ball, occluders=(OccluderSphere(np.array([-2.0, 0.3, 1.0]), 0.1),))[0, 0]
    # A thin plate rotated 45 degrees about z, across the line of sight; beyond the ball it hides nothing.
    c, s = np.cos(np.pi / 4), np.sin(np.pi / 4)
    R_WB = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    plate = OccluderBox(np.array([-3.0, 0.0, 1.0]), np.array([0.3, 0.01, 0.3]), R_WB)
    assert not visibility([camera], ball, occluders=(plate,))[0, 0]
    behind = OccluderBox(np.array([1.0, 0.0, 1.0]), np.array([0.3, 0.01, 0.3]), R_WB)
    assert visibility([camera], ball, occluders=(behind,))[0, 0]


def test_segments_parallel_to_box_faces():
    box = OccluderBox(np.zeros(3), np.array([1.0, 1.0, 1.0]))
    origins = np.array([[-5.0, 0.5, 0.5], [-5.0, 1.5, 0.5]])  # inside the y and z slabs; outside the y slab
    targets = np.array([[5.0, 0.5, 0.5], [5.0, 1.5, 0.5], [-2.0, 0.5, 0.5]])  # the last stops short of the box
    blocked = segments_blocked(origins, targets, (box,))
    # Parallel to the y and z faces: through the box inside the slabs, past it outside; diagonals cross it.
    np.testing.assert_array_equal(blocked, [[True, True, False], [True, False, False]])


def test_table_occluder_dimensions():
    box = table_occluder()
    np.testing.assert_allclose(box.half_extents, [1.37, 0.7625, 0.38])
    np.testing.assert_allclose(box.p_WB, [0.0, 0.0, -0.38])


def test_detection_noise_and_dropout_statistics():
    cameras = [camera_looking_at(f"c{i}", [8.0 * np.cos(a), 5.0 * np.sin(a), 2.0], [0.0, 0.0, 0.3], 2000.0) for i, a in enumerate(np.linspace(0, 2 * np.pi, 9, endpoint=False))]
    ball = np.array([0.1, -0.2, 0.4])
    truth, _ = project_points(cameras, ball[None])
    rng = np.random.default_rng(7)
    draws = np.array([simulate_detections(cameras, ball, rng, 0.5, 0.2) for _ in range(2000)])  # (2000, 9, 2)
    detected = np.isfinite(draws[..., 0])
    assert detected.mean() == pytest.approx(0.8, abs=0.015)
    errors = (draws - truth[:, 0])[detected]
    assert errors.std() == pytest.approx(0.5, rel=0.03)
    assert abs(errors.mean()) < 0.02


def test_detections_are_reproducible_and_need_visibility():
    cameras = [camera_along_x(), camera_looking_at("side", [0.0, -4.0, 1.0], [0.0, 0.0, 0.3], 1200.0)]
    ball = np.array([0.2, 0.0, 0.5])
    first = simulate_detections(cameras, ball, np.random.default_rng(3), 0.5, 0.1)
    second = simulate_detections(cameras, ball, np.random.default_rng(3), 0.5, 0.1)
    other = simulate_detections(cameras, ball, np.random.default_rng(4), 0.5, 0.1)
    np.testing.assert_array_equal(first, second)
    assert not np.array_equal(first, other, equal_nan=True)
    hidden = simulate_detections(cameras, np.array([0.2, 0.0, -0.3]), np.random.default_rng(3), 0.0, 0.0)
    assert np.all(np.isnan(hidden))  # under the table


def test_detection_frame_is_immutable():
    frame = DetectionFrame(1, 0.0, 0.0102, ("a", "b"), [[1.0, 2.0], [np.nan, np.nan]])
    np.testing.assert_array_equal(frame.detected, [True, False])
    with pytest.raises(ValueError):
        frame.pixels[0, 0] = 5.0
    with pytest.raises(ValueError, match="before its capture"):
        DetectionFrame(1, 1.0, 0.5, ("a",), [[1.0, 2.0]])


# ---------------------------------------------------------------------------------- calibration


def test_shipped_calibration_loads():
    cameras = load_cameras(DEFAULT_CALIBRATION)
    assert len(cameras) == 9
    assert all((camera.width, camera.height) == (1440, 1080) for camera in cameras)
    area = PlayingArea()
    assert not np.any(area.inside(np.array([camera.p_WC for camera in cameras])))
    # Every camera looks at the play volume: the table's centre is in its image.
    assert visibility(cameras, np.array([[0.0, 0.0, 0.3]]), occluders=()).all()


def test_save_and_load_round_trip(tmp_path):
    cameras = (camera_along_x((-0.1, 0.02, 1e-4, -2e-4, 0.001)), camera_looking_at("side", [0.5, -4.0, 1.5], [0.0, 0.0, 0.3], 1234.5))
    path = tmp_path / "cams.yaml"
    save_cameras(path, cameras, header="two cameras\nfor a test")
    assert path.read_text().startswith("# two cameras\n# for a test\n")
    loaded = load_cameras(path)
    for original, copy in zip(cameras, loaded):
        assert copy.name == original.name and (copy.width, copy.height) == (original.width, original.height)
        for field in ("K", "distortion", "R_WC", "p_WC"):
            np.testing.assert_array_equal(getattr(copy, field), getattr(original, field))


def write_camera(tmp_path, **overrides):
    entry = {
        "name": "north",
        "resolution": [1440, 1080],
        "K": K.tolist(),
        "distortion": [-0.1, 0.02, 0.0, 0.0, 0.0],
        "R_WC": R_WC_ALONG_X.tolist(),
        "p_WC": [-8.0, 0.0, 1.0],
    }
    entry.update(overrides)
    entry = {key: value for key, value in entry.items() if value is not None}
    path = tmp_path / "cams.yaml"
    path.write_text(yaml.safe_dump({"cameras": [entry]}))
    return path


@pytest.mark.parametrize(
    ("overrides", "message"),
    [
        ({"K": [[-1000.0, 0, 719.5], [0, 1000.0, 539.5], [0, 0, 1]]}, r"camera 'north': focal lengths fx, fy must be > 0"),
        ({"K": [[1000.0, 0, 719.5], [0, 1000.0, 539.5]]}, r"camera 'north': K: expected shape \(3, 3\)"),
        ({"K": [[1000.0, 0, 2000.0], [0, 1000.0, 539.5], [0, 0, 1]]}, r"camera 'north': principal point"),
        ({"distortion": [0.1, 0.2, 0.3]}, r"camera 'north': distortion needs 4, 5, 8, 12, 14 coefficients, got 3"),
        ({"R_WC": [[1.0, 0.1, 0], [0, 1, 0], [0, 0, 1]]}, r"camera 'north': R_WC must be a rotation"),
        ({"R_WC": [[-1.0, 0, 0], [0, 1, 0], [0, 0, 1]]}, r"camera 'north': R_WC must be a rotation"),
        ({"p_WC": [-3.0, 0.0, 1.0]}, r"camera 'north': p_WC = \[-3.0, 0.0, 1.0\] m is inside the court"),
        ({"p_WC": [-8.0, 0.0, 5.0]}, r"camera 'north': p_WC z = 5.0 m"),
        ({"p_WC": [-8.0, 0.0, "high"]}, r"camera 'north': p_WC: expected numbers"),
        ({"resolution": [1440]}, r"camera 'north': resolution must be \[width, height\]"),
        ({"p_WC": None}, r"camera 'north': missing field\(s\) \['p_WC'\]"),
        ({"focal": 8}, r"camera 'north': .*unknown field\(s\) \['focal'\]"),
        ({"name": ""}, r"cameras\[0\]: 'name' must be a non-empty string"),
    ],
)
def test_bad_calibration_files_name_camera_and_field(tmp_path, overrides, message):
    path = write_camera(tmp_path, **overrides)
    with pytest.raises(ConfigError, match=message) as error:
        load_cameras(path)
    assert str(path) in str(error.value)


def test_bad_calibration_file_structure(tmp_path):
    with pytest.raises(ConfigError, match="not found"):
        load_cameras(tmp_path / "missing.yaml")
    path = tmp_path / "empty.yaml"
    path.write_text("cameras: []\n")
    with pytest.raises(ConfigError, match="top-level 'cameras' list"):
        load_cameras(path)
    path.write_text("cameras: [unclosed\n")
    with pytest.raises(ConfigError, match="not valid YAML"):
        load_cameras(path)


def test_duplicate_camera_names_are_rejected():
    with pytest.raises(ConfigError, match=r"repeated: \['end'\]"):
        validate_camera_array([camera_along_x(), camera_along_x()])
