"""``bench sim``'s parts: the per-system profile, the ready-pose controller, argument checks."""

import numpy as np
import pytest

from ace_drake.analysis.sim_bench import ReadyPosePolicy, profile_by_system
from ace_drake.cli import main
from ace_drake.contracts import ObservationLayout
from ace_drake.control.params import ControlParams
from ace_drake.control.stack import ControlStack
from ace_drake.diagrams import build_ball_diagram, make_simulator
from ace_drake.physics.flight import make_state
from ace_drake.robot.model import load_scenario


def test_the_profile_charges_the_ball_diagrams_time_to_the_ball():
    diagram = build_ball_diagram()
    simulator = make_simulator(diagram)
    context = simulator.get_mutable_context()
    ball = diagram.GetSubsystemByName("ball")

    def run():
        context.SetTime(0.0)
        ball.SetBallState(ball.GetMyMutableContextFromRoot(context), make_state((1.0, 0.0, 0.3), (-5.0, 0.0, 1.0), (0.0, 0.0, 0.0)))
        simulator.Initialize()
        simulator.AdvanceTo(0.1)

    profile = profile_by_system(run, 0.1)
    assert list(profile["systems"]) == ["ball"]
    assert profile["systems"]["ball"]["share"] + profile["outside_systems_share"] == pytest.approx(1.0)
    assert profile["systems"]["ball"]["calls_per_simulated_second"]["DoCalcTimeDerivatives"] > 1000  # >= 1 per 1 ms step
    assert profile["top_functions"]


def test_the_ready_pose_controller_holds_the_ready_pose():
    stack = ControlStack(load_scenario(), ControlParams())
    layout = ObservationLayout()
    robot_state = np.concatenate([stack.reset_pose, np.zeros(16)])
    observation = np.zeros(layout.size)
    observation[layout.slice("robot_state")] = robot_state
    action = ReadyPosePolicy(stack, layout)(observation)
    proposal = stack.propose(stack.reset_pose, np.zeros(8), np.zeros(8), action)
    assert proposal.safe
    np.testing.assert_allclose(proposal.segment.state(-1)[0], stack.reset_pose, atol=1e-6)


def test_bad_arguments_are_refused():
    assert main(["bench", "sim", "--seconds", "0"]) == 2
    assert main(["bench", "sim", "--repeats", "0"]) == 2


def test_the_ceilings_run_the_ball_and_the_controlled_robot_alone():
    from ace_drake.analysis.sim_bench import _ceilings

    shots = np.array([make_state((1.2, 0.0, 0.3), (-6.0, 0.0, 1.0), (0.0, 0.0, 0.0))] * 2)
    said = []
    ceilings = _ceilings(shots, 0.05, said.append)
    assert said == ["ceilings: the ball alone", "ceilings: the robot alone under the control stack"]
    assert all(np.isfinite(rate) and rate > 0.0 for rate in ceilings.values())


def test_the_ready_pose_controller_on_the_robot_alone_keeps_it_at_the_ready_pose():
    from ace_drake.analysis.sim_bench import ReadyPosePolicy
    from ace_drake.diagrams import build_controlled_robot_diagram, start_controlled_robot

    stack = ControlStack(load_scenario(), ControlParams())
    diagram = build_controlled_robot_diagram(ReadyPosePolicy(stack))  # observation: [q, v, a]
    simulator = make_simulator(diagram)
    context = simulator.get_mutable_context()
    start_controlled_robot(diagram, context)
    simulator.AdvanceTo(0.1)
    supervisor = diagram.GetSubsystemByName("safety_supervisor")
    status = supervisor.supervisor_state(supervisor.GetMyContextFromRoot(context))
    assert status.accepted >= 3 and status.rejected == 0  # segments asked and executed
    joint_plant = diagram.GetSubsystemByName("joint_plant")
    q = joint_plant.q_port.Eval(joint_plant.GetMyContextFromRoot(context))
    np.testing.assert_allclose(q, stack.reset_pose, atol=1e-6)
