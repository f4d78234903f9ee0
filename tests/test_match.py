"""Matches on the segment-stepped rally diagram: a serve's planned start, a rally's continuing robot,
the diagram's umpire, and whole (short) matches against the recorded players' opponent model."""

from pathlib import Path

import numpy as np
import pytest

from ace_drake.contracts import ObservationLayout
from ace_drake.control.params import ControlParams, RallyParams
from ace_drake.control.serve import TossState, strike_from_genes
from ace_drake.control.serve_execution import execute_commands, plan_strike, plan_toss, serve_episode_start
from ace_drake.control.stack import make_control_stack
from ace_drake.diagrams import build_segment_rally_diagram, make_segment_simulator, start_segment_episodes
from ace_drake.evaluation.match import MatchRunner, episode_seed
from ace_drake.perception.params import PerceptionParams
from ace_drake.physics.params import BallPhysicsParams
from ace_drake.play.opponent_model import OpponentModel
from ace_drake.play.scoring import HUMAN, ROBOT, Match, MatchRules
from ace_drake.play.umpire import RallyEvent, judge_rally
from ace_drake.robot.model import RobotModel
from tests.test_serve_execution import SHORT_BACKSPIN  # a legal serve at the ball level that the robot makes

DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "ace_match_events_elite.csv"
needs_data = pytest.mark.skipif(not DATA.is_file(), reason=f"shared match data not found at {DATA}")

PARAMS = RallyParams(perception=PerceptionParams(positions="statistical"), hit_prediction=False, stepping="segment")
LAYOUT = ObservationLayout(PARAMS.position_history, PARAMS.spin_history)
SHOT = np.array([1.3, 0.1, 0.25, -5.0, 0.0, 1.2, 0.0, 0.0, 0.0])  # an incoming ball from the human
AWAY = np.array([-0.05, 0.2, 0.0, 0.3, 0.0, 0.0, 0.0, 0.0])  # a pose clear of the table
T = 0.032
IDLE_CALL = 10  # the policy's call at tick 10 (it decides from tick 1 on)


@pytest.fixture(scope="module")
def serve():
    """The short backspin serve planned on the robot: (its StrikePlan, its TossPlan)."""
    model = RobotModel()
    stack = make_control_stack(model.scenario, ControlParams())
    toss = plan_toss(model, stack)
    return plan_strike(model, stack, toss, strike_from_genes(SHORT_BACKSPIN, TossState(), BallPhysicsParams())), toss


class Towards:
    """Steers the robot towards ``goal`` through the stack's action; counts its calls, and has no
    action at call number ``idle`` (from 1)."""

    def __init__(self, goal, stack, idle=None):
        self.goal, self.stack, self.calls, self.idle = goal, stack, 0, idle

    def __call__(self, observation):
        self.calls += 1
        if self.calls == self.idle:
            return None
        q, v, a = np.split(LAYOUT.part(observation, "robot_state"), 3)
        return self.stack.action_towards(q, v, a, self.goal)


def segment_diagram(policy, batch=1):
    diagram = build_segment_rally_diagram(PARAMS, policy, batch)
    simulator = make_segment_simulator(diagram)
    context = simulator.get_mutable_context()
    diagram.GetInputPort("light_curtain").FixValue(context, np.zeros(batch))
    return diagram, simulator, context


def test_a_serve_starts_part_way_along_its_plan_and_the_supervisor_holds_it(serve):
    """The joints at every tick are the offline execution's (``execute_commands``) at the same
    command sample, bit for bit, while a policy that wants to go elsewhere is ignored; after the
    plan's hold its segments are taken."""
    plan, toss = serve
    start = serve_episode_start(plan.commands.plan, toss.t_lift, toss.release, toss.physics)
    scenario = RobotModel().scenario
    stack = make_control_stack(scenario, ControlParams())
    policy = Towards(AWAY, stack)
    diagram, simulator, context = segment_diagram(policy)
    start_segment_episodes(diagram, context, [0], start.ball[None], [0], planned=[start.planned])
    simulator.Initialize()
    joints, supervisor = diagram.GetSubsystemByName("joint_plant"), diagram.GetSubsystemByName("safety_supervisor")
    executed = execute_commands(scenario.dynamics, plan.commands.plan, settle=400)
    lead = diagram.GetSubsystemByName("episode_clock").timing.lead
    hold_ticks = int(np.ceil(start.planned.hold_samples / 32))
    for tick in range(1, hold_ticks + 1):
        simulator.AdvanceTo(tick * T)
        sample = start.planned.start_sample + tick * 32 - lead  # the plan's sample at this tick's start
        state = joints.plant_state(joints.GetMyContextFromRoot(context))
        np.testing.assert_array_equal(state.zeta[0], executed.zeta[0, sample])
        assert supervisor.supervisor_states(supervisor.GetMyContextFromRoot(context))[0].accepted == 0
    assert policy.calls >= hold_ticks - 1  # the policy ran and was not followed
    for tick in range(hold_ticks + 1, hold_ticks + 4):
        simulator.AdvanceTo(tick * T)
    assert supervisor.supervisor_states(supervisor.GetMyContextFromRoot(context))[0].accepted >= 2


def test_the_served_ball_meets_the_racket_as_planned_and_the_umpire_judges_the_service(serve):
    """On the diagram the racket strikes the released ball within a few ms of the planned hit, and
    the diagram's umpire reaches the decision ``judge_rally`` gives on the ball's own contacts."""
    plan, toss = serve
    start = serve_episode_start(plan.commands.plan, toss.t_lift, toss.release, toss.physics)
    diagram, simulator, context = segment_diagram(lambda observation: None)
    start_segment_episodes(diagram, context, [0], start.ball[None], [3], planned=[start.planned])
    umpire = diagram.GetSubsystemByName("umpire")
    umpire.StartPoints(umpire.GetMyMutableContextFromRoot(context), [0], [ROBOT], [start.toss])
    simulator.Initialize()
    for tick in range(1, 60):
        simulator.AdvanceTo(tick * T)
        judged = umpire.umpires_port.Eval(umpire.GetMyContextFromRoot(context))[0]
        if judged.decision is not None or judged.bounced:
            break
    ball = diagram.GetSubsystemByName("ball")
    events = ball.plant_state(ball.GetMyContextFromRoot(context)).events[0]
    assert events[0].kind == 4  # the racket first
    hit = plan.t_hit - start.planned.start_sample * 1e-3
    assert abs(events[0].time - hit) < 0.006
    rally = [RallyEvent.from_contact(e, ROBOT if e.kind == 4 else None) for e in events]
    expected = judge_rally(ROBOT, rally, start.toss)
    if expected is None:
        assert judged.decision is None and judged.bounced and judged.to_play == HUMAN
    else:
        assert (judged.decision.winner, judged.decision.reason, judged.decision.event.time) == (expected.winner, expected.reason, expected.event.time)


def test_a_continuing_robot_moves_on_exactly_as_if_no_new_episode_had_started():
    """Restarting the episode of a moving robot (``continuing=True``: the next shot of a rally)
    leaves its joints' motion, tick by tick, as it would have been had its policy not acted at
    that tick (a new episode's first tick decides no segment): the plan is re-timed, not
    replaced."""
    stack = make_control_stack(RobotModel().scenario, ControlParams())

    def run(restart_at, idle):
        diagram, simulator, context = segment_diagram(Towards(AWAY, stack, idle=idle))
        start_segment_episodes(diagram, context, [0], SHOT[None], [0])
        simulator.Initialize()
        joints = diagram.GetSubsystemByName("joint_plant")
        history = []
        for tick in range(1, 25):
            simulator.AdvanceTo(tick * T)
            if tick == restart_at:
                start_segment_episodes(diagram, context, [0], (SHOT + 0.1)[None], [1], continuing=True)
            history.append(joints.plant_state(joints.GetMyContextFromRoot(context)).zeta[0].copy())
        return np.array(history)

    moving = run(None, None)
    idle = run(None, IDLE_CALL)
    continued = run(10, None)
    assert np.abs(moving[-1] - moving[0]).max() > 0.05  # the robot did move
    assert np.abs(moving - idle).max() > 1e-3  # and the idle call matters
    np.testing.assert_allclose(continued, idle, rtol=0.0, atol=1e-12)
    diagram, _, context = segment_diagram(lambda observation: None)
    with pytest.raises(ValueError, match="continuing"):
        start_segment_episodes(diagram, context, [0], SHOT[None], [0], q=AWAY[None], continuing=True)


class OneServe:
    """The robot's serves for the tests: always the planned short backspin, no execution noise."""

    def __init__(self, serve):
        plan, toss = serve
        self.start_ = serve_episode_start(plan.commands.plan, toss.t_lift, toss.release, toss.physics)

    def start(self, rng, recent):
        return "short_backspin", self.start_


@needs_data
def test_short_matches_are_scored_by_the_rules_and_reproducible(serve):
    """Two first-to-3 matches against Elite C's opponent model with the returner: every decided
    point is awarded, a game ends at 3 with a 2-point lead (or later), the server changes every 2
    points by the Laws; the same seeds give the same matches whether they play side by side or alone."""
    from ace_drake.evaluation.controllers import make_controller, rally_params

    params = rally_params(None, "statistical", 0, "segment")
    opponent = OpponentModel.from_match_data(DATA, ["Elite C"])
    rules = MatchRules(points_to_win=3, best_of=1)
    together, track = MatchRunner([make_controller("returner", params) for _ in range(2)], params, 2).play(
        opponent, OneServe(serve), 2, rules, seed=5, opponent_name="Elite C", record=1)
    alone, _ = MatchRunner([make_controller("returner", params)], params, 1).play(opponent, OneServe(serve), 2, rules, seed=5, opponent_name="Elite C")
    for match in together:
        decided = [p for p in match.points if not p.let]
        robot, human = match.games[0]
        assert max(robot, human) >= 3 and abs(robot - human) >= 2
        assert robot + human == len(decided) == match.summary()["points_played"]
        assert match.summary()["points_won"] == robot
        scorer = Match(rules, decided[0].server)  # the Laws' service order, replayed
        for point in decided:
            assert (point.server, point.score) == (scorer.server, scorer.points)
            scorer.award(point.winner)
        assert all(p.reason for p in match.points)
    assert [m.points for m in together] == [m.points for m in alone]
    assert len(track.points) == len(together[1].points) and track.times.size > 100
    assert episode_seed(5, 0, 1, 2) != episode_seed(5, 0, 2, 1)


def test_a_points_strikes_errors_aces_and_faults_are_read_from_its_ending():
    """PointResult's bookkeeping on hand-made points: strikes alternate from the server; the last
    striker losing after the service made a return error; a one-strike point is an ace or a
    service fault."""
    from ace_drake.evaluation.match import PointResult

    def point(server, winner, shots):
        return PointResult(1, (0, 0), server, None, winner, "", "", shots, 1.0)

    long_rally = point(ROBOT, ROBOT, 5)  # robot, human, robot, human, robot: the human missed
    assert (long_rally.strikes_by(ROBOT), long_rally.strikes_by(HUMAN), long_rally.last_striker) == (3, 2, ROBOT)
    assert long_rally.return_error is None and not long_rally.ace and not long_rally.service_fault
    out = point(HUMAN, HUMAN, 4)  # human, robot, human, robot: the robot's return went out
    assert out.last_striker == ROBOT and out.return_error == ROBOT
    assert point(ROBOT, ROBOT, 1).ace and point(ROBOT, HUMAN, 1).service_fault
    assert point(ROBOT, None, 1).return_error is None and not point(ROBOT, None, 1).service_fault  # a let
