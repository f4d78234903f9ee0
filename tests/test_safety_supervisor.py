"""The control stack in a diagram: a random policy within the limits, a policy driving into the
table never executed into it, and the light curtain's protective stop."""

import numpy as np
import pytest
from pydrake.systems.analysis import Simulator

from ace_drake.control.trajectory import CommandLimits
from ace_drake.diagrams import build_controlled_robot_diagram, start_controlled_robot
from ace_drake.robot.collision import TrajectoryCollisionChecker
from ace_drake.robot.params import RobotScenario
from ace_drake.robot.trajectory import JointTrajectory

# Found with RobotModel.solve_racket_pose_ik: the blade centre at (-1.1, 0, 0), in the table top.
IN_THE_TABLE = np.array([0.398, -0.112, -0.043, 0.423, 0.333, -0.002, -0.748, 0.04])


def run(policy, duration, curtain_schedule=()):
    """Simulates the controlled robot; curtain_schedule: (time, value) changes of the curtain."""
    diagram = build_controlled_robot_diagram(policy)
    simulator = Simulator(diagram)
    context = simulator.get_mutable_context()
    start_controlled_robot(diagram, context)
    for time, value in curtain_schedule:
        simulator.AdvanceTo(time)
        diagram.GetInputPort("light_curtain").FixValue(context, [value])
    simulator.AdvanceTo(duration)
    supervisor = diagram.GetSubsystemByName("safety_supervisor")
    commands = diagram.GetSubsystemByName("command_logger").FindLog(context)
    joints = diagram.GetSubsystemByName("joint_logger").FindLog(context)
    return supervisor, supervisor.supervisor_state(supervisor.GetMyContextFromRoot(context)), commands, joints


def random_policy(seed):
    rng = np.random.default_rng(seed)
    return lambda observation: rng.choice([-1.0, 1.0], 16) if rng.random() < 0.5 else rng.uniform(-1, 1, 16)


@pytest.fixture(scope="module")
def checker():
    return TrajectoryCollisionChecker(margin=0.0)


def test_a_random_policy_moves_within_the_limits(checker):
    supervisor, state, commands, joints = run(random_policy(0), 1.0)
    assert state.accepted >= 25
    limits = supervisor.stack.limits
    q, v, a = np.split(commands.data().T, 3, axis=1)
    assert limits.violations(JointTrajectory(0.001, q, v, a), tolerance=1e-6) == {"position": 0, "velocity": 0, "acceleration": 0}
    hardware = CommandLimits.hardware(RobotScenario().limits)
    q_joint, v_joint = np.split(joints.data().T, 2, axis=1)
    assert np.all(q_joint >= hardware.lower) and np.all(q_joint <= hardware.upper)
    assert np.all(np.abs(v_joint) <= hardware.velocity)
    assert all(checker.check_config(q) for q in q_joint[::5])


def test_a_policy_driving_into_the_table_is_refused(checker):
    stack_holder = {}

    def into_the_table(observation):
        q, v, a = np.split(observation, 3)
        return stack_holder["stack"].action_towards(q, v, a, IN_THE_TABLE)

    diagram = build_controlled_robot_diagram(into_the_table)
    stack_holder["stack"] = diagram.GetSubsystemByName("safety_supervisor").stack
    simulator = Simulator(diagram)
    context = simulator.get_mutable_context()
    start_controlled_robot(diagram, context)
    simulator.AdvanceTo(1.5)
    supervisor = diagram.GetSubsystemByName("safety_supervisor")
    state = supervisor.supervisor_state(supervisor.GetMyContextFromRoot(context))
    assert state.accepted > 0 and state.rejected > 0
    assert "collision predicted" in state.last_reason
    joints = diagram.GetSubsystemByName("joint_logger").FindLog(context).data().T[:, :8]
    clearances = [checker.clearance(q) for q in joints[::2]]
    assert min(clearances) > 0.0
    # It got close: the refusals are about the table, not about anything far away.
    assert min(clearances) < 0.05


def test_the_light_curtain_stops_the_robot_and_holds_it():
    supervisor, state, commands, _ = run(random_policy(1), 0.6, curtain_schedule=[(0.2005, 1.0)])
    assert state.stopped and state.last_reason.startswith("protective stop")
    q, v, a = np.split(commands.data().T, 3, axis=1)
    times = commands.sample_times()
    # Stopped within the time the hardest-moving joint needs to brake, and held still after.
    after = times > 0.2 + 0.1
    assert np.all(v[after] == 0.0) and np.all(np.ptp(q[after], axis=0) == 0.0)
    accepted_at_stop = state.accepted
    supervisor, resumed, _, _ = run(random_policy(1), 0.6, curtain_schedule=[(0.2005, 1.0), (0.4005, 0.0)])
    assert not resumed.stopped and resumed.accepted > accepted_at_stop
