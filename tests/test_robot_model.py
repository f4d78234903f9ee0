"""The robot model: loading, limits from config, court geometry, kinematics, collisions, IK."""

import dataclasses

import numpy as np
import pytest
from pydrake.geometry import Box, Role

from ace_drake.config import ConfigError, from_dict
from ace_drake.physics.params import BallPhysicsParams
from ace_drake.robot.model import DEFAULT_SCENARIO, RobotModel, load_scenario, racket_reach_box
from ace_drake.robot.params import JOINT_NAMES, JointLimits, RobotScenario


@pytest.fixture(scope="module")
def dut():
    return RobotModel()


def test_model_loads_and_finalizes_with_positions_in_joint_order(dut):
    assert dut.plant.is_finalized()
    assert dut.plant.num_positions() == dut.plant.num_velocities() == 8
    for index, name in enumerate(JOINT_NAMES):
        assert dut.plant.GetJointByName(name).position_start() == index
    kinds = [dut.plant.GetJointByName(name).type_name() for name in JOINT_NAMES]
    assert kinds == ["prismatic"] * 2 + ["revolute"] * 6  # paper Fig. 2c


def test_the_shipped_scenario_file_is_the_config_default():
    assert load_scenario(DEFAULT_SCENARIO) == RobotScenario()


def test_limits_come_from_the_config(dut):
    limits = dut.scenario.limits.as_arrays()
    plant = dut.plant
    np.testing.assert_array_equal(plant.GetPositionLowerLimits(), limits["lower"])
    np.testing.assert_array_equal(plant.GetPositionUpperLimits(), limits["upper"])
    np.testing.assert_array_equal(plant.GetVelocityUpperLimits(), limits["velocity"])
    np.testing.assert_array_equal(plant.GetAccelerationLowerLimits(), -limits["acceleration"])
    # A different config gives a different plant.
    scenario = dataclasses.replace(RobotScenario(), limits=dataclasses.replace(RobotScenario().limits, elbow=JointLimits(-1.0, 1.5, 3.0, 30.0)))
    elbow = RobotModel(scenario).plant.GetJointByName("elbow")
    assert (elbow.position_lower_limits()[0], elbow.position_upper_limits()[0]) == (-1.0, 1.5)
    assert (elbow.velocity_upper_limits()[0], elbow.acceleration_upper_limits()[0]) == (3.0, 30.0)


def test_bad_scenarios_are_rejected_naming_the_field(tmp_path):
    with pytest.raises(ConfigError, match="ready_pose outside the joint limits: gantry_x"):
        RobotScenario(ready_pose=(5.0, 0, 0, 0, 0, 0, 0, 0))
    with pytest.raises(ConfigError, match="lower must be < upper"):
        from_dict(RobotScenario, {"limits": {"elbow": {"lower": 1.0, "upper": -1.0, "velocity": 1.0, "acceleration": 1.0}}})
    with pytest.raises(ConfigError, match="unknown field"):
        from_dict(RobotScenario, {"limits": {"elbw": {"lower": -1.0, "upper": 1.0, "velocity": 1.0, "acceleration": 1.0}}})
    with pytest.raises(ConfigError, match="model file not found"):
        RobotModel(RobotScenario(robot_model="missing.sdf"))


def test_court_geometry_matches_the_ball_model(dut):
    params = BallPhysicsParams()
    inspector = dut.scene_graph.model_inspector()
    body = dut.plant.GetBodyByName("table")
    (top,) = [g for g in dut.plant.GetCollisionGeometriesForBody(body) if inspector.GetName(g).endswith("top")]
    shape = inspector.GetShape(top)
    assert isinstance(shape, Box)
    assert (shape.width(), shape.depth()) == (params.table.length, params.table.width)
    X_WG = inspector.GetPoseInFrame(top)
    assert X_WG.translation()[2] + 0.5 * shape.height() == pytest.approx(0.0)  # the playing surface is z = 0
    net = dut.plant.GetBodyByName("net")
    (mesh,) = [g for g in inspector.GetGeometries(dut.plant.GetBodyFrameIdOrThrow(net.index()), Role.kIllustration) if inspector.GetName(g).endswith("mesh")]
    assert inspector.GetShape(mesh).height() == pytest.approx(params.net.height)
    assert inspector.GetShape(mesh).depth() == pytest.approx(params.table.width + 2 * params.net.overhang)


def test_racket_frame_at_zero_is_worked_out_by_hand(dut):
    # Base at (-2.45, 0, -0.76); wrist at (1.13, 0.15, 1.11) in the base; blade 0.22 m up the handle.
    X_WR = dut.racket_pose(np.zeros(8))
    np.testing.assert_allclose(X_WR.translation(), [-2.45 + 1.13, 0.15, -0.76 + 1.11 + 0.22], atol=1e-12)
    R = X_WR.rotation().matrix()
    np.testing.assert_allclose(R[:, 2], [1, 0, 0], atol=1e-12)  # forehand normal faces the opponent
    np.testing.assert_allclose(R[:, 0], [0, 0, 1], atol=1e-12)  # handle to tip points up
    # The gantry moves the racket one for one.
    q = np.zeros(8)
    q[:2] = [0.3, -0.4]
    np.testing.assert_allclose(dut.racket_pose(q).translation() - X_WR.translation(), [0.3, -0.4, 0.0], atol=1e-12)


def test_racket_velocity_matches_finite_differences(dut):
    rng = np.random.default_rng(3)
    for _ in range(5):
        q = rng.uniform(dut.lower, dut.upper)
        v = rng.uniform(-dut.velocity_limit, dut.velocity_limit)
        h = 1e-6
        X_plus, X_minus = dut.racket_pose(q + h * v), dut.racket_pose(q - h * v)
        V = dut.racket_spatial_velocity(q, v)
        np.testing.assert_allclose(V.translational(), (X_plus.translation() - X_minus.translation()) / (2 * h), atol=1e-5)
        R_delta = X_plus.rotation().matrix() @ X_minus.rotation().matrix().T
        w_numeric = np.array([R_delta[2, 1] - R_delta[1, 2], R_delta[0, 2] - R_delta[2, 0], R_delta[1, 0] - R_delta[0, 1]]) / (4 * h)
        np.testing.assert_allclose(V.rotational(), w_numeric, atol=1e-4)
        np.testing.assert_allclose(dut.racket_jacobian(q) @ v, V.get_coeffs(), atol=1e-9)


def test_ready_pose_is_clear_and_the_arm_in_the_table_is_not(dut):
    assert dut.colliding_pairs(dut.ready_pose, margin=0.01) == []
    into_table = np.array([0.8, -0.15, 0.0, 0.6, 0.0, 0.0, -0.6, 0.0])  # arm lowered over the table
    names = " ".join(a + " " + b for a, b, _ in dut.colliding_pairs(into_table))
    assert "table/court::top" in names and "racket/ace_robot::blade" in names


def test_ik_meets_a_ball_with_the_blade_facing_the_opponent(dut):
    p_WB = np.array([-1.6, 0.4, 0.2])
    result = dut.solve_racket_ik(p_WB)
    assert result.success
    assert np.all(result.q >= dut.lower - 1e-9) and np.all(result.q <= dut.upper + 1e-9)
    X_WR = dut.racket_pose(result.q)
    p_RB = X_WR.inverse().multiply(p_WB)
    assert p_RB[2] == pytest.approx(0.027, abs=1.1e-3)  # ball radius + half the blade
    assert np.hypot(p_RB[0], p_RB[1]) <= 0.04 * np.sqrt(2) + 1e-6
    assert np.degrees(np.arccos(X_WR.rotation().matrix()[0, 2])) <= 45.0 + 1e-6
    assert dut.colliding_pairs(result.q, margin=0.009) == []


def test_ik_fails_out_of_reach_and_rejects_bad_input(dut):
    assert not dut.solve_racket_ik(np.array([1.0, 0.0, 0.2])).success  # the opponent's half
    with pytest.raises(ValueError, match="p_WB"):
        dut.solve_racket_ik(np.array([np.nan, 0.0, 0.2]))
    with pytest.raises(ValueError, match="q_seed"):
        dut.solve_racket_ik(np.array([-1.6, 0.0, 0.2]), q_seed=np.zeros(3))


def test_racket_pose_ik_puts_the_blade_where_asked(dut):
    normal = np.array([np.cos(0.3), 0.0, np.sin(0.3)])
    result = dut.solve_racket_pose_ik(np.array([-1.7, -0.2, 0.3]), normal)
    assert result.success
    X_WR = dut.racket_pose(result.q)
    np.testing.assert_allclose(X_WR.translation(), [-1.7, -0.2, 0.3], atol=1.01e-3)
    assert np.degrees(np.arccos(X_WR.rotation().matrix()[:, 2] @ normal)) <= 0.51


def test_racket_reach_box_holds_every_configuration_and_stops_short_of_the_net(dut):
    lower, upper = racket_reach_box(dut.scenario)
    rng = np.random.default_rng(3)
    for _ in range(2000):  # random configurations, half of the joints at one of their limits
        q = rng.uniform(dut.lower, dut.upper)
        at_limit = rng.random(8) < 0.5
        q[at_limit] = np.where(rng.random(8) < 0.5, dut.lower, dut.upper)[at_limit]
        p_WR = dut.racket_pose(q).translation()
        assert np.all(lower <= p_WR) and np.all(p_WR <= upper)
    assert upper[0] < 0.0  # never over the opponent's half: the ball's racket witness skips it there
