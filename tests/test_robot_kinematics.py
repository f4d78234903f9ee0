"""RobotKinematics and the robot sub-diagram: outputs against RobotModel and finite differences in time."""

import numpy as np
import pytest
from pydrake.math import RigidTransform
from pydrake.multibody.plant import MultibodyPlant
from pydrake.trajectories import PiecewisePolynomial

from ace_drake.diagrams import build_swing_diagram, make_simulator
from ace_drake.robot.model import RobotModel, add_robot_to_plant, load_scenario
from ace_drake.systems.robot_kinematics import RobotKinematics


@pytest.fixture(scope="module")
def model():
    return RobotModel()


def test_outputs_match_the_robot_model(model):
    plant = MultibodyPlant(0.0)
    add_robot_to_plant(plant, model.scenario)
    plant.Finalize()
    dut = RobotKinematics(plant)
    context = dut.CreateDefaultContext()
    rng = np.random.default_rng(0)
    q = rng.uniform(model.lower, model.upper)
    v = rng.uniform(-model.velocity_limit, model.velocity_limit)
    dut.joint_state_port.FixValue(context, np.concatenate([q, v]))
    X_WR = dut.racket_pose_port.Eval(context)
    V_WR = dut.racket_velocity_port.Eval(context)
    assert X_WR.IsNearlyEqualTo(model.racket_pose(q), 1e-12)
    np.testing.assert_allclose(V_WR.get_coeffs(), model.racket_spatial_velocity(q, v).get_coeffs(), atol=1e-12)
    state = dut.end_effector_state_port.Eval(context)
    np.testing.assert_allclose(state[:3], X_WR.translation(), atol=1e-12)
    np.testing.assert_allclose(state[7:10], V_WR.translational(), atol=1e-12)
    np.testing.assert_allclose(state[10:13], V_WR.rotational(), atol=1e-12)
    from pydrake.common.eigen_geometry import Quaternion

    assert RigidTransform(Quaternion(state[3:7]), state[:3]).IsNearlyEqualTo(X_WR, 1e-12)


def test_an_unfinalized_plant_is_refused():
    with pytest.raises(ValueError, match="finalized"):
        RobotKinematics(MultibodyPlant(0.0))


def test_racket_moves_continuously_between_and_across_command_samples(model):
    # A swing of the shoulder yaw and the gantry: the racket's velocity output must be the time
    # derivative of its pose output at any instant, including off the 1 kHz grid.
    scenario = load_scenario()
    ready = np.asarray(scenario.ready_pose)
    target = ready + np.array([0.2, 0.1, 0.5, 0.0, 0.0, 0.0, 0.3, 0.0])
    command = PiecewisePolynomial.CubicShapePreserving([0.0, 0.01, 0.2], np.column_stack([ready, ready, target]), True)
    diagram = build_swing_diagram(command, scenario)
    context = diagram.CreateDefaultContext()
    joints = diagram.GetSubsystemByName("joint_plant")
    joints.SetJointState(joints.GetMyMutableContextFromRoot(context), ready)
    kinematics = diagram.GetSubsystemByName("robot_kinematics")
    simulator = make_simulator(diagram, context)
    simulator.AdvanceTo(0.0904)
    kinematics_context = kinematics.GetMyContextFromRoot(context)

    def racket_at(t):
        context.SetTime(t)
        pose = kinematics.racket_pose_port.Eval(kinematics_context).translation().copy()
        return pose, kinematics.racket_velocity_port.Eval(kinematics_context).translational().copy()

    h = 1e-6
    for t in (0.0904, 0.09055, 0.09095):
        (p_minus, _), (p_plus, _) = racket_at(t - h), racket_at(t + h)
        _, v = racket_at(t)
        assert np.linalg.norm(v) > 0.5  # it is moving
        np.testing.assert_allclose((p_plus - p_minus) / (2 * h), v, rtol=1e-5, atol=1e-6)
    # Across an update: the pose just before the 91 ms sample equals the pose after it.
    p_before, v_before = racket_at(0.091 - 1e-9)
    context.SetTime(0.0904)
    simulator.AdvanceTo(0.091)
    p_after, v_after = racket_at(0.091)
    np.testing.assert_allclose(p_after, p_before, atol=1e-8)
    np.testing.assert_allclose(v_after, v_before, atol=1e-5)
