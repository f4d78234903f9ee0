"""The segment-stepped rally diagram against the continuous-time reference, and its batch."""

import dataclasses

import numpy as np
import pytest

from ace_drake.control.params import RallyParams
from ace_drake.diagrams import build_rally_diagram, build_segment_rally_diagram, make_segment_simulator, start_segment_episodes
from ace_drake.evaluation.controllers import make_controller
from ace_drake.evaluation.runner import RallyRunner
from ace_drake.perception.params import PerceptionParams
from ace_drake.physics.propagate import ContactKind
from ace_drake.play.params import ShotParams
from ace_drake.play.shots import make_distribution

PARAMS = RallyParams(perception=PerceptionParams(positions="statistical"), perturb=False)
SEGMENT = dataclasses.replace(PARAMS, stepping="segment")


@pytest.fixture(scope="module")
def shots():
    sample = make_distribution(ShotParams(), PARAMS.physics).draw(np.random.default_rng(3), 3)
    return sample.states, sample.serve


def _replay(diagram, simulator, context, default, shot, actions, extra_ticks=3):
    """One B = 1 episode of the segment diagram with the given actions (None: none) at ticks 1, 2, ..."""
    context.SetTimeStateAndParametersFrom(default)
    start_segment_episodes(diagram, context, [0], shot[None], [0])
    diagram.GetInputPort("light_curtain").FixValue(context, np.zeros(1))
    request = diagram.GetInputPort("action_request")
    request.FixValue(context, np.zeros((1, 17)))
    simulator.Initialize()
    simulator.AdvanceTo(0.032)  # tick 0: to the first observation
    for tick, action in enumerate(list(actions) + [None] * extra_ticks, start=2):
        value = np.zeros((1, 17))
        if action is not None:
            value[0, :16], value[0, 16] = action, 1.0
        request.FixValue(context, value)
        simulator.AdvanceTo(tick * 0.032)  # whole ticks: a time summed tick by tick can stop one ulp short of a tick
    ball = diagram.GetSubsystemByName("ball")
    return ball.plant_state(ball.GetMyContextFromRoot(context)).events[0]


def test_the_returners_actions_give_the_references_contacts(shots):
    """The model-based returner plays the reference diagram; its actions, replayed open loop on the
    segment-stepped diagram, move the robot the same way (the same plans from the same segment
    start states), so every contact, the moving racket's included, agrees: times within 1e-6 s,
    positions within 1 mm (issue 29's bar), post-contact velocities within 1 mm/s."""
    returner = make_controller("returner", PARAMS)
    calls = []

    def recording(observation):
        action = returner(observation)
        calls.append(None if action is None else np.array(action))
        return action

    recording.reset = returner.reset
    reference = RallyRunner(build_rally_diagram(PARAMS, recording), PARAMS)
    dut = build_segment_rally_diagram(SEGMENT, None, 1)
    simulator = make_segment_simulator(dut)
    context, default = simulator.get_mutable_context(), dut.CreateDefaultContext()
    rackets = 0
    for shot, serve in zip(*shots):
        calls.clear()
        reference.run(shot, seed=0, serve=bool(serve))
        expected = reference._ball.contact_events_port.Eval(reference._ball.GetMyContextFromRoot(reference.context))
        events = _replay(dut, simulator, context, default, shot, calls)
        assert [e.kind for e in events[: len(expected)]] == [e.kind for e in expected]
        for got, want in zip(events, expected):
            assert abs(got.time - want.time) < 1e-6
            np.testing.assert_allclose(got.state_pre[:3], want.state_pre[:3], atol=1e-3)
            np.testing.assert_allclose(got.state_post[3:6], want.state_post[3:6], atol=1e-3)
        rackets += sum(e.kind == ContactKind.RACKET for e in expected)
    assert rackets >= 2  # the comparison covered moving-racket contacts


def test_a_batch_gives_the_episodes_of_single_runs(shots):
    """Three environments in one batch give, row by row and bit for bit, the contacts and
    observations of the same episodes run alone (B = 1)."""
    states, _ = shots
    rng = np.random.default_rng(7)
    actions = rng.uniform(-0.2, 0.2, (12, 3, 16))

    def run(rows):
        diagram = build_segment_rally_diagram(SEGMENT, None, len(rows))
        simulator = make_segment_simulator(diagram)
        context = simulator.get_mutable_context()
        start_segment_episodes(diagram, context, np.arange(len(rows)), states[rows], np.array(rows) + 10)
        diagram.GetInputPort("light_curtain").FixValue(context, np.zeros(len(rows)))
        simulator.Initialize()
        request = diagram.GetInputPort("action_request")
        request.FixValue(context, np.zeros((len(rows), 17)))
        simulator.AdvanceTo(0.032)
        observations = []
        for tick in range(actions.shape[0]):
            request.FixValue(context, np.concatenate([actions[tick, rows], np.ones((len(rows), 1))], axis=1))
            simulator.AdvanceTo((tick + 2) * 0.032)
            builder = diagram.GetSubsystemByName("observation_builder")
            observations.append(builder.observation_port.Eval(builder.GetMyContextFromRoot(context)).copy())
        ball = diagram.GetSubsystemByName("ball")
        return np.array(observations), ball.plant_state(ball.GetMyContextFromRoot(context))

    batch_observations, batch_state = run([0, 1, 2])
    for row in range(3):
        observations, state = run([row])
        np.testing.assert_array_equal(batch_observations[:, row], observations[:, 0])
        np.testing.assert_array_equal(batch_state.balls[row], state.balls[0])
        assert [(e.kind, e.time) for e in batch_state.events[row]] == [(e.kind, e.time) for e in state.events[0]]
