"""Camera placement: coverage on hand-worked cases, genes, a CMA-ES run that improves a bad
placement reproducibly, the plot, and the shipped calibration's recorded figures."""

import json

import numpy as np
import pytest

from ace_drake.perception.cameras import DEFAULT_CALIBRATION, camera_looking_at, load_cameras
from ace_drake.perception.placement import (
    DEFAULT_TOWERS,
    PlacementProblem,
    cameras_from_genes,
    coverage,
    evaluate_placement,
    genes_aimed_at,
    optimize_and_write,
    optimize_placement,
    play_volume_points,
    write_coverage_plot,
)

SMALL_GRID = play_volume_points(spacing=0.6)


def test_play_volume_grid():
    points = play_volume_points(spacing=0.25)
    assert points.shape == (21 * 11 * 6, 3)
    np.testing.assert_allclose(points.min(axis=0), [-2.5, -1.2, 0.05])
    np.testing.assert_allclose(points.max(axis=0), [2.5, 1.2, 1.2])


def test_coverage_counts_views_at_the_minimum_radius():
    # Three cameras 10 m from a point, f = 2000 px: the ball's radius is 2000 * 0.02 / 10 = 4 px.
    point = np.array([[0.0, 0.0, 0.3]])
    cameras = [
        camera_looking_at(f"c{i}", point[0] + 10.0 * np.array([np.cos(a), np.sin(a), 0.0]), point[0], 2000.0)
        for i, a in enumerate([0.3, 2.0, 4.0])
    ]
    assert coverage(cameras, point, min_views=3, min_radius_px=3.9) == 1.0
    assert coverage(cameras, point, min_views=3, min_radius_px=5.0) == 0.0
    assert coverage(cameras[:2], point, min_views=3, min_radius_px=3.9) == 0.0
    assert coverage(cameras[:2], point, min_views=2, min_radius_px=3.9) == 1.0
    # Under the table the same cameras (level with the ball) are blocked by the table's box.
    below = np.array([[0.0, 0.0, -0.3]])
    level = [camera_looking_at(c.name, c.p_WC - [0, 0, 0.6], below[0], 2000.0) for c in cameras]
    assert coverage(level, below, min_views=1, min_radius_px=1.0) == 0.0
    assert coverage(level, below, min_views=1, min_radius_px=1.0, occluders=()) == 1.0


def test_genes_aimed_at_point_the_cameras():
    problem = PlacementProblem()
    target = np.array([0.0, 0.0, 0.3])
    cameras, lenses = cameras_from_genes(genes_aimed_at(target, problem), problem)
    assert [c.name for c in cameras] == [t.name for t in DEFAULT_TOWERS]
    assert lenses == (2,) * len(DEFAULT_TOWERS)  # the middle of five lenses: 8 mm
    for camera in cameras:
        direction = (target - camera.p_WC) / np.linalg.norm(target - camera.p_WC)
        np.testing.assert_allclose(camera.R_WC[:, 2], direction, atol=1e-9)
        assert camera.focal_length_px == pytest.approx(8e-3 / 3.45e-6)
        assert camera.p_WC[2] == pytest.approx(2.5 - 0.76)


def test_evaluation_figures():
    problem = PlacementProblem()
    cameras, _ = cameras_from_genes(genes_aimed_at([0.0, 0.0, 0.3], problem), problem)
    figures = evaluate_placement(cameras, SMALL_GRID, problem)
    assert figures.coverage == coverage(cameras, SMALL_GRID)
    assert figures.views.shape == (len(SMALL_GRID),)
    assert 0.0 < figures.uncertainty < 0.01  # m: a few millimetres at 0.5 px
    expected_cost = (1 - figures.coverage) + problem.partial_weight * (1 - np.mean(np.minimum(figures.views, 3) / 3)) + problem.uncertainty_weight * 1e3 * figures.uncertainty
    assert figures.cost == pytest.approx(expected_cost)


def bad_genes(problem):
    # Every camera low, with the longest lens, looking 50 degrees away from the table and upwards.
    genes = np.tile([0.99, 0.0, 0.0, 1.0], len(problem.towers))
    return genes


def test_optimiser_improves_a_bad_placement_reproducibly():
    problem = PlacementProblem()
    calls = []
    run = dict(points=SMALL_GRID, seed=3, iterations=25, population_size=10, initial_genes=bad_genes(problem), initial_step=0.3)
    result = optimize_placement(problem, progress=lambda i, cost, figures: calls.append((i, cost)), **run)
    assert result.initial_figures.coverage < 0.05
    assert result.figures.coverage > result.initial_figures.coverage + 0.4
    assert result.figures.cost < result.initial_figures.cost
    assert [i for i, _ in calls] == list(range(25))
    assert all(later <= earlier for (_, earlier), (_, later) in zip(calls, calls[1:]))  # best so far
    assert result.evaluations == 1 + 25 * 10
    # The returned cameras are the genes' cameras and score as reported.
    assert evaluate_placement(result.cameras, SMALL_GRID, problem).cost == pytest.approx(result.figures.cost)
    again = optimize_placement(problem, **run)
    np.testing.assert_array_equal(again.genes, result.genes)
    other = optimize_placement(problem, **{**run, "seed": 4})
    assert not np.array_equal(other.genes, result.genes)


def test_optimize_and_write_and_the_plot(tmp_path):
    path = tmp_path / "cams.yaml"
    sidecar = optimize_and_write(path, seed=1, iterations=2, spacing=0.8, validation_spacing=0.8, population_size=4, plot_path=tmp_path / "coverage.png", command="test")
    cameras = load_cameras(path)
    assert len(cameras) == 9
    stored = json.loads(path.with_suffix(".json").read_text())
    assert stored == sidecar
    assert stored["seed"] == 1 and stored["command"] == "test" and stored["evaluations"] == 9
    assert coverage(cameras, play_volume_points(0.8)) == pytest.approx(stored["figures"]["coverage"], abs=1e-5)
    assert (tmp_path / "coverage.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_coverage_plot_writes_an_image(tmp_path):
    cameras = load_cameras(DEFAULT_CALIBRATION)
    write_coverage_plot(cameras, SMALL_GRID, tmp_path / "plot.png")
    assert (tmp_path / "plot.png").stat().st_size > 10_000


def test_shipped_placement_has_its_recorded_figures():
    sidecar = json.loads(DEFAULT_CALIBRATION.with_suffix(".json").read_text())
    cameras = load_cameras(DEFAULT_CALIBRATION)
    points = play_volume_points(sidecar["play_volume"]["spacing_m"])
    assert len(points) == sidecar["play_volume"]["points"]
    figures = evaluate_placement(cameras, points, PlacementProblem())
    assert figures.coverage == pytest.approx(sidecar["figures"]["coverage"], abs=1e-5)
    assert 1e3 * figures.uncertainty == pytest.approx(sidecar["figures"]["uncertainty_mm"], abs=1e-3)
    assert figures.coverage >= 0.95
    assert sidecar["figures"]["initial_coverage"] < figures.coverage
