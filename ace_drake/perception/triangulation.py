"""Multi-view triangulation of the ball's centre from the frame cameras' detections (paper,
Methods *Ball triangulation*: the server triangulates the 3D position from the cameras' 2D
detections with the pre-calibrated camera parameters).

The pipeline for one trigger:

1. linear triangulation (DLT) of the undistorted, normalised image points (``cv2.undistortPoints``);
2. Gauss-Newton on the reprojection error in pixels through the full camera model with its lens
   distortion (``cv2.projectPoints`` and its Jacobian);
3. outlier rejection: while the view with the largest reprojection residual |r_i| (px) exceeds
   ``outlier_threshold_px`` and more than two views remain, that view is dropped and steps 1-2 are
   rerun on the rest. Two views whose residual still exceeds the threshold disagree and neither
   can be singled out: the trigger gives no position. So does one with fewer than ``min_views``
   views left;
4. the position's covariance from the Gauss-Newton normal matrix, sigma^2 (J^T J)^-1, with sigma
   the detections' pixel noise.

OpenCV supplies the camera maths (undistortion, projection with distortion and its Jacobian). Its
``cv2.triangulatePoints`` takes exactly two views and it has no N-view refinement outside the
contrib ``sfm`` module, so the N-view DLT (one SVD of a 2N x 4 matrix) and the three-parameter
Gauss-Newton are written here.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import cv2
import numpy as np

from ace_drake.perception.cameras import Camera

GAUSS_NEWTON_ITERATIONS = 10
GAUSS_NEWTON_STEP_TOLERANCE = 1e-10  # m; the refinement stops once a step is shorter


@dataclasses.dataclass(frozen=True, eq=False)
class Triangulation:
    """One triangulated ball centre.

    position (3,): p_WB, m.
    covariance (3, 3): of ``position``, m^2 (linearised, from the pixel noise).
    views: indices of the cameras used (after outlier rejection), ascending.
    rms_residual_px: sqrt(mean over the views used of |r_i|^2), with r_i the reprojection
        residual (2,) of view i, px.
    """

    position: np.ndarray
    covariance: np.ndarray
    views: tuple[int, ...]
    rms_residual_px: float


def triangulate(
    cameras: Sequence[Camera],
    pixels: np.ndarray,
    pixel_noise_sigma: float,
    outlier_threshold_px: float = 8.0,
    min_views: int = 2,
) -> Triangulation | None:
    """Triangulates one ball centre from the detections ``pixels`` (C, 2), px, of the C
    ``cameras`` (NaN rows: no detection), with outlier rejection (module docstring). Returns None
    when fewer than ``min_views`` (>= 2) consistent views remain.

    pixel_noise_sigma: the detections' standard deviation per axis, px (scales the covariance).
    outlier_threshold_px: the largest reprojection residual |r_i| accepted for one view, px.
    """
    if min_views < 2:
        raise ValueError(f"triangulate: min_views must be >= 2, got {min_views}")
    pixels = np.asarray(pixels, dtype=float).reshape(len(cameras), 2)
    views = [int(i) for i in np.flatnonzero(np.all(np.isfinite(pixels), axis=1))]
    while len(views) >= min_views:
        used = [cameras[i] for i in views]
        position = triangulate_linear(used, pixels[views])
        position, residuals, jacobians = refine_position(used, pixels[views], position)
        residual_norms = np.linalg.norm(residuals, axis=1)
        worst = int(np.argmax(residual_norms))
        if residual_norms[worst] <= outlier_threshold_px:
            depths = np.array([camera.to_camera_frame(position)[0, 2] for camera in used])
            covariance = position_covariance_from_jacobians(jacobians, pixel_noise_sigma)
            if np.any(depths <= 0) or not np.all(np.isfinite(covariance)):
                return None  # the rays meet behind a camera, or are parallel
            return Triangulation(
                position=position,
                covariance=covariance,
                views=tuple(views),
                rms_residual_px=float(np.sqrt(np.mean(residual_norms**2))),
            )
        if len(views) <= 2:
            return None
        del views[worst]
    return None


def triangulate_linear(cameras: Sequence[Camera], pixels: np.ndarray) -> np.ndarray:
    """The direct linear transform (DLT): p_W (3,), m, minimising the algebraic error of the
    undistorted normalised image points x_i ~ [R_CW | t] [p; 1] of two or more views (pixels
    (V, 2), px, all finite)."""
    pixels = np.asarray(pixels, dtype=float).reshape(-1, 2)
    if len(cameras) < 2 or len(pixels) != len(cameras):
        raise ValueError(f"triangulate_linear: needs >= 2 views with one pixel each, got {len(cameras)} cameras and {len(pixels)} pixels")
    rows = []
    for camera, pixel in zip(cameras, pixels):
        normalised = cv2.undistortPoints(pixel.reshape(1, 1, 2), camera.K, camera.distortion).ravel()
        projection = np.hstack([camera.R_CW, camera.tvec[:, None]])  # (3, 4)
        rows.append(normalised[0] * projection[2] - projection[0])
        rows.append(normalised[1] * projection[2] - projection[1])
    _, _, vt = np.linalg.svd(np.array(rows))
    homogeneous = vt[-1]
    return homogeneous[:3] / homogeneous[3]


def refine_position(
    cameras: Sequence[Camera],
    pixels: np.ndarray,
    initial_position: np.ndarray,
    iterations: int = GAUSS_NEWTON_ITERATIONS,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Gauss-Newton on the reprojection error sum_i |pi_i(p) - u_i|^2 (px^2), from
    ``initial_position`` (3,), m. Returns the position (3,), the residuals pi_i(p) - u_i (V, 2),
    px, and the Jacobians d pi_i / d p (V, 2, 3), px/m, at it."""
    pixels = np.asarray(pixels, dtype=float).reshape(-1, 2)
    position = np.asarray(initial_position, dtype=float).copy()
    for _ in range(iterations):
        residuals, jacobians = _residuals(cameras, pixels, position)
        step = np.linalg.lstsq(jacobians.reshape(-1, 3), -residuals.ravel(), rcond=None)[0]
        position = position + step
        if np.linalg.norm(step) < GAUSS_NEWTON_STEP_TOLERANCE:
            break
    residuals, jacobians = _residuals(cameras, pixels, position)
    return position, residuals, jacobians


def position_covariance_from_jacobians(jacobians: np.ndarray, pixel_noise_sigma: float) -> np.ndarray:
    """sigma^2 (J^T J)^-1 (3, 3), m^2: the covariance of a least-squares position from views with
    Jacobians (..., V, 2, 3), px/m, and independent pixel noise of sigma px per axis. Batched over
    leading dimensions; infinite where the views do not determine the position."""
    jacobians = np.asarray(jacobians, dtype=float)
    information = np.einsum("...vki,...vkj->...ij", jacobians, jacobians)
    return pixel_noise_sigma**2 * inverse_or_inf(information)


def position_covariance(
    cameras: Sequence[Camera],
    p_W: np.ndarray,
    seen: np.ndarray,
    pixel_noise_sigma: float,
) -> np.ndarray:
    """The linearised covariance (N, 3, 3), m^2, of triangulating points p_W (N, 3), m, from the
    cameras that see them (``seen`` (C, N) bool) with pixel noise sigma px per axis; infinite where
    fewer than two views see a point. For planning camera placements."""
    p_W = np.asarray(p_W, dtype=float).reshape(-1, 3)
    information = np.zeros((len(p_W), 3, 3))
    for camera, mask in zip(cameras, np.asarray(seen, dtype=bool)):
        if not mask.any():
            continue
        _, jacobian = camera.project_with_jacobian(p_W[mask])
        information[mask] += np.einsum("nki,nkj->nij", jacobian, jacobian)
    return pixel_noise_sigma**2 * inverse_or_inf(information)


def inverse_or_inf(information: np.ndarray) -> np.ndarray:
    """Inverse of symmetric positive semi-definite matrices (..., 3, 3); inf where singular."""
    result = np.full(information.shape, np.inf)
    eigenvalues = np.linalg.eigvalsh(information)
    regular = eigenvalues[..., 0] > 1e-12 * np.maximum(eigenvalues[..., -1], 1e-300)
    if np.any(regular):
        result[regular] = np.linalg.inv(information[regular])
    return result


def _residuals(cameras: Sequence[Camera], pixels: np.ndarray, position: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    residuals = np.empty((len(cameras), 2))
    jacobians = np.empty((len(cameras), 2, 3))
    for index, camera in enumerate(cameras):
        projected, jacobian = camera.project_with_jacobian(position)
        residuals[index] = projected[0] - pixels[index]
        jacobians[index] = jacobian[0]
    return residuals, jacobians
