"""The observation layout and the ObservationBuilder system."""

import numpy as np
import pytest
from pydrake.common.value import AbstractValue

from ace_drake.analysis.scripted_swing import INCOMING_BALL
from ace_drake.config import MODELS_DIR
from ace_drake.contracts import ObservationLayout
from ace_drake.control.hit_prediction import HitPredictor
from ace_drake.control.params import ControlParams
from ace_drake.perception.measurements import Measurement, MeasurementHistory
from ace_drake.physics.params import BallPhysicsParams
from ace_drake.physics.propagate import simulate
from ace_drake.robot.model import load_scenario
from ace_drake.systems.observation_builder import ObservationBuilder


def test_layout_parts_tile_the_vector():
    layout = ObservationLayout(position_history=3, spin_history=2)
    names = ["positions", "spins", "robot_state", "end_effector", "skill", "estimate", "estimate_status", "hit_prediction"]
    covered = np.zeros(layout.size, dtype=int)
    for name in names:
        covered[layout.slice(name)] += 1
    assert np.all(covered == 1) and layout.size == 12 + 8 + 24 + 13 + 3 + 9 + 3 + 11
    np.testing.assert_array_equal(layout.indices(["skill", "positions"]), np.r_[12 + 8 + 24 + 13 + np.arange(3), np.arange(12)])
    assert layout.indices([]).size == 0
    with pytest.raises(KeyError, match="parts are"):
        layout.slice("velocity")
    with pytest.raises(ValueError, match=">= 1"):
        ObservationLayout(position_history=0)


def test_assemble_and_part_round_trip_and_size_errors():
    layout = ObservationLayout(2, 2)
    parts = dict(
        positions=np.arange(8.0).reshape(2, 4), spins=-np.arange(8.0).reshape(2, 4), robot_state=np.full(24, 2.0),
        end_effector=np.full(13, 3.0), skill=[0.2, 1.0, -0.5], estimate=np.full(9, 4.0), estimate_status=[1.0, 0.0, 0.01],
        hit_prediction=np.full(11, 6.0),
    )
    observation = layout.assemble(**parts)
    for name, value in parts.items():
        np.testing.assert_array_equal(layout.part(observation, name), np.asarray(value, dtype=float))
    with pytest.raises(ValueError, match="skill has 2 values, expected 3"):
        layout.assemble(**{**parts, "skill": [0.0, 1.0]})


def test_builder_reads_histories_with_ages_and_the_episode_skill():
    builder = ObservationBuilder(ObservationLayout(3, 2))
    context = builder.CreateDefaultContext()
    context.SetTime(0.1)
    positions = MeasurementHistory()
    for sequence, capture in enumerate((0.07, 0.08, 0.09), start=1):
        positions = positions.appended(Measurement(sequence, capture, capture + 0.01, [capture, 0.0, 0.1], np.eye(3) * 1e-6))
    builder.position_measurements_port.FixValue(context, AbstractValue.Make(positions))
    builder.spin_measurements_port.FixValue(context, AbstractValue.Make(MeasurementHistory()))
    builder.robot_state_port.FixValue(context, np.arange(24.0))
    builder.end_effector_state_port.FixValue(context, np.ones(13))
    builder.ball_state_estimate_port.FixValue(context, np.full(9, 5.0))
    builder.estimate_status_port.FixValue(context, [1.0, 0.0, 0.01])
    builder.SetSkill(context, [0.3, 0.5, -1.0])
    observation = builder.observation_port.Eval(context)
    layout = builder.layout
    history = layout.part(observation, "positions")
    np.testing.assert_allclose(history[:, 0], [0.09, 0.08, 0.07])  # newest first
    np.testing.assert_allclose(history[:, 3], [0.01, 0.02, 0.03])  # ages from the context's time
    np.testing.assert_array_equal(layout.part(observation, "spins")[:, 3], [-1.0, -1.0])  # none yet
    np.testing.assert_array_equal(layout.part(observation, "skill"), [0.3, 0.5, -1.0])
    np.testing.assert_array_equal(layout.part(observation, "robot_state"), np.arange(24.0))
    with pytest.raises(ValueError, match="w_p must be in"):
        builder.SetSkill(context, [0.0, 1.5, 0.0])


def test_builder_fills_the_hit_prediction_from_the_estimate():
    scenario = load_scenario(MODELS_DIR / "scenario.yaml")
    predictor = HitPredictor.for_robot(scenario, ControlParams(), BallPhysicsParams())
    estimate = simulate(INCOMING_BALL, BallPhysicsParams(), 0.1).final_state[0]
    assert predictor.features(estimate, True)[0] == 1.0  # the scripted swing's ball has a hit
    for dut, expected in ((ObservationBuilder(ObservationLayout(2, 2), predictor=predictor), predictor.features(estimate, True)),
                          (ObservationBuilder(ObservationLayout(2, 2)), np.zeros(11))):
        context = dut.CreateDefaultContext()
        dut.position_measurements_port.FixValue(context, AbstractValue.Make(MeasurementHistory()))
        dut.spin_measurements_port.FixValue(context, AbstractValue.Make(MeasurementHistory()))
        dut.robot_state_port.FixValue(context, np.zeros(24))
        dut.end_effector_state_port.FixValue(context, np.zeros(13))
        dut.ball_state_estimate_port.FixValue(context, estimate)
        dut.estimate_status_port.FixValue(context, [1.0, 1.0, 0.0])
        hit = dut.layout.part(dut.observation_port.Eval(context), "hit_prediction")
        np.testing.assert_array_equal(hit, expected)
    # Without a track the part is zeros, whatever the estimate holds.
    dut = ObservationBuilder(ObservationLayout(2, 2), predictor=predictor)
    context = dut.CreateDefaultContext()
    for port, value in ((dut.robot_state_port, np.zeros(24)), (dut.end_effector_state_port, np.zeros(13)),
                        (dut.ball_state_estimate_port, estimate), (dut.estimate_status_port, [0.0, 0.0, -1.0])):
        port.FixValue(context, value)
    for port in (dut.position_measurements_port, dut.spin_measurements_port):
        port.FixValue(context, AbstractValue.Make(MeasurementHistory()))
    np.testing.assert_array_equal(dut.layout.part(dut.observation_port.Eval(context), "hit_prediction"), np.zeros(11))


def test_the_rally_diagram_predicts_the_hit_unless_told_not_to():
    from ace_drake.control.params import RallyParams
    from ace_drake.diagrams import build_rally_diagram

    for on in (True, False):
        diagram = build_rally_diagram(RallyParams(hit_prediction=on))
        builder = diagram.GetSubsystemByName("observation_builder")
        assert (builder.predictor is not None) == on


def test_the_builder_with_hit_memory_keeps_the_hit_it_predicted():
    from pydrake.systems.analysis import Simulator

    scenario = load_scenario(MODELS_DIR / "scenario.yaml")
    physics = BallPhysicsParams()
    predictor = HitPredictor.for_robot(scenario, ControlParams(), physics)
    with pytest.raises(ValueError, match="needs a predictor"):
        ObservationBuilder(hit_memory=True)
    dut = ObservationBuilder(ObservationLayout(2, 2), predictor=predictor, hit_memory=True)
    context = dut.CreateDefaultContext()
    for port in (dut.position_measurements_port, dut.spin_measurements_port):
        port.FixValue(context, AbstractValue.Make(MeasurementHistory()))
    dut.robot_state_port.FixValue(context, np.zeros(24))
    dut.end_effector_state_port.FixValue(context, np.zeros(13))
    dut.estimate_status_port.FixValue(context, [1.0, 1.0, 0.0])
    first = predictor.segment - predictor.lead  # the PolicyController's first observation instant
    simulator = Simulator(dut, context)

    def observe(t):
        """The hit_prediction part at t (before the event at t), the estimate following the ball's flight."""
        dut.ball_state_estimate_port.FixValue(context, simulate(INCOMING_BALL, physics, 0.1 + t).final_state[0])
        simulator.AdvanceTo(t)
        return dut.layout.part(dut.observation_port.Eval(context), "hit_prediction")

    estimate = simulate(INCOMING_BALL, physics, 0.1 + first).final_state[0]
    assert np.isnan(context.get_discrete_state(0).get_value()[0])  # nothing kept yet: judged from the estimate
    np.testing.assert_array_equal(observe(first), predictor.features(estimate, True))
    # Keep a hit one segment past the preferred one: it stays the observation's hit, one segment
    # nearer at the next observation, and the event stores it again.
    preferred = predictor.preferred_hit(estimate)[0]
    context.get_mutable_discrete_state(0).SetFromVector([first + preferred + predictor.segment])
    np.testing.assert_array_equal(observe(first), predictor.features(estimate, True, keep=preferred + predictor.segment))
    hit = observe(first + predictor.segment)
    assert hit[0] == 1.0 and hit[1] == pytest.approx(preferred, abs=1e-9)
    assert context.get_discrete_state(0).get_value()[0] == pytest.approx(first + preferred + predictor.segment, abs=1e-9)
    # The memory is forgotten when the observation has no hit (here: no track).
    dut.estimate_status_port.FixValue(context, [0.0, 0.0, -1.0])
    assert observe(first + 2 * predictor.segment)[0] == 0.0
    simulator.AdvanceTo(first + 2 * predictor.segment + 1e-4)
    assert np.isnan(context.get_discrete_state(0).get_value()[0])
