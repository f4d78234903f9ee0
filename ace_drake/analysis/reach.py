"""What the robot can reach and how fast it can swing: ``ace-drake bench reach``.

Reach: for each recorded robot contact point, inverse kinematics for a racket that meets the ball
there with the blade facing the opponent, within the joint limits and clear of the court
(``RobotModel.solve_racket_ik``). Speed: the fastest racket-centre velocity along +x that a swing
from rest can have at a hitting configuration, within every joint's position, velocity and
acceleration limits, found by differential evolution over hitting configurations.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable

import numpy as np
from scipy.optimize import differential_evolution

from ace_drake.artefacts import sha256
from ace_drake.config import InputError
from ace_drake.match_data import load_match_events
from ace_drake.robot.model import RobotModel, load_scenario

# Racket-centre heights above the playing surface at which the swing speed is measured, m: the
# recorded robot contact points lie 0.10-0.42 m above the table.
HIT_HEIGHT = (0.10, 0.45)


def robot_contact_points(path: str) -> np.ndarray:
    """Ball positions (N, 3), m, at the robot's recorded hits (``shot_p1`` events) in a match-data CSV."""
    points = [event.state[:3] for event in load_match_events(path) if event.kind == "shot" and event.side == "p1"]
    if not points:
        raise InputError(f"{path}: no robot contact points (shot_p1 events)")
    return np.array(points)


def reach_coverage(model: RobotModel, points: np.ndarray, progress: Callable[[str], None] | None = None) -> dict:
    """Solves the racket IK for every point (N, 3); returns the fraction reached, solve times (s)
    and the points not reached."""
    reached, times, missed = [], [], []
    for index, point in enumerate(points):
        result = model.solve_racket_ik(point)
        reached.append(result.success)
        times.append(result.solve_time)
        if not result.success:
            missed.append([round(float(x), 3) for x in point])
        if progress and (index + 1) % 100 == 0:
            progress(f"reach: {index + 1}/{len(points)} points, {np.mean(reached):.1%} reached")
    times = np.array(times)
    return {
        "points": len(points),
        "reached": int(np.sum(reached)),
        "fraction_reached": float(np.mean(reached)),
        "solve_time_median_s": float(np.median(times)),
        "solve_time_p99_s": float(np.percentile(times, 99)),
        "solve_time_max_s": float(np.max(times)),
        "missed_points": missed,
    }


@dataclasses.dataclass(frozen=True)
class Swing:
    """A swing from rest that passes the hitting configuration q_hit (8,) with joint velocities
    v_hit (8,): each joint accelerates at its limit from q_start, passes q_hit at v_hit and can
    brake to rest within its position limits afterwards. speed is the racket centre's velocity
    along +x at q_hit (m/s); normal_angle the forehand normal's angle from +x (rad)."""

    q_hit: np.ndarray
    v_hit: np.ndarray
    q_start: np.ndarray
    speed: float
    normal_angle: float


def swing_through(model: RobotModel, q_hit: np.ndarray) -> Swing:
    """The fastest +x swing through q_hit: every joint moves in the direction that adds to the
    racket's +x velocity at its fastest speed that leaves room, within its position limits, to
    accelerate to it from rest and to brake from it (v_i = min(v_max, sqrt(2 a_max d_i)))."""
    jacobian_x = model.racket_jacobian(q_hit)[3]
    direction = np.sign(jacobian_x)
    room_behind = np.where(direction >= 0, q_hit - model.lower, model.upper - q_hit)
    room_ahead = np.where(direction >= 0, model.upper - q_hit, q_hit - model.lower)
    room = np.maximum(np.minimum(room_behind, room_ahead), 0.0)
    speed_per_joint = np.minimum(model.velocity_limit, np.sqrt(2.0 * model.acceleration_limit * room))
    v_hit = direction * speed_per_joint
    q_start = q_hit - direction * speed_per_joint**2 / (2.0 * model.acceleration_limit)
    normal = model.racket_pose(q_hit).rotation().matrix()[:, 2]
    return Swing(q_hit, v_hit, q_start, float(jacobian_x @ v_hit), float(np.arccos(np.clip(normal[0], -1.0, 1.0))))


def fastest_swing(model: RobotModel, seed: int = 0, max_normal_angle: float = np.radians(45.0), maxiter: int = 60) -> Swing:
    """The hitting configuration with the fastest +x swing (``swing_through``) whose blade faces
    +x within ``max_normal_angle``, with the racket centre at hitting height (HIT_HEIGHT) and the robot
    collision-free at the hit and at the start of its run-up (SciPy's differential evolution,
    seeded)."""

    def cost(q: np.ndarray) -> float:
        # Infeasible configurations cost more than any feasible one (whose cost is -speed <= 0).
        swing = swing_through(model, q)
        height = model.racket_pose(q).translation()[2]
        violation = max(0.0, swing.normal_angle - max_normal_angle)
        violation += max(0.0, HIT_HEIGHT[0] - height) + max(0.0, height - HIT_HEIGHT[1])
        if violation > 0.0:
            return 1.0 + violation
        if model.colliding_pairs(q) or model.colliding_pairs(swing.q_start):
            return 1.0
        return -swing.speed

    result = differential_evolution(
        cost, list(zip(model.lower, model.upper)), seed=seed, maxiter=maxiter, popsize=12, tol=1e-6, polish=False,
        x0=model.ready_pose,
    )
    return swing_through(model, result.x)


def bench_reach(model: RobotModel, points: np.ndarray, seed: int = 0, progress: Callable[[str], None] | None = None) -> dict:
    """The figures of ``ace-drake bench reach``: coverage of ``points`` and of their mirror in y,
    and the fastest +x swing."""
    mirrored = points * np.array([1.0, -1.0, 1.0])
    start = time.perf_counter()
    coverage = reach_coverage(model, points, progress)
    coverage_mirrored = reach_coverage(model, mirrored, progress)
    if progress:
        progress("speed: searching hitting configurations (differential evolution)")
    swing = fastest_swing(model, seed=seed)
    return {
        "reach": coverage,
        "reach_mirrored_y": coverage_mirrored,
        "max_racket_speed_x_m_s": swing.speed,
        "fastest_swing": {
            "q_hit": swing.q_hit.round(4).tolist(),
            "v_hit": swing.v_hit.round(4).tolist(),
            "q_start": swing.q_start.round(4).tolist(),
            "racket_position_m": model.racket_pose(swing.q_hit).translation().round(4).tolist(),
            "normal_angle_deg": float(np.degrees(swing.normal_angle)),
        },
        "wall_time_s": time.perf_counter() - start,
    }


def bench_reach_on_file(data, scenario=None, seed: int = 0, progress: Callable[[str], None] | None = None) -> dict:
    """``ace-drake bench reach``: ``bench_reach`` of the robot of the scenario YAML ``scenario``
    (None: models/scenario.yaml) on the robot's contact points (shot_p1) of the match-data CSV
    ``data``, with ``data``, its sha256 and ``scenario``."""
    points = robot_contact_points(data)
    model = RobotModel(load_scenario(scenario))
    if progress:
        progress(f"bench reach: {len(points)} robot contact points from {data}, and their mirror in y")
    figures = bench_reach(model, points, seed=seed, progress=progress)
    return {**figures, "data": str(data), "data_sha256": sha256(data), "scenario": str(scenario or "models/scenario.yaml")}

