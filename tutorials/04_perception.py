"""Tutorial 04: perception, or how the robot knows where the ball is and how it spins.

Read this file top to bottom like a notebook. The robot never sees the true ball: nine frame
cameras on towers around the court detect it at every 200 Hz trigger, a triangulator turns their
detections into a 3D position 10.2 ms later, a gaze-control system measures its spin at 400-700 Hz,
and an extended Kalman filter on the project's own ball physics fuses both into the state the
controller uses (paper, Fig. 2 and Methods *Ball triangulation*, *Sensor modelling*). It shows

  1. the camera array: where the nine cameras stand, what they look at (their frusta, in Meshcat),
     and how much of the play volume at least three of them see with the ball at least 5 px wide;
  2. a recorded shot seen through them: the perception Diagram of ace_drake.diagrams (ball ->
     aps_cameras -> triangulator, spin_sensor, -> ball_estimator) in a Simulator; the detections'
     triangulations and the EKF's estimate against the truth, plotted;
  3. what dropout and latency cost: the EKF's velocity error 50 ms and 150 ms after the hit with
     the training path's position sensor at several dropout probabilities and latencies.

Numbers are SI units (m, s, rad). Run it from the repository root:

    .venv/bin/python tutorials/04_perception.py                # all parts
    .venv/bin/python tutorials/04_perception.py --no-html      # skip the Meshcat file
    .venv/bin/python tutorials/04_perception.py --out DIR

It writes perception.png and, unless --no-html, cameras.html into --out (default
out/tutorials/04). It uses the match data at ../shared/data/ace_match_events_elite.csv for the
shot when it is there, a built-in shot otherwise. It takes about 10 s.
"""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path

import matplotlib
import matplotlib.pyplot as plt
import numpy as np
from pydrake.geometry import Cylinder, Meshcat, Rgba, Sphere
from pydrake.math import RigidTransform, RotationMatrix

from ace_drake.config import MODELS_DIR
from ace_drake.diagrams import build_perception_diagram, make_simulator
from ace_drake.match_data import load_match_events
from ace_drake.perception.ball_ekf import BallEkf
from ace_drake.perception.cameras import load_cameras
from ace_drake.perception.ekf_evaluation import evaluate, simulate_shots
from ace_drake.perception.params import PerceptionParams, PositionSensorParams
from ace_drake.perception.placement import coverage, play_volume_points
from ace_drake.physics.flight import make_state
from ace_drake.physics.params import BallPhysicsParams
from ace_drake.systems.ball_visualizer import draw_table

matplotlib.use("Agg")  # write files only, never open a window

REPO_ROOT = Path(__file__).resolve().parents[1]
DATA = REPO_ROOT.parent / "shared" / "data" / "ace_match_events_elite.csv"
# A shot from the human's side when the match data is absent: 9 m/s with topspin.
BUILT_IN_SHOT = make_state((1.5, 0.3, 0.2), (-8.5, -0.4, 1.2), (0.0, 120.0, 0.0))


def parse_args() -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=REPO_ROOT / "out" / "tutorials" / "04")
    parser.add_argument("--no-html", action="store_true", help="skip the Meshcat HTML file")
    return parser.parse_args()


def draw_frustum(meshcat: Meshcat, path: str, camera, depth: float = 1.2) -> None:
    """The camera as a small sphere at its centre and four edges to the image corners at
    ``depth`` m along its optical axis."""
    meshcat.SetObject(f"{path}/centre", Sphere(0.06), Rgba(0.1, 0.1, 0.1, 1.0))
    meshcat.SetTransform(f"{path}/centre", RigidTransform(camera.p_WC))
    corners_px = np.array([[0, 0], [camera.width, 0], [camera.width, camera.height], [0, camera.height]], dtype=float)
    K_inverse = np.linalg.inv(camera.K)
    for i, corner in enumerate(corners_px):
        ray_C = K_inverse @ np.array([corner[0], corner[1], 1.0])  # z = 1 in the camera frame
        end_W = camera.p_WC + camera.R_WC @ (ray_C * depth)
        edge = end_W - camera.p_WC
        length = float(np.linalg.norm(edge))
        # A thin cylinder along the edge (Meshcat cylinders lie along their z axis).
        z = edge / length
        x = np.cross([0.0, 0.0, 1.0], z) if abs(z[2]) < 0.99 else np.array([1.0, 0.0, 0.0])
        x /= np.linalg.norm(x)
        R = RotationMatrix(np.column_stack([x, np.cross(z, x), z]))
        meshcat.SetObject(f"{path}/edge_{i}", Cylinder(0.01, length), Rgba(0.2, 0.4, 0.9, 0.8))
        meshcat.SetTransform(f"{path}/edge_{i}", RigidTransform(R, camera.p_WC + 0.5 * edge))


def recorded_shot() -> tuple[np.ndarray, str]:
    """The first recorded human shot that lands on the robot's half, or the built-in one."""
    if not DATA.is_file():
        return BUILT_IN_SHOT, "built-in shot (match data not found)"
    for event in load_match_events(DATA):
        if event.kind == "shot" and event.side == "p2" and event.state[3] < -6.0:
            return event.state, f"recorded shot from {DATA.name}"
    return BUILT_IN_SHOT, "built-in shot"


def main() -> None:
    args = parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    physics = BallPhysicsParams()
    figure, axes = plt.subplots(2, 2, figsize=(14, 10))

    # ------------------------------------------------------------------ 1. the camera array
    params = PerceptionParams()
    cameras = load_cameras(MODELS_DIR / params.camera.calibration)
    print("1. the camera array (models/cameras.yaml, placed by `ace-drake cameras optimize`):")
    for camera in cameras:
        print(f"   {camera.name:<14} at {np.round(camera.p_WC, 2)} m, focal length {camera.focal_length_px:.0f} px")
    covered = coverage(cameras, play_volume_points(0.2))
    print(f"   the play volume seen by >= 3 cameras with the ball >= 5 px in radius: {100 * covered:.1f} %")
    ax = axes[0, 0]
    ax.add_patch(plt.Rectangle((-1.37, -0.7625), 2.74, 1.525, color="tab:green", alpha=0.4))
    for camera in cameras:
        ax.plot(*camera.p_WC[:2], "ks")
        axis = camera.R_WC[:, 2]
        ax.arrow(*camera.p_WC[:2], *(1.2 * axis[:2]), head_width=0.12, color="tab:blue")
        ax.annotate(camera.name, camera.p_WC[:2], fontsize=7, xytext=(4, 4), textcoords="offset points")
    ax.set_aspect("equal")
    ax.set(xlabel="x (m)", ylabel="y (m)", title=f"1. nine cameras, optical axes; {100 * covered:.0f}% of the volume in >= 3 views")

    meshcat = None if args.no_html else Meshcat()
    if meshcat is not None:
        draw_table(meshcat, physics)
        meshcat.SetCameraPose(np.array([-5.5, -6.0, 4.0]), np.array([0.0, 0.0, 0.0]))
        for camera in cameras:
            draw_frustum(meshcat, f"/cameras/{camera.name}", camera)

    # ------------------------------------------------------------------ 2. a shot seen through them
    shot, source = recorded_shot()
    print(f"\n2. {source}: p = {np.round(shot[:3], 2)} m, v = {np.round(shot[3:6], 2)} m/s, w = {np.round(shot[6:], 0)} rad/s")
    diagram = build_perception_diagram(params, physics, meshcat=meshcat)
    simulator = make_simulator(diagram)
    context = simulator.get_mutable_context()
    diagram.GetSubsystemByName("ball").GetMyMutableContextFromRoot(context).SetContinuousState(shot)
    simulator.Initialize()
    if meshcat is not None:
        meshcat.StartRecording(frames_per_second=60.0, set_visualizations_while_recording=False)
    triangulator = diagram.GetSubsystemByName("triangulator")
    triangulations = {}  # sequence -> (capture time, position, release time)
    duration = 0.55
    for t in np.arange(0.005, duration + 1e-9, 0.005):
        simulator.AdvanceTo(t)
        history = triangulator.position_measurements_port.Eval(triangulator.GetMyContextFromRoot(context))
        for measurement in history.measurements:
            triangulations[measurement.sequence] = (measurement.capture_time, measurement.value, measurement.release_time)
    if meshcat is not None:
        meshcat.StopRecording()
        meshcat.PublishRecording()
        html = args.out / "cameras.html"
        html.write_text(meshcat.StaticHtml())
    truth_log = diagram.GetSubsystemByName("ball_logger").FindLog(context)
    estimate_log = diagram.GetSubsystemByName("estimate_logger").FindLog(context)
    times, truth = truth_log.sample_times(), truth_log.data()
    estimate_times, estimate = estimate_log.sample_times(), estimate_log.data()
    captures = np.array([value[0] for value in triangulations.values()])
    positions = np.array([value[1] for value in triangulations.values()])
    latencies = np.array([value[2] - value[0] for value in triangulations.values()])
    true_at_capture = np.array([np.interp(captures, times, truth[i]) for i in range(3)]).T
    triangulation_error = np.linalg.norm(positions - true_at_capture, axis=1)
    print(f"   {len(positions)} triangulations in {duration} s, released {1e3 * latencies.mean():.1f} ms after capture; "
          f"error mean {1e3 * triangulation_error.mean():.2f} mm, max {1e3 * triangulation_error.max():.2f} mm")
    truth_at_estimate = np.array([np.interp(estimate_times, times, truth[i]) for i in range(9)])
    tracked = np.any(estimate != 0.0, axis=0)  # the estimator outputs zeros until it has a track
    errors = {
        "position (mm)": 1e3 * np.linalg.norm(estimate[:3] - truth_at_estimate[:3], axis=0),
        "velocity (cm/s)": 1e2 * np.linalg.norm(estimate[3:6] - truth_at_estimate[3:6], axis=0),
        "spin (rad/s)": np.linalg.norm(estimate[6:] - truth_at_estimate[6:], axis=0),
    }
    for moment in (0.05, 0.15, 0.45):
        row = np.searchsorted(estimate_times, moment)
        print(f"   EKF at {moment:.2f} s: " + ", ".join(f"{name} error {values[row]:.1f}" for name, values in errors.items()))
    ax = axes[0, 1]
    for i, (name, color) in enumerate(zip("xyz", ["tab:red", "tab:green", "tab:blue"])):
        ax.plot(times, truth[i], color=color, lw=1.0, label=f"{name} true")
        ax.plot(captures, positions[:, i], ".", color=color, ms=3, label=f"{name} triangulated")
        ax.plot(estimate_times[tracked], estimate[i, tracked], "--", color="k", lw=0.8, label="EKF" if i == 0 else None)
    ax.set(xlabel="t (s)", ylabel="m", title="2. the shot: truth, triangulations (at capture time), EKF")
    ax.legend(fontsize=7, ncol=2)
    ax = axes[1, 0]
    ax.plot(captures, 1e3 * triangulation_error, ".", ms=3, label="triangulation (mm)")
    for name, values in errors.items():
        ax.plot(estimate_times[tracked], values[tracked], lw=1.0, label=f"EKF {name}")
    bounces = [event.time for event in diagram.GetSubsystemByName("ball").contact_events_port.Eval(
        diagram.GetSubsystemByName("ball").GetMyContextFromRoot(context))]
    for bounce in bounces:
        ax.axvline(bounce, color="grey", ls=":")
    ax.set_yscale("log")
    ax.set(xlabel="t (s)", title="2. errors against the truth (dotted: a contact, which the EKF sees ~10 ms late)")
    ax.legend(fontsize=7)

    # ------------------------------------------------------------------ 3. dropout and latency
    print("\n3. the EKF's velocity error with the training path's position sensor, 10 built-in shots:")
    rng = np.random.default_rng(4)
    shots = make_state(
        np.c_[rng.uniform(1.2, 1.6, 10), rng.uniform(-0.4, 0.4, 10), rng.uniform(0.1, 0.3, 10)],
        np.c_[rng.uniform(-11.0, -6.0, 10), rng.uniform(-0.8, 0.8, 10), rng.uniform(0.5, 2.0, 10)],
        rng.normal(0.0, 150.0, (10, 3)),
    )
    base = PositionSensorParams()
    variants = {
        "as configured": base,
        "dropout 30%": dataclasses.replace(base, dropout_probability=0.3),
        "dropout 60%": dataclasses.replace(base, dropout_probability=0.6),
        "latency 20-24 ms": dataclasses.replace(base, latency_min=0.020, latency_max=0.024),
        "noise x3": dataclasses.replace(base, noise_std=3 * base.noise_std),
    }
    figures = {}
    for name, position in variants.items():
        simulated = simulate_shots(shots, 0.16, seed=1, position=position)
        result = evaluate(BallEkf(), simulated)["report_times"]
        figures[name] = [result[t]["velocity_error_mean_m_s"] for t in (0.05, 0.15)]
        print(f"   {name:<18} after 50 ms {figures[name][0]:.3f} m/s, after 150 ms {figures[name][1]:.3f} m/s")
    ax = axes[1, 1]
    x = np.arange(len(figures))
    ax.bar(x - 0.2, [v[0] for v in figures.values()], 0.4, label="50 ms after the hit")
    ax.bar(x + 0.2, [v[1] for v in figures.values()], 0.4, label="150 ms after the hit")
    ax.set_xticks(x, list(figures), rotation=20, fontsize=8)
    ax.set(ylabel="mean velocity error (m/s)", title="3. what dropout, latency and noise cost")
    ax.legend(fontsize=8)
    figure.tight_layout()
    png = args.out / "perception.png"
    figure.savefig(png, dpi=90)
    print(f"\nwrote {png}")
    if meshcat is None:
        print("(--no-html: Meshcat file skipped)")
    else:
        print(f"wrote {html}")


if __name__ == "__main__":
    main()
