"""CameraSegment: the batched camera array and triangulator of a control segment equal the
reference systems (ApsCameraArray, analytic, + Triangulator) over a whole flight; triangulate_frames
equals triangulate frame by frame; the noise is numpy's default_rng([seed, trigger]) bit for bit;
the compiled OpenCV arithmetic is cv2's bit for bit and the compiled detections the NumPy/OpenCV
ones; a batch gives row by row the single-environment results; bad input raises."""

import cv2
import numba
import numpy as np
import pytest
from pydrake.common import RandomGenerator
from pydrake.common.value import AbstractValue
from pydrake.systems.framework import DiagramBuilder
from pydrake.systems.primitives import VectorLogSink

from ace_drake.diagrams import add_ball, add_random_sources, make_simulator
from ace_drake.perception.camera_segment import (
    CameraSegment,
    _CameraStack,
    _opencv_normalised,
    _opencv_project,
    _regular,
    _triangulate_compiled,
    _triangulate_rounds,
    _visible,
    draw_detection_noise,
    triangulate_frames,
    trigger_times,
)
from ace_drake.perception.cameras import (
    DEFAULT_CALIBRATION,
    OccluderSphere,
    camera_looking_at,
    load_cameras,
    project_points,
    simulate_detections,
    table_occluder,
    visibility,
)
from ace_drake.perception.params import CameraParams
from ace_drake.perception.triangulation import triangulate
from ace_drake.physics.flight import make_state
from ace_drake.physics.params import BallPhysicsParams
from ace_drake.systems.aps_camera_array import ApsCameraArray
from ace_drake.systems.random_seed import episode_seed
from ace_drake.systems.triangulator import Triangulator

CAMERAS = load_cameras(DEFAULT_CALIBRATION)
C = len(CAMERAS)
SEGMENT = 0.032  # s, one control segment
# A sphere in front of the first camera, hiding the ball from it over part of the flight.
BLOCKER = OccluderSphere(0.6 * CAMERAS[0].p_WC, 0.6)


def points_in_play_volume(count, seed):
    rng = np.random.default_rng(seed)
    return rng.uniform([-2.5, -1.2, 0.05], [2.5, 1.2, 1.2], size=(count, 3))


def noisy_frames(count, seed):
    """Frames (count, C, 2) with noise, dropout, outliers, too few views and inconsistent pairs."""
    rng = np.random.default_rng(seed)
    points = points_in_play_volume(count, seed)
    pixels, _ = project_points(CAMERAS, points)
    pixels = pixels.transpose(1, 0, 2) + rng.normal(0.0, 1.5, (count, C, 2))
    pixels[~visibility(CAMERAS, points).T] = np.nan
    pixels[rng.random((count, C)) < 0.3] = np.nan
    outliers = rng.random((count, C)) < 0.12
    pixels[outliers] += rng.normal(0.0, 30.0, (outliers.sum(), 2))
    pixels[: count // 10, 2:] = np.nan  # two views (some inconsistent) or fewer
    pixels[: count // 20, 1:] = np.nan  # one view
    return pixels


def assert_same_triangulations(batch, frames, **kwargs):
    flat_valid = batch.valid.reshape(-1)
    references = [triangulate(CAMERAS, frame, 1.5, **kwargs) for frame in frames.reshape(-1, C, 2)]
    for index, reference in enumerate(references):
        if reference is None:
            assert not flat_valid[index], index
            assert np.all(np.isnan(batch.position.reshape(-1, 3)[index]))
            continue
        assert flat_valid[index], index
        assert tuple(np.flatnonzero(batch.views.reshape(-1, C)[index])) == reference.views
        np.testing.assert_allclose(batch.position.reshape(-1, 3)[index], reference.position, rtol=0, atol=1e-9)
        np.testing.assert_allclose(batch.covariance.reshape(-1, 3, 3)[index], reference.covariance, rtol=1e-9, atol=1e-15)
        assert batch.rms_residual_px.reshape(-1)[index] == pytest.approx(reference.rms_residual_px, abs=1e-9)
    return references


# ---------------------------------------------------------------------------------- the reference


def run_reference(seed, duration, occluders=()):
    """A thrown ball (through its bounce) seen by ApsCameraArray + Triangulator, seeded by Drake's
    random context; returns the measurements, the true ball at each trigger and the seeds the
    array's random_seed port gave at t = 0 and after."""
    params = CameraParams()
    builder = DiagramBuilder()
    ball = add_ball(builder, BallPhysicsParams())
    cameras = builder.AddNamedSystem("aps_cameras", ApsCameraArray(CAMERAS, params))
    triangulator = builder.AddNamedSystem("triangulator", Triangulator(CAMERAS, params, history_capacity=1000))
    truth = builder.AddNamedSystem("truth_logger", VectorLogSink(9, publish_period=1.0 / params.trigger_rate))
    builder.Connect(ball.ball_state_port, cameras.ball_state_port)
    builder.Connect(ball.ball_state_port, truth.get_input_port())
    builder.Connect(cameras.detections_port, triangulator.detections_port)
    add_random_sources(builder)
    diagram = builder.Build()
    simulator = make_simulator(diagram)
    context = simulator.get_mutable_context()
    diagram.SetRandomContext(context, RandomGenerator(seed))
    ball.SetBallState(ball.GetMyMutableContextFromRoot(context), make_state([1.6, -0.3, 0.3], [-5.5, 0.5, 1.0], [0.0, -80.0, 0.0]))
    camera_context = cameras.GetMyContextFromRoot(context)
    if occluders:
        cameras.occluders_port.FixValue(camera_context, AbstractValue.Make(tuple(occluders)))
    seed_at_start = episode_seed(cameras.random_seed_port, camera_context, 0)
    simulator.AdvanceTo(duration)
    seed_after_start = episode_seed(cameras.random_seed_port, camera_context, 0)
    history = triangulator.position_measurements_port.Eval(triangulator.GetMyContextFromRoot(context))
    log = truth.FindLog(context)
    return history.measurements, log.sample_times(), log.data()[:3].T, (seed_at_start, seed_after_start)


@pytest.mark.parametrize("occluded", [False, True])
def test_segments_give_the_reference_measurements_over_a_flight(occluded):
    duration = 0.8
    extra = (BLOCKER,) if occluded else ()
    reference, log_times, log_positions, (seed_at_start, seed_after_start) = run_reference(11, duration, extra)
    assert seed_at_start != seed_after_start  # the RandomSource re-samples at t = 0
    dut = CameraSegment(CAMERAS, CameraParams())
    measurements, last_sequence = [], np.zeros(1, dtype=int)
    for start in np.arange(0.0, duration, SEGMENT):
        indices, times = trigger_times(start, start + SEGMENT, dut.params.trigger_rate)
        rows = [int(np.flatnonzero(np.abs(log_times - time) < 1e-12)[0]) for time in times]
        sequences = indices + 1  # the episode started at t = 0
        # Trigger 1 (t = 0) reads the seed drawn by SetRandomContext, later ones the source's next sample.
        seeds = np.where(sequences == 1, seed_at_start, seed_after_start).astype(np.uint64)[None]
        result = dut.measure(log_positions[rows][None], times, seeds, sequences, last_sequence, occluders=[extra])
        last_sequence = result.last_sequence
        measurements += result.measurements(0)
    released = [m for m in measurements if m.release_time <= duration]
    assert len(reference) > 140 and len(released) == len(reference)
    if occluded:  # the blocker hides the ball from the first camera over part of the flight
        hidden = visibility(CAMERAS, log_positions) & ~visibility(CAMERAS, log_positions, (table_occluder(), BLOCKER))
        assert 5 < hidden[0].sum() < len(log_times) - 5
    for mine, theirs in zip(released, reference):
        assert (mine.sequence, mine.capture_time, mine.release_time) == (theirs.sequence, theirs.capture_time, theirs.release_time)
        np.testing.assert_allclose(mine.value, theirs.value, rtol=0, atol=1e-9)
        np.testing.assert_allclose(mine.covariance, theirs.covariance, rtol=1e-9, atol=1e-15)


def test_detections_equal_simulate_detections_per_trigger():
    dut = CameraSegment(CAMERAS, CameraParams(dropout_probability=0.2))
    p_WB = points_in_play_volume(12, seed=3).reshape(2, 6, 3)
    seeds = np.array([2**64 - 5, 17], dtype=np.uint64)
    sequences = np.arange(1, 7)
    extra = [(), (BLOCKER, OccluderSphere(np.array([0.0, 0.0, 2.0]), 0.3))]
    pixels = dut.detect(p_WB, seeds, sequences, extra)
    for b in range(2):
        for k in range(6):
            rng = np.random.default_rng([int(seeds[b]), int(sequences[k])])
            expected = simulate_detections(CAMERAS, p_WB[b, k], rng, 1.5, 0.2, (table_occluder(), *extra[b]))
            np.testing.assert_array_equal(pixels[b, k], expected)


def test_noise_is_default_rng_bit_for_bit():
    # Enough triggers (36k normals) for the ziggurat's rare paths: rejections and the tail beyond 3.65.
    rng = np.random.default_rng(5)
    seeds = np.concatenate([rng.integers(0, 2**64, 2000, dtype=np.uint64), np.array([0, 1, 2**32 - 1, 2**32, 2**64 - 1], dtype=np.uint64)])
    sequences = rng.integers(1, 2**32, len(seeds))
    sequences[:3] = [1, 2, 3]
    noise, uniforms = draw_detection_noise(seeds, sequences, C)
    few_noise, few_uniforms = draw_detection_noise(seeds[-8:], sequences[-8:], C)
    np.testing.assert_array_equal(few_noise, noise[-8:])
    np.testing.assert_array_equal(few_uniforms, uniforms[-8:])
    for index, (seed, sequence) in enumerate(zip(seeds.tolist(), sequences.tolist())):
        generator = np.random.default_rng([seed, sequence])
        assert np.array_equal(noise[index].view(np.uint64), generator.normal(0.0, 1.0, size=(C, 2)).view(np.uint64)), index
        assert np.array_equal(uniforms[index].view(np.uint64), generator.random(C).view(np.uint64)), index
    assert np.sum(np.abs(noise) > 3.6541528853610087) >= 3  # the tail was drawn


# ---------------------------------------------------------------------------------- triangulation


def test_batched_triangulation_equals_triangulate_frame_by_frame():
    frames = noisy_frames(400, seed=7)
    batch = triangulate_frames(CAMERAS, frames.reshape(4, 100, C, 2), 1.5)
    assert batch.valid.shape == (4, 100) and batch.position.shape == (4, 100, 3) and batch.views.shape == (4, 100, C)
    references = assert_same_triangulations(batch, frames)
    dropped = [r for r, f in zip(references, frames) if r is not None and len(r.views) < np.all(np.isfinite(f), axis=1).sum()]
    assert len(dropped) > 20 and sum(r is None for r in references) > 20  # outliers rejected; frames without a position


def test_batched_triangulation_with_other_thresholds():
    frames = noisy_frames(150, seed=8)
    batch = triangulate_frames(CAMERAS, frames, 1.5, outlier_threshold_px=4.0, min_views=3)
    assert_same_triangulations(batch, frames, outlier_threshold_px=4.0, min_views=3)


def test_compiled_triangulation_equals_the_vectorised_rounds():
    frames = noisy_frames(300, seed=12)
    stack = _CameraStack(CAMERAS)
    usable = np.all(np.isfinite(frames), axis=2)
    normalised = stack.normalised(frames, usable)
    for threshold, min_views in ((8.0, 2), (4.0, 3)):
        compiled = _triangulate_compiled(stack, frames, 1.5, threshold, min_views, (len(frames),))
        rounds = _triangulate_rounds(stack, frames, normalised, usable, 1.5, threshold, min_views, (len(frames),))
        np.testing.assert_array_equal(compiled.valid, rounds.valid)
        np.testing.assert_array_equal(compiled.views, rounds.views)
        np.testing.assert_allclose(compiled.position, rounds.position, rtol=0, atol=1e-12)
        np.testing.assert_allclose(compiled.covariance, rounds.covariance, rtol=1e-9, atol=1e-18)
        np.testing.assert_allclose(compiled.rms_residual_px, rounds.rms_residual_px, rtol=1e-9, atol=1e-12)
        assert 50 < compiled.valid.sum() < len(frames)


def test_compiled_visibility_equals_visibility():
    rng = np.random.default_rng(13)
    points = np.concatenate([points_in_play_volume(300, seed=13), rng.uniform([-6.0, -4.0, -1.0], [6.0, 4.0, 4.0], size=(300, 3))])
    dut = CameraSegment(CAMERAS)
    pixels, _ = project_points(CAMERAS, points)
    seen = np.empty((C, len(points)), dtype=bool)
    _visible(points, pixels, dut._stack.R_CW, dut._stack.tvec, dut._focal_px, dut._image_size, dut._origins, *dut._boxes, dut.ball_radius, seen)
    expected = visibility(CAMERAS, points, (table_occluder(),), dut.ball_radius, pixels=pixels)
    np.testing.assert_array_equal(seen, expected)
    assert 0.1 < expected.mean() < 0.9


def test_stacked_projection_equals_opencv():
    cameras = [
        camera_looking_at("rational", [-5.0, 4.0, 2.0], [0.0, 0.0, 0.3], 1500.0, (-0.1, 0.03, 1e-3, -2e-3, 0.01, 0.02, -0.01, 0.005)),
        camera_looking_at("four", [0.0, -4.0, 3.0], [0.0, 0.0, 0.3], 1400.0, (-0.05, 0.02, 2e-3, 1e-3)),
        *CAMERAS[:3],
    ]
    stack = _CameraStack(cameras)
    assert stack.stacked
    points = points_in_play_volume(50, seed=9)
    pixels, jacobians = stack.project_with_jacobian(points)
    for index, camera in enumerate(cameras):
        expected_pixels, expected_jacobians = camera.project_with_jacobian(points)
        np.testing.assert_allclose(pixels[:, index], expected_pixels, rtol=0, atol=1e-9)
        np.testing.assert_allclose(jacobians[:, index], expected_jacobians, rtol=1e-9, atol=1e-9)


@numba.njit
def _opencv_undistort(pixels, intrinsics, k, out):
    for n in range(pixels.shape[0]):
        out[n, 0], out[n, 1] = _opencv_normalised(pixels[n, 0], pixels[n, 1], intrinsics, k)


def test_opencv_arithmetic_is_cv2_bit_for_bit():
    # Lens models of 4, 5, 8 and 12 coefficients; points in view, out of the image and behind the cameras.
    cameras = [
        camera_looking_at("rational", [-5.0, 4.0, 2.0], [0.0, 0.0, 0.3], 1500.0, (-0.1, 0.03, 1e-3, -2e-3, 0.01, 0.02, -0.01, 0.005)),
        camera_looking_at("four", [0.0, -4.0, 3.0], [0.0, 0.0, 0.3], 1400.0, (-0.05, 0.02, 2e-3, 1e-3)),
        camera_looking_at("thin prism", [4.0, 0.5, 2.5], [0.0, 0.0, 0.3], 1300.0, (-0.05, 0.02, 2e-3, 1e-3, 0.01, 0, 0, 0, 1e-3, -1e-3, 2e-3, 5e-4)),
        *CAMERAS,
    ]
    stack = _CameraStack(cameras)
    rng = np.random.default_rng(14)
    points = np.concatenate([points_in_play_volume(3000, seed=14), rng.uniform([-8.0, -6.0, -1.0], [8.0, 6.0, 5.0], size=(3000, 3))])
    pixels = np.empty((len(cameras), len(points), 2))
    _opencv_project(points, stack.cv_rotation, stack.tvec, stack.cv_intrinsics, stack.cv_distortion, pixels)
    for index, camera in enumerate(cameras):
        assert np.array_equal(pixels[index].view(np.uint64), camera.project(points).view(np.uint64)), camera.name
        detected = pixels[index] + rng.normal(0.0, 2.0, pixels[index].shape)
        detected = np.concatenate([detected[np.all(np.abs(detected) < 5000.0, axis=1)], rng.uniform(-500.0, 2000.0, (2000, 2))])
        normalised = np.empty_like(detected)
        _opencv_undistort(detected, stack.cv_intrinsics[index], stack.cv_distortion[index], normalised)
        expected = cv2.undistortPoints(detected.reshape(-1, 1, 2), camera.K, camera.distortion).reshape(-1, 2)
        assert np.array_equal(normalised.view(np.uint64), expected.view(np.uint64)), camera.name


@pytest.mark.parametrize("dropout", [0.02, 0.2])
def test_compiled_detections_equal_numpy_and_opencv(dropout):
    dut = CameraSegment(CAMERAS, CameraParams(dropout_probability=dropout))
    reference = CameraSegment(CAMERAS, CameraParams(dropout_probability=dropout))
    reference._compiled = False  # the same steps in NumPy and OpenCV (draw_detection_noise, cv2.projectPoints, _visible)
    reference._stack.stacked = False
    rng = np.random.default_rng(15)
    p_WB = np.concatenate([points_in_play_volume(200, seed=15), rng.uniform([-6.0, -4.0, -1.0], [6.0, 4.0, 4.0], size=(200, 3))]).reshape(4, 100, 3)
    seeds = rng.integers(0, 2**64, 4, dtype=np.uint64)
    sequences = rng.integers(1, 2**32, (4, 100))
    occluders = [(), (BLOCKER,), (), (OccluderSphere(np.array([0.0, 0.0, 2.0]), 0.3),)]
    pixels = dut.detect(p_WB, seeds, sequences, occluders)
    expected = reference.detect(p_WB, seeds, sequences, occluders)
    assert np.array_equal(pixels.view(np.uint64), expected.view(np.uint64))
    assert 0.2 < np.isfinite(pixels[..., 0]).mean() < 0.9
    measured, measured_reference = dut.measure(p_WB, np.zeros(100), seeds, sequences), reference.measure(p_WB, np.zeros(100), seeds, sequences)
    np.testing.assert_array_equal(measured.valid, measured_reference.valid)
    np.testing.assert_allclose(measured.value, measured_reference.value, rtol=0, atol=1e-12)


def test_frames_are_the_flat_measurements():
    dut = CameraSegment(CAMERAS)
    p_WB = points_in_play_volume(12, seed=16).reshape(2, 6, 3)
    seeds = np.array([2**64 - 5, 17], dtype=np.uint64)
    sequences = np.arange(1, 13).reshape(2, 6)
    measured = dut.measure(p_WB, np.arange(6) * 0.005, seeds, sequences)
    pixels, frames = dut.frames(p_WB.reshape(-1, 3), np.repeat(seeds, 6), sequences.reshape(-1).astype(np.uint64))
    np.testing.assert_array_equal(pixels, measured.pixels.reshape(-1, C, 2))
    np.testing.assert_array_equal(frames.valid, measured.valid.reshape(-1))
    np.testing.assert_array_equal(frames.position, measured.value.reshape(-1, 3))
    np.testing.assert_array_equal(frames.covariance, measured.covariance.reshape(-1, 3, 3))
    # measure reads frames: the pixels also equal the NumPy and OpenCV steps' (the reference path)
    reference = CameraSegment(CAMERAS)
    reference._compiled = False
    reference._stack.stacked = False
    expected = reference.detect(p_WB, seeds, sequences)
    assert np.array_equal(pixels.view(np.uint64), expected.reshape(-1, C, 2).view(np.uint64))
    with pytest.raises(ValueError, match="p_WB must be finite"):
        dut.frames(np.full((1, 3), np.nan), seeds[:1], np.ones(1, dtype=np.uint64))


@numba.njit
def _economy_and_full_right_vectors(matrices):
    out = np.empty((len(matrices), 2, matrices.shape[2], matrices.shape[2]))
    for n in range(len(matrices)):
        out[n, 0] = np.linalg.svd(matrices[n], full_matrices=False)[2]
        out[n, 1] = np.linalg.svd(matrices[n])[2]
    return out


def test_compiled_triangulation_shortcuts_change_nothing():
    # The DLT's economy SVD has the full SVD's right singular vectors bit for bit (views dropped as
    # zero rows), and _regular decides as LAPACK's eigenvalues do, near-singular matrices included.
    frames = noisy_frames(2000, seed=17)
    stack = _CameraStack(CAMERAS)
    usable = np.all(np.isfinite(frames), axis=2) & (np.random.default_rng(17).random((len(frames), C)) < 0.8)
    normalised = stack.normalised(frames, usable)
    P = stack.projection
    rows = np.stack([normalised[..., :1] * P[None, :, 2] - P[None, :, 0], normalised[..., 1:] * P[None, :, 2] - P[None, :, 1]], axis=2)
    rows = (rows * usable[:, :, None, None]).reshape(len(frames), 2 * C, 4)
    vectors = _economy_and_full_right_vectors(rows[usable.sum(axis=1) >= 2])
    assert np.array_equal(vectors[:, 0].view(np.uint64), vectors[:, 1].view(np.uint64))
    rng = np.random.default_rng(18)
    for condition in 10.0 ** np.arange(0.1, 17, 0.25):  # clear of the 1e12 boundary, where roundings decide
        rotation = np.linalg.qr(rng.normal(size=(3, 3)))[0]
        scale = 10.0 ** rng.uniform(-3, 9)
        information = scale * rotation @ np.diag([1.0, rng.uniform(1.0, condition), condition]) @ rotation.T
        information = 0.5 * (information + information.T)
        eigenvalues = np.linalg.eigvalsh(information)
        assert _regular(information) == (eigenvalues[0] > 1e-12 * max(eigenvalues[2], 1e-300)), condition
    assert not _regular(np.zeros((3, 3)))


def test_degenerate_frames_give_no_position():
    truth, _ = project_points(CAMERAS, np.array([[0.2, 0.1, 0.4]]))
    frames = np.full((3, C, 2), np.nan)
    frames[1, 0] = truth[0, 0]  # one view
    frames[2, :2] = truth[:2, 0]
    frames[2, 1] += [60.0, -60.0]  # two views that disagree
    batch = triangulate_frames(CAMERAS, frames, 1.5)
    assert not batch.valid.any() and not batch.views.any() and np.all(np.isnan(batch.covariance))
    assert_same_triangulations(batch, frames)


# ---------------------------------------------------------------------------------- batches, timing, errors


def test_a_batch_gives_the_single_environment_results_row_by_row():
    dut = CameraSegment(CAMERAS, CameraParams())
    indices, times = trigger_times(0.1, 0.1 + SEGMENT, 200.0)
    B, m = 5, len(indices)
    rng = np.random.default_rng(4)
    start = rng.uniform([-1.2, -0.6, 0.1], [1.2, 0.6, 0.5], (B, 1, 3))
    velocity = rng.uniform([-6.0, -1.0, -1.0], [-3.0, 1.0, 1.0], (B, 1, 3))
    p_WB = start + velocity * (times - times[0])[None, :, None]
    seeds = rng.integers(0, 2**64, B, dtype=np.uint64)
    sequences = indices[None] + 1 - np.arange(B)[:, None]  # episodes that started at different triggers
    last = np.array([0, 3, 9, 0, 40])
    occluders = [(), (BLOCKER,), (), (BLOCKER,), ()]
    batch = dut.measure(p_WB, times, seeds, sequences, last, occluders)
    assert batch.valid.shape == (B, m) and batch.value.shape == (B, m, 3) and batch.covariance.shape == (B, m, 3, 3)
    for b in range(B):
        single = dut.measure(p_WB[b : b + 1], times, seeds[b : b + 1], sequences[b : b + 1], last[b : b + 1], occluders[b : b + 1])
        np.testing.assert_array_equal(batch.valid[b], single.valid[0])
        np.testing.assert_array_equal(batch.sequence[b], single.sequence[0])
        np.testing.assert_array_equal(batch.pixels[b], single.pixels[0])
        np.testing.assert_allclose(batch.value[b], single.value[0], rtol=0, atol=1e-12)
        np.testing.assert_allclose(batch.covariance[b], single.covariance[0], rtol=1e-12, atol=1e-18)
    np.testing.assert_array_equal(batch.release_time, np.broadcast_to(times + 0.0102, (B, m)))
    valid_counts = batch.valid.sum(axis=1)
    np.testing.assert_array_equal(batch.last_sequence, last + valid_counts)
    nothing = dut.measure(p_WB[:1] + [0.0, 0.0, -5.0], times, seeds[:1], sequences[:1], last[1:2])  # under the floor: unseen
    assert not nothing.valid.any() and nothing.last_sequence.tolist() == [3]


def test_trigger_times_on_the_200_hz_grid():
    indices, times = trigger_times(0.0, SEGMENT, 200.0)
    np.testing.assert_array_equal(indices, np.arange(7))
    np.testing.assert_array_equal(times, np.arange(7) * 0.005)
    indices, _ = trigger_times(SEGMENT, 2 * SEGMENT, 200.0)
    np.testing.assert_array_equal(indices, np.arange(7, 13))  # 35, 40, ..., 60 ms
    assert trigger_times(0.005 - 1e-12, 0.005, 200.0)[0].tolist() == []  # 5 ms is on the grid, and excluded at the end
    assert trigger_times(0.005 - 1e-12, 0.0051, 200.0)[0].tolist() == [1]
    with pytest.raises(ValueError, match="start <= end"):
        trigger_times(0.1, 0.0, 200.0)


def test_bad_input_raises_naming_the_value():
    dut = CameraSegment(CAMERAS, CameraParams())
    p_WB = np.zeros((2, 3, 3)) + [0.0, 0.0, 0.3]
    seeds = np.array([1, 2], dtype=np.uint64)
    times = np.array([0.0, 0.005, 0.01])
    with pytest.raises(ValueError, match=r"p_WB must have shape \(B, m, 3\)"):
        dut.measure(np.zeros((3, 3)), times, seeds, [1, 2, 3])
    with pytest.raises(ValueError, match="seeds must be integers of shape"):
        dut.measure(p_WB, times, np.array([1.0, 2.0]), np.array([1, 2, 3]))
    with pytest.raises(ValueError, match="sequences must be integers of shape"):
        dut.measure(p_WB, times, seeds, np.array([1, 2]))
    with pytest.raises(ValueError, match="start at 1"):
        dut.measure(p_WB, times, seeds, np.array([0, 1, 2]))
    with pytest.raises(ValueError, match="capture_times must be finite, of shape"):
        dut.measure(p_WB, times[:2], seeds, np.array([1, 2, 3]))
    with pytest.raises(ValueError, match="last_sequence must have shape"):
        dut.measure(p_WB, times, seeds, np.array([1, 2, 3]), last_sequence=np.zeros(3, dtype=int))
    with pytest.raises(ValueError, match="one sequence per environment"):
        dut.measure(p_WB, times, seeds, np.array([1, 2, 3]), occluders=[()])
    with pytest.raises(ValueError, match=r"pixels must have shape \(\.\.\., 9, 2\)"):
        triangulate_frames(CAMERAS, np.zeros((4, 8, 2)), 1.5)
    with pytest.raises(ValueError, match="only the analytic mode"):
        CameraSegment(CAMERAS, CameraParams(mode="rendered"))
