"""Ball detection in camera images: a colour segmentation followed by a shape check and a
sub-pixel centre (paper, Methods *Ball triangulation*: each camera segments the ball into a
detection mask, and the server verifies the ball's shape before triangulating).

The detector thresholds the image in HSV (``cv2.inRange``), splits the mask into connected
components (``cv2.connectedComponentsWithStats``), keeps the components whose size and shape fit a
ball's disc (area between those of the smallest and largest expected radius; the fraction of its
bounding box it fills near pi/4; a bounding box nearly square) and returns the centroid of the
largest by the image moments of its mask (``cv2.moments``), which is sub-pixel.
"""

from __future__ import annotations

import dataclasses
import math

import cv2
import numpy as np

# The rendered ball's colour (RGBA in [0, 1]): the orange of the project's Meshcat ball, which the
# default thresholds below pick out from the blue table, the reddish floor and the grey robot.
BALL_RENDER_COLOR = (1.0, 0.55, 0.0, 1.0)


@dataclasses.dataclass(frozen=True)
class BallColorThreshold:
    """HSV bounds of ball pixels in OpenCV's ranges (hue 0-179, saturation and value 0-255).

    The default accepts the orange ball (hue 16.5) from dark shading to full brightness and
    rejects the floor (hue 3.5), the robot's orange (hue 13) when lit the same way, the table
    (blue) and the white lines (unsaturated)."""

    hue_low: int = 15
    hue_high: int = 22
    saturation_min: int = 150
    value_min: int = 60

    def __post_init__(self) -> None:
        if not 0 <= self.hue_low <= self.hue_high <= 179:
            raise ValueError(f"BallColorThreshold: need 0 <= hue_low <= hue_high <= 179, got {self.hue_low}, {self.hue_high}")
        if not (0 <= self.saturation_min <= 255 and 0 <= self.value_min <= 255):
            raise ValueError(f"BallColorThreshold: saturation_min and value_min must be in [0, 255], got {self.saturation_min}, {self.value_min}")


@dataclasses.dataclass(frozen=True)
class BallDetection:
    """A detected ball: centre (2,) in image pixels (top-left pixel centre at (0, 0)), the radius
    of the disc with the detected area, px, and that area, px^2."""

    center: np.ndarray
    radius: float
    area: float


def ball_mask(image_rgb: np.ndarray, color: BallColorThreshold | None = None) -> np.ndarray:
    """The uint8 mask (H, W), 255 on ball-coloured pixels, of an RGB or RGBA uint8 image."""
    color = color or BallColorThreshold()
    image = np.asarray(image_rgb)
    if image.ndim != 3 or image.shape[2] not in (3, 4) or image.dtype != np.uint8:
        raise ValueError(f"ball_mask: expected an RGB(A) uint8 image (H, W, 3 or 4), got {image.dtype} {image.shape}")
    hsv = cv2.cvtColor(np.ascontiguousarray(image[:, :, :3]), cv2.COLOR_RGB2HSV)
    lower = np.array([color.hue_low, color.saturation_min, color.value_min], dtype=np.uint8)
    upper = np.array([color.hue_high, 255, 255], dtype=np.uint8)
    return cv2.inRange(hsv, lower, upper)


def detect_ball(
    image_rgb: np.ndarray,
    min_radius_px: float = 1.0,
    max_radius_px: float = 200.0,
    color: BallColorThreshold | None = None,
    min_fill: float = 0.55,
    max_aspect: float = 1.6,
) -> BallDetection | None:
    """The ball in an RGB(A) uint8 image (module docstring), or None.

    min_radius_px, max_radius_px: the range of disc radii accepted, px (the expected projected
        ball radius with a margin).
    min_fill: smallest area / bounding-box area accepted (a disc fills pi/4 = 0.785; small discs
        less, a thin or L-shaped blob much less).
    max_aspect: largest ratio of the bounding box's long side to its short side.
    """
    mask = ball_mask(image_rgb, color)
    count, labels, stats, _ = cv2.connectedComponentsWithStats(mask, connectivity=8)
    min_area, max_area = math.pi * min_radius_px**2, math.pi * max_radius_px**2
    best_label, best_area = 0, 0
    for label in range(1, count):
        left, top, width, height, area = stats[label]
        if not min_area <= area <= max_area:
            continue
        if area < min_fill * width * height or max(width, height) > max_aspect * min(width, height):
            continue
        if area > best_area:
            best_label, best_area = label, area
    if best_label == 0:
        return None
    left, top, width, height, _ = stats[best_label]
    component = (labels[top : top + height, left : left + width] == best_label).astype(np.uint8)
    moments = cv2.moments(component, binaryImage=True)
    center = np.array([left + moments["m10"] / moments["m00"], top + moments["m01"] / moments["m00"]])
    return BallDetection(center=center, radius=math.sqrt(best_area / math.pi), area=float(best_area))
