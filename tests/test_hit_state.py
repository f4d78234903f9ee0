"""The hit-state action: its parameterisation, the layer that drives the joints to it (shared with
the returner), the racket kinematics in torch, the cloning loss, and a hit-state policy's path
through the workers, the artefact and the controllers."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from ace_drake.analysis.scripted_swing import INCOMING_BALL
from ace_drake.config import ConfigError
from ace_drake.contracts import ObservationLayout
from ace_drake.control.action_mapping import ACTION_SIZE, map_action
from ace_drake.control.feasible_set import feasible_sets
from ace_drake.control.hit_prediction import HitPredictor
from ace_drake.control.hit_state import HitDriver, HitStateAction, HitStateLayer, hermite
from ace_drake.control.params import RallyParams, ReturnerParams
from ace_drake.control.returner import ModelBasedReturner
from ace_drake.control.stack import ControlStack
from ace_drake.learning.hit_state import HitStateCloning, RacketKinematics
from ace_drake.learning.replay import DemonstrationBuffer
from ace_drake.learning.sac import PlayOptions, SacConfig, SacLearner, load_policy, save_policy
from ace_drake.physics.params import BallPhysicsParams
from ace_drake.physics.propagate import simulate
from ace_drake.robot.model import RobotModel
from ace_drake.training.rollout import ExplorationParams, RolloutWorker

PARTS = ("positions", "spins", "robot_state", "end_effector", "skill", "estimate", "estimate_status", "hit_prediction")
SMALL = SacConfig(batch_size=16, actor_hidden=(32, 32), embedding_size=32, decoder_hidden=(16,), critic_hidden=(32, 32),
                  action="hit_state", actor_observation_parts=PARTS)
READY = np.asarray(RallyParams().control.reset_pose or (-0.45, -0.15, 0.0, 0.15, 0.35, 0.0, -0.5, 0.0))


@pytest.fixture(scope="module")
def model():
    return RobotModel()


@pytest.fixture(scope="module")
def layer():
    return HitStateLayer.for_rally(RallyParams())


def observation(layout: ObservationLayout, estimate, predictor: HitPredictor, q=READY, v=np.zeros(8)) -> np.ndarray:
    """An observation of the ball estimated at ``estimate`` with its hit prediction, the robot's
    segment starting at (q, v) with no acceleration; empty histories."""
    empty = np.column_stack([np.zeros((10, 3)), -np.ones(10)])
    return layout.assemble(
        positions=empty, spins=empty, robot_state=np.concatenate([q, v, np.zeros(8)]), end_effector=np.zeros(13),
        skill=[0.0, 1.0, 0.0], estimate=estimate, estimate_status=[1.0, 1.0, 0.01], hit_prediction=predictor.features(estimate, True),
    )


def test_the_parameterisation_round_trips_and_works_in_torch(layer):
    parameterisation = layer.parameterisation
    rng = np.random.default_rng(0)
    y = rng.uniform(-1, 1, (5, ACTION_SIZE))
    q_hit, v_hit = parameterisation.hit_state(y, READY)
    np.testing.assert_allclose(parameterisation.coordinates(q_hit, v_hit, READY), y, atol=1e-12)
    np.testing.assert_allclose(v_hit, y[:, 8:] * layer.driver.stack.limits.velocity)
    q_t, v_t = parameterisation.hit_state(torch.as_tensor(y), torch.as_tensor(READY))
    np.testing.assert_allclose(q_t.numpy(), q_hit)
    np.testing.assert_allclose(v_t.numpy(), v_hit)
    assert HitStateAction.from_dict(parameterisation.as_dict()).matches(parameterisation)


def test_steps_to_hit_agree_in_numpy_and_torch(layer):
    # The layer's k and the cloning loss's k come from one formula, rounding alike at half steps.
    from ace_drake.control.hit_state import steps_to_hit

    times = layer.lead + layer.lag + layer.segment * np.array([-0.5, 0.0, 0.5, 1.49, 1.5, 2.5, 7.2])
    k = layer.steps_to_hit(times)
    np.testing.assert_array_equal(k, [0, 0, 0, 1, 2, 2, 7])
    np.testing.assert_array_equal(steps_to_hit(torch.as_tensor(times), layer.lead, layer.lag, layer.segment).numpy(), k)
    assert isinstance(layer.steps_to_hit(float(times[-1])), np.integer)


def test_torch_kinematics_match_drake(model):
    kinematics = RacketKinematics(model, torch.float64)
    rng = np.random.default_rng(1)
    q, v = rng.uniform(model.lower, model.upper, (6, 8)), rng.normal(0.0, 1.0, (6, 8))
    p, R, velocity = kinematics.pose_and_velocity(torch.as_tensor(q), torch.as_tensor(v))
    for i in range(6):
        X_WR, V_WR = model.racket_pose(q[i]), model.racket_spatial_velocity(q[i], v[i])
        np.testing.assert_allclose(p[i].numpy(), X_WR.translation(), atol=1e-12)
        np.testing.assert_allclose(R[i].numpy(), X_WR.rotation().matrix(), atol=1e-12)
        np.testing.assert_allclose(velocity[i].numpy(), V_WR.translational(), atol=1e-12)


def test_the_driver_commands_the_hermite_one_segment_ahead():
    stack = ControlStack(None, None, None)  # no collision check: the maths alone
    driver = HitDriver(stack)
    q0, v0 = READY, np.zeros(8)
    q_hit = q0 + np.r_[0.0, 0.0, 0.02, 0.05, -0.05, 0.05, 0.05, 0.05]
    v_hit = np.r_[0.0, 0.0, 0.1, 0.2, -0.2, 0.2, 0.2, 0.2]
    action = driver.drive(q0, v0, np.zeros(8), q_hit, v_hit, 6 * driver.segment)
    q_T, v_T = map_action(action, feasible_sets(q0, v0, np.zeros(8), stack.limits, stack.control, stack.period))
    expected = hermite(q0, v0, q_hit, v_hit, 6 * driver.segment, driver.segment)
    np.testing.assert_allclose(q_T, expected[0], atol=1e-9)
    np.testing.assert_allclose(v_T, expected[1], atol=1e-9)
    assert driver.last_choice == 0
    # Following through carries the joints on at their velocities.
    v_moving = np.r_[0.0, 0.0, 0.0, 0.3, 0.0, -0.3, 0.0, 0.0]
    q_T, v_T = map_action(driver.follow_through(q0, v_moving, np.zeros(8)),
                          feasible_sets(q0, v_moving, np.zeros(8), stack.limits, stack.control, stack.period))
    np.testing.assert_allclose(q_T, q0 + v_moving * driver.segment, atol=1e-9)
    np.testing.assert_allclose(v_T, v_moving, atol=1e-9)


def test_the_layer_fed_the_returners_plan_sends_the_returners_action(layer):
    # The layer is the returner's own last step: given the memoryless returner's planned hit state
    # at the predicted hit, it sends exactly the returner's action.
    returner = ModelBasedReturner.for_rally(RallyParams(), ReturnerParams(memory=False))
    estimate = simulate(INCOMING_BALL, BallPhysicsParams(), 0.1).final_state[0]
    obs = observation(layer.layout, estimate, returner.predictor)
    action = returner(obs)
    plan = returner.last_plan
    hit = layer.layout.part(obs, "hit_prediction")
    assert action is not None and plan is not None and plan.time == pytest.approx(hit[1])
    assert layer.steps_to_hit(hit[1]) >= 2
    y = layer.parameterisation.coordinates(plan.q, plan.v, READY)
    np.testing.assert_allclose(layer(obs, y), action, atol=1e-9)


def test_the_layer_that_meets_the_ball_moves_the_blade_onto_the_predicted_ball_and_keeps_its_orientation(layer, model):
    from ace_drake.physics.contact import blade_standoff

    meeting = HitStateLayer.for_rally(RallyParams(), meet_ball=True)
    assert meeting.meets_ball and not layer.meets_ball
    assert meeting.standoff == pytest.approx(blade_standoff(BallPhysicsParams().aero.ball_radius, BallPhysicsParams().racket))
    returner = ModelBasedReturner.for_rally(RallyParams(), ReturnerParams(memory=False))
    estimate = simulate(INCOMING_BALL, BallPhysicsParams(), 0.1).final_state[0]
    obs = observation(layer.layout, estimate, returner.predictor)
    plan, _ = returner.plan(obs)
    ball = layer.layout.part(obs, "hit_prediction")[2:5]
    # The returner's own plan already meets the ball: the layer leaves it (nearly) where it is.
    np.testing.assert_allclose(meeting.meet_ball(plan.q, ball), plan.q, atol=2e-3)
    # An actor's hit state a few cm off (a 0.05 rad shoulder error) is moved back onto the ball.
    off = plan.q + np.r_[0.0, 0.0, 0.05, 0.0, 0.0, 0.0, 0.0, 0.0]
    X_off = model.racket_pose(off)
    miss = ball - meeting.standoff * X_off.rotation().matrix()[:, 2] - X_off.translation()
    assert np.linalg.norm(miss) > 0.02
    met = meeting.meet_ball(off, ball)
    X_met = model.racket_pose(met)
    np.testing.assert_allclose(X_met.translation() + meeting.standoff * X_met.rotation().matrix()[:, 2], ball, atol=1e-3)
    np.testing.assert_allclose(X_met.rotation().matrix(), X_off.rotation().matrix(), atol=1e-3)
    limits = meeting.driver.stack.limits
    assert np.all(met >= limits.lower) and np.all(met <= limits.upper)
    # Out of reach: the result stays inside the command limits.
    far = meeting.meet_ball(plan.q, ball + np.r_[0.0, 5.0, 0.0])
    assert np.all(far >= limits.lower) and np.all(far <= limits.upper)
    # Through the layer, the action is the one for the met hit state.
    y_off = layer.parameterisation.coordinates(off, plan.v, READY)
    y_met = layer.parameterisation.coordinates(met, plan.v, READY)
    np.testing.assert_allclose(meeting(obs, y_off), layer(obs, y_met), atol=1e-9)


def test_the_layer_has_no_action_without_a_predicted_hit_and_follows_through_at_it(layer):
    predictor = HitPredictor.for_robot(layer.driver.stack.scenario, layer.driver.stack.control, BallPhysicsParams())
    estimate = simulate(INCOMING_BALL, BallPhysicsParams(), 0.1).final_state[0]
    obs = observation(layer.layout, estimate, predictor)
    no_hit = obs.copy()
    no_hit[layer.layout.slice("hit_prediction")] = 0.0
    assert layer(no_hit, np.zeros(ACTION_SIZE)) is None
    imminent = obs.copy()
    imminent[layer.layout.slice("hit_prediction").start + 1] = layer.lead + layer.lag  # k = 0: the hit is in this segment
    assert layer.steps_to_hit(layer.lead + layer.lag) == 0
    v_moving = np.r_[0.0, 0.0, 0.0, 0.3, 0.0, -0.3, 0.0, 0.0]
    imminent[layer.layout.slice("robot_state")] = np.concatenate([READY, v_moving, np.zeros(8)])
    rng = np.random.default_rng(2)
    actions = [layer(imminent, rng.uniform(-1, 1, ACTION_SIZE)) for _ in range(2)]
    np.testing.assert_array_equal(actions[0], actions[1])  # whatever the actor says
    np.testing.assert_array_equal(actions[0], layer.driver.follow_through(READY, v_moving, np.zeros(8)))


@pytest.fixture(scope="module")
def cloning():
    return HitStateCloning(RallyParams(), ObservationLayout(), (0.02, 0.05, 0.2), 30.0)


def _rows(layout: ObservationLayout, count: int, seed: int):
    rng = np.random.default_rng(seed)
    obs = np.zeros((count, layout.size))
    robot = layout.slice("robot_state")
    obs[:, robot.start:robot.start + 8] = READY + rng.normal(0.0, 0.05, (count, 8))
    obs[:, robot.start + 8:robot.start + 16] = rng.normal(0.0, 0.2, (count, 8))
    hit = layout.slice("hit_prediction")
    obs[:, hit.start], obs[:, hit.start + 1] = 1.0, rng.uniform(0.05, 0.3, count)
    return torch.as_tensor(obs, dtype=torch.float32), torch.as_tensor(rng.uniform(-0.3, 0.3, (count, ACTION_SIZE)), dtype=torch.float32)


def test_the_cloning_loss_is_zero_at_the_label_and_counts_each_term(cloning):
    obs, label = _rows(ObservationLayout(), 8, 3)
    robot = obs[:, ObservationLayout().slice("robot_state")]
    hit_time = obs[:, ObservationLayout().slice("hit_prediction")][:, 1:2]
    duration = torch.clamp(torch.round((hit_time - cloning.lead - cloning.lag) / cloning.segment), min=1.0) * cloning.segment
    inside = (cloning.coasting(label, robot[:, :8], robot[:, 8:16], duration).abs() <= 2.0).all(-1)  # the label's c is not clipped
    assert cloning.loss(obs[inside], label[inside], label[inside]).item() == pytest.approx(0.0, abs=1e-6)
    # A coasting hit state has c = 0.
    coast = cloning.parameterisation.coordinates((robot[:, :8] + robot[:, 8:16] * duration).numpy(), robot[:, 8:16].numpy(), robot[:, :8].numpy())
    np.testing.assert_allclose(cloning.coasting(torch.as_tensor(coast, dtype=torch.float32), robot[:, :8], robot[:, 8:16], duration).numpy(), 0.0, atol=1e-4)
    # A change of the gantry alone moves the blade by its travel: the task term sees it.
    moved = label.clone()
    moved[:, 0] += 0.01 / float(cloning.parameterisation.half_range[0])  # 1 cm of gantry x
    weights_off = HitStateCloning.__new__(HitStateCloning)
    weights_off.__dict__.update(cloning.__dict__, consistency_weight=0.0)
    joint = ((moved - label) ** 2).sum(-1).mean().item()
    assert weights_off.loss(obs, moved, label).item() == pytest.approx(joint + (0.01 / 0.02) ** 2, rel=1e-3)


def test_the_hit_state_cloning_term_fits_the_labels():
    learner = SacLearner(dataclasses.replace(SMALL, seed=4, actor_lr=1e-3))
    obs, label = _rows(learner.config.layout, 64, 5)
    demonstrations = {"obs": obs.numpy(), "demo_action": label.numpy()}
    first = learner.behaviour_cloning_loss(demonstrations).item()
    optimiser = torch.optim.Adam(learner.actor.parameters(), 1e-3)
    for _ in range(200):
        loss = learner.behaviour_cloning_loss(demonstrations)
        optimiser.zero_grad()
        loss.backward()
        optimiser.step()
    assert loss.item() < 0.2 * first


def test_the_hit_state_action_needs_the_predicted_hit_in_the_actors_parts():
    with pytest.raises(ValueError, match="hit_prediction"):
        SacConfig(action="hit_state")
    with pytest.raises(ValueError, match="action"):
        SacConfig(action="torques")


def test_a_hit_state_worker_stores_hit_states_and_labels_planned_hits():
    # No DART noise: where the demonstrator plays a label, its stored action is that label. (Seed
    # 7: its episodes carry 8 and 16 labels; seed 6's demonstration labelled 1 of 12 rows with the
    # IK from the segment start and none with the braking rule, returning the ball by the
    # returner's own actions where it planned another hit than the predicted one.)
    worker = RolloutWorker(sac=SMALL, seed=7, returner=ReturnerParams(memory=False), exploration=ExplorationParams(demo_noise_fraction=0.0))
    demo, = worker.collect(1, "demonstrator")
    dagger, = worker.collect(1, "dagger")
    for episode in (demo, dagger):
        t = episode.transitions
        assert np.all(np.abs(t["action"]) <= 1.0)
        labelled = np.all(np.isfinite(t["demo_action"]), axis=-1)
        assert labelled.any() and np.all(np.abs(t["demo_action"][labelled]) <= 1.0)
        assert np.all(np.isnan(t["demo_action"][~labelled]))
    # Only labelled rows become cloning rows.
    buffer = DemonstrationBuffer()
    buffer.add(demo.transitions)
    assert len(buffer) == int(np.all(np.isfinite(demo.transitions["demo_action"]), axis=-1).sum())
    t = demo.transitions
    labelled = np.all(np.isfinite(t["demo_action"]), axis=-1)
    np.testing.assert_array_equal(t["action"][labelled], t["demo_action"][labelled])


def test_a_hit_state_policy_round_trips_and_plays_through_the_layer(tmp_path, monkeypatch):
    from ace_drake.evaluation import controllers

    learner = SacLearner(SMALL)
    save_policy(tmp_path / "hit_state.pt", learner)
    policy = load_policy(tmp_path / "hit_state.pt")
    assert policy.action == "hit_state" and policy.hit_state.matches(learner.policy().hit_state)
    monkeypatch.setattr(controllers, "POLICIES_DIR", tmp_path)
    controller = controllers.make_controller("policy:hit_state", RallyParams())
    assert isinstance(controller, controllers.HitStatePolicy)
    params = RallyParams()
    assert controllers.diagram_params_for(controller, params) == params  # it reads the predicted hit (no memory)
    assert controllers.hit_state_controller(controller, params) is controller
    estimate = simulate(INCOMING_BALL, BallPhysicsParams(), 0.1).final_state[0]
    obs = observation(controller.layer.layout, estimate, HitPredictor.for_robot(controller.layer.driver.stack.scenario,
                                                                                   controller.layer.driver.stack.control, BallPhysicsParams()))
    y = controller.policy(torch.as_tensor(obs, dtype=torch.float32)[None])[0].numpy()
    np.testing.assert_allclose(controller(obs), controller.layer(obs, y))
    assert not controller.layer.meets_ball
    # A policy trained for the ball-meeting layer keeps it in its artefact and plays through it.
    save_policy(tmp_path / "meeting.pt", SacLearner(SMALL, play=PlayOptions(meet_ball=True)))
    assert load_policy(tmp_path / "meeting.pt").meet_ball
    assert controllers.make_controller("policy:meeting", RallyParams()).layer.meets_ball
    with pytest.raises(ConfigError, match="hit_prediction"):
        controllers.make_controller("policy:hit_state", RallyParams(hit_prediction=False))
    # A policy trained with other command limits reads its actions in its own coordinates; the
    # diagram's layer is left as it was.
    other = HitStateAction(policy.hit_state.half_range * 1.1, policy.hit_state.velocity)
    trained_elsewhere = controllers.HitStatePolicy(type(policy)(policy.actor, policy.index, policy.scale, "hit_state", other), controller.layer)
    assert trained_elsewhere.layer.parameterisation.matches(other) and controller.layer.parameterisation.matches(policy.hit_state)
    q0 = controller.layer.layout.part(obs, "robot_state")[:8]
    q_hit, _ = trained_elsewhere.layer.parameterisation.hit_state(np.full(16, 0.01), q0)
    np.testing.assert_allclose(q_hit - q0, 0.01 * 1.1 * policy.hit_state.half_range)
    action = trained_elsewhere(obs)  # it plays: an eq. (12) action in the box, the diagram's limits bounding q_hit
    assert action is None or (action.shape == (16,) and np.all(np.abs(action) <= 1.0))


def test_the_returners_planned_hit_state_plays_through_the_layer(layer):
    from ace_drake.control.hit_state import PlannedHitState
    from ace_drake.evaluation import controllers

    params = RallyParams()

    def planned_hit_state(hit_memory):  # as the rollout workers label (analysis.experiments names them)
        return PlannedHitState(ModelBasedReturner.for_rally(params, ReturnerParams(memory=False)), HitStateLayer.for_rally(params),
                               hit_memory=hit_memory)

    planned = planned_hit_state(False)
    assert isinstance(planned, PlannedHitState) and controllers.diagram_params_for(planned, params) == params
    with pytest.raises(ConfigError, match="hit_prediction"):
        HitStateLayer.for_rally(RallyParams(hit_prediction=False))
    with pytest.raises(ValueError, match="memoryless"):
        PlannedHitState(ModelBasedReturner.for_rally(params), layer)
    estimate = simulate(INCOMING_BALL, BallPhysicsParams(), 0.1).final_state[0]
    obs = observation(layer.layout, estimate, planned.returner.predictor)
    y, at_prediction, action = planned.plan(obs)
    assert at_prediction and action is None  # a plan played through the layer is not driven the returner's way
    np.testing.assert_allclose(y, layer.parameterisation.coordinates(planned.returner.last_plan.q, planned.returner.last_plan.v, READY))
    np.testing.assert_allclose(planned(obs), layer(obs, y))
    no_hit = obs.copy()
    no_hit[layer.layout.slice("hit_prediction")] = 0.0
    assert planned.plan(no_hit)[0] is None
    # On an observation that keeps its predicted hit, the returner plans the observed hit first:
    # here one segment past the one it prefers, which it then plans, and labels.
    remembering = planned_hit_state(True)
    assert remembering.hit_memory and not planned.hit_memory
    preferred = planned.returner.predictor.preferred_hit(estimate)[0]
    later = obs.copy()
    later[layer.layout.slice("hit_prediction")] = planned.returner.predictor.features(estimate, True, keep=preferred + layer.segment)
    y_later, at_prediction, _ = remembering.plan(later)
    assert at_prediction and remembering.returner.last_plan.time == pytest.approx(preferred + layer.segment, abs=1e-9)
    assert not planned.plan(later)[1]  # the memoryless labeller plans its own preference: no label there
    assert not np.allclose(y_later, y)


def test_a_non_finite_hit_state_is_an_invalid_action_like_a_plain_policys(layer):
    from pydrake.systems.analysis import Simulator
    from pydrake.systems.framework import DiagramBuilder
    from pydrake.systems.primitives import ConstantVectorSource

    from ace_drake.control.params import ControlParams
    from ace_drake.systems.policy_controller import PolicyController

    meeting = HitStateLayer.for_rally(RallyParams(), meet_ball=True)
    predictor = HitPredictor.for_robot(layer.driver.stack.scenario, layer.driver.stack.control, BallPhysicsParams())
    estimate = simulate(INCOMING_BALL, BallPhysicsParams(), 0.1).final_state[0]
    obs = observation(layer.layout, estimate, predictor)
    assert layer.steps_to_hit(layer.layout.part(obs, "hit_prediction")[1]) >= 2
    nan_y = np.r_[np.full(3, np.nan), np.zeros(ACTION_SIZE - 3)]
    # The layer computes nothing from it (the meeting layer's kinematics would raise on NaN) and
    # passes it on; None stays None.
    for dut in (layer, meeting):
        passed = dut(obs, nan_y)
        assert passed.shape == (ACTION_SIZE,) and np.isnan(passed[:3]).all()
        assert dut(obs, None) is None
    # Behind a PolicyController the hit-state actor's NaN counts as invalid, as a plain NaN policy's does.
    outputs = iter([np.zeros(ACTION_SIZE), nan_y])
    builder = DiagramBuilder()
    dut = builder.AddNamedSystem("dut", PolicyController(lambda o: meeting(o, next(outputs)), len(obs), ControlParams()))
    builder.Connect(builder.AddSystem(ConstantVectorSource(obs)).get_output_port(), dut.observation_port)
    simulator = Simulator(builder.Build())
    context = dut.GetMyContextFromRoot(simulator.get_context())
    simulator.AdvanceTo(0.0271)
    assert dut.counts(context) == (1, 0) and dut.action_valid_port.Eval(context)[0] == 1.0
    simulator.AdvanceTo(0.0271 + 0.032)
    assert dut.counts(context) == (2, 1) and dut.action_valid_port.Eval(context)[0] == 0.0
