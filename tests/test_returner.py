"""The model-based returner: the racket contact inversion, the return solve, the controller's
actions on constructed observations, and one episode through the full rally diagram."""

import numpy as np
import pytest

import ace_drake.control.returner as returner_module
from ace_drake.analysis.scripted_swing import INCOMING_BALL
from ace_drake.config import ConfigError
from ace_drake.contracts import ObservationLayout
from ace_drake.control.action_mapping import map_action
from ace_drake.control.feasible_set import feasible_sets
from ace_drake.control.hit_state import hermite
from ace_drake.control.params import RETURNER_MEMORY_PARTS, RallyParams, ReturnerParams
from ace_drake.control.returner import ModelBasedReturner, racket_plans
from ace_drake.control.stack import ControlStack
from ace_drake.physics.contact import racket_impact
from ace_drake.physics.params import BallPhysicsParams
from ace_drake.physics.propagate import ContactKind, simulate
from ace_drake.physics.racket_inverse import contact_frame

PARAMS = BallPhysicsParams()
RADIUS = PARAMS.aero.ball_radius
# The scripted swing's incoming ball at the top of its bounce on the robot's half (0.68 s).
APEX_BALL = simulate(INCOMING_BALL, PARAMS, 0.68).final_state[0]


@pytest.fixture(scope="module")
def returner():
    return ModelBasedReturner()


def observation(layout: ObservationLayout, estimate, valid=True, q=None, skill=(0.0, 1.0, 0.0)) -> np.ndarray:
    """An observation with the EKF estimate ``estimate`` (9,), the robot at rest at q (default:
    the ready pose) and ``skill`` [y_desired, w_p, w_s]; empty histories."""
    q = np.asarray(RallyParams().control.reset_pose or (-0.45, -0.15, 0.0, 0.15, 0.35, 0.0, -0.5, 0.0)) if q is None else q
    empty = np.column_stack([np.zeros((10, 3)), -np.ones(10)])
    return layout.assemble(
        positions=empty, spins=empty, robot_state=np.concatenate([q, np.zeros(16)]), end_effector=np.zeros(13),
        skill=skill, estimate=estimate if valid else np.zeros(9), estimate_status=[1.0 if valid else 0.0, 1.0 if valid else 0.0, 0.01 if valid else -1.0],
    )


def test_racket_plans_send_the_predicted_ball_to_the_target_through_the_contact_model():
    plan = next(racket_plans(APEX_BALL, 0.68, PARAMS, np.array([0.75, 0.2])))
    v_post, w_post = racket_impact(APEX_BALL[3:6], APEX_BALL[6:9], plan.velocity, contact_frame(plan.normal), PARAMS.racket, RADIUS)
    np.testing.assert_allclose(np.concatenate([v_post, w_post]), plan.ball_out[3:], atol=1e-9)
    standoff = RADIUS + 0.5 * PARAMS.racket.blade_thickness
    np.testing.assert_allclose(plan.position + standoff * plan.normal, APEX_BALL[:3], atol=1e-12)
    landing = simulate(plan.ball_out, PARAMS, 2.0, stop_on=(ContactKind.TABLE, ContactKind.NET, ContactKind.FLOOR)).stop_events[0]
    assert landing.kind == ContactKind.TABLE
    np.testing.assert_allclose(landing.state_pre[:2], [0.75, 0.2], atol=0.01)


def test_the_hermite_meets_its_ends_and_continues_straight():
    q0, v0, q1, v1 = np.array([0.0, 1.0]), np.array([1.0, 0.0]), np.array([2.0, -1.0]), np.array([0.5, 3.0])
    for t, expected in [(0.0, (q0, v0)), (0.4, (q1, v1)), (0.5, (q1 + 0.1 * v1, v1))]:
        q, v = hermite(q0, v0, q1, v1, 0.4, t)
        np.testing.assert_allclose(q, expected[0], atol=1e-12)
        np.testing.assert_allclose(v, expected[1], atol=1e-12)


def test_no_track_or_a_ball_going_away_means_no_new_segment(returner):
    returner.reset()
    assert returner(observation(returner.layout, np.zeros(9), valid=False)) is None
    going_away = np.array([-1.5, 0.0, 0.3, 5.0, 0.0, 2.0, 0.0, 100.0, 0.0])
    assert returner(observation(returner.layout, going_away)) is None


def test_an_invalid_shot_is_left_alone(returner):
    returner.reset()
    into_the_net = np.array([1.5, 0.0, 0.05, -6.0, 0.0, 0.0, 0.0, 0.0, 0.0])
    assert returner(observation(returner.layout, into_the_net)) is None


def test_the_action_for_a_reachable_ball_moves_the_racket_towards_the_hit(returner):
    returner.reset()
    estimate = simulate(INCOMING_BALL, PARAMS, 0.1).final_state[0]  # still on the opponent's side
    obs = observation(returner.layout, estimate)
    action = returner(obs)
    plan = returner.last_plan
    assert action is not None and plan is not None
    assert np.all(np.abs(action) <= 1.0)
    # The hit is after the bounce on the robot's half, at a height the returner accepts.
    bounce = simulate(estimate, PARAMS, 1.0, stop_on=(ContactKind.TABLE,)).stop_events[0]
    assert bounce.state_pre[0] < 0.0 and plan.time > bounce.time
    assert returner.params.hit_height_min <= plan.racket.ball_state[2] <= returner.params.hit_height_max
    # The segment this action commands ends nearer the hit configuration, and the racket there
    # nearer the planned racket position.
    robot = returner.layout.part(obs, "robot_state")
    q0 = robot[:8]
    stack = returner.stack
    q_end, _ = map_action(action, feasible_sets(q0, robot[8:16], robot[16:], stack.limits, stack.control, stack.period))
    assert np.linalg.norm(q_end - plan.q) < np.linalg.norm(q0 - plan.q)
    model = returner.model
    distance = [np.linalg.norm(model.racket_pose(q).translation() - plan.racket.position) for q in (q0, q_end)]
    assert distance[1] < distance[0]


def test_the_returner_follows_the_skill_aiming_at_y_desired_and_brushing_by_w_s(returner):
    # Paper, *Rewards*: y_desired is where the return should land, w_s weighs its topspin at
    # landing. The returner aims at y_desired (clipped to target_y_limit) and brushes the ball along
    # the blade by skill_brush * w_s: up for topspin, down for backspin.
    from ace_drake.learning.rewards import travel_frame_spin
    from ace_drake.physics.racket_inverse import _blade_up

    estimate = simulate(INCOMING_BALL, PARAMS, 0.1).final_state[0]
    plans = {}
    for skill in [(0.3, 1.0, 1.0), (0.3, 1.0, 0.0), (0.3, 1.0, -1.0), (-0.9, 1.0, 0.0)]:
        returner.reset()
        assert returner(observation(returner.layout, estimate, skill=skill)) is not None
        plans[skill] = returner.last_plan.racket
    brush = {w_s: plans[(0.3, 1.0, w_s)].velocity @ _blade_up(plans[(0.3, 1.0, w_s)].normal) for w_s in (1.0, 0.0, -1.0)}
    flat = brush[0.0]  # a racket moving along its normal has no component along the blade
    assert flat == pytest.approx(0.0, abs=1e-9)
    assert brush[1.0] == pytest.approx(returner.params.skill_brush, abs=1e-9) and brush[-1.0] == pytest.approx(-returner.params.skill_brush, abs=1e-9)
    landing_spin = {}
    for skill, plan in plans.items():
        landing = simulate(plan.ball_out, PARAMS, 2.0, stop_on=(ContactKind.TABLE,)).stop_events[0].state_pre
        target_y = float(np.clip(skill[0], -returner.params.target_y_limit, returner.params.target_y_limit))
        np.testing.assert_allclose(landing[:2], [returner.params.target_x, target_y], atol=0.01)
        landing_spin[skill] = travel_frame_spin(landing)
    assert landing_spin[(0.3, 1.0, 1.0)] > landing_spin[(0.3, 1.0, 0.0)] + 100.0 > landing_spin[(0.3, 1.0, -1.0)] + 200.0
    # With skill_brush 0 the spin skill is ignored (the earlier training runs' labeller).
    flat_returner = ModelBasedReturner(model=returner.model, stack=returner.stack, params=ReturnerParams(skill_brush=0.0))
    for w_s in (1.0, -1.0):
        flat_returner.reset()
        flat_returner(observation(flat_returner.layout, estimate, skill=(0.3, 1.0, w_s)))
        np.testing.assert_allclose(flat_returner.last_plan.racket.velocity, plans[(0.3, 1.0, 0.0)].velocity, atol=1e-9)


class _Report:
    def __init__(self, free):
        self.free, self.pairs, self.time = free, () if free else ("racket - table",), 0.0


@pytest.mark.parametrize("free", [True, False])
def test_an_action_the_supervisor_would_refuse_is_not_sent(returner, free):
    # The returner proposes its action to a control stack like the supervisor's; with a check that
    # refuses everything it sends nothing (the supervisor keeps its plan), with one that accepts
    # everything it sends its first choice.
    dut = ModelBasedReturner(model=returner.model, stack=ControlStack(returner.model.scenario, returner.stack.control, lambda plan: _Report(free)))
    estimate = simulate(INCOMING_BALL, PARAMS, 0.1).final_state[0]
    action = dut(observation(dut.layout, estimate))
    assert (action is not None) == free
    assert dut.last_plan is not None


@pytest.fixture(scope="module")
def memoryless(returner):
    return ModelBasedReturner(model=returner.model, stack=returner.stack, params=ReturnerParams(memory=False))


def test_the_memoryless_returner_finds_a_bounce_behind_the_ball_from_its_flight(memoryless):
    bounce = simulate(INCOMING_BALL, PARAMS, 1.0, stop_on=(ContactKind.TABLE,)).stop_events[0]
    assert bounce.state_pre[0] < 0.0
    # At the top of the bounce (0.68 s) the bounce lies behind; before it, none does.
    assert memoryless.predictor.bounce_behind(APEX_BALL) == pytest.approx(bounce.time - 0.68, abs=2e-3)
    for before in (0.1, bounce.time - 0.02):
        assert memoryless.predictor.bounce_behind(simulate(INCOMING_BALL, PARAMS, before).final_state[0]) is None
    # A ball that bounced on the opponent's half and rises over the net has not bounced on the robot's.
    assert memoryless.predictor.bounce_behind(np.array([-0.2, 0.0, 0.25, -5.0, 0.0, 1.0, 0.0, 0.0, 0.0])) is None


def test_the_memoryless_returner_acts_on_the_observation_alone(returner, memoryless):
    # Just after the bounce, a returner that did not see the bounce coming has no hit; the
    # memoryless one finds the bounce behind the ball and plans the hit after it.
    bounce = simulate(INCOMING_BALL, PARAMS, 1.0, stop_on=(ContactKind.TABLE,)).stop_events[0]
    rising = observation(returner.layout, simulate(INCOMING_BALL, PARAMS, bounce.time + 0.03).final_state[0])
    returner.reset()
    assert returner(rising) is None
    memoryless.last_plan = None
    action = memoryless(rising)
    assert action is not None and memoryless.last_plan is not None and memoryless.last_plan.time > 0.0
    assert memoryless.params.hit_height_min <= memoryless.last_plan.racket.ball_state[2] <= memoryless.params.hit_height_max
    # Its action is a function of the observation: the same after another ball in between.
    early = observation(memoryless.layout, simulate(INCOMING_BALL, PARAMS, 0.1).final_state[0])
    first = memoryless(early)
    memoryless(observation(memoryless.layout, APEX_BALL))
    np.testing.assert_array_equal(memoryless(early), first)


def test_forgetting_the_plans_configuration_solves_the_full_ik_again(returner, monkeypatch):
    # Two calls for the same ball one segment apart: with its memory the returner moves the first
    # call's hit configuration onto the new racket target (no full IK); with "ik" forgotten it
    # solves the full IK from the segment start again, and the plan is otherwise the same hit.
    solved = []
    solve = returner_module.solve_hit_ik

    def counting(*args, **kwargs):
        solved.append(args[1])
        return solve(*args, **kwargs)

    hits = {}
    for forget in ((), ("ik",)):
        dut = ModelBasedReturner(model=returner.model, stack=returner.stack, params=ReturnerParams(forget=forget))
        dut(observation(dut.layout, simulate(INCOMING_BALL, PARAMS, 0.1).final_state[0]))
        first = dut.last_plan.time
        monkeypatch.setattr(returner_module, "solve_hit_ik", counting)
        solved.clear()
        assert dut(observation(dut.layout, simulate(INCOMING_BALL, PARAMS, 0.1 + dut.segment).final_state[0])) is not None
        monkeypatch.setattr(returner_module, "solve_hit_ik", solve)
        assert dut.last_plan.time == pytest.approx(first, abs=1e-9)  # the same hit, on the returner's clock
        hits[forget] = len(solved)
    assert hits[()] == 0 and hits[("ik",)] >= 1


@pytest.mark.parametrize("rule", ["braking", "segment_start"])
def test_a_full_ik_starts_where_braking_would_stop_the_moving_arm(returner, monkeypatch, rule):
    # The robot moving at the segment start: a full IK's nominal configuration (and first seed)
    # is, with "braking", the arm's joints at q0 + v0 D / 2 for the hit's D > 0 (one D for every
    # joint), the gantry at q0; with "segment_start", q0 itself.
    dut = ModelBasedReturner(model=returner.model, stack=returner.stack, params=ReturnerParams(memory=False, ik_nominal=rule))
    obs = observation(dut.layout, simulate(INCOMING_BALL, PARAMS, 0.1).final_state[0])
    q0 = dut.layout.part(obs, "robot_state")[:8].copy()
    v0 = np.array([0.3, -0.2, 0.4, -0.3, 0.5, 0.6, -0.4, 0.2])  # rad/s or m/s, well inside the limits
    obs[dut.layout.slice("robot_state")][8:16] = v0
    starts = []
    solve = returner_module.solve_hit_ik

    def recording(model, p_WR, normal_W, q_nominal, seeds, clearance):
        starts.append((np.array(q_nominal), np.array(seeds[0])))
        return solve(model, p_WR, normal_W, q_nominal, seeds, clearance)

    monkeypatch.setattr(returner_module, "solve_hit_ik", recording)
    assert dut(obs) is not None and dut.last_plan is not None
    nominal, seed = starts[0]
    np.testing.assert_array_equal(seed, nominal)
    arm = dut.model.revolute
    np.testing.assert_array_equal(nominal[~arm], q0[~arm])  # the gantry: where it is
    if rule == "segment_start":
        np.testing.assert_array_equal(nominal, q0)
    else:
        half_durations = (nominal[arm] - q0[arm]) / v0[arm]
        assert half_durations[0] > 0.0
        np.testing.assert_allclose(half_durations, half_durations[0], rtol=1e-9)
        assert half_durations[0] <= 0.5 * dut.params.prediction_horizon


def test_the_ik_nominal_is_one_of_the_named_rules_by_default_the_better_one_for_each_mode():
    with pytest.raises(ConfigError, match="ik_nominal must be one of braking, segment_start"):
        ReturnerParams(ik_nominal="ready_pose")
    assert ReturnerParams().ik_rule == "segment_start" and ReturnerParams(memory=False).ik_rule == "braking"
    assert ReturnerParams(memory=False, ik_nominal="segment_start").ik_rule == "segment_start"


@pytest.mark.parametrize("part", RETURNER_MEMORY_PARTS)
def test_the_returner_plays_a_ball_with_any_part_of_its_memory_forgotten(returner, part):
    dut = ModelBasedReturner(model=returner.model, stack=returner.stack, params=ReturnerParams(forget=(part,)))
    for elapsed in (0.1, 0.1 + dut.segment, 0.1 + 2 * dut.segment):
        action = dut(observation(dut.layout, simulate(INCOMING_BALL, PARAMS, elapsed).final_state[0]))
        assert action is not None and np.all(np.abs(action) <= 1.0) and dut.last_plan is not None


def assert_returns_an_easy_shot(dut, params) -> None:
    """``dut`` (a controller) returns the scripted swing's incoming ball through the full rally
    diagram of ``params``, with no segment refused, onto the opponent's half (shared with
    tests/test_experiments.py, for the study variants)."""
    from ace_drake.contracts import Outcome
    from ace_drake.diagrams import build_rally_diagram
    from ace_drake.evaluation.runner import RallyRunner

    runner = RallyRunner(build_rally_diagram(params, dut), params)
    episode = runner.run(INCOMING_BALL, seed=0)
    assert episode.result.outcome == Outcome.RETURNED, episode.result.reason
    assert episode.segments[1] == 0  # no refused segment
    landing = episode.result.landing.state_pre
    assert 0.0 < landing[0] < 1.37 and abs(landing[1]) < 0.7625


def test_an_easy_shot_is_returned_through_the_full_rally_diagram():
    from ace_drake.evaluation.controllers import make_controller

    params = RallyParams()  # cameras, triangulation, EKF, perturbations: the full stack
    dut = make_controller("returner", params)
    assert isinstance(dut, ModelBasedReturner) and dut.params.memory
    assert_returns_an_easy_shot(dut, params)


def test_the_returner_plays_the_same_episode_without_the_observations_hit_prediction():
    # It predicts the ball itself, so the CLI builds its diagram without the part (faster):
    # evaluation.controllers.diagram_params_for. The episode must not change.
    from ace_drake.diagrams import build_rally_diagram
    from ace_drake.evaluation.runner import RallyRunner
    from ace_drake.perception.params import PerceptionParams

    results = []
    for on in (True, False):
        params = RallyParams(perception=PerceptionParams(positions="statistical"), hit_prediction=on)
        dut = ModelBasedReturner.for_rally(params, ReturnerParams(memory=False))
        episode = RallyRunner(build_rally_diagram(params, dut), params).run(INCOMING_BALL, seed=3)
        results.append((episode.result.outcome, episode.result.landing.state_pre.tolist(), episode.segments))
    assert results[0] == results[1]


def test_a_non_finite_estimate_keeps_the_plan_or_sends_nothing_without_one(returner, memoryless):
    estimate = simulate(INCOMING_BALL, PARAMS, 0.1).final_state[0]
    nan_estimate = np.r_[estimate[:3], np.nan, estimate[4:]]
    # No plan yet: no new segment (the supervisor holds its plan, ending at the ready pose).
    returner.reset()
    assert returner(observation(returner.layout, nan_estimate)) is None and returner.last_plan is None
    memoryless.last_plan = None
    assert memoryless(observation(memoryless.layout, np.full(9, np.inf))) is None
    # With a plan: the next call, one segment on, drives on towards the same hit as planned.
    returner.reset()
    assert returner(observation(returner.layout, estimate)) is not None
    plan = returner.last_plan
    later = simulate(INCOMING_BALL, PARAMS, 0.1 + returner.segment).final_state[0]
    obs = observation(returner.layout, np.r_[later[:3], np.nan, later[4:]])
    action = returner(obs)
    assert returner.last_plan is plan
    robot = returner.layout.part(obs, "robot_state")
    boundary = plan.time - returner.segment - returner.lag - returner.lead  # its clock: 0 at the first call, one segment at this one
    np.testing.assert_array_equal(action, returner.driver.drive(robot[:8], robot[8:16], robot[16:], plan.q, plan.v, boundary))
    # And the ball is still played when the estimate comes back.
    assert returner(observation(returner.layout, simulate(INCOMING_BALL, PARAMS, 0.1 + 2 * returner.segment).final_state[0])) is not None
