"""The trajectory collision checker: filters, speed and acceleration bounds, collisions found,
soundness (over thousands of plans, against Drake on a dense grid), cost."""

import time

import numpy as np
import pytest
from pydrake.common import Parallelism
from pydrake.geometry import Box, Capsule, Cylinder, Sphere
from pydrake.planning import RobotDiagramBuilder, SceneGraphCollisionChecker

from ace_drake.analysis.control_bench import ACTION_KINDS, make_stack, random_action
from ace_drake.control.params import ControlParams
from ace_drake.control.stack import random_invariant_state
from ace_drake.robot.collision import (
    BLOCK_SAMPLES,
    DISTANCE_ERROR,
    PROOF_TOLERANCE,
    CollisionReport,
    TrajectoryCollisionChecker,
    _joint_ranges,
    _motion_bounds,
    interpolate,
    joint_acceleration_bounds,
    joint_speed_bounds,
)
from ace_drake.robot.model import add_robot_to_plant, load_scenario
from ace_drake.robot.params import JOINT_NAMES
from ace_drake.robot.trajectory import JointTrajectory

PERIOD = 0.001
MARGIN = ControlParams().collision_margin
INTO_TABLE = np.array([0.8, -0.15, 0.0, 0.6, 0.0, 0.0, -0.6, 0.0])  # arm lowered over the table
RACKET_INTO_TABLE = np.array([0.5, -0.15, 0.0, -0.05, 0.55, 0.0, 1.9, 0.0])  # forearm clear, blade 6.6 cm deep
INTO_COLUMN = np.array([-0.43, 0.8, -1.0, 0.3, 1.73, 2.52, -0.06, -0.58])  # elbow folded back: blade into the column


@pytest.fixture(scope="module")
def dut():
    return TrajectoryCollisionChecker(margin=MARGIN, influence=ControlParams().collision_influence)


@pytest.fixture(scope="module")
def reference():
    """An independent Drake checker with the margin as padding: CheckConfigCollisionFree(q) is
    False iff some non-filtered pair is within the margin (the ground truth)."""
    builder = RobotDiagramBuilder(time_step=0.0)
    robot = add_robot_to_plant(builder.plant(), load_scenario())
    builder.plant().Finalize()
    return SceneGraphCollisionChecker(
        model=builder.Build(), robot_model_instances=[robot], edge_step_size=0.05,
        env_collision_padding=MARGIN, self_collision_padding=MARGIN, implicit_context_parallelism=Parallelism(1),
    )


# ---------------------------------------------------------------------------------- helpers
def polynomial_trajectory(q0, v0, a0, q1, v1, a1, duration, period=PERIOD) -> JointTrajectory:
    """The quintic from (q0, v0, a0) to (q1, v1, a1) over ``duration`` (a whole number of
    periods), sampled exactly (a cubic when both accelerations are left free: pass None)."""
    n = int(round(duration / period))
    T = n * period
    t = np.arange(n + 1)[:, None] * period
    if a0 is None:  # cubic Hermite
        s = t / T
        h00, h10, h01, h11 = 2 * s**3 - 3 * s**2 + 1, s**3 - 2 * s**2 + s, 3 * s**2 - 2 * s**3, s**3 - s**2
        dh00, dh10, dh01, dh11 = (6 * s**2 - 6 * s) / T, 3 * s**2 - 4 * s + 1, (6 * s - 6 * s**2) / T, 3 * s**2 - 2 * s
        ddh00, ddh10, ddh01, ddh11 = (12 * s - 6) / T**2, (6 * s - 4) / T, (6 - 12 * s) / T**2, (6 * s - 2) / T
        q = h00 * q0 + h10 * T * v0 + h01 * q1 + h11 * T * v1
        v = dh00 * q0 + dh10 * v0 + dh01 * q1 + dh11 * v1
        a = ddh00 * q0 + ddh10 * v0 + ddh01 * q1 + ddh11 * v1
        return JointTrajectory(period, q, v, a)
    # Quintic coefficients c0..c5 per joint.
    A = np.array([[T**3, T**4, T**5], [3 * T**2, 4 * T**3, 5 * T**4], [6 * T, 12 * T**2, 20 * T**3]])
    rhs = np.stack([q1 - q0 - v0 * T - 0.5 * a0 * T**2, v1 - v0 - a0 * T, a1 - a0])
    c3, c4, c5 = np.linalg.solve(A, rhs)
    q = q0 + v0 * t + 0.5 * a0 * t**2 + c3 * t**3 + c4 * t**4 + c5 * t**5
    v = v0 + a0 * t + 3 * c3 * t**2 + 4 * c4 * t**3 + 5 * c5 * t**4
    a = a0 + 6 * c3 * t + 12 * c4 * t**2 + 20 * c5 * t**3
    return JointTrajectory(period, q, v, a)


def move(q0, q1, duration) -> JointTrajectory:
    """From rest at q0 to rest at q1."""
    zero = np.zeros(8)
    return polynomial_trajectory(np.asarray(q0, float), zero, zero, np.asarray(q1, float), zero, zero, duration)


def dense_configurations(trajectory: JointTrajectory, spacing: float = 5e-5) -> tuple[np.ndarray, np.ndarray]:
    """Times (m,) and configurations (m, 8) every ``spacing`` s along the Hermite interpolant of
    the trajectory's samples (the samples included)."""
    h = trajectory.period
    per = int(round(h / spacing))
    s = (np.arange(1, per + 1) / per)[None, :, None]  # within each interval, its end included
    q0, v0, q1, v1 = (x[:, None, :] for x in (trajectory.q[:-1], trajectory.v[:-1], trajectory.q[1:], trajectory.v[1:]))
    inner = (2 * s**3 - 3 * s**2 + 1) * q0 + (s**3 - 2 * s**2 + s) * h * v0 + (3 * s**2 - 2 * s**3) * q1 + (s**3 - s**2) * h * v1
    times = (np.arange(trajectory.samples)[:, None] + s[0, :, 0]) * h
    return np.concatenate([[0.0], times.ravel()]), np.concatenate([trajectory.q[:1], inner.reshape(-1, 8)])


def first_collision(reference, trajectory: JointTrajectory, spacing: float = 5e-5) -> float | None:
    """The first dense time at which the reference checker finds a pair within the margin."""
    times, configs = dense_configurations(trajectory, spacing)
    free = np.array(reference.CheckConfigsCollisionFree(list(configs), Parallelism(1)))
    return None if free.all() else float(times[np.argmin(free)])


def surface_points(shape, X_BG, rng, count=40) -> np.ndarray:
    """Points (count, 3) on a collision shape's surface, in the body frame (boxes: corners first)."""
    if isinstance(shape, Box):
        half = 0.5 * np.array([shape.width(), shape.depth(), shape.height()])
        corners = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)]) * half
        points = np.vstack([corners, rng.uniform(-half, half, (count - 8, 3))])
    elif isinstance(shape, Sphere):
        d = rng.normal(size=(count, 3))
        points = shape.radius() * d / np.linalg.norm(d, axis=1, keepdims=True)
    elif isinstance(shape, (Capsule, Cylinder)):
        angle = rng.uniform(0, 2 * np.pi, count)
        z = rng.choice([-0.5, 0.5], count) * shape.length()
        points = np.column_stack([shape.radius() * np.cos(angle), shape.radius() * np.sin(angle), z])
        if isinstance(shape, Capsule):
            d = rng.normal(size=(count, 3))
            d = shape.radius() * d / np.linalg.norm(d, axis=1, keepdims=True)
            points = np.column_stack([d[:, 0], d[:, 1], z + np.abs(d[:, 2]) * np.sign(z)])
    else:
        raise AssertionError(f"unexpected shape {shape}")
    return (X_BG.rotation().matrix() @ points.T).T + X_BG.translation()


# ---------------------------------------------------------------------------------- configurations
def test_ready_pose_is_clear_and_filtered_pairs_are_not_checked(dut):
    ready = np.asarray(dut.scenario.ready_pose)
    assert dut.check_config(ready)
    assert MARGIN < dut.clearance(ready) <= dut.influence
    report = dut.check(JointTrajectory.stationary(ready, PERIOD))
    # Proven by the gates and swept boxes alone: no exact query.
    assert report == CollisionReport(True, None, (), 0, report.min_distance) and report.min_distance > MARGIN
    bodies = {tuple(sorted(part.split("/")[0] for part in name.split(" - "))) for name in dut.pair_rates()}
    # Adjacent links, the SDF's collision filter groups, and bodies welded to the world together.
    filtered = [
        ("base", "carriage_x"), ("carriage_x", "carriage_y"), ("carriage_y", "shoulder"), ("shoulder", "upper_arm"),
        ("forearm", "upper_arm"), ("forearm", "wrist_1_link"), ("racket", "wrist_1_link"), ("base", "carriage_y"),
        ("base", "shoulder"), ("base", "table"), ("base", "floor"),
    ]
    for pair in filtered:
        assert tuple(sorted(pair)) not in bodies, pair
    # The forearm and the racket still check against each other (ace_robot.sdf), as do the
    # racket and the court, and the arm and the gantry's column.
    for pair in [("forearm", "racket"), ("racket", "table"), ("carriage_y", "upper_arm"), ("base", "racket")]:
        assert tuple(sorted(pair)) in bodies, pair
    # The closest pairs at the ready pose: the handle to the forearm (3 cm).
    name, distance = dut.pair_distances(ready)[0]
    assert name == "forearm/ace_robot::link - racket/ace_robot::handle" and distance == pytest.approx(dut.clearance(ready))


def test_bad_input_is_rejected(dut):
    with pytest.raises(ValueError, match="q: expected 8 finite"):
        dut.clearance(np.zeros(7))
    with pytest.raises(ValueError, match="q: expected 8 finite"):
        dut.check_config(np.full(8, np.nan))
    with pytest.raises(ValueError, match="expected a JointTrajectory"):
        dut.check(np.zeros((3, 8)))
    bad = move(dut.scenario.ready_pose, dut.scenario.ready_pose, 0.01)
    with pytest.raises(ValueError, match="v has non-finite values at samples \\[4\\]"):
        dut.check(JointTrajectory(PERIOD, bad.q, np.where(np.arange(11)[:, None] == 4, np.inf, bad.v), bad.a))
    with pytest.raises(ValueError, match="period"):
        dut.check(JointTrajectory(0.0, bad.q, bad.v, bad.a))
    with pytest.raises(ValueError, match="margin"):
        TrajectoryCollisionChecker(margin=-0.001)
    with pytest.raises(ValueError, match="influence"):
        TrajectoryCollisionChecker(margin=0.01, influence=0.01)


# ---------------------------------------------------------------------------------- speed bounds
def test_speed_radii_follow_from_the_model(dut):
    # Chains of fixed distances between joint origins (ace_robot.sdf) plus the blade's reach
    # about the wrist: its centre 0.22 m up the handle, radius 0.075 m, half thickness 0.007 m.
    blade = 0.22 + np.hypot(0.075, 0.007)
    checker = dut
    # The shoulder_pitch pivot lies on the shoulder_yaw axis: the two share a lever.
    expected = [1.0, 1.0, 0.55 + 0.50 + blade, 0.55 + 0.50 + blade, 0.50 + blade, blade, blade, np.hypot(0.075, 0.007)]
    np.testing.assert_allclose(checker.speed_radii, expected, rtol=0, atol=5e-4)
    assert np.all(checker.speed_radii >= np.array(expected) - 1e-9)  # the rim sampling pads up


def test_no_point_of_the_collision_geometry_moves_faster_than_the_bound(dut):
    plant, inspector = dut.plant, dut.inspector
    context = plant.CreateDefaultContext()
    rng = np.random.default_rng(7)
    lower, upper = plant.GetPositionLowerLimits(), plant.GetPositionUpperLimits()
    velocity = plant.GetVelocityUpperLimits()
    geometries = []
    for name in ["upper_arm", "forearm", "wrist_1_link", "racket", "shoulder", "carriage_y", "carriage_x"]:
        body = plant.GetBodyByName(name)
        for g in plant.GetCollisionGeometriesForBody(body):
            geometries.append((body, surface_points(inspector.GetShape(g), inspector.GetPoseInFrame(g), rng)))
    h = 1e-6
    worst = 0.0
    for _ in range(150):
        q = rng.uniform(lower, upper)
        v = rng.uniform(-velocity, velocity) * (rng.random(8) < 0.7)  # some joints still
        bound = np.abs(v) @ dut.speed_radii
        positions = []
        for sign in (1, -1):
            plant.SetPositions(context, q + sign * h * v)
            positions.append(np.hstack([plant.CalcPointsPositions(context, body.body_frame(), points.T, plant.world_frame()) for body, points in geometries]))
        speed = np.linalg.norm(positions[0] - positions[1], axis=0) / (2 * h)
        assert speed.max() <= bound * (1 + 1e-6) + 1e-6
        worst = max(worst, speed.max() / bound)
    assert worst > 0.5  # and the bound is not absurdly loose somewhere


def test_no_pair_distance_changes_faster_than_its_rate_bound(dut):
    # The per-pair coefficients (joints on the path between the bodies; joints about which a
    # shape is symmetric dropped) bound the rate of each pair's signed distance.
    rates = dut.pair_rates()
    plant = dut.plant
    rng = np.random.default_rng(11)
    lower, upper = plant.GetPositionLowerLimits(), plant.GetPositionUpperLimits()
    velocity = plant.GetVelocityUpperLimits()
    ready = np.asarray(dut.scenario.ready_pose)
    # Central differences over a finite step still obey a rate bound (mean value); Drake's
    # GJK distances carry ~1e-5 m of noise, so the step is 1 ms of motion and the tolerance
    # 2 * DISTANCE_ERROR / (2 h).
    h = 1e-3
    checked = set()
    for i in range(300):
        q = rng.uniform(lower, upper) if i % 2 else np.clip(ready + rng.normal(0, 0.4, 8), lower, upper)
        v = rng.uniform(-velocity, velocity)
        plus, minus = dict(dut.pair_distances(q + h * v)), dict(dut.pair_distances(q - h * v))
        for name in plus.keys() & minus.keys():
            if min(plus[name], minus[name]) <= 1e-4:
                continue  # penetrating: signed distance gradients are not what the bound is about
            rate = abs(plus[name] - minus[name]) / (2 * h)
            assert rate <= np.abs(v) @ rates[name] + DISTANCE_ERROR / h, name
            checked.add(name)
    assert "forearm/ace_robot::link - racket/ace_robot::handle" in checked
    assert any("table" in name and "racket" in name for name in checked)
    # wrist_1 turns the racket about the forearm capsule's axis, wrist_3 the handle about its own.
    handle = rates["forearm/ace_robot::link - racket/ace_robot::handle"]
    assert handle[JOINT_NAMES.index("wrist_1")] == 0 and handle[JOINT_NAMES.index("wrist_3")] == 0
    assert handle[JOINT_NAMES.index("wrist_2")] == pytest.approx(0.16, abs=1e-4)


def test_no_lowest_point_falls_faster_than_its_height_rate_bound(dut):
    # The height certificates: a robot geometry's lowest point moves vertically at most at its
    # height rate; the gantry's carriages and the shoulder's yaw (axes fixed in the world,
    # horizontal travel and vertical rotation) cannot move anything vertically.
    heights = dut._heights
    for joint in ("gantry_x", "gantry_y", "shoulder_yaw"):
        assert np.all(heights.rate_matrix[:, JOINT_NAMES.index(joint)] < 1e-9)
    plant = dut.plant
    rng = np.random.default_rng(5)
    lower, upper = plant.GetPositionLowerLimits(), plant.GetPositionUpperLimits()
    velocity = plant.GetVelocityUpperLimits()
    context = dut._full
    h = 1e-4
    worst = 0.0
    for _ in range(200):
        q, v = rng.uniform(lower, upper), rng.uniform(-velocity, velocity)
        lowest = []
        for sign in (1, -1):
            dut.checker.UpdateContextPositions(context, q + sign * h * v)
            query = context.GetQueryObject()
            lowest.append(np.array([heights.lowest(query, geometry) for geometry, _, _ in heights.certificate]))
        rate = np.abs(lowest[0] - lowest[1]) / (2 * h)
        bound = heights.rate_matrix @ np.abs(v)
        assert np.all(rate <= bound * (1 + 1e-6) + 1e-9)
        worst = max(worst, float(np.max(rate / np.maximum(bound, 1e-12))))
    assert worst > 0.3  # and not absurdly loose


def test_joint_speed_bounds_hold_between_samples():
    rng = np.random.default_rng(3)
    for _ in range(200):
        q0, q1 = rng.normal(0, 1, 8), rng.normal(0, 1, 8)
        v0, v1 = rng.normal(0, 20, 8), rng.normal(0, 20, 8)
        trajectory = polynomial_trajectory(q0, v0, None, q0 + 0.01 * q1, v1, None, PERIOD)
        bound = joint_speed_bounds(trajectory.q, trajectory.v, np.zeros((2, 8)), PERIOD)[0]
        t = np.linspace(0, PERIOD, 201)[:, None]
        q = np.array([interpolate(trajectory.q[0], trajectory.v[0], trajectory.q[1], trajectory.v[1], PERIOD, s) for s in t[:, 0]])
        speed = np.abs(np.gradient(q, t[:, 0], axis=0))
        assert np.all(speed.max(axis=0) <= bound * (1 + 1e-3) + 1e-6)
    # Linear acceleration between consistent samples: max |v| + max |a| * period / 4.
    v0, a0, a1 = 1.0, 300.0, -300.0
    v1 = v0 + 0.5 * (a0 + a1) * PERIOD
    bound = joint_speed_bounds(np.zeros((2, 8)), np.full((2, 8), [[v0], [v1]]), np.full((2, 8), [[a0], [a1]]), PERIOD)[0, 0]
    assert bound >= v0 + a0 * PERIOD / 4 - 1e-12  # the peak of v at mid-interval


def test_joint_acceleration_bounds_hold_between_samples():
    rng = np.random.default_rng(4)
    for _ in range(200):
        q0, q1 = rng.normal(0, 1, 8), rng.normal(0, 1, 8)
        v0, v1 = rng.normal(0, 20, 8), rng.normal(0, 20, 8)
        trajectory = polynomial_trajectory(q0, v0, None, q0 + 0.01 * q1, v1, None, PERIOD)
        bound = joint_acceleration_bounds(trajectory.q, trajectory.v, np.zeros((2, 8)), PERIOD)[0]
        t = np.linspace(0, PERIOD, 201)
        q = np.array([interpolate(trajectory.q[0], trajectory.v[0], trajectory.q[1], trajectory.v[1], PERIOD, s) for s in t])
        acceleration = np.abs(np.gradient(np.gradient(q, t, axis=0), t, axis=0))[2:-2]
        assert np.all(acceleration.max(axis=0) <= bound * (1 + 1e-3) + 1e-6)
        assert np.all(acceleration.max(axis=0) >= bound * 0.95)  # the largest is at an end: tight
    # Sampled accelerations count too (motion with linear acceleration between them).
    a = np.full((2, 8), [[300.0], [-500.0]])
    assert np.all(joint_acceleration_bounds(np.zeros((2, 8)), np.zeros((2, 8)), a, PERIOD) == 500.0)


# ---------------------------------------------------------------------------------- collisions found
def test_the_racket_pushed_into_the_table_is_found_with_its_time(dut, reference):
    assert not dut.check_config(RACKET_INTO_TABLE)
    assert [name for name, d in dut.pair_distances(RACKET_INTO_TABLE) if d < MARGIN] == ["racket/ace_robot::blade - table/court::top"]
    trajectory = move(dut.scenario.ready_pose, RACKET_INTO_TABLE, 0.4)
    report = dut.check(trajectory)
    assert not report.free
    assert any("table/court::top" in name for name in report.pairs), report.pairs
    # The report's configuration is (within the proof tolerance) margin-close, and no earlier
    # dense configuration is within the margin.
    first = first_collision(reference, trajectory)
    assert first is not None and report.time <= first + 1e-12
    k = int(report.time // PERIOD)
    q_report = interpolate(trajectory.q[k], trajectory.v[k], trajectory.q[min(k + 1, trajectory.samples)], trajectory.v[min(k + 1, trajectory.samples)], PERIOD, report.time - k * PERIOD)
    assert dut.clearance(q_report) < MARGIN + PROOF_TOLERANCE + DISTANCE_ERROR + 1e-9
    assert report.min_distance < MARGIN + PROOF_TOLERANCE + DISTANCE_ERROR


def test_self_collisions_are_found(dut, reference):
    assert not dut.check_config(INTO_COLUMN)
    assert dut.pair_distances(INTO_COLUMN)[0][0] == "carriage_y/ace_robot::column - racket/ace_robot::blade"
    start = INTO_COLUMN.copy()
    start[3] -= 0.5  # raise the arm: the blade clears the column
    assert dut.check_config(start)
    report = dut.check(move(start, INTO_COLUMN, 0.2))
    assert not report.free and report.pairs[0] == "carriage_y/ace_robot::column - racket/ace_robot::blade"
    assert report.time <= first_collision(reference, move(start, INTO_COLUMN, 0.2)) + 1e-12
    # Folding the wrist back puts the handle into the forearm; the checker leaves that pair out
    # only for trajectories that provably keep wrist_2 where it cannot happen.
    folded = np.asarray(dut.scenario.ready_pose).copy()
    folded[6] = -1.57
    report = dut.check(move(dut.scenario.ready_pose, folded, 0.3))
    assert not report.free and "forearm/ace_robot::link - racket/ace_robot::handle" in report.pairs
    assert "forearm/ace_robot::link - racket/ace_robot::handle" not in dut.certified


def test_a_collision_between_samples_is_not_missed(dut, reference):
    # Two samples 20 ms apart, both clear, whose Hermite interpolant dips the blade into the
    # table: shoulder_pitch leaves at +V and comes back at -V, peaking V * T / 4 higher midway.
    low, dip = INTO_TABLE.copy(), INTO_TABLE.copy()
    low[3], dip[3] = 0.2, 0.35
    assert dut.check_config(low) and not dut.check_config(dip)
    T = 0.02
    speed = (dip[3] - low[3]) / (T / 4)
    v = np.zeros((2, 8))
    v[:, 3] = [speed, -speed]
    trajectory = JointTrajectory(T, np.array([low, low]), v, np.zeros((2, 8)))
    first = first_collision(reference, trajectory, spacing=1e-4)
    assert first is not None and 0 < first < T
    report = dut.check(trajectory)
    assert not report.free and 0 < report.time <= first
    assert any("table/court::top" in name for name in report.pairs)


def test_gating_leaves_out_only_pairs_that_provably_stay_clear(dut):
    # Pairs that depend on at most two joints and stay clear over the joint limits are certified.
    assert "carriage_x/ace_robot::beam - floor/court::ground" in dut.certified
    assert "shoulder/ace_robot::housing - table/court::top" in dut.certified
    assert not any("racket" in name and ("table" in name or "forearm" in name) for name in dut.certified)
    # Single configurations: gated pairs are left out only where their map proves them clear.
    folded = np.asarray(dut.scenario.ready_pose).copy()
    folded[6] = -1.57
    report = dut.check(JointTrajectory.stationary(folded, PERIOD))
    assert not report.free and report.pairs[0] == "forearm/ace_robot::link - racket/ace_robot::handle"
    # Outside the joint limits (and the gating box) every pair is queried.
    outside = np.asarray(dut.scenario.ready_pose).copy()
    outside[0] = dut.box_upper[0] + 0.5  # the gantry 0.55 m past its limit, the racket over the table
    assert dut.check(JointTrajectory.stationary(outside, PERIOD)).free == dut.check_config(outside)
    assert dut.check(move(folded, outside, 0.2)).free is False


# ---------------------------------------------------------------------------------- soundness
def random_trajectories(dut, count, rng):
    """Fast cubic Hermite motions (20-60 ms at 1 kHz) between random configurations over and
    around the table's end, near the court and the robot itself."""
    plant = dut.plant
    lower, upper = plant.GetPositionLowerLimits() + 0.02, plant.GetPositionUpperLimits() - 0.02
    velocity = 0.6 * plant.GetVelocityUpperLimits()
    anchors = [INTO_TABLE + [0, 0, 0, -0.25, 0, 0, 0, 0], np.asarray(dut.scenario.ready_pose), INTO_COLUMN + [0, 0, 0.4, 0, 0, 0, 0, 0],
               np.array([0.5, 0.3, 0.3, 0.35, 0.4, 1.0, -0.9, 0.5]), np.array([0.2, -0.6, -0.4, 0.9, -0.6, -1.5, 0.8, 1.0])]
    for _ in range(count):
        q0 = np.clip(anchors[rng.integers(len(anchors))] + rng.normal(0, 0.15, 8), lower, upper)
        q1 = np.clip(q0 + rng.normal(0, 0.15, 8), lower, upper)
        v0, v1 = rng.uniform(-velocity, velocity), rng.uniform(-velocity, velocity)
        duration = PERIOD * rng.integers(20, 61)
        yield polynomial_trajectory(q0, v0, None, q1, v1, None, duration)


def grazing(dut, trajectory, target):
    """The trajectory shifted in shoulder_pitch (lowering the arm) until its dense clearance is
    about ``target`` m, or None."""
    def clearance(shift):
        shifted = JointTrajectory(trajectory.period, trajectory.q + shift * np.eye(8)[3], trajectory.v, trajectory.a)
        return min(dut.clearance(q) for q in dense_configurations(shifted, 5e-4)[1]), shifted

    low, high = -0.5, 0.5
    if not (clearance(low)[0] > target > clearance(high)[0]):
        return None
    for _ in range(12):
        middle = 0.5 * (low + high)
        if clearance(middle)[0] > target:
            low = middle
        else:
            high = middle
    return clearance(0.5 * (low + high))[1]


def test_free_means_free_and_dense_collisions_are_never_free(dut, reference):
    rng = np.random.default_rng(2024)
    outcomes = {"free": 0, "collision": 0, "unproven": 0}
    trajectories = list(random_trajectories(dut, 260, rng))
    # Grazing ones: the arm skims the court or itself within a fraction of a mm of the margin.
    for trajectory in trajectories[:60]:
        shifted = grazing(dut, trajectory, MARGIN + rng.uniform(-5e-4, 1.5e-3))
        if shifted is not None:
            trajectories.append(shifted)
    assert len(trajectories) >= 260 + 20
    for trajectory in trajectories:
        report = dut.check(trajectory)
        first = first_collision(reference, trajectory)
        if report.free:
            assert first is None, f"check says free, but dense finds a config within the margin at {first} s"
            outcomes["free"] += 1
        else:
            assert report.time is not None and report.pairs and report.queries >= 1
            if first is not None:
                assert report.time <= first + 1e-12
                outcomes["collision"] += 1
            else:
                outcomes["unproven"] += 1  # within PROOF_TOLERANCE, or touching between dense samples
    print(f"\nsoundness: {outcomes}")
    assert outcomes["free"] >= 40 and outcomes["collision"] >= 40
    assert outcomes["unproven"] <= 0.1 * len(trajectories)


def stack_plans(count, rng):
    """What the supervisor checks: segment + reset plans of the control stack (its own collision
    check off) from random invariant starts (control.stack.random_invariant_state) under random actions of
    every kind (all +-1, alternating, uniform, corners)."""
    stack = make_stack(check_collisions=False)
    plans = []
    while len(plans) < count:
        q, v, a = random_invariant_state(stack, rng)
        proposal = stack.propose(q, v, a, random_action(rng, ACTION_KINDS[rng.integers(len(ACTION_KINDS))], int(rng.integers(2))))
        if proposal.plan is not None:
            plans.append(proposal.plan)
    return plans


@pytest.mark.slow
def test_plans_dense_sampling_finds_colliding_are_never_reported_free(dut, reference):
    # Thousands of motions, short and fast near the court and the robot itself, and whole
    # segment + reset plans: whatever the check reports free, Drake finds no configuration within
    # the margin along it (every 0.1 ms, or 0.25 ms on the long plans); and (on every fourth of
    # the others) a reported collision time is never after the first one found.
    rng = np.random.default_rng(77)
    plans = list(random_trajectories(dut, 1500, rng)) + stack_plans(500, rng)
    outcomes = {"free": 0, "collision": 0, "unproven": 0, "not sampled": 0}
    for i, plan in enumerate(plans):
        report = dut.check(plan)
        if not report.free and i % 4:
            outcomes["not sampled"] += 1
            continue
        first = first_collision(reference, plan, spacing=1e-4 if plan.samples <= 60 else 2.5e-4)
        if report.free:
            assert first is None, f"check says free, but Drake finds a configuration within the margin at {first} s"
            outcomes["free"] += 1
        elif first is not None:
            assert report.time <= first + 1e-12
            outcomes["collision"] += 1
        else:
            outcomes["unproven"] += 1
    print(f"\nsoundness over {len(plans)} plans: {outcomes}")
    assert outcomes["free"] >= 500 and outcomes["collision"] >= 200
    assert outcomes["unproven"] <= 0.05 * (outcomes["collision"] + outcomes["unproven"])


# ---------------------------------------------------------------------------------- cost
def typical_segments_with_resets(dut, count, rng):
    """A 32 ms fast segment (a swing around the hitting region behind the table: arm joints up
    to half their speed limits, wrist joints up to a third, accelerations up to a third of the
    limits) followed by a 0.5 s reset to the ready pose: a 40 ms brake to rest (quintic), then
    a quintic rest to rest."""
    ready = np.asarray(dut.scenario.ready_pose)
    velocity, acceleration = dut.plant.GetVelocityUpperLimits(), dut.plant.GetAccelerationUpperLimits()
    speed = np.array([0.5, 0.5, 0.5, 0.5, 0.5, 0.33, 0.33, 0.33]) * velocity
    zero = np.zeros(8)
    for _ in range(count):
        q0 = ready + rng.normal(0, [0.15, 0.3, 0.2, 0.1, 0.2, 0.3, 0.1, 0.3])
        v0 = rng.uniform(-speed, speed)
        a0 = rng.uniform(-0.33, 0.33, 8) * acceleration
        segment = polynomial_trajectory(q0, v0, a0, q0 + 0.032 * v0 + 0.5 * 0.032**2 * a0, v0 + 0.032 * a0, a0, 0.032)
        q, v, a = segment.state(-1)
        brake = polynomial_trajectory(q, v, a, q + 0.02 * v, zero, zero, 0.04)
        reset = brake.then(polynomial_trajectory(brake.q[-1], zero, zero, ready, zero, zero, 0.46))
        yield segment.then(reset)


def test_cost_of_a_segment_and_its_reset(dut, reference):
    rng = np.random.default_rng(5)
    trajectories = list(typical_segments_with_resets(dut, 200, rng))
    for trajectory in trajectories[:20]:
        dut.check(trajectory)  # warm up (a query context per gating combination)
    times, reports = [], []
    for trajectory in trajectories:
        start = time.perf_counter()
        reports.append(dut.check(trajectory))
        times.append(time.perf_counter() - start)
    times, queries, free = 1e3 * np.array(times), np.array([r.queries for r in reports]), np.array([r.free for r in reports])
    print(
        f"\nsegment + reset ({trajectories[0].duration:.3f} s, {np.mean(free):.0%} free): "
        f"queries median {np.median(queries):.0f} p99 {np.percentile(queries, 99):.0f}; "
        f"time median {np.median(times):.3f} ms p99 {np.percentile(times, 99):.3f} ms"
    )
    assert np.mean(free) > 0.8
    # Long trajectories are sound too: the free ones that came closest, densely.
    closest = sorted((r.min_distance, i) for i, r in enumerate(reports) if r.free)[:6]
    for _, i in closest:
        assert first_collision(reference, trajectories[i]) is None
    for i in [i for i, r in enumerate(reports) if not r.free][:4]:
        first = first_collision(reference, trajectories[i])
        assert first is None or reports[i].time <= first


def test_a_query_budget_bounds_the_work(dut):
    # A free motion that passes close enough to the court or the robot for some exact queries.
    motions = random_trajectories(dut, 200, np.random.default_rng(1))
    trajectory, full = next((motion, report) for motion in motions if (report := dut.check(motion)).free and report.queries > 2)
    report = dut.check(trajectory, max_queries=2)
    assert not report.free and report.pairs == () and report.queries == 2
    assert 0 < report.time < trajectory.duration
    assert dut.check(trajectory, max_queries=full.queries) == full
    with pytest.raises(ValueError, match="max_queries"):
        dut.check(trajectory, max_queries=0)


# ---------------------------------------------------------------------------------- fast paths
def reference_broad_phase(dut, q, sag, bend):
    """``TrajectoryCollisionChecker._broad_phase`` as it was before its fast paths (the joints'
    ranges by NumPy, every interval's box up front, the pairs and rows assembled in lists)."""
    n = sag.shape[1]
    lower, upper = np.minimum(q[:, :-1], q[:, 1:]) - sag, np.maximum(q[:, :-1], q[:, 1:]) + sag
    low, high = lower.min(axis=1).tolist(), upper.max(axis=1).tolist()
    inside = [lo >= box_lo and hi <= box_hi for lo, hi, box_lo, box_hi in zip(low, high, dut.box_lower.tolist(), dut.box_upper.tolist())]
    gates = [gate for gate in dut._gates if all(inside[j] for j in gate.joints.tolist())]
    gated = {gate.pair for gate in gates}
    pairs, rows = [], []
    for gate in gates:
        if gate.bad and gate.box_touches(low, high):
            row = gate.touched(lower, upper)
            if row.any():
                pairs.append(gate.pair)
                rows.append(row)
    bounded = np.array([p for p in np.flatnonzero(dut._bounds.bounded).tolist() if p not in gated], dtype=int)
    swept_open, smallest, X_WB = dut._bounds.open_intervals(q, bend, BLOCK_SAMPLES, bounded, dut.margin)
    failing = np.flatnonzero(swept_open.any(axis=1))
    pairs += bounded[failing].tolist()
    rows += list(swept_open[failing])
    for p in np.flatnonzero(~dut._bounds.bounded).tolist():
        if p not in gated:
            pairs.append(p)
            rows.append(np.ones(n, dtype=bool))
    return np.array(pairs, dtype=int), np.array(rows, dtype=bool).reshape(len(pairs), n), min(dut.influence, smallest), X_WB


def test_broad_phase_equals_its_reference_bit_for_bit(dut):
    rng = np.random.default_rng(11)
    plans = list(random_trajectories(dut, 150, rng)) + list(typical_segments_with_resets(dut, 40, rng))
    # Some leave the gates' box (the gates of the joints that do are skipped), some stand still.
    plans += [JointTrajectory(p.period, p.q + [0, 0, 0, 0, 0, 0, 1.5, 0], p.v, p.a) for p in plans[:20]]
    plans += [JointTrajectory.stationary(p.q[0], PERIOD) for p in plans[:5]]
    kinds = set()
    for plan in plans:
        q, v, a = (np.asarray(x, dtype=float) for x in (plan.q, plan.v, plan.a))
        if q.shape[0] == 1:
            q, v, a = q[[0, 0]], np.zeros((2, 8)), np.zeros((2, 8))
        _, sag, bend = _motion_bounds(q, v, a, plan.period, dut._upstream)
        q_columns = np.ascontiguousarray(q.T)
        fast, slow = dut._broad_phase(q_columns, sag, bend), reference_broad_phase(dut, q_columns, sag, bend)
        for x, y in zip(fast, slow):
            assert np.array_equal(x, y) and np.asarray(x).dtype == np.asarray(y).dtype and np.shape(x) == np.shape(y)
        kinds.add((len(fast[0]) > 0, any(p in {g.pair for g in dut._bad_gates} for p in fast[0].tolist())))
    assert kinds == {(False, False), (True, False), (True, True)}  # all clear, open pairs, a gate's rows


def test_joint_ranges_equal_numpy_reductions():
    rng = np.random.default_rng(3)
    for n in (1, 2, 17, 300):
        for special in (None, np.nan, np.inf, 0.0):
            q = rng.normal(0, 1, (8, n + 1))
            q[:, ::3] = np.round(q[:, ::3], 1)  # ties between consecutive samples
            q[2, :2] = [-0.0, 0.0]
            sag = rng.uniform(0, 1e-4, (8, n))
            if special is not None:
                sag[rng.integers(8), rng.integers(n)] = special
                sag[5] = special
            low, high = _joint_ranges(q, sag)
            expected_low = (np.minimum(q[:, :-1], q[:, 1:]) - sag).min(axis=1)
            expected_high = (np.maximum(q[:, :-1], q[:, 1:]) + sag).max(axis=1)
            assert np.array_equal(low, expected_low, equal_nan=True) and np.array_equal(high, expected_high, equal_nan=True)


def test_a_second_checker_of_the_model_reuses_the_gates_and_decides_the_same(dut):
    again = TrajectoryCollisionChecker(margin=MARGIN, influence=ControlParams().collision_influence)
    assert [gate.pair for gate in again._gates] == [gate.pair for gate in dut._gates] and again.certified == dut.certified
    # The shared maps are the ones a fresh construction would build.
    fresh = [gate for p in range(len(dut._pairs)) if (gate := dut._gate(p)) is not None]
    assert len(fresh) == len(dut._gates)
    for built, shared in zip(fresh, again._gates):
        assert built.pair == shared.pair and built.bad == shared.bad
        for field in ("joints", "origin", "width", "counts"):
            assert np.array_equal(getattr(built, field), getattr(shared, field))
        assert not shared.counts.flags.writeable
    for plan in random_trajectories(dut, 30, np.random.default_rng(4)):
        assert again.check(plan) == dut.check(plan)
    assert all(a is b for a, b in zip(again._gates, dut._gates))  # shared, not rebuilt
    other = TrajectoryCollisionChecker(margin=2 * MARGIN, influence=ControlParams().collision_influence)  # another margin: its own maps
    assert not any(a is b for a, b in zip(other._gates, dut._gates))
