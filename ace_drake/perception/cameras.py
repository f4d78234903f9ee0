"""The frame (APS) cameras: camera models, calibration files, projection of the ball, visibility
and the detection noise model (paper, Methods *Ball triangulation*; notes.md *Perception*).

The real system has nine cameras with Sony IMX273 sensors (1440 x 1080 px, 3.45 um pixels) on
towers outside the court (paper, Fig. 2a), triggered together at 200 Hz. A camera here is the
OpenCV model: intrinsics K (px), distortion coefficients in OpenCV's order (k1, k2, p1, p2[, k3
...]) and the pose X_WC of the camera frame C in world, C in OpenCV's convention (x right, y down,
z along the optical axis; Drake's camera frame is the same). Pixel coordinates follow OpenCV and
Drake: the centre of the top-left pixel is (0, 0).

All functions take NumPy arrays, work on batches of points (``(N, 3)``) and loop over cameras
only where OpenCV takes one pose per call. Nothing here knows Drake.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from pathlib import Path

import cv2
import numpy as np
import yaml

from ace_drake.config import MODELS_DIR, ConfigError
from ace_drake.physics.params import TableParams

SENSOR_WIDTH_PX = 1440  # paper, *Ball triangulation*: 1,440 x 1,080 pixel images
SENSOR_HEIGHT_PX = 1080
PIXEL_PITCH = 3.45e-6  # m, Sony IMX273 (paper, main text: the APS cameras' sensor)
BALL_RADIUS = 0.02  # m (DESIGN.md)
DEFAULT_CALIBRATION = MODELS_DIR / "cameras.yaml"
ORTHONORMAL_TOLERANCE = 1e-6  # max |R^T R - I| entry accepted for a rotation read from a file
DISTORTION_LENGTHS = (4, 5, 8, 12, 14)  # the coefficient counts OpenCV accepts


# ----------------------------------------------------------------------------------------------
# The court and the occluders
# ----------------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class PlayingArea:
    """The court the cameras must stand outside of (paper, Fig. 2a: towers outside the play area).

    length, width: the floor rectangle centred on the table, m (ITTF minimum for international
    play, 14 x 7 m; the paper's hall is 7 x 7 x 5 m on the player's side). ceiling: the hall's
    height above the floor, m. floor_depth: the floor below the world origin (the playing
    surface), m.
    """

    length: float = 14.0
    width: float = 7.0
    ceiling: float = 5.0
    floor_depth: float = 0.76

    def inside(self, p_W: np.ndarray) -> np.ndarray:
        """Whether points (..., 3), m, stand over the court's floor rectangle."""
        p_W = np.asarray(p_W, dtype=float)
        return (np.abs(p_W[..., 0]) < 0.5 * self.length) & (np.abs(p_W[..., 1]) < 0.5 * self.width)


@dataclasses.dataclass(frozen=True)
class OccluderBox:
    """An opaque box: pose of its centre frame B in world (R_WB (3, 3), p_WB (3,), m) and its half
    extents along B's axes (3,), m."""

    p_WB: np.ndarray
    half_extents: np.ndarray
    R_WB: np.ndarray = dataclasses.field(default_factory=lambda: np.eye(3))

    def __post_init__(self) -> None:
        for name, shape in (("p_WB", (3,)), ("half_extents", (3,)), ("R_WB", (3, 3))):
            value = np.asarray(getattr(self, name), dtype=float)
            if value.shape != shape or not np.all(np.isfinite(value)):
                raise ValueError(f"OccluderBox.{name}: expected finite {shape}, got {getattr(self, name)!r}")
            object.__setattr__(self, name, value)
        if not np.all(self.half_extents > 0):
            raise ValueError(f"OccluderBox.half_extents must be > 0, got {self.half_extents}")


@dataclasses.dataclass(frozen=True)
class OccluderSphere:
    """An opaque sphere: centre p_WS (3,), m, and radius, m."""

    p_WS: np.ndarray
    radius: float

    def __post_init__(self) -> None:
        center = np.asarray(self.p_WS, dtype=float)
        if center.shape != (3,) or not np.all(np.isfinite(center)) or not self.radius > 0:
            raise ValueError(f"OccluderSphere: expected a finite centre (3,) and radius > 0, got {self.p_WS!r}, {self.radius}")
        object.__setattr__(self, "p_WS", center)


Occluder = OccluderBox | OccluderSphere


def table_occluder(table: TableParams | None = None) -> OccluderBox:
    """The table as a solid box from the floor to the playing surface (2.74 x 1.525 x 0.76 m by
    default): cameras see neither through its top nor under it."""
    table = table or TableParams()
    half = np.array([0.5 * table.length, 0.5 * table.width, 0.5 * table.surface_height])
    return OccluderBox(p_WB=np.array([0.0, 0.0, -0.5 * table.surface_height]), half_extents=half)


# ----------------------------------------------------------------------------------------------
# The camera model
# ----------------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True, eq=False)
class Camera:
    """One pinhole camera with OpenCV lens distortion.

    name: unique in a camera array.
    K (3, 3): intrinsics [[fx, s, cx], [0, fy, cy], [0, 0, 1]], px.
    distortion (4, 5, 8, 12 or 14,): OpenCV coefficients (k1, k2, p1, p2[, k3, ...]).
    R_WC (3, 3), p_WC (3,): pose of the camera frame C in world (m); C's z axis is the optical
        axis, x points right and y down in the image.
    width, height: image size, px.

    Bad values raise ConfigError naming the camera and the field.
    """

    name: str
    K: np.ndarray
    distortion: np.ndarray
    R_WC: np.ndarray
    p_WC: np.ndarray
    width: int = SENSOR_WIDTH_PX
    height: int = SENSOR_HEIGHT_PX

    def __post_init__(self) -> None:
        where = f"camera {self.name!r}"
        if not isinstance(self.name, str) or not self.name:
            raise ConfigError(f"camera name must be a non-empty string, got {self.name!r}")
        for name in ("width", "height"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value <= 0:
                raise ConfigError(f"{where}: {name} must be a positive integer (px), got {value!r}")
            object.__setattr__(self, name, int(value))
        K = _finite_array(self.K, (3, 3), f"{where}: K")
        distortion = _finite_array(self.distortion, None, f"{where}: distortion").ravel()
        R_WC = _finite_array(self.R_WC, (3, 3), f"{where}: R_WC")
        p_WC = _finite_array(self.p_WC, (3,), f"{where}: p_WC")
        if not (K[0, 0] > 0 and K[1, 1] > 0):
            raise ConfigError(f"{where}: focal lengths fx, fy must be > 0 px, got {K[0, 0]} and {K[1, 1]}")
        if K[1, 0] != 0 or K[2, 0] != 0 or K[2, 1] != 0 or K[2, 2] != 1:
            raise ConfigError(f"{where}: K must be upper triangular with K[2, 2] = 1, got {K.tolist()}")
        if not (0 <= K[0, 2] <= self.width - 1 and 0 <= K[1, 2] <= self.height - 1):
            raise ConfigError(
                f"{where}: principal point ({K[0, 2]}, {K[1, 2]}) px lies outside the {self.width} x {self.height} image"
            )
        if distortion.size not in DISTORTION_LENGTHS:
            raise ConfigError(f"{where}: distortion needs {', '.join(map(str, DISTORTION_LENGTHS))} coefficients, got {distortion.size}")
        orthonormality_error = np.abs(R_WC.T @ R_WC - np.eye(3)).max()
        if orthonormality_error > ORTHONORMAL_TOLERANCE or np.linalg.det(R_WC) < 0:
            raise ConfigError(
                f"{where}: R_WC must be a rotation (orthonormal, determinant +1); |R^T R - I| = "
                f"{orthonormality_error:.3g}, det = {np.linalg.det(R_WC):.6g}"
            )
        for name, value in (("K", K), ("distortion", distortion), ("R_WC", R_WC), ("p_WC", p_WC)):
            value.setflags(write=False)
            object.__setattr__(self, name, value)
        # OpenCV's extrinsics: p_C = R_CW p_W + t, as a Rodrigues vector and a translation.
        R_CW = R_WC.T
        rvec, _ = cv2.Rodrigues(R_CW)
        object.__setattr__(self, "R_CW", R_CW)
        object.__setattr__(self, "rvec", rvec.ravel())
        object.__setattr__(self, "tvec", -R_CW @ p_WC)

    @property
    def focal_length_px(self) -> float:
        """The smaller of fx and fy, px."""
        return float(min(self.K[0, 0], self.K[1, 1]))

    def project(self, p_W: np.ndarray) -> np.ndarray:
        """Pixels (N, 2) of world points p_W (N, 3), m, with lens distortion (``cv2.projectPoints``).
        Points behind the camera get meaningless pixels: check ``depth``."""
        points = np.ascontiguousarray(np.asarray(p_W, dtype=float).reshape(-1, 1, 3))
        pixels, _ = cv2.projectPoints(points, self.rvec, self.tvec, self.K, self.distortion)
        return pixels.reshape(-1, 2)

    def project_with_jacobian(self, p_W: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Pixels (N, 2) and their derivatives with respect to the world point, (N, 2, 3) px/m.

        OpenCV returns d(pixel)/d(tvec); since p_C = R_CW p_W + tvec, d(pixel)/d(p_W) =
        d(pixel)/d(tvec) R_CW."""
        points = np.ascontiguousarray(np.asarray(p_W, dtype=float).reshape(-1, 1, 3))
        pixels, jacobian = cv2.projectPoints(points, self.rvec, self.tvec, self.K, self.distortion)
        d_pixel_d_tvec = jacobian[:, 3:6].reshape(-1, 2, 3)
        return pixels.reshape(-1, 2), d_pixel_d_tvec @ self.R_CW

    def to_camera_frame(self, p_W: np.ndarray) -> np.ndarray:
        """p_C (N, 3), m: world points in the camera frame."""
        return np.asarray(p_W, dtype=float).reshape(-1, 3) @ self.R_CW.T + self.tvec

    def scaled(self, scale: float) -> Camera:
        """This camera for images resized by ``scale`` (e.g. 0.25 for 360 x 270 renders): pixel
        centres map as u' = (u + 0.5) scale - 0.5; the distortion is unchanged (it acts on
        normalised coordinates)."""
        if not scale > 0:
            raise ValueError(f"Camera.scaled: scale must be > 0, got {scale}")
        width, height = round(self.width * scale), round(self.height * scale)
        K = self.K.copy()
        K[0, 0] *= scale
        K[0, 1] *= scale
        K[1, 1] *= scale
        K[0, 2] = (K[0, 2] + 0.5) * scale - 0.5
        K[1, 2] = (K[1, 2] + 0.5) * scale - 0.5
        return Camera(self.name, K, self.distortion.copy(), self.R_WC.copy(), self.p_WC.copy(), width, height)


def camera_looking_at(
    name: str,
    p_WC: np.ndarray,
    target_W: np.ndarray,
    focal_length_px: float,
    distortion: Sequence[float] = (0.0, 0.0, 0.0, 0.0, 0.0),
    width: int = SENSOR_WIDTH_PX,
    height: int = SENSOR_HEIGHT_PX,
) -> Camera:
    """A camera at p_WC (m) whose optical axis points at target_W (m), image x axis horizontal
    (no roll), square pixels of focal length ``focal_length_px`` and the principal point at the
    image centre."""
    p_WC = np.asarray(p_WC, dtype=float)
    z_C = np.asarray(target_W, dtype=float) - p_WC
    z_C /= np.linalg.norm(z_C)
    R_WC = rotation_from_optical_axis(z_C)
    K = np.array([[focal_length_px, 0.0, 0.5 * (width - 1)], [0.0, focal_length_px, 0.5 * (height - 1)], [0.0, 0.0, 1.0]])
    return Camera(name, K, np.asarray(distortion, dtype=float), R_WC, p_WC, width, height)


def rotation_from_optical_axis(z_C: np.ndarray) -> np.ndarray:
    """R_WC with the optical axis along z_C (3,) (world) and no roll: the image's x axis is
    horizontal, y points down. z_C must not be vertical."""
    z_C = np.asarray(z_C, dtype=float) / np.linalg.norm(z_C)
    x_C = np.cross(z_C, [0.0, 0.0, 1.0])
    if np.linalg.norm(x_C) < 1e-9:
        raise ValueError(f"rotation_from_optical_axis: the optical axis {z_C} is vertical; the roll is undefined")
    x_C /= np.linalg.norm(x_C)
    y_C = np.cross(z_C, x_C)
    return np.column_stack([x_C, y_C, z_C])


def rotation_from_yaw_pitch(yaw: float, pitch: float) -> np.ndarray:
    """R_WC of a camera with no roll whose optical axis has heading ``yaw`` (rad, from +x towards
    +y) and elevation ``pitch`` (rad, negative looking down)."""
    z_C = np.array([math.cos(pitch) * math.cos(yaw), math.cos(pitch) * math.sin(yaw), math.sin(pitch)])
    return rotation_from_optical_axis(z_C)


# ----------------------------------------------------------------------------------------------
# Projection and visibility over a camera array
# ----------------------------------------------------------------------------------------------


def project_points(cameras: Sequence[Camera], p_W: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pixels (C, N, 2) of world points p_W (N, 3), m, in each of the C cameras, and their depths
    (C, N), m, along each optical axis (negative behind the camera)."""
    p_W = np.asarray(p_W, dtype=float).reshape(-1, 3)
    pixels = np.stack([camera.project(p_W) for camera in cameras]) if cameras else np.zeros((0, len(p_W), 2))
    depth = np.stack([camera.to_camera_frame(p_W)[:, 2] for camera in cameras]) if cameras else np.zeros((0, len(p_W)))
    return pixels, depth


def projected_ball_radius(cameras: Sequence[Camera], p_W: np.ndarray, ball_radius: float = BALL_RADIUS) -> np.ndarray:
    """The ball's projected radius (C, N), px: the minor semi-axis of its image, f tan(theta) d / z
    with theta = asin(r / d) the sphere's angular radius, d its distance and z its depth (pinhole,
    distortion neglected). Zero behind a camera or when the camera is inside the ball."""
    p_W = np.asarray(p_W, dtype=float).reshape(-1, 3)
    radius = np.zeros((len(cameras), len(p_W)))
    for index, camera in enumerate(cameras):
        p_C = camera.to_camera_frame(p_W)
        distance = np.linalg.norm(p_C, axis=1)
        valid = (p_C[:, 2] > 0) & (distance > ball_radius)
        tan_theta = ball_radius / np.sqrt(np.maximum(distance**2 - ball_radius**2, 1e-300))
        radius[index] = np.where(valid, camera.focal_length_px * tan_theta * distance / np.where(valid, p_C[:, 2], 1.0), 0.0)
    return radius


def segments_blocked(origins: np.ndarray, targets: np.ndarray, occluders: Sequence[Occluder]) -> np.ndarray:
    """Whether the segments from each origin (C, 3) to each target (N, 3), m, pass through any
    occluder: (C, N) bool. Boxes use the slab test in the box's frame; spheres the closest point
    of the segment. Written here because OpenCV has no ray casting and the test is a few lines."""
    origins = np.asarray(origins, dtype=float).reshape(-1, 3)
    targets = np.asarray(targets, dtype=float).reshape(-1, 3)
    blocked = np.zeros((len(origins), len(targets)), dtype=bool)
    for occluder in occluders:
        if isinstance(occluder, OccluderBox):
            blocked |= _segments_hit_box(origins, targets, occluder)
        elif isinstance(occluder, OccluderSphere):
            blocked |= _segments_hit_sphere(origins, targets, occluder)
        else:
            raise TypeError(f"segments_blocked: unknown occluder {occluder!r}")
    return blocked


def _segments_hit_box(origins: np.ndarray, targets: np.ndarray, box: OccluderBox) -> np.ndarray:
    start = (origins - box.p_WB) @ box.R_WB  # (C, 3) in the box frame
    end = (targets - box.p_WB) @ box.R_WB  # (N, 3)
    direction = end[None, :, :] - start[:, None, :]  # (C, N, 3)
    lower = -box.half_extents - start[:, None, :]
    upper = box.half_extents - start[:, None, :]
    with np.errstate(divide="ignore", invalid="ignore"):
        t_lower = lower / direction
        t_upper = upper / direction
    parallel = direction == 0
    # A segment parallel to a slab is inside it for all t or for none.
    inside_slab = (lower <= 0) & (upper >= 0)
    t_enter = np.where(parallel, np.where(inside_slab, -np.inf, np.inf), np.minimum(t_lower, t_upper)).max(axis=2)
    t_exit = np.where(parallel, np.where(inside_slab, np.inf, -np.inf), np.maximum(t_lower, t_upper)).min(axis=2)
    return (t_enter <= t_exit) & (t_exit >= 0.0) & (t_enter <= 1.0)


def _segments_hit_sphere(origins: np.ndarray, targets: np.ndarray, sphere: OccluderSphere) -> np.ndarray:
    direction = targets[None, :, :] - origins[:, None, :]
    to_center = sphere.p_WS - origins[:, None, :]
    length_squared = np.maximum(np.einsum("cnk,cnk->cn", direction, direction), 1e-300)
    t = np.clip(np.einsum("cnk,cnk->cn", to_center, direction) / length_squared, 0.0, 1.0)
    closest = origins[:, None, :] + t[..., None] * direction
    return np.linalg.norm(closest - sphere.p_WS, axis=2) < sphere.radius


def visibility(
    cameras: Sequence[Camera],
    p_W: np.ndarray,
    occluders: Sequence[Occluder] | None = None,
    ball_radius: float = BALL_RADIUS,
    pixels: np.ndarray | None = None,
) -> np.ndarray:
    """Whether each camera sees the ball centred at each point p_W (N, 3), m: (C, N) bool.

    Seen means in front of the camera (depth > ball radius), its whole projected disc inside the
    image (centre at least one projected radius from the border), and the line of sight from the
    camera centre to the ball's centre blocked by no occluder (default: the table,
    ``table_occluder``; pass ``()`` for none, or add the robot's links). ``pixels`` (C, N, 2) may
    pass the projections when the caller has them already.
    """
    p_W = np.asarray(p_W, dtype=float).reshape(-1, 3)
    if occluders is None:
        occluders = (table_occluder(),)
    if pixels is None:
        pixels, depth = project_points(cameras, p_W)
    else:
        depth = np.stack([camera.to_camera_frame(p_W)[:, 2] for camera in cameras])
    radius = projected_ball_radius(cameras, p_W, ball_radius)
    size = np.array([[camera.width, camera.height] for camera in cameras], dtype=float)[:, None, :]
    with np.errstate(invalid="ignore"):
        in_frame = np.all((pixels - radius[..., None] >= -0.5) & (pixels + radius[..., None] <= size - 0.5), axis=2)
    seen = (depth > ball_radius) & in_frame
    if occluders:
        origins = np.array([camera.p_WC for camera in cameras])
        seen &= ~segments_blocked(origins, p_W, occluders)
    return seen


def simulate_detections(
    cameras: Sequence[Camera],
    p_WB: np.ndarray,
    rng: np.random.Generator,
    pixel_noise_sigma: float,
    dropout_probability: float,
    occluders: Sequence[Occluder] | None = None,
    ball_radius: float = BALL_RADIUS,
    ideal_pixels: np.ndarray | None = None,
) -> np.ndarray:
    """One trigger of the camera array: each camera's detected ball centre (C, 2), px, NaN where
    it has none.

    A camera detects the ball when it sees it (``visibility``) and the detection does not drop
    out (probability ``dropout_probability``, independently per camera); the detected centre is
    the projection of the ball's centre plus zero-mean Gaussian noise of ``pixel_noise_sigma`` px
    per axis. ``ideal_pixels`` (C, 2) replaces the projection (e.g. centres found in rendered
    images, NaN where none). The generator draws the same numbers whatever is visible (noise (C,
    2), then dropout (C,)), so a seed fixes the whole sequence.
    """
    p_WB = np.asarray(p_WB, dtype=float).reshape(1, 3)
    if not 0.0 <= dropout_probability <= 1.0:
        raise ValueError(f"simulate_detections: dropout_probability must be in [0, 1], got {dropout_probability}")
    if not pixel_noise_sigma >= 0.0:
        raise ValueError(f"simulate_detections: pixel_noise_sigma must be >= 0 px, got {pixel_noise_sigma}")
    noise = rng.normal(0.0, 1.0, size=(len(cameras), 2)) * pixel_noise_sigma
    kept = rng.random(len(cameras)) >= dropout_probability
    if ideal_pixels is None:
        pixels, _ = project_points(cameras, p_WB)
        seen = visibility(cameras, p_WB, occluders, ball_radius, pixels=pixels)[:, 0]
        pixels = pixels[:, 0, :]
    else:
        pixels = np.asarray(ideal_pixels, dtype=float).reshape(len(cameras), 2)
        seen = np.all(np.isfinite(pixels), axis=1)
    detected = seen & kept
    return np.where(detected[:, None], pixels + noise, np.nan)


@dataclasses.dataclass(frozen=True, eq=False)
class DetectionFrame:
    """The ball detections of one trigger of the camera array, as released to the triangulator.

    sequence: trigger number, 1, 2, ... (0: no frame yet).
    capture_time: s, the trigger (exposure) time.
    release_time: s, when the detections were published (capture_time + latency).
    camera_names: the C cameras, in calibration order.
    pixels (C, 2): detected ball centres, px (distorted image coordinates), NaN where a camera has
        no detection.
    """

    sequence: int = 0
    capture_time: float = 0.0
    release_time: float = 0.0
    camera_names: tuple[str, ...] = ()
    pixels: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros((0, 2)))

    def __post_init__(self) -> None:
        pixels = np.array(self.pixels, dtype=float).reshape(-1, 2)
        if len(pixels) != len(self.camera_names):
            raise ValueError(f"DetectionFrame: {len(self.camera_names)} cameras but {len(pixels)} pixel rows")
        if self.release_time < self.capture_time:
            raise ValueError(f"DetectionFrame {self.sequence}: released at {self.release_time} s before its capture at {self.capture_time} s")
        pixels.setflags(write=False)
        object.__setattr__(self, "pixels", pixels)

    @property
    def detected(self) -> np.ndarray:
        """(C,) bool: which cameras detected the ball."""
        return np.all(np.isfinite(self.pixels), axis=1)

    def __deepcopy__(self, memo) -> DetectionFrame:
        # Immutable (frozen, read-only pixels): Drake clones abstract values by deep copy, which
        # would otherwise copy every frame at every state update.
        return self


# ----------------------------------------------------------------------------------------------
# Calibration files
# ----------------------------------------------------------------------------------------------


def load_cameras(path: str | Path = DEFAULT_CALIBRATION, playing_area: PlayingArea | None = None) -> tuple[Camera, ...]:
    """Reads a calibration file (``models/cameras.yaml``; format in ``save_cameras``) and checks
    it with ``validate_camera_array``. Errors raise ConfigError naming the file, the camera and the
    field."""
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"camera calibration file not found: {path}")
    try:
        data = yaml.safe_load(path.read_text())
    except yaml.YAMLError as error:
        raise ConfigError(f"{path}: not valid YAML: {error}") from None
    if not isinstance(data, dict) or not isinstance(data.get("cameras"), list) or not data["cameras"]:
        raise ConfigError(f"{path}: expected a top-level 'cameras' list with at least one camera")
    try:
        cameras = tuple(_camera_from_dict(entry, index) for index, entry in enumerate(data["cameras"]))
        validate_camera_array(cameras, playing_area)
    except ConfigError as error:
        raise ConfigError(f"{path}: {error}") from None
    return cameras


def validate_camera_array(cameras: Sequence[Camera], playing_area: PlayingArea | None = None) -> None:
    """Checks a camera array: unique names, every camera outside the court's floor rectangle
    (paper, Fig. 2a), above the floor and below the ceiling. Raises ConfigError naming the camera."""
    playing_area = playing_area or PlayingArea()
    names = [camera.name for camera in cameras]
    duplicates = sorted({name for name in names if names.count(name) > 1})
    if duplicates:
        raise ConfigError(f"camera names must be unique, repeated: {duplicates}")
    for camera in cameras:
        if playing_area.inside(camera.p_WC):
            raise ConfigError(
                f"camera {camera.name!r}: p_WC = {camera.p_WC.tolist()} m is inside the court "
                f"(|x| < {0.5 * playing_area.length}, |y| < {0.5 * playing_area.width} m); cameras stand outside it"
            )
        height_above_floor = camera.p_WC[2] + playing_area.floor_depth
        if not 0.0 < height_above_floor <= playing_area.ceiling:
            raise ConfigError(
                f"camera {camera.name!r}: p_WC z = {camera.p_WC[2]} m puts it {height_above_floor:.3f} m above the floor, "
                f"outside (0, {playing_area.ceiling}] m"
            )


def save_cameras(path: str | Path, cameras: Sequence[Camera], header: str = "") -> None:
    """Writes a calibration file that ``load_cameras`` reads back exactly:

    ```yaml
    cameras:
      - name: north_0
        resolution: [1440, 1080]          # width, height, px
        K: [[fx, 0, cx], [0, fy, cy], [0, 0, 1]]   # px
        distortion: [k1, k2, p1, p2, k3]  # OpenCV order
        R_WC: [[...], [...], [...]]       # columns: the camera's x (right), y (down), z (optical axis) in world
        p_WC: [x, y, z]                   # m, world (origin at the centre of the playing surface, z up)
    ```
    ``header`` is written first as comment lines."""
    entries = [
        {
            "name": camera.name,
            "resolution": [camera.width, camera.height],
            "K": camera.K.tolist(),
            "distortion": camera.distortion.tolist(),
            "R_WC": camera.R_WC.tolist(),
            "p_WC": camera.p_WC.tolist(),
        }
        for camera in cameras
    ]
    comments = "".join(f"# {line}".rstrip() + "\n" for line in header.splitlines())
    body = yaml.safe_dump({"cameras": entries}, sort_keys=False, default_flow_style=None, width=200)
    Path(path).write_text(comments + body)


def _camera_from_dict(entry, index: int) -> Camera:
    if not isinstance(entry, dict):
        raise ConfigError(f"cameras[{index}]: expected a mapping, got {entry!r}")
    name = entry.get("name")
    where = f"camera {name!r}" if isinstance(name, str) and name else f"cameras[{index}]"
    if not isinstance(name, str) or not name:
        raise ConfigError(f"{where}: 'name' must be a non-empty string, got {name!r}")
    expected = {"name", "resolution", "K", "distortion", "R_WC", "p_WC"}
    missing, unknown = sorted(expected - set(entry)), sorted(set(entry) - expected)
    if missing or unknown:
        raise ConfigError(f"{where}: missing field(s) {missing}, unknown field(s) {unknown}; expected {sorted(expected)}")
    resolution = entry["resolution"]
    if not (isinstance(resolution, list) and len(resolution) == 2 and all(isinstance(v, int) and not isinstance(v, bool) for v in resolution)):
        raise ConfigError(f"{where}: resolution must be [width, height] integers (px), got {resolution!r}")
    arrays = {key: _numeric(entry[key], f"{where}: {key}") for key in ("K", "distortion", "R_WC", "p_WC")}
    return Camera(name, arrays["K"], arrays["distortion"], arrays["R_WC"], arrays["p_WC"], resolution[0], resolution[1])


def _numeric(value, where: str) -> np.ndarray:
    try:
        array = np.array(value, dtype=float)
    except (TypeError, ValueError):
        raise ConfigError(f"{where}: expected numbers, got {value!r}") from None
    return array


def _finite_array(value, shape: tuple[int, ...] | None, where: str) -> np.ndarray:
    try:
        array = np.array(value, dtype=float)
    except (TypeError, ValueError):
        raise ConfigError(f"{where}: expected numbers, got {value!r}") from None
    if shape is not None and array.shape != shape:
        raise ConfigError(f"{where}: expected shape {shape}, got {array.shape}")
    if not np.all(np.isfinite(array)):
        raise ConfigError(f"{where}: values must be finite, got {array.tolist()}")
    return array
