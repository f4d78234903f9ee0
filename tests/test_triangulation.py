"""Triangulation: exact without noise, outlier rejection, failure cases, and a covariance that is
consistent with the error it describes (Monte Carlo)."""

import numpy as np
import pytest

from ace_drake.perception.cameras import DEFAULT_CALIBRATION, camera_looking_at, load_cameras, project_points, visibility
from ace_drake.perception.triangulation import (
    position_covariance,
    position_covariance_from_jacobians,
    refine_position,
    triangulate,
    triangulate_linear,
)

CAMERAS = load_cameras(DEFAULT_CALIBRATION)


def points_in_play_volume(count, seed):
    rng = np.random.default_rng(seed)
    return rng.uniform([-2.5, -1.2, 0.05], [2.5, 1.2, 1.2], size=(count, 3))


def test_round_trip_is_exact_without_noise():
    points = points_in_play_volume(40, seed=1)
    pixels, _ = project_points(CAMERAS, points)
    seen = visibility(CAMERAS, points)
    for index, point in enumerate(points):
        detections = np.where(seen[:, index, None], pixels[:, index], np.nan)
        result = triangulate(CAMERAS, detections, pixel_noise_sigma=0.5)
        assert result is not None
        assert np.linalg.norm(result.position - point) < 1e-6
        assert result.views == tuple(np.flatnonzero(seen[:, index]))
        assert result.rms_residual_px < 1e-6


def test_linear_triangulation_without_distortion_is_exact():
    cameras = [camera_looking_at(f"c{i}", position, [0.0, 0.0, 0.3], 1500.0) for i, position in enumerate([[-5, 4, 2], [0, -4, 3], [6, 3, 1.5]])]
    point = np.array([0.4, -0.3, 0.6])
    pixels, _ = project_points(cameras, point[None])
    np.testing.assert_allclose(triangulate_linear(cameras, pixels[:, 0]), point, atol=1e-9)


def test_gauss_newton_converges_from_a_poor_start():
    point = np.array([-1.0, 0.4, 0.3])
    pixels, _ = project_points(CAMERAS, point[None])
    position, residuals, jacobians = refine_position(CAMERAS, pixels[:, 0], point + [0.05, -0.04, 0.03])
    np.testing.assert_allclose(position, point, atol=1e-9)
    assert np.abs(residuals).max() < 1e-6
    assert jacobians.shape == (len(CAMERAS), 2, 3)


def test_one_corrupted_view_is_rejected():
    point = np.array([0.5, 0.2, 0.4])
    pixels, _ = project_points(CAMERAS, point[None])
    pixels = pixels[:, 0].copy()
    pixels[4] += [25.0, -10.0]
    result = triangulate(CAMERAS, pixels, pixel_noise_sigma=0.5, outlier_threshold_px=3.0)
    assert 4 not in result.views and len(result.views) == len(CAMERAS) - 1
    assert np.linalg.norm(result.position - point) < 1e-6


def test_corrupted_view_with_noise_is_rejected_among_three():
    rng = np.random.default_rng(5)
    point = np.array([-0.3, -0.2, 0.5])
    pixels, _ = project_points(CAMERAS[:3], point[None])
    pixels = pixels[:, 0] + rng.normal(0.0, 0.5, size=(3, 2))
    pixels[1] += [0.0, 40.0]
    result = triangulate(CAMERAS[:3], pixels, pixel_noise_sigma=0.5)
    assert result.views == (0, 2)
    assert np.linalg.norm(result.position - point) < 0.01


def test_too_few_or_inconsistent_views_give_none():
    point = np.array([0.1, 0.1, 0.3])
    pixels, _ = project_points(CAMERAS, point[None])
    pixels = pixels[:, 0]
    only_one = np.full_like(pixels, np.nan)
    only_one[2] = pixels[2]
    assert triangulate(CAMERAS, only_one, 0.5) is None
    two = np.full_like(pixels, np.nan)
    two[[1, 5]] = pixels[[1, 5]]
    assert triangulate(CAMERAS, two, 0.5) is not None
    assert triangulate(CAMERAS, two, 0.5, min_views=3) is None
    two[5] += [30.0, 30.0]  # two views that disagree: neither can be singled out
    assert triangulate(CAMERAS, two, 0.5) is None
    with pytest.raises(ValueError, match="min_views"):
        triangulate(CAMERAS, pixels, 0.5, min_views=1)


def test_noisy_triangulation_is_unbiased_and_its_covariance_consistent():
    # Monte Carlo: the normalised estimation error squared e^T Sigma^-1 e averages 3 (chi-square, 3 dof).
    sigma = 0.5
    rng = np.random.default_rng(11)
    point = np.array([0.8, -0.4, 0.35])
    truth, _ = project_points(CAMERAS, point[None])
    trials = 1500
    errors, nees = np.empty((trials, 3)), np.empty(trials)
    for trial in range(trials):
        result = triangulate(CAMERAS, truth[:, 0] + rng.normal(0.0, sigma, size=(len(CAMERAS), 2)), sigma)
        errors[trial] = result.position - point
        nees[trial] = errors[trial] @ np.linalg.solve(result.covariance, errors[trial])
    # chi-square(3) has variance 6: the mean of 1500 is within 3 +- 0.19 at three standard errors.
    assert nees.mean() == pytest.approx(3.0, abs=3 * np.sqrt(6 / trials))
    standard_error = errors.std(axis=0) / np.sqrt(trials)
    assert np.all(np.abs(errors.mean(axis=0)) < 4 * standard_error)
    # The sample covariance agrees with the predicted one.
    predicted = result.covariance
    np.testing.assert_allclose(np.cov(errors.T), predicted, atol=0.15 * np.trace(predicted) / 3)


def test_planning_covariance_equals_the_triangulation_covariance():
    point = np.array([[0.2, 0.3, 0.6]])
    pixels, _ = project_points(CAMERAS, point)
    result = triangulate(CAMERAS, pixels[:, 0], 0.7)
    seen = np.ones((len(CAMERAS), 1), dtype=bool)
    np.testing.assert_allclose(position_covariance(CAMERAS, point, seen, 0.7)[0], result.covariance, rtol=1e-9)
    one_view = np.zeros_like(seen)
    one_view[0] = True
    assert np.all(np.isinf(position_covariance(CAMERAS, point, one_view, 0.7)))


def test_covariance_from_jacobians_hand_case():
    # Two views measuring (x, y) and (y, z) with unit Jacobians: information diag(1, 2, 1) / sigma^2.
    jacobians = np.array([[[1.0, 0, 0], [0, 1.0, 0]], [[0, 1.0, 0], [0, 0, 1.0]]])
    np.testing.assert_allclose(position_covariance_from_jacobians(jacobians, 2.0), np.diag([4.0, 2.0, 4.0]))
