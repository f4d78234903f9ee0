"""ApsCameraArray: the nine frame cameras' ball detections, triggered at 200 Hz and released after
the triangulation latency (paper, Methods *Ball triangulation*)."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence

import cv2
import numpy as np
from pydrake.common.value import AbstractValue
from pydrake.geometry import ClippingRange, ColorRenderCamera, DepthRange, DepthRenderCamera, FrameId, RenderCameraCore
from pydrake.math import RigidTransform, RotationMatrix
from pydrake.systems.framework import BasicVector, LeafSystem
from pydrake.systems.sensors import CameraInfo, ImageRgba8U, RgbdSensor

from ace_drake.perception.cameras import BALL_RADIUS, Camera, DetectionFrame, Occluder, simulate_detections, table_occluder
from ace_drake.perception.detection import BallColorThreshold, detect_ball
from ace_drake.perception.params import CameraParams
from ace_drake.systems.random_seed import declare_seed_port, episode_seed

RENDER_CLIPPING = (0.05, 40.0)  # m, near and far planes of the rendering cameras
RENDER_DEPTH_RANGE = (0.06, 39.0)  # m, the (unused) depth camera's range, inside the clipping
TIME_TOLERANCE = 1e-9  # s; event times are sums of periods and offsets in floating point
# Drake's VTK renderer draws a point whose CameraInfo projection is (u, v) at the pixel whose
# centre is (u - 0.5, v - 0.5) (measured: tests/test_aps_camera_array.py), i.e. it treats the
# principal point as measured from the image's corner rather than from the first pixel's centre as
# CameraInfo documents and OpenCV does. Render cameras get the principal point shifted by this, so
# that rendered images follow the OpenCV convention of ``Camera``.
RENDER_PRINCIPAL_POINT_SHIFT = 0.5  # px


def render_cameras(camera: Camera, render_scale: float, renderer_name: str) -> tuple[ColorRenderCamera, DepthRenderCamera]:
    """Drake's colour and depth render cameras for ``camera`` at ``render_scale`` times its
    resolution: the scaled pinhole intrinsics (``Camera.scaled``) without lens distortion, which
    Drake's renderers do not model (``ApsCameraArray`` applies it to the detected centres)."""
    scaled = camera.scaled(render_scale)
    shift = RENDER_PRINCIPAL_POINT_SHIFT
    info = CameraInfo(scaled.width, scaled.height, scaled.K[0, 0], scaled.K[1, 1], scaled.K[0, 2] + shift, scaled.K[1, 2] + shift)
    core = RenderCameraCore(renderer_name, info, ClippingRange(*RENDER_CLIPPING), RigidTransform())
    return ColorRenderCamera(core, show_window=False), DepthRenderCamera(core, DepthRange(*RENDER_DEPTH_RANGE))


def make_rgbd_sensor(camera: Camera, render_scale: float, renderer_name: str, world_frame_id: FrameId) -> RgbdSensor:
    """An RgbdSensor fixed in world at the camera's pose X_WC (Drake's camera frame, like
    OpenCV's, has z along the optical axis, x right and y down), rendering with ``renderer_name``
    at ``render_scale`` times the camera's resolution. Connect its ``color_image`` output to the
    ApsCameraArray's ``color_image_<camera name>`` input and its query input to the SceneGraph."""
    color, depth = render_cameras(camera, render_scale, renderer_name)
    X_WC = RigidTransform(RotationMatrix(camera.R_WC), camera.p_WC)
    return RgbdSensor(world_frame_id, X_WC, color, depth)


@dataclasses.dataclass(frozen=True)
class _ArrayState:
    """The camera array's state: frames captured and not yet released (capture order), the latest
    released frame and the number of triggers so far. Immutable."""

    pending: tuple[DetectionFrame, ...]
    released: DetectionFrame
    captures: int

    def __deepcopy__(self, memo) -> _ArrayState:
        return self  # immutable: spare Drake's deep copy of abstract state at every update


class ApsCameraArray(LeafSystem):
    """The frame-camera array (paper, Methods *Ball triangulation*): at each hardware trigger every
    camera detects the ball or not, and the trigger's detections are released together after the
    triangulation latency.

    Input ports:
        ball_state (9,): [p_WB (m), v_WB (m/s), w_WB (rad/s)] in world, from the BallPlant; the
            analytic mode projects p_WB.
        occluders (abstract tuple[OccluderBox | OccluderSphere]), optional: opaque shapes in world
            (e.g. the robot's links) besides the table, which always occludes. Analytic mode only.
        color_image_<camera name> (abstract ImageRgba8U), one per camera, rendered mode only: that
            camera's image at ``params.render_scale`` of 1440 x 1080 (``make_rgbd_sensor``).
        random_seed (1,), random uniform: the seed of the pixel noise and dropout, drawn by
            Drake's random context (``systems.random_seed``). Unconnected: the seed parameter.
    Output ports:
        detections (abstract DetectionFrame): the latest released trigger: sequence number,
            capture time (s), release time (s) and each camera's detected ball centre in px (NaN:
            none). Sequence 0 with no detections before the first release.
    State:
        abstract: the captured, unreleased frames; the latest released frame; the trigger count.
    Parameters:
        numeric (1,): the seed of the pixel noise and dropout while random_seed is unconnected.
    Events:
        periodic unrestricted update at ``params.trigger_rate`` (200 Hz, offset 0): capture. Per
            camera, analytic mode: project the ball's centre (cv2.projectPoints), keep it if
            visible (in front, whole disc in frame, line of sight clear of the table and the
            occluders); rendered mode: detect the ball in the camera's image (OpenCV) and apply the
            lens distortion to the centre. Then add Gaussian noise (``pixel_noise_sigma`` px) and
            drop detections with ``dropout_probability``, from numpy's generator seeded with
            [seed, trigger number]; the frame is due at capture time + ``params.latency``.
        periodic unrestricted update at the same rate, offset latency mod period: release of the
            due frames (both events run the same idempotent update, so they may coincide).

    The trigger number and the seed fix each frame's random numbers, so the same seed gives the
    same detections bit for bit, whatever else the diagram evaluates.
    """

    def __init__(
        self,
        cameras: Sequence[Camera],
        params: CameraParams | None = None,
        seed: int = 0,
        occluders: Sequence[Occluder] | None = None,
        ball_radius: float = BALL_RADIUS,
        ball_color: BallColorThreshold | None = None,
    ):
        """Args: cameras, the calibrated array (``cameras.load_cameras``); params, rate, latency,
        noise, dropout and mode; seed, the default of the seed parameter; occluders, static shapes
        hiding the ball (default: the table, ``table_occluder``); ball_radius, m; ball_color, the
        rendered mode's detector thresholds."""
        super().__init__()
        if not cameras:
            raise ValueError("ApsCameraArray: needs at least one camera")
        self.cameras = tuple(cameras)
        self.params = params or CameraParams()
        self.camera_names = tuple(camera.name for camera in self.cameras)
        self._occluders = tuple(occluders) if occluders is not None else (table_occluder(),)
        self._ball_radius = ball_radius
        self._ball_color = ball_color
        self.period = 1.0 / self.params.trigger_rate

        initial = _ArrayState((), DetectionFrame(0, 0.0, 0.0, self.camera_names, np.full((len(self.cameras), 2), np.nan)), 0)
        self._state_index = self.DeclareAbstractState(AbstractValue.Make(initial))
        self._seed_index = self.DeclareNumericParameter(BasicVector([float(seed)]))
        self.ball_state_port = self.DeclareVectorInputPort("ball_state", 9)
        self.occluders_port = self.DeclareAbstractInputPort("occluders", AbstractValue.Make(()))
        self.random_seed_port = declare_seed_port(self)
        self.image_ports = {}
        if self.params.mode == "rendered":
            self.render_cameras = tuple(camera.scaled(self.params.render_scale) for camera in self.cameras)
            for camera in self.cameras:
                self.image_ports[camera.name] = self.DeclareAbstractInputPort(f"color_image_{camera.name}", AbstractValue.Make(ImageRgba8U()))
        self.detections_port = self.DeclareAbstractOutputPort(
            "detections",
            lambda: AbstractValue.Make(initial.released),
            self.CalcDetections,
            prerequisites_of_calc={self.abstract_state_ticket(self._state_index)},
        )
        self.DeclarePeriodicUnrestrictedUpdateEvent(self.period, 0.0, self.UpdateFrames)
        release_offset = math.fmod(self.params.latency, self.period)
        if TIME_TOLERANCE < release_offset < self.period - TIME_TOLERANCE:
            self.DeclarePeriodicUnrestrictedUpdateEvent(self.period, release_offset, self.UpdateFrames)

    # ------------------------------------------------------------------------------ set-up
    def SetSeed(self, context, seed: int) -> None:
        """Sets the seed of the pixel noise and dropout for this context, used while the
        random_seed input is unconnected (a diagram's random context seeds it otherwise)."""
        context.get_mutable_numeric_parameter(self._seed_index).SetAtIndex(0, float(seed))

    # ------------------------------------------------------------------------------ outputs
    def CalcDetections(self, context, output):
        output.set_value(self._state(context).released)

    # ------------------------------------------------------------------------------ update
    def UpdateFrames(self, context, state):
        """Captures a frame at a trigger instant, then releases every frame that is due."""
        time = context.get_time()
        current = self._state(context)
        pending, captures = current.pending, current.captures
        trigger = round(time / self.period)
        if abs(time - trigger * self.period) <= TIME_TOLERANCE:
            captures += 1
            frame = DetectionFrame(captures, time, time + self.params.latency, self.camera_names, self._Capture(context, captures))
            pending = pending + (frame,)
        due = tuple(frame for frame in pending if frame.release_time <= time + TIME_TOLERANCE)
        released = due[-1] if due else current.released
        pending = pending[len(due) :]
        state.get_mutable_abstract_state(self._state_index).set_value(_ArrayState(pending, released, captures))

    def _Capture(self, context, sequence: int) -> np.ndarray:
        """The detections (C, 2), px, of trigger ``sequence`` at the context's time."""
        seed = episode_seed(self.random_seed_port, context, context.get_numeric_parameter(self._seed_index).GetAtIndex(0))
        rng = np.random.default_rng([seed, sequence])
        p_WB = self.ball_state_port.Eval(context)[:3]
        ideal_pixels = self._DetectInImages(context) if self.params.mode == "rendered" else None
        occluders = self._occluders
        if self.occluders_port.HasValue(context):
            occluders = occluders + tuple(self.occluders_port.Eval(context))
        return simulate_detections(
            self.cameras, p_WB, rng, self.params.pixel_noise_sigma, self.params.dropout_probability,
            occluders, self._ball_radius, ideal_pixels,
        )

    def _DetectInImages(self, context) -> np.ndarray:
        """Ball centres (C, 2) found in the rendered images, mapped to the full-resolution image
        with lens distortion (px); NaN where the detector finds none."""
        pixels = np.full((len(self.cameras), 2), np.nan)
        for index, (camera, render_camera) in enumerate(zip(self.cameras, self.render_cameras)):
            port = self.image_ports[camera.name]
            if not port.HasValue(context):
                raise RuntimeError(
                    f"ApsCameraArray (rendered mode): input port {port.get_name()} is not connected; connect an "
                    "RgbdSensor's color_image output (make_rgbd_sensor) for every camera, or use the analytic mode"
                )
            image = port.Eval(context)
            detection = detect_ball(
                image.data, min_radius_px=0.5, max_radius_px=0.25 * render_camera.height, color=self._ball_color
            )
            if detection is None:
                continue
            # Render pixels -> normalised pinhole coordinates -> the real lens's pixels.
            K = render_camera.K
            y = (detection.center[1] - K[1, 2]) / K[1, 1]
            x = (detection.center[0] - K[0, 2] - K[0, 1] * y) / K[0, 0]
            distorted, _ = cv2.projectPoints(np.array([[[x, y, 1.0]]]), np.zeros(3), np.zeros(3), camera.K, camera.distortion)
            pixels[index] = distorted.ravel()
        return pixels

    def _state(self, context) -> _ArrayState:
        return context.get_abstract_state(self._state_index).get_value()
