"""The perception benchmark (``ace-drake bench perception``): the frame-camera path and the ball
state estimator on incoming shots from recorded matches.

Each shot starts at a recorded ``shot_p2`` ball state (the human's hit) and flies under the
project's physics (post-bounce perturbations on). At every 200 Hz trigger the nine cameras of
``models/cameras.yaml`` see the true ball centre with the configured pixel noise and dropout
(``perception.cameras.simulate_detections``, occlusion by the table) and the triangulator
reconstructs it (``perception.triangulation.triangulate``); the positions are released after the
configured latency. The EKF (``perception.ball_ekf``) then runs on those positions and on the
statistical spin sensor's measurements, as the ``BallEstimator`` does in the diagram; the same
EKF on the statistical position sensor (the training path) is reported beside it. Pure NumPy
and OpenCV: the Drake systems wrap exactly these functions.
"""

from __future__ import annotations

import time
from collections.abc import Callable

import numpy as np

from ace_drake.artefacts import sha256
from ace_drake.config import MODELS_DIR, InputError
from ace_drake.match_data import load_match_events
from ace_drake.perception.ball_ekf import BallEkf
from ace_drake.perception.cameras import load_cameras, simulate_detections
from ace_drake.perception.ekf_evaluation import SimulatedShot, evaluate, simulate_shots
from ace_drake.perception.params import CameraParams
from ace_drake.perception.placement import coverage, play_volume_points
from ace_drake.perception.sensor_models import PendingMeasurement, insert_pending
from ace_drake.perception.triangulation import triangulate

CAMERA_STREAM = 21  # random stream of the camera detections under the seed


def incoming_shots(path: str, count: int, seed: int) -> np.ndarray:
    """``count`` recorded human shots (``shot_p2`` ball states (count, 9): p (m), v (m/s), w
    (rad/s)) of a match-data CSV, drawn without replacement (all of them if there are fewer)."""
    states = np.array([event.state for event in load_match_events(path) if event.kind == "shot" and event.side == "p2"])
    if not len(states):
        raise InputError(f"{path}: no incoming shots (shot_p2 events)")
    rng = np.random.default_rng(seed)
    return states[np.sort(rng.choice(len(states), size=min(count, len(states)), replace=False))]


def bench_perception(
    data: str,
    shots: int = 50,
    seed: int = 0,
    duration: float = 0.5,
    params: CameraParams | None = None,
    progress: Callable[[str], None] | None = None,
) -> dict:
    """The figures of ``ace-drake bench perception`` (module docstring) over ``shots`` incoming
    shots of ``data``, each followed for ``duration`` s: triangulation error against the truth
    (mean, p95, max, m), the fraction of triggers with a triangulation, latency (configured, s)
    and CPU time per 9-camera triangulation (median, p99, ms); EKF errors 50 ms and 150 ms after
    the hit on the camera path and on the statistical one; coverage of the shipped placement;
    ``data`` and its sha256."""
    say = progress or (lambda _: None)
    params = params or CameraParams()
    cameras = load_cameras(MODELS_DIR / params.calibration)
    initial = incoming_shots(data, shots, seed)
    say(f"bench perception: simulating {len(initial)} shots for {duration} s")
    simulated = simulate_shots(initial, duration, seed=seed)
    errors, seconds, triggers, camera_shots = [], [], 0, []
    trigger_step = int(round(1.0 / params.trigger_rate / (simulated[0].times[1] - simulated[0].times[0])))
    for index, shot in enumerate(simulated):
        rng = np.random.default_rng([seed, CAMERA_STREAM, index])
        positions = []
        for row in range(0, len(shot.times), trigger_step):
            capture, truth = float(shot.times[row]), shot.states[row, :3]
            pixels = simulate_detections(cameras, truth, rng, params.pixel_noise_sigma, params.dropout_probability)
            start = time.perf_counter()
            result = triangulate(cameras, pixels, params.pixel_noise_sigma, params.outlier_threshold_px, params.min_views)
            seconds.append(time.perf_counter() - start)
            triggers += 1
            if result is None:
                continue
            errors.append(float(np.linalg.norm(result.position - truth)))
            positions.append(PendingMeasurement(capture, capture + params.latency, result.position, result.covariance))
        camera_shots.append(SimulatedShot(shot.times, shot.states, shot.events, insert_pending((), positions), shot.spins))
        if (index + 1) % 10 == 0:
            say(f"bench perception: {index + 1}/{len(simulated)} shots triangulated")
    say("bench perception: the EKF on both position paths")
    errors, seconds = np.array(errors), np.array(seconds) * 1e3
    say("bench perception: coverage of the shipped placement on a 0.1 m grid")
    return {
        "data": str(data),
        "data_sha256": sha256(data),
        "shots": len(initial),
        "seed": seed,
        "cameras": len(cameras),
        "pixel_noise_sigma_px": params.pixel_noise_sigma,
        "dropout_probability": params.dropout_probability,
        "triangulation": {
            "triggers": triggers,
            "valid_fraction": len(errors) / max(triggers, 1),
            "error_mean_m": float(errors.mean()),
            "error_p95_m": float(np.percentile(errors, 95)),
            "error_max_m": float(errors.max()),
            "latency_s": params.latency,
            "cpu_median_ms": float(np.median(seconds)),
            "cpu_p99_ms": float(np.percentile(seconds, 99)),
        },
        "ekf_cameras": evaluate(BallEkf(), camera_shots),
        "ekf_statistical_sensor": evaluate(BallEkf(), simulated),
        "coverage_3_views_5_px": coverage(cameras, play_volume_points(0.1)),
    }
