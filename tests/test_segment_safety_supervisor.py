"""The segment-stepped supervisor in the batched rally diagram: a policy driving into the table is
refused while its neighbour plays on, and the light curtain stops one environment and not the
other."""

import numpy as np
import pytest

from ace_drake.contracts import ObservationLayout
from ace_drake.control.params import RallyParams
from ace_drake.diagrams import build_segment_rally_diagram, make_segment_simulator, start_segment_episodes
from ace_drake.perception.params import PerceptionParams
from ace_drake.robot.collision import TrajectoryCollisionChecker

# The blade centre at (-1.1, 0, 0), in the table top (tests/test_safety_supervisor.py).
IN_THE_TABLE = np.array([0.398, -0.112, -0.043, 0.423, 0.333, -0.002, -0.748, 0.04])
PARAMS = RallyParams(perception=PerceptionParams(positions="statistical"), hit_prediction=False, stepping="segment")
AWAY = np.array([-0.05, 0.2, 0.0, 0.3, 0.0, 0.0, 0.0, 0.0])  # a pose clear of the table
SHOT = np.array([1.3, 0.1, 0.25, -5.0, 0.0, 1.2, 0.0, 0.0, 0.0])
LAYOUT = ObservationLayout(PARAMS.position_history, PARAMS.spin_history)


class Towards:
    """Steers the robot towards ``goal`` through the stack's action (a per-environment policy)."""

    def __init__(self, goal):
        self.goal, self.stack = goal, None

    def __call__(self, observation):
        q, v, a = np.split(LAYOUT.part(observation, "robot_state"), 3)
        return self.stack.action_towards(q, v, a, self.goal)


def run(policies, ticks, curtain=lambda tick: np.zeros(2)):
    diagram = build_segment_rally_diagram(PARAMS, policies, len(policies))
    supervisor = diagram.GetSubsystemByName("safety_supervisor")
    for policy in policies:
        policy.stack = supervisor.stack
    simulator = make_segment_simulator(diagram)
    context = simulator.get_mutable_context()
    start_segment_episodes(diagram, context, np.arange(len(policies)), np.tile(SHOT, (len(policies), 1)), np.arange(len(policies)))
    joints = diagram.GetSubsystemByName("joint_plant")
    curtain_port = diagram.GetInputPort("light_curtain")
    curtain_port.FixValue(context, curtain(0))
    simulator.Initialize()
    history, states = [], []
    for tick in range(1, ticks + 1):
        curtain_port.FixValue(context, curtain(tick))
        simulator.AdvanceTo(tick * 0.032)
        history.append(joints.joint_state_port.Eval(joints.GetMyContextFromRoot(context)).copy())
        states.append(supervisor.supervisor_states(supervisor.GetMyContextFromRoot(context)))
    return np.array(history), states


@pytest.fixture(scope="module")
def checker():
    return TrajectoryCollisionChecker(margin=0.0)


def test_a_policy_driving_into_the_table_is_refused_and_its_neighbour_plays_on(checker):
    joints, states = run([Towards(IN_THE_TABLE), Towards(AWAY)], 45)
    table, other = states[-1]
    assert table.accepted > 0 and table.rejected > 0 and "collision predicted" in table.last_reason
    clearances = [checker.clearance(q) for q in joints[:, 0, :8]]
    assert min(clearances) > 0.0 and min(clearances) < 0.05  # close to the table, never in it
    assert other.accepted > table.accepted  # the other environment's segments go on being accepted
    assert all(checker.clearance(q) > 0.0 for q in joints[:, 1, :8])


def test_the_light_curtain_stops_one_environment_and_holds_it(checker):
    def curtain(tick):
        return np.array([1.0 if 6 <= tick < 14 else 0.0, 0.0])

    joints, states = run([Towards(AWAY), Towards(AWAY)], 24, curtain)
    during = states[12]
    assert during[0].stopped and during[0].last_reason.startswith("protective stop") and not during[1].stopped
    # Held still through the stop once braked (ticks 9-13), while the other keeps moving.
    held = joints[9:13, 0]
    assert np.ptp(held[:, :8], axis=0).max() < 1e-9 and np.abs(held[:, 8:]).max() < 1e-9
    assert not states[-1][0].stopped and states[-1][0].accepted > during[0].accepted
