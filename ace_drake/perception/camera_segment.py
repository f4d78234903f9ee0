"""The nine frame cameras and the triangulator over one control segment, for B environments at
once (paper, Methods *Ball triangulation*): the batched, segment-stepped counterpart of the
reference systems ``ApsCameraArray`` (analytic mode) + ``Triangulator`` (issue 29).

The reference's timing, which this module reproduces and its callers must follow:

- Triggers are on the ``1 / trigger_rate`` grid of the diagram's clock (200 Hz, offset 0): trigger
  k is captured at t_k = k * period (``trigger_times``). The array numbers its triggers 1, 2, ...
  from the episode's start (the first trigger of an episode that starts at time 0 is number 1).
- Trigger number n of an episode with seed s draws its noise from its own generator,
  ``numpy.random.default_rng([s, n])``: first the pixel noise (C, 2) (standard normal times
  ``pixel_noise_sigma``), then the dropout uniforms (C,), whatever is visible
  (``cameras.simulate_detections``). s is the 64 bits of the array's ``random_seed`` port
  (``systems.random_seed.episode_seed``) at the trigger; nothing else advances a stream, so the
  draws of an (environment, trigger) pair do not depend on any other pair.
- A trigger's detections are released at t_k + latency (10.2 ms) and triangulated then: the
  Triangulator's measurement has capture time t_k, release time t_k + latency, the triangulated
  position and covariance (``triangulation.triangulate``), and sequence number one above the
  previous measurement's (release order, 1, 2, ...); a trigger with fewer than ``min_views``
  consistent views gives no measurement and takes no number.

``triangulate_frames`` is ``triangulate`` over a batch of frames (..., C, 2): the same accepted
views, outlier rejection and covariance, with the DLT, Gauss-Newton and rejection rounds
vectorised over all frames still in play. ``CameraSegment`` is built once from the calibration and
``CameraParams`` and maps the true ball positions at a segment's triggers (B, m, 3) to the
measurements of those triggers (``SegmentMeasurements``). For the usual arrays (lens models of up
to 8 coefficients, box occluders) a tick's triggers are detected and triangulated in one compiled
call (``_measure_frames``): the draws (``random_streams``), OpenCV's projection and undistortion
and the visibility bit for bit as the NumPy/OpenCV steps give them.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence

import cv2
import numba
import numpy as np

from ace_drake.perception import random_streams
from ace_drake.perception.cameras import BALL_RADIUS, Camera, Occluder, OccluderBox, segments_blocked, table_occluder, visibility
from ace_drake.perception.measurements import Measurement
from ace_drake.perception.params import CameraParams
from ace_drake.perception.triangulation import GAUSS_NEWTON_ITERATIONS, GAUSS_NEWTON_STEP_TOLERANCE, inverse_or_inf

TIME_TOLERANCE = 1e-9  # s; as ApsCameraArray: trigger times are products of the period in floating point


# ----------------------------------------------------------------------------------------------
# Batched triangulation
# ----------------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True, eq=False)
class FrameTriangulations:
    """Triangulations of a batch of frames with leading shape S (``triangulate_frames``).

    valid S: whether the frame gave a position (``triangulate`` returned a Triangulation).
    position S + (3,): p_WB, m; NaN where not valid.
    covariance S + (3, 3): m^2; NaN where not valid.
    views S + (C,): the cameras used after outlier rejection; all False where not valid.
    rms_residual_px S: px; NaN where not valid.
    """

    valid: np.ndarray
    position: np.ndarray
    covariance: np.ndarray
    views: np.ndarray
    rms_residual_px: np.ndarray

    @classmethod
    def of_frames(cls, valid, position, covariance, views, rms_residual_px, shape: tuple) -> FrameTriangulations:
        """The results of N flat frames (N,), (N, 3), (N, 3, 3), (N, C), (N,) reshaped to ``shape`` S."""
        return cls(valid=valid.reshape(shape), position=position.reshape(shape + (3,)), covariance=covariance.reshape(shape + (3, 3)),
                   views=views.reshape(shape + views.shape[-1:]), rms_residual_px=rms_residual_px.reshape(shape))


_STACKED_DISTORTION_LENGTHS = (4, 5, 8)  # OpenCV's radial-tangential and rational models


class _CameraStack:
    """The C cameras' matrices stacked for vectorised maths: R_CW (C, 3, 3), tvec (C, 3), the
    projection matrices [R_CW | t] (C, 3, 4), and for the lens models of 4, 5 or 8 coefficients
    (zero skew, as ``cv2.projectPoints`` reads K) the intrinsics and distortion (C, 8) for a
    projection vectorised over cameras as well as points."""

    def __init__(self, cameras: Sequence[Camera]):
        self.cameras = tuple(cameras)
        self.R_CW = np.stack([camera.R_CW for camera in self.cameras])
        self.tvec = np.stack([camera.tvec for camera in self.cameras])
        self.projection = np.concatenate([self.R_CW, self.tvec[:, :, None]], axis=2)
        self.stacked = all(camera.distortion.size in _STACKED_DISTORTION_LENGTHS and camera.K[0, 1] == 0 for camera in self.cameras)
        self.focal = np.array([[camera.K[0, 0], camera.K[1, 1]] for camera in self.cameras])  # (C, 2)
        self.centre = np.array([[camera.K[0, 2], camera.K[1, 2]] for camera in self.cameras])  # (C, 2)
        self.distortion = np.zeros((len(self.cameras), 8))  # k1, k2, p1, p2, k3, k4, k5, k6
        for index, camera in enumerate(self.cameras):
            count = min(camera.distortion.size, 8)
            self.distortion[index, :count] = camera.distortion[:count]
        # For OpenCV's own arithmetic (``_opencv_pixel``, ``_opencv_normalised``; stacked arrays
        # only): the rotation cv2.projectPoints rebuilds from the Rodrigues vector (not R_CW bit
        # for bit), K as (fx, fy, cx, cy) and the coefficients zero-padded to OpenCV's 14.
        self.cv_rotation = np.stack([cv2.Rodrigues(camera.rvec)[0] for camera in self.cameras])
        self.cv_intrinsics = np.concatenate([self.focal, self.centre], axis=1)
        self.cv_distortion = np.zeros((len(self.cameras), 14))
        for index, camera in enumerate(self.cameras):
            self.cv_distortion[index, : camera.distortion.size] = camera.distortion
        # What the compiled kernels read, in one tuple (``_detect_frames``, ``_triangulate_frames``).
        self.kernel_arrays = (self.cv_rotation, self.tvec, self.cv_intrinsics, self.cv_distortion, self.R_CW, self.projection, self.focal,
                              self.centre, self.distortion)

    def __len__(self) -> int:
        return len(self.cameras)

    def normalised(self, pixels: np.ndarray, usable: np.ndarray) -> np.ndarray:
        """Undistorted normalised image points (N, C, 2) of pixels (N, C, 2), px
        (``cv2.undistortPoints`` per camera over all frames); zero where not ``usable`` (N, C)."""
        out = np.zeros(pixels.shape)
        for index, camera in enumerate(self.cameras):
            rows = np.flatnonzero(usable[:, index])
            if rows.size:
                points = np.ascontiguousarray(pixels[rows, index].reshape(-1, 1, 2))
                out[rows, index] = cv2.undistortPoints(points, camera.K, camera.distortion).reshape(-1, 2)
        return out

    def project_with_jacobian(self, positions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Pixels (N, C, 2) of positions (N, 3), m, in every camera and their Jacobians
        d pixel / d p_W (N, C, 2, 3), px/m: ``Camera.project_with_jacobian`` (OpenCV's model;
        equal to ``cv2.projectPoints`` to ~1e-12 px), compiled over points and cameras
        (``_project_all``) when the lens models allow, else one OpenCV call per camera."""
        if not self.stacked:
            pixels = np.empty((len(positions), len(self.cameras), 2))
            jacobians = np.empty((len(positions), len(self.cameras), 2, 3))
            for index, camera in enumerate(self.cameras):
                pixels[:, index], jacobians[:, index] = camera.project_with_jacobian(positions)
            return pixels, jacobians
        positions = np.ascontiguousarray(positions, dtype=float).reshape(-1, 3)
        pixels = np.empty((len(positions), len(self.cameras), 2))
        jacobians = np.empty((len(positions), len(self.cameras), 2, 3))
        _project_all(positions, self.R_CW, self.tvec, self.focal, self.centre, self.distortion, pixels, jacobians)
        return pixels, jacobians

    def depths(self, positions: np.ndarray) -> np.ndarray:
        """Depths (N, C), m, of positions (N, 3) along each camera's optical axis."""
        return np.einsum("ck,nk->nc", self.R_CW[:, 2, :], positions) + self.tvec[:, 2]


def _least_squares_steps(jacobians: np.ndarray, residuals: np.ndarray, views: np.ndarray) -> np.ndarray:
    """Gauss-Newton steps (N, 3), m: the least-squares solutions of J step = -r over the views
    used, with J (N, C, 2, 3), r (N, C, 2) and views (N, C) bool (unused views are zero rows,
    which change neither the normal matrix nor the solution). Solved from the normal equations
    (closed-form 3 x 3 inverse); frames whose normal matrix is near singular get the minimum-norm
    solution of ``numpy.linalg.lstsq`` (its default cut-off) instead."""
    J = np.where(views[:, :, None, None], jacobians, 0.0).reshape(len(views), -1, 3)
    b = -np.where(views[:, :, None], residuals, 0.0).reshape(len(views), -1)
    H = np.einsum("nki,nkj->nij", J, J)
    g = np.einsum("nki,nk->ni", J, b)
    cofactor = np.stack(
        [
            H[:, 1, 1] * H[:, 2, 2] - H[:, 1, 2] * H[:, 2, 1],
            H[:, 0, 2] * H[:, 2, 1] - H[:, 0, 1] * H[:, 2, 2],
            H[:, 0, 1] * H[:, 1, 2] - H[:, 0, 2] * H[:, 1, 1],
            H[:, 1, 2] * H[:, 2, 0] - H[:, 1, 0] * H[:, 2, 2],
            H[:, 0, 0] * H[:, 2, 2] - H[:, 0, 2] * H[:, 2, 0],
            H[:, 0, 2] * H[:, 1, 0] - H[:, 0, 0] * H[:, 1, 2],
            H[:, 1, 0] * H[:, 2, 1] - H[:, 1, 1] * H[:, 2, 0],
            H[:, 0, 1] * H[:, 2, 0] - H[:, 0, 0] * H[:, 2, 1],
            H[:, 0, 0] * H[:, 1, 1] - H[:, 0, 1] * H[:, 1, 0],
        ],
        axis=1,
    ).reshape(-1, 3, 3)
    determinant = np.einsum("ni,ni->n", H[:, 0], cofactor[:, :, 0])
    scale = np.einsum("nii->n", H) / 3.0
    regular = determinant > 1e-9 * scale**3  # condition number below ~1e9
    with np.errstate(divide="ignore", invalid="ignore"):
        steps = np.einsum("nij,nj->ni", cofactor, g) / determinant[:, None]
    singular = np.flatnonzero(~regular)
    if singular.size:
        U, S, Vt = np.linalg.svd(J[singular], full_matrices=False)  # (n, 2C, 3), (n, 3), (n, 3, 3)
        rows = 2 * views[singular].sum(axis=1)
        cutoff = np.finfo(float).eps * np.maximum(rows, 3)[:, None] * S[:, :1]
        inverse = np.where(S > cutoff, 1.0 / np.where(S > cutoff, S, 1.0), 0.0)
        steps[singular] = np.einsum("nji,nj->ni", Vt, inverse * np.einsum("nkj,nk->nj", U, b[singular]))
    return steps


def _linear_positions(stack: _CameraStack, normalised: np.ndarray, views: np.ndarray) -> np.ndarray:
    """The DLT (``triangulation.triangulate_linear``) for N frames: p_W (N, 3), m, from the
    normalised points (N, C, 2) of the views used (N, C) bool; unused views are zero rows."""
    P = stack.projection  # (C, 3, 4)
    rows = np.stack(
        [normalised[..., 0, None] * P[None, :, 2] - P[None, :, 0], normalised[..., 1, None] * P[None, :, 2] - P[None, :, 1]],
        axis=2,
    )  # (N, C, 2, 4)
    rows = rows * views[:, :, None, None]
    _, _, vt = np.linalg.svd(rows.reshape(len(views), -1, 4))
    homogeneous = vt[:, -1]
    return homogeneous[:, :3] / homogeneous[:, 3:]


def _refine_positions(
    stack: _CameraStack, pixels: np.ndarray, positions: np.ndarray, views: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``triangulation.refine_position`` for N frames: Gauss-Newton on the reprojection error of
    the views used (N, C), each frame stopping after its first step shorter than the tolerance.
    Returns positions (N, 3), residuals (N, C, 2), px, and Jacobians (N, C, 2, 3), px/m, at them
    (every camera's; only the views used are meaningful)."""
    positions = positions.copy()
    active = np.arange(len(positions))
    for _ in range(GAUSS_NEWTON_ITERATIONS):
        if active.size == 0:
            break
        projected, jacobians = stack.project_with_jacobian(positions[active])
        steps = _least_squares_steps(jacobians, projected - pixels[active], views[active])
        positions[active] = positions[active] + steps
        active = active[np.linalg.norm(steps, axis=1) >= GAUSS_NEWTON_STEP_TOLERANCE]
    projected, jacobians = stack.project_with_jacobian(positions)
    return positions, projected - pixels, jacobians


def triangulate_frames(
    cameras: Sequence[Camera],
    pixels: np.ndarray,
    pixel_noise_sigma: float,
    outlier_threshold_px: float = 8.0,
    min_views: int = 2,
) -> FrameTriangulations:
    """``triangulation.triangulate`` for a batch of frames: the detections ``pixels`` S + (C, 2),
    px, of the C ``cameras`` (NaN rows: no detection) for any leading shape S. Each frame gets
    the views, outlier rejection, position and covariance that ``triangulate`` gives it (to
    rounding, ~1e-12 m): frame by frame in one compiled call when the stacked projection covers
    the lenses (``_triangulate_compiled``), else in rounds vectorised over the frames still in
    play (``_triangulate_rounds``)."""
    if min_views < 2:
        raise ValueError(f"triangulate_frames: min_views must be >= 2, got {min_views}")
    pixels = np.asarray(pixels, dtype=float)
    C = len(cameras)
    if pixels.ndim < 2 or pixels.shape[-2:] != (C, 2):
        raise ValueError(f"triangulate_frames: pixels must have shape (..., {C}, 2) for {C} cameras, got {pixels.shape}")
    shape = pixels.shape[:-2]
    flat = pixels.reshape(-1, C, 2)
    stack = cameras if isinstance(cameras, _CameraStack) else _CameraStack(cameras)
    if stack.stacked:
        return _triangulate_compiled(stack, flat, pixel_noise_sigma, outlier_threshold_px, min_views, shape)
    usable = np.all(np.isfinite(flat), axis=2)
    return _triangulate_rounds(stack, flat, stack.normalised(flat, usable), usable, pixel_noise_sigma, outlier_threshold_px, min_views, shape)


def _triangulate_rounds(stack: _CameraStack, flat: np.ndarray, normalised: np.ndarray, usable: np.ndarray, pixel_noise_sigma: float,
                        outlier_threshold_px: float, min_views: int, shape: tuple) -> FrameTriangulations:
    """``triangulate_frames``' rounds (DLT, Gauss-Newton, outlier rejection) vectorised over the
    frames still in play, for frames (N, C, 2), px, with their normalised points (N, C, 2) and
    usable views (N, C); results reshaped to the leading shape ``shape``."""
    N, C = usable.shape
    views = usable.copy()
    valid = np.zeros(N, dtype=bool)
    position = np.full((N, 3), np.nan)
    covariance = np.full((N, 3, 3), np.nan)
    rms = np.full(N, np.nan)
    pending = np.flatnonzero(views.sum(axis=1) >= min_views)
    while pending.size:
        used = views[pending]
        start = _linear_positions(stack, normalised[pending], used)
        refined, residuals, jacobians = _refine_positions(stack, flat[pending], start, used)
        norms = np.where(used, np.linalg.norm(residuals, axis=2), -np.inf)
        worst = np.argmax(norms, axis=1)
        worst_norm = norms[np.arange(len(pending)), worst]
        count = used.sum(axis=1)
        consistent = worst_norm <= outlier_threshold_px
        if np.any(consistent):
            rows = pending[consistent]
            accepted_jacobians = np.where(used[consistent][:, :, None, None], jacobians[consistent], 0.0)
            information = np.einsum("nvki,nvkj->nij", accepted_jacobians, accepted_jacobians)
            accepted_covariance = pixel_noise_sigma**2 * inverse_or_inf(information)
            depths = np.where(used[consistent], stack.depths(refined[consistent]), np.inf)
            good = np.all(depths > 0, axis=1) & np.all(np.isfinite(accepted_covariance), axis=(1, 2))
            rows, good_index = rows[good], np.flatnonzero(good)
            valid[rows] = True
            position[rows] = refined[consistent][good_index]
            covariance[rows] = accepted_covariance[good_index]
            squared = np.where(used[consistent][good_index], norms[consistent][good_index], 0.0) ** 2
            rms[rows] = np.sqrt(squared.sum(axis=1) / count[consistent][good_index])
        # Inconsistent frames drop their worst view while more than two remain (triangulate).
        again = ~consistent & (count > 2)
        rows = pending[again]
        views[rows, worst[again]] = False
        pending = rows[views[rows].sum(axis=1) >= min_views]
    views &= valid[:, None]
    return FrameTriangulations.of_frames(valid, position, covariance, views, rms, shape)


def _triangulate_compiled(stack: _CameraStack, flat: np.ndarray, pixel_noise_sigma: float, outlier_threshold_px: float, min_views: int,
                          shape: tuple) -> FrameTriangulations:
    """``triangulate_frames``' rounds frame by frame in one compiled call (``_triangulate_frames``)
    for frames (N, C, 2), px, of an array whose lens models the stacked projection covers: the
    same views, rejections and results to round-off (the SVDs, eigenvalues and sums are LAPACK's
    and loops' rather than NumPy's batched ones; tests/test_camera_segment.py); results reshaped
    to the leading shape ``shape``."""
    result = _triangulate_frames(np.ascontiguousarray(flat), float(pixel_noise_sigma), float(outlier_threshold_px), int(min_views),
                                 GAUSS_NEWTON_ITERATIONS, GAUSS_NEWTON_STEP_TOLERANCE, stack.kernel_arrays)
    return FrameTriangulations.of_frames(*result, shape)


@numba.njit(cache=True)
def _project_one(p, R_CW, tvec, focal, centre, distortion, used, residual_to, residuals, jacobians, scratch):
    """``_CameraStack.project_with_jacobian`` of one position p (3,) in the cameras ``used`` (C,):
    residuals (C, 2), px (the projection less ``residual_to`` (C, 2)), and Jacobians (C, 2, 3),
    px/m (zero for the other cameras), in that method's order of operations. scratch (2, 3): work
    space (the caller's, so that a call allocates nothing)."""
    dx_dp_C, dy_dp_C = scratch[0], scratch[1]
    for c in range(R_CW.shape[0]):
        if not used[c]:
            residuals[c, 0] = residuals[c, 1] = 0.0
            jacobians[c] = 0.0
            continue
        R = R_CW[c]
        p_C0 = R[0, 0] * p[0] + R[0, 1] * p[1] + R[0, 2] * p[2] + tvec[c, 0]
        p_C1 = R[1, 0] * p[0] + R[1, 1] * p[1] + R[1, 2] * p[2] + tvec[c, 1]
        p_C2 = R[2, 0] * p[0] + R[2, 1] * p[1] + R[2, 2] * p[2] + tvec[c, 2]
        inverse_depth = 1.0 / p_C2
        a, b = p_C0 * inverse_depth, p_C1 * inverse_depth
        k1, k2, p1, p2, k3, k4, k5, k6 = distortion[c]
        r2 = a * a + b * b
        numerator = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
        denominator = 1.0 + r2 * (k4 + r2 * (k5 + r2 * k6))
        radial = numerator / denominator
        d_radial = ((k1 + r2 * (2.0 * k2 + 3.0 * r2 * k3)) * denominator - (k4 + r2 * (2.0 * k5 + 3.0 * r2 * k6)) * numerator) / denominator**2
        x = a * radial + 2.0 * p1 * a * b + p2 * (r2 + 2.0 * a * a)
        y = b * radial + p1 * (r2 + 2.0 * b * b) + 2.0 * p2 * a * b
        residuals[c, 0] = x * focal[c, 0] + centre[c, 0] - residual_to[c, 0]
        residuals[c, 1] = y * focal[c, 1] + centre[c, 1] - residual_to[c, 1]
        da = (inverse_depth, 0.0, -a * inverse_depth)  # d(a, b) / d p_C, then the chain rule
        db = (0.0, inverse_depth, -b * inverse_depth)
        ax, bx, rx = radial + 2.0 * p1 * b + 4.0 * p2 * a, 2.0 * p1 * a, a * d_radial + p2
        by, ay, ry = radial + 2.0 * p2 * a + 4.0 * p1 * b, 2.0 * p2 * b, b * d_radial + p1
        for j in range(3):  # d pixel / d p_C
            dr2 = 2.0 * (a * da[j] + b * db[j])
            dx_dp_C[j] = (ax * da[j] + bx * db[j] + rx * dr2) * focal[c, 0]
            dy_dp_C[j] = (by * db[j] + ay * da[j] + ry * dr2) * focal[c, 1]
        for i in range(3):  # d pixel / d p_W = d pixel / d p_C R_CW
            jacobians[c, 0, i] = dx_dp_C[0] * R[0, i] + dx_dp_C[1] * R[1, i] + dx_dp_C[2] * R[2, i]
            jacobians[c, 1, i] = dy_dp_C[0] * R[0, i] + dy_dp_C[1] * R[1, i] + dy_dp_C[2] * R[2, i]


@numba.njit(cache=True)
def _project_all(positions, R_CW, tvec, focal, centre, distortion, pixels, jacobians):
    """Pixels (N, C, 2) and Jacobians (N, C, 2, 3) of positions (N, 3) in every camera, into the
    arrays given: ``_project_one`` per position (the one written form of the lens model here)."""
    used = np.ones(R_CW.shape[0], dtype=np.bool_)
    origin = np.zeros((R_CW.shape[0], 2))
    scratch = np.empty((2, 3))
    for n in range(positions.shape[0]):
        _project_one(positions[n], R_CW, tvec, focal, centre, distortion, used, origin, pixels[n], jacobians[n], scratch)


# OpenCV's arithmetic written out, operation for operation, for the lens models of up to 12
# coefficients without the sensor tilt (OpenCV 5's 3d module: cv::projectPoints in
# calibration_base.cpp, cv::undistortPoints in undistort.dispatch.cpp): the same pixels and
# normalised points bit for bit (tests/test_camera_segment.py checks them against cv2), without a
# Python call per camera. The identity tilt and rectification products are kept as OpenCV's Matx
# products sum them (0 + 1 x + 0 y + 0), which only decides the sign of a zero.


@numba.njit(cache=True, inline="always")
def _opencv_pixel(X, Y, Z, R, t, intrinsics, k):
    """``cv2.projectPoints`` of the world point (X, Y, Z), m, for a camera with OpenCV's rotation R
    (3, 3) (rebuilt from the Rodrigues vector), translation t (3,), intrinsics (fx, fy, cx, cy) and
    coefficients k (14,): the pixel (u, v)."""
    x = R[0, 0] * X + R[0, 1] * Y + R[0, 2] * Z + t[0]
    y = R[1, 0] * X + R[1, 1] * Y + R[1, 2] * Z + t[1]
    z = R[2, 0] * X + R[2, 1] * Y + R[2, 2] * Z + t[2]
    z = 1.0 / z if z != 0.0 else 1.0
    x *= z
    y *= z
    r2 = x * x + y * y
    r4 = r2 * r2
    r6 = r4 * r2
    a1 = 2.0 * x * y
    a2 = r2 + 2.0 * x * x
    a3 = r2 + 2.0 * y * y
    cdist = 1.0 + k[0] * r2 + k[1] * r4 + k[4] * r6
    icdist2 = 1.0 / (1.0 + k[5] * r2 + k[6] * r4 + k[7] * r6)
    xd0 = x * cdist * icdist2 + k[2] * a1 + k[3] * a2 + k[8] * r2 + k[9] * r4
    yd0 = y * cdist * icdist2 + k[2] * a3 + k[3] * a1 + k[10] * r2 + k[11] * r4
    tilted_x = 0.0 + 1.0 * xd0 + 0.0 * yd0 + 0.0 * 1.0  # the identity tilt matrix times (xd0, yd0, 1)
    tilted_y = 0.0 + 0.0 * xd0 + 1.0 * yd0 + 0.0 * 1.0
    tilted_w = 0.0 + 0.0 * xd0 + 0.0 * yd0 + 1.0 * 1.0
    inverse_projection = 1.0 / tilted_w if tilted_w != 0.0 else 1.0
    xd = inverse_projection * tilted_x
    yd = inverse_projection * tilted_y
    return xd * intrinsics[0] + intrinsics[2], yd * intrinsics[1] + intrinsics[3]


_UNDISTORT_ITERATIONS = 5  # cv2.undistortPoints' default criterion: five iterations, no tolerance


@numba.njit(cache=True, inline="always")
def _opencv_normalised(u, v, intrinsics, k):
    """``cv2.undistortPoints`` of the pixel (u, v) for a camera with intrinsics (fx, fy, cx, cy)
    and coefficients k (14,) (no rectification, no new camera matrix): the undistorted
    normalised point (x, y)."""
    cx, cy = intrinsics[2], intrinsics[3]
    ifx = 1.0 / intrinsics[0]
    ify = 1.0 / intrinsics[1]
    x = (u - cx) * ifx
    y = (v - cy) * ify
    untilted_x = 0.0 + 1.0 * x + 0.0 * y + 0.0 * 1.0  # the identity inverse tilt matrix times (x, y, 1)
    untilted_y = 0.0 + 0.0 * x + 1.0 * y + 0.0 * 1.0
    untilted_w = 0.0 + 0.0 * x + 0.0 * y + 1.0 * 1.0
    inverse_projection = 1.0 / untilted_w if untilted_w != 0.0 else 1.0
    x = x0 = inverse_projection * untilted_x
    y = y0 = inverse_projection * untilted_y
    for _ in range(_UNDISTORT_ITERATIONS):
        r2 = x * x + y * y
        icdist = (1.0 + ((k[7] * r2 + k[6]) * r2 + k[5]) * r2) / (1.0 + ((k[4] * r2 + k[1]) * r2 + k[0]) * r2)
        if icdist < 0.0:
            x = (u - cx) * ifx
            y = (v - cy) * ify
            break
        delta_x = 2.0 * k[2] * x * y + k[3] * (r2 + 2.0 * x * x) + k[8] * r2 + k[9] * r2 * r2
        delta_y = k[2] * (r2 + 2.0 * y * y) + 2.0 * k[3] * x * y + k[10] * r2 + k[11] * r2 * r2
        x = (x0 - delta_x) * icdist
        y = (y0 - delta_y) * icdist
    rectified_x = 1.0 * x + 0.0 * y + 0.0  # the identity rectification
    rectified_y = 0.0 * x + 1.0 * y + 0.0
    inverse_w = 1.0 / (0.0 * x + 0.0 * y + 1.0)
    return rectified_x * inverse_w, rectified_y * inverse_w


@numba.njit(cache=True)
def _opencv_project(points, R, t, intrinsics, k, pixels):
    """``_opencv_pixel`` of points (N, 3), m, in C cameras (R (C, 3, 3), t (C, 3), intrinsics (C,
    4), k (C, 14)) into pixels (C, N, 2), as ``np.stack([camera.project(points) ...])``."""
    for c in range(R.shape[0]):
        for n in range(points.shape[0]):
            pixels[c, n, 0], pixels[c, n, 1] = _opencv_pixel(points[n, 0], points[n, 1], points[n, 2], R[c], t[c], intrinsics[c], k[c])


@numba.njit(cache=True)
def _gauss_newton_step(jacobians, residuals, used, step, scratch):
    """``_least_squares_steps`` of one frame into step (3,): the normal equations' closed-form
    solution, or the minimum-norm least-squares solution (SVD) when they are near singular.
    scratch (7, 3): work space (the caller's, so that a call allocates nothing)."""
    C = jacobians.shape[0]
    H, g, cofactor = scratch[:3], scratch[3], scratch[4:]
    H[:] = 0.0
    g[:] = 0.0
    for c in range(C):
        if not used[c]:
            continue
        for k in range(2):
            for i in range(3):
                g[i] += jacobians[c, k, i] * -residuals[c, k]
                for j in range(3):
                    H[i, j] += jacobians[c, k, i] * jacobians[c, k, j]
    cofactor[0, 0] = H[1, 1] * H[2, 2] - H[1, 2] * H[2, 1]
    cofactor[0, 1] = H[0, 2] * H[2, 1] - H[0, 1] * H[2, 2]
    cofactor[0, 2] = H[0, 1] * H[1, 2] - H[0, 2] * H[1, 1]
    cofactor[1, 0] = H[1, 2] * H[2, 0] - H[1, 0] * H[2, 2]
    cofactor[1, 1] = H[0, 0] * H[2, 2] - H[0, 2] * H[2, 0]
    cofactor[1, 2] = H[0, 2] * H[1, 0] - H[0, 0] * H[1, 2]
    cofactor[2, 0] = H[1, 0] * H[2, 1] - H[1, 1] * H[2, 0]
    cofactor[2, 1] = H[0, 1] * H[2, 0] - H[0, 0] * H[2, 1]
    cofactor[2, 2] = H[0, 0] * H[1, 1] - H[0, 1] * H[1, 0]
    determinant = H[0, 0] * cofactor[0, 0] + H[0, 1] * cofactor[1, 0] + H[0, 2] * cofactor[2, 0]
    scale = (H[0, 0] + H[1, 1] + H[2, 2]) / 3.0
    if determinant > 1e-9 * scale**3:  # condition number below ~1e9
        for i in range(3):
            step[i] = (cofactor[i, 0] * g[0] + cofactor[i, 1] * g[1] + cofactor[i, 2] * g[2]) / determinant
        return
    J = jacobians.reshape(2 * C, 3).copy()  # unused views are zero rows (``_project_one``)
    b = -residuals.reshape(2 * C)
    count = 0
    for c in range(C):
        if used[c]:
            count += 1
    U, S, Vt = np.linalg.svd(J, full_matrices=False)
    cutoff = np.finfo(np.float64).eps * max(2 * count, 3) * S[0]
    projected = U.T @ b
    step[:] = 0.0
    for k in range(3):
        if S[k] > cutoff:
            for i in range(3):
                step[i] += Vt[k, i] * (projected[k] / S[k])


@numba.njit(cache=True)
def _regular(information):
    """``inverse_or_inf``'s test of a symmetric positive semi-definite (3, 3) matrix: its smallest
    eigenvalue above 1e-12 of its largest, as LAPACK's eigenvalues decide it. A determinant above
    1e-9 trace^3 proves the smallest (>= det / trace^2) far above 1e-12 of the largest (<= trace),
    every rounding included, so the usual case skips the LAPACK call without changing a decision."""
    H = information
    determinant = (H[0, 0] * (H[1, 1] * H[2, 2] - H[1, 2] * H[2, 1]) - H[0, 1] * (H[1, 0] * H[2, 2] - H[1, 2] * H[2, 0])
                   + H[0, 2] * (H[1, 0] * H[2, 1] - H[1, 1] * H[2, 0]))
    if determinant > 1e-9 * (H[0, 0] + H[1, 1] + H[2, 2]) ** 3:
        return True
    eigenvalues = np.linalg.eigvalsh(information)
    return eigenvalues[0] > 1e-12 * max(eigenvalues[2], 1e-300)


@numba.njit(cache=True)
def _triangulate_frames(pixels, sigma, threshold, min_views, iterations, tolerance, cameras):
    """``triangulate_frames``' per-frame logic for N frames, pixels (N, C, 2), px (NaN: no
    detection), with the stacked camera model ``cameras`` (``_CameraStack.kernel_arrays``; the
    usable views are undistorted as ``_CameraStack.normalised`` does it, ``_opencv_normalised``):
    valid (N,), position (N, 3), covariance (N, 3, 3), views (N, C), rms (N,) (``FrameTriangulations``)."""
    _, tvec, intrinsics, cv_distortion, R_CW, projection, focal, centre, distortion = cameras
    N, C = pixels.shape[0], R_CW.shape[0]
    valid = np.zeros(N, dtype=np.bool_)
    position = np.full((N, 3), np.nan)
    covariance = np.full((N, 3, 3), np.nan)
    rms = np.full(N, np.nan)
    views = np.empty((N, C), dtype=np.bool_)  # the usable views, then those used
    for n in range(N):
        for c in range(C):
            views[n, c] = math.isfinite(pixels[n, c, 0]) and math.isfinite(pixels[n, c, 1])
    rows = np.zeros((2 * C, 4))
    residuals, jacobians = np.empty((C, 2)), np.empty((C, 2, 3))
    step, p = np.empty(3), np.empty(3)
    information, projection_scratch, step_scratch = np.empty((3, 3)), np.empty((2, 3)), np.empty((7, 3))
    norms = np.empty(C)
    normalised = np.zeros((C, 2))
    for n in range(N):
        used = views[n]
        for c in range(C):  # _CameraStack.normalised: cv2.undistortPoints of the usable views
            if used[c]:
                normalised[c, 0], normalised[c, 1] = _opencv_normalised(pixels[n, c, 0], pixels[n, c, 1], intrinsics[c], cv_distortion[c])
        while used.sum() >= min_views:
            # The DLT (triangulation.triangulate_linear) over the views used; unused ones are zero rows.
            for c in range(C):
                for j in range(4):
                    if used[c]:
                        rows[2 * c, j] = normalised[c, 0] * projection[c, 2, j] - projection[c, 0, j]
                        rows[2 * c + 1, j] = normalised[c, 1] * projection[c, 2, j] - projection[c, 1, j]
                    else:
                        rows[2 * c, j] = rows[2 * c + 1, j] = 0.0
            # Economy SVD: its right singular vectors are the full SVD's bit for bit (dgesdd's paths
            # share the QR, bidiagonalisation and its SVD; they differ in U only), at less cost.
            _, _, vt = np.linalg.svd(rows, full_matrices=False)
            for i in range(3):
                p[i] = vt[3, i] / vt[3, 3]
            # Gauss-Newton (triangulation.refine_position), stopping after the first short step.
            for _ in range(iterations):
                _project_one(p, R_CW, tvec, focal, centre, distortion, used, pixels[n], residuals, jacobians, projection_scratch)
                _gauss_newton_step(jacobians, residuals, used, step, step_scratch)
                for i in range(3):
                    p[i] = p[i] + step[i]
                if not math.sqrt(step[0] * step[0] + step[1] * step[1] + step[2] * step[2]) >= tolerance:
                    break
            _project_one(p, R_CW, tvec, focal, centre, distortion, used, pixels[n], residuals, jacobians, projection_scratch)
            count, worst = 0, -1
            for c in range(C):
                norms[c] = math.sqrt(residuals[c, 0] * residuals[c, 0] + residuals[c, 1] * residuals[c, 1]) if used[c] else -np.inf
                if used[c]:
                    count += 1
                if worst < 0 or norms[c] > norms[worst]:
                    worst = c
            if norms[worst] <= threshold:
                information[:] = 0.0
                squared = 0.0
                good = True
                for c in range(C):
                    if not used[c]:
                        continue
                    squared += norms[c] ** 2
                    R = R_CW[c]
                    good = good and R[2, 0] * p[0] + R[2, 1] * p[1] + R[2, 2] * p[2] + tvec[c, 2] > 0.0
                    for k in range(2):
                        for i in range(3):
                            for j in range(3):
                                information[i, j] += jacobians[c, k, i] * jacobians[c, k, j]
                # inverse_or_inf: sigma^2 (J^T J)^-1, infinite where singular.
                regular = _regular(information)
                good = good and regular
                if good:
                    inverse = np.linalg.inv(information)
                    for i in range(3):
                        for j in range(3):
                            good = good and math.isfinite(inverse[i, j])
                if good:
                    valid[n] = True
                    position[n] = p
                    covariance[n] = sigma**2 * inverse
                    rms[n] = math.sqrt(squared / count)
                break
            if count <= 2:
                break
            used[worst] = False  # drop the worst view and try the rest (triangulate)
        if not valid[n]:
            used[:] = False
    return valid, position, covariance, views, rms


@numba.njit(cache=True)
def _box_starts(origins, box_centres, box_rotations):
    """The camera centres origins (C, 3), m, in the frames of K boxes (centres (K, 3), rotations
    R_WB (K, 3, 3)): (C, K, 3), as ``segments_blocked``'s slab test takes them."""
    C, K = origins.shape[0], box_centres.shape[0]
    start = np.empty((C, K, 3))
    for c in range(C):
        for k in range(K):
            for i in range(3):
                start[c, k, i] = ((origins[c, 0] - box_centres[k, 0]) * box_rotations[k, 0, i]
                                  + (origins[c, 1] - box_centres[k, 1]) * box_rotations[k, 1, i]
                                  + (origins[c, 2] - box_centres[k, 2]) * box_rotations[k, 2, i])
    return start


@numba.njit(cache=True, inline="always")
def _sees(x, y, z, pixel, R, t, focal_px, image_size, start, box_centres, box_rotations, box_half_extents, ball_radius):
    """``cameras.visibility`` of the ball at (x, y, z), m, projected at pixel (2,), px, by a camera
    R_CW (3, 3), tvec (3,), smaller focal length, px, image size (2,), px, and centre start (K, 3)
    in the frames of the static boxes (``_box_starts``; centres (K, 3), rotations R_WB (K, 3, 3),
    half extents (K, 3), m): in front (depth > ball radius), the projected disc inside the image
    (``projected_ball_radius``) and the line of sight through no box (``segments_blocked``'s slab
    test); the same tests in the same order."""
    p_C0 = x * R[0, 0] + y * R[0, 1] + z * R[0, 2] + t[0]
    p_C1 = x * R[1, 0] + y * R[1, 1] + z * R[1, 2] + t[1]
    p_C2 = x * R[2, 0] + y * R[2, 1] + z * R[2, 2] + t[2]
    distance = math.sqrt(p_C0 * p_C0 + p_C1 * p_C1 + p_C2 * p_C2)
    visible = p_C2 > ball_radius and distance > ball_radius
    if visible:
        tan_theta = ball_radius / math.sqrt(max(distance**2 - ball_radius**2, 1e-300))
        radius = focal_px * tan_theta * distance / p_C2
        for axis in range(2):
            visible = visible and pixel[axis] - radius >= -0.5 and pixel[axis] + radius <= image_size[axis] - 0.5
    for k in range(box_centres.shape[0]):
        if not visible:
            break
        t_enter, t_exit = -np.inf, np.inf
        for i in range(3):
            end = ((x - box_centres[k, 0]) * box_rotations[k, 0, i] + (y - box_centres[k, 1]) * box_rotations[k, 1, i]
                   + (z - box_centres[k, 2]) * box_rotations[k, 2, i])
            direction = end - start[k, i]
            lower = -box_half_extents[k, i] - start[k, i]
            upper = box_half_extents[k, i] - start[k, i]
            if direction == 0.0:  # parallel to the slab: inside it for all t or for none
                inside = lower <= 0.0 and upper >= 0.0
                enter, leave = (-np.inf, np.inf) if inside else (np.inf, -np.inf)
            else:
                t_lower, t_upper = lower / direction, upper / direction
                enter, leave = min(t_lower, t_upper), max(t_lower, t_upper)
            t_enter, t_exit = max(t_enter, enter), min(t_exit, leave)
        visible = not (t_enter <= t_exit and t_exit >= 0.0 and t_enter <= 1.0)
    return visible


@numba.njit(cache=True)
def _visible(points, pixels, R_CW, tvec, focal_px, image_size, origins, box_centres, box_rotations, box_half_extents, ball_radius,
             seen):
    """``cameras.visibility`` of the ball at points (N, 3), m, whose projections pixels (C, N, 2),
    px, are given, for cameras R_CW (C, 3, 3), tvec (C, 3), smaller focal lengths (C,), px,
    image sizes (C, 2), px, and centres (C, 3), m, behind static boxes (K of them: centres (K,
    3), rotations R_WB (K, 3, 3), half extents (K, 3), m), into seen (C, N) (``_sees``)."""
    start = _box_starts(origins, box_centres, box_rotations)
    for c in range(R_CW.shape[0]):
        for n in range(points.shape[0]):
            seen[c, n] = _sees(points[n, 0], points[n, 1], points[n, 2], pixels[c, n], R_CW[c], tvec[c], focal_px[c], image_size[c], start[c],
                               box_centres, box_rotations, box_half_extents, ball_radius)


@numba.njit(cache=True)
def _detect_frames(points, seeds, sequences, blocked, sigma, dropout, cameras, scene):
    """``CameraSegment.detect`` of N triggers in one pass, for a stacked array behind static
    boxes: the ball at points (N, 3), m, trigger sequences (N,) of the episodes seeded seeds (N,)
    (uint64), lines of sight blocked (C, N) by other occluders, pixel noise sigma, px, and the
    dropout probability; the cameras ``_CameraStack.kernel_arrays``, the scene
    ``CameraSegment._scene``. Returns the detections (N, C, 2), px (NaN: none): per trigger the
    draws of ``_draw_trigger``, each camera's ``cv2.projectPoints`` pixel (``_opencv_pixel``)
    and ``_sees``, then the pixel plus the noise where seen and not dropped out, as
    ``cameras.simulate_detections`` has them."""
    cv_rotation, tvec, intrinsics, cv_distortion, R_CW = cameras[:5]
    focal_px, image_size, origins, box_centres, box_rotations, box_half_extents, ball_radius = scene
    N, C = points.shape[0], R_CW.shape[0]
    detections = np.empty((N, C, 2))
    start = _box_starts(origins, box_centres, box_rotations)
    generator, scratch = np.empty(4, np.uint64), np.empty(random_streams.GENERATOR_SCRATCH + 2, np.uint64)
    noise, uniforms, pixel = np.empty((C, 2)), np.empty(C), np.empty(2)
    for n in range(N):
        _trigger_generator(seeds[n], sequences[n], generator, scratch)
        _draw_trigger(generator, noise, uniforms)
        x, y, z = points[n, 0], points[n, 1], points[n, 2]
        for c in range(C):
            pixel[0], pixel[1] = _opencv_pixel(x, y, z, cv_rotation[c], tvec[c], intrinsics[c], cv_distortion[c])
            seen = _sees(x, y, z, pixel, R_CW[c], tvec[c], focal_px[c], image_size[c], start[c], box_centres, box_rotations, box_half_extents,
                         ball_radius)
            if seen and not blocked[c, n] and uniforms[c] >= dropout:
                detections[n, c, 0] = pixel[0] + noise[c, 0] * sigma
                detections[n, c, 1] = pixel[1] + noise[c, 1] * sigma
            else:
                detections[n, c, 0] = detections[n, c, 1] = np.nan
    return detections


@numba.njit(cache=True)
def _measure_frames(points, seeds, sequences, blocked, sigma, dropout, threshold, min_views, iterations, tolerance, cameras, scene):
    """``_detect_frames`` then ``_triangulate_frames`` of its detections in one call: (detections
    (N, C, 2), valid, position, covariance, views, rms)."""
    detections = _detect_frames(points, seeds, sequences, blocked, sigma, dropout, cameras, scene)
    valid, position, covariance, views, rms = _triangulate_frames(detections, sigma, threshold, min_views, iterations, tolerance, cameras)
    return detections, valid, position, covariance, views, rms


# ----------------------------------------------------------------------------------------------
# Detection noise, as the reference draws it
# ----------------------------------------------------------------------------------------------


# Each trigger's generator and draws, compiled (``random_streams``: numpy's default_rng bit for bit).


@numba.njit(cache=True)
def _trigger_generator(seed, sequence, generator, scratch):
    """generator (4,) <- ``numpy.random.default_rng([seed, sequence])``'s PCG64; scratch
    (``random_streams.GENERATOR_SCRATCH`` + 2,) uint64."""
    entropy = scratch[random_streams.GENERATOR_SCRATCH:]
    entropy[0], entropy[1] = seed, sequence
    random_streams.seed_generator(entropy, 2, generator, scratch[:random_streams.GENERATOR_SCRATCH])


@numba.njit(cache=True)
def _draw_trigger(generator, noise, uniforms):
    """One trigger's draws in the reference's order: ``normal(0.0, 1.0, size=(C, 2))`` into noise
    (C, 2) (loc + scale z, as numpy computes it), then ``random(C)`` into uniforms (C,)."""
    for c in range(noise.shape[0]):
        for axis in range(2):
            noise[c, axis] = 0.0 + 1.0 * random_streams.standard_normal(generator)
    for c in range(uniforms.shape[0]):
        uniforms[c] = random_streams.random(generator)


@numba.njit(cache=True)
def _draw_noise(seeds, sequences, noise, uniforms):
    """``draw_detection_noise``'s draws into noise (N, C, 2) and uniforms (N, C)."""
    generator, scratch = np.empty(4, np.uint64), np.empty(random_streams.GENERATOR_SCRATCH + 2, np.uint64)
    for n in range(seeds.shape[0]):
        _trigger_generator(seeds[n], sequences[n], generator, scratch)
        _draw_trigger(generator, noise[n], uniforms[n])


def draw_detection_noise(seeds: np.ndarray, sequences: np.ndarray, camera_count: int) -> tuple[np.ndarray, np.ndarray]:
    """The standard-normal pixel noise (N, C, 2) and dropout uniforms (N, C) of N triggers, trigger
    ``sequences[i]`` (N,) of the episode seeded ``seeds[i]`` (N,), each from its own generator
    ``numpy.random.default_rng([seed, sequence])`` in the reference's order (noise, then dropout;
    ``cameras.simulate_detections``): the same numbers, bit for bit, seeded and drawn in one
    compiled pass."""
    seeds = np.asarray(seeds).reshape(-1)
    sequences = np.asarray(sequences).reshape(-1)
    if seeds.shape != sequences.shape:
        raise ValueError(f"draw_detection_noise: seeds {seeds.shape} and sequences {sequences.shape} must match")
    if len(seeds) and (seeds.dtype.kind not in "iu" or sequences.dtype.kind not in "iu" or seeds.min() < 0 or sequences.min() < 0):
        raise ValueError("draw_detection_noise: seeds (< 2**64) and sequences (< 2**32) must be non-negative integers")
    if len(seeds) and sequences.max() > random_streams.MASK32:
        raise ValueError(f"draw_detection_noise: sequences must be < 2**32, got {sequences.max()}")
    noise = np.empty((len(seeds), camera_count, 2))
    uniforms = np.empty((len(seeds), camera_count))
    _draw_noise(seeds.astype(np.uint64), sequences.astype(np.uint64), noise, uniforms)
    return noise, uniforms


# ----------------------------------------------------------------------------------------------
# One control segment for B environments
# ----------------------------------------------------------------------------------------------


def trigger_times(start: float, end: float, trigger_rate: float) -> tuple[np.ndarray, np.ndarray]:
    """The camera triggers in [start, end), s, on the grid k / trigger_rate (Hz) from time 0:
    their indices k (m,) and times k / trigger_rate (m,), s, as the reference's periodic event
    has them (within ``TIME_TOLERANCE`` of a grid time counts as on it). A trigger index k is
    trigger number k + 1 of an episode that started at time 0."""
    if not trigger_rate > 0:
        raise ValueError(f"trigger_times: trigger_rate must be > 0 Hz, got {trigger_rate}")
    if not (np.isfinite(start) and np.isfinite(end) and end >= start):
        raise ValueError(f"trigger_times: expected finite start <= end (s), got [{start}, {end})")
    period = 1.0 / trigger_rate
    first = int(np.ceil((start - TIME_TOLERANCE) / period))
    stop = int(np.ceil((end - TIME_TOLERANCE) / period))
    indices = np.arange(first, max(stop, first))
    return indices, indices * period


@dataclasses.dataclass(frozen=True, eq=False)
class SegmentMeasurements:
    """The position measurements of a segment's m triggers in B environments (``CameraSegment``).

    valid (B, m): whether the trigger gave a measurement (enough consistent views).
    sequence (B, m): the Triangulator's sequence number of each measurement (release order,
        following ``last_sequence``); 0 where not valid.
    capture_time, release_time (B, m): s; release = capture + latency.
    value (B, m, 3): p_WB, m; NaN where not valid.
    covariance (B, m, 3, 3): m^2; NaN where not valid.
    pixels (B, m, C, 2): the detections triangulated, px (NaN: none).
    last_sequence (B,): each environment's latest measurement number after the segment (its
        ``last_sequence`` before it when the segment adds none): where the next segment continues.
    """

    valid: np.ndarray
    sequence: np.ndarray
    capture_time: np.ndarray
    release_time: np.ndarray
    value: np.ndarray
    covariance: np.ndarray
    pixels: np.ndarray
    last_sequence: np.ndarray

    def measurements(self, environment: int) -> tuple[Measurement, ...]:
        """Environment ``environment``'s measurements in release order, as the Triangulator's
        ``MeasurementHistory`` holds them."""
        return tuple(
            Measurement(
                int(self.sequence[environment, k]),
                float(self.capture_time[environment, k]),
                float(self.release_time[environment, k]),
                self.value[environment, k],
                self.covariance[environment, k],
            )
            for k in np.flatnonzero(self.valid[environment])
        )


class CameraSegment:
    """The camera array and the triangulator of the reference diagram (``ApsCameraArray``,
    analytic mode, + ``Triangulator``) as one batched function of a control segment.

    Built once from the calibrated cameras and ``CameraParams``; ``measure`` takes the true ball
    centres at a segment's triggers in B environments and returns their measurements (module
    docstring for the timing). Static occluders (default: the table) are fixed at construction;
    per-environment occluders (e.g. the robot's links) may be passed per call.
    """

    def __init__(
        self,
        cameras: Sequence[Camera],
        params: CameraParams | None = None,
        occluders: Sequence[Occluder] | None = None,
        ball_radius: float = BALL_RADIUS,
    ):
        """Args: cameras, the calibrated array (``cameras.load_cameras``); params, rate, latency,
        noise, dropout, outlier threshold and minimum views (analytic mode only); occluders, the
        static shapes hiding the ball (default: the table, ``table_occluder``); ball_radius, m."""
        if not cameras:
            raise ValueError("CameraSegment: needs at least one camera")
        self.params = params or CameraParams()
        if self.params.mode != "analytic":
            raise ValueError(f"CameraSegment: only the analytic mode is batched, got mode {self.params.mode!r}")
        self.cameras = tuple(cameras)
        self.camera_names = tuple(camera.name for camera in self.cameras)
        self.occluders = tuple(occluders) if occluders is not None else (table_occluder(),)
        self.ball_radius = float(ball_radius)
        self.period = 1.0 / self.params.trigger_rate
        self._stack = _CameraStack(self.cameras)
        self._origins = np.array([camera.p_WC for camera in self.cameras])
        # ``visibility``'s constants for the compiled test (``_visible``): each camera's smaller
        # focal length, px, and image size, px; the static boxes as (K, 3) centres, (K, 3, 3)
        # rotations and (K, 3) half extents (None when some static occluder is not a box).
        self._focal_px = np.array([camera.focal_length_px for camera in self.cameras])
        self._image_size = np.array([[camera.width, camera.height] for camera in self.cameras], dtype=float)
        boxes = [occluder for occluder in self.occluders if isinstance(occluder, OccluderBox)]
        self._boxes = None if len(boxes) != len(self.occluders) else (
            np.array([box.p_WB for box in boxes], dtype=float).reshape(-1, 3),
            np.array([box.R_WB for box in boxes], dtype=float).reshape(-1, 3, 3),
            np.array([box.half_extents for box in boxes], dtype=float).reshape(-1, 3),
        )
        # The whole detection and triangulation in one compiled call (``_measure_frames``) when
        # the lenses are stacked and the static occluders boxes; its scene argument.
        self._compiled = self._stack.stacked and self._boxes is not None
        self._scene = (self._focal_px, self._image_size, self._origins, *self._boxes, self.ball_radius) if self._compiled else None

    def detect(
        self,
        p_WB: np.ndarray,
        seeds: np.ndarray,
        sequences: np.ndarray,
        occluders: Sequence[Sequence[Occluder]] | None = None,
    ) -> np.ndarray:
        """The detections (B, m, C, 2), px (NaN: none), of m triggers in B environments:
        ``cameras.simulate_detections`` of each ball centre p_WB (B, m, 3), m, with trigger
        ``sequences`` (B, m) (or (m,)) of the episode seeded ``seeds`` (B,) (or (B, m), the seed
        at each trigger); ``occluders``: per environment, shapes added to the static ones."""
        p_WB, seeds, sequences = self._check(p_WB, seeds, sequences, occluders)
        return self._detections(*self._flat(p_WB, seeds, sequences, occluders)).reshape(p_WB.shape[:2] + (len(self.cameras), 2))

    def triangulate(self, pixels: np.ndarray) -> FrameTriangulations:
        """``triangulate_frames`` of detections (..., C, 2) with this array's parameters."""
        p = self.params
        return triangulate_frames(self._stack, pixels, p.pixel_noise_sigma, p.outlier_threshold_px, p.min_views)

    def frames(self, p_WB: np.ndarray, seeds: np.ndarray, sequences: np.ndarray, blocked: np.ndarray | None = None) -> tuple[np.ndarray, FrameTriangulations]:
        """The detections (N, C, 2), px (NaN: none), of N triggers and their triangulations (N,):
        ``detect`` then ``triangulate`` for callers whose input is in the flat form already:
        ball centres p_WB (N, 3), m, float; the episodes' seeds (N,) and the triggers' numbers
        sequences (N,), uint64, in [1, 2**32) (not checked, ``measure`` checks them); the lines of
        sight blocked (C, N) by per-environment occluders (None: none)."""
        p_WB = np.ascontiguousarray(p_WB, dtype=float)
        if not np.isfinite(p_WB).all():
            raise ValueError("CameraSegment: p_WB must be finite")
        if blocked is None:
            blocked = np.zeros((len(self.cameras), len(p_WB)), dtype=np.bool_)
        p = self.params
        if self._compiled:
            detections, *result = _measure_frames(p_WB, seeds, sequences, blocked, float(p.pixel_noise_sigma), float(p.dropout_probability),
                                                  float(p.outlier_threshold_px), int(p.min_views), GAUSS_NEWTON_ITERATIONS,
                                                  GAUSS_NEWTON_STEP_TOLERANCE, self._stack.kernel_arrays, self._scene)
            return detections, FrameTriangulations(*result)
        detections = self._detections(p_WB, seeds, sequences, blocked)
        return detections, self.triangulate(detections)

    def measure(
        self,
        p_WB: np.ndarray,
        capture_times: np.ndarray,
        seeds: np.ndarray,
        sequences: np.ndarray,
        last_sequence: np.ndarray | None = None,
        occluders: Sequence[Sequence[Occluder]] | None = None,
    ) -> SegmentMeasurements:
        """The measurements of a segment's m triggers in B environments.

        p_WB (B, m, 3): the true ball centre at each trigger, m.
        capture_times (m,) or (B, m): the trigger times, s (``trigger_times``).
        seeds (B,) or (B, m): each environment's episode seed (the 64 bits of the random_seed port
            at the trigger, ``systems.random_seed.episode_seed``).
        sequences (m,) or (B, m): the triggers' numbers in their episodes, 1, 2, ...
        last_sequence (B,): each environment's last measurement number before the segment (0).
        occluders: per environment, occluders added to the static ones for the whole segment.
        """
        p_WB, seeds, sequences = self._check(p_WB, seeds, sequences, occluders)
        B, m = p_WB.shape[:2]
        capture_times = np.asarray(capture_times, dtype=float)
        if capture_times.shape not in ((m,), (B, m)) or not np.all(np.isfinite(capture_times)):
            raise ValueError(f"CameraSegment.measure: capture_times must be finite, of shape ({m},) or ({B}, {m}), got {capture_times.shape}")
        capture_times = np.broadcast_to(capture_times, (B, m))
        last_sequence = np.zeros(B, dtype=int) if last_sequence is None else np.asarray(last_sequence)
        if last_sequence.shape != (B,):
            raise ValueError(f"CameraSegment.measure: last_sequence must have shape ({B},), got {last_sequence.shape}")
        pixels, result = self.frames(*self._flat(p_WB, seeds, sequences, occluders))
        valid = result.valid.reshape(B, m)
        sequence = np.where(valid, last_sequence[:, None] + np.cumsum(valid, axis=1), 0)
        return SegmentMeasurements(
            valid=valid,
            sequence=sequence,
            capture_time=capture_times.copy(),
            release_time=capture_times + self.params.latency,
            value=result.position.reshape(B, m, 3),
            covariance=result.covariance.reshape(B, m, 3, 3),
            pixels=pixels.reshape(B, m, len(self.cameras), 2),
            last_sequence=last_sequence + valid.sum(axis=1),
        )

    def _flat(self, p_WB, seeds, sequences, occluders) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """``_check``'s (B, m) input as ``frames`` takes it: the N = B m ball centres (N, 3), seeds
        and sequences (N,) uint64 and the lines of sight (C, N) the per-environment occluders block."""
        m = p_WB.shape[1]
        points = np.ascontiguousarray(p_WB.reshape(-1, 3))
        blocked = np.zeros((len(self.cameras), len(points)), dtype=np.bool_)
        for environment, extra in enumerate(occluders or ()):
            if extra:
                rows = slice(environment * m, (environment + 1) * m)
                blocked[:, rows] = segments_blocked(self._origins, points[rows], tuple(extra))
        return points, seeds.reshape(-1).astype(np.uint64), sequences.reshape(-1).astype(np.uint64), blocked

    def _detections(self, points: np.ndarray, seeds: np.ndarray, sequences: np.ndarray, blocked: np.ndarray) -> np.ndarray:
        """``detect`` of ``_flat``'s arrays: (N, C, 2), px; compiled (``_detect_frames``) or for
        other lenses or occluders the same steps in NumPy and OpenCV."""
        stack, params = self._stack, self.params
        if self._compiled:
            return _detect_frames(points, seeds, sequences, blocked, float(params.pixel_noise_sigma), float(params.dropout_probability),
                                  stack.kernel_arrays, self._scene)
        noise, uniforms = draw_detection_noise(seeds, sequences, len(self.cameras))
        if stack.stacked:
            pixels = np.empty((len(self.cameras), len(points), 2))
            _opencv_project(points, stack.cv_rotation, stack.tvec, stack.cv_intrinsics, stack.cv_distortion, pixels)
        else:
            pixels = np.stack([camera.project(points) for camera in self.cameras])  # (C, N, 2)
        if self._boxes is None:
            seen = visibility(self.cameras, points, self.occluders, self.ball_radius, pixels=pixels)  # (C, N)
        else:
            seen = np.empty(blocked.shape, dtype=np.bool_)
            _visible(points, pixels, stack.R_CW, stack.tvec, self._focal_px, self._image_size, self._origins, *self._boxes, self.ball_radius, seen)
        detected = (seen & ~blocked).T & (uniforms >= params.dropout_probability)  # (N, C)
        noisy = pixels.transpose(1, 0, 2) + noise * params.pixel_noise_sigma
        return np.where(detected[..., None], noisy, np.nan)

    def _check(self, p_WB, seeds, sequences, occluders) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Validated (B, m, 3) positions and (B, m) seeds and trigger numbers."""
        p_WB = np.asarray(p_WB, dtype=float)
        if p_WB.ndim != 3 or p_WB.shape[2] != 3:
            raise ValueError(f"CameraSegment: p_WB must have shape (B, m, 3) (m), got {p_WB.shape}")
        if not np.all(np.isfinite(p_WB)):
            raise ValueError("CameraSegment: p_WB must be finite")
        B, m = p_WB.shape[:2]
        seeds = np.asarray(seeds)
        if seeds.shape == (B,):
            seeds = np.repeat(seeds[:, None], m, axis=1)
        if seeds.shape != (B, m) or seeds.dtype.kind not in "iu":
            raise ValueError(f"CameraSegment: seeds must be integers of shape ({B},) or ({B}, {m}), got {seeds.dtype} {seeds.shape}")
        if np.any(seeds < 0):
            raise ValueError(f"CameraSegment: seeds must be >= 0, got {seeds[seeds < 0][:3]}")
        sequences = np.asarray(sequences)
        if sequences.shape == (m,):
            sequences = np.broadcast_to(sequences, (B, m))
        if sequences.shape != (B, m) or sequences.dtype.kind not in "iu":
            raise ValueError(f"CameraSegment: sequences must be integers of shape ({m},) or ({B}, {m}), got {sequences.dtype} {sequences.shape}")
        if np.any(sequences < 1) or np.any(sequences > random_streams.MASK32):
            raise ValueError("CameraSegment: trigger sequence numbers start at 1 and are < 2**32")
        if occluders is not None and len(occluders) != B:
            raise ValueError(f"CameraSegment: occluders must give one sequence per environment ({B}), got {len(occluders)}")
        return p_WB, seeds, sequences
